"""experiments/sim2sim.py: the agreement band, layout statistics and target names (no peer venv)."""

import itertools

import numpy as np
import pytest

from experiments.sim2sim import in_band, layout_stats, target_task
from safecdt_jax import envs


def _row(ours, theirs, med_ours, med_theirs, ret_ratio=1.0, ci=(0.8, 1.3)):
    return {"ours_cost": ours, "theirs_cost": theirs, "cost_ratio": theirs / max(ours, 1e-9),
            "cost_ratio_ci": ci, "ours_median_cost": med_ours, "theirs_median_cost": med_theirs,
            "return_ratio": ret_ratio}


def test_in_band_needs_mean_median_interval_and_return():
    assert in_band(_row(100.0, 120.0, 90.0, 100.0))
    assert not in_band(_row(100.0, 150.0, 90.0, 100.0))  # mean ratio 1.5
    assert not in_band(_row(100.0, 120.0, 90.0, 100.0, ci=(1.05, 1.4)))  # interval misses 1
    assert not in_band(_row(100.0, 120.0, 63.5, 0.0))  # one median 0, the other not
    assert in_band(_row(30.0, 40.0, 0.0, 0.0, ci=(0.7, 2.6)))  # both medians 0
    assert not in_band(_row(100.0, 120.0, 90.0, 100.0, ret_ratio=0.79))


def test_layout_stats_on_a_hand_made_layout():
    pos = {"agent": np.array([[0.0, 0.0], [1.0, -1.0]]), "goal": np.array([[1.0, 0.0], [1.0, 1.0]]),
           "hazards": np.array([[[0.5, 0.0]], [[1.0, 0.0]]]), "vases": np.zeros((2, 0, 2))}
    stats = layout_stats(pos, {"agent": 0.4, "hazards": 0.18, "vases": 0.15})
    assert stats["agent |x| mean"] == 0.5 and stats["agent |x|,|y| max"] == 1.0
    assert stats["agent-goal distance"] == pytest.approx(1.5)
    assert stats["agent-nearest hazard"] == pytest.approx(0.75)
    assert stats["smallest keepout slack"] == pytest.approx(0.5 - 0.58)  # a violated keepout
    assert "agent-nearest vase" not in stats


def test_targets_and_env_versions():
    assert target_task("CarGoal1") == "CarGoal2" and target_task("PointCircle1") == "PointCircle2"
    assert envs.env_version("CarGoal2") == (
        f"Car{envs.PHYSICS_VERSIONS['Car']}-Goal{envs.TASK_VERSIONS['Goal']}")
    assert envs.env_version("PointCircle1").startswith("Point")
    with pytest.raises(ValueError, match="unknown task 'CarGoal3'"):
        envs.env_version("CarGoal3")


def test_car_fit_loss_weights_switching_turns_and_leaves_random_drift_out_by_default():
    from experiments.car_fit import LOW_WEIGHT, SWITCH_WEIGHT, loss, scripts

    names = [name for name, _ in scripts()]
    assert names[-1] == "random" and len(names) == len(set(names))
    native = {name: [0.5, 1.0] for name in names} | {"from rest": [0.4, 0.5]}
    assert loss(native, native) == 0.0
    off = lambda key, i, by: native | {key: [v + by * (j == i) for j, v in enumerate(native[key])]}
    n = 2 * len(names) + 2
    assert loss(off("spin (1, -1)", 1, 0.1), native) == pytest.approx(0.1 / np.sqrt(n))
    assert loss(off("switching, p = 0.5", 1, 0.1), native) == pytest.approx(
        SWITCH_WEIGHT * 0.1 / np.sqrt(n))
    assert loss(off("(0.01, 0.01)", 0, 0.1), native) == pytest.approx(
        LOW_WEIGHT * 0.1 / np.sqrt(n))
    assert loss(off("random", 0, 0.1), native) == 0.0  # reported, not fitted
    assert loss(off("random", 0, 0.1), native, random_weight=5.0) == pytest.approx(
        0.5 / np.sqrt(n))


