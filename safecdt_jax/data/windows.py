"""Returns-to-go, trajectory sampling weights and K-step training windows (OSRL 2.3-2.5).

Works on any episode container with padded `observations`, `actions`, `rewards`, `costs`
`[n, T, ...]` and `lengths [n]`: a `Dataset` or an `EpisodeBuffer`. Optional per-episode
`return_offset` / `cost_offset` (set by Pareto relabelling) shift every valid RTG / CTG.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


def _valid(lengths, horizon: int):
    """Bool [n, T]: step t is inside episode i."""
    return jnp.arange(horizon)[None, :] < jnp.asarray(lengths)[:, None]


def suffix_sums(values, lengths):
    """Undiscounted suffix sums over padded episodes: out[i, t] = sum_{u=t}^{len_i-1} values[i, u].

    `values` [n, T], `lengths` [n]; zero at and past each length, whatever `values` holds there.
    Same units as `values`. jit-able.
    """
    values = jnp.asarray(values)
    valid = _valid(lengths, values.shape[1])
    kept = jnp.where(valid, values, 0.0)
    return jnp.where(valid, jnp.cumsum(kept[:, ::-1], axis=1)[:, ::-1], 0.0)


def _offset(data, name: str, n: int):
    offset = getattr(data, name, None)
    return jnp.zeros(n, jnp.float32) if offset is None else jnp.asarray(offset, jnp.float32)


def _to_go(values, lengths, offset, constant: bool):
    out = suffix_sums(values, lengths)
    valid = _valid(lengths, out.shape[1])
    if constant:  # every step carries its episode's t=0 value
        out = jnp.where(valid, out[:, :1], 0.0)
    return out + jnp.where(valid, offset[:, None], 0.0)


def returns_to_go(data, constant: bool = False):
    """Raw (unscaled) return-to-go [n, T]: suffix sums of rewards + `return_offset`, 0 past len.

    `constant=True` (`CDTConfig.constant_targets`): each valid step holds the t=0 value."""
    return _to_go(data.rewards, data.lengths,
                  _offset(data, "return_offset", data.rewards.shape[0]), constant)


def costs_to_go(data, constant: bool = False):
    """Raw (unscaled) cost-to-go [n, T]: suffix sums of costs plus `cost_offset`, 0 past len.

    `constant=True` (`CDTConfig.constant_targets`): each valid step holds the t=0 value."""
    return _to_go(data.costs, data.lengths,
                  _offset(data, "cost_offset", data.costs.shape[0]), constant)


def episode_costs(data) -> np.ndarray:
    """Per-episode cost-to-go at t=0 (total cost plus `cost_offset`), raw units, float64 [n]."""
    valid = np.arange(np.shape(data.costs)[1])[None, :] < np.asarray(data.lengths)[:, None]
    total = np.where(valid, np.asarray(data.costs, np.float64), 0.0).sum(axis=1)
    offset = getattr(data, "cost_offset", None)
    return total + (0.0 if offset is None else np.asarray(offset, np.float64))


def episode_returns(data) -> np.ndarray:
    """Per-episode return-to-go at t=0 (total reward plus `return_offset`), raw, float64 [n]."""
    valid = np.arange(np.shape(data.rewards)[1])[None, :] < np.asarray(data.lengths)[:, None]
    total = np.where(valid, np.asarray(data.rewards, np.float64), 0.0).sum(axis=1)
    offset = getattr(data, "return_offset", None)
    return total + (0.0 if offset is None else np.asarray(offset, np.float64))


def trajectory_weights(data, c0: float = 70.0) -> np.ndarray:
    """OSRL's episode sampling probabilities: max(0, c0 - C_i), normalised (float32 [n]).

    C_i is the episode's cost-to-go at t=0 in raw cost units (relabelled copies included), so
    episodes with C_i >= c0 (default 70) are never drawn; empty episodes get weight 0.
    Raises ValueError when every weight is zero.
    """
    costs = episode_costs(data)
    w = np.maximum(0.0, c0 - costs) * (np.asarray(data.lengths) > 0)
    total = w.sum()
    if not total > 0:
        raise ValueError(
            f"trajectory_weights: all {costs.size} episodes have zero weight (every episode "
            f"cost-to-go >= c0={c0}, min {costs.min() if costs.size else float('nan'):g}); "
            "raise c0 or use other data"
        )
    return (w / total).astype(np.float32)


class Windows(NamedTuple):
    """A batch of K-step training windows (B = batch).

    states [B, K, obs_dim], actions [B, K, act_dim]: zero past the episode end.
    returns_to_go, costs_to_go [B, K]: RTG * reward_scale, CTG * cost_scale, zero past the end.
    costs [B, K]: raw per-step costs (cost-head labels), zero past the end.
    timesteps [B, K] int32: absolute steps start..start+K-1, counting on past the end.
    mask [B, K] float32: 1 on real steps, 0 on padding.
    episode_index [B] int32, start [B] int32: where each window came from.
    """

    states: Any
    actions: Any
    returns_to_go: Any
    costs_to_go: Any
    costs: Any
    timesteps: Any
    mask: Any
    episode_index: Any
    start: Any


def _draw(key, p, batch: int):
    """Inverse-CDF draw of `batch` indices with probability proportional to p >= 0."""
    cdf = jnp.cumsum(p)
    u = jax.random.uniform(key, (batch,)) * cdf[-1]
    # side="right" skips zero-weight entries: their cdf equals the previous entry's.
    return jnp.minimum(jnp.searchsorted(cdf, u, side="right"), p.shape[0] - 1).astype(jnp.int32)


def sample_windows(
    key,
    data,
    batch: int,
    K: int,
    weights=None,
    reward_scale: float = 0.1,
    cost_scale: float = 1.0,
    constant: bool = False,
) -> Windows:
    """Sample `batch` windows of `K` steps, as OSRL's SequenceDataset (docs/METHOD.md A.2).

    An episode is drawn with probability proportional to `weights` [n] (e.g. `trajectory_weights`;
    empty episodes never), or, with `weights=None`, proportional to its length, i.e. uniform over
    all valid (episode, step) positions (the online buffer rule). The start is uniform over
    [0, len-1]. Returns `Windows`; RTG/CTG are scaled by `reward_scale` / `cost_scale`;
    `constant=True` (`CDTConfig.constant_targets`) gives every step its episode's t=0 values.
    jit with `static_argnames=("batch", "K", "constant")`. If no episode has positive weight
    (an empty buffer) the draw is arbitrary and its window is fully masked.
    A `data.source` [n] (optional) makes the episodes a view: episode i reads its steps from
    row `source[i]` of the step arrays (observations, actions, rewards, costs) and keeps its own
    length and offsets, so relabelled copies need no copied steps (`pretrain.seeds`).
    """
    lengths = jnp.asarray(data.lengths, jnp.int32)
    n, horizon = lengths.shape[0], data.rewards.shape[1]
    source = getattr(data, "source", None)
    if weights is None:
        p = lengths.astype(jnp.float32)
    else:
        p = jnp.where(lengths > 0, jnp.asarray(weights, jnp.float32), 0.0)
    k_episode, k_start = jax.random.split(key)
    episode = _draw(k_episode, p, batch)
    row = episode if source is None else jnp.asarray(source, jnp.int32)[episode]
    length = lengths[episode]
    start = jax.random.randint(k_start, (batch,), 0, jnp.maximum(length, 1), dtype=jnp.int32)
    timesteps = start[:, None] + jnp.arange(K, dtype=jnp.int32)[None, :]
    valid = timesteps < length[:, None]
    step = jnp.minimum(timesteps, horizon - 1)  # gather index; padded steps are zeroed below
    rows = row[:, None]

    def window(x):
        x = jnp.asarray(x)[rows, step]
        return jnp.where(valid.reshape(valid.shape + (1,) * (x.ndim - 2)), x, 0).astype(x.dtype)

    # Suffix sums over the drawn episodes only: O(batch * T), no precomputed [n, T] arrays.
    picked = _Picked(
        rewards=jnp.asarray(data.rewards)[row],
        costs=jnp.asarray(data.costs)[row],
        lengths=length,
        return_offset=_offset(data, "return_offset", n)[episode],
        cost_offset=_offset(data, "cost_offset", n)[episode],
    )
    rtg = jnp.take_along_axis(returns_to_go(picked, constant), step, axis=1)
    ctg = jnp.take_along_axis(costs_to_go(picked, constant), step, axis=1)
    return Windows(
        states=window(data.observations),
        actions=window(data.actions),
        returns_to_go=jnp.where(valid, rtg * reward_scale, 0.0),
        costs_to_go=jnp.where(valid, ctg * cost_scale, 0.0),
        costs=window(data.costs),
        timesteps=timesteps,
        mask=valid.astype(jnp.float32),
        episode_index=episode,
        start=start,
    )


class _Picked(NamedTuple):
    rewards: Any
    costs: Any
    lengths: Any
    return_offset: Any
    cost_offset: Any
