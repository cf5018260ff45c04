"""Behaviour policies, the collector, `ensure_dataset` and the data CLI commands.

Policies are checked on synthetic states (pose, layout, cost spent), which compile in a blink;
one short real collection (PointCircle1, 3 episodes of 20 steps) covers the env integration.
"""

import dataclasses
import json
from types import SimpleNamespace

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from safecdt_jax import envs
from safecdt_jax.cli import app
from safecdt_jax.data import collect as collect_mod
from safecdt_jax.data import load_dataset, make_dataset, write_dataset
from safecdt_jax.data.behaviour import (
    CAR_DRIVE,
    family,
    knob_names,
    make_policy,
    robot_drive,
    sample_knobs,
    schedule,
)
from safecdt_jax.data.collect import (
    COLLECTOR_VERSION,
    collect,
    ensure_dataset,
    is_current,
    write_collected,
)

SOURCE_TASKS = ("CarGoal1", "CarCircle1", "PointCircle1", "PointGoal1")


def fake_state(qpos, qvel, goal, hazards, vases, steps):
    """The parts of an env `State` a behaviour policy reads (pose, layout, step count)."""
    return SimpleNamespace(data=SimpleNamespace(qpos=qpos, qvel=qvel),
                           task={"goal": goal, "hazards": hazards, "vases": vases},
                           info={"steps": steps})


def random_actions(task: str, key: jax.Array, n: int = 256) -> jax.Array:
    """Actions [n, 2] of `task`'s policy on random poses, layouts, budgets spent and knobs."""
    env, params = envs.make(task)
    policy = make_policy(task, params)
    ks = jax.random.split(key, 8)
    extent = 2.2  # beyond the widest layout, so poses fall inside and outside walls and hazards
    qpos = jnp.concatenate([jax.random.uniform(ks[0], (n, 2), minval=-extent, maxval=extent),
                            jax.random.uniform(ks[1], (n, 1), minval=-10.0, maxval=10.0)], -1)
    qvel = jax.random.normal(ks[2], (n, 3))
    goal = jax.random.uniform(ks[3], (n, 2), minval=-extent, maxval=extent)
    hazards = jax.random.uniform(ks[4], (n, 10, 2), minval=-extent, maxval=extent)
    vases = jax.random.uniform(ks[5], (n, 10, 2), minval=-extent, maxval=extent)
    steps = jax.random.randint(ks[6], (n,), 0, env.episode_length)
    spent = jax.random.uniform(ks[7], (n,), maxval=300.0)
    knobs = sample_knobs(jax.random.fold_in(key, 1), task, n)
    keys = jax.random.split(jax.random.fold_in(key, 2), n)

    def act(qpos, qvel, goal, hazards, vases, steps, spent, knobs, key):
        state = fake_state(qpos, qvel, goal, hazards, vases, steps)
        return policy(knobs, state, spent, key)

    return jax.jit(jax.vmap(act))(qpos, qvel, goal, hazards, vases, steps, spent, knobs, keys)


@pytest.mark.parametrize("task", envs.NAMES)
def test_actions_finite_in_box_and_deterministic(task):
    a = np.asarray(random_actions(task, jax.random.PRNGKey(0)))
    assert np.all(np.isfinite(a)) and np.all(np.abs(a) <= 1.0)
    # Mapped into the actuators' linear range: never beyond the saturation point.
    assert np.all(np.abs(a) <= np.asarray(robot_drive(task).saturation) + 1e-7)
    assert np.array_equal(a, np.asarray(random_actions(task, jax.random.PRNGKey(0))))
    assert not np.array_equal(a, np.asarray(random_actions(task, jax.random.PRNGKey(1))))


def test_schedule_ramps_to_the_budget_at_spread():
    # budget 50 over half of a 1000-step episode: 0.1 cost steps owed per step, then flat.
    knobs = {"budget": jnp.float32(50.0), "spread": jnp.float32(0.5)}
    owed = [float(schedule(knobs, jnp.int32(t), 1000)) for t in (0, 249, 499, 900)]
    np.testing.assert_allclose(owed, [0.1, 25.0, 50.0, 50.0], rtol=1e-6)
    assert float(schedule(dict(knobs, budget=jnp.float32(0.0)), jnp.int32(10), 1000)) == 0.0


