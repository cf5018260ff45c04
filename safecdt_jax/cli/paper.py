"""`safecdt-jax paper`: every experiment of the paper's evaluation, and the report."""

from pathlib import Path
from typing import Annotated

import typer

from safecdt_jax.analysis.evaluate import DEFAULT_ACTION_MODE
from safecdt_jax.cli.app import (
    Coordinator,
    NumProcesses,
    ProcessId,
    app,
    enable_persistent_cache,
    fail,
    join_processes,
)


@app.command()
def paper(
    pairs: Annotated[str, typer.Option(help="Comma-separated pairs.")]
        = "CG1-CG2,CC1-CC2,PC1-PC2",
    quick: Annotated[bool, typer.Option(
        help="Few seeds and episodes (2 seeds x 10 episodes, 20 for the intervention), cached "
             "baselines only: a first look in minutes.")] = False,
    out: Annotated[Path | None, typer.Option(
        help="Report folder (default report/, or runs/paper-quick with --quick).")] = None,
    preset: Annotated[str, typer.Option(help="CDT preset pretrained per source task.")] = "cpu",
    baselines: Annotated[bool, typer.Option(
        help="Train the baselines that are not cached (default on, off with --quick).")]
        = True,
    seed: Annotated[int, typer.Option(min=0, help="Base PRNG seed.")] = 0,
    pretrain_seeds: Annotated[int | None, typer.Option(
        min=1, help="Pretrained checkpoints per pair behind Tables 1-3 (default 3; 1 with "
                    "--quick): each row runs as checkpoints x deployment seeds.")] = None,
    lora_labels: Annotated[str, typer.Option(
        help="What the LoRA finetuning windows' tokens read: auto (target when the CDT acts "
             "with samples, else stage), stage (the mean outcome of the episodes run under the "
             "same targets), target or hindsight (the paper's).")]
        = "auto",
    replay_excess: Annotated[str, typer.Option(
        help="What the replay weights' excess reads: projected (a cut episode's cost "
             "extended over the horizon at its own rate) or realised (the paper's).")]
        = "projected",
    act: Annotated[str, typer.Option(
        help="How the CDT acts in every deployment: sample (samples of its policy), mean or "
             "checkpoint (as it was saved: the mean in every preset).")]
        = DEFAULT_ACTION_MODE,
    coordinator: Coordinator = None,
    num_processes: NumProcesses = None,
    process_id: ProcessId = None,
) -> None:
    """Tables 1-7, Figure 2 and the safety certificate, ours beside the paper's, in
    OUT/REPORT.md; finished experiments (OUT/experiments/*.json) are reused, so an
    interrupted run continues where it stopped."""
    from safecdt_jax.deploy.job import parse_list
    from safecdt_jax.paper import PaperPlan, quick_plan, run_paper

    join_processes(coordinator, num_processes, process_id)
    try:
        pair_list = tuple(parse_list(pairs, str, "pair"))
        study = "CG1-CG2" if "CG1-CG2" in pair_list else pair_list[0]
        settings = dict(pairs=pair_list, study_pair=study, preset=preset, seed=seed,
                        lora_labels=lora_labels, replay_excess=replay_excess, act=act)
        if pretrain_seeds is not None:
            settings["pretrain_seeds"] = pretrain_seeds
        plan = (quick_plan(**settings) if quick else
                PaperPlan(**settings, train_baselines=baselines))
    except ValueError as e:
        fail(e)
    enable_persistent_cache()
    folder = out or (Path("runs") / "paper-quick" if quick else Path("report"))
    summary = run_paper(plan, folder, log=typer.echo)
    from safecdt_jax.distributed import is_writer

    if not is_writer():  # one of several cooperating processes: process 0 wrote the report
        return
    typer.echo(f"wrote {folder / 'REPORT.md'} ({summary['seconds'] / 60:.1f} min)")

