"""Behaviour experts as DSRL makes them: PPO-Lagrangian trained on our MJX tasks, snapshots kept,
rolled out and grid-filtered into DSRL-format source data."""

from safecdt_jax.experts.config import NO_LIMIT, CostSchedule, ExpertConfig, expert_preset
from safecdt_jax.experts.ppo_lag import cost_limit, gae, make_train, pid_step

__all__ = ["NO_LIMIT", "CostSchedule", "ExpertConfig", "cost_limit", "expert_preset", "gae",
           "make_train", "pid_step"]
