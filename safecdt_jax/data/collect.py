"""Collect a source data set: behaviour-policy episodes, one jitted, vmapped program per chunk.

    data = collect(jax.random.PRNGKey(0), "CarGoal1", episodes=1000)   # a `Dataset`
    write_collected(path, data)                                        # DSRL-format HDF5
    path = ensure_dataset("CarGoal1", 1000, seed=0)   # the cached file, or collected and written

Every episode runs the task's full time limit (there are no terminations), so episodes are equally
long and the data are plain `[n, T, ...]` arrays. Per-episode keys and knobs are drawn from the
one key up front, so the data do not depend on the chunk size, which only sets the progress bar's
step and the memory one compiled call holds.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import h5py
import jax
import jax.numpy as jnp
import numpy as np

from safecdt_jax import envs, paths
from safecdt_jax.data.behaviour import Knobs, family, make_policy, sample_knobs
from safecdt_jax.data.dataset import Attrs, Dataset
from safecdt_jax.data.dsrl import write_dataset

# Bump whenever the behaviour policies, their knob ranges or the collection loop change: cached
# data sets written by another version are collected again.
COLLECTOR_VERSION = 5  # 5: the Point runs the graded Circle family (Car and Goal data as in 4)
DEFAULT_EPISODES = 1000  # as DSRL's data sets (>= 1000 episodes per task)
DEFAULT_CHUNK = 100  # episodes per compiled call: ~29 MB of CarGoal observations


@functools.cache
def _rollout_fn(task: str, horizon: int) -> Callable:
    """jit(vmap(episode)): (keys [c], knobs {name: [c]}) -> (obs [c, T, d], final obs [c, d],
    actions [c, T, 2], rewards [c, T], costs [c, T]) with T = `horizon`. Cached: compiled once."""
    env, params = envs.make(task)
    policy = make_policy(task, params)

    def episode(key: jax.Array, knobs: Knobs):
        k_reset, k_steps = jax.random.split(key)

        def step(carry, k):
            state, spent = carry  # spent: the episode's cost so far, which budgets act on
            action = policy(knobs, state, spent, k)
            nxt = env.step(state, action, params)
            return (nxt, spent + nxt.cost), (state.obs, action, nxt.reward, nxt.cost)

        init = (env.reset(k_reset, params), jnp.float32(0.0))
        (final, _), (obs, actions, rewards, costs) = jax.lax.scan(
            step, init, jax.random.split(k_steps, horizon))
        return obs, final.obs, actions, rewards, costs

    return jax.jit(jax.vmap(episode))


def env_params_attrs(task: str) -> dict:
    """The task's `EnvParams` as plain floats and lists (for file attributes)."""
    params = envs.make(task)[1]
    return {f.name: np.asarray(getattr(params, f.name)).tolist()
            for f in dataclasses.fields(params)}


def collect(key: jax.Array, task: str, episodes: int, chunk: int = DEFAULT_CHUNK,
            progress: Callable[[int], None] | None = None, seed: int | None = None,
            horizon: int | None = None) -> Dataset:
    """Runs `episodes` behaviour episodes of `task` and returns them as a `Dataset` (numpy).

    Arrays: observations and next_observations [n, T, obs_dim], actions [n, T, 2], rewards and
    costs [n, T] (raw per-step values), lengths [n] = T, every episode ending in a timeout.
    T is `horizon`, by default the task's time limit (1000 Goal, 500 Circle; shorter horizons
    are for tests and smoke runs). `episode_info` holds each episode's knobs (float32 [n] per knob);
    `attrs` the task, its env params, the collector version, the behaviour family and its
    ranges, the episode count and `seed` (if given). Episodes run `chunk` at a time (the last
    chunk padded, so one compiled program serves all); `progress(k)` is called after each chunk
    with the number of episodes it finished. Raises ValueError for an unknown task or
    episodes < 1.
    """
    fam = family(task)  # validates the name
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    env, _ = envs.make(task)
    t = env.episode_length if horizon is None else int(horizon)
    if t < 1:
        raise ValueError(f"horizon must be >= 1, got {t}")
    k_knobs, k_eps = jax.random.split(key)
    knobs = sample_knobs(k_knobs, task, episodes)
    arrays = run_episodes(_rollout_fn(task, t), jax.random.split(k_eps, episodes), knobs,
                          env.observation_size, env.action_size, chunk, progress)
    attrs = {
        "task": task,
        "env_params": env_params_attrs(task),
        "collector_version": COLLECTOR_VERSION,
        "physics_version": envs.physics_version(task),
        "behaviour": type(fam).__name__,
        "behaviour_family": dataclasses.asdict(fam),
        "episodes": episodes,
        "horizon": t,
    }
    if seed is not None:
        attrs["seed"] = int(seed)
    return full_length_dataset(arrays, {k: np.asarray(v, np.float32) for k, v in knobs.items()},
                               attrs)


