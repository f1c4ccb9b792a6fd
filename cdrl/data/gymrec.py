"""Any registered gymnasium game as a data set: `cdrl collect DIR --env ID`.

`ID` is a registered id (`CartPole-v1`), or gymnasium's `module:ID` form: `module` is
imported first, for a game that a package registers when it is imported (gymnasium 1.x
imports no plugins by itself), e.g. `ale_py:ALE/Pong-v5`. The packages of known namespaces
(`NAMESPACE_PACKAGES`: `ALE/` games come with `pip install ale-py`) are imported when they
are installed, so `--env ALE/Pong-v5` works too; an id of an unknown namespace is an error
naming the package to install or the `module:ID` form.

A game's observations must be images, or it must render RGB frames (`--obs render` records
`env.render()` of `render_mode="rgb_array"`, e.g. CartPole-v1). Frames go through the
thesis's pre-processing (`envs.preprocess.preprocess`: a crop, block means down to a square
of `size`, the max over colour channels). Actions are recorded as vectors in [0, 1], as the
models take them: a Discrete(n) action as its one-hot vector (n values; the env gets the
argmax), a Box action rescaled from its bounds (the env gets low + a (high - low)), a
MultiBinary one as is (the env gets a > 0.5). The recording itself is `record_gym` (for any
environment object and policy): atomic episode files, a manifest, resumable, locked
(`cdrl.data.writer`).
"""
from __future__ import annotations

import contextlib
import dataclasses
import importlib
import importlib.util
import json
import os
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from cdrl.data.episode import Episode
from cdrl.data.store import DatasetError
from cdrl.data.writer import Writer, check_collection, write_set

OBS_MODES = ("image", "render")
POLICIES = ("uniform",)
# Namespaces of gymnasium ids whose games a package registers when it is imported (gymnasium
# 1.x loads no plugins by itself): namespace -> (the module to import, what to pip install).
NAMESPACE_PACKAGES = {"ALE": ("ale_py", "ale-py")}


class GameError(ValueError):
    """A gymnasium game failed (made, reset or stepped): the message names the game and what it raised."""


@dataclasses.dataclass(frozen=True)
class ActionCodec:
    """How an action space maps to and from the recorded vectors in [0, 1]^dim."""

    space: str
    dim: int
    decode: Callable[[np.ndarray], Any]  # recorded vector -> what env.step takes
    sample: Callable[[np.random.Generator], np.ndarray]  # uniform over the space, as a recorded vector


def action_codec(space) -> ActionCodec:
    """The codec of a Discrete, Box (finite bounds) or MultiBinary action space; ValueError
    naming any other."""
    from gymnasium import spaces

    if isinstance(space, spaces.Discrete):
        n, start = int(space.n), int(space.start)

        def one_hot(rng):
            return np.eye(n, dtype=np.float32)[rng.integers(n)]

        return ActionCodec(str(space), n, lambda a: int(np.argmax(a)) + start, one_hot)
    if isinstance(space, spaces.Box):
        low, high = np.asarray(space.low, np.float64), np.asarray(space.high, np.float64)
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
            raise ValueError(f"action space {space} has unbounded values: they cannot be rescaled to [0, 1]")
        shape, dtype, dim = space.shape, space.dtype, int(np.prod(space.shape))

        def rescale(a):
            return (low + np.asarray(a, np.float64).reshape(shape) * (high - low)).astype(dtype)

        return ActionCodec(str(space), dim, rescale, lambda rng: rng.uniform(0.0, 1.0, dim).astype(np.float32))
    if isinstance(space, spaces.MultiBinary):
        dim = int(np.prod(space.shape))
        return ActionCodec(str(space), dim, lambda a: (np.asarray(a).reshape(space.shape) > 0.5).astype(np.int8),
                           lambda rng: rng.integers(0, 2, dim).astype(np.float32))
    raise ValueError(f"action space {space} is not supported: cdrl records Discrete, Box (bounded) and MultiBinary "
                     "actions")