def test_circle_robot_runs_wide_only_while_behind_schedule():
    # On CarCircle1's x-walls (|x| > 1.125 costs) the chased point lies beyond the wall when
    # behind schedule (reckless) and inside it when ahead: the wheel commands differ.
    policy = make_policy("CarCircle1")
    knobs = {k: jnp.float32(np.mean(v)) for k, v in
             sample_knobs(jax.random.PRNGKey(0), "CarCircle1", 64).items()}
    knobs |= {"noise": jnp.float32(0.0), "budget": jnp.float32(50.0), "spread": jnp.float32(1.0)}
    far = jnp.full((10, 2), 1e3)
    state = fake_state(jnp.asarray([1.0, 0.0, 0.0]), jnp.zeros(3), far[0], far, far,
                       jnp.int32(250))  # schedule: 50 * 251 / 500 = 25.1 owed
    act = [np.asarray(policy(knobs, state, jnp.float32(spent), jax.random.PRNGKey(0)))
           for spent in (10.0, 20.0, 30.0, 40.0)]
    np.testing.assert_array_equal(act[0], act[1])  # both behind: same (reckless) command
    np.testing.assert_array_equal(act[2], act[3])  # both ahead: same (careful) command
    assert not np.allclose(act[1], act[2])


def test_point_circle_is_graded_between_the_careful_and_the_reckless_circle():
    # PointCircle1 (collector v5) blends the two circles by the remaining budget's rate; the
    # same policy switched (full_rate 0) gives the two ends: careful when the budget is spent,
    # reckless when the rate is at least full_rate.
    assert family("PointCircle1").full_rate == 0.25 and family("CarCircle1").full_rate == 0.0
    knobs = {k: jnp.float32(np.mean(v)) for k, v in
             sample_knobs(jax.random.PRNGKey(0), "PointCircle1", 64).items()}
    knobs |= {"noise": jnp.float32(0.0), "budget": jnp.float32(100.0)}
    far = jnp.full((10, 2), 1e3)
    state = fake_state(jnp.asarray([1.0, 0.0, 0.0]), jnp.zeros(3), far[0], far, far,
                       jnp.int32(300))  # 200 steps left
    graded = make_policy("PointCircle1")
    switched = make_policy("PointCircle1",
                           fam=dataclasses.replace(family("PointCircle1"), full_rate=0.0))
    key = jax.random.PRNGKey(0)

    def act(policy, spent, budget=100.0):
        return np.asarray(policy(dict(knobs, budget=jnp.float32(budget)), state,
                                 jnp.float32(spent), key))

    careful, reckless = act(switched, 100.0), act(switched, 0.0, budget=1000.0)
    np.testing.assert_allclose(act(graded, 100.0), careful, atol=1e-6)  # nothing left: careful
    np.testing.assert_allclose(act(graded, 0.0), reckless, atol=1e-6)  # 0.5 per step left
    between = act(graded, 75.0)  # 25 left over 200 steps: boldness 0.5
    assert not np.allclose(between, careful) and not np.allclose(between, reckless)


def test_knobs_in_ranges_and_budget_mixture():
    for task in SOURCE_TASKS:
        fam = family(task)
        knobs = sample_knobs(jax.random.PRNGKey(3), task, 2000)
        assert set(knobs) == set(knob_names(fam))
        for name, v in knobs.items():
            v = np.asarray(v)
            assert v.shape == (2000,) and v.dtype == np.float32
            lo, hi = getattr(fam, name)
            ok = (v >= lo) & (v <= hi)
            if name == "budget":  # careful episodes have budget 0
                assert abs(np.mean(v == 0) - fam.p_careful) < 0.05
                ok |= v == 0
            assert ok.all(), name


def car_action(goal_offset):
    """The Car's action at rest at the origin, travelling toward -y (yaw 0), with the goal at
    `goal_offset`: careful (budget 0, no hazards near), and reckless (behind its cost schedule,
    with a hazard on the goal, which it ignores)."""
    policy = make_policy("CarGoal1")
    goal = jnp.asarray(goal_offset, jnp.float32)
    far = jnp.full((10, 2), 1e3)
    knobs = {k: jnp.float32(np.mean(v)) for k, v in
             sample_knobs(jax.random.PRNGKey(0), "CarGoal1", 64).items()}
    knobs["noise"] = jnp.float32(0.0)
    out = []
    for budget, hazards in ((0.0, far), (1e3, far.at[0].set(goal))):
        state = fake_state(jnp.zeros(3), jnp.zeros(3), goal, hazards, far, jnp.int32(0))
        out.append(np.asarray(policy(dict(knobs, budget=jnp.float32(budget)), state,
                                     jnp.float32(0.0), jax.random.PRNGKey(0))))
    return out


