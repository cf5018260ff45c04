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
) -> None:
    """Trains one expert per (cost limit, seed), all in one compiled program; writes learning
    curves (PNG, JSON), resumable orbax checkpoints and the snapshot history."""
    from tqdm import tqdm

    from safecdt_jax import paths
    from safecdt_jax.experts.config import CostSchedule, expert_preset
    from safecdt_jax.experts.export import (
        plot_curves,
        write_curves,
        write_snapshots,
        write_tensorboard,
    )
    from safecdt_jax.experts.run import train_experts

    try:
        schedules = [CostSchedule.parse(t) for t in cost_limit.split(",")]
        given = {"num_envs": num_envs, "minibatches": minibatches}
        cfg = expert_preset(preset, task=task, steps=steps,
                            **{k: v for k, v in given.items() if v is not None})
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
                                   resume=resume, progress=progress)
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
        write_snapshots(snapshots, result, keep)
        typer.echo(f"snapshots: {snapshots}")