def run_episodes(rollout: Callable, keys: jax.Array, inputs, obs_dim: int, act_dim: int,
                 chunk: int = DEFAULT_CHUNK, progress: Callable[[int], None] | None = None
                 ) -> dict[str, np.ndarray]:
    """Runs `rollout(keys [c], inputs {leaves [c, ...]})` (a jitted, vmapped whole-episode
    program returning (obs [c, T, d], final obs [c, d], actions, rewards, costs)) over all
    episodes, `chunk` at a time (the last chunk padded with repeats, so one compiled program
    serves all), into numpy arrays: observations, next_observations [n, T, d], actions
    [n, T, act_dim], rewards, costs [n, T]. `progress(k)` after each chunk of k episodes."""
    episodes = keys.shape[0]
    obs = nxt = actions = rewards = costs = None
    chunk = max(1, min(chunk, episodes))
    for start in range(0, episodes, chunk):
        stop = min(start + chunk, episodes)
        idx = np.minimum(np.arange(start, start + chunk), episodes - 1)  # pad with repeats
        out = rollout(keys[idx], jax.tree.map(lambda v, i=idx: v[i], inputs))
        o, last, a, r, c = (np.asarray(x)[: stop - start] for x in out)
        if obs is None:
            t = o.shape[1]
            obs = np.empty((episodes, t, obs_dim), np.float32)
            nxt = np.empty_like(obs)
            actions = np.empty((episodes, t, act_dim), np.float32)
            rewards = np.empty((episodes, t), np.float32)
            costs = np.empty((episodes, t), np.float32)
        obs[start:stop], nxt[start:stop, :-1], nxt[start:stop, -1] = o, o[:, 1:], last
        actions[start:stop], rewards[start:stop], costs[start:stop] = a, r, c
        if progress is not None:
            progress(stop - start)
    return dict(observations=obs, next_observations=nxt, actions=actions, rewards=rewards,
                costs=costs)


def full_length_dataset(arrays: dict[str, np.ndarray], episode_info: dict, attrs: dict
                        ) -> Dataset:
    """A `Dataset` of `run_episodes` arrays: every episode runs the whole horizon and ends in a
    timeout (the tasks have no terminations)."""
    n, t = arrays["rewards"].shape
    return Dataset(**arrays, lengths=np.full(n, t, np.int32), terminals=np.zeros(n, bool),
                   timeouts=np.ones(n, bool), return_offset=np.zeros(n, np.float32),
                   cost_offset=np.zeros(n, np.float32), episode_info=episode_info,
                   attrs=Attrs(attrs))


def write_collected(path: str | os.PathLike, data: Dataset) -> Path:
    """Writes collected data to `path` as DSRL-format HDF5 (atomically); returns the path."""
    # lzf: fast and built into h5py; gzip takes longer than collecting on this CPU.
    write_dataset(path, data, compression="lzf")
    return Path(path)


def check_writable(path: str | os.PathLike) -> Path:
    """`path` as a Path if a file can be written there, else ValueError; checked before a
    collection, not after it. Creates the folder and a scratch file in it (then removes it),
    the way the atomic writer will."""
    path = Path(path).expanduser()
    if path.is_dir():
        raise ValueError(f"cannot write {path}: it is a directory")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=".tmp-"):
            pass
    except OSError as e:
        raise ValueError(f"cannot write {path}: {e.strerror or e}") from None
    return path


def file_attrs(path: str | os.PathLike) -> dict | None:
    """The attributes of an HDF5 file (task, collector_version, seed, episodes, ...) without
    reading its data, or None if it is missing or unreadable."""
    try:
        with h5py.File(path, "r") as f:
            return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in f.attrs.items()}
    except (OSError, ValueError):
        return None


def is_current(path: str | os.PathLike, task: str, episodes: int, seed: int) -> bool:
    """Whether `path` holds `task` data from this collector and physics version and `seed`, with
    at least `episodes` full-length episodes."""
    attrs = file_attrs(path)
    if attrs is None:
        return False
    return (attrs.get("task") == task and attrs.get("collector_version") == COLLECTOR_VERSION
            and attrs.get("physics_version") == envs.physics_version(task)
            and attrs.get("seed") == seed and int(attrs.get("episodes", 0)) >= episodes
            and attrs.get("horizon") == envs.make(task)[0].episode_length)


def ensure_dataset(task: str, episodes: int = DEFAULT_EPISODES, seed: int = 0,
                   path: str | os.PathLike | None = None,
                   progress: Callable[[int], None] | None = None) -> Path:
    """The path of a current data set for `task` (default `paths.dataset_path(task)`).

    Returns the file as is when `is_current` (same task, collector version and seed, at least
    `episodes` full-length episodes); otherwise collects `episodes` episodes with
    `PRNGKey(seed)` and writes them there, replacing what was there. Raises ValueError for an
    unknown task, episodes < 1 or an unwritable path.
    """
    family(task)  # validates the name before touching the disk
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    path = Path(paths.dataset_path(task) if path is None else path).expanduser()
    if is_current(path, task, episodes, seed):
        return path
    path = check_writable(path)
    data = collect(jax.random.PRNGKey(seed), task, episodes, progress=progress, seed=seed)
    return write_collected(path, data)


def coverage_checks(summary: dict, min_episodes: int = DEFAULT_EPISODES) -> dict[str, bool]:
    """Whether a `summarize_dataset` summary (default thresholds) has the coverage a source data
    set needs: at least `min_episodes` episodes; costs from 0 to at least 100; at least 20% of
    episodes at cost <= 30 and 20% above; and a rising frontier, the best return at cost 30-100
    beating the best at cost <= 10 by at least 10% (of its magnitude)."""
    safe, risky = summary["best_return_cost_le_10"], summary["best_return_cost_30_100"]
    return {
        "episodes": summary["n_episodes"] >= min_episodes,
        "cost_span": summary["cost_min"] <= 0.0 and summary["cost_max"] >= 100.0,
        "cost_split": summary["frac_cost_le_30"] >= 0.2 and summary["frac_cost_gt_30"] >= 0.2,
        "frontier": safe is not None and risky is not None and risky - safe >= 0.1 * abs(safe),
    }


__all__ = [
    "COLLECTOR_VERSION",
    "DEFAULT_EPISODES",
    "check_writable",
    "collect",
    "coverage_checks",
    "ensure_dataset",
    "env_params_attrs",
    "file_attrs",
    "full_length_dataset",
    "is_current",
    "run_episodes",
    "write_collected",
]
