"""Online LoRA finetuning of the CDT on the deployment buffer (docs/METHOD.md section 4).

After every episode: `cfg.lora_steps` Adam steps on the adapters only (the base params are a
constant of the loss), each on `cfg.lora_batch` K-step windows drawn uniformly over the buffer's
valid (episode, step) positions, RTG/CTG tokens read from the episodes' online labels
(`deploy.labels`: the mean outcome of the episodes run under the same targets by default), and the
cost-aware weighted behaviour-cloning loss of paper eq. 4-5. A variant without LoRA runs the same
program and discards the update with `jnp.where`, so its adapters stay bit-identical.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from safecdt_jax.data.buffer import EpisodeBuffer, buffer_size
from safecdt_jax.data.windows import Windows, sample_windows
from safecdt_jax.deploy.config import DeployConfig, Variant
from safecdt_jax.deploy.reweight import projected_cost_to_go, replay_weights
from safecdt_jax.model.cdt import Params
from safecdt_jax.model.config import CDTConfig
from safecdt_jax.model.lora import Lora, apply_cdt_lora
from safecdt_jax.model.optim import micro_batches, sum_over_passes


def adapter_optimizer(cfg: DeployConfig) -> optax.GradientTransformation:
    """Adam with the adapters' learning rate `cfg.lora_lr` (optax defaults otherwise)."""
    return optax.adam(cfg.lora_lr)


def init_adapter_opt(lora: Lora, cfg: DeployConfig | None = None) -> optax.OptState:
    """Fresh Adam state for `lora` (zero moments, count 0); it does not depend on the lr."""
    return adapter_optimizer(DeployConfig() if cfg is None else cfg).init(lora)


class LabelledEpisodes(NamedTuple):
    """The buffer's episodes with per-episode offsets that move their t = 0 return- and
    cost-to-go onto their online labels (`deploy.labels`); `sample_windows` reads it."""

    observations: Any
    actions: Any
    rewards: Any
    costs: Any
    lengths: Any
    return_offset: Any
    cost_offset: Any


def labelled_episodes(buffer: EpisodeBuffer, labels) -> LabelledEpisodes:
    """`buffer` with each slot's labels `(return_label, cost_label)` [capacity] (raw units) as
    offsets from its realised totals, so that its windows' tokens read the labels at t = 0."""
    ret, cost = labels
    return LabelledEpisodes(
        buffer.observations, buffer.actions, buffer.rewards, buffer.costs, buffer.lengths,
        return_offset=ret - buffer.rewards.sum(axis=1),
        cost_offset=cost - buffer.costs.sum(axis=1))


def valid_windows(windows: Windows) -> jax.Array:
    """[N] bool: the windows with a real first step, the ones the loss averages over."""
    return jnp.asarray(windows.mask)[:, 0] > 0


def lora_loss(
    lora: Lora,
    base_params: Params,
    model_cfg: CDTConfig,
    windows: Windows,
    weights,
    key: jax.Array | None = None,
    count: jax.Array | None = None,
) -> jax.Array:
    """Weighted behaviour-cloning loss of the merged model (scalar, action units squared).

    `mean_i w_i * (masked mean over the window's steps of ||a_hat - a||^2)`, a_hat = the mean of
    the CDT's Gaussian action head with `merge_lora(base_params, lora)`; the mean over i runs over
    the valid windows (those with a real first step). `weights` [N] from `replay_weights`.
    `key` None: evaluation-mode forward pass (no dropout); a key turns the CDT's dropout on.
    `count`: the number of valid windows to divide by (default: those of `windows`); a slice of
    a larger batch passes the whole batch's count, so that the slices' losses sum to its loss.
    """
    batch = windows._asdict()
    out = apply_cdt_lora(base_params, lora, model_cfg, batch, train=key is not None, key=key)
    mask = jnp.asarray(windows.mask, jnp.float32)  # [N, K]
    # jnp.where, not a product: padded targets never reach the sum, whatever they hold.
    err = jnp.where(mask[..., None] > 0, out["action_mean"] - windows.actions, 0.0)
    per_window = (err * err).sum(axis=(1, 2)) / jnp.maximum(mask.sum(axis=1), 1.0)
    valid = valid_windows(windows)
    count = valid.sum() if count is None else count
    return (jnp.where(valid, weights * per_window, 0.0).sum()
            / jnp.maximum(count, 1).astype(jnp.float32))


def adapter_gradient(
    lora: Lora,
    base_params: Params,
    model_cfg: CDTConfig,
    windows: Windows,
    weights,
    key: jax.Array | None,
    micro_batch: int = 0,
) -> tuple[jax.Array, Lora]:
    """`(loss, grads)` of `lora_loss` with respect to the adapters, in passes of at most
    `micro_batch` windows (0: one pass).

    The passes (`model.micro_batches` equal slices, one `lax.scan` step each) divide by the
    whole batch's count of valid windows and are summed: the same loss and gradient up to float
    summation order, with one slice's activations alive at a time (faster on a CPU, where a
    whole batch's activations spill the caches: docs/PERFORMANCE.md). Slice `i` draws its
    dropout with `fold_in(key, i)`.
    """
    grad_fn = jax.value_and_grad(lora_loss)
    size = windows.mask.shape[0]
    n = micro_batches(size, micro_batch)
    if n == 1:
        return grad_fn(lora, base_params, model_cfg, windows, weights, key)
    count = valid_windows(windows).sum()
    return sum_over_passes(
        lambda part, k: grad_fn(lora, base_params, model_cfg, *part, k, count),
        (windows, weights), n, key)


