"""Task semantics: rewards, costs, goal re-sampling, lidar, layouts, vases, level difficulty."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from env_helpers import batch_episodes, jitted

from safecdt_jax import envs
from safecdt_jax.envs.geometry import pseudo_lidar
from safecdt_jax.envs.goal import (
    GOAL_KEEPOUT,
    HAZARD_KEEPOUT,
    VASE_KEEPOUT,
    VASE_PUSH,
    VASE_RADIUS,
    VASE_SPEED_COST,
)
from safecdt_jax.envs.robots import GRAVITY


def _reset(name, key=0):
    env, params = envs.make(name)
    reset, step = jitted(name)
    return env, params, reset(jax.random.PRNGKey(key), params), step


def test_hazard_cost_inside_not_outside():
    _env, params, s, step = _reset("PointGoal1")
    agent = s.data.qpos[:2]
    inside = s.replace(task={**s.task, "hazards": s.task["hazards"].at[0].set(agent + 0.1)})
    outside = s.replace(task={**s.task, "hazards": s.task["hazards"].at[0].set(agent + 0.25)})
    assert float(step(inside, jnp.zeros(2), params).cost) == 1.0
    assert float(step(inside, jnp.zeros(2), params).info["cost_hazards"]) == 1.0
    assert float(step(outside, jnp.zeros(2), params).cost) == 0.0
    # an inactive hazard slot never costs
    off = params.replace(hazard_mask=params.hazard_mask.at[0].set(0.0))
    assert float(step(inside, jnp.zeros(2), off).cost) == 0.0


@pytest.mark.parametrize("key", range(4))
def test_goal_bonus_and_resampling_with_keepouts(key):
    _env, params, s, step = _reset("CarGoal2", key)
    agent = s.data.qpos[:2]
    s = s.replace(task={**s.task, "goal": agent + jnp.array([0.2, 0.0]), "last_dist": 0.2})
    n = step(s, jnp.zeros(2), params)
    assert float(n.info["goal_met"]) == 1.0
    assert float(n.reward) == pytest.approx(1.0 + 0.2 - 0.2, abs=1e-4)  # bonus + shaping
    goal, agent = np.asarray(n.task["goal"]), np.asarray(n.data.qpos[:2])
    assert np.linalg.norm(goal - agent) >= 0.4 + GOAL_KEEPOUT - 1e-6
    hz = np.asarray(n.task["hazards"])[np.asarray(params.hazard_mask) > 0]
    assert np.linalg.norm(hz - goal, axis=1).min() >= HAZARD_KEEPOUT + GOAL_KEEPOUT - 1e-6
    vs = np.asarray(n.task["vases"])[np.asarray(params.vase_mask) > 0]
    assert np.linalg.norm(vs - goal, axis=1).min() >= VASE_KEEPOUT + GOAL_KEEPOUT - 1e-6
    assert np.abs(goal).max() <= float(params.extent) - GOAL_KEEPOUT
    assert float(n.task["last_dist"]) == pytest.approx(np.linalg.norm(goal - agent), rel=1e-5)
    # the next step's reward is only shaping again: no jump from the moved goal
    assert abs(float(step(n, jnp.zeros(2), params).reward)) < 0.05


def test_goal_shaping_is_distance_decrease():
    _env, params, s, step = _reset("PointGoal1", 3)
    n = step(s, jnp.array([1.0, 0.0]), params)
    d0 = np.linalg.norm(np.asarray(s.task["goal"] - s.data.qpos[:2]))
    d1 = np.linalg.norm(np.asarray(n.task["goal"] - n.data.qpos[:2]))
    assert float(n.reward) == pytest.approx(d0 - d1, abs=1e-5)


def test_circle_reward_formula_and_boundaries():
    env, p1 = envs.make("CarCircle1")
    _, p2 = envs.make("CarCircle2")
    _, _, s, _ = _reset("CarCircle1")
    x, y, u, v = 1.0, 0.5, -0.2, 0.4
    data = s.data.replace(qpos=jnp.array([x, y, 0.3]), qvel=jnp.array([u, v, 0.0]))
    reward, costs, _, _ = env.task.step(None, p1, env.robot, data, {}, env.dt)
    rho = np.hypot(x, y)
    assert float(reward) == pytest.approx(0.1 * ((-u * y + v * x) / rho) / (1 + abs(rho - 1.5)),
                                          rel=1e-5)
    assert float(costs["cost_out_of_boundary"]) == 0.0
    out_y = data.replace(qpos=jnp.array([0.0, 1.3, 0.0]))
    assert float(env.task.step(None, p1, env.robot, out_y, {}, env.dt)[1][
        "cost_out_of_boundary"]) == 0.0
    assert float(env.task.step(None, p2, env.robot, out_y, {}, env.dt)[1][
        "cost_out_of_boundary"]) == 1.0
    out_x = data.replace(qpos=jnp.array([-1.2, 0.0, 0.0]))
    for p in (p1, p2):
        assert float(env.task.step(None, p, env.robot, out_x, {}, env.dt)[1][
            "cost_out_of_boundary"]) == 1.0


def test_lidar_values_at_hand_set_layout():
    agent, yaw = jnp.zeros(2), jnp.float32(np.pi / 2)  # facing world +y
    width = 2 * np.pi / 16
    # straight ahead (world +y = body +x) at 1.5 m with range 3: 0.5 in bin 0, aliased fully
    # into bin 15 (frac 0) and not into bin 1
    ahead = pseudo_lidar(jnp.array([[0.0, 1.5]]), jnp.ones(1), agent, yaw, 3.0)
    expected = np.zeros(16)
    expected[0], expected[15] = 0.5, 0.5
    np.testing.assert_allclose(ahead, expected, atol=1e-6)
    # at the centre of bin 4 (body angle 4.5 bin widths), 1 m away, range 2: 0.5 and 0.25 beside
    ang = yaw + 4.5 * width
    pt = jnp.array([[jnp.cos(ang), jnp.sin(ang)]])
    mid = pseudo_lidar(pt, jnp.ones(1), agent, yaw, 2.0)
    expected = np.zeros(16)
    expected[4], expected[3], expected[5] = 0.5, 0.25, 0.25
    np.testing.assert_allclose(mid, expected, atol=1e-5)
    # two objects in one bin keep the max; masked and out-of-range objects read nothing
    both = pseudo_lidar(jnp.array([[0.0, 1.5], [0.0, 0.3], [0.0, 0.1]]),
                        jnp.array([1.0, 1.0, 0.0]), agent, yaw, 3.0)
    assert float(both[0]) == pytest.approx(0.9, abs=1e-6)
    far = pseudo_lidar(jnp.array([[5.0, 0.0]]), jnp.ones(1), agent, yaw, 3.0)
    assert float(far.max()) == 0.0


def test_observation_blocks_point_at_objects():
    _env, _params, s, _ = _reset("PointGoal2", 1)
    obs = np.asarray(s.obs)
    goal_lidar, hz_lidar, vase_lidar = obs[12:28], obs[28:44], obs[44:60]
    d_goal = np.linalg.norm(np.asarray(s.task["goal"] - s.data.qpos[:2]))
    assert goal_lidar.max() == pytest.approx(max(0.0, 3.0 - d_goal) / 3.0, abs=1e-5)
    assert hz_lidar.max() > 0 and vase_lidar.max() > 0


@pytest.mark.parametrize("name", ["PointGoal1", "CarGoal2"])
def test_layouts_respect_keepouts_and_never_start_in_cost(name):
    env, params = envs.make(name)
    states = jax.jit(jax.vmap(env.reset, (0, None)))(jax.random.split(jax.random.PRNGKey(9), 64),
                                                     params)
    hz_on, vs_on = np.asarray(params.hazard_mask) > 0, np.asarray(params.vase_mask) > 0
    for i in range(64):
        pts = [np.asarray(states.data.qpos[i, :2])[None], np.asarray(states.task["goal"][i])[None],
               np.asarray(states.task["hazards"][i])[hz_on], np.asarray(states.task["vases"][i])[
                   vs_on]]
        keep = np.concatenate([[0.4], [GOAL_KEEPOUT], np.full(hz_on.sum(), HAZARD_KEEPOUT),
                               np.full(vs_on.sum(), VASE_KEEPOUT)])
        pts = np.concatenate(pts)
        gap = np.linalg.norm(pts[:, None] - pts[None], axis=-1) - (keep[:, None] + keep[None])
        np.fill_diagonal(gap, 0.0)
        assert gap.min() >= -1e-5, f"layout {i} violates a keepout by {-gap.min():.3f} m"
        assert np.abs(pts).max() <= float(params.extent) + 1e-6
    assert float(np.asarray(states.cost).max()) == 0.0


def test_pushing_a_vase_costs_in_level_2_only():
    for level, expected in ((1, 0.0), (2, 1.0)):
        _env, params = envs.make(f"PointGoal{level}")
        reset, step = jitted("PointGoal1")
        s = reset(jax.random.PRNGKey(0), params)
        agent, yaw = s.data.qpos[:2], s.data.qpos[2]
        ahead = agent + 0.22 * jnp.array([jnp.cos(yaw), jnp.sin(yaw)])
        s = s.replace(task={**s.task, "vases": s.task["vases"].at[0].set(ahead)})
        moved, costs = s, []
        for _ in range(15):
            moved = step(moved, jnp.array([1.0, 0.0]), params)
            costs.append(float(moved.cost))
        assert np.linalg.norm(np.asarray(moved.task["vases"][0] - ahead)) > 0.01  # pushed
        assert max(costs) == expected


@pytest.mark.parametrize("name", ["CarGoal2", "PointGoal2"])
def test_released_vase_slides_then_creeps_and_costs_while_above_the_threshold(name):
    # A vase sliding at 0.5 m/s, far from the robot: Coulomb friction (mu g) slows it while
    # that is the slower decay, then the soft-contact creep, exp(-1 / n) per step; it costs on
    # every step its speed is still >= 1e-4 m/s (Safety-Gymnasium's velocity threshold).
    env, params, s, _ = _reset(name)
    creep_steps = VASE_PUSH[env.robot.name][1]
    far = s.data.qpos[:2] + jnp.array([1.0, 1.0]) * 3.0
    task = {**s.task, "vases": s.task["vases"].at[0].set(far),
            "vase_vel": s.task["vase_vel"].at[0].set(jnp.array([0.5, 0.0]))}
    speed, expected_speeds, costs = 0.5, [], []
    for _ in range(40):
        speed = max(speed - GRAVITY * env.dt, speed * np.exp(-1 / creep_steps))
        expected_speeds.append(speed)
        _, terms, _, task = env.task.step(jax.random.PRNGKey(0), params, env.robot, s.data,
                                          task, env.dt)
        costs.append(float(terms["cost_vases_velocity"]))
        assert float(jnp.linalg.norm(task["vase_vel"][0])) == pytest.approx(speed, rel=1e-4)
    expected = [float(v >= VASE_SPEED_COST) for v in expected_speeds]
    assert costs == expected and 0 < sum(costs) < 40
    assert float(terms["cost_vases_contact"]) == 0.0


@pytest.mark.parametrize("name", ["CarGoal2", "PointGoal2"])
def test_robot_kicks_a_vase_ahead_at_one_plus_restitution_times_its_speed(name):
    # The robot, heading 0 and moving at 0.5 m/s along +x, meets a vase just overlapping its
    # outline circle that reaches farthest along +x: the vase takes (1 + e) times the closing
    # speed, then decays (Coulomb or creep, whichever is slower), with the robot's own (e, n).
    env, params, s, _ = _reset(name)
    restitution, creep_steps = VASE_PUSH[env.robot.name]
    assert (restitution, creep_steps) == {"Car": (1.5, 2.0), "Point": (1.0, 2.5)}[env.robot.name]
    qpos = s.data.qpos.at[:3].set(0.0)
    data = s.data.replace(qpos=qpos, qvel=jnp.zeros_like(s.data.qvel).at[0].set(0.5))
    circles = np.asarray(env.robot.circles)
    front = circles[np.argmax(circles[:, 0] + circles[:, 2])]  # body frame = world frame here
    centre = front[:2] + np.array([front[2] + VASE_RADIUS - 0.01, 0.0])  # 1 cm overlap
    task = {**s.task, "vases": s.task["vases"].at[0].set(jnp.asarray(centre)),
            "vase_vel": jnp.zeros_like(s.task["vase_vel"])}
    _, terms, _, task = env.task.step(jax.random.PRNGKey(0), params, env.robot, data, task,
                                      env.dt)
    kicked = (1 + restitution) * 0.5
    speed = max(kicked - GRAVITY * env.dt, kicked * np.exp(-1 / creep_steps))
    np.testing.assert_allclose(np.asarray(task["vase_vel"][0]), [speed, 0.0], atol=1e-5)
    assert float(terms["cost_vases_contact"]) == 1.0
    assert float(terms["cost_vases_velocity"]) == 1.0


def test_circle_boundary_just_inside_and_just_outside():
    env, p2 = envs.make("PointCircle2")
    _, _, s, _ = _reset("PointCircle2")
    for x, y, cost in ((1.124, 0.0, 0.0), (1.126, 0.0, 1.0), (0.0, -1.124, 0.0),
                       (0.0, -1.126, 1.0), (1.124, 1.124, 0.0), (-1.126, 1.124, 1.0)):
        data = s.data.replace(qpos=jnp.array([x, y, 0.0]))
        terms = env.task.step(None, p2, env.robot, data, {}, env.dt)[1]
        assert float(terms["cost_out_of_boundary"]) == cost, (x, y)


@pytest.mark.slow
@pytest.mark.parametrize("task", ["CarGoal", "CarCircle", "PointCircle"])
def test_random_policy_costs_more_on_level_2(task):
    # Random-policy costs are heavy-tailed (a robot parked in a hazard costs every step), so a
    # batch of episodes is compared; both levels see the same keys.
    keys = jax.random.split(jax.random.PRNGKey(11), 128)
    env, p1 = envs.make(task + "1")
    _, p2 = envs.make(task + "2")
    run = batch_episodes(task + "1", env.episode_length)
    c1, c2 = np.asarray(run(keys, p1)["cost"]), np.asarray(run(keys, p2)["cost"])
    assert c2.mean() > c1.mean(), f"level-2 cost {c2.mean():.1f} <= {c1.mean():.1f}"
    assert (c2 > 0).mean() > (c1 > 0).mean()  # more episodes pay any cost on level 2