def test_car_turns_through_wheel_difference():
    # The Car travels toward body -y; at yaw 0 its left is world +x. Action 0 is the right
    # wheel: a left turn (counter-clockwise) needs action 0 > action 1.
    for a in car_action([1.0, 0.0]):  # goal on the left
        assert a[0] > a[1]
    for a in car_action([-1.0, 0.0]):  # goal on the right
        assert a[0] < a[1]
    for a in car_action([0.0, -1.0]):  # goal straight ahead: both wheels forward, equal
        assert a[0] > 0 and a[0] == pytest.approx(a[1], abs=1e-6)
    assert CAR_DRIVE.saturation == (0.02, 0.02)


def test_goal_reckless_drives_through_a_hazard_the_careful_one_avoids():
    # A hazard halfway to a goal straight ahead (1.2 m toward -y). Behind its schedule the Car
    # drives straight at it (equal wheels); on schedule (budget 0) it steers around it.
    policy = make_policy("CarGoal1")
    far = jnp.full((10, 2), 1e3)
    knobs = {k: jnp.float32(np.mean(v)) for k, v in
             sample_knobs(jax.random.PRNGKey(0), "CarGoal1", 64).items()}
    knobs |= {"noise": jnp.float32(0.0), "clearance": jnp.float32(0.3)}
    state = fake_state(jnp.zeros(3), jnp.zeros(3), jnp.asarray([0.0, -1.2]),
                       far.at[0].set(jnp.asarray([0.0, -0.6])), far, jnp.int32(0))
    reckless, careful = (np.asarray(policy(dict(knobs, budget=jnp.float32(b)), state,
                                           jnp.float32(0.0), jax.random.PRNGKey(0)))
                         for b in (50.0, 0.0))
    assert reckless[0] > 0 and reckless[0] == pytest.approx(reckless[1], abs=1e-6)
    assert abs(careful[0] - careful[1]) > 0.1 * CAR_DRIVE.saturation[0]


@pytest.fixture(scope="module")
def small_collection():
    """3 PointCircle1 episodes of 20 steps, in chunks of 2 (the last chunk padded)."""
    return collect(jax.random.PRNGKey(7), "PointCircle1", 3, chunk=2, seed=7, horizon=20)


def test_collect_shapes_knobs_and_determinism(small_collection):
    d = small_collection
    env, _ = envs.make("PointCircle1")
    assert d.observations.shape == (3, 20, env.observation_size)
    assert d.actions.shape == (3, 20, 2) and d.rewards.shape == d.costs.shape == (3, 20)
    assert np.all(np.abs(d.actions) <= 1.0) and np.all(np.isfinite(d.observations))
    np.testing.assert_array_equal(d.next_observations[:, :-1], d.observations[:, 1:])
    assert list(d.lengths) == [20] * 3 and d.timeouts.all() and not d.terminals.any()
    # Knobs are stored per episode, exactly as drawn.
    k_knobs, _ = jax.random.split(jax.random.PRNGKey(7))
    drawn = sample_knobs(k_knobs, "PointCircle1", 3)
    assert set(d.episode_info) == set(knob_names(family("PointCircle1")))
    for name, v in drawn.items():
        np.testing.assert_array_equal(d.episode_info[name], np.asarray(v))
    attrs = d.attrs
    assert attrs["task"] == "PointCircle1" and attrs["collector_version"] == COLLECTOR_VERSION
    assert attrs["seed"] == 7 and attrs["episodes"] == 3 and attrs["horizon"] == 20
    assert attrs["env_params"]["boundary"] == pytest.approx(1.125)
    # Same key, same bits, whatever the chunking.
    again = collect(jax.random.PRNGKey(7), "PointCircle1", 3, chunk=2, seed=7, horizon=20)
    for name in ("observations", "actions", "rewards", "costs"):
        np.testing.assert_array_equal(getattr(again, name), getattr(d, name))


