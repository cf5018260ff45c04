"""One training program for every baseline: `make_train(cfg, data) -> train(key)`, the updates
a `lax.scan` with batches sampled inside it, so `jit(vmap(train))(keys)` trains all seeds at
once; and the chunked form the runner uses for progress and checkpoints (the same bits)."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from safecdt_jax.baselines import bcql, bearl, cpq
from safecdt_jax.baselines.common import (
    Algorithm,
    TrainState,
    Transitions,
    qc_threshold,
    sample_batch,
)
from safecdt_jax.baselines.config import BaselineConfig

_MAKERS = {"bcql": bcql.make, "bearl": bearl.make, "cpq": cpq.make}


def make_algorithm(cfg: BaselineConfig, obs_dim: int, act_dim: int,
                   episode_len: int) -> Algorithm:
    """`cfg.algo`'s (init, update, act) for these sizes; the per-step cost threshold comes from
    `cfg.cost_limit` over `cfg.episode_len` (or `episode_len`, the data's) steps."""
    length = cfg.episode_len or episode_len
    return _MAKERS[cfg.algo](cfg, obs_dim, act_dim,
                             qc_threshold(cfg.cost_limit, cfg.gamma, length))


def make_chunk(cfg: BaselineConfig, algo: Algorithm) -> Callable:
    """`chunk(state, key, data) -> (state, metrics [chunk] per name)`: `cfg.chunk` updates.
    Step s draws its batch and noise from `fold_in(key, s)`, so a run cut into chunks (or
    resumed from a checkpoint) takes the same steps as one uninterrupted scan."""
    def chunk(state: TrainState, key: jax.Array, data: Transitions):
        def body(state, _):
            k_batch, k_update = jax.random.split(jax.random.fold_in(key, state.step))
            return algo.update(state, sample_batch(k_batch, data, cfg.batch), k_update)

        return jax.lax.scan(body, state, None, length=cfg.chunk)

    return chunk


def make_train(cfg: BaselineConfig, data: Transitions, episode_len: int) -> Callable:
    """`train(key) -> (params, metrics)`: `cfg.steps` updates (rounded up to whole chunks) of
    `cfg.algo` on `data`, metrics [chunks] per name (each the chunk's mean). Pure in `key`."""
    algo = make_algorithm(cfg, data.obs.shape[1], data.action.shape[1], episode_len)
    chunk = make_chunk(cfg, algo)
    n_chunks = -(-cfg.steps // cfg.chunk)

    def train(key: jax.Array):
        k_init, k_train = jax.random.split(key)

        def body(state, _):
            state, metrics = chunk(state, k_train, data)
            return state, jax.tree.map(jnp.mean, metrics)

        state, metrics = jax.lax.scan(body, algo.init(k_init), None, length=n_chunks)
        return state.params, metrics

    return train


__all__ = ["make_algorithm", "make_chunk", "make_train"]
