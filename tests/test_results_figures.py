"""The deployment figures summarise each scheduler stage: mean over seeds with a 95% interval."""

import numpy as np
import pytest

from safecdt_jax.results.figures import plot_deployment, stage_means


def test_stage_means_known_values_and_a_partial_last_stage():
    values = np.arange(24.0).reshape(2, 12)  # seed 0: 0..11, seed 1: 12..23
    stage, mean, half = stage_means(values, 5)
    assert stage.tolist() == [1, 2, 3]
    assert mean.tolist() == [8.0, 13.0, 16.5]  # the last stage holds episodes 11-12 only
    # per-seed stage means differ by 12 between the seeds: sample std 12/sqrt(2), n = 2
    assert half == pytest.approx(np.full(3, 1.96 * 12 / np.sqrt(2) / np.sqrt(2)))
    assert stage_means(values[:1], 4)[2].tolist() == [0.0, 0.0, 0.0]  # one seed: no interval


def test_plot_deployment_writes_the_three_figures(tmp_path):
    rng = np.random.default_rng(0)
    metrics = {"cost": rng.uniform(0, 40, (3, 10)), "ctg_target": np.full((3, 10), 18.0),
               "violation": rng.uniform(0, 1, (3, 10)) > 0.7}
    paths = plot_deployment({"safe_cdt": metrics}, 30.0, tmp_path, "test", stage_len=5)
    assert [p.rsplit("/", 1)[1] for p in paths] == ["cost.png", "ctg_target.png",
                                                    "violation_rate.png"]
    assert all((tmp_path / name).stat().st_size > 1000 for name in ("cost.png",))
