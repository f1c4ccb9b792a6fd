"""Collecting the built-in game's data sets: many Slither episodes at once as one jitted,
vmapped rollout, written to disk (:mod:`cdrl.data.writer`) in a background thread while the
next batch is simulated."""

from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from cdrl.data.episode import Episode
from cdrl.data.writer import Writer, check_collection, params_dict, write_set


@functools.lru_cache(maxsize=8)
def _rollout_fn(game_items: tuple, policy_name: str, chunk_steps: int, obs_size: int = 150, max_filter: int = 1):
    """A jitted function running a batch of episodes for ``chunk_steps`` steps.

    Carry per episode: (game state, policy state, obs of that state, reward on
    arriving at obs, finished = the episode ended before obs, key).  Each step emits
    (uint8 frame, action, reward, valid = not finished) for the current
    observation, then steps the game.
    """
    import jax
    import jax.numpy as jnp

    from cdrl.data.frames import resize_obs
    from envs import fastrng
    from envs.policies import get_policy
    from envs.flow_view import make_game

    game = make_game(**dict(game_items))
    policy = get_policy(policy_name)

    def start(key, params):
        k_reset, k_policy, k_run = fastrng.split(key, 3)
        state = game.reset_state(k_reset, params)
        obs = game.get_obs(state, params)
        return (state, policy.init(k_policy), obs, jnp.zeros((), jnp.float32),
                jnp.zeros((), bool), k_run)

    def one_step(carry, params):
        state, pstate, obs, reward, finished, key = carry
        key, k_policy, k_env = fastrng.split(key, 3)
        action, pstate = policy.step(k_policy, pstate, obs)
        frame = jnp.round(resize_obs(obs, obs_size, max_filter) * 255.0).astype(jnp.uint8)
        out = (frame, action.astype(jnp.float32), reward, ~finished)
        is_last = state.terminated | (state.time >= params.max_steps)
        state, reward, _, _, _ = game.step_state(k_env, state, action, params)
        obs = game.get_obs(state, params)
        carry = (state, pstate, obs, reward.astype(jnp.float32), finished | is_last, key)
        return carry, out

    def run(carry, params):
        def body(c, _):
            return jax.vmap(one_step, in_axes=(0, None))(c, params)

        return jax.lax.scan(body, carry, None, length=chunk_steps)

    return jax.jit(jax.vmap(start, in_axes=(0, None))), jax.jit(run)


def games_sharding(devices: int, batch_size: int):
    """The layout of a batch of ``batch_size`` games over this process's first ``devices``
    devices (0: all of them): a ``NamedSharding`` splitting the batch axis (mesh axis
    ``games``), or None for one device. The games are independent, so the sharded program runs
    each device's block with no communication, and XLA's CPU backend runs the blocks of its
    host devices on separate cores (``jax.config.update("jax_num_cpu_devices", N)`` before JAX
    starts, or ``XLA_FLAGS=--xla_force_host_platform_device_count=N``). Raises ``ValueError``
    naming the option (as ``cdrl collect`` spells it) when there are fewer devices or the batch
    does not split evenly."""
    import jax
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    local = jax.local_devices()
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise ValueError(f"--batch-size must be an integer >= 1, got {batch_size!r}")
    if isinstance(devices, bool) or not isinstance(devices, (int, np.integer)) or not 0 <= devices <= len(local):
        raise ValueError(f"--devices {devices!r}: this process has {len(local)} {local[0].platform} device(s); use 1 "
                         f"to {len(local)}, or 0 for all (more CPU devices: jax_num_cpu_devices or "
                         f"--xla_force_host_platform_device_count before JAX starts)")
    devices = devices or len(local)
    if batch_size % devices:
        raise ValueError(f"--batch-size {batch_size} does not split over {devices} devices; use a multiple of {devices}")
    if devices == 1:
        return None
    return NamedSharding(Mesh(np.array(local[:devices]), ("games",)), PartitionSpec("games"))


