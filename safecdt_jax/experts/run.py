"""Train several experts in one vmapped program, in jitted chunks of rounds, resumably.

    result = train_experts(cfg, [CostSchedule(10, 10), CostSchedule(25, 25)], seeds=[0],
                           out="runs/experts/CarGoal1")

Runs are the product schedules x seeds (schedule-major); run i trains from `PRNGKey(seed_i)`.
After every chunk the batched runner state goes to an orbax checkpoint (`out/ckpt/<round>`) and
the learning curves and snapshots so far to `out/history.npz` (atomically), so an interrupted
call with `resume=True` continues where it stopped, with the bits of an uninterrupted run.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from safecdt_jax.experts.config import CostSchedule, ExpertConfig
from safecdt_jax.experts.ppo_lag import make_train
from safecdt_jax.io import atomic_path

CURVES = ("return", "cost", "cost_limit", "lambda", "std")


@dataclass
class ExpertRun:
    """What `train_experts` returns: the config, each run's schedule and seed, the per-round
    curves {name: [runs, rounds]} (CURVES; raw episode totals) and the per-round snapshots
    (pytree, leaves [runs, rounds, ...])."""

    cfg: ExpertConfig
    schedules: list[CostSchedule]
    seeds: list[int]
    curves: dict[str, np.ndarray]
    snapshots: Any

    @property
    def labels(self) -> list[str]:
        """'limit 25, seed 0' per run."""
        return [f"limit {s.label()}, seed {k}" for s, k in zip(self.schedules, self.seeds,
                                                                strict=True)]


def _meta(cfg: ExpertConfig, schedules, seeds, warm_start=None) -> dict[str, Any]:
    meta = {"format": 1, "expert": cfg.to_json(),
            "schedules": [s.as_array().tolist() for s in schedules], "seeds": list(seeds)}
    if warm_start is not None:  # a resumed run must start from the same snapshot
        import hashlib

        digest = hashlib.blake2b(digest_size=16)
        for leaf in jax.tree.leaves(warm_start):
            digest.update(np.ascontiguousarray(leaf, np.float32).tobytes())
        meta["warm_start"] = digest.hexdigest()
    return meta


def _warm_started(runner: Any, snapshot: dict, runs: int) -> Any:
    """`runner` (batched over `runs`) with every run's actor and normaliser from `snapshot`."""
    want = jax.tree.structure({"actor": runner.params["actor"], "norm": runner.norm})
    if jax.tree.structure(snapshot) != want or any(
            np.shape(a) != np.shape(b)[1:] for a, b in zip(
                jax.tree.leaves(snapshot),
                jax.tree.leaves({"actor": runner.params["actor"], "norm": runner.norm}),
                strict=True)):
        raise ValueError("warm_start: the snapshot's actor or normaliser does not match this "
                         "task and config (hidden widths, observation size)")
    tile = lambda x: jnp.broadcast_to(jnp.asarray(x, jnp.float32), (runs, *np.shape(x)))
    snap = jax.tree.map(tile, snapshot)
    return runner._replace(params=runner.params | {"actor": snap["actor"]}, norm=snap["norm"])


def _save_history(path: Path, curves: dict, snapshots: Any) -> None:
    flat = {f"curve/{k}": v for k, v in curves.items()}
    leaves, _ = jax.tree.flatten(snapshots)
    flat |= {f"snapshot/{i}": np.asarray(x) for i, x in enumerate(leaves)}
    with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as f:
        np.savez(f, **flat)


def _load_history(path: Path, snapshot_def) -> tuple[dict, Any]:
    with np.load(path) as z:
        curves = {k: z[f"curve/{k}"] for k in CURVES}
        leaves = [z[f"snapshot/{i}"] for i in range(snapshot_def.num_leaves)]
    return curves, jax.tree.unflatten(snapshot_def, leaves)


