"""benchmarks/levers.py: the per-seed metrics and the two spreads, by hand."""

import numpy as np
import pytest

from benchmarks.levers import per_seed, spread


def test_per_seed_metrics_and_drift_by_hand():
    cost = np.zeros((2, 50))
    cost[0, -10:] = 31.0  # seed 0 violates in its last 10 episodes, seed 1 never
    run = {"metrics": {"cost": cost.tolist(), "violation": (cost > 30).tolist(),
                       "return": np.ones((2, 50)).tolist()}}
    m = per_seed(run)
    np.testing.assert_allclose(m["vr"], [20.0, 0.0])
    np.testing.assert_allclose(m["cost"], [6.2, 0.0])
    np.testing.assert_allclose(m["late"], [31.0, 0.0])
    np.testing.assert_allclose(m["drift"], [31.0, 0.0])
    np.testing.assert_allclose(m["reward"], [1.0, 1.0])


def test_spread_separates_checkpoints_from_seeds():
    s = spread([np.array([1.0, 3.0]), np.array([5.0, 7.0])])  # ckpt means 2 and 6
    assert s == pytest.approx({"mean": 4.0, "ckpt_std": 2.0, "seed_std": 1.0})
