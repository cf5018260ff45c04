"""`safecdt-jax collect` and `safecdt-jax analyze data`: source data sets and their coverage."""

import time
from pathlib import Path
from typing import Annotated

import typer

from safecdt_jax.cli.app import analyze, app, fail


@app.command("collect")
def collect_cmd(
    task: Annotated[str, typer.Option(help="Task, e.g. CarGoal1: {Car,Point}{Goal,Circle}{1,2}.")],
    episodes: Annotated[int | None, typer.Option(
        help="Episodes kept (default: DSRL's count for the task).")] = None,
    out: Annotated[Path | None, typer.Option(
        help="Output HDF5 file (default: the cache's datasets/TASK.hdf5, TASK-executed.hdf5 "
             "with --record-actions executed).")] = None,
    seed: Annotated[int, typer.Option(help="PRNG seed (layouts, action noise, filter).")] = 0,
    snapshots: Annotated[Path | None, typer.Option(
        help="Expert snapshot file (default: the committed one of TASK).")] = None,
    actions: Annotated[str, typer.Option(
        "--record-actions",
        help="How expert actions are recorded: 'sampled' (the Gaussian sample clipped to "
             "[-1, 1], DSRL's convention, the default) or 'executed' (the Car's torques "
             "clipped to +-0.02; docs/EXPERTS.md).")] = "sampled",
) -> None:
    """Rolls out the task's PPO-Lagrangian expert snapshots and grid-filters the episodes to
    DSRL's size, into a DSRL-format HDF5 file."""
    from safecdt_jax import envs
    if task not in envs.NAMES:
        fail(f"unknown task {task!r}; valid names: {', '.join(envs.NAMES)}")
    if episodes is not None and episodes < 1:
        fail(f"--episodes must be at least 1, got {episodes}")

    import jax
    from tqdm import tqdm

    from safecdt_jax import paths
    from safecdt_jax.data.collect import check_writable, write_collected
    from safecdt_jax.experts.collect import (
        ACTION_RECORDINGS,
        expert_dataset,
        planned_episodes,
        snapshot_path,
        target_size,
    )

    try:
        if actions not in ACTION_RECORDINGS:
            raise ValueError(f"unknown --record-actions {actions!r}; choose one of "
                             f"{', '.join(ACTION_RECORDINGS)}")
        if snapshots is None:
            snapshot_path(task)
        path = check_writable(paths.dataset_path(task, actions) if out is None else out)
    except ValueError as e:
        fail(e)
    start = time.perf_counter()
    key = jax.random.PRNGKey(seed)
    total = planned_episodes(task, episodes) if snapshots is None else None
    with tqdm(total=total, desc=f"roll out {task} experts", unit="ep") as bar:
        data = expert_dataset(key, task, size=target_size(task, episodes),
                              snapshots=snapshots, progress=bar.update, seed=seed,
                              actions=actions)
    collected = time.perf_counter()
    try:
        write_collected(path, data)
    except OSError as e:
        fail(f"cannot write {path}: {e}")
    done = time.perf_counter()
    typer.echo(f"wrote {data.n_episodes} episodes ({int(data.lengths.sum()):,} transitions) of "
               f"{task} to {path} in {done - start:.1f} s (collect {collected - start:.1f} s "
               f"incl. compile, write {done - collected:.1f} s)")


@analyze.command("data")
def data_summary(
    path: Annotated[Path, typer.Argument(help="A DSRL-format HDF5 file (ours or DSRL's).")],
    png: Annotated[Path | None, typer.Option(
        help="Scatter plot file (default: PATH with suffix .png).")] = None,
) -> None:
    """Prints a data set's reward-cost coverage and checks; writes a reward-cost scatter PNG."""
    from safecdt_jax.data.collect import coverage_checks
    from safecdt_jax.data.dataset import DatasetError
    from safecdt_jax.data.dsrl import load_dataset
    from safecdt_jax.data.summary import summarize_dataset

    png = path.with_suffix(".png") if png is None else png
    try:
        data = load_dataset(path)
        s = summarize_dataset(data, png_path=png)
    except DatasetError as e:
        fail(e)
    except OSError as e:
        fail(f"cannot write {png}: {e}")
    attrs = data.attrs
    origin = ", ".join(f"{k} {attrs[k]}" for k in ("collector_version", "seed") if k in attrs)
    typer.echo(f"{attrs.get('task', path.name)}: {s['n_episodes']} episodes, "
               f"{s['n_transitions']:,} transitions" + (f" ({origin})" if origin else ""))
    typer.echo(f"  return min/median/max  {s['return_min']:8.2f} {s['return_median']:8.2f} "
               f"{s['return_max']:8.2f}")
    typer.echo(f"  cost   min/median/max  {s['cost_min']:8.0f} {s['cost_median']:8.1f} "
               f"{s['cost_max']:8.0f}")
    typer.echo(f"  episodes at cost <= 30: {s['frac_cost_le_30']:.1%}, above 30: "
               f"{s['frac_cost_gt_30']:.1%}")
    safe, risky = s["best_return_cost_le_10"], s["best_return_cost_30_100"]
    gain = (f" ({(risky - safe) / abs(safe):+.1%})" if safe and risky is not None else "")
    fmt = lambda x: "none" if x is None else f"{x:.2f}"
    typer.echo(f"  best return at cost <= 10: {fmt(safe)} ({s['n_cost_le_10']} episodes); at "
               f"cost 30-100: {fmt(risky)} ({s['n_cost_30_100']} episodes){gain}")
    if s["cost_share_by_snapshot"] is not None:
        typer.echo(f"  variance between expert snapshots: cost {s['cost_share_by_snapshot']:.2f}"
                   f", return {s['return_share_by_snapshot']:.2f} (the rest: layout and "
                   f"sampling)")
    if s["policy_cost_shares"] is not None:
        bands = ", ".join(f"{k} {v:.1%}" for k, v in s["policy_cost_shares"].items())
        typer.echo(f"  policy-mean cost {s['policy_cost_min']:.1f} to "
                   f"{s['policy_cost_max']:.1f}; episodes by their policy's mean cost: {bands}")
    labels = {"episodes": ">= 1000 episodes", "cost_span": "costs 0 to >= 100",
              "cost_split": ">= 20% at cost <= 30 and > 30",
              "frontier": "best return at cost 30-100 >= 1.1x best at cost <= 10"}
    for name, ok in coverage_checks(s).items():
        typer.echo(f"  {'PASS' if ok else 'FAIL'}  {labels[name]}")
    typer.echo(f"scatter plot: {png}")
