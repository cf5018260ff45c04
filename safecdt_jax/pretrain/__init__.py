"""Offline CDT pretraining: the chunked training loop, orbax checkpoints, and loading them.

    result = pretrain("CarGoal1.hdf5", "ckpt/", preset="cpu")   # or resume=True
    params, cfg, meta = load_policy("ckpt/", task="CarGoal2")    # checks the sizes fit
"""

from safecdt_jax.pretrain.checkpoint import (
    Checkpoint,
    CheckpointError,
    checkpoint_steps,
    config_diff,
    configs_from_meta,
    load_checkpoint,
    load_policy,
    read_meta,
    restore_state,
    save_checkpoint,
)
from safecdt_jax.pretrain.config import PretrainConfig, default_pretrain
from safecdt_jax.pretrain.loop import (
    METRICS,
    History,
    TrainData,
    make_train_chunk,
    make_update,
    prepare_data,
    run_key,
    train,
)
from safecdt_jax.pretrain.run import (
    PretrainResult,
    RunSpec,
    dataset_record,
    ensure_checkpoint,
    plan,
    pretrain,
    train_run,
)

__all__ = [
    "METRICS",
    "Checkpoint",
    "CheckpointError",
    "History",
    "PretrainConfig",
    "PretrainResult",
    "RunSpec",
    "TrainData",
    "checkpoint_steps",
    "config_diff",
    "configs_from_meta",
    "dataset_record",
    "default_pretrain",
    "ensure_checkpoint",
    "load_checkpoint",
    "load_policy",
    "make_train_chunk",
    "make_update",
    "plan",
    "prepare_data",
    "pretrain",
    "read_meta",
    "restore_state",
    "run_key",
    "save_checkpoint",
    "train",
    "train_run",
]
