"""How much a pretrained CDT relies on each conditioning token, measured on its training windows.

    gaps = conditioning_gaps("ckpt/", "CarGoal1.hdf5")
    gaps["costs_to_go"]     # nats per action dim lost when the CTG tokens are shuffled

A shuffle test: draw windows exactly as pretraining does (relabelled data, OSRL trajectory
weights, the checkpoint's token scales), score the action log-likelihood in evaluation mode, then
score it again with one token type permuted across the windows (each window keeps its states and
actions, but gets another window's whole return- or cost-to-go sequence). The drop is what that
token tells the model beyond everything else in the context. A CDT whose cost-to-go gap is near
zero ignores its cost target: the deployment's scheduler then has nothing to steer.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp

from safecdt_jax.data import sample_windows
from safecdt_jax.data.dsrl import load_dataset
from safecdt_jax.model import CDTConfig
from safecdt_jax.model.loss import cdt_loss
from safecdt_jax.pretrain.checkpoint import configs_from_meta, load_checkpoint
from safecdt_jax.pretrain.loop import prepare_data

TOKENS = ("returns_to_go", "costs_to_go", "timesteps")


def conditioning_gaps(ckpt: str | os.PathLike, data_path: str | os.PathLike,
                      windows: int = 4096, seed: int = 0) -> dict[str, float]:
    """Action log-likelihood (nats per action dim, mean over valid steps) of checkpoint `ckpt` on
    `windows` training windows of `data_path`, and its drop when each token in `TOKENS` is
    shuffled across the windows.

    Returns `{"log_likelihood": ll, "share_ctg_positive": s, token: drop, ...}`, `s` the share of
    the windows whose first step has a positive cost-to-go. Deterministic in `seed`.
    """
    if windows < 2:
        raise ValueError(f"windows must be >= 2 to shuffle, got {windows}")
    model = load_checkpoint(ckpt)
    _, _, cfg = configs_from_meta(model.meta)
    data, weights, _ = prepare_data(load_dataset(data_path), cfg)
    k_draw, k_perm = jax.random.split(jax.random.key(seed))
    win = sample_windows(k_draw, data, windows, model.cfg.seq_len, weights,
                         model.cfg.reward_scale, model.cfg.cost_scale,
                         model.cfg.constant_targets)
    out = shuffle_gaps(model.params, model.cfg, win._asdict(), k_perm)  # as pretraining's batch
    return {**out, "share_ctg_positive": float(jnp.mean(win.costs_to_go[:, 0] > 0))}


def shuffle_gaps(params, cfg: CDTConfig, batch: dict, key: jax.Array) -> dict[str, float]:
    """`{"log_likelihood": ll, token: drop, ...}` of the CDT `(params, cfg)` on the windows
    `batch` (`cdt_loss` inputs), for each token in `TOKENS` permuted across the windows by one
    permutation drawn from `key`; nats per action dim, evaluation mode."""

    @jax.jit
    def log_likelihood(b):
        return cdt_loss(params, jnp.float32(0.0), cfg, b, None)[1]["log_likelihood"]

    base = float(log_likelihood(batch))
    perm = jax.random.permutation(key, batch["mask"].shape[0])
    out = {"log_likelihood": base}
    for name in TOKENS:
        out[name] = base - float(log_likelihood({**batch, name: batch[name][perm]}))
    return out
