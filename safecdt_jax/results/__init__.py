"""Deployment results as tables (the paper's Table 1 row) and figures (PNG)."""

from safecdt_jax.results.figures import plot_deployment, plot_robustness
from safecdt_jax.results.tables import (
    METRIC_NAMES,
    markdown_table,
    results_table,
    seed_summaries,
    summarize_runs,
)

__all__ = ["METRIC_NAMES", "markdown_table", "plot_deployment", "plot_robustness",
           "results_table", "seed_summaries", "summarize_runs"]
