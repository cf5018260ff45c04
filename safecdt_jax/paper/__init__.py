"""The paper's evaluation as one command (`safecdt-jax paper`): Tables 1-7, Figure 2 and the
safety certificate from resumable, vmapped experiments, in a generated REPORT.md."""

from safecdt_jax.paper.plan import PaperPlan, experiments, quick_plan
from safecdt_jax.paper.run import run_paper

__all__ = ["PaperPlan", "experiments", "quick_plan", "run_paper"]
