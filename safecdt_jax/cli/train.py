"""`safecdt-jax pretrain`: train a CDT preset on a DSRL-format data file, with checkpoints."""

from pathlib import Path
from typing import Annotated

import typer

from safecdt_jax.cli.app import (
    Coordinator,
    NumProcesses,
    ProcessId,
    analyze,
    app,
    fail,
    join_processes,
)


@app.command()
def pretrain(
    data: Annotated[Path, typer.Option(exists=True, dir_okay=False,
                                       help="DSRL-format HDF5 file.")],
    preset: Annotated[str, typer.Option(help="Model preset: tiny, cpu, osrl or paper.")] = "cpu",
    steps: Annotated[int | None, typer.Option(
        min=1, help="Total updates (default: the preset's).")] = None,
    out: Annotated[Path | None, typer.Option(
        help="Checkpoint folder (default: $SAFECDT_CACHE/checkpoints/TASK-PRESET).")] = None,
    batch: Annotated[int | None, typer.Option(
        min=1, help="Windows per update (default: the preset's).")] = None,
    seed: Annotated[int, typer.Option(
        min=0, help="PRNG seed (init, relabelling, every batch).")] = 0,
    task: Annotated[str | None, typer.Option(
        help="Task name (default: the file's task attribute).")] = None,
    resume: Annotated[bool, typer.Option(
        help="Continue the checkpoint in --out up to --steps.")] = False,
    overwrite: Annotated[bool, typer.Option(
        help="Delete checkpoints already in --out first.")] = False,
    settings: Annotated[list[str] | None, typer.Option(
        "--set", metavar="FIELD=VALUE",
        help="Set any PretrainConfig or CDTConfig field (repeatable), e.g. --set "
             "micro_batch=16, --set token_bins=0, --set labels=episode; docs/CLI.md lists "
             "them.")] = None,
    data_parallel: Annotated[bool, typer.Option(
        help="Split every batch over all devices of all cooperating processes (gradients "
             "reduced by the compiler; equal to one device up to float summation order). "
             "Default: one device.")] = False,
    coordinator: Coordinator = None,
    num_processes: NumProcesses = None,
    process_id: ProcessId = None,
) -> None:
    """Pretrains the CDT offline (OSRL's recipe) and saves orbax checkpoints with their configs.

    The preset fixes every setting; `--set` changes any field of the run's `PretrainConfig`
    (labels, relabelling, normalisation, micro-batches, token spans) or of the model's
    `CDTConfig` (size, token encoding, dropout); the checkpoint records them all, and evaluate
    and deploy read the token encoding back from it (docs/METHOD.md section 0).
    `--data-parallel` trains over every device, also of N processes started with
    `--num-processes` (process 0 writes the checkpoints; docs/CLI.md).
    """
    import dataclasses

    if (num_processes or 1) > 1 and not data_parallel:
        fail("--num-processes > 1 trains one model together: add --data-parallel")
    join_processes(coordinator, num_processes, process_id)
    import jax

    from safecdt_jax import pretrain as pt
    from safecdt_jax.model.config import CDTConfig
    from safecdt_jax.validate import field_overrides

    try:
        fields = field_overrides(settings or [], pt.PretrainConfig, CDTConfig)
        run_fields = {f.name for f in dataclasses.fields(pt.PretrainConfig)}
        overrides = {k: v for k, v in fields.items() if k in run_fields}
        model = {k: v for k, v in fields.items() if k not in run_fields}
        given = {"seed": seed, "steps": steps, "batch_size": batch}
        overrides.update({k: v for k, v in given.items() if v is not None})
        cfg = pt.default_pretrain(preset, **overrides)
        result = pt.pretrain(data, out, preset=preset, config=cfg, task=task, resume=resume,
                             overwrite=overwrite, model_overrides=model,
                             devices=jax.devices() if data_parallel else None)
    except ValueError as e:  # CheckpointError, DatasetError and bad settings: one clean line
        fail(e)
    if not jax.process_index() == 0:
        return  # process 0 reports for all
    meta, hist = result.meta, result.history
    loss, ll = hist.metrics["loss"], hist.metrics["log_likelihood"]
    # One chunk's mean swings by +-1 nat on heavy-tailed data: end on the mean of the last 10.
    tail = min(10, len(loss))
    end_loss, end_ll = sum(loss[-tail:]) / tail, sum(ll[-tail:]) / tail
    typer.echo(
        f"{meta['task']} / {preset}: {meta['n_params']:,} params, {meta['step']} updates of "
        f"{cfg.batch_size} x {meta['model']['seq_len']} steps in {hist.wall_s:.0f} s; loss "
        f"{loss[0]:.3f} -> {end_loss:.3f}, action log-likelihood {ll[0]:.2f} -> {end_ll:.2f} "
        f"nats/dim (first chunk -> mean of the last {tail}); "
        f"R_ref {meta['dataset']['reference_return']:.2f}"
    )
    if data_parallel:
        typer.echo(f"data-parallel over {jax.device_count()} devices of "
                   f"{jax.process_count()} process(es)")
    typer.echo(f"checkpoint: {result.path}")


