"""Collected data: shapes, chunking that never changes the data, the HDF5 round trip, the
data CLI commands and their errors."""

import json

import numpy as np
import pytest
from data_helpers import expert_episodes
from typer.testing import CliRunner

from safecdt_jax import envs
from safecdt_jax.cli import app
from safecdt_jax.data import load_dataset
from safecdt_jax.data.collect import check_writable, write_collected


def test_expert_episodes_shapes_and_chunking():
    d = expert_episodes("PointCircle1", n=3, horizon=20, seed=7)
    env, _ = envs.make("PointCircle1")
    assert d.observations.shape == (3, 20, env.observation_size)
    assert d.actions.shape == (3, 20, 2) and d.rewards.shape == d.costs.shape == (3, 20)
    assert np.all(np.abs(d.actions) <= 1.0) and np.all(np.isfinite(d.observations))
    np.testing.assert_array_equal(d.next_observations[:, :-1], d.observations[:, 1:])
    assert list(d.lengths) == [20] * 3 and d.timeouts.all() and not d.terminals.any()
    assert d.attrs["task"] == "PointCircle1" and d.attrs["horizon"] == 20
    # Same key, same bits, whatever the chunking (the last chunk is padded).
    again = expert_episodes("PointCircle1", n=3, horizon=20, seed=7, chunk=2)
    for name in ("observations", "actions", "rewards", "costs"):
        np.testing.assert_array_equal(getattr(again, name), getattr(d, name))


def test_write_load_round_trip_and_summary(tmp_path):
    d = expert_episodes("PointCircle1", n=3, horizon=20, seed=7)
    path = write_collected(tmp_path / "sub" / "PointCircle1.hdf5", d)
    back = load_dataset(path)
    assert back.n_episodes == 3 and list(back.lengths) == [20] * 3
    for name in ("observations", "next_observations", "actions", "rewards", "costs"):
        np.testing.assert_array_equal(getattr(back, name), getattr(d, name))
    for name, v in d.episode_info.items():
        np.testing.assert_array_equal(back.episode_info[name], v)
    assert back.attrs["task"] == "PointCircle1" and back.attrs["behaviour"] == "expert"
    assert json.loads(back.attrs["env_params"])["boundary_y"] == 0.0  # dicts are stored as JSON

    result = CliRunner().invoke(app, ["analyze", "data", str(path)])
    assert result.exit_code == 0, result.output
    assert "3 episodes" in result.output and "FAIL  >= 1000 episodes" in result.output
    assert path.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"


def test_bad_input_errors(tmp_path):
    with pytest.raises(ValueError, match="directory"):
        check_writable(tmp_path)
    runner = CliRunner()
    for args, message in (
        (["collect", "--task", "Ant"], "error: unknown task 'Ant'; valid names: CarGoal1"),
        (["collect", "--task", "CarGoal1", "--episodes", "0"], "error: --episodes must be"),
        (["collect", "--task", "CarGoal1", "--out", str(tmp_path)], "it is a directory"),
        (["analyze", "data", str(tmp_path / "missing.hdf5")], "file not found"),
    ):
        result = runner.invoke(app, args)
        assert result.exit_code == 1 and message in result.output, result.output
        assert len(result.output.strip().splitlines()) == 1
