"""The Goal task: reach goals that re-appear, avoid hazard discs and (level 2) leave vases alone."""

import dataclasses

import jax
import jax.numpy as jnp

from safecdt_jax.envs.geometry import N_LIDAR_BINS, place, place_all, pseudo_lidar, rot2
from safecdt_jax.envs.protocols import RobotLike
from safecdt_jax.envs.robots import GRAVITY
from safecdt_jax.envs.types import MAX_HAZARDS, MAX_VASES, EnvParams

GOAL_RADIUS = 0.3  # m: reached when the agent origin is this close
GOAL_KEEPOUT = 0.305
HAZARD_RADIUS = 0.2  # m: cost when the agent origin is inside
HAZARD_KEEPOUT = 0.18
VASE_KEEPOUT = 0.15
VASE_RADIUS = 0.1  # m: the 0.2 m vase cube as a disc (its inscribed circle)
VASE_SPEED_COST = 1e-4  # m/s: a vase moving at least this fast costs (level 2)
# A pushed vase in Safety-Gymnasium is a 8e-6 kg box on MuJoCo's soft contacts: it is knocked
# ahead of the robot rather than carried, and keeps moving (costing) long after Coulomb
# friction would have stopped it. Two effective constants per robot, (e, n): a vase leaves at
# (1 + e) times the robot's closing speed, and its speed decays no faster than by exp(-1 / n)
# per env step. Per env step, not per second: the Car's world runs at a 0.004 s timestep, the
# Point's at 0.002 s, and the fits agree better in steps than in seconds. Per robot because e
# stands for how soon the robot's body and the box part, which a disc pushed by circles cannot
# model: the Car's box chassis and bumpers shed a vase sooner than the Point's sphere. Fitted to
# native cost steps per term (contact, velocity) of each robot's limit-25 Goal1 expert in its
# level-2 task (experiments.vase_fit and sim2sim, 2026-12-07: ratios native / ours, mean action
# and sampled, 0.94 / 0.93 contact and 0.92 / 1.04 velocity for the Car; 0.97-1.48 and 0.96-1.34
# for the Point). e > 1 is not a physical coefficient: the box also tips and spins.
VASE_PUSH = {"Car": (1.5, 2.0), "Point": (1.0, 2.5)}  # robot name -> (e, n env steps)
LIDAR_RANGE = 3.0  # m
GOAL_BONUS = 1.0


