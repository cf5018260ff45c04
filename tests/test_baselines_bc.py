"""Behaviour cloning baseline: it fits a learnable mapping, selects BC-Safe episodes, is
deterministic, vmaps its seeds, rejects bad settings, and runs end to end from the CLI."""

import jax
import numpy as np
import pytest
from data_helpers import write_expert_episodes
from typer.testing import CliRunner

from safecdt_jax.baselines.bc import (
    BCConfig,
    bc_action,
    evaluate_bc,
    fit_bc,
    fit_bc_seeds,
    select_transitions,
)
from safecdt_jax.cli import app
from safecdt_jax.data import make_dataset, write_dataset

CFG = BCConfig(hidden=32, steps=600, batch=64, lr=3e-3, chunk=200)


def linear_data(n=12, horizon=10, obs_dim=4, seed=0):
    """Actions 0.02 * tanh(obs @ W) (Car-sized), episode i costing i (one cost step each)."""
    rng = np.random.default_rng(seed)
    obs = rng.normal(3.0, 5.0, (n, horizon, obs_dim)).astype(np.float32)  # off-centre, wide
    w = rng.normal(size=(obs_dim, 2)) / np.sqrt(obs_dim)
    actions = (0.02 * np.tanh((obs - 3.0) / 5.0 @ w)).astype(np.float32)
    costs = np.zeros((n, horizon), np.float32)
    costs[:, :] = (np.arange(horizon)[None, :] < np.arange(n)[:, None])
    return make_dataset(obs, actions, np.zeros((n, horizon), np.float32), costs,
                        np.full(n, horizon), attrs={"task": "Synthetic"})


def test_fits_a_learnable_mapping_in_units_of_the_action_range():
    data = linear_data()
    policy, loss = fit_bc(jax.random.PRNGKey(0), data, CFG)
    assert loss.shape == (3,) and loss[-1] < 0.2 * loss[0]
    pred = np.asarray(bc_action(policy, data.observations))
    rmse = np.sqrt(np.mean((pred - data.actions) ** 2)) / 0.02
    assert rmse < 0.15  # of the action range, on the training data
    np.testing.assert_allclose(policy.action_scale, np.abs(data.actions).max((0, 1)), rtol=1e-6)


def test_same_key_same_bits():
    data = linear_data()
    a, la = fit_bc(jax.random.PRNGKey(3), data, CFG)
    b, lb = fit_bc(jax.random.PRNGKey(3), data, CFG)
    np.testing.assert_array_equal(la, lb)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)


def test_seeds_vmapped_equal_seeds_fitted_one_by_one():
    data = linear_data()
    keys = jax.random.split(jax.random.PRNGKey(5), 3)
    stacked, losses = fit_bc_seeds(keys, data, CFG)
    assert losses.shape == (3, 3) and stacked.obs_mean.shape == (3, 4)
    for s in range(3):
        one, loss = fit_bc(keys[s], data, CFG)
        np.testing.assert_allclose(losses[s], loss, rtol=1e-5)
        for x, y in zip(jax.tree.leaves(one), jax.tree.leaves(stacked), strict=True):
            np.testing.assert_allclose(x, y[s], rtol=1e-4, atol=1e-6)
    assert not np.allclose(losses[0], losses[1])  # different seeds, different fits


def test_bc_safe_keeps_only_cheap_episodes():
    data = linear_data()  # episode i costs i
    obs, actions = select_transitions(data, 3.0)
    assert obs.shape == (4 * 10, 4) and actions.shape == (40, 2)
    np.testing.assert_array_equal(obs, data.observations[:4].reshape(-1, 4))
    assert len(select_transitions(data, None)[0]) == 12 * 10
    cheap = make_dataset(data.observations, data.actions, data.rewards, data.costs + 1.0,
                         data.lengths)
    with pytest.raises(ValueError, match=r"no episode has cost <= 0 \(episode costs span 10-20\)"):
        select_transitions(cheap, 0.0)


def test_cost_band_keeps_exactly_the_band():
    data = linear_data()  # episode i costs min(i, 10)
    obs, _ = select_transitions(data, 7.0, 5.0)  # episodes 5, 6, 7
    np.testing.assert_array_equal(obs, data.observations[5:8].reshape(-1, 4))
    assert len(select_transitions(data, None, 9.0)[0]) == 3 * 10  # episodes 9-11
    with pytest.raises(ValueError, match=r"no episode has cost in \[3.5, 3.9\]"):
        select_transitions(data, 3.9, 3.5)
    with pytest.raises(ValueError, match=r"BCConfig.min_cost \(5\) must be <= max_cost \(2\)"):
        BCConfig(min_cost=5.0, max_cost=2.0)


@pytest.mark.parametrize("bad", [dict(steps=0), dict(lr=0.0), dict(max_cost=-1.0),
                                 dict(min_cost=-0.5), dict(hidden=1.5)])
def test_bad_settings_name_the_field(bad):
    with pytest.raises(ValueError, match=f"BCConfig.{next(iter(bad))}"):
        BCConfig(**bad)


def test_rollout_checks_the_observation_size():
    policy, _ = fit_bc(jax.random.PRNGKey(0), linear_data(), BCConfig(hidden=8, steps=1, chunk=1))
    with pytest.raises(ValueError, match="reads 4 observation dims, PointCircle1 gives"):
        evaluate_bc(jax.random.PRNGKey(0), "PointCircle1", policy, episodes=1)


def test_cli_end_to_end(tmp_path):
    path = tmp_path / "pc1.hdf5"
    write_expert_episodes(path)
    result = CliRunner().invoke(app, ["analyze", "bc", "--data", str(path), "--steps", "20",
                                      "--episodes", "2"])
    assert result.exit_code == 0, result.output
    assert "BC-All: 4 episodes, 80 transitions" in result.output
    assert "PointCircle1, 2 episodes: return" in result.output
    # 20 steps from the start never reach a wall: every episode costs 0, BC-Safe keeps all.
    safe = CliRunner().invoke(app, ["analyze", "bc", "--data", str(path), "--max-cost", "0",
                                    "--steps", "20", "--episodes", "2"])
    assert safe.exit_code == 0 and "BC-Safe (cost <= 0): 4 episodes" in safe.output
    band = CliRunner().invoke(app, ["analyze", "bc", "--data", str(path), "--min-cost", "1",
                                    "--steps", "1"])
    assert band.exit_code == 1  # no episode costs >= 1: one line, before any fitting
    assert "error: no episode has cost >= 1 (episode costs span 0-0)" in band.output

def test_synthetic_file_without_a_known_task_is_a_clean_error(tmp_path):
    path = tmp_path / "syn.hdf5"
    write_dataset(path, linear_data())
    result = CliRunner().invoke(app, ["analyze", "bc", "--data", str(path), "--steps", "1"])
    assert result.exit_code == 1
    assert "error: unknown task 'Synthetic' (from " in result.output
