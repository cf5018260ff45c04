"""A fixed-size episode buffer for the online deployment loop (docs/METHOD.md section 4).

Shapes never change, so adding and sampling live inside one jit-ed / scanned program. The same
`sample_windows` works on it: with `weights=None` windows are drawn uniformly over the valid
(episode, step) positions, and empty slots (length 0) are never drawn.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp


@dataclasses.dataclass(frozen=True)
class EpisodeBuffer:
    """Ring buffer of `capacity` episodes x `horizon` steps (a pytree).

    observations [N, T, obs_dim], actions [N, T, act_dim], rewards, costs [N, T] (raw per-step
    values, zero past each length), lengths int32 [N] (0 = empty slot), count int32 [] = episodes
    added so far (may exceed N; the valid episodes are the last min(count, N) added).
    """

    observations: Any
    actions: Any
    rewards: Any
    costs: Any
    lengths: Any
    count: Any

    @property
    def capacity(self) -> int:
        """Number of episode slots N."""
        return self.rewards.shape[0]

    @property
    def horizon(self) -> int:
        """Steps per slot T."""
        return self.rewards.shape[1]


jax.tree_util.register_dataclass(EpisodeBuffer)


def buffer_init(capacity: int, horizon: int, obs_dim: int, act_dim: int) -> EpisodeBuffer:
    """An empty buffer: all slots zero with length 0, count 0 (float32 arrays)."""
    return EpisodeBuffer(
        observations=jnp.zeros((capacity, horizon, obs_dim), jnp.float32),
        actions=jnp.zeros((capacity, horizon, act_dim), jnp.float32),
        rewards=jnp.zeros((capacity, horizon), jnp.float32),
        costs=jnp.zeros((capacity, horizon), jnp.float32),
        lengths=jnp.zeros((capacity,), jnp.int32),
        count=jnp.zeros((), jnp.int32),
    )


def buffer_add(buf: EpisodeBuffer, episode: Mapping[str, Any], length) -> EpisodeBuffer:
    """Write one episode into slot `count % capacity` and return the new buffer (pure, jit-able).

    `episode` holds `observations` [T, obs_dim], `actions` [T, act_dim], `rewards`, `costs` [T]
    (T = the buffer horizon, raw units); `length` (traced int ok) is the number of real steps,
    clipped to [0, T]. Steps at and past `length` are stored as zeros.
    Full buffer: it wraps, overwriting the oldest episode, so it always holds the most recent
    min(count, capacity) episodes; a deployment sized capacity >= episodes never wraps.
    """
    length = jnp.clip(jnp.asarray(length, jnp.int32), 0, buf.horizon)
    slot = buf.count % buf.capacity
    valid = jnp.arange(buf.horizon) < length

    def put(store, key):
        x = jnp.asarray(episode[key], store.dtype).reshape(store.shape[1:])
        x = jnp.where(valid.reshape(valid.shape + (1,) * (x.ndim - 1)), x, 0)
        return store.at[slot].set(x)

    return EpisodeBuffer(
        observations=put(buf.observations, "observations"),
        actions=put(buf.actions, "actions"),
        rewards=put(buf.rewards, "rewards"),
        costs=put(buf.costs, "costs"),
        lengths=buf.lengths.at[slot].set(length),
        count=buf.count + 1,
    )


def buffer_size(buf: EpisodeBuffer):
    """Number of valid episodes held: min(count, capacity) (int32 array)."""
    return jnp.minimum(buf.count, buf.capacity)
