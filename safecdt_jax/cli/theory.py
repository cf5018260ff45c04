"""`safecdt-jax certify`: the paper's safety theory applied to a deployment's results."""

import json
from pathlib import Path
from typing import Annotated

import typer

from safecdt_jax.cli.app import analyze, fail


@analyze.command()
def certify(
    results: Annotated[Path, typer.Argument(help="A deployment results.json (deploy or run).")],
    budget: Annotated[float, typer.Option(help="Budget B to certify (cost units).")] = 30.0,
    alpha: Annotated[float, typer.Option(help="Tolerated probability of any violation.")]
        = 0.05,
    kappa: Annotated[float, typer.Option(help="Confidence coefficient of B*.")] = 1.0,
    source: Annotated[Path | None, typer.Option(
        help="Results measured in the source task at the same CTG conditions: adds the "
             "transfer check (Theorem 4.4).")] = None,
    out: Annotated[Path | None, typer.Option(help="Also write the certificate as JSON.")]
        = None,
) -> None:
    """Per CTG condition: phi, sigma, the empirical violation rate beside the bounds of
    Theorems 4.1-4.2; the critical and certified budgets (Theorem 4.3); the transfer check."""
    from safecdt_jax.io import write_text_atomic
    from safecdt_jax.theory import certificate_table, certify_file

    try:
        cert = certify_file(results, budget, alpha, kappa, source)
    except (ValueError, OSError, KeyError) as e:
        fail(e)
    typer.echo(certificate_table(cert))
    if out is not None:
        write_text_atomic(out, json.dumps(cert, indent=1))
