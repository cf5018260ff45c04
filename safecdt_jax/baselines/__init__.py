"""Offline safe-RL baselines of the paper's comparison, in JAX: BCQ-Lag, BEAR-Lag and CPQ (and
OSRL's BC-All / BC-Safe through the same interface). docs/BASELINES.md describes them.

    cfg = preset("bcql", "cpu", cost_limit=30.0)
    trained = train_baseline(cfg, load_source(path, "CarGoal1"), seeds=[0, 1, 2])
    returns, costs = evaluate_trained(trained, "CarGoal2", episodes=20, stop_cost=30.0)
"""

from safecdt_jax.baselines.config import ALGOS, PRESET_NAMES, BaselineConfig, preset
from safecdt_jax.baselines.run import (
    BC_ALGOS,
    Trained,
    evaluate_trained,
    load_source,
    train_baseline,
    train_bc,
)
from safecdt_jax.baselines.train import make_algorithm, make_chunk, make_train

__all__ = ["ALGOS", "BC_ALGOS", "PRESET_NAMES", "BaselineConfig", "Trained", "evaluate_trained",
           "load_source", "make_algorithm", "make_chunk", "make_train", "preset",
           "train_baseline", "train_bc"]
