"""The Safe-CDT deployment (docs/METHOD.md) as one pure function, and sweeps of it as one call.

`deploy` runs `cfg.episodes` episodes as one `lax.scan`; each episode is itself a `lax.scan` over
the env horizon (`rollout.cdt_episode`), and the online buffer is a fixed-size `EpisodeBuffer`.
Per episode, in order: roll out with the current targets and merged adapters; store the episode;
update lambda (after the warmup); run the LoRA steps with cost-aware weights; at the end of every
stage of U episodes run the Wilson-score scheduler. Variants, budgets and the reference return
are data (`DeploySpec`), so every variant shares one compiled program.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from safecdt_jax.data.buffer import buffer_add, buffer_init
from safecdt_jax.deploy.config import DeployConfig, Variant
from safecdt_jax.deploy.finetune import init_adapter_opt, lora_finetune
from safecdt_jax.deploy.labels import online_labels, resolve_label_rule
from safecdt_jax.deploy.reweight import lambda_init, lambda_update
from safecdt_jax.deploy.rollout import cdt_episode
from safecdt_jax.deploy.scheduler import (
    scheduler_init,
    scheduler_step,
    stage_ratios,
    targets,
    window_mask,
)
from safecdt_jax.envs.env import SafetyEnv
from safecdt_jax.envs.types import EnvParams
from safecdt_jax.model.cdt import Params
from safecdt_jax.model.config import CDTConfig
from safecdt_jax.model.lora import Lora, init_lora, merge_lora


@dataclass(frozen=True)
class DeploySpec:
    """What one deployment is asked to do, as arrays (a pytree; stack it to sweep).

    Attributes:
        variant: which parts of Safe-CDT run (`config.make_variant`).
        budget: float32 [], the cost budget B in cost units (an episode violates when cost > B).
        reference_return: float32 [], R_ref, the 95th percentile of the source data set's episode
            returns (return units); RTG targets are RR * R_ref.
    """

    variant: Variant
    budget: Any
    reference_return: Any


jax.tree_util.register_dataclass(DeploySpec)


def make_spec(variant: Variant, budget: float, reference_return: float) -> DeploySpec:
    """A `DeploySpec` with float32 scalars; raises ValueError for a non-positive budget."""
    if not budget > 0:
        raise ValueError(f"the cost budget must be positive, got {budget!r}")
    return DeploySpec(variant, jnp.float32(budget), jnp.float32(reference_return))


class Metrics(NamedTuple):
    """Per-episode metrics of a deployment, each [episodes] (leading axes added by sweeps).

    returns, costs: the episode's return and cost (raw units). violation: bool, cost > B.
    ctg_target, rtg_target: the raw targets the episode started from. lam: lambda after the
    episode. a_c, a_r: the scheduler's Wilson lower bounds over the window ending at the episode.
    lora_loss: the weighted adapter loss at the last LoRA step after the episode (0 for a
        variant without LoRA, whose update is discarded).
    """

    returns: jax.Array
    costs: jax.Array
    violation: jax.Array
    ctg_target: jax.Array
    rtg_target: jax.Array
    lam: jax.Array
    a_c: jax.Array
    a_r: jax.Array
    lora_loss: jax.Array


class Carry(NamedTuple):
    """Everything a deployment carries from one episode to the next (a pytree)."""

    lora: Lora
    opt_state: Any
    buffer: Any
    scheduler: Any
    lam: jax.Array
    history: dict[str, jax.Array]
    key: jax.Array


def deploy_init(key: jax.Array, lora_init: Lora, spec: DeploySpec, *, env: SafetyEnv,
                model_cfg: CDTConfig, cfg: DeployConfig) -> Carry:
    """The carry before episode 0: fresh Adam state, empty buffer, CR_0 / RR_0, lambda_0."""
    zeros = jnp.zeros((cfg.episodes,), jnp.float32)
    return Carry(
        lora=lora_init,
        opt_state=init_adapter_opt(lora_init, cfg),
        buffer=buffer_init(cfg.episodes, cfg.horizon or env.episode_length, model_cfg.obs_dim,
                           model_cfg.act_dim),
        scheduler=scheduler_init(cfg),
        lam=lambda_init(cfg, spec.variant.reweight),
        history={"costs": zeros, "returns": zeros, "rtg": zeros, "ctg": zeros},
        key=key,
    )


def deploy_episodes(
    carry: Carry,
    episodes: jax.Array,
    base_params: Params,
    env_params: EnvParams,
    spec: DeploySpec,
    *,
    env: SafetyEnv,
    model_cfg: CDTConfig,
    cfg: DeployConfig,
    finetune: bool = True,
) -> tuple[Carry, Metrics]:
    """Run the episodes with indices `episodes` [n] (consecutive, from the carry's point on).

    `deploy` runs all of them in one scan; a caller may also run the same program in chunks
    (e.g. to show progress), with identical results. `finetune` (static) False leaves the LoRA
    steps out of the program: valid only when no variant of the batch trains its adapters
    (`variant.lora` all False), where the update is discarded anyway, so every metric is the
    same bits and the episodes cost only their rollouts.
    """
    variant, budget = spec.variant, spec.budget

    def episode(carry: Carry, e):
        key, k_env, k_lora = jax.random.split(carry.key, 3)
        cr, rr = stage_ratios(carry.scheduler, e, variant, cfg)
        ctg, rtg = targets(cr, rr, budget, spec.reference_return)
        params = merge_lora(base_params, carry.lora, model_cfg)
        ep = cdt_episode(k_env, env, env_params, params, model_cfg, rtg, ctg,
                         clip_ctg=cfg.clip_ctg, horizon=cfg.horizon,
                         stop_cost=budget if cfg.stop_over_budget else None)
        buffer = buffer_add(carry.buffer, ep, ep["length"])
        h = carry.history
        history = {"costs": h["costs"].at[e].set(ep["cost"]),
                   "returns": h["returns"].at[e].set(ep["return"]),
                   "rtg": h["rtg"].at[e].set(rtg),
                   "ctg": h["ctg"].at[e].set(ctg)}
        window = window_mask(e, cfg.episodes, cfg.window)
        violations = history["costs"] > budget
        lam = lambda_update(carry.lam, violations, window, e, cfg, enabled=variant.reweight)
        if finetune:
            # Buffer slot e holds episode e: its capacity is the deployment's length.
            rule = resolve_label_rule(cfg.lora_labels, model_cfg.stochastic_actions)
            labels = None if rule == "hindsight" else online_labels(
                rule, history["returns"], history["costs"], buffer.lengths,
                history["rtg"], history["ctg"], jnp.arange(cfg.episodes) <= e, buffer.horizon)
            lora, opt_state, aux = lora_finetune(
                k_lora, carry.lora, carry.opt_state, base_params=base_params,
                model_cfg=model_cfg, buffer=buffer, lam=lam, budget=budget, variant=variant,
                cfg=cfg, labels=labels)
            loss = jnp.where(variant.lora, aux["loss"][-1], 0.0)
        else:
            lora, opt_state, loss = carry.lora, carry.opt_state, jnp.zeros((), jnp.float32)
        sched, a_c, a_r = scheduler_step(
            carry.scheduler, e, window_costs=history["costs"], window_returns=history["returns"],
            window_rtg_targets=history["rtg"], window_valid=window, budget=budget,
            variant=variant, cfg=cfg)
        metrics = Metrics(returns=ep["return"], costs=ep["cost"], violation=ep["cost"] > budget,
                          ctg_target=ctg, rtg_target=rtg, lam=lam, a_c=a_c, a_r=a_r,
                          lora_loss=loss)
        return Carry(lora, opt_state, buffer, sched, lam, history, key), metrics

    return jax.lax.scan(episode, carry, jnp.asarray(episodes, jnp.int32))


def deploy(
    key: jax.Array,
    base_params: Params,
    lora_init: Lora,
    env_params: EnvParams,
    spec: DeploySpec,
    *,
    env: SafetyEnv,
    model_cfg: CDTConfig,
    cfg: DeployConfig,
) -> Metrics:
    """Deploy the pretrained CDT for `cfg.episodes` episodes in the target task (pure).

    Args:
        key: PRNG key of this seed (layouts, window sampling).
        base_params: the pretrained CDT (frozen).
        lora_init: the adapters at the start (`init_lora`; B = 0, so the model starts as the base).
        env_params: the target task's params (level, dynamics).
        spec: variant, budget and reference return (data).
        env, model_cfg, cfg: static (the task, the model's config, the deployment's numbers).

    Returns `Metrics`, arrays [cfg.episodes]: one `lax.scan` over episodes, each a `lax.scan`
    over the env horizon.
    """
    static = dict(env=env, model_cfg=model_cfg, cfg=cfg)
    carry = deploy_init(key, lora_init, spec, **static)
    _, metrics = deploy_episodes(carry, jnp.arange(cfg.episodes), base_params, env_params, spec,
                                 **static)
    return metrics


def seed_keys(seed: int, seeds: int) -> jax.Array:
    """`seeds` PRNG keys of a sweep; seed i's key is the same whatever the number of seeds."""
    return jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(seed), i))(
        jnp.arange(seeds, dtype=jnp.uint32))


def init_adapters(keys: jax.Array, base_params: Params, model_cfg: CDTConfig) -> Lora:
    """One fresh adapter set per key (leading axis = seeds), sharing the base's shapes."""
    sub = jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys)
    return jax.vmap(lambda k: init_lora(k, base_params, model_cfg))(sub)