def train_experts(cfg: ExpertConfig, schedules: Sequence[CostSchedule], seeds: Sequence[int],
                  out: str | os.PathLike | None = None, chunk_rounds: int = 4,
                  resume: bool = False,
                  progress: Callable[[int, dict], None] | None = None,
                  warm_start: dict | None = None) -> ExpertRun:
    """Trains one expert per (schedule, seed) pair, all in one vmapped program.

    `chunk_rounds` rounds run per jitted call; `progress(rounds_done, last_round)` is called
    after each chunk with the last round's curves ({name: [runs]}). With `out`, checkpoints
    after each chunk; `resume` continues from the latest one (its config, schedules and seeds
    must equal these, else ValueError). `warm_start` ({'actor', 'norm'}, one snapshot as
    `load_snapshots` gives it, indexed) starts every run's actor and observation normaliser from
    that snapshot; the critics, optimiser and PID start fresh (a competent driver tightened to a
    lower limit: issue 49's careful experts). Raises ValueError for an empty run list or a
    snapshot of another shape.
    """
    from safecdt_jax.pretrain.checkpoint import _manager, checkpoint_steps

    runs = [(s, int(k)) for s in schedules for k in seeds]
    if not runs:
        raise ValueError("train_experts: no runs (give at least one schedule and one seed)")
    scheds = [s for s, _ in runs]
    run_seeds = [k for _, k in runs]
    train = make_train(cfg)
    sched = jnp.asarray(np.stack([s.as_array() for s in scheds]))
    keys = jnp.stack([jax.random.PRNGKey(k) for k in run_seeds])
    init = jax.jit(jax.vmap(train.init))
    chunk_fn = jax.jit(jax.vmap(train.run_rounds, in_axes=(0, 0, None)), static_argnums=2)
    runner = init(keys)
    if warm_start is not None:
        runner = _warm_started(runner, warm_start, len(runs))
    meta = _meta(cfg, scheds, run_seeds, warm_start)
    out = None if out is None else Path(out).expanduser()
    curves: dict[str, np.ndarray] = {k: np.zeros((len(runs), 0), np.float32) for k in CURVES}
    snapshots = None
    done = 0
    ckpt_dir = None if out is None else (out / "ckpt").absolute()
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        steps = checkpoint_steps(ckpt_dir)
        if steps and not resume:
            raise ValueError(f"{out} already holds an expert run; pass resume=True (--resume) "
                             f"or choose another --out")
        if steps:
            import orbax.checkpoint as ocp

            with _manager(ckpt_dir, read_only=True) as mngr:
                saved = mngr.restore(steps[-1], args=ocp.args.Composite(
                    meta=ocp.args.JsonRestore()))["meta"]
                if saved != meta:
                    raise ValueError(f"{out}: the saved run has another config, schedules, "
                                     f"seeds or warm start than requested; cannot resume it")
                runner = mngr.restore(steps[-1], args=ocp.args.Composite(
                    state=ocp.args.StandardRestore(runner)))["state"]
            snap_def = jax.tree.structure(jax.eval_shape(
                lambda r: jax.vmap(train.run_rounds, in_axes=(0, 0, None))(r, sched, 1),
                runner)[1]["snapshot"])
            curves, snapshots = _load_history(out / "history.npz", snap_def)
            done = steps[-1]
    while done < cfg.rounds:
        n = min(chunk_rounds, cfg.rounds - done)
        runner, outputs = chunk_fn(runner, sched, n)
        outputs = jax.device_get(outputs)
        curves = {k: np.concatenate([curves[k], np.asarray(outputs[k])], axis=1)
                  for k in CURVES}
        snapshots = outputs["snapshot"] if snapshots is None else jax.tree.map(
            lambda a, b: np.concatenate([a, b], axis=1), snapshots, outputs["snapshot"])
        done += n
        if out is not None:
            import orbax.checkpoint as ocp

            _save_history(out / "history.npz", curves, snapshots)
            with _manager(ckpt_dir, max_to_keep=2) as mngr:
                mngr.save(done, args=ocp.args.Composite(state=ocp.args.StandardSave(runner),
                                                        meta=ocp.args.JsonSave(meta)))
                mngr.wait_until_finished()
        if progress is not None:
            progress(done, {k: v[:, -1] for k, v in curves.items()})
    result = ExpertRun(cfg, scheds, run_seeds, curves, snapshots)
    if out is not None:
        (out / "config.json").write_text(json.dumps(meta, indent=1))
    return result


__all__ = ["CURVES", "ExpertRun", "train_experts"]
