"""Safe-CDT deployment: config and variants, target scheduler, replay reweighting, LoRA updates.

Per episode e (0-based) of a deployment, in this order: roll out with the targets of
`stage_ratios(sched, e, variant, cfg)` -> `targets(...)`; add the episode to the buffer;
`lambda_update` (after the warmup); `lora_finetune` with the new lambda; `scheduler_step`
(changes CR/RR at the end of each U-episode stage). Every piece is pure and shape-static, and
variants are arrays (`make_variant`, `stack_variants`), so a whole deployment is one program.
"""

from safecdt_jax.deploy.config import (
    VARIANT_SPECS,
    DeployConfig,
    Variant,
    make_variant,
    stack_variants,
)
from safecdt_jax.deploy.finetune import (
    adapter_gradient,
    adapter_optimizer,
    init_adapter_opt,
    lora_finetune,
    lora_loss,
)
from safecdt_jax.deploy.loop import (
    Carry,
    DeploySpec,
    Metrics,
    deploy,
    deploy_episodes,
    deploy_init,
    init_adapters,
    make_spec,
    seed_keys,
)
from safecdt_jax.deploy.reweight import lambda_init, lambda_update, replay_weights
from safecdt_jax.deploy.rollout import cdt_episode, evaluate_targets
from safecdt_jax.deploy.scheduler import (
    SchedulerState,
    scheduler_init,
    scheduler_step,
    scheduler_update,
    stage_ratios,
    targets,
    wilson_lower,
    window_mask,
)
from safecdt_jax.deploy.sweep import stack_specs, sweep

__all__ = [
    "VARIANT_SPECS",
    "Carry",
    "DeployConfig",
    "DeploySpec",
    "Metrics",
    "SchedulerState",
    "Variant",
    "adapter_gradient",
    "adapter_optimizer",
    "cdt_episode",
    "deploy",
    "deploy_episodes",
    "deploy_init",
    "evaluate_targets",
    "init_adapter_opt",
    "init_adapters",
    "lambda_init",
    "lambda_update",
    "lora_finetune",
    "lora_loss",
    "make_spec",
    "make_variant",
    "replay_weights",
    "scheduler_init",
    "scheduler_step",
    "scheduler_update",
    "seed_keys",
    "stack_specs",
    "stack_variants",
    "stage_ratios",
    "sweep",
    "targets",
    "wilson_lower",
    "window_mask",
]
