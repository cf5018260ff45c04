"""The `safecdt-jax` command line: one module per group of subcommands, all on one Typer app.

Command modules import heavy dependencies (JAX, MJX) inside their functions, so `--help` is fast.
"""

from safecdt_jax.cli import (
    baselines,  # noqa: F401
    data,  # noqa: F401
    demo,  # noqa: F401  (each module registers its commands)
    deploy,  # noqa: F401
    expert,  # noqa: F401
    paper,  # noqa: F401
    theory,  # noqa: F401
    train,  # noqa: F401
)
from safecdt_jax.cli.app import app, enable_persistent_cache


def main() -> None:
    """Console-script entry point: every command keeps its compiled programs across runs."""
    enable_persistent_cache()
    app()


__all__ = ["app", "main"]
