"""The Python API: the workflow of `safecdt-jax run` as five functions, raw units in and out.

    from safecdt_jax import api as sc

    data = sc.collect("CarGoal1")                      # DSRL-format HDF5 from the expert snapshots
    ckpt = sc.pretrain(data)                           # a checkpoint folder (`cpu` preset)
    result = sc.deploy(ckpt, "CarGoal2", variants=["safe_cdt", "zero_shot"], budgets=[30])
    result.run("safe_cdt").cost                        # [seeds, episodes] episode costs
    sc.evaluate(ckpt, "CarGoal1", [(40, 10), (40, 20)]).spearman

Returns and costs are summed per episode in the task's own units (reward and cost per step);
targets are per-episode totals in the same units. Data and checkpoints land in the cache
(`$SAFECDT_CACHE`, default `~/.cache/safecdt-jax`) unless `out` says otherwise, and are reused
when current, as the command line reuses them. `load_policy` returns params that read raw
observations and emit raw actions, whatever normalisation pretraining used.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from safecdt_jax.pretrain.checkpoint import Checkpoint, load_policy


def collect(task: str, *, episodes: int | None = None, seed: int = 0,
            out: str | os.PathLike | None = None, progress: bool = False) -> Path:
    """Roll out the task's committed PPO-Lagrangian expert snapshots into a DSRL-format HDF5
    data set, grid-filtered to DSRL's size (`episodes` overrides the count), and return its path
    (default: the cache's `datasets/TASK.hdf5`; a current file there is reused, not redone)."""
    from safecdt_jax.experts.collect import ensure_source_data, planned_episodes
    from safecdt_jax.progress import Bar

    with Bar(planned_episodes(task, episodes), f"collect {task}", enabled=progress) as bar:
        return ensure_source_data(task, episodes, seed, path=out, progress=bar.update)


def pretrain(data: str | os.PathLike, *, preset: str = "cpu", steps: int | None = None,
             seed: int = 0, out: str | os.PathLike | None = None, overwrite: bool = False,
             progress: bool = False) -> Path:
    """Pretrain a CDT of model preset `preset` (tiny, cpu, osrl, paper) on data file `data` for
    `steps` updates (default: the preset's) and return the checkpoint folder (default: the
    cache's `checkpoints/TASK-PRESET`). A finished checkpoint of the same data and configs is
    reused, a shorter one resumed; one of another run raises CheckpointError unless
    `overwrite`. The task is the file's `task` attribute, else its name."""
    from safecdt_jax.pretrain.run import ensure_checkpoint

    return ensure_checkpoint(data, None, preset, steps, seed=seed, out=out,
                             overwrite=overwrite, progress=progress)


@dataclasses.dataclass(frozen=True)
class DeployedRun:
    """One (variant, budget, dynamics shift) run of a deployment: `metrics[name]` is a
    [seeds, episodes] array for each name of `results.METRIC_NAMES` (return and cost per
    episode; violation 1.0 where the cost exceeded the budget; the targets the episode ran
    under; the replay lambda; the scheduler's ratios; the mean LoRA loss), `summary` the
    across-seed means and population stds of the per-seed means (reward, cost, VR in %)."""

    variant: str
    budget: float
    dynamics: Mapping[str, float]
    metrics: Mapping[str, np.ndarray]
    summary: Mapping[str, float]

    @property
    def reward(self) -> np.ndarray:
        """Episode returns [seeds, episodes]."""
        return self.metrics["return"]

    @property
    def cost(self) -> np.ndarray:
        """Episode costs [seeds, episodes]."""
        return self.metrics["cost"]

    @property
    def violation(self) -> np.ndarray:
        """1.0 where an episode's cost exceeded the budget, else 0.0 [seeds, episodes]."""
        return self.metrics["violation"]


@dataclasses.dataclass(frozen=True)
class Deployment:
    """A deployment sweep's result: its `runs` and the JSON-ready `record` (`results.json`:
    configs, versions, timing and the same metrics as lists)."""

    runs: tuple[DeployedRun, ...]
    record: Mapping[str, Any]

    def run(self, variant: str, budget: float | None = None) -> DeployedRun:
        """The run of `variant` (at `budget`, needed when several budgets ran; nominal dynamics
        first). KeyError names the runs there are."""
        for r in self.runs:
            if r.variant == variant and (budget is None or r.budget == budget):
                return r
        have = ", ".join(f"{r.variant} B={r.budget:g}" for r in self.runs)
        raise KeyError(f"no run {variant!r}" + ("" if budget is None else f" at B={budget:g}")
                       + f"; runs: {have}")

    def write(self, out: str | os.PathLike, title: str = "Safe-CDT deployment") -> list[Path]:
        """Write results.json, table.md and the figures into folder `out` (atomically)."""
        from safecdt_jax.deploy.job import write_results

        return write_results(out, dict(self.record), title)


def deploy(ckpt: str | os.PathLike, target: str, *, variants: Sequence[str] = ("safe_cdt",),
           budgets: Sequence[float] = (30.0,), seeds: int = 15, seed: int = 0,
           episodes: int | None = None, config=None,
           dynamics: Sequence[Mapping[str, float]] = ({},), sample_actions: bool | None = True,
           progress: bool = False) -> Deployment:
    """Deploy checkpoint `ckpt` into task `target` for every variant x budget x dynamics shift
    and `seeds` seeds, in one compiled sweep.

    `variants`: names of `deploy.VARIANT_SPECS` (e.g. safe_cdt, zero_shot, naive_lora,
    fixed_ctg(0.5)); `budgets`: cost budgets B per episode; `config`: a `DeployConfig` (default
    its defaults) and `episodes` its deployment length; `dynamics`: shifts of the target's
    dynamics ({field: scale}, `{}` nominal); `sample_actions`: act with samples of the policy
    (True, the default: `analysis.evaluate.DEFAULT_ACTION_MODE`) or its mean (False), None as
    the checkpoint says.
    """
    from safecdt_jax.deploy.config import DeployConfig
    from safecdt_jax.deploy.job import run_deployment

    cfg = config if config is not None else DeployConfig()
    if episodes is not None:
        cfg = dataclasses.replace(cfg, episodes=episodes)
    record = run_deployment(ckpt, target, list(variants), list(budgets), seeds, seed=seed,
                            cfg=cfg, progress=progress, dynamics=dynamics,
                            stochastic_actions=sample_actions)
    runs = tuple(DeployedRun(r["variant"], r["budget"], dict(r["dynamics"]),
                             {k: np.asarray(v) for k, v in r["metrics"].items()},
                             dict(r["summary"])) for r in record["runs"])
    return Deployment(runs, record)


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """Rollouts of a policy at fixed (return, cost) targets: `returns` and `costs` are
    [targets, episodes] (every target on the same layouts), `target_return` / `target_cost`
    [targets]; `summary` is the JSON-ready table (`analysis.evaluate.summarize_evaluation`)."""

    target_return: np.ndarray
    target_cost: np.ndarray
    returns: np.ndarray
    costs: np.ndarray
    summary: Mapping[str, Any]

    @property
    def spearman(self) -> float | None:
        """Rank correlation of mean episode cost with the cost target at the first return target
        run at two or more cost targets (None: no such target, or all mean costs tie)."""
        following = self.summary["cost_following"]
        return following[0]["spearman"] if following else None


def evaluate(ckpt: str | os.PathLike, task: str, targets: Sequence[tuple[float, float]], *,
             episodes: int = 20, seed: int = 0, horizon: int | None = None,
             dynamics: Mapping[str, float] | None = None,
             sample_actions: bool | None = True) -> Evaluation:
    """Roll out checkpoint `ckpt` in `task` for `episodes` episodes at each (return, cost)
    target, without any adaptation, in one compiled call; prints nothing. `sample_actions` as
    in `deploy`."""
    from safecdt_jax.analysis.evaluate import evaluate_policy, summarize_evaluation

    res = evaluate_policy(ckpt, task, [(float(r), float(c)) for r, c in targets], episodes, seed,
                          horizon, dict(dynamics or {}), sample_actions)
    return Evaluation(res["target_return"], res["target_cost"], res["returns"], res["costs"],
                      summarize_evaluation(task, res))


__all__ = [
    "Checkpoint",
    "DeployedRun",
    "Deployment",
    "Evaluation",
    "collect",
    "deploy",
    "evaluate",
    "load_policy",
    "pretrain",
]
