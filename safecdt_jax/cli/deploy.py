"""`safecdt-jax evaluate`, `deploy` and `run` (the main job: data -> pretraining -> deployment)."""

import time
from pathlib import Path
from typing import Annotated

import typer

from safecdt_jax.analysis.evaluate import DEFAULT_ACTION_MODE, parse_action_mode
from safecdt_jax.cli.app import Coordinator, NumProcesses, ProcessId, app, fail, join_processes
from safecdt_jax.deploy.config import VARIANT_SPECS, DeployConfig
from safecdt_jax.progress import Bar

# Defaults come from the configs, so the CLI cannot drift from them.
_DEFAULT = DeployConfig()
DEFAULT_BUDGET = f"{_DEFAULT.budget:g}"
Variants = Annotated[str, typer.Option(
    help="Comma-separated variants: " + ", ".join(VARIANT_SPECS) + ".")]
Budgets = Annotated[str, typer.Option(help="Comma-separated cost budgets B (cost units).")]
Seeds = Annotated[int, typer.Option(min=1, help="Seeds, all in one vmapped call.")]
Episodes = Annotated[int, typer.Option(min=1, help="Deployment episodes per seed.")]
Dynamics = Annotated[str | None, typer.Option(
    help="Shift the target's dynamics, e.g. friction_scale=0.5,gear_scale=0.8; a field with "
         "several values (friction_scale=1:0.75:0.5) is a run axis of the same compiled sweep "
         "(several such fields: a grid). Fields: friction_scale, gear_scale, damping_scale, "
         "mass_scale.")]


SetFields = Annotated[list[str] | None, typer.Option(
    "--set", metavar="FIELD=VALUE",
    help="Set any DeployConfig field (repeatable), e.g. --set horizon=200 (cut every episode "
         "there), --set stop_over_budget=false (full episodes), --set lora_labels=hindsight "
         "and --set replay_excess=realised (the paper's labels and replay weights), --set "
         "lora_in_turn=false; docs/CLI.md lists them.")]


def _deploy_config(episodes: int, settings: list[str] | None = None) -> DeployConfig:
    from safecdt_jax.validate import field_overrides

    return DeployConfig(**{"episodes": episodes, **field_overrides(settings or [], DeployConfig)})


def _check_runs(variant: str, budget: str, episodes: int, dynamics: str | None = None,
                settings: list[str] | None = None) -> None:
    """Parse and validate variants, budgets, shifts and the config before any long phase."""
    from safecdt_jax.deploy.config import make_variant
    from safecdt_jax.deploy.job import parse_list
    from safecdt_jax.envs.dynamics import parse_dynamics

    parse_dynamics(dynamics)
    cfg = _deploy_config(episodes, settings)
    for v in parse_list(variant, str, "variant"):
        make_variant(v, cfg)
    for b in parse_list(budget, float, "budget"):
        if not b > 0:
            raise ValueError(f"the cost budget must be positive, got {b:g}")


Act = Annotated[str, typer.Option(
    help="How the CDT acts: sample (a sample of the policy's Gaussian each step, as the "
         "experts behind its data acted), mean (the policy mean, OSRL's) or checkpoint (its "
         "own setting).")]


def _deploy_and_write(ckpt, target, variant, budget, seeds, episodes, seed, out, title,
                      dynamics=None, act=DEFAULT_ACTION_MODE, settings=None):
    from safecdt_jax.deploy.job import parse_list, run_deployment, write_results
    from safecdt_jax.envs.dynamics import parse_dynamics

    variants = parse_list(variant, str, "variant")
    budgets = parse_list(budget, float, "budget")
    cfg = _deploy_config(episodes, settings)
    results = run_deployment(ckpt, target, variants, budgets, seeds, seed=seed, cfg=cfg,
                             dynamics=parse_dynamics(dynamics),
                             stochastic_actions=parse_action_mode(act))
    written = write_results(out, results, title)
    if not written:  # one of several cooperating processes: process 0 writes
        import jax

        typer.echo(f"process {jax.process_index()}: done; process 0 writes {out}")
        return results
    typer.echo((Path(out) / "table.md").read_text())
    typer.echo("wrote " + ", ".join(str(p) for p in written))
    return results


