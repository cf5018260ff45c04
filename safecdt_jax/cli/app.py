"""The one Typer app every `safecdt-jax` subcommand registers on."""

import os

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")

import typer

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Safe-CDT in JAX: environments, offline data, CDT, safe deployment.")


@app.callback()
def _root() -> None:
    """Safe-CDT in JAX."""
