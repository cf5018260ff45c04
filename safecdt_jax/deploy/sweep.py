"""Sweeps: `jit(vmap(vmap(deploy)))` over runs (variants, budgets, env params) and seeds.

One call deploys every (run, seed) pair: runs are the leading axis of a stacked `DeploySpec`
(and, optionally, of the env params), seeds the second. With several devices the seed axis is
sharded over a `('seeds',)` mesh (seeds padded to a multiple of the device count, the padding
dropped from the result); each seed's result does not depend on how many devices ran it. Under
several cooperating processes (`safecdt_jax.distributed`) the mesh spans every process's
devices: each process computes its seeds, and the metrics are gathered to all of them.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from safecdt_jax import distributed, programs
from safecdt_jax.deploy.config import DeployConfig
from safecdt_jax.deploy.loop import (
    Carry,
    DeploySpec,
    Metrics,
    deploy_episodes,
    deploy_init,
    init_adapters,
)
from safecdt_jax.envs.env import SafetyEnv
from safecdt_jax.envs.types import EnvParams
from safecdt_jax.model.cdt import Params
from safecdt_jax.model.config import CDTConfig


@functools.cache
def _compiled(env: SafetyEnv, model_cfg: CDTConfig, cfg: DeployConfig, env_batched: bool,
              finetune: bool = True, params_batched: bool = False):
    """Jitted (init, episodes) programs over runs x seeds for one (env, model, config); without
    the LoRA steps when not `finetune` (`loop.deploy_episodes`); with a base model per seed
    when `params_batched`."""
    static = dict(env=env, model_cfg=model_cfg, cfg=cfg)
    env_axis = 0 if env_batched else None
    base_axis = 0 if params_batched else None

    def init(key, lora, spec):
        return deploy_init(key, lora, spec, **static)

    def episodes(carry, index, base, env_params, spec):
        return deploy_episodes(carry, index, base, env_params, spec, **static,
                               finetune=finetune)

    init_all = jax.vmap(jax.vmap(init, (0, 0, None)), (None, None, 0))
    run_all = jax.vmap(jax.vmap(episodes, (0, None, base_axis, None, None)),
                       (0, None, None, env_axis, 0))
    # The carry (adapters, optimiser, the online buffer: GBs at hundreds of seeds) is donated, so
    # each chunk updates it in place instead of holding the old and the new copy.
    return jax.jit(init_all), jax.jit(run_all, donate_argnums=0)


def stored_episodes(run_all: Callable, args: tuple, *, env: SafetyEnv, model_cfg: CDTConfig,
                    cfg: DeployConfig, env_params_batched: bool, finetune: bool,
                    params_batched: bool = False) -> Callable:
    """The episodes program `run_all` of `_compiled(env, model_cfg, cfg, env_params_batched,
    finetune, params_batched)` for arguments shaped like `args`, or, with storing on
    (`programs.enable`), its stored trace: a warm start then skips tracing the whole
    deployment (same bits)."""
    static = (env, model_cfg, cfg, env_params_batched, finetune)
    return programs.cached(run_all, args, name="deploy.sweep.episodes",
                           static=static + ((True,) if params_batched else ()), donate=(0,))


def sweep(
    keys: jax.Array,
    base_params: Params,
    env_params: EnvParams,
    specs: DeploySpec,
    *,
    env: SafetyEnv,
    model_cfg: CDTConfig,
    cfg: DeployConfig,
    env_params_batched: bool = False,
    devices: list | None = None,
    chunk: int | None = None,
    progress: Callable[[int], None] | None = None,
    return_carry: bool = False,
    params_batched: bool = False,
) -> Metrics | tuple[Metrics, Carry]:
    """Deploy every run in `specs` with every seed key; returns `Metrics` arrays [R, S, E].

    Args:
        keys: [S] PRNG keys, one per seed (`loop.seed_keys`); each seed also gets its own fresh
            adapters, drawn from its key.
        base_params: the pretrained CDT, shared by every run and seed; with
            `params_batched` every leaf has a leading [S] axis, one base model per seed (e.g.
            several pretraining seeds' checkpoints, each deployed with several keys).
        env_params: the target task's params; with `env_params_batched` every leaf has a leading
            [R] axis (e.g. a sweep over friction scales), else one set for all runs.
        specs: a `DeploySpec` whose leaves have a leading [R] axis (`stack_specs`).
        env, model_cfg, cfg: static; one compilation per distinct triple and shapes.
        devices: devices to shard the seed axis over (default: all of the default backend's,
            every process's when several cooperate; the seeds are then padded to a multiple
            of the global device count, and every process gets the whole result).
        chunk: episodes per device call (default: all `cfg.episodes` in one call). Every chunk
            runs the same compiled program, so chunking changes nothing but the progress
            reports; it must divide `cfg.episodes`.
        progress: called with the number of episodes finished after each chunk.
        return_carry: also return the final `Carry` (leaves [R, S, ...]: the adapters after
            the deployment, the buffer, the scheduler and lambda), as `(metrics, carry)`.

    Runs and seeds execute as one program; no Python loop over either. When no run trains
    adapters, the program leaves the LoRA steps out (same metrics, rollouts' cost only).
    """
    chunk = cfg.episodes if chunk is None else chunk
    if chunk < 1 or cfg.episodes % chunk:
        raise ValueError(f"chunk {chunk} must divide the {cfg.episodes} episodes")
    devices = jax.devices() if devices is None else list(devices)
    cfg = cfg.resolved(devices)
    n_seeds = keys.shape[0]
    pad = (-n_seeds) % len(devices)
    if params_batched and jax.tree.leaves(base_params)[0].shape[0] != n_seeds:
        raise ValueError(f"base params for {jax.tree.leaves(base_params)[0].shape[0]} seeds, "
                         f"keys for {n_seeds}")
    pad_seeds = lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)])
    if pad:  # repeat the last key (and model); the padded seeds are computed and dropped
        keys = pad_seeds(keys)
        if params_batched:
            base_params = jax.tree.map(pad_seeds, base_params)
    one_base = jax.tree.map(lambda x: x[0], base_params) if params_batched else base_params
    lora = init_adapters(keys, one_base, model_cfg)
    # A batch with no LoRA variant (zero-shot, fixed CTG, step changes) gets the program
    # without LoRA steps: the same bits at the cost of the rollouts alone. Read before the
    # specs are spread over the processes (a global array cannot be read whole).
    finetune = bool(np.any(np.asarray(jax.device_get(specs.variant.lora))))
    spread = distributed.spans_processes(devices)
    if len(devices) > 1:
        mesh = Mesh(np.asarray(devices), ("seeds",))
        seeded = NamedSharding(mesh, PartitionSpec("seeds"))
        replicated = NamedSharding(mesh, PartitionSpec())
        put = distributed.to_global if spread else jax.device_put
        keys, lora = put((keys, lora), seeded)
        base_params = put(base_params, seeded if params_batched else replicated)
        env_params, specs = put((env_params, specs), replicated)
    # Across processes each chunk's metrics are gathered whole into every process.
    whole = distributed.gather if spread else (lambda tree: tree)
    # (`params_batched` passed only when set: the cache keys of the other programs stay.)
    init_all, run_all = _compiled(env, model_cfg, cfg, env_params_batched, finetune,
                                  *((True,) if params_batched else ()))
    carry = init_all(keys, lora, specs)
    run_all = stored_episodes(
        run_all, (carry, jnp.arange(chunk, dtype=jnp.int32), base_params, env_params, specs),
        env=env, model_cfg=model_cfg, cfg=cfg, env_params_batched=env_params_batched,
        finetune=finetune, params_batched=params_batched)
    parts = []
    for start in range(0, cfg.episodes, chunk):
        index = jnp.arange(start, start + chunk, dtype=jnp.int32)
        carry, metrics = run_all(carry, index, base_params, env_params, specs)
        parts.append(jax.tree.map(lambda x: x[:, :n_seeds], whole(metrics)))
        if progress is not None:
            jax.block_until_ready(parts[-1])
            progress(chunk)
    metrics = jax.tree.map(lambda *xs: jnp.concatenate(xs, axis=2), *parts)
    if return_carry:
        return metrics, jax.tree.map(lambda x: x[:, :n_seeds], whole(carry))
    return metrics


def stack_specs(specs: list[DeploySpec]) -> DeploySpec:
    """Stack specs along a new leading run axis (runs may differ in variant and budget)."""
    if not specs:
        raise ValueError("stack_specs needs at least one DeploySpec")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *specs)
