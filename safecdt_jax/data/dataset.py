"""The in-memory episode dataset: padded `[n_episodes, T, ...]` arrays plus per-episode lengths.

Flat DSRL rows (one per transition, episodes contiguous) are converted to and from this padded form
here; the HDF5 reading and writing lives in `dsrl.py`.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator, Mapping
from typing import Any

import jax
import numpy as np


class DatasetError(ValueError):
    """A data set file or array set is unusable; the message names the file and the problem."""


def _freeze(value: Any) -> Any:
    """Turn an attribute value into a hashable, comparable Python value."""
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return tuple(_freeze(v) for v in value.tolist())
    if isinstance(value, Mapping):
        return Attrs(value)
    if isinstance(value, list | tuple):
        return tuple(_freeze(v) for v in value)
    return value


class Attrs(Mapping[str, Any]):
    """Immutable, hashable file attributes (task name, env params JSON, collector version, ...).

    Hashable so that a `Dataset` can be a jit argument: the attributes are static pytree metadata.
    Lists become tuples, numpy scalars become Python scalars.
    """

    __slots__ = ("_dict", "_key")

    def __init__(self, items: Mapping[str, Any] | None = None):
        frozen = {str(k): _freeze(v) for k, v in dict(items or {}).items()}
        self._dict = frozen
        self._key = tuple(sorted(frozen.items(), key=lambda kv: kv[0]))

    def __getitem__(self, key: str) -> Any:
        return self._dict[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._dict)

    def __len__(self) -> int:
        return len(self._dict)

    def __hash__(self) -> int:
        return hash(self._key)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Mapping) and dict(self.items()) == dict(other.items())

    def __repr__(self) -> str:
        return f"Attrs({self._dict!r})"


@dataclasses.dataclass(frozen=True)
class Dataset:
    """Episodes padded to a common length T, zeros past each episode's length.

    Fields (n = episodes, T = horizon):
      observations, next_observations: float32 [n, T, obs_dim]
      actions: float32 [n, T, act_dim]
      rewards, costs: float32 [n, T], raw per-step values (unscaled)
      lengths: int32 [n], valid steps per episode
      terminals, timeouts: bool [n], the DSRL flags on the episode's last row
      return_offset, cost_offset: float32 [n], constants added to every valid return-to-go /
        cost-to-go of the episode (0 for real data; set by `relabel_pareto` on relabelled copies)
      episode_info: dict of per-episode arrays [n, ...] (e.g. behaviour knobs)
      attrs: `Attrs`, static metadata (not traced under jit)

    A pytree: `jax.device_put(ds)` moves it to the accelerator once, which is what a jit-ed
    sampler should be given (numpy arrays would be copied to the device on every call).
    """

    observations: Any
    next_observations: Any
    actions: Any
    rewards: Any
    costs: Any
    lengths: Any
    terminals: Any
    timeouts: Any
    return_offset: Any
    cost_offset: Any
    episode_info: dict = dataclasses.field(default_factory=dict)
    attrs: Attrs = dataclasses.field(default_factory=Attrs, metadata={"static": True})

    @property
    def n_episodes(self) -> int:
        """Number of episodes (rows of the padded arrays)."""
        return self.rewards.shape[0]

    @property
    def horizon(self) -> int:
        """Padded episode length T in steps."""
        return self.rewards.shape[1]

    @property
    def obs_dim(self) -> int:
        """Observation size."""
        return self.observations.shape[-1]

    @property
    def act_dim(self) -> int:
        """Action size."""
        return self.actions.shape[-1]

    @property
    def valid_steps(self) -> np.ndarray:
        """Bool numpy array [n, T]: True where step t lies inside episode i, False on padding."""
        return np.arange(self.horizon)[None, :] < np.asarray(self.lengths)[:, None]


jax.tree_util.register_dataclass(Dataset)


def make_dataset(
    observations,
    actions,
    rewards,
    costs,
    lengths,
    *,
    next_observations=None,
    terminals=None,
    timeouts=None,
    return_offset=None,
    cost_offset=None,
    episode_info: Mapping[str, Any] | None = None,
    attrs: Mapping[str, Any] | None = None,
) -> Dataset:
    """Build a `Dataset` from padded numpy arrays, filling the optional fields.

    Defaults: `next_observations[t] = observations[t+1]` inside an episode and a repeat of the
    last observation at its final step; `terminals` False; `timeouts` = not `terminals` (a
    time-limit end); zero offsets. Values past each length are zeroed.
    """
    obs = np.asarray(observations, np.float32)
    n, t = obs.shape[:2]
    lengths = np.asarray(lengths, np.int32)
    valid = np.arange(t)[None, :] < lengths[:, None]
    if next_observations is None:
        last = np.clip(lengths - 1, 0, t - 1)
        nxt = np.concatenate([obs[:, 1:], obs[:, -1:]], axis=1)
        nxt[np.arange(n), last] = obs[np.arange(n), last]
    else:
        nxt = np.asarray(next_observations, np.float32)

    def zero_pad(x):
        x = np.asarray(x, np.float32)
        return np.where(valid.reshape(valid.shape + (1,) * (x.ndim - 2)), x, 0.0).astype(np.float32)

    def per_episode(x, default, dtype):
        return np.full(n, default, dtype) if x is None else np.asarray(x, dtype).reshape(n)

    return Dataset(
        observations=zero_pad(obs),
        next_observations=zero_pad(nxt),
        actions=zero_pad(actions),
        rewards=zero_pad(rewards),
        costs=zero_pad(costs),
        lengths=lengths,
        terminals=per_episode(terminals, False, bool),
        timeouts=(
            ~per_episode(terminals, False, bool)
            if timeouts is None
            else per_episode(timeouts, True, bool)
        ),
        return_offset=per_episode(return_offset, 0.0, np.float32),
        cost_offset=per_episode(cost_offset, 0.0, np.float32),
        episode_info={k: np.asarray(v) for k, v in dict(episode_info or {}).items()},
        attrs=Attrs(attrs),
    )


def select_episodes(data: Dataset, index) -> Dataset:
    """The episodes `index` (int array, repeats allowed) of `data`, in that order (numpy copy)."""
    index = np.asarray(index, np.int64)
    take = lambda x: np.asarray(x)[index]
    return dataclasses.replace(
        data,
        **{
            f.name: take(getattr(data, f.name))
            for f in dataclasses.fields(Dataset)
            if f.name not in ("episode_info", "attrs")
        },
        episode_info={k: take(v) for k, v in data.episode_info.items()},
    )


def episode_bounds(terminals, timeouts) -> tuple[np.ndarray, np.ndarray]:
    """Start row and length of each episode in flat DSRL rows.

    Episodes end at rows where `terminals | timeouts`; rows after the last flagged row form one
    more (unfinished) episode, so nothing is dropped.
    """
    ends = np.asarray(terminals, bool) | np.asarray(timeouts, bool)
    n_rows = ends.shape[0]
    last = np.flatnonzero(ends)
    if n_rows and (last.size == 0 or last[-1] != n_rows - 1):
        last = np.append(last, n_rows - 1)
    starts = np.concatenate([[0], last[:-1] + 1]).astype(np.int64)
    return starts, (last - starts + 1).astype(np.int64)


def pad_flat(rows: np.ndarray, starts: np.ndarray, lengths: np.ndarray, horizon: int) -> np.ndarray:
    """Scatter flat rows `[N, ...]` into zero-padded episodes `[n_episodes, horizon, ...]`."""
    episode = np.repeat(np.arange(lengths.size), lengths)
    step = np.arange(rows.shape[0]) - starts[episode]
    out = np.zeros((lengths.size, horizon, *rows.shape[1:]), rows.dtype)
    out[episode, step] = rows
    return out


def to_flat(data: Dataset) -> dict[str, np.ndarray]:
    """The 7 DSRL keys as flat rows, episodes contiguous in order.

    An episode with neither flag that is not the last one gets `timeouts=True` on its last row;
    otherwise it would merge with the next episode when read back.
    """
    lengths = np.asarray(data.lengths)
    if np.any(lengths <= 0):
        raise DatasetError(f"episode {int(np.argmax(lengths <= 0))} has no steps; cannot write it")
    valid = data.valid_steps
    out = {
        k: np.asarray(getattr(data, k))[valid]
        for k in ("observations", "next_observations", "actions", "rewards", "costs")
    }
    end_rows = np.cumsum(lengths) - 1
    terminals, timeouts = np.asarray(data.terminals, bool), np.asarray(data.timeouts, bool).copy()
    timeouts[:-1] |= ~(terminals[:-1] | timeouts[:-1])
    out["terminals"] = np.zeros(end_rows[-1] + 1, bool)
    out["timeouts"] = np.zeros(end_rows[-1] + 1, bool)
    out["terminals"][end_rows] = terminals
    out["timeouts"][end_rows] = timeouts
    return out


def encode_attr(value: Any) -> Any:
    """An HDF5-storable attribute: scalars and strings as is, anything else as a JSON string."""
    if isinstance(value, str | bool | int | float | np.generic):
        return value
    return json.dumps(_thaw(value), sort_keys=True)


def _thaw(value: Any) -> Any:
    """Plain JSON-able containers from frozen ones (Attrs -> dict, tuple/array -> list)."""
    if isinstance(value, Mapping):
        return {str(k): _thaw(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [_thaw(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value
