"""`safecdt-jax expert`: train PPO-Lagrangian behaviour experts, one vmapped call per task."""

import time
from pathlib import Path
from typing import Annotated

import typer

from safecdt_jax.cli.app import app, fail


@app.command("expert")
def expert_cmd(
    task: Annotated[str, typer.Option(help="Task, e.g. CarGoal1: {Car,Point}{Goal,Circle}{1,2}.")],
    steps: Annotated[int, typer.Option(min=1, help="Env steps per expert.")] = 5_000_000,
    seeds: Annotated[int, typer.Option(min=1, help="Seeds per cost limit (0, 1, ...).")] = 1,
    cost_limit: Annotated[str, typer.Option(
        help="Comma-separated episode-cost limits, one expert each: a number, 'none', or an "
             "anneal 'A:B' / 'A:B:begin:finish' (fractions of training).")] = "25",
    num_envs: Annotated[int | None, typer.Option(
        min=1, help="Parallel envs per expert (default: the preset's).")] = None,
    minibatches: Annotated[int | None, typer.Option(
        min=1, help="PPO minibatches per epoch (default: the preset's).")] = None,
    preset: Annotated[str, typer.Option(help="Expert preset: tiny or cpu.")] = "cpu",
    chunk: Annotated[int, typer.Option(min=1, help="Rounds (episodes) per jitted call.")] = 2,
    out: Annotated[Path | None, typer.Option(
        help="Run folder (default: $SAFECDT_CACHE/experts/TASK).")] = None,
    resume: Annotated[bool, typer.Option(help="Continue the run saved in --out.")] = False,
    snapshots: Annotated[Path | None, typer.Option(
        help="Also write the snapshots the collector rolls out to this .npz file.")] = None,
    keep: Annotated[int, typer.Option(
        min=1, help="Snapshots per expert in --snapshots, evenly spaced over training.")] = 8,
    append: Annotated[bool, typer.Option(
        help="Add the snapshots to those already in --snapshots instead of replacing the "
             "file (experts of the same architecture; docs/EXPERTS.md).")] = False,
    warm_start: Annotated[str | None, typer.Option(
        help="FILE.npz:INDEX: start every expert's actor and normaliser from snapshot INDEX "
             "of a snapshot file (0-based, expert-major: with --keep K, expert i's k-th "
             "snapshot is i*K+k); the critics and the Lagrange multiplier start fresh.")] = None,
    settings: Annotated[list[str] | None, typer.Option(
        "--set", metavar="FIELD=VALUE",
        help="Set any ExpertConfig field (repeatable), e.g. --set pid_ki=0.05, --set "
             "min_std=0.2; docs/EXPERTS.md lists them.")] = None,
) -> None:
    """Trains one expert per (cost limit, seed), all in one compiled program; writes learning
    curves (PNG, JSON), resumable orbax checkpoints and the snapshot history."""
    from tqdm import tqdm

    from safecdt_jax import paths
    from safecdt_jax.experts.config import CostSchedule, ExpertConfig, expert_preset
    from safecdt_jax.experts.export import (
        merge_snapshots,
        plot_curves,
        write_curves,
        write_snapshots,
        write_tensorboard,
    )
    from safecdt_jax.experts.run import train_experts
    from safecdt_jax.validate import field_overrides

    try:
        schedules = [CostSchedule.parse(t) for t in cost_limit.split(",")]
        given = {"num_envs": num_envs, "minibatches": minibatches}
        overrides = field_overrides(settings or [], ExpertConfig)
        own = sorted({"task", "steps", "num_envs", "minibatches"} & set(overrides))
        if own:
            raise ValueError(f"--set {own[0]}: use the --{own[0].replace('_', '-')} option")
        cfg = expert_preset(preset, **(overrides | dict(task=task, steps=steps) | {
            k: v for k, v in given.items() if v is not None}))
        start_from = None if warm_start is None else _snapshot_at(warm_start, cfg)
    except ValueError as e:
        fail(e)
    out = paths.cache_root() / "experts" / task if out is None else out
    start = time.perf_counter()
    runs = len(schedules) * seeds
    env_steps = runs * cfg.num_envs * cfg.horizon

    with tqdm(total=cfg.rounds, desc=f"expert {task} x{runs}", unit="round") as bar:
        def progress(done, last):
            bar.n = done
            rate = env_steps * (done - bar.initial) / max(time.perf_counter() - start, 1e-9)
            bar.set_postfix_str(
                f"return {last['return'].mean():.1f} cost {last['cost'].mean():.1f} "
                f"lambda {last['lambda'].mean():.2f} {rate:,.0f} steps/s")
            bar.refresh()

        try:
            result = train_experts(cfg, schedules, range(seeds), out=out, chunk_rounds=chunk,
                                   resume=resume, progress=progress, warm_start=start_from)
        except ValueError as e:
            fail(e)
    write_curves(out / "curves.json", result)
    plot_curves(out / "curves.png", result)
    write_tensorboard(out / "tensorboard", result)
    typer.echo(f"trained {runs} experts x {cfg.rounds * cfg.num_envs * cfg.horizon:,} env steps "
               f"in {time.perf_counter() - start:.0f} s; curves {out / 'curves.png'}")
    for label, r, c in zip(result.labels, result.curves["return"], result.curves["cost"],
                           strict=True):
        tail = max(1, r.size // 10)
        typer.echo(f"  {label}: last tenth return {r[-tail:].mean():.2f}, cost "
                   f"{c[-tail:].mean():.1f}")
    if snapshots is not None:
        if append and snapshots.exists():
            fresh = out / "snapshots-new.npz"
            if fresh.resolve() == snapshots.resolve():
                fail(f"--append: --snapshots {snapshots} is this run's own scratch file")
            write_snapshots(fresh, result, keep)
            try:
                merge_snapshots(snapshots, snapshots, fresh)
            except ValueError as e:
                fail(f"{e}; the new snapshots are in {fresh}")
        else:
            write_snapshots(snapshots, result, keep)
        typer.echo(f"snapshots: {snapshots}")


def _snapshot_at(spec: str, cfg) -> dict:
    """Snapshot INDEX of FILE from 'FILE:INDEX', checked against `cfg`'s task (ValueError)."""
    import jax

    from safecdt_jax.experts.export import load_snapshots

    path, _, index = spec.rpartition(":")
    if not path or not index.isdigit():
        raise ValueError(f"--warm-start {spec!r}: expected FILE.npz:INDEX")
    snaps, meta = load_snapshots(path)
    if meta["task"] != cfg.task:
        raise ValueError(f"--warm-start {path}: snapshots of {meta['task']}, not {cfg.task}")
    n = len(meta["snapshots"])
    if int(index) >= n:
        raise ValueError(f"--warm-start {spec!r}: the file holds {n} snapshots (0-{n - 1})")
    return jax.tree.map(lambda x: x[int(index)], snaps)
