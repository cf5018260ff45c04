"""`safecdt-jax baselines`: the paper's offline safe-RL comparison (Tables 4 and 7)."""

from pathlib import Path
from typing import Annotated

import typer

from safecdt_jax.baselines.config import PRESET_NAMES
from safecdt_jax.cli.app import app, fail


@app.command()
def baselines(
    pair: Annotated[str, typer.Option(help="Deployment pair, e.g. CG1-CG2.")] = "CG1-CG2",
    algos: Annotated[str, typer.Option(
        help="Comma-separated baselines: bcql, bearl, cpq, bc_all, bc_safe.")]
        = "bcql,bearl,cpq,bc_all,bc_safe",
    seeds: Annotated[int, typer.Option(min=1, help="Seeds per baseline, vmapped.")] = 3,
    budget: Annotated[float, typer.Option(help="Cost budget B (cost units).")] = 30.0,
    preset: Annotated[str, typer.Option(
        help="Q-learning preset: " + ", ".join(PRESET_NAMES) + ".")] = "cpu",
    episodes: Annotated[int, typer.Option(min=1, help="Evaluation episodes per seed.")] = 20,
    steps: Annotated[int | None, typer.Option(
        min=1, help="Override the preset's gradient steps.")] = None,
    data: Annotated[Path | None, typer.Option(
        help="Source data set (default: the cached one, collected if missing).")] = None,
    full_episodes: Annotated[bool, typer.Option(
        help="Run every evaluation episode to the time limit instead of ending it at the "
             "first step over the budget (the paper's runtime budget).")] = False,
    overwrite: Annotated[bool, typer.Option(
        help="Retrain when --out holds checkpoints of another config.")] = False,
    out: Annotated[Path | None, typer.Option(
        help="Output folder (default runs/baselines/PAIR); a `run` folder adds Safe-CDT's "
             "row.")] = None,
) -> None:
    """Trains offline baselines on the pair's source data (all seeds of an algorithm in one
    compiled call) and evaluates them offline-only in the target task; writes baselines.json,
    baselines.md (the paper's Table 7 beside ours) and baselines_scatter.png."""
    from safecdt_jax.baselines.job import parse_algos, run_baselines

    try:
        names = parse_algos(algos)
        folder = out if out is not None else Path("runs") / "baselines" / pair
        run_baselines(pair, names, seeds, budget, preset, episodes, folder, data_path=data,
                      steps=steps, stop_over_budget=not full_episodes, overwrite=overwrite)
    except ValueError as e:
        fail(e)
    typer.echo((folder / "baselines.md").read_text())