def parse_env_kwargs(items: Sequence[str] | str | None) -> dict:
    """`--env-kwargs`: one JSON object, or key=value items whose values are read as JSON
    where they parse (numbers, true/false, lists), else as strings."""
    if not items:
        return {}
    items = [items] if isinstance(items, str) else list(items)
    if len(items) == 1 and items[0].lstrip().startswith("{"):
        try:
            value = json.loads(items[0])
        except json.JSONDecodeError as exc:
            raise ValueError(f"bad --env-kwargs {items[0]!r}: not a JSON object ({exc})") from None
        if not isinstance(value, dict):
            raise ValueError(f"bad --env-kwargs {items[0]!r}: not a JSON object")
        return value
    out = {}
    for item in items:
        for part in item.split(","):
            key, sep, text = part.partition("=")
            if not sep or not key.strip():
                raise ValueError(f"bad --env-kwargs item {part!r}: use key=value (or one JSON object)")
            try:
                out[key.strip()] = json.loads(text)
            except json.JSONDecodeError:
                out[key.strip()] = text
    return out


def _namespace(env_id: str) -> str | None:
    """The namespace of `env_id` ('ALE' of 'ALE/Pong-v5' and of 'ale_py:ALE/Pong-v5'; None without one)."""
    name = env_id.partition(":")[2] if ":" in env_id else env_id
    namespace, sep, _ = name.partition("/")
    return namespace if sep else None


def _import_registering_module(env_id: str) -> None:
    """Imports the module that registers `env_id`: the one the id names (`module:ID`), else
    the package of its namespace in `NAMESPACE_PACKAGES` when it is installed."""
    module, sep, _ = env_id.partition(":")
    namespace = _namespace(env_id)
    if not sep:
        if namespace not in NAMESPACE_PACKAGES or importlib.util.find_spec(NAMESPACE_PACKAGES[namespace][0]) is None:
            return
        module = NAMESPACE_PACKAGES[namespace][0]
    try:
        importlib.import_module(module)
    except ImportError as exc:
        install = {m: pip for m, pip in NAMESPACE_PACKAGES.values()}.get(module)
        hint = f" (pip install {install})" if install else ""
        raise ValueError(f"gymnasium environment {env_id!r}: importing {module}, which registers it, failed: "
                         f"{exc}{hint}") from None


def _namespace_fix(env_id: str) -> str:
    """How to make the games of `env_id`'s unknown namespace known."""
    namespace = _namespace(env_id)
    if namespace in NAMESPACE_PACKAGES and ":" not in env_id:
        return f"install the package that registers them: pip install {NAMESPACE_PACKAGES[namespace][1]}"
    return (f"if a package registers them when it is imported, name it in the id: --env "
            f"MODULE:{env_id.partition(':')[2] if ':' in env_id else env_id} (gymnasium's module:ID form)")


def make_env(env_id: str, obs: str = "image", env_kwargs: dict | None = None):
    """The gymnasium game `env_id` (with `env_kwargs`), whose observations are images
    (`obs` 'render': its rendered RGB frames). ValueError naming what is wrong.

    `env_id` is a registered id, or gymnasium's `module:ID` form (`module` is imported first,
    for a game a package registers when imported). The package of a namespace in
    `NAMESPACE_PACKAGES` (ALE: ale_py) is imported when it is installed; an unknown namespace
    is an error saying what to install or how to name the module."""
    import gymnasium as gym

    import envs  # noqa: F401  (registers cdrl/Slither-v0)

    if obs not in OBS_MODES:
        raise ValueError(f"--obs must be one of {', '.join(OBS_MODES)}; got {obs!r}")
    kwargs = dict(env_kwargs or {})
    if obs == "render":
        kwargs.setdefault("render_mode", "rgb_array")
    _import_registering_module(env_id)
    try:
        env = gym.make(env_id, **kwargs)
    except gym.error.NamespaceNotFound as exc:
        raise ValueError(f"unknown gymnasium environment {env_id!r}: {exc} To record its games, "
                         f"{_namespace_fix(env_id)}") from None
    except (gym.error.NameNotFound, gym.error.VersionNotFound, gym.error.UnregisteredEnv) as exc:
        raise ValueError(f"unknown gymnasium environment {env_id!r}: {exc}") from None
    except gym.error.Error as exc:
        raise ValueError(f"gymnasium cannot make {env_id!r}: {exc}") from None
    except TypeError as exc:
        raise ValueError(f"gymnasium environment {env_id!r} does not take --env-kwargs {kwargs}: {exc}") from None
    except Exception as exc:  # noqa: BLE001 - a game's own constructor may raise anything on bad options
        raise GameError(f"gymnasium cannot make {env_id!r} with --env-kwargs {kwargs}: "
                        f"{type(exc).__name__}: {exc}") from None
    if obs == "render":
        if env.render_mode != "rgb_array":
            raise ValueError(f"{env_id} does not render RGB frames (render_mode {env.render_mode!r})")
        env = gym.wrappers.AddRenderObservation(env, render_only=True)
    space = env.observation_space
    shape = getattr(space, "shape", None) or ()
    is_image = (isinstance(space, gym.spaces.Box) and (len(shape) == 2 or (len(shape) == 3 and shape[2] in (1, 3)))
                and min(shape[:2]) >= 2)
    if not is_image:
        hint = "" if obs == "render" else "; record its rendered frames with --obs render"
        raise ValueError(f"{env_id}'s observations are not images (observation space {space}){hint}")
    return env


