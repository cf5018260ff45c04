"""Collection plumbing shared by the source-data collectors: run a jitted, vmapped whole-episode
program over many episodes chunk by chunk, turn the arrays into a `Dataset`, write it as
DSRL-format HDF5, and the checks around that (a writable path, a file's attributes, coverage).

The collector itself is `experts.collect` (the committed PPO-Lagrangian snapshots rolled out and
grid-filtered to DSRL's size). Every episode runs its whole horizon (the tasks have no
terminations), so the data are plain `[n, T, ...]` arrays; the chunk size sets only the
progress step and the memory one compiled call holds, never the data.
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import h5py
import jax
import numpy as np

from safecdt_jax import envs
from safecdt_jax.data.dataset import Attrs, Dataset
from safecdt_jax.data.dsrl import write_dataset

MIN_EPISODES = 1000  # the episode count of DSRL's source data sets, a coverage check
DEFAULT_CHUNK = 100  # episodes per compiled call: ~29 MB of CarGoal observations


def env_params_attrs(task: str) -> dict:
    """The task's `EnvParams` as plain floats and lists (for file attributes)."""
    params = envs.make(task)[1]
    return {f.name: np.asarray(getattr(params, f.name)).tolist()
            for f in dataclasses.fields(params)}


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


def coverage_checks(summary: dict, min_episodes: int = MIN_EPISODES) -> dict[str, bool]:
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
    "DEFAULT_CHUNK",
    "MIN_EPISODES",
    "check_writable",
    "coverage_checks",
    "env_params_attrs",
    "file_attrs",
    "full_length_dataset",
    "run_episodes",
    "write_collected",
]