def test_write_load_round_trip(small_collection, tmp_path):
    d = small_collection
    path = write_collected(tmp_path / "sub" / "PointCircle1.hdf5", d)
    back = load_dataset(path)
    assert back.n_episodes == 3 and list(back.lengths) == [20] * 3
    for name in ("observations", "next_observations", "actions", "rewards", "costs"):
        np.testing.assert_array_equal(getattr(back, name), getattr(d, name))
    np.testing.assert_allclose(back.rewards.sum(1), d.rewards.sum(1))
    for name, v in d.episode_info.items():
        np.testing.assert_array_equal(back.episode_info[name], v)
    assert back.attrs["task"] == "PointCircle1" and back.attrs["seed"] == 7
    assert back.attrs["collector_version"] == COLLECTOR_VERSION
    assert json.loads(back.attrs["env_params"])["boundary_y"] == 0.0  # dicts are stored as JSON
    # A short-horizon file is never taken for a full data set.
    assert not is_current(path, "PointCircle1", 3, seed=7)

    result = CliRunner().invoke(app, ["data-summary", str(path)])
    assert result.exit_code == 0, result.output
    assert "3 episodes" in result.output and "FAIL  >= 1000 episodes" in result.output
    assert path.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"


def fake_data(task="PointCircle1", version=COLLECTOR_VERSION, seed=0, episodes=2,
              physics=None):
    """Tiny data whose attributes (those `is_current` reads) claim a full collection."""
    attrs = {"task": task, "collector_version": version, "seed": seed, "episodes": episodes,
             "horizon": envs.make(task)[0].episode_length,
             "physics_version": envs.physics_version(task) if physics is None else physics}
    return make_dataset(np.zeros((episodes, 2, 3)), np.zeros((episodes, 2, 2)),
                        np.ones((episodes, 2)), np.zeros((episodes, 2)), np.full(episodes, 2),
                        attrs=attrs)


def test_ensure_dataset_reuses_and_recollects(tmp_path, monkeypatch):
    monkeypatch.setenv("SAFECDT_CACHE", str(tmp_path))
    path = tmp_path / "datasets" / "PointCircle1.hdf5"
    path.parent.mkdir()
    write_dataset(path, fake_data(episodes=5))
    calls = []

    def fake_collect(key, task, episodes, progress=None, seed=None, **kw):
        calls.append((task, episodes, seed))
        return fake_data(task, seed=seed, episodes=episodes)

    monkeypatch.setattr(collect_mod, "collect", fake_collect)
    assert ensure_dataset("PointCircle1", 4, seed=0) == path and calls == []  # cached, enough
    assert ensure_dataset("PointCircle1", 5, seed=0) == path and calls == []
    ensure_dataset("PointCircle1", 6, seed=0)  # too few episodes: collects
    ensure_dataset("PointCircle1", 6, seed=1)  # another seed: collects
    assert calls == [("PointCircle1", 6, 0), ("PointCircle1", 6, 1)]
    write_dataset(path, fake_data(version=COLLECTOR_VERSION - 1, episodes=50))  # older collector
    calls.clear()
    assert ensure_dataset("PointCircle1", 6, seed=0) == path
    assert calls == [("PointCircle1", 6, 0)]
    with h5py.File(path) as f:
        assert f.attrs["collector_version"] == COLLECTOR_VERSION and f.attrs["episodes"] == 6
    old = envs.physics_version("PointCircle1") - 1  # data from older dynamics
    write_dataset(path, fake_data(physics=old, episodes=50))
    calls.clear()
    ensure_dataset("PointCircle1", 6, seed=0)
    assert calls == [("PointCircle1", 6, 0)]


def test_bad_input_errors(tmp_path):
    for call in (lambda: family("CarGoal3"), lambda: sample_knobs(jax.random.PRNGKey(0), "X", 2),
                 lambda: collect(jax.random.PRNGKey(0), "Ant", 2),
                 lambda: ensure_dataset("Ant", 2, path=tmp_path / "a.hdf5")):
        with pytest.raises(ValueError, match="valid names: CarGoal1"):
            call()
    with pytest.raises(ValueError, match="episodes"):
        collect(jax.random.PRNGKey(0), "CarGoal1", 0)
    with pytest.raises(ValueError, match="directory"):
        ensure_dataset("CarGoal1", 2, path=tmp_path)
    runner = CliRunner()
    for args, message in (
        (["collect", "--task", "Ant"], "error: unknown task 'Ant'; valid names: CarGoal1"),
        (["collect", "--task", "CarGoal1", "--episodes", "0"], "error: --episodes must be"),
        (["collect", "--task", "CarGoal1", "--out", str(tmp_path)], "it is a directory"),
        (["data-summary", str(tmp_path / "missing.hdf5")], "file not found"),
    ):
        result = runner.invoke(app, args)
        assert result.exit_code == 2 and message in result.output, result.output
        assert len(result.output.strip().splitlines()) == 1