def default_crop(height: int, width: int, size: int) -> tuple[int, int, int, int]:
    """The central square crop whose side is the largest multiple of `size` in the frame."""
    side = min(height, width) // size * size
    if side < size:
        raise ValueError(f"frames of {height}x{width} are smaller than the output size {size}")
    return ((height - side) // 2, (width - side) // 2, side, side)


def record_env(env_id: str, out_dir: str | Path, episodes: int, size: int = 64, crop: Sequence[int] | None = None,
               obs: str = "image", policy: str = "uniform", seed: int = 0, max_steps: int | None = None,
               env_kwargs: dict | None = None, test_fraction: float = 0.1) -> dict:
    """Record `episodes` episodes of gymnasium game `env_id` into the data set `out_dir`
    (resumes an interrupted recording). `crop`: (top, left, height, width) of the frame to
    keep, a multiple of `size` (default: the central square, `default_crop`). Returns the
    manifest."""
    if policy not in POLICIES:
        raise ValueError(f"policy {policy!r} is for the built-in game; a gymnasium game records with "
                         f"{', '.join(POLICIES)}")
    check_collection(episodes, max_steps, size, seed)
    env = make_env(env_id, obs, env_kwargs)
    try:
        codec = action_codec(env.action_space)
        height, width = env.observation_space.shape[:2]
        box = tuple(int(v) for v in crop) if crop is not None else default_crop(height, width, size)
        if len(box) != 4:
            raise ValueError(f"--crop takes 4 numbers (top left height width), got {list(box)}")
        _check_crop(box, height, width, size)

        def uniform(_obs, rng):
            return codec.sample(rng)

        _probe(env, env_id, uniform, codec.decode, seed)
        return record_gym(
            env, out_dir, episodes, uniform, preprocess_kwargs={"crop": box, "out_size": (size, size)}, seed=seed,
            max_steps=max_steps, test_fraction=test_fraction, action_fn=codec.decode,
            config_extra={"env_kwargs": env_kwargs or {}, "obs": obs, "action_space": codec.space})
    finally:
        env.close()


def _probe(env, env_id: str, policy_fn, action_fn, seed: int) -> None:
    """One reset and one step of the game, before anything is written, so that a game that
    fails on its options fails here, naming them (recording resets every episode anew)."""
    with _game_errors(env_id, "its first reset and step"):
        obs, _ = env.reset(seed=int(seed))
        env.step(action_fn(np.asarray(policy_fn(obs, np.random.default_rng(0)), np.float32).reshape(-1)))


@contextlib.contextmanager
def _game_errors(env_id: str, what: str):
    """Whatever the game raises in `what` as a `GameError` naming it (a game's own code may raise
    anything; cdrl's errors pass through)."""
    try:
        yield
    except (GameError, DatasetError):
        raise
    except Exception as exc:  # noqa: BLE001
        raise GameError(f"gymnasium game {env_id!r} failed in {what}: {type(exc).__name__}: {exc}") from None


def _check_crop(box: tuple[int, ...], height: int, width: int, size: int) -> None:
    top, left, h, w = box
    if top < 0 or left < 0 or h < 1 or w < 1 or top + h > height or left + w > width:
        raise ValueError(f"--crop {list(box)} does not fit in the {height}x{width} frames")
    if h % size or w % size:
        raise ValueError(f"--crop {list(box)}: its height and width must be multiples of the output size {size}")


def record_gym(
    env,
    out_dir: str | os.PathLike,
    num_episodes: int,
    policy_fn: Callable[[np.ndarray, np.random.Generator], np.ndarray],
    preprocess_kwargs: dict | None = None,
    seed: int = 0,
    max_steps: int | None = None,
    test_fraction: float = 0.1,
    action_fn: Callable[[np.ndarray], Any] | None = None,
    compress: bool = True,
    config_extra: dict | None = None,
) -> dict:
    """Records episodes of any gymnasium environment with image observations.

    Observations ([H, W, C] or [H, W] images, uint8 or float in [0, 1]) are
    pre-processed with :func:`envs.preprocess.preprocess` (``preprocess_kwargs``:
    ``crop`` and ``out_size``; the defaults suit a 500 x 300 frame) and stored as
    uint8.  Writing, resuming and the manifest work as in :func:`cdrl.data.collect.collect`.

    Args:
      env: a gymnasium environment.
      out_dir: data set directory.
      num_episodes: number of episodes.
      policy_fn: ``policy_fn(raw_obs, rng) -> action``: a 1-D array of values in
        [0, 1], which is what gets recorded.
      preprocess_kwargs: options for :func:`envs.preprocess.preprocess`.
      seed: episode ``i`` resets the environment with ``seed + i`` and gives the
        policy ``np.random.default_rng([seed, i])``.
      max_steps: stop an episode after this many steps (None = until the
        environment ends it).
      test_fraction: share of episodes held out as the test split.
      action_fn: maps the recorded action to what ``env.step`` takes (default:
        the action itself).
      compress: write compressed ``.npz`` files.
      config_extra: more of what defines the recording (the environment's options,
        the observation mode), stored in the manifest's config and checked on resume.
    Returns:
      The manifest.
    """
    check_collection(num_episodes, max_steps, seed=seed)
    kwargs = dict(preprocess_kwargs or {})
    spec = getattr(env, "spec", None)
    config = {
        "source": "gym",
        "env": spec.id if spec is not None else type(env.unwrapped).__name__,
        "policy": getattr(policy_fn, "__name__", type(policy_fn).__name__),
        "seed": int(seed),
        "preprocess": {k: list(v) if isinstance(v, tuple) else v for k, v in kwargs.items()},
        "max_steps": None if max_steps is None else int(max_steps),
        "test_fraction": float(test_fraction),
        "num_episodes": int(num_episodes),
        **(config_extra or {}),
    }
    return write_set(out_dir, config,
                      lambda writer: _record(writer, env, policy_fn, kwargs, int(seed), max_steps, action_fn, compress))


def _record(writer: Writer, env, policy_fn, kwargs: dict, seed: int, max_steps: int | None, action_fn,
            compress: bool) -> None:
    """Plays and writes the episodes ``writer`` is missing (the body of :func:`record_gym`)."""
    from envs.preprocess import preprocess

    def to_frame(obs) -> np.ndarray:
        obs = np.asarray(obs)
        if obs.ndim == 2:
            obs = obs[..., None]
        return np.round(preprocess(obs, **kwargs) * 255.0).astype(np.uint8)

    spec = getattr(env, "spec", None)
    name = spec.id if spec is not None else type(env.unwrapped).__name__
    for index in writer.missing:
        with _game_errors(name, f"episode {index}"):
            episode = _play(env, policy_fn, to_frame, int(seed), index, max_steps, action_fn)
        writer.write(index, episode, compress)
        writer.flush()


def _play(env, policy_fn, to_frame, seed: int, index: int, max_steps: int | None, action_fn) -> Episode:
    """Episode `index` of a recording (see `record_gym`)."""
    rng = np.random.default_rng([int(seed), index])
    obs, _ = env.reset(seed=int(seed) + index)
    frames, actions, rewards = [], [], [0.0]
    steps = 0
    while True:
        action = np.asarray(policy_fn(obs, rng), np.float32).reshape(-1)
        frames.append(to_frame(obs))
        actions.append(action)
        if max_steps is not None and steps >= max_steps:
            break
        obs, reward, terminated, truncated, _ = env.step(
            action if action_fn is None else action_fn(action)
        )
        steps += 1
        if terminated or truncated:
            frames.append(to_frame(obs))
            actions.append(np.asarray(policy_fn(obs, rng), np.float32).reshape(-1))
            rewards.append(float(reward))
            break
        rewards.append(float(reward))
    return Episode(
        frames=np.stack(frames),
        actions=np.stack(actions).astype(np.float32),
        rewards=np.asarray(rewards[:len(frames)], np.float32),
    )