def lora_finetune(
    key: jax.Array,
    lora: Lora,
    opt_state: optax.OptState,
    base_params: Params,
    model_cfg: CDTConfig,
    buffer: EpisodeBuffer,
    lam,
    budget,
    variant: Variant,
    cfg: DeployConfig,
    labels=None,
) -> tuple[Lora, optax.OptState, dict[str, jax.Array]]:
    """`cfg.lora_steps` Adam steps on the adapters from the online buffer (one `lax.scan`).

    Args:
        key: PRNG key of this finetuning round.
        lora, opt_state: the adapters and their Adam state (`init_adapter_opt`).
        base_params: the frozen pretrained CDT params (no gradient flows to them).
        model_cfg: the CDT config (static); windows have its `seq_len` steps.
        buffer: the deployment's episodes (raw rewards/costs); windows are drawn uniformly over
            its valid positions and relabelled with the model's `reward_scale` / `cost_scale`.
        lam: the reweighting multiplier (from `lambda_update`).
        budget: the cost budget B (raw cost units).
        variant: `variant.lora` off (or an empty buffer) returns `lora` and `opt_state`
            bit-identical; `variant.reweight` off makes every replay weight 1.
        cfg: the deployment config (static).
        labels: None (the paper's hindsight labels: each window's tokens count from what its
            episode realised), or `(return_label, cost_label)` [capacity] raw per-slot labels
            from `deploy.labels.online_labels`, which the windows' t = 0 tokens then read. The
            replay weights always use the realised cost-to-go (docs/METHOD.md section 3).

    Returns `(lora, opt_state, aux)`; aux holds per-step arrays [lora_steps]: `loss` (the
    weighted loss before each step's update), `weight_min` (smallest valid replay weight) and
    `excess_fraction` (share of sequences whose cost-to-go exceeds B).
    """
    opt = adapter_optimizer(cfg)
    on = jnp.asarray(variant.lora) & (buffer_size(buffer) > 0)
    episodes = buffer if labels is None else labelled_episodes(buffer, labels)
    episode_costs = buffer.costs.sum(axis=1)  # [capacity], once: the steps only index it

    def gradient(lora, base_params, win, weights, drop_key):
        return adapter_gradient(lora, base_params, model_cfg, win, weights, drop_key,
                                cfg.lora_micro_batch)

    if cfg.resolved().lora_in_turn:
        # A loop over each vmapped axis instead of one batched product, so that one pass's
        # activations stay in cache: wrapped twice for the sweep's two vmaps (runs, seeds).
        in_turn = jax.custom_batching.sequential_vmap
        gradient = in_turn(in_turn(gradient))

    def step(carry, k):
        lora, opt_state = carry
        k_win, k_drop = jax.random.split(k)
        win = sample_windows(
            k_win, episodes, cfg.lora_batch, model_cfg.seq_len, None,
            model_cfg.reward_scale, model_cfg.cost_scale, model_cfg.constant_targets,
        )
        valid = valid_windows(win)
        ctg_first = win.costs_to_go[:, 0] / model_cfg.cost_scale  # back to raw cost units
        if labels is not None:  # the weights read the realised cost-to-go, not the label
            ctg_first = ctg_first - episodes.cost_offset[win.episode_index]
        if cfg.replay_excess == "projected":
            idx = win.episode_index
            ctg_first = projected_cost_to_go(ctg_first, episodes.lengths[idx],
                                             episode_costs[idx], episodes.costs.shape[1])
        weights = replay_weights(ctg_first, valid, lam, budget, cfg, enabled=variant.reweight)
        drop_key = k_drop if cfg.lora_dropout else None
        loss, grads = gradient(lora, base_params, win, weights, drop_key)
        updates, new_opt_state = opt.update(grads, opt_state, lora)
        new_lora = optax.apply_updates(lora, updates)
        # Variants are data: compute the update always, keep it only where LoRA is on.
        lora = jax.tree.map(lambda a, b: jnp.where(on, a, b), new_lora, lora)
        opt_state = jax.tree.map(lambda a, b: jnp.where(on, a, b), new_opt_state, opt_state)
        aux = {
            "loss": loss,
            "weight_min": jnp.where(valid.any(), jnp.min(jnp.where(valid, weights, jnp.inf)), 0.0),
            "excess_fraction": jnp.mean(valid & (ctg_first > budget)),
        }
        return (lora, opt_state), aux

    keys = jax.random.split(key, cfg.lora_steps)
    (lora, opt_state), aux = jax.lax.scan(step, (lora, opt_state), keys)
    return lora, opt_state, aux
