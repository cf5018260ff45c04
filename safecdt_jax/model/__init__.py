"""The CDT model (Flax), functional LoRA adapters, OSRL's loss and optimisers."""

from safecdt_jax.model.cdt import (
    CDT,
    Params,
    apply_cdt,
    count_params,
    dummy_batch,
    init_cdt,
    last_action,
    newest_action,
    param_shapes,
)
from safecdt_jax.model.config import PRESET_NAMES, CDTConfig
from safecdt_jax.model.lora import (
    Lora,
    apply_cdt_lora,
    init_lora,
    lora_param_count,
    merge_lora,
)
from safecdt_jax.model.loss import (
    cdt_loss,
    gaussian_entropy,
    gaussian_log_prob,
    loss_normalisers,
)
from safecdt_jax.model.optim import (
    OptimConfig,
    Optimizers,
    TrainState,
    batch_gradients,
    init_train_state,
    learning_rate_schedule,
    make_optimizer,
    make_train_step,
    micro_batches,
)
from safecdt_jax.model.tokens import (
    fit_edges,
    piecewise_linear,
    with_nominal_edges,
    with_token_edges,
)

__all__ = [
    "CDT",
    "PRESET_NAMES",
    "CDTConfig",
    "Lora",
    "OptimConfig",
    "Optimizers",
    "Params",
    "TrainState",
    "apply_cdt",
    "apply_cdt_lora",
    "batch_gradients",
    "cdt_loss",
    "count_params",
    "dummy_batch",
    "fit_edges",
    "gaussian_entropy",
    "gaussian_log_prob",
    "init_cdt",
    "init_lora",
    "init_train_state",
    "last_action",
    "learning_rate_schedule",
    "lora_param_count",
    "loss_normalisers",
    "make_optimizer",
    "make_train_step",
    "merge_lora",
    "micro_batches",
    "newest_action",
    "param_shapes",
    "piecewise_linear",
    "with_nominal_edges",
    "with_token_edges",
]
