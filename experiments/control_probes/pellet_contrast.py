"""How visible a level's pellets are at each observation size: the game's 150 x 150 observation
drawn with and without its pellets, both resized to the model's size (`cdrl.data.frames.resize_obs`,
area-averaging, after a `--max-filter` max filter as preset `small-max` sees the game), and the
difference split into connected blobs (brightness change above 0.02).

Reported per level and size, as the mean over the start frames of `--games` games: the median
blob's peak brightness change (`contrast`, in [0, 1]), its pixels, the blobs per frame, and the
share of the frame's pixels the pellets change (`area_share`: what a pellet weighs in a mean
per-pixel loss).

    .venv/bin/python experiments/control_probes/pellet_contrast.py --out experiments/control_probes/results/pellet_contrast.json
    .venv/bin/python experiments/control_probes/pellet_contrast.py --levels thesis --sizes 64 --max-filter 5
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit  # noqa: E402


def measure(level: str, sizes, games: int, max_filter: int = 1) -> dict:
    import jax
    import jax.numpy as jnp
    from scipy.ndimage import label

    from cdrl.data.frames import resize_obs
    from envs.slither import level_game, level_params

    game, params = level_game(level), level_params(level)
    rows = {size: [] for size in sizes}
    for seed in range(games):
        state = game.jit.reset_state(jax.random.PRNGKey(seed), params)
        with_pellets = game.jit.get_obs(state, params)
        without = game.jit.get_obs(state.replace(pellet_value=jnp.zeros_like(state.pellet_value)), params)
        for size in sizes:
            seen = [resize_obs(frame, size, max_filter) for frame in (with_pellets, without)]
            change = np.abs(np.asarray(seen[0] - seen[1]))
            blobs, n = label(change > 0.02)
            peaks = [change[blobs == i].max() for i in range(1, n + 1)]
            pixels = [np.sum(blobs == i) for i in range(1, n + 1)]
            rows[size].append((np.median(peaks), np.median(pixels), n, np.sum(blobs > 0) / change.size))
    out = {}
    for size, values in rows.items():
        contrast, pixels, blobs, share = np.mean(np.asarray(values, np.float64), axis=0)
        out[str(size)] = {"contrast": round(float(contrast), 3), "pixels": round(float(pixels), 1),
                          "blobs_per_frame": round(float(blobs), 1), "area_share": float(share)}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--levels", nargs="+", default=["thesis", "visible"])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 96, 128, 150])
    parser.add_argument("--games", type=int, default=8)
    parser.add_argument("--max-filter", type=int, default=1,
                        help="side of the max filter before the resizing (preset small-max: 5; default: 1, none)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    result = {"games": args.games, "max_filter": args.max_filter,
              "levels": {level: measure(level, args.sizes, args.games, args.max_filter) for level in args.levels}}
    for level, sizes in result["levels"].items():
        for size, row in sizes.items():
            print(f"{level:10s} {size:>4s} x {size:<4s} contrast {row['contrast']:.2f}  pixels {row['pixels']:5.1f}  "
                  f"pellets/frame {row['blobs_per_frame']:4.1f}  share of the frame {row['area_share']:.4f}")
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