def test_sensor_reliance_groups_tile_the_cars_sensors_and_reject_other_robots():
    from experiments.sensor_reliance import GROUPS, main
    from experiments.sim2sim import SENSOR_NAMES

    names = SENSOR_NAMES["Car"]
    spans = sorted(GROUPS.values())
    assert spans[0][0] == 0 and spans[-1][1] == len(names) == 24
    assert all(a[1] == b[0] for a, b in itertools.pairwise(spans))  # no gap, no overlap
    prefix = {"accelerometer": "acc", "velocimeter": "vel", "gyro": "gyro",
              "magnetometer": "mag", "ball angular velocity": "ballangvel",
              "ball orientation": "ballquat"}
    for group, (lo, hi) in GROUPS.items():
        assert all(n.startswith(prefix[group] + "_") for n in names[lo:hi]), group
    with pytest.raises(SystemExit, match="the sensor groups are the Car's, got PointCircle2"):
        main(["--task", "PointCircle2", "--no-native"])


def test_caster_ball_stats_rotate_the_spin_into_the_chassis_frame():
    """A ball whose orientation is a quarter turn about z reads its spin along its own y; in the
    chassis frame that is -x (the roll), here alternating 2 and 4 rad/s: percentiles from the
    known values, lag-1 autocorrelation -1, no spin about y or z; a Point task is refused."""
    from experiments.caster_ball import WARMUP, ball_stats, main

    steps = WARMUP + 10
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z
    roll = np.tile([2.0, 4.0], steps // 2)
    obs = np.zeros((1, steps, 24))
    obs[0, :, 4] = -0.5  # forward at 0.5 m/s (the velocimeter's y points backward)
    obs[0, :, 12:15] = (rot.T @ np.stack([roll, 0 * roll, 0 * roll])).T
    obs[0, :, 15:24] = rot.reshape(-1)
    s = ball_stats(obs)
    assert s["speed"] == pytest.approx(0.5)
    assert s["roll_pct"][0] == 2.0 and s["roll_pct"][-1] == 4.0 and s["roll_pct"][2] == 3.0
    assert s["lag1"] == pytest.approx(-1.0) and s["std_y"] < 1e-12 and s["std_z"] < 1e-12
    with pytest.raises(SystemExit, match="the caster ball is the Car's, got PointCircle1"):
        main(["--task", "PointCircle1"])


def test_vase_fit_reads_the_native_side_and_restores_the_vase_rule(tmp_path, monkeypatch):
    import json

    import experiments.vase_fit as vase_fit
    from safecdt_jax.envs import goal

    rows = [{"task": "CarGoal1", "run_in": run_in, "deterministic": det}
            for run_in in ("CarGoal1", "CarGoal2") for det in (True, False)]
    path = tmp_path / "sim2sim.json"
    path.write_text(json.dumps({"transfer": rows}))
    found = vase_fit.native_rows(path, "CarGoal1")
    assert {k: v["run_in"] for k, v in found.items()} == {True: "CarGoal2", False: "CarGoal2"}
    with pytest.raises(SystemExit, match="no transfer rows of PointGoal1 in PointGoal2"):
        vase_fit.native_rows(path, "PointGoal1")

    # The rule is set while the episode is traced and put back afterwards, even on an error.
    before = dict(goal.VASE_PUSH)
    seen = []

    def fake_policy(*args):
        seen.append(dict(goal.VASE_PUSH))
        raise RuntimeError("stop")

    monkeypatch.setattr(vase_fit, "ours_policy", fake_policy)
    monkeypatch.setattr(vase_fit, "pick_expert", lambda task: 0)
    with pytest.raises(RuntimeError, match="stop"):
        vase_fit.run_fit("CarGoal1", 0.7, 3.0, 4, 0, True)
    assert seen == [before | {"Car": (0.7, 3.0)}]  # the Car's rule only
    assert goal.VASE_PUSH == before

    # Random actions (deterministic None) run in the level-2 target under the fitted rule, and
    # the native side of random actions is one `policy` request without weights.
    monkeypatch.setattr(vase_fit, "ours_random", lambda task, episodes, seed: {
        "task": task, "rule": goal.VASE_PUSH["Point"]})
    assert vase_fit.run_fit("PointGoal1", 0.9, 2.0, 4, 0, None) == {
        "task": "PointGoal2", "rule": (0.9, 2.0)}
    assert goal.VASE_PUSH == before
    requests = []

    def fake_native(request):
        requests.append(request)
        return {"return": np.array([1.0, 3.0]), "cost": np.array([10.0, 20.0]),
                "cost_hazards": np.array([2.0, 4.0])}

    monkeypatch.setattr(vase_fit, "native", fake_native)
    row = vase_fit.native_random("CarGoal2", 2)
    assert requests == [{"cmd": "policy", "task": "CarGoal2", "weights": None, "episodes": 2,
                         "seed": 0, "deterministic": False}]
    assert row == {"theirs_return": 2.0, "theirs_cost": 15.0, "theirs_costs": [10.0, 20.0],
                   "terms": {"cost_hazards": {"theirs": 3.0}}}


def test_shift_sensitivity_moves_one_field_each_way_and_rejects_a_bad_scale():
    from experiments.shift_sensitivity import shifts_of
    from safecdt_jax.envs.dynamics import DYNAMICS_FIELDS

    shifts = shifts_of(0.1)
    assert shifts[0] == {} and len(shifts) == 1 + 2 * len(DYNAMICS_FIELDS)
    assert {"gear_scale": 0.9} in shifts and {"mass_scale": 1.1} in shifts
    assert all(len(s) == 1 for s in shifts[1:])
    with pytest.raises(SystemExit, match="--scale must lie in"):
        shifts_of(1.5)


def test_levers_reuse_a_sweep_only_on_the_env_version_it_ran_on(tmp_path):
    import json

    from experiments.levers import reusable

    assert reusable(tmp_path, "CarGoal2") is None  # nothing there yet
    record = {"target_env": envs.env_version("CarGoal2"), "runs": []}
    (tmp_path / "results.json").write_text(json.dumps(record))
    assert reusable(tmp_path, "CarGoal2") == record
    (tmp_path / "results.json").write_text(json.dumps(record | {"target_env": "Car7-Goal2"}))
    assert reusable(tmp_path, "CarGoal2") is None  # older task rules: run again


def test_cached_sweep_runs_once_per_env_version(tmp_path, monkeypatch):
    import json

    import safecdt_jax.deploy.job as job
    from experiments.levers import cached_sweep

    runs = []

    def fake_write(out, result, title):
        out.mkdir(parents=True, exist_ok=True)
        (out / "results.json").write_text(json.dumps(result | {"title": title}))

    def run():
        runs.append(1)
        return {"target_env": envs.env_version("CarGoal2"), "n": len(runs)}

    monkeypatch.setattr(job, "write_results", fake_write)
    first = cached_sweep(tmp_path / "s", "CarGoal2", run, "t")
    assert first["n"] == 1 and first["title"] == "t"
    assert cached_sweep(tmp_path / "s", "CarGoal2", run, "t") == first and len(runs) == 1
    stale = json.loads((tmp_path / "s" / "results.json").read_text()) | {"target_env": "old"}
    (tmp_path / "s" / "results.json").write_text(json.dumps(stale))
    assert cached_sweep(tmp_path / "s", "CarGoal2", run, "t")["n"] == 2  # run again


def test_drive_summary_reads_goals_speed_turn_and_spawn_distance_from_records():
    """Two hand-made episodes of 4 steps: a goal met at step 1, the next goal 1.5 m away on the
    lidar; the velocimeter's y and the gyro's z give the speed and |yaw rate|."""
    from experiments.drive_stats import drive_summary

    n_sensors = 24
    obs = np.zeros((2, 4, n_sensors + 48), np.float32)
    obs[..., 4], obs[..., 8] = 0.5, -0.2
    obs[:, :, n_sensors + 4] = 0.5  # the goal 1.5 m away (3 m range) in lidar bin 4 (90-112 deg)
    actions = np.tile(np.array([[-1.0, 0.0]], np.float32), (2, 4, 1))
    goal_met = np.zeros((2, 4), bool)
    goal_met[0, 1] = True
    s = drive_summary({"obs": obs, "actions": actions, "goal_met": goal_met,
                       "cost": np.array([0.0, 4.0])}, n_sensors)
    assert s["goals"] == 0.5 and s["steps_per_goal"] == 8.0
    assert s["spawn_distance"] == pytest.approx(1.5) and s["goal_distance"] == pytest.approx(1.5)
    assert s["heading_error_deg"] == pytest.approx(11.25)  # bin 4's centre, from body +y
    assert s["speed_plus_y"] == pytest.approx(0.5) and s["abs_yaw_rate"] == pytest.approx(0.2)
    assert s["drive"] == -0.5 and s["abs_turn"] == 0.5 and s["saturated"] == 0.5
    assert s["cost"] == 2.0 and s["median_cost"] == 2.0
    assert "goals" not in drive_summary({"obs": obs, "actions": actions, "goal_met": goal_met,
                                         "cost": np.zeros(2)}, n_sensors, goal_task=False)
    # The Car's torques saturate at 0.02: (-1, 0.01) executes as (-1, 0.5) of the limit.
    nudged = actions + np.float32([0.0, 0.01])
    car = drive_summary({"obs": obs, "actions": nudged, "goal_met": goal_met,
                         "cost": np.zeros(2)}, n_sensors, limit=0.02)
    assert car["drive"] == pytest.approx(-0.25) and car["abs_turn"] == pytest.approx(0.75)


def test_recovery_and_car_fit_scripts_cover_both_travel_directions():
    from experiments.car_fit import PLUS_Y, STEPS, loss, metrics, scripts
    from experiments.drive_stats import recovery_scripts

    rec = recovery_scripts()
    assert len(rec) == 4
    for (name_minus, minus), (name_plus, plus) in zip(rec[::2], rec[1::2], strict=True):
        assert name_minus.endswith("-y") and name_plus.endswith("+y")
        np.testing.assert_array_equal(plus, -minus)
        assert minus.shape == (230, 2) and (minus[:100] > 0).all()  # toward -y first
    names = [name for name, _ in scripts(True)]
    assert names[-1] == "random" and len(names) == len(set(names))
    recoveries = [n for n in names if n.startswith("recovery: ")]
    mirrored = [n for n in names if n.endswith(PLUS_Y) and n not in recoveries]
    assert len(recoveries) == 4 and len(mirrored) == 9
    assert [n for n, _ in scripts()] == [n for n in names if n not in recoveries + mirrored]
    # a recovery row: a 1 rad/s turn (steps 100-130) then 0.2 rad/s left over, at 0.5 m/s
    yaw = np.zeros((len(names) + 1, STEPS))
    yaw[:, 100:130], yaw[:, 135:195] = -1.0, -0.2
    m = metrics(np.full_like(yaw, 0.5), yaw, plus_y=True)
    assert m["recovery: spin, toward +y"] == pytest.approx([1.0, 1.0, 0.2, 0.5])
    assert loss(m, m) == 0.0


def test_car_variants_read_fields_and_fits_and_refuse_an_unknown_field(tmp_path):
    import json

    from experiments.car_variants import fit_variant, main, parse_variant

    assert parse_variant("pyr=friction_cone:pyramidal,sliding:0.9") == (
        "pyr", {"friction_cone": "pyramidal", "sliding": 0.9})
    assert parse_variant("hop=wheel_hop:0.75/11/10") == ("hop", {"wheel_hop": (0.75, 11.0, 10.0)})
    with pytest.raises(SystemExit, match="'grip' is not a CarRobot field"):
        parse_variant("x=grip:1")
    path = tmp_path / "fit.json"
    path.write_text(json.dumps({"constants": {"sliding": 1.0}, "saturation_power": 2.0,
                                "cone": "pyramidal"}))
    assert fit_variant(path) == {"sliding": 1.0, "saturation_power": 2.0,
                                 "friction_cone": "pyramidal"}
    for bad in (["--cells", "middle"], ["--modes", "greedy"]):
        with pytest.raises(SystemExit, match="--cells from source,target"):
            main([*bad, "--out", str(tmp_path / "out.json")])


def test_car_fit_sideways_velocities_are_keyed_weighted_and_optional():
    from experiments.car_fit import LATERAL, LATERAL_WEIGHT, STEPS, loss, metrics, scripts

    n = len(scripts()) + 1
    speed, yaw = np.full((n, STEPS), 0.5), np.zeros((n, STEPS))
    assert not any(k.endswith(LATERAL) for k in metrics(speed, yaw))
    m = metrics(speed, yaw, lateral=np.full((n, STEPS), 0.02))
    sideways = [k for k in m if k.endswith(LATERAL)]
    assert len(sideways) == len(scripts()) - 1  # every script but the random one
    assert m["spin (1, -1)" + LATERAL] == pytest.approx([0.02])
    off = dict(m) | {"spin (1, -1)" + LATERAL: [0.03]}
    assert loss(off, m) == pytest.approx(LATERAL_WEIGHT * 0.01 / np.sqrt(
        sum(len(v) for v in m.values())))


def test_car_sysid_segments_read_heading_and_velocities_from_native_records():
    from experiments.car_sysid import parse_data, segments
    from experiments.drive_stats import GYRO_Z, MAGNETOMETER, VELOCIMETER, heading

    assert parse_data("CarGoal1:25:64,CarCircle1:5:128") == [("CarGoal1", 25.0, 64),
                                                             ("CarCircle1", 5.0, 128)]
    for bad in ("CarGoal1:25", "PointGoal1:25:64"):
        with pytest.raises(SystemExit, match="--data"):
            parse_data(bad)
    steps = 60
    psi = np.linspace(0.0, 12.0, steps)  # two turns round: the heading must unwrap
    obs = np.zeros((2, steps, 40), np.float32)
    obs[..., MAGNETOMETER], obs[..., MAGNETOMETER + 1] = -0.5 * np.sin(psi), -0.5 * np.cos(psi)
    obs[..., VELOCIMETER] = np.arange(steps) * 0.001
    obs[..., VELOCIMETER + 1] = -np.arange(steps) * 0.01
    obs[..., GYRO_Z] = 0.3
    np.testing.assert_allclose(heading(obs)[0], psi, atol=1e-5)
    actions = np.broadcast_to(np.arange(steps, dtype=np.float32)[None, :, None], (2, steps, 2))
    state, acts, target = segments(obs, actions, horizon=4, stride=25)
    starts = [1, 26, 51]
    assert state.shape == (6, 3) and acts.shape == (6, 4, 2) and target.shape == (6, 4, 3)
    np.testing.assert_allclose(state[:3, 1], [-0.01 * t for t in starts], rtol=1e-6)
    assert (state[:, 2] == np.float32(0.3)).all()
    np.testing.assert_array_equal(acts[1, :, 0], [26, 27, 28, 29])  # the actions from the start
    np.testing.assert_allclose(target[1, :, 1], [-0.27, -0.28, -0.29, -0.30], rtol=1e-5)
    dpsi = 12.0 / (steps - 1)
    np.testing.assert_allclose(target[1, :, 2], dpsi * np.arange(1, 5), atol=1e-4)


def test_car_sysid_loss_is_zero_at_the_constants_that_made_the_data():
    from experiments.car_sysid import SEARCHED, _program, current_constants, prediction_loss

    truth = current_constants()
    other = truth.copy()
    other[SEARCHED.index("yaw_scrub")] *= 2
    rng = np.random.default_rng(0)
    state = np.stack([rng.uniform(-0.05, 0.05, 4), rng.uniform(-0.6, 0.6, 4),
                      rng.uniform(-1, 1, 4)], -1).astype(np.float32)
    acts = rng.choice([-1.0, 1.0], size=(4, 3, 2)).astype(np.float32)
    made = np.asarray(_program(SEARCHED)(truth[None].astype(np.float32), state, acts))[0]
    assert np.abs(made[:, -1, 2]).max() > 0.005  # the spin pulses turn the car
    loss = prediction_loss(np.stack([truth, other]), SEARCHED, [(state, acts, made)])
    assert loss.shape == (2, 1) and loss[0, 0] == 0.0 and loss[1, 0] > 1e-4
    # the lateral term: the error of the mean sideways velocity over every step, weighted
    drifted = made + np.array([0.01, 0.0, 0.0], np.float32)
    plain, weighted = (prediction_loss(truth[None], SEARCHED, [(state, acts, drifted)],
                                       lateral_weight=w)[0, 0] for w in (0.0, 5.0))
    assert weighted - plain == pytest.approx(0.05, rel=1e-3)


def test_car_sysid_pulse_response_signs_spin_pulses_by_direction_and_skips_the_rest():
    from experiments.car_sysid import pulse_response

    n = 40
    state = np.zeros((n, 3), np.float32)
    state[:10, 1], state[10:20, 1], state[30:, 1] = 0.5, -0.5, 0.5
    acts = np.zeros((n, 2, 2), np.float32)
    acts[:20, 0] = [1.0, -1.0]  # a spin pulse (past the 0.02 torque clip)
    acts[20:30, 0] = [-0.02, 0.02]  # the other way, from rest
    acts[30:, 0] = [1.0, 1.0]  # straight: not a pulse
    turn = np.where(np.arange(n) < 20, 0.1, -0.2).astype(np.float32)
    turn[30:] = 5.0
    out = pulse_response(state, acts, turn)
    assert out == pytest.approx({"toward +y": 0.1, "toward -y": 0.1, "near rest": 0.2})
    assert np.isnan(pulse_response(state[:5], acts[:5], turn[:5])["toward -y"])


def test_circle_positions_come_back_from_the_lidar_and_magnetometer_and_laps_count_entries():
    import jax

    from experiments.drive_stats import circle_positions, lap_summary
    from safecdt_jax.envs.rollout import scan_episode, uniform_policy

    env, params = envs.make("CarCircle1")
    _, (obs, xy) = scan_episode(env, params, jax.random.PRNGKey(3), uniform_policy,
                                lambda s: (s.obs, s.data.qpos[:2]), 40)
    x, y = circle_positions(np.asarray(obs)[None], env.robot.n_sensors)
    np.testing.assert_allclose(np.stack([x[0], y[0]], -1), np.asarray(xy), atol=2e-3)
    # a synthetic episode: one crossing of the wall at x = 1.125, 3 steps beyond it
    xs = np.array([[1.0, 1.1, 1.15, 1.2, 1.15, 1.1, 1.0]])
    lidar_obs = np.zeros((1, 7, env.robot.n_sensors + 16), np.float32)
    lidar_obs[..., 10] = -0.5  # heading 0: the magnetometer reads (0, -0.5)
    lidar_obs[..., env.robot.n_sensors + 8] = 1.0 - xs / 6.0  # the origin straight behind
    laps = lap_summary(lidar_obs, env.robot.n_sensors, 1.125, env.dt)
    assert env.dt == pytest.approx(0.04)
    assert laps["steps_beyond"] == 3 and laps["wall_entries"] == 1
    assert laps["entry_speed"] == pytest.approx(0.05 / 0.04, rel=1e-3)
    assert laps["net_heading_rate"] == 0.0 and np.isnan(laps["curving_radius"])
    # a quarter circle of radius 2 at 0.5 m/s, heading along the path: curving radius 2
    from experiments.drive_stats import curvature

    t = np.arange(201) * 0.04
    psi = 0.5 / 2 * t
    arc = curvature(2 * np.sin(psi)[None], (2 - 2 * np.cos(psi))[None], psi[None], 0.04)
    assert arc["path_speed"] == pytest.approx(0.5, rel=1e-3)
    assert arc["curving_radius"] == pytest.approx(2.0, rel=1e-3)
    assert laps["median_max_abs_x"] == pytest.approx(1.2, rel=1e-5)


def test_wheel_hop_summary_counts_the_lifted_substeps_against_the_lead():
    from experiments.wheel_hop import BEFORE, COLUMNS, PULSE, summary

    n = (BEFORE + len(PULSE)) * 10
    sub = np.zeros((2, n, len(COLUMNS)))
    col = {c: i for i, c in enumerate(COLUMNS)}
    sub[..., col["load_right"]] = 0.08
    sub[:, 3, col["load_right"]] = 0.0  # one lifted substep while driving straight
    start = BEFORE * 10
    sub[0, start + 1:start + 16, col["load_right"]] = 0.0  # 15 and 5 substeps off the ground
    sub[1, start + 1:start + 6, col["load_right"]] = 0.0
    sub[:, start, col["load_right"]] = 0.6  # the flip's spike
    sub[:, start:, col["yaw_rate"]] = np.linspace(0.8, 0.0, n - start)
    sub[:, :, col["height"]] = 0.1
    sub[:, start + 4, col["height"]] = 0.1025
    out = summary(sub)
    assert out["right_wheel_unloaded_substeps"] == 10.0
    assert out["right_wheel_unloaded_substeps_before"] == 1.0
    assert out["right_wheel_peak_load"] == pytest.approx(0.6)
    assert out["yaw_first_substep"] == pytest.approx(0.8)
    assert len(out["yaw_step_end"]) == len(PULSE) and out["rise_mm"] == pytest.approx(2.5)
