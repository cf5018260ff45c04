"""Data set summary figures on episodes with known returns and costs, and the scatter PNG."""

import dataclasses
import json
import os
import stat

import numpy as np
import pytest

from safecdt_jax.data import make_dataset, summarize_dataset, write_dataset
from safecdt_jax.data.summary import between_group_share, policy_cost_bands
from safecdt_jax.io import write_text_atomic

COSTS = [0.0, 10.0, 25.0, 31.0, 100.0, 150.0]
RETURNS = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]


def known_dataset():
    """Six 4-step episodes whose per-step values sum to the totals above (junk past length 3)."""
    n = len(COSTS)
    rewards = np.tile(np.array(RETURNS)[:, None] / 4, (1, 4))
    costs = np.zeros((n, 4))
    costs[:, 0], costs[:, 2] = np.array(COSTS) / 2, np.array(COSTS) / 2
    lengths = np.full(n, 4)
    lengths[0] = 3  # episode 0: cost 0 and return 0.75 (its 4th step is cut)
    return make_dataset(
        np.zeros((n, 4, 2)),
        np.zeros((n, 4, 1)),
        rewards,
        costs,
        lengths,
        attrs={"task": "PointGoal1"},
    )


def test_summary_known_values(tmp_path):
    s = summarize_dataset(known_dataset())
    assert s["n_episodes"] == 6 and s["n_transitions"] == 23
    assert s["cost_min"] == 0.0 and s["cost_max"] == 150.0 and s["cost_median"] == 28.0
    assert s["frac_cost_le_30"] == 0.5 and s["frac_cost_gt_30"] == 0.5
    assert s["best_return_cost_le_10"] == 2.0  # costs 0 and 10 qualify
    assert s["best_return_cost_30_100"] == 5.0  # costs 31 and 100; 150 is out
    assert s["n_cost_le_10"] == 2 and s["n_cost_30_100"] == 2
    assert s["return_min"] == 0.75 and s["return_max"] == 6.0
    json.dumps(s)  # plain numbers only


def test_summary_thresholds_and_missing_groups():
    s = summarize_dataset(known_dataset(), budget=200.0, safe_cost=-1.0, high_cost=300.0)
    assert s["frac_cost_le_200"] == 1.0 and s["frac_cost_gt_200"] == 0.0
    assert s["best_return_cost_le_m1"] is None and s["best_return_cost_200_300"] is None
    assert s["n_cost_le_m1"] == 0


def test_summary_from_file_writes_png_atomically(tmp_path):
    path = tmp_path / "d.hdf5"
    write_dataset(path, known_dataset())
    png = tmp_path / "plots" / "scatter.png"
    s = summarize_dataset(path, png_path=png)
    assert s == summarize_dataset(known_dataset())
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 1000
    assert sorted(p.name for p in png.parent.iterdir()) == ["scatter.png"]


def test_atomic_writes_get_the_umask_permissions_not_mkstemps_private_ones(tmp_path):
    old = os.umask(0o027)
    try:
        path = write_text_atomic(tmp_path / "r.json", "{}")
    finally:
        os.umask(old)
    assert path.read_text() == "{}"
    assert stat.S_IMODE(path.stat().st_mode) == 0o640
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_variance_share_between_snapshots_known_values():
    # Groups {0, 0, 1, 1}: means 1 and 5 around 3, so between = 4 * 4 = 16 of total 16 + 4.
    assert between_group_share(np.array([0.0, 2.0, 4.0, 6.0]), np.array([0, 0, 1, 1])) == 0.8
    assert between_group_share(np.array([1.0, 1.0]), np.array([0, 1])) is None
    assert between_group_share(np.array([1.0, 2.0]), None) is None
    s = summarize_dataset(known_dataset())
    assert s["cost_share_by_snapshot"] is None  # no snapshot ids: not expert data
    data = dataclasses.replace(known_dataset(), episode_info={"snapshot": np.arange(6) % 2})
    # costs 0, 25, 100 | 10, 31, 150: means 41.67 and 63.67 around 52.67
    costs = np.array(COSTS)
    want = 6 * 11.0**2 / np.sum((costs - costs.mean()) ** 2)
    assert summarize_dataset(data)["cost_share_by_snapshot"] == pytest.approx(want)


def test_policy_cost_bands_known_values():
    # Policy 0 costs 0, 10 (mean 5: the careful band, its edge inclusive); policy 1 costs 30
    # (mean 30); policy 2 costs 100, 140 (mean 120).
    costs = np.array([0.0, 10.0, 30.0, 100.0, 140.0])
    out = policy_cost_bands(costs, np.array([0, 0, 1, 2, 2]))
    assert out["policy_cost_min"] == 5.0 and out["policy_cost_max"] == 120.0
    assert out["policy_cost_shares"] == {"<=5": 0.4, "5-20": 0.0, "20-60": 0.2, ">60": 0.4}
    assert policy_cost_bands(costs, None)["policy_cost_shares"] is None
    data = dataclasses.replace(known_dataset(), episode_info={"snapshot": np.arange(6) % 2})
    # costs 0, 25, 100 | 10, 31, 150: policy means 41.67 and 63.67, three episodes each
    s = summarize_dataset(data)
    assert s["policy_cost_min"] == pytest.approx(125 / 3)
    assert s["policy_cost_shares"] == {"<=5": 0.0, "5-20": 0.0, "20-60": 0.5, ">60": 0.5}
