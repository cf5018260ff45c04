"""Train baselines on a source data set (all seeds of one algorithm in one vmapped program,
resumable orbax checkpoints) and evaluate them in a task through the shared episode protocol
(`envs.rollout.policy_episode`, the runtime budget included).

    data = load_source(path, "CarGoal1")
    trained = train_baseline(preset("bcql", "cpu"), data, seeds=[0, 1, 2], ckpt="runs/b/bcql")
    returns, costs = evaluate_trained(trained, "CarGoal2", episodes=20, stop_cost=30.0)
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from safecdt_jax.baselines.common import transitions
from safecdt_jax.baselines.config import BaselineConfig
from safecdt_jax.baselines.train import make_algorithm, make_chunk
from safecdt_jax.data.dataset import Dataset, DatasetError
from safecdt_jax.pretrain.normalize import IONorm

BC_ALGOS = ("bc_all", "bc_safe")
CKPT_FORMAT = 1


@dataclasses.dataclass
class Trained:
    """A trained baseline, all seeds: `params` (pytree, leaves [seeds, ...]), the `norm` from
    raw observations/actions to the networks' units, `act(params, obs, key) -> action` (raw
    units, one seed's params), per-chunk training metrics {name: [seeds, chunks]}, the
    training wall time in seconds and whether it was loaded from a checkpoint."""

    algo: str
    config: dict
    seeds: list[int]
    params: Any
    norm: IONorm
    act: Callable
    history: dict[str, np.ndarray]
    seconds: float
    reused: bool


def load_source(path: str | os.PathLike, task: str) -> Dataset:
    """The data set at `path`, checked to be `task`'s (by its `task` attribute and the task's
    observation size): a DatasetError names the mismatch."""
    from safecdt_jax import envs
    from safecdt_jax.data.dsrl import load_dataset

    env, _ = envs.make(task)
    data = load_dataset(path, obs_dim=env.observation_size)
    found = data.attrs.get("task")
    if found is not None and found != task:
        raise DatasetError(f"{path}: a {found} data set, but the baselines train on {task}")
    return data


def _fingerprint(data: Dataset) -> str:
    from safecdt_jax.pretrain.run import dataset_record

    return dataset_record("", data)["fingerprint"]


def _act_fn(algo, norm: IONorm) -> Callable:
    mean, std, scale = (jnp.asarray(x) for x in norm)

    def act(params, obs, key):
        return algo.act(params, (obs - mean) / std, key) * scale

    return act


def _same_run(saved: dict, meta: dict, done: int, n_chunks: int) -> dict[str, bool]:
    """Which parts of a saved run's metadata match the requested run: every entry equal,
    except that the saved run may have fewer updates (it is then resumed and extended)."""
    same = {k: saved.get(k) == v for k, v in meta.items()}
    config = dict(saved.get("config", {}), steps=meta["config"]["steps"])
    same["config"] = config == meta["config"] and done <= n_chunks
    return same


def train_baseline(cfg: BaselineConfig, data: Dataset, seeds: Sequence[int],
                   ckpt: str | os.PathLike | None = None, overwrite: bool = False,
                   progress: bool = True, data_id: str | None = None) -> Trained:
    """Trains `cfg.algo` on `data` for every seed in one vmapped program, in jitted chunks of
    `cfg.chunk` steps (the bits of one uninterrupted scan, `train.make_train`).

    With `ckpt`, the state is saved after every chunk; a finished run there with the same
    config, data and seeds is loaded instead of retrained, an unfinished or shorter one resumed
    (and extended to `cfg.steps`). A checkpoint of another config, data or seeds (or of more
    updates) raises ValueError unless `overwrite`. `data_id`: the data's fingerprint
    (`pretrain.run.dataset_record`), when the caller has it; computed otherwise.
    """
    from safecdt_jax.pretrain.checkpoint import _manager, checkpoint_steps

    seeds = [int(s) for s in seeds]
    data_t, norm = transitions(data, cfg.obs_std_floor)
    obs_dim, act_dim = data.obs_dim, data.act_dim
    algo = make_algorithm(cfg, obs_dim, act_dim, data.horizon)
    chunk = jax.jit(jax.vmap(make_chunk(cfg, algo), in_axes=(0, 0, None)))
    keys = jnp.stack([jax.random.split(jax.random.PRNGKey(s)) for s in seeds])
    state = jax.jit(jax.vmap(algo.init))(keys[:, 0])
    n_chunks = -(-cfg.steps // cfg.chunk)
    meta = {"format": CKPT_FORMAT, "config": cfg.record(), "seeds": seeds,
            "data": data_id or _fingerprint(data), "norm": norm.to_json()}
    history: dict[str, list] = {}
    done, reused, seconds = 0, False, 0.0
    path = None if ckpt is None else Path(ckpt).expanduser().absolute()
    steps = [] if path is None else checkpoint_steps(path)
    if steps:
        import orbax.checkpoint as ocp

        with _manager(path, read_only=True) as mngr:
            saved = mngr.restore(steps[-1], args=ocp.args.Composite(
                meta=ocp.args.JsonRestore()))["meta"]
            same = _same_run(saved, meta, steps[-1], n_chunks)
            if not all(same.values()) and not overwrite:
                differs = ", ".join(k for k, ok in same.items() if not ok)
                raise ValueError(f"{path} holds a {cfg.algo} run with another {differs}; "
                                 f"pass overwrite=True (--overwrite) or another --out")
            if all(same.values()):
                state = mngr.restore(steps[-1], args=ocp.args.Composite(
                    state=ocp.args.StandardRestore(state)))["state"]
                done, seconds = steps[-1], float(saved["seconds"])
                history = {k: [np.asarray(v, np.float32)] for k, v in saved["history"].items()}
                reused = done >= n_chunks
        if overwrite and not all(same.values()):
            import shutil

            shutil.rmtree(path)
    bar = None
    if progress and done < n_chunks:
        from tqdm import tqdm

        bar = tqdm(total=n_chunks * cfg.chunk, initial=done * cfg.chunk,
                   desc=f"{cfg.algo} x{len(seeds)}", unit="step")
    while done < n_chunks:
        start = time.perf_counter()
        state, metrics = chunk(state, keys[:, 1], data_t)
        metrics = {k: np.asarray(v).mean(axis=1, keepdims=True)
                   for k, v in jax.device_get(metrics).items()}
        seconds += time.perf_counter() - start
        for k, v in metrics.items():
            history.setdefault(k, []).append(v)
        done += 1
        if path is not None:
            import orbax.checkpoint as ocp

            record = meta | {"seconds": seconds, "history": {
                k: np.concatenate(v, axis=1).tolist() for k, v in history.items()}}
            with _manager(path, max_to_keep=1) as mngr:
                mngr.save(done, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                        meta=ocp.args.JsonSave(record)))
                mngr.wait_until_finished()
        if bar is not None:
            bar.update(cfg.chunk)
            bar.set_postfix({k: f"{float(np.mean(v[:, -1])):.3g}" for k, v in metrics.items()
                             if k in ("critic_loss", "cost_critic_loss", "lambda", "qc")})
    if bar is not None:
        bar.close()
    return Trained(cfg.algo, cfg.record(), seeds, state.params, norm,
                   _act_fn(algo, norm),
                   {k: np.concatenate(v, axis=1) for k, v in history.items()}, seconds, reused)


def train_bc(kind: str, data: Dataset, seeds: Sequence[int], budget: float,
             steps: int | None = None, progress: bool = True) -> Trained:
    """BC-All (every episode) or BC-Safe (the episodes of cost <= `budget`), OSRL's behaviour
    cloning baselines: `baselines.bc.fit_bc_seeds`, every seed in one vmapped program."""
    from safecdt_jax.baselines.bc import BCConfig, bc_action, fit_bc_seeds

    if kind not in BC_ALGOS:
        raise ValueError(f"unknown behaviour-cloning baseline {kind!r}; choose from "
                         f"{', '.join(BC_ALGOS)}")
    cfg = BCConfig(max_cost=budget if kind == "bc_safe" else None,
                   **({} if steps is None else {"steps": steps}))
    start = time.perf_counter()
    keys = jnp.stack([jax.random.PRNGKey(int(s)) for s in seeds])
    params, loss = fit_bc_seeds(keys, data, cfg)
    if progress:
        print(f"{kind} seeds {', '.join(str(s) for s in seeds)}: final loss "
              + ", ".join(f"{v:.4f}" for v in loss[:, -1]), flush=True)
    record = dataclasses.asdict(cfg) | {"algo": kind}
    norm = IONorm(*(np.asarray(x[0]) for x in (params.obs_mean, params.obs_std,
                                               params.action_scale)))
    return Trained(kind, record, [int(s) for s in seeds], params, norm,
                   lambda p, obs, key: bc_action(p, obs), {"loss": loss},
                   time.perf_counter() - start, False)


def evaluate_trained(trained: Trained, task: str, episodes: int, seed: int = 0,
                     stop_cost: float | None = None, dynamics: dict[str, float] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(returns, costs) [seeds, episodes] of every seed's policy in `task` (dynamics shifted by
    `dynamics`), `episodes` full episodes each (ended early by the runtime budget `stop_cost`),
    the layouts of seed s's episodes from `fold_in(PRNGKey(seed), s)`. One jitted program."""
    from safecdt_jax import envs
    from safecdt_jax.envs.dynamics import apply_dynamics
    from safecdt_jax.envs.rollout import policy_episode

    env, params = envs.make(task)
    params = apply_dynamics(params, dynamics or {})
    if trained.norm.obs_mean.shape[0] != env.observation_size:
        raise ValueError(f"the {trained.algo} policy reads {trained.norm.obs_mean.shape[0]} "
                         f"observation dims, {task} gives {env.observation_size}")

    def episode(policy_params, key):
        out = policy_episode(
            env, params, key, lambda ps, obs, t, k: (trained.act(policy_params, obs, k), ps),
            lambda ps, r, c: ps, (), stop_cost=stop_cost)
        return out["return"], out["cost"]

    base = jax.random.PRNGKey(seed)
    keys = jnp.stack([jax.random.split(jax.random.fold_in(base, s), episodes)
                      for s in trained.seeds])
    run = jax.jit(jax.vmap(jax.vmap(episode, in_axes=(None, 0))))
    returns, costs = jax.device_get(run(trained.params, keys))
    return np.asarray(returns), np.asarray(costs)


__all__ = ["BC_ALGOS", "Trained", "evaluate_trained", "load_source", "train_baseline",
           "train_bc"]