@app.command()
def deploy(
    ckpt: Annotated[Path, typer.Option(help="Pretrained checkpoint folder.")],
    pair: Annotated[str, typer.Option(help="Source-target pair: CG1-CG2, CC1-CC2, PC1-PC2, "
                                           "PG1-PG2 (the checkpoint must fit its target).")],
    variant: Variants = "zero_shot,safe_cdt",
    budget: Budgets = DEFAULT_BUDGET,
    seeds: Seeds = 15,
    episodes: Episodes = _DEFAULT.episodes,
    seed: Annotated[int, typer.Option(min=0, help="Base PRNG seed.")] = 0,
    out: Annotated[Path | None, typer.Option(help="Output folder (default runs/PAIR).")] = None,
    dynamics: Dynamics = None,
    act: Act = DEFAULT_ACTION_MODE,
    settings: SetFields = None,
    coordinator: Coordinator = None,
    num_processes: NumProcesses = None,
    process_id: ProcessId = None,
) -> None:
    """Deploys a pretrained CDT in the pair's target task: every variant x budget x dynamics
    shift x seed at once (the seeds sharded over every device of N cooperating processes with
    --num-processes, docs/CLI.md)."""
    from safecdt_jax.pairs import parse_pair

    join_processes(coordinator, num_processes, process_id)
    try:
        _, target = parse_pair(pair)
        _check_runs(variant, budget, episodes, dynamics, settings)
        parse_action_mode(act)
        _deploy_and_write(ckpt, target, variant, budget, seeds, episodes, seed,
                          out or Path("runs") / pair, f"Safe-CDT deployment {pair}", dynamics,
                          act, settings)
    except ValueError as e:  # bad pair/variant/budget, CheckpointError: one clean line
        fail(e)


@app.command()
def run(
    pair: Annotated[str, typer.Option(help="CG1-CG2, CC1-CC2, PC1-PC2 or PG1-PG2.")] = "CG1-CG2",
    budget: Budgets = DEFAULT_BUDGET,
    seeds: Seeds = 15,
    episodes: Episodes = _DEFAULT.episodes,
    variant: Variants = "safe_cdt",
    preset: Annotated[str, typer.Option(help="CDT preset: tiny, cpu, osrl, paper.")] = "cpu",
    data_episodes: Annotated[int | None, typer.Option(
        min=1, help="Source data set size (default: DSRL's for the task).")] = None,
    steps: Annotated[int | None, typer.Option(
        min=1, help="Pretraining updates (default: the preset's).")] = None,
    seed: Annotated[int, typer.Option(min=0, help="Base PRNG seed.")] = 0,
    out: Annotated[Path | None, typer.Option(help="Output folder (default runs/PAIR).")] = None,
    dynamics: Dynamics = None,
    act: Act = DEFAULT_ACTION_MODE,
    settings: SetFields = None,
    coordinator: Coordinator = None,
    num_processes: NumProcesses = None,
    process_id: ProcessId = None,
) -> None:
    """The whole chain: reuse or collect the source data, reuse or pretrain, deploy, report.
    With N cooperating processes process 0 makes the data and checkpoint while the others
    wait, then all deploy together."""
    from safecdt_jax.distributed import process_zero_first
    from safecdt_jax.experts.collect import ensure_source_data, planned_episodes
    from safecdt_jax.pairs import parse_pair
    from safecdt_jax.pretrain.run import ensure_checkpoint

    join_processes(coordinator, num_processes, process_id)
    start = time.perf_counter()
    try:
        source, target = parse_pair(pair)
        _check_runs(variant, budget, episodes, dynamics, settings)
        parse_action_mode(act)
        typer.echo(f"[1/3] source data: {source}, expert behaviour")

        def collect():
            with Bar(planned_episodes(source, data_episodes), f"collect {source}") as bar:
                return ensure_source_data(source, data_episodes, seed, progress=bar.update)

        data = process_zero_first("run:data", collect)
        typer.echo(f"      {data}")
        typer.echo(f"[2/3] pretrained CDT: preset {preset}")
        # The cache is run's own: a checkpoint of older data (e.g. recollected after a
        # collector change) or of another config is retrained, not an error.
        ckpt = process_zero_first("run:checkpoint", lambda: ensure_checkpoint(
            data, source, preset, steps, seed=seed, overwrite=True))
        typer.echo(f"      {ckpt}")
        shifted = f", dynamics {dynamics}" if dynamics else ""
        typer.echo(f"[3/3] deployment: {target}{shifted}, {variant}, B={budget}, {seeds} seeds "
                   f"x {episodes} episodes")
        _deploy_and_write(ckpt, target, variant, budget, seeds, episodes, seed,
                          out or Path("runs") / pair, f"Safe-CDT {pair} ({preset} preset)",
                          dynamics, act, settings)
    except ValueError as e:
        fail(e)
    typer.echo(f"total {time.perf_counter() - start:.0f} s")