def collect(
    out_dir: str | os.PathLike,
    num_episodes: int,
    policy: str = "behaviour",
    seed: int = 0,
    env_params=None,
    max_steps: int = 1000,
    test_fraction: float = 0.1,
    batch_size: int = 16,
    chunk_steps: int = 64,
    game_kwargs: dict | None = None,
    compress: bool = True,
    progress: bool | None = None,
    obs_size: int = 150,
    max_filter: int = 1,
    devices: int = 1,
) -> dict:
    """Collects ``num_episodes`` Slither episodes into ``out_dir`` (or resumes).

    Episodes run ``batch_size`` at a time as one vmapped game scanned over
    ``chunk_steps`` steps per call; a batch is written to disk (in a background
    thread, one episode after another) while the next one is simulated, and the
    manifest is rewritten after every written batch.  Episode ``i`` depends only on ``seed`` and ``i``
    (its key is ``envs.fastrng.fold_in(PRNGKey(seed), i)``), so resuming reproduces the same
    episodes.  An episode ends when the player dies or after ``max_steps`` steps
    (so it has at most ``max_steps + 1`` frames).

    Args:
      out_dir: data set directory (created if needed).
      num_episodes: number of episodes the data set should hold.
      policy: "behaviour" (behaviour switching) or "uniform" (uniform random).
      seed: collection seed (episode keys and the train/test split).
      env_params: :class:`envs.slither.SlitherParams`, or a dict of field overrides,
        or None for the defaults; ``max_steps`` overrides its ``max_steps``.
      max_steps: truncation length in steps.
      test_fraction: share of episodes held out as the test split.
      batch_size: episodes simulated together.
      chunk_steps: steps per compiled call (bounds device memory).
      game_kwargs: static sizes for :class:`envs.slither.Slither`.
      compress: write compressed ``.npz`` files.
      progress: show a tqdm bar (None = only on a terminal).
      obs_size: side of the stored observations; the game's 150 x 150 observation is
        area-resized to it (for the smaller architecture presets).
      max_filter: side of the max filter applied before that resizing (`ArchConfig.max_filter`;
        1: none).
      devices: local devices the batch's games are spread over (:func:`games_sharding`;
        0: all); the episodes are the same for any count.
    Returns:
      The manifest (as written to ``out_dir/manifest.json``).
    Raises:
      DatasetError: the directory holds a data set collected with other settings, or
        an episode file in it is corrupt, or one could not be written (a full disk).
      LockedError: another process is writing to the directory.
    """
    from envs.policies import get_policy
    from envs.render import OBS_SIZE
    from envs.slither import SlitherParams, canonical_params

    check_collection(num_episodes, max_steps, obs_size, seed, largest=OBS_SIZE)
    if int(max_filter) < 1:
        raise ValueError(f"--max-filter must be >= 1 (1: none), got {max_filter}")
    get_policy(policy)
    sharding = games_sharding(devices, batch_size)
    if isinstance(env_params, dict):
        params = SlitherParams(**env_params)
    else:
        params = SlitherParams() if env_params is None else env_params
    params = canonical_params(params.replace(max_steps=int(max_steps)))
    game_kwargs = dict(sorted((game_kwargs or {}).items()))
    config = {
        "source": "slither",
        "policy": policy,
        "seed": int(seed),
        "env_params": params_dict(params),
        "game": game_kwargs,
        "max_steps": int(max_steps),
        "test_fraction": float(test_fraction),
        "num_episodes": int(num_episodes),
        "obs_size": int(obs_size),
    }
    if int(max_filter) > 1:  # absent from the data sets collected before the option (and without it)
        config["max_filter"] = int(max_filter)
    def fill(writer):
        if writer.missing:
            _simulate(writer, params, game_kwargs, policy, int(seed), int(max_steps), int(batch_size),
                      int(chunk_steps), int(obs_size), int(max_filter), compress, progress, sharding)

    return write_set(out_dir, config, fill)


def _simulate(writer: Writer, params, game_kwargs: dict, policy: str, seed: int, max_steps: int, batch_size: int,
              chunk_steps: int, obs_size: int, max_filter: int, compress: bool, progress: bool | None,
              sharding=None) -> None:
    """Runs and writes the episodes ``writer`` is missing (the body of :func:`collect`)."""
    import jax
    from tqdm.auto import tqdm

    from envs import fastrng

    missing = writer.missing
    start, run = _rollout_fn(tuple(game_kwargs.items()), policy, int(chunk_steps), int(obs_size), int(max_filter))
    base = jax.random.PRNGKey(int(seed))
    episode_keys = jax.jit(jax.vmap(lambda i: fastrng.fold_in(base, i)))
    bar = tqdm(total=len(missing), desc="collect", unit="ep", disable=None if progress is None else not progress)

    def write_batch(episodes):
        for index, episode in episodes:
            writer.write(index, episode, compress)
            bar.update(1)

    pending = None
    with ThreadPoolExecutor(max_workers=1) as pool:
        for b in range(0, len(missing), batch_size):
            batch = missing[b:b + batch_size]
            padded = batch + [batch[-1]] * (batch_size - len(batch))
            keys = episode_keys(np.asarray(padded, np.uint32))
            carry = start(keys if sharding is None else jax.device_put(keys, sharding), params)
            pieces = []
            steps = 0
            while steps <= max_steps:
                carry, out = run(carry, params)
                out = jax.device_get(out)
                pieces.append(out)
                steps += chunk_steps
                if not out[3][-1].any():
                    break
            frames, actions, rewards, valid = (np.concatenate(p, axis=0) for p in zip(*pieces))
            episodes = []
            for j, index in enumerate(batch):
                n = int(valid[:, j].sum())
                episodes.append((index, Episode(
                    frames=np.ascontiguousarray(frames[:n, j]),
                    actions=np.ascontiguousarray(actions[:n, j]),
                    rewards=np.ascontiguousarray(rewards[:n, j]),
                )))
            if pending is not None:
                pending.result()
                writer.flush()
            pending = pool.submit(write_batch, episodes)
        pending.result()
        writer.flush()
    bar.close()
