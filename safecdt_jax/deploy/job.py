"""The deployment job behind `safecdt-jax deploy` and `run`: load, sweep, write results.

A job deploys one checkpoint into one target task for every (variant, budget) run and every
seed, in one compiled sweep, then writes `results.json` (every per-episode metric per seed, the
configs and versions), `table.md` (the paper's Table 1 rows) and PNG figures, each atomically.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

RESULTS_FORMAT = 1


def parse_list(text: str, kind: Callable[[str], Any], what: str) -> list:
    """Split a comma-separated option into values of `kind` (ValueError names the bad item).

    Commas inside parentheses belong to the item, so `step_change(0.2,0.8)` stays whole.
    """
    items, depth, current = [], 0, ""
    for ch in text:
        depth += (ch == "(") - (ch == ")")
        if ch == "," and depth == 0:
            items.append(current)
            current = ""
        else:
            current += ch
    items.append(current)
    out = []
    for item in (i.strip() for i in items):
        if not item:
            raise ValueError(f"empty item in {what} list {text!r}")
        try:
            out.append(kind(item))
        except ValueError as e:
            raise ValueError(f"bad {what} {item!r}: {e}") from e
    return out


def load_deployment(ckpt: str | os.PathLike, target: str, cfg=None,
                    stochastic_actions: bool | None = None):
    """What deploying checkpoint `ckpt` into task `target` needs: `(env, env_params, policy,
    cfg, r_ref)`. `cfg` defaults to `DeployConfig()`; the token encoding comes with the policy's
    model config, as it was trained, and so does how it acts unless `stochastic_actions` (True:
    samples of the policy, False: its mean) overrides it, and so does the adapters' rank where
    `cfg.lora_rank` is set; `cfg`'s "auto" LoRA labels become the rule for how it acts.
    `r_ref` is the checkpoint's reference return (raw units). Raises
    CheckpointError if the model does not fit the task."""
    from safecdt_jax import envs
    from safecdt_jax.deploy.config import DeployConfig
    from safecdt_jax.pretrain.checkpoint import load_policy, with_action_mode

    env, env_params = envs.make(target)
    policy = with_action_mode(load_policy(ckpt, task=target), stochastic_actions)
    cfg = (DeployConfig() if cfg is None else cfg).resolved()
    cfg = cfg.for_acting(policy.cfg.stochastic_actions)
    if cfg.lora_rank:  # the adapters are made at deployment: any rank fits the base model
        policy = policy._replace(cfg=policy.cfg.replace(lora_rank=cfg.lora_rank))
    return env, env_params, policy, cfg, float(policy.meta["dataset"]["reference_return"])


def _stacked_policies(ckpts: Sequence[str | os.PathLike], target: str, cfg, first,
                      stochastic_actions: bool | None, r_ref: float):
    """The base params of every checkpoint stacked on a leading axis; ValueError when one
    differs from the first (`first`, its policy) in model config or reference return (they
    must be pretraining seeds of one run on one data set)."""
    params = [first.params]
    data = first.meta["dataset"]["fingerprint"]
    for path in ckpts[1:]:
        _, _, policy, _, ref = load_deployment(path, target, cfg, stochastic_actions)
        if (policy.cfg != first.cfg or ref != r_ref
                or policy.meta["dataset"]["fingerprint"] != data):
            raise ValueError(f"{os.fspath(path)}: another model config or data than "
                             f"{os.fspath(ckpts[0])}; checkpoints deployed together must be "
                             f"pretraining seeds of one run")
        params.append(policy.params)
    return jax.tree.map(lambda *xs: np.stack(xs), *params)


def run_deployment(
    ckpt: str | os.PathLike | Sequence[str | os.PathLike],
    target: str,
    variants: Sequence[str],
    budgets: Sequence[float],
    seeds: int,
    *,
    seed: int = 0,
    cfg=None,
    progress: bool = True,
    dynamics: Sequence[dict[str, float]] = ({},),
    runs: Sequence[tuple[str, float]] | None = None,
    stochastic_actions: bool | None = None,
) -> dict[str, Any]:
    """Deploy checkpoint `ckpt` into task `target` for every (variant, budget, shift) and seed.

    `ckpt` may list several checkpoints (pretraining seeds of one run: same model config and
    data): each is deployed with the same `seeds` deployment seeds, all in the same sweep
    (a base model per seed row), and the per-episode metrics hold checkpoint-major rows
    [checkpoints * seeds]; each run's summary adds the spreads between checkpoints and across
    deployment seeds (`summarize_runs`).

    `runs`, when given, lists the (variant, budget) pairs to run instead of every variant x
    budget (e.g. one variant at five budgets beside four variants at one), each at every shift.

    `cfg` (default `DeployConfig()`) sets the deployment; the token encoding comes with the
    checkpoint. `dynamics` lists the target's dynamics shifts ({field: scale}, from
    `envs.dynamics.parse_dynamics`; `{}` is the nominal target): each is a run axis of the same
    compiled sweep, next to variants and budgets. `stochastic_actions` (None: the checkpoint's
    own `CDTConfig.stochastic_actions`) makes the CDT act with samples of its policy or its mean.

    One sweep call (runs x seeds); the episodes advance in stage-sized chunks of the same
    compiled program so a progress bar can follow. Returns the results record (plain Python,
    JSON-ready): `runs`, one per (variant, budget, shift), each with its shift, its env params,
    per-episode metrics [seeds][episodes] and the across-seed summary; plus configs, versions
    and timings.
    """
    from safecdt_jax import envs
    from safecdt_jax.deploy.config import make_variant
    from safecdt_jax.deploy.loop import make_spec, seed_keys
    from safecdt_jax.deploy.sweep import stack_specs, sweep
    from safecdt_jax.envs.dynamics import apply_dynamics, params_record, stack_params
    from safecdt_jax.pretrain.support import checkpoint_support, requested_targets, support_note
    from safecdt_jax.progress import Bar
    from safecdt_jax.results.tables import summarize_runs
    from safecdt_jax.versions import versions

    if seeds < 1:
        raise ValueError(f"seeds must be >= 1, got {seeds}")
    progress = progress and jax.process_index() == 0  # one bar among cooperating processes
    ckpts = [ckpt] if isinstance(ckpt, str | os.PathLike) else list(ckpt)
    if not ckpts:
        raise ValueError("run_deployment: no checkpoint")
    env, env_params, policy, cfg, r_ref = load_deployment(ckpts[0], target, cfg,
                                                          stochastic_actions)
    base, several = policy.params, len(ckpts) > 1
    if several:
        base = _stacked_policies(ckpts, target, cfg, policy, stochastic_actions, r_ref)
        base = jax.tree.map(lambda x: np.repeat(x, seeds, axis=0), base)
    dynamics = list(dynamics) or [{}]
    pairs = list(itertools.product(variants, budgets)) if runs is None else list(runs)
    combos = [(v, b, shift) for v, b in pairs for shift in dynamics]
    parsed = [(make_variant(v, cfg), b) for v, b, _ in combos]
    specs = stack_specs([make_spec(v, b, r_ref) for v, b in parsed])
    note = support_note(checkpoint_support(policy.meta), *requested_targets(parsed, cfg, r_ref))
    if note and progress:
        print(note, file=sys.stderr)
    per_run = [apply_dynamics(env_params, shift) for _, _, shift in combos]
    # One target for all runs is broadcast (as before shifts existed); several are a run axis.
    batched = len(dynamics) > 1
    swept_params = stack_params(per_run) if batched else per_run[0]
    keys = seed_keys(seed, seeds)
    if several:  # every checkpoint meets the same deployment seeds (paired comparisons)
        keys = jax.numpy.concatenate([keys] * len(ckpts))
    chunk = cfg.stage_len if cfg.episodes % cfg.stage_len == 0 else cfg.episodes
    label = f"deploy {len(combos)} run(s) x {len(ckpts) * seeds} seeds"
    start = time.perf_counter()
    with Bar(cfg.episodes, label, enabled=progress) as bar:
        metrics = sweep(keys, base, swept_params, specs, env=env, model_cfg=policy.cfg,
                        cfg=cfg, chunk=chunk, progress=bar.update, env_params_batched=batched,
                        params_batched=several)
        metrics = jax.device_get(metrics)
    wall = time.perf_counter() - start
    runs = []
    for r, (variant, budget, shift) in enumerate(combos):
        per = {name: np.asarray(value[r]) for name, value in metrics._asdict().items()}
        named = {"return": per["returns"], "cost": per["costs"], "violation": per["violation"],
                 "ctg_target": per["ctg_target"], "rtg_target": per["rtg_target"],
                 "lambda": per["lam"], "a_c": per["a_c"], "a_r": per["a_r"],
                 "lora_loss": per["lora_loss"]}
        runs.append({
            "variant": variant,
            "budget": float(budget),
            "dynamics": dict(shift),
            "env_params": params_record(per_run[r]),
            "summary": summarize_runs(named, len(ckpts)),
            "metrics": {k: v.astype(float).tolist() for k, v in named.items()},
        })
    steps = len(combos) * len(ckpts) * seeds * cfg.episodes * (cfg.horizon or env.episode_length)
    several_record = {"checkpoints": [str(Path(c).absolute()) for c in ckpts]} if several else {}
    return {
        "format": RESULTS_FORMAT,
        "checkpoint": str(Path(ckpts[0]).absolute()),
        **several_record,
        "source": policy.meta.get("task"),
        "target": target,
        "target_env": envs.env_version(target),
        "seeds": len(ckpts) * seeds,
        "deploy_seeds": seeds,
        "seed": seed,
        "reference_return": r_ref,
        "deploy_config": dataclasses.asdict(cfg),
        "model_config": policy.meta["model"],
        "stochastic_actions": policy.cfg.stochastic_actions,  # as acted (may override the ckpt)
        "support_note": note,
        "versions": versions(),
        "timing": {"deploy_s": wall, "env_steps": steps, "env_steps_per_s": steps / wall},
        "runs": runs,
    }


def run_label(run: dict[str, Any], budgets: int, shifts: int = 1) -> str:
    """A run's row label: the variant, plus the budget when several budgets were run and the
    dynamics shift when several shifts were."""
    from safecdt_jax.envs.dynamics import shift_label

    label = run["variant"] + (f" B={run['budget']:g}" if budgets > 1 else "")
    return label + (f" [{shift_label(run.get('dynamics', {}))}]" if shifts > 1 else "")


def shift_axes(runs: Sequence[dict[str, Any]]) -> dict[str, list[float]]:
    """The dynamics fields whose value differs between runs, with their sorted values."""
    fields = {k for run in runs for k in run.get("dynamics", {})}
    axes = {f: sorted({run["dynamics"][f] for run in runs if f in run.get("dynamics", {})})
            for f in sorted(fields)}
    return {f: v for f, v in axes.items() if len(v) > 1}


def write_results(out_dir: str | os.PathLike, results: dict[str, Any], title: str) -> list[Path]:
    """Write `results.json`, `table.md` and the figures into `out_dir` (each atomically), and
    each run's per-episode curves as TensorBoard events in `out_dir/tensorboard`. Among
    cooperating processes (`safecdt_jax.distributed`) only process 0 writes; the others write
    nothing and return []."""
    from safecdt_jax.distributed import is_writer

    if not is_writer():
        return []
    from safecdt_jax.envs.dynamics import shift_label
    from safecdt_jax.io import write_text_atomic
    from safecdt_jax.results.figures import plot_deployment, plot_robustness
    from safecdt_jax.results.tables import results_table
    from safecdt_jax.tensorboard import deployment_curves

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = [write_text_atomic(out / "results.json", json.dumps(results, indent=1))]
    budgets = sorted({run["budget"] for run in results["runs"]})
    shifts = sorted({shift_label(run.get("dynamics", {})) for run in results["runs"]})
    rows = [dict(run["summary"], label=run_label(run, len(budgets), len(shifts)))
            for run in results["runs"]]
    timing = results["timing"]
    protocol = (" (each ended at the first step over the budget, the paper's runtime budget)"
                if results["deploy_config"].get("stop_over_budget") else " (full episodes)")
    header = (f"# {title}\n\n{results['source']} -> {results['target']}, "
              f"{results['seeds']} seeds x {results['deploy_config']['episodes']} episodes"
              f"{protocol}; reward, cost and VR as mean ± std over seeds (population std); "
              f"deployment {timing['deploy_s']:.0f} s "
              f"({timing['env_steps_per_s']:,.0f} env steps/s).\n\n")
    written.append(write_text_atomic(out / "table.md", header + results_table(rows)))
    deployment_curves(out / "tensorboard", {run_label(r, len(budgets), len(shifts)): r["metrics"]
                                             for r in results["runs"]})
    for budget in budgets:
        runs = {run_label(r, 1, len(shifts)): r["metrics"] for r in results["runs"]
                if r["budget"] == budget}
        folder = out if len(budgets) == 1 else out / f"budget_{budget:g}"
        figures = plot_deployment(runs, budget, folder, f"{title}, B={budget:g}",
                                  results["deploy_config"]["stage_len"])
        written += [Path(p) for p in figures]
    for field, values in shift_axes(results["runs"]).items():
        if len(values) >= 3:  # a robustness curve needs a few points
            written.append(Path(plot_robustness(results["runs"], field,
                                                out / f"robustness_{field}.png", title)))
    return written

