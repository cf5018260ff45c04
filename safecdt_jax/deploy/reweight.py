"""Cost-aware replay reweighting (docs/METHOD.md section 3; paper eq. 3 and 5).

A multiplier lambda tracks the recent violation rate: it rises fast when more than v* of the
window's episodes exceed the budget and decays slowly otherwise. Replay sequences whose realized
cost-to-go exceeds the budget are down-weighted by exp(-lambda * excess / B) (floored), and the
weights are renormalised to mean 1 so the loss scale stays stable. Variants without reweighting
hold lambda = 0 and every weight 1.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from safecdt_jax.deploy.config import DeployConfig


def lambda_init(cfg: DeployConfig, enabled=True) -> jax.Array:
    """Initial multiplier (float32 []): `cfg.lambda0`, or 0 when reweighting is off (`enabled`
    may be a traced bool, e.g. `variant.reweight`)."""
    return jnp.where(enabled, jnp.float32(cfg.lambda0), jnp.float32(0.0))


def lambda_update(
    lam, window_violations, window_valid, episode_index, cfg: DeployConfig, enabled=True
) -> jax.Array:
    """The multiplier after episode `episode_index` (0-based, traced ok) finished (float32 []).

    v = violation rate over the valid window entries (`window_violations` [W'] bool/0-1: episode
    cost > B). Frozen while fewer than `cfg.lambda_warmup` episodes have finished (i.e. for
    episode_index < warmup - 1); afterwards, every episode: if v > v*, lambda <- min(lambda +
    lambda_rise * (v - v*), lambda_max), else lambda <- max(lambda_decay * lambda, 0).
    `enabled` False (the variant's `reweight` flag) gives 0 throughout.
    """
    lam = jnp.asarray(lam, jnp.float32)
    valid = jnp.asarray(window_valid, jnp.bool_)
    n = valid.sum()
    violations = (valid & (jnp.asarray(window_violations) > 0)).sum()
    v = violations / jnp.maximum(n, 1)  # empty window: v = 0 (no evidence of violations)
    rise = jnp.minimum(lam + cfg.lambda_rise * (v - cfg.violation_target), cfg.lambda_max)
    decay = jnp.maximum(cfg.lambda_decay * lam, 0.0)
    new = jnp.where(v > cfg.violation_target, rise, decay)
    warm = episode_index + 1 >= cfg.lambda_warmup
    new = jnp.where(warm, new, lam)
    return jnp.where(enabled, new, 0.0).astype(jnp.float32)


def projected_cost_to_go(ctg_first, lengths, totals, horizon: int) -> jax.Array:
    """[N] cost-to-go (raw cost units) of windows whose episodes may have been cut short,
    extended over the steps an episode did not run at the cost rate it ran them.

    `ctg_first` [N]: each window's realised cost-to-go at its first step; `lengths` [N] and
    `totals` [N]: its episode's steps and realised total cost; `horizon`: the steps of a full
    episode. C = ctg_first + (horizon - length) * total / length, so a full-length episode's
    windows keep their realised value, and every window of an episode cut at B + 1 after a
    third of the horizon reads about 2 (B + 1) more: what the episode was on course to pay.
    """
    length = jnp.maximum(jnp.asarray(lengths, jnp.float32), 1.0)
    missing = jnp.maximum(horizon - length, 0.0)
    return jnp.asarray(ctg_first, jnp.float32) + missing * jnp.asarray(totals, jnp.float32) / length


def replay_weights(ctg_first, mask, lam, budget, cfg: DeployConfig, enabled=True) -> jax.Array:
    """Per-sequence loss weights w [N] (float32), paper eq. 5.

    `ctg_first` [N]: each sequence's realized cost-to-go at its first step, raw cost units (not
    scaled by cost_scale). `mask` [N]: which sequences are real (an empty buffer draws fully
    masked ones). e = max(0, C - B); w~ = max(exp(-lambda e / B), weight_floor); w = w~ / mean of
    w~ over the valid sequences, so the valid weights average exactly 1. Invalid sequences get 0.
    `enabled` False (traced ok): weight 1 for every valid sequence. `budget` B > 0.
    """
    valid = jnp.asarray(mask, jnp.bool_)
    excess = jnp.maximum(jnp.asarray(ctg_first, jnp.float32) - budget, 0.0)
    raw = jnp.maximum(jnp.exp(-lam * excess / budget), cfg.weight_floor)
    raw = jnp.where(valid, raw, 0.0)
    mean = raw.sum() / jnp.maximum(valid.sum(), 1)
    weights = raw / jnp.where(mean > 0, mean, 1.0)
    return jnp.where(enabled, weights, valid.astype(jnp.float32)).astype(jnp.float32)
