"""Statistics across seeds: the mean of a figure with its Student-t confidence interval."""
from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.stats


def across(values: Sequence[float]) -> dict:
    """Mean, standard deviation (ddof 1) and 95 % CI (Student t, n - 1 dof) over seeds.

    With one value, `std` and `ci95` are None. `per_seed` holds the values as given."""
    n = len(values)
    mean = float(np.mean(values))
    if n < 2:
        return {"mean": mean, "std": None, "ci95": None, "per_seed": list(values)}
    std = float(np.std(values, ddof=1))
    half = float(scipy.stats.t.ppf(0.975, n - 1) * std / np.sqrt(n))
    return {"mean": mean, "std": std, "ci95": [mean - half, mean + half], "per_seed": list(values)}
