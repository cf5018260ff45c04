"""OSRL's CDT training loss: Gaussian NLL with entropy bonus, cost classifier, state MSE."""

from __future__ import annotations

import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp

from safecdt_jax.model.cdt import Params, apply_cdt
from safecdt_jax.model.config import CDTConfig

_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


def gaussian_log_prob(x: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """Per-dimension log-density of `x` under N(mean, exp(log_std)^2) (same shape as x)."""
    z = (x - mean) * jnp.exp(-log_std)
    return -0.5 * z * z - log_std - _HALF_LOG_2PI


def gaussian_entropy(log_std: jax.Array) -> jax.Array:
    """Per-dimension differential entropy (nats) of N(., exp(log_std)^2)."""
    return 0.5 + _HALF_LOG_2PI + log_std


def loss_normalisers(batch: Mapping[str, jax.Array]) -> dict[str, jax.Array]:
    """The denominators of `cdt_loss`'s averages over a whole batch (counts, float32).

    `valid`: real steps (at least 1); `positions`: all B*K window positions; `pairs`: steps t
    with t and t+1 both real (at least 1; the next-state head's targets). A loss over a slice
    of the batch divided by these is that slice's share of the whole batch's loss, so the
    slices' losses and gradients add up to the whole batch's.
    """
    mask = jnp.asarray(batch["mask"]).astype(jnp.float32)
    pair = mask[:, :-1] * mask[:, 1:]
    return {
        "valid": jnp.maximum(mask.sum(), 1.0),
        "positions": jnp.asarray(mask.size, jnp.float32),
        "pairs": jnp.maximum(pair.sum(), 1.0),
    }


def cdt_loss(
    params: Params,
    log_temperature: jax.Array,
    cfg: CDTConfig,
    batch: Mapping[str, jax.Array],
    key: jax.Array | None,
    norms: Mapping[str, jax.Array] | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """OSRL's CDT loss `act_loss + cost_loss_weight * cost_loss + state_loss_weight * state_loss`.

    Args:
        params: CDT params (the gradient target).
        log_temperature: scalar log of the entropy temperature T; used with stopped gradient.
        cfg: the model config.
        batch: the `apply_cdt` inputs plus `costs [B,K]`, the per-step cost (0/1; any value > 0
            is class 1). Targets: `actions` for the action head, `states[:, 1:]` for the
            next-state head.
        key: dropout key; None evaluates without dropout.
        norms: `loss_normalisers` of the batch this one is a slice of (micro-batching); None
            averages over this batch itself.

    Returns:
        `(loss, aux)`; aux holds `act_loss`, `cost_loss`, `state_loss`, `log_likelihood` and
        `entropy` (per action dimension, mean over valid steps), `cost_accuracy` (over valid
        steps) and `temperature`.

    Averaging follows OSRL: log-likelihood and entropy over valid positions x action dims; the
    cost NLL is masked but divided by all B*K positions (padding counts in the denominator).
    """
    out = apply_cdt(params, cfg, batch, train=key is not None, key=key)
    mask = jnp.asarray(batch["mask"]).astype(jnp.float32)  # [B, K]
    norms = loss_normalisers(batch) if norms is None else norms
    n_valid = norms["valid"]
    temperature = jax.lax.stop_gradient(jnp.exp(log_temperature))

    # The mask multiplies the per-element terms, so whatever the padded actions are, they
    # contribute exactly 0 (jnp.where also stops NaN/inf from padded targets leaking in).
    valid_a = mask[..., None] > 0
    actions = jnp.where(valid_a, jnp.asarray(batch["actions"], jnp.float32), 0.0)
    log_prob = gaussian_log_prob(actions, out["action_mean"], out["action_log_std"])
    per_dim = n_valid * cfg.act_dim
    log_likelihood = jnp.where(valid_a, log_prob, 0.0).sum() / per_dim
    entropy = jnp.where(valid_a, gaussian_entropy(out["action_log_std"]), 0.0).sum() / per_dim
    act_loss = -(log_likelihood + temperature * entropy)

    labels = (jnp.asarray(batch["costs"]) > 0).astype(jnp.int32)  # binarise: OSRL needs {0, 1}
    logp = out["cost_log_probs"]
    nll = -jnp.take_along_axis(logp, labels[..., None], axis=-1)[..., 0]
    cost_loss = (nll * mask).sum() / norms["positions"]
    correct = (jnp.argmax(logp, axis=-1) == labels).astype(jnp.float32)
    cost_accuracy = (correct * mask).sum() / n_valid

    loss = act_loss + cfg.cost_loss_weight * cost_loss
    state_loss = jnp.zeros((), jnp.float32)
    if cfg.use_state_head:
        # Predict s_{t+1} from step t's action token; both steps must be valid.
        pair = mask[:, :-1] * mask[:, 1:]
        target = jnp.asarray(batch["states"], jnp.float32)[:, 1:]
        err = jnp.where(pair[..., None] > 0, out["next_state"][:, :-1] - target, 0.0)
        state_loss = (err * err).sum() / (norms["pairs"] * cfg.obs_dim)
        loss = loss + cfg.state_loss_weight * state_loss

    aux = {
        "act_loss": act_loss,
        "cost_loss": cost_loss,
        "state_loss": state_loss,
        "log_likelihood": log_likelihood,
        "entropy": entropy,
        "cost_accuracy": cost_accuracy,
        "temperature": temperature,
    }
    return loss, aux


def temperature_loss(log_temperature: jax.Array, entropy: jax.Array, cfg: CDTConfig) -> jax.Array:
    """Temperature loss `T * (H - target)` with H stopped and target entropy `-act_dim`.

    Its gradient lowers T when the policy's per-dimension entropy H is above the target.
    """
    target = -float(cfg.act_dim)
    return jnp.exp(log_temperature) * (jax.lax.stop_gradient(entropy) - target)
