"""`safecdt-jax pretrain`: train a CDT preset on a DSRL-format data file, with checkpoints."""

from pathlib import Path
from typing import Annotated

import typer

from safecdt_jax.cli.app import app


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
    micro_batch: Annotated[int | None, typer.Option(
        min=0, help="Windows per forward/backward pass; the update sums the passes' gradients "
                    "(0 = the whole batch; default: 16 for the osrl and paper presets on a CPU, "
                    "where cache-sized passes run a batch of 2048 twice as fast, else 0).")
    ] = None,
    seed: Annotated[int, typer.Option(
        min=0, help="PRNG seed (init, relabelling, every batch).")] = 0,
    chunk: Annotated[int | None, typer.Option(
        min=1, help="Updates per jitted call (default: 100).")] = None,
    task: Annotated[str | None, typer.Option(
        help="Task name (default: the file's task attribute).")] = None,
    resume: Annotated[bool, typer.Option(
        help="Continue the checkpoint in --out up to --steps.")] = False,
    overwrite: Annotated[bool, typer.Option(
        help="Delete checkpoints already in --out first.")] = False,
    scale_actions: Annotated[bool | None, typer.Option(
        help="Train on actions divided by the data's largest |action| (folded into the saved "
             "weights, which emit raw actions either way; default: the preset's, cpu on).")
    ] = None,
    standardize_obs: Annotated[bool | None, typer.Option(
        help="Train on observations standardised by the data's mean and std (folded into "
             "the saved weights; default: the preset's, cpu on).")] = None,
    relabel_percent: Annotated[float | None, typer.Option(
        min=0.0, help="Pareto-relabelled copies per episode (default: the preset's; cpu 1.0, "
                      "OSRL 0.2).")] = None,
    cost_scale: Annotated[float | None, typer.Option(
        help="Cost-to-go tokens are raw CTG times this (default: the preset's; cpu 0.1, "
             "OSRL 1).")] = None,
    cost_offset: Annotated[float | None, typer.Option(
        help="The model reads cost_offset - scaled CTG (default: the preset's; cpu 5, "
             "OSRL 50).")] = None,
    token_bins: Annotated[int | None, typer.Option(
        min=0, help="Encode the RTG and CTG tokens as this many piecewise-linear ramps, edges "
                    "fitted to the data (default: the preset's; 0 = linear, as OSRL).")] = None,
    token_rates: Annotated[bool | None, typer.Option(
        help="Feed RTG and CTG per step left, in whole-episode units (T / (T - t) times "
             "each).")] = None,
    constant_targets: Annotated[bool | None, typer.Option(
        help="Tokens hold each episode's t=0 return and cost at every step, and rollouts "
             "keep their targets (not decremented); best with --labels policy (default: the "
             "preset's, cpu on).")] = None,
    stochastic_actions: Annotated[bool | None, typer.Option(
        help="Act with samples of the policy's Gaussian instead of its mean in evaluation "
             "and deployment (default: off).")] = None,
    labels: Annotated[str | None, typer.Option(
        help="What the tokens count from: episode (its realised return and cost) or policy "
             "(the mean of the episodes of its behaviour policy, episode_info/snapshot), or "
             "auto (policy where the data have snapshots; default: the preset's, cpu auto, "
             "OSRL episode).")
    ] = None,
) -> None:
    """Pretrains the CDT offline (OSRL's recipe) and saves orbax checkpoints with their configs.

    `--cost-scale` and `--cost-offset` set the cost-to-go token; evaluate and deploy read both
    back from the checkpoint. The token passes a LayerNorm that keeps only its direction once
    the scaled input outweighs the bias, so it should span about [-1, 1] over the cost-to-go
    range that matters (docs/CDT_FINDINGS.md, section 1): e.g. 0.025 and 1 for 0-80.
    `--token-bins` avoids that limit (ramps keep each value's own direction), `--token-rates`
    and `--labels policy` make the tokens name the policy rather than the layout's luck
    (section 12); `--constant-targets --labels policy` keeps that name all episode (section 14).
    """
    from safecdt_jax import pretrain as pt

    overrides = {"seed": seed}
    for name, value in (("steps", steps), ("batch_size", batch), ("chunk", chunk),
                        ("micro_batch", micro_batch),
                        ("scale_actions", scale_actions), ("standardize_obs", standardize_obs),
                        ("labels", labels), ("relabel_percent", relabel_percent)):
        if value is not None:
            overrides[name] = value
    model = {name: value for name, value in (
        ("cost_scale", cost_scale), ("cost_offset", cost_offset), ("token_bins", token_bins),
        ("token_rates", token_rates), ("constant_targets", constant_targets),
        ("stochastic_actions", stochastic_actions))
        if value is not None}
    try:
        cfg = pt.default_pretrain(preset, **overrides)
        result = pt.pretrain(data, out, preset=preset, config=cfg, task=task, resume=resume,
                             overwrite=overwrite, model_overrides=model)
    except ValueError as e:  # CheckpointError, DatasetError and bad settings: one clean line
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
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
    typer.echo(f"checkpoint: {result.path}")


@app.command()
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
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
    typer.echo(f"action log-likelihood {gaps['log_likelihood']:.4f} nats/dim on {windows} "
               f"training windows ({100 * gaps['share_ctg_positive']:.0f}% with CTG > 0)")
    typer.echo("| token shuffled | log-likelihood drop (nats/dim) |\n|---|---|")
    for name in TOKENS:
        typer.echo(f"| {name} | {gaps[name]:.5f} |")


@app.command()
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
    from safecdt_jax.analysis.bc import BCConfig, cloned_episodes, cost_band, evaluate_bc, fit_bc
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
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
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