@analyze.command()
def diagnose(
    ckpt: Annotated[Path, typer.Option(exists=True, file_okay=False,
                                       help="Checkpoint folder.")],
    data: Annotated[Path, typer.Option(exists=True, dir_okay=False,
                                       help="The DSRL-format HDF5 file it was trained on.")],
    windows: Annotated[int, typer.Option(min=2, help="Training windows scored.")] = 4096,
    seed: Annotated[int, typer.Option(min=0, help="PRNG seed of the draw and shuffle.")] = 0,
) -> None:
    """Shuffle test: how much the action log-likelihood drops when the return-to-go, cost-to-go
    or timestep tokens are permuted across training windows (nats per action dim)."""
    from safecdt_jax.analysis.diagnose import TOKENS, conditioning_gaps

    try:
        gaps = conditioning_gaps(ckpt, data, windows, seed)
    except ValueError as e:
        fail(e)
    typer.echo(f"action log-likelihood {gaps['log_likelihood']:.4f} nats/dim on {windows} "
               f"training windows ({100 * gaps['share_ctg_positive']:.0f}% with CTG > 0)")
    typer.echo("| token shuffled | log-likelihood drop (nats/dim) |\n|---|---|")
    for name in TOKENS:
        typer.echo(f"| {name} | {gaps[name]:.5f} |")


@analyze.command()
def bc(
    data: Annotated[Path, typer.Option(exists=True, dir_okay=False,
                                       help="DSRL-format HDF5 file.")],
    task: Annotated[str | None, typer.Option(
        help="Task to roll the clone out in (default: the file's task attribute).")] = None,
    max_cost: Annotated[float | None, typer.Option(
        min=0, help="Clone only episodes of cost <= this (BC-Safe); default: all (BC-All).")
    ] = None,
    min_cost: Annotated[float | None, typer.Option(
        min=0, help="Clone only episodes of cost >= this (with --max-cost: one cost band).")
    ] = None,
    steps: Annotated[int, typer.Option(min=1, help="Adam updates of 256 transitions.")] = 20_000,
    episodes: Annotated[int, typer.Option(min=1, help="Evaluation episodes.")] = 20,
    seed: Annotated[int, typer.Option(min=0, help="PRNG seed (init, batches, layouts).")] = 0,
) -> None:
    """Behaviour cloning baseline: fit a per-step MLP to the data's actions and roll it out,
    to tell whether the data can be imitated at all (mean return and cost per episode)."""
    import jax
    import numpy as np

    from safecdt_jax import envs
    from safecdt_jax.baselines.bc import BCConfig, cloned_episodes, cost_band, evaluate_bc, fit_bc
    from safecdt_jax.data.dsrl import load_dataset
    from safecdt_jax.data.windows import episode_costs, episode_returns

    try:
        cfg = BCConfig(steps=steps, max_cost=max_cost, min_cost=min_cost,
                       chunk=min(1_000, steps))
        ds = load_dataset(data)
        task_flag = task is not None
        task = task or ds.attrs.get("task")
        if task is None:
            raise ValueError(f"{data} has no task attribute: pass --task")
        if task not in envs.NAMES:  # before minutes of fitting, not after
            raise ValueError(f"unknown task {task!r} (from {'--task' if task_flag else data}); "
                             f"valid names: {', '.join(envs.NAMES)}")
        # Before fitting: no qualifying episode is an error.
        keep = cloned_episodes(ds, max_cost, min_cost)
        key = jax.random.PRNGKey(seed)
        policy, loss = fit_bc(key, ds, cfg)
        returns, costs = evaluate_bc(jax.random.fold_in(key, 1), task, policy, episodes)
    except ValueError as e:  # DatasetError, an unknown task, no qualifying episode: one line
        fail(e)
    band = cost_band(max_cost, min_cost)
    label = ("BC-All" if band == "any" else
             f"BC-Safe (cost {band})" if min_cost is None else f"BC (cost {band})")
    n = int(np.asarray(ds.lengths)[keep].sum())
    typer.echo(f"{label}: {keep.sum()} episodes, {n:,} transitions; data mean return "
               f"{episode_returns(ds)[keep].mean():.2f}, cost {episode_costs(ds)[keep].mean():.2f}")
    typer.echo(f"fit: RMSE {np.sqrt(loss[0]):.3f} -> {np.sqrt(loss[-1]):.3f} of each action's "
               f"range (first -> last {cfg.chunk} updates)")
    typer.echo(f"{task}, {episodes} episodes: return {returns.mean():.2f}, cost "
               f"{costs.mean():.2f} (max {costs.max():g}, {np.mean(costs == 0):.0%} at 0)")