@app.command()
def evaluate(
    ckpt: Annotated[Path, typer.Option(help="Pretrained checkpoint folder.")],
    task: Annotated[str, typer.Option(help="Task to evaluate in, e.g. CarGoal1.")],
    targets: Annotated[str, typer.Option(
        help="Comma-separated RETURN:COST targets (raw units), e.g. 40:20,40:40.")],
    episodes: Annotated[int, typer.Option(min=1, help="Episodes per target.")] = 20,
    seed: Annotated[int, typer.Option(min=0, help="PRNG seed (layouts).")] = 0,
    horizon: Annotated[int | None, typer.Option(
        min=1, help="Cut every episode at this many steps (default: the task's).")] = None,
    data: Annotated[Path | None, typer.Option(
        help="Data set to compare with: prints its median episode cost.")] = None,
    out: Annotated[Path | None, typer.Option(
        help="Also write the summary and every episode's return and cost here (JSON).")] = None,
    dynamics: Annotated[str | None, typer.Option(
        help="Shift the task's dynamics, e.g. friction_scale=0.5,gear_scale=0.8 (one value per "
             "field here; `deploy` takes a list of values as a run axis).")] = None,
    act: Act = DEFAULT_ACTION_MODE,
) -> None:
    """Rolls out the CDT for each (return, cost) target; prints mean return, cost and VR, and
    how the mean cost follows the cost target (Spearman, per return target)."""
    import json

    try:
        from safecdt_jax.analysis.evaluate import (
            evaluate_checkpoint,
            evaluation_table,
            parse_targets,
        )
        from safecdt_jax.data import summarize_dataset
        from safecdt_jax.envs.dynamics import parse_dynamics
        from safecdt_jax.io import write_text_atomic

        pairs = parse_targets(targets)
        shifts = parse_dynamics(dynamics)
        if len(shifts) > 1:
            raise ValueError("evaluate takes one value per dynamics field; deploy --dynamics "
                             "sweeps a list of values")
        median = None if data is None else summarize_dataset(data)["cost_median"]
        summary = evaluate_checkpoint(ckpt, task, pairs, episodes, seed, horizon, median,
                                      shifts[0], parse_action_mode(act))
    except (ValueError, OSError) as e:  # bad targets, task, checkpoint or data file: one line
        fail(e)
    if summary["support_note"]:
        typer.echo(summary["support_note"], err=True)
    typer.echo(evaluation_table(summary))
    if out is not None:
        try:
            write_text_atomic(out, json.dumps(summary, indent=1))
        except OSError as e:
            fail(e)
        typer.echo(f"wrote {out}")
