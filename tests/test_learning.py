"""Learning is pinned: `main` with the default recipe, on a small seeded data set of the
built-in game, predicts held-out frames better than copying the last frame within a fixed
number of steps (experiments/learning/time_to_quality.py measures how fast, in seconds)."""
import json

import pytest

from cdrl.runs.config import DEFAULT_RECIPE, RunConfig
from cdrl.runs.train import train_run

STEPS = 800
pytestmark = pytest.mark.default_opt  # compiled as users run it (tests/conftest.py)


def test_main_beats_copy_last_frame_on_the_game(tmp_path):
    cfg = RunConfig(variant="main", preset="small", episodes=60, episode_steps=200, seed=0, steps=STEPS,
                    eval_every=STEPS // 4, eval_episodes=6, checkpoint_every=STEPS)
    assert cfg.recipe == DEFAULT_RECIPE == "tuned"
    summary = train_run(cfg, tmp_path / "run", progress=False)
    evals = [json.loads(line) for line in (tmp_path / "run" / "eval.jsonl").read_text().splitlines()]
    ratios = [e["excess_ratio"] for e in evals]
    assert len(ratios) == 4 and ratios[-1] == summary["final_eval"]["excess_ratio"]
    assert ratios[0] > ratios[-1], ratios  # it improves...
    assert ratios[-1] < 1.0, ratios  # ...past copying the last frame
    final = summary["final_eval"]
    assert final["target_entropy"] < final["bce"] < final["copy_bce"]
