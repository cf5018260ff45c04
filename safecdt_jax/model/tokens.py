"""Piecewise-linear encoding of the return-to-go and cost-to-go inputs, and its bin edges.

A linear embedding `w * x + b` of a scalar followed by the embedding LayerNorm keeps mostly the
sign of `x`: LayerNorm divides each token by its own spread, so once `|w * x|` outgrows `b` and
the timestep embedding every positive value maps to nearly the same direction. With OSRL's
encodings every return-to-go is positive, and `50 - CTG` changes sign only at CTG 50, so the
cost targets 10, 20 and 40 all read alike. The encoding here (Gorishniy et al. 2022's
piecewise-linear encoding) feeds the embedding with one ramp per bin, 1 below ... 0 above, so each
value has its own direction, and values outside the fitted edges saturate at the end bins.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def steps_left_scale(timesteps, episode_len: int):
    """`T / max(T - t, 1)` for timesteps `t` (same shape, float32): what `token_rates` multiplies
    the return-to-go and cost-to-go by, turning them into the return and cost per step still to
    come, in whole-episode units (equal to the plain values at t = 0)."""
    t = jnp.asarray(timesteps, jnp.float32)
    return episode_len / jnp.maximum(episode_len - t, 1.0)


def piecewise_linear(x: jax.Array, edges: tuple[float, ...]) -> jax.Array:
    """Ramps of `x` [...] over bins `edges` (E increasing floats) -> [..., E - 1] in [0, 1].

    Feature i is `clip((x - edges[i]) / (edges[i+1] - edges[i]), 0, 1)`: all ones below `x`'s
    bin, the fractional position inside it, zeros above. Units are those of `x` and `edges`.
    """
    lo = jnp.asarray(edges[:-1], jnp.float32)
    width = jnp.asarray(np.diff(edges), jnp.float32)
    return jnp.clip((x[..., None] - lo) / width, 0.0, 1.0)


def fit_edges(values: np.ndarray, bins: int, weights: np.ndarray | None = None,
              span: tuple[float, float] | None = None) -> tuple[float, ...]:
    """At most `bins + 1` strictly increasing edges at evenly spaced quantiles of `values`.

    `weights` (same shape, >= 0) weight the quantiles, e.g. by how often training samples each
    step. Repeated quantiles (a value many steps share, such as a cost-to-go of 0) merge, so no
    bin is empty. A constant input gets the two edges `(v, v + 1)`. `span` (lo, hi), same units:
    the edges reach at least this far; an end of the span beyond the values takes one of the
    `bins` as an end bin, so that every value in the span is a distinct input even where the
    values have none (the quantiles then fill the remaining bins). Raises ValueError for an
    empty or non-finite `values`, weights that sum to zero, or a span with lo >= hi.
    """
    values = np.asarray(values, np.float64).reshape(-1)
    w = np.ones_like(values) if weights is None else np.asarray(weights, np.float64).reshape(-1)
    if values.size == 0 or not np.all(np.isfinite(values)):
        raise ValueError("fit_edges needs a non-empty array of finite values")
    if w.shape != values.shape or not np.all(w >= 0) or not w.sum() > 0:
        raise ValueError("fit_edges: weights must match the values, be >= 0 and not all zero")
    order = np.argsort(values, kind="stable")
    values, w = values[order][w[order] > 0], w[order][w[order] > 0]
    below = above = False
    if span is not None:
        lo, hi = (float(x) for x in span)
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ValueError(f"fit_edges: span must be two finite numbers lo < hi, got {span!r}")
        below, above = lo < values[0], hi > values[-1]
        if bins - below - above < 1:
            raise ValueError(f"fit_edges: {bins} bins leave none for the values inside the span")
    cum = (np.cumsum(w) - 0.5 * w) / w.sum()  # each value's mid-point rank in [0, 1]
    q = np.interp(np.linspace(0.0, 1.0, bins - below - above + 1), cum, values)
    q = np.concatenate([[lo] if below else [], q, [hi] if above else []])
    # Merge edges closer than float32 rounding of the values, so that no bin is a sliver.
    tol = 1e-5 * max(1.0, float(np.abs(q).max()))
    edges = [float(np.float32(q[0]))]
    for e in np.float32(q[1:]):
        if e - edges[-1] > tol:
            edges.append(float(e))
    edges = np.asarray(edges, np.float32)
    if edges.size < 2:
        edges = np.array([edges[0], edges[0] + 1.0], np.float32)
    return tuple(float(e) for e in edges)


def with_token_edges(cfg, returns_to_go: np.ndarray, costs_to_go: np.ndarray,
                     weights: np.ndarray | None = None, timesteps: np.ndarray | None = None,
                     return_span: tuple[float, ...] = (), cost_span: tuple[float, ...] = ()):
    """`cfg` (a `CDTConfig`) with `return_edges` / `cost_edges` fitted to per-step raw values.

    `returns_to_go`, `costs_to_go`: arrays of raw (unscaled) RTG and CTG of the steps the model
    will be trained on, `weights` how often each is sampled, `timesteps` their steps in the
    episode (needed with `cfg.token_rates`); the values are scaled by `cfg.reward_scale` /
    `cfg.cost_scale` (and the steps-left scale) first, as the model's inputs are.
    `return_span`, `cost_span`: raw (lo, hi) ranges the edges must cover beyond the values (end
    bins, `fit_edges`), or () for the values' own range. A config with `token_bins == 0` is
    returned unchanged.
    """
    if not cfg.token_bins:
        return cfg
    rtg = np.asarray(returns_to_go) * cfg.reward_scale
    ctg = np.asarray(costs_to_go) * cfg.cost_scale
    if cfg.token_rates:
        if timesteps is None:
            raise ValueError("with_token_edges: token_rates needs the steps' timesteps")
        scale = np.asarray(steps_left_scale(np.asarray(timesteps), cfg.episode_len))
        rtg, ctg = rtg * scale, ctg * scale
    r_span = tuple(x * cfg.reward_scale for x in return_span) or None
    c_span = tuple(x * cfg.cost_scale for x in cost_span) or None
    return cfg.replace(return_edges=fit_edges(rtg, cfg.token_bins, weights, r_span),
                       cost_edges=fit_edges(ctg, cfg.token_bins, weights, c_span))


def with_nominal_edges(cfg, max_return: float = 60.0, max_cost: float = 100.0):
    """`cfg` with evenly spaced ramp edges over raw return-to-go [0, max_return] and cost-to-go
    [0, max_cost] (the source tasks' range), for a model built without data: throughput
    benchmarks and tests of the architecture. Pretraining fits the edges to its data instead
    (`with_token_edges`). A config with `token_bins == 0` is returned unchanged."""
    if not cfg.token_bins:
        return cfg
    n = cfg.token_bins + 1
    return with_token_edges(cfg, np.linspace(0.0, max_return, n), np.linspace(0.0, max_cost, n))