@dataclasses.dataclass(frozen=True)
class GoalTask:
    """Goal1/Goal2 logic on top of a robot; the level lives in EnvParams."""

    episode_length: int = 1000

    def observation_size(self, robot: RobotLike) -> int:
        """Sensors then goal, hazards and vases lidars (16 bins each)."""
        return robot.n_sensors + 3 * N_LIDAR_BINS

    def cost_terms(self) -> tuple[str, ...]:
        """Names of the per-term cost indicators reported in `info`."""
        return ("cost_hazards", "cost_vases_contact", "cost_vases_velocity")

    def reset(self, key: jax.Array, params: EnvParams, robot: RobotLike):
        """Samples a layout: agent, goal, hazards, vases with keepouts; then re-samples the goal.

        Returns (agent_xy [2], yaw, task dict).
        """
        k_layout, k_yaw, k_goal = jax.random.split(key, 3)
        keepouts = jnp.concatenate([
            jnp.array([robot.keepout, GOAL_KEEPOUT]),
            jnp.full(MAX_HAZARDS, HAZARD_KEEPOUT), jnp.full(MAX_VASES, VASE_KEEPOUT)])
        active = jnp.concatenate([jnp.ones(2), params.hazard_mask, params.vase_mask])
        pos = place_all(k_layout, params.extent, keepouts, active)
        agent = pos[0]
        hazards = pos[2:2 + MAX_HAZARDS]
        vases = pos[2 + MAX_HAZARDS:]
        yaw = jax.random.uniform(k_yaw, (), maxval=2 * jnp.pi)
        task = {"hazards": hazards, "vases": vases, "vase_vel": jnp.zeros((MAX_VASES, 2))}
        goal = self._resample_goal(k_goal, params, robot, agent, task)
        task["goal"] = goal
        task["last_dist"] = jnp.linalg.norm(agent - goal)
        return agent, yaw, task

    def _resample_goal(self, key, params, robot, agent, task) -> jax.Array:
        """A new goal in the extent shrunk by its keepout, clear of the agent and every object."""
        others = jnp.concatenate([agent[None], task["hazards"], task["vases"]])
        keepouts = jnp.concatenate([jnp.array([robot.keepout]), jnp.full(MAX_HAZARDS,
                                   HAZARD_KEEPOUT), jnp.full(MAX_VASES, VASE_KEEPOUT)])
        mask = jnp.concatenate([jnp.ones(1), params.hazard_mask, params.vase_mask])
        return place(key, params.extent, GOAL_KEEPOUT, others, keepouts, mask)

    def _push_vases(self, params, robot, data, task, dt):
        """Moves vases pushed by the robot, then lets them slide to rest on the floor.

        Vases weigh 8e-6 kg against the robot's 5e-3 to 3e-2 kg, so the robot pushes them without
        feeling them: a vase overlapping a robot circle is moved out along the contact normal and
        leaves at (1 + e) times the robot's closing speed there; floor friction then slows it
        by mu g, but never faster than by exp(-1 / n) per env step, (e, n) = `VASE_PUSH[robot]`
        (`dt` seconds), so a pushed vase keeps moving (and costing) after contact as in MuJoCo.
        Vases do not collide with each other (documented deviation). Returns (task, contact).
        """
        restitution, creep_steps = VASE_PUSH[robot.name]
        xy, yaw, vel, omega = data.qpos[:2], data.qpos[2], data.qvel[:2], data.qvel[2]
        circles = jnp.array(robot.circles)
        centres = xy + circles[:, :2] @ rot2(yaw).T
        c_vel = vel + omega * jnp.stack([-(centres - xy)[:, 1], (centres - xy)[:, 0]], -1)
        delta = task["vases"][:, None, :] - centres[None, :, :]  # [V, C, 2]
        dist = jnp.linalg.norm(delta, axis=-1)
        normal = delta / jnp.maximum(dist, 1e-9)[..., None]
        pen = (circles[None, :, 2] + VASE_RADIUS - dist) * params.vase_mask[:, None]
        # Each vase is pushed by the robot circle it overlaps most: two overlapping circles
        # along one normal must not hand it the robot's speed twice.
        rows = jnp.arange(pen.shape[0])
        deepest = jnp.argmax(pen, axis=1)
        pen, normal, c_vel = pen[rows, deepest], normal[rows, deepest], c_vel[deepest]
        touching = pen > 0
        pos = task["vases"] + jnp.where(touching, pen, 0.0)[:, None] * normal
        v_push = jnp.sum(c_vel * normal, axis=-1)  # the robot's speed along the normal
        v_vase = task["vase_vel"]
        gap = jnp.maximum(v_push - jnp.sum(v_vase * normal, axis=-1), 0.0)
        kick = (1.0 + restitution) * jnp.where(touching, gap, 0.0)
        v_vase = v_vase + kick[:, None] * normal
        speed = jnp.linalg.norm(v_vase, axis=-1)
        coulomb = speed - GRAVITY * params.friction_scale * dt
        slow = jnp.maximum(coulomb, speed * jnp.exp(-1.0 / creep_steps))
        v_vase = v_vase * (slow / jnp.maximum(speed, 1e-12))[:, None]
        pos = pos + v_vase * dt
        return {**task, "vases": pos, "vase_vel": v_vase}, jnp.any(touching)

    def step(self, key, params: EnvParams, robot: RobotLike, data, task: dict, dt: float):
        """Reward, cost terms and the next task state after a physics step of `dt` seconds."""
        task, contact = self._push_vases(params, robot, data, task, dt)
        agent = data.qpos[:2]
        dist = jnp.linalg.norm(agent - task["goal"])
        goal_met = dist <= GOAL_RADIUS
        reward = task["last_dist"] - dist + GOAL_BONUS * goal_met
        new_goal = self._resample_goal(key, params, robot, agent, task)
        goal = jnp.where(goal_met, new_goal, task["goal"])
        # After a re-sample the distance baseline moves with the goal: no reward jump.
        task = {**task, "goal": goal, "last_dist": jnp.linalg.norm(agent - goal)}
        hz_dist = jnp.linalg.norm(task["hazards"] - agent, axis=-1)
        in_hazard = jnp.any((hz_dist <= HAZARD_RADIUS) & (params.hazard_mask > 0))
        moving = jnp.linalg.norm(task["vase_vel"], axis=-1) >= VASE_SPEED_COST
        moving = jnp.any(moving & (params.vase_mask > 0))
        costs = {
            "cost_hazards": in_hazard.astype(jnp.float32),
            "cost_vases_contact": (contact * params.vases_constrained).astype(jnp.float32),
            "cost_vases_velocity": (moving * params.vases_constrained).astype(jnp.float32),
        }
        return jnp.clip(reward, -10.0, 10.0), costs, goal_met.astype(jnp.float32), task

    def observe(self, params: EnvParams, data, task: dict) -> jax.Array:
        """Goal, hazards and vases lidars [48] (range 3 m), objects at live positions."""
        xy, yaw = data.qpos[:2], data.qpos[2]
        goal = pseudo_lidar(task["goal"][None], jnp.ones(1), xy, yaw, LIDAR_RANGE)
        hz = pseudo_lidar(task["hazards"], params.hazard_mask, xy, yaw, LIDAR_RANGE)
        vs = pseudo_lidar(task["vases"], params.vase_mask, xy, yaw, LIDAR_RANGE)
        return jnp.concatenate([goal, hz, vs])


def goal_params(level: int) -> EnvParams:
    """Safety-Gymnasium's Goal level 1 (8 hazards, 1 free vase, [-1.5, 1.5]^2) or level 2
    (10 hazards, 10 constrained vases, [-2, 2]^2)."""
    if level == 1:
        return EnvParams(extent=jnp.float32(1.5), hazard_mask=_first(8, MAX_HAZARDS),
                         vase_mask=_first(1, MAX_VASES), vases_constrained=jnp.float32(0.0))
    return EnvParams(extent=jnp.float32(2.0), hazard_mask=_first(10, MAX_HAZARDS),
                     vase_mask=_first(10, MAX_VASES), vases_constrained=jnp.float32(1.0))


def _first(n: int, size: int) -> jax.Array:
    return (jnp.arange(size) < n).astype(jnp.float32)


