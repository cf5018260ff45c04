"""This project's side of the peer benchmark: the same work as `worker.py`, timed the same way.

Each `make_*` function builds and compiles (one warm-up call) and returns a callable that runs
one timed unit of work and answers a dict shaped like the worker's (`{"seconds": ..., ...}`), so
`run_all` can alternate the two sides without timing compilation. Models are the `osrl` preset
(OSRL's CDT size) with random weights: the cost of a step does not depend on the weights.
"""

import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.deploy_throughput import setup as deploy_setup
from benchmarks.train_throughput import SIZES, synthetic_data
from safecdt_jax import envs
from safecdt_jax.deploy import cdt_episode, seed_keys, stack_specs, sweep
from safecdt_jax.envs.rollout import run_episode
from safecdt_jax.model import (
    CDTConfig,
    OptimConfig,
    init_cdt,
    init_train_state,
    last_action,
)
from safecdt_jax.model.cdt import newest_action
from safecdt_jax.pretrain import PretrainConfig, make_train_chunk, run_key

PRESET = "osrl"


def _timed(fn: Callable, *args) -> float:
    t = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - t


def model_config(task: str) -> CDTConfig:
    """The `osrl` preset for a task family's sizes (`CarGoal`, `CarCircle`, ...)."""
    family = task.rstrip("0123456789")
    return CDTConfig.preset(PRESET, *SIZES[family])


def make_env_steps(task: str, batch: int) -> Callable[[], dict]:
    """`batch` random-policy episodes of `task` in one vmapped call, reset included."""
    env, params = envs.make(task)
    fn = jax.jit(jax.vmap(lambda k: run_episode(env, params, k)))
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    _timed(fn, keys)
    return lambda: {"seconds": _timed(fn, keys), "env_steps": batch * env.episode_length}


def make_train(task: str, batch: int, steps: int, micro_batch: int = 0) -> Callable[[], dict]:
    """`steps` CDT updates in one `train_chunk` call (window sampling on the device included),
    each update's gradient in passes of at most `micro_batch` windows (0: one pass)."""
    cfg = model_config(task)
    data = synthetic_data(cfg.obs_dim, cfg.act_dim, cfg.episode_len)
    weights = jnp.full(data.lengths.shape, 1.0 / data.lengths.shape[0])
    fn = make_train_chunk(cfg, OptimConfig(), PretrainConfig(batch_size=batch, chunk=steps,
                                                                   micro_batch=micro_batch))
    state = init_train_state(jax.random.key(0), cfg)
    args = (state, run_key(0), data, weights, jnp.int32(2**30))
    _timed(fn, *args)
    return lambda: {"seconds": _timed(fn, *args), "steps": steps}


def _window(cfg: CDTConfig, batch: int) -> dict:
    k = cfg.seq_len
    return {"states": jnp.ones((batch, k, cfg.obs_dim)),
            "actions": jnp.zeros((batch, k, cfg.act_dim)),
            "returns_to_go": jnp.full((batch, k), 2.0), "costs_to_go": jnp.full((batch, k), 30.0),
            "timesteps": jnp.broadcast_to(jnp.arange(k) + 100, (batch, k)),
            "mask": jnp.ones((batch, k))}


def make_infer(task: str, batch: int, calls: int, trimmed: bool) -> Callable[[], dict]:
    """`calls` back-to-back jitted action calls on a full window, each waiting for the last.

    `trimmed`: `newest_action` (what our rollouts call: the last block computes one query);
    otherwise `last_action` (the whole forward, the same work as OSRL's call).
    """
    cfg = model_config(task)
    params = init_cdt(jax.random.PRNGKey(0), cfg)
    window = _window(cfg, batch)
    action = newest_action if trimmed else last_action
    fn = jax.jit(lambda p, w: action(p, cfg, w))
    jax.block_until_ready(fn(params, window))

    def run() -> dict:
        t = time.perf_counter()
        for _ in range(calls):
            np.asarray(fn(params, window))  # to host, as a rollout feeding a Python env would
        return {"seconds": time.perf_counter() - t, "calls": calls}

    return run


def make_zero_shot(task: str, seeds: int, episodes: int, target_return: float,
                   target_cost: float) -> Callable[[], dict]:
    """Every (seed, episode) of the zero-shot CDT deployment in one vmapped, jitted call.

    With no adaptation the episodes are independent, so all `seeds * episodes` run side by side.
    """
    env, params = envs.make(task)
    cfg = model_config(task)
    base = init_cdt(jax.random.PRNGKey(0), cfg)

    def one(key):
        ep = cdt_episode(key, env, params, base, cfg, target_return, target_cost)
        return ep["return"], ep["cost"]

    fn = jax.jit(jax.vmap(one))
    keys = jax.random.split(jax.random.PRNGKey(0), seeds * episodes)
    _timed(fn, keys)

    def run() -> dict:
        t = time.perf_counter()
        returns, costs = jax.block_until_ready(fn(keys))
        return {"seconds": time.perf_counter() - t, "episodes": seeds * episodes,
                "env_steps": seeds * episodes * env.episode_length,
                "mean_return": float(returns.mean()), "mean_cost": float(costs.mean())}

    return run


def make_safe_cdt(task: str, seeds: int, episodes: int) -> Callable[[], dict]:
    """The full Safe-CDT loop (LoRA after every episode, scheduler, reweighting), one sweep call.

    Seeds are vmapped; episodes run in sequence inside the program (each adapts to the last).
    """
    env, params, model_cfg, base, cfg, spec = deploy_setup(task, PRESET, episodes)
    keys, specs = seed_keys(0, seeds), stack_specs([spec])

    def call():
        return sweep(keys, base, params, specs, env=env, model_cfg=model_cfg, cfg=cfg)

    _timed(call)

    def run() -> dict:
        t = time.perf_counter()
        metrics = jax.block_until_ready(call())
        return {"seconds": time.perf_counter() - t, "episodes": seeds * episodes,
                "env_steps": seeds * episodes * env.episode_length,
                "mean_return": float(metrics.returns.mean()),
                "mean_cost": float(metrics.costs.mean())}

    return run


def make_gemm(n: int, calls: int) -> Callable[[], dict]:
    """`calls` jitted float32 n x n matrix products (this CPU's matmul rate in XLA)."""
    x = jnp.asarray(np.random.default_rng(0).normal(size=(n, n)), jnp.float32)
    fn = jax.jit(lambda a: a @ a)
    _timed(fn, x)

    def run() -> dict:
        t = time.perf_counter()
        for _ in range(calls):
            fn(x).block_until_ready()
        return {"seconds": time.perf_counter() - t, "flops": 2.0 * n**3 * calls}

    return run


def compiled_flops(task: str, batch: int, trimmed: bool) -> float:
    """FLOPs XLA reports for one jitted action call (`cost_analysis`; all ops, not only matmuls)."""
    cfg = model_config(task)
    params = init_cdt(jax.random.PRNGKey(0), cfg)
    action = newest_action if trimmed else last_action
    lowered = jax.jit(lambda p, w: action(p, cfg, w)).lower(params, _window(cfg, batch))
    analysis = lowered.compile().cost_analysis()
    analysis = analysis[0] if isinstance(analysis, list) else analysis
    return float(analysis["flops"])
