"""The one Typer app every `safecdt-jax` subcommand registers on, its `analyze` group, and the
one way a command reports bad input."""

import os
from typing import Annotated, NoReturn

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")

import typer

app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode="markdown",
                  help="Safe-CDT in JAX: environments, offline data, CDT, safe deployment.")
analyze = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode="markdown",
                      help="Analyses of data sets, checkpoints, results and environments.")
app.add_typer(analyze, name="analyze")

# The exit status of every error a command reports itself (bad input, a missing or unfit file);
# typer's own usage errors (an unknown option, a value out of range) keep click's status 2.
ERROR_EXIT = 1


def fail(error: Exception | str) -> NoReturn:
    """Print `error: <message>` as one line on stderr and exit with `ERROR_EXIT`."""
    typer.echo(f"error: {error}", err=True)
    raise typer.Exit(ERROR_EXIT) from (error if isinstance(error, Exception) else None)


@app.callback()
def _root() -> None:
    """Safe-CDT in JAX."""


def enable_persistent_cache() -> None:
    """Keep compiled XLA programs across runs in `$SAFECDT_CACHE/xla` (or
    `$JAX_COMPILATION_CACHE_DIR`), and the deployment's traced program in
    `$SAFECDT_CACHE/programs`: a second deployment of the same shapes loads both instead of
    tracing and compiling (`benchmarks/compile_time.py`); a resumed paper suite skips its
    compiles."""
    import jax

    from safecdt_jax import programs
    from safecdt_jax.paths import cache_root

    programs.enable(cache_root() / "programs")
    if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
        jax.config.update("jax_compilation_cache_dir", str(cache_root() / "xla"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


# Several cooperating processes (`safecdt_jax.distributed`): the same command started N times.
Coordinator = Annotated[str | None, typer.Option(
    envvar="JAX_COORDINATOR_ADDRESS", rich_help_panel="Several processes",
    help="HOST:PORT of process 0's coordinator, when N processes cooperate on one sweep.")]
NumProcesses = Annotated[int | None, typer.Option(
    min=1, envvar="JAX_NUM_PROCESSES", rich_help_panel="Several processes",
    help="How many processes cooperate (default 1: this process alone).")]
ProcessId = Annotated[int | None, typer.Option(
    min=0, envvar="JAX_PROCESS_ID", rich_help_panel="Several processes",
    help="This process's id, 0..N-1; process 0 writes the results.")]


def join_processes(coordinator: str | None, num_processes: int | None,
                   process_id: int | None) -> bool:
    """Join the cooperating processes these options describe (`distributed.initialize`), or
    report bad settings or a failed start as one line; returns whether several cooperate.
    Must run before the command computes anything with JAX."""
    from safecdt_jax import distributed

    try:
        return distributed.initialize(
            distributed.cluster_from(coordinator, num_processes, process_id))
    except (ValueError, RuntimeError) as e:  # bad settings; a peer or coordinator not reached
        fail(str(e).strip().splitlines()[0] if str(e).strip() else repr(e))
