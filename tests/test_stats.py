"""`cdrl.evaluation.stats.across`: the mean over seeds and its Student-t interval."""
import numpy as np
import pytest
import scipy.stats

from cdrl.evaluation.stats import across


def test_across_gives_the_student_t_interval():
    values = [1.0, 2.0, 4.0]
    r = across(values)
    sd = np.std(values, ddof=1)
    half = scipy.stats.t.ppf(0.975, 2) * sd / np.sqrt(3)
    assert r["mean"] == pytest.approx(7 / 3) and r["std"] == pytest.approx(sd)
    assert r["ci95"] == pytest.approx([7 / 3 - half, 7 / 3 + half])
    assert r["per_seed"] == values


def test_across_one_seed_has_no_interval():
    assert across([0.5]) == {"mean": 0.5, "std": None, "ci95": None, "per_seed": [0.5]}
