"""Scripted behaviour policies with privileged state: the families that produce the offline data.

Each task has one policy family: a pure function `policy(knobs, state, spent, key) -> action`
steered by a few continuous knobs drawn once per episode (`sample_knobs`). Every episode has a
cost `budget` and a `spread`: the budget is meant to be spent on a schedule that rises linearly
to all of it at `spread` of the episode (`schedule`; by default spread 1, a constant pace). The
robot is *reckless* while behind its schedule: on Circle it runs a wide circle through the
walls, on Goal it drives straight for the goal through whatever lies in the way, both at full
agility. Otherwise it is *careful*: it avoids the costly regions and drives slower. Paced this
way, an episode's share of reckless steps is set by its cost rate, which its cost-to-go reveals
at every step (about rate x steps left), as in data of policies trained under different cost
limits; a budget spent early would instead leave most steps with a cost-to-go of 0 and let the
model pick its mode from the return target. The Point on Circle is graded instead of switched
(`CircleFamily.full_rate`): one reckless excursion of it costs about 60, more than most
budgets. Budgets of 0 give careful episodes, and the other knobs (speed, steering gain,
look-ahead, noise, avoidance strength and clearance, caution, target circle radius) spread the
returns at every cost.

Policies read the true pose (`state.data.qpos[:3]`, `qvel[:2]`) and the task layout
(`state.task`), never the observation, plus `spent`, the episode's cost so far (the collector
keeps it). They compute a desired planar direction of travel, then a forward and a turn command
in robot-independent units (fractions of top thrust and of top yaw rate) that `actuate` maps to
each robot's actuators: the Point's thrust and yaw servo, the Car's two wheels.

Units: metres, seconds, radians; costs in cost steps; actions in the env's [-1, 1]^2 box.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp

from safecdt_jax import envs
from safecdt_jax.envs.goal import HAZARD_RADIUS, VASE_RADIUS
from safecdt_jax.envs.types import EnvParams, State

Knobs = dict[str, jax.Array]  # knob name -> scalar (one episode) or [n] (n episodes)
# (knobs, state, spent: the episode's cost so far, key) -> action [2]
Policy = Callable[[Knobs, State, jax.Array, jax.Array], jax.Array]
Range = tuple[float, float]


# --- robots: pose and actuation -------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Drive:
    """How a robot turns (forward, turn) commands into its two actuator inputs.

    Attributes:
      heading_offset: rad, the direction of travel in the body frame (Point +x: 0; Car -y: -pi/2).
      max_yaw_rate: rad/s at full turn command (Point servo at a1 = 1: 3.0; Car at wheels
        (1, -1): 1.26); converts a desired yaw rate into a turn command.
      saturation: action magnitudes beyond which the actuators saturate (Point thrust 0.05,
        Car wheel torque 0.02; the Point's yaw servo uses its whole [-1, 1]). Commands map into
        the linear range, so equal commands have equal effects and the data hold no dead zone.
      reverse: whether the forward command may go negative (the Point brakes with reverse thrust;
        the Car turns in place instead).
      differential: whether the two actions are wheels (Car) rather than thrust and yaw (Point).
    """

    heading_offset: float
    max_yaw_rate: float
    saturation: tuple[float, float]
    reverse: bool
    differential: bool


POINT_DRIVE = Drive(heading_offset=0.0, max_yaw_rate=3.0, saturation=(0.05, 1.0), reverse=True,
                    differential=False)
CAR_DRIVE = Drive(heading_offset=-jnp.pi / 2, max_yaw_rate=1.26, saturation=(0.02, 0.02),
                  reverse=False, differential=True)


def robot_drive(task: str) -> Drive:
    """The `Drive` of the robot in a task name ('Car...' or 'Point...')."""
    return CAR_DRIVE if task.startswith("Car") else POINT_DRIVE


def pose(drive: Drive, state: State) -> tuple[jax.Array, jax.Array, jax.Array]:
    """World position [2] (m), heading of travel (rad) and world velocity [2] (m/s)."""
    qpos, qvel = state.data.qpos, state.data.qvel
    return qpos[:2], qpos[2] + drive.heading_offset, qvel[:2]


def actuate(drive: Drive, forward: jax.Array, turn: jax.Array) -> jax.Array:
    """Actions [2] for a forward and a turn command, both clipped to [-1, 1].

    `forward` is a fraction of top thrust (Point) or wheel torque (Car); `turn` a fraction of the
    top yaw rate, positive counter-clockwise. Point: (thrust, yaw servo). Car, a differential
    drive: action 0 drives the wheel at body x = -0.13, action 1 the one at x = +0.13. The Car
    travels toward body -y, so action 0 is its right wheel and action 1 its left one, and a
    left (counter-clockwise) turn needs action 0 > action 1. The forward command yields to the
    turn, so no wheel saturates and the turn is never lost.
    """
    forward, turn = jnp.clip(forward, -1.0, 1.0), jnp.clip(turn, -1.0, 1.0)
    if drive.differential:
        room = 1.0 - jnp.abs(turn)
        forward = jnp.clip(forward, -room, room)
        u = jnp.stack([forward + turn, forward - turn])
    else:
        u = jnp.stack([forward, turn])
    return u * jnp.asarray(drive.saturation, jnp.float32)


def steer(drive: Drive, heading: jax.Array, desired: jax.Array, speed: jax.Array,
          turn_gain: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(forward, turn) commands that point the robot along the world direction `desired` [2].

    The turn asks for a yaw rate of `turn_gain` (1/s) times the heading error (rad); the forward
    command is `speed * cos(error)`, so the robot slows while it turns toward a target behind it
    (the Point brakes: its momentum would otherwise carry it ~0.75 m at top speed).
    """
    error = _wrap(jnp.arctan2(desired[1], desired[0]) - heading)
    turn = turn_gain * error / drive.max_yaw_rate
    align = jnp.cos(error)
    forward = speed * (align if drive.reverse else jnp.maximum(align, 0.0))
    return forward, turn


def _wrap(angle: jax.Array) -> jax.Array:
    """Angle wrapped into [-pi, pi)."""
    return jnp.mod(angle + jnp.pi, 2 * jnp.pi) - jnp.pi


def _unit(v: jax.Array) -> jax.Array:
    return v / jnp.maximum(jnp.linalg.norm(v, axis=-1, keepdims=True), 1e-6)


def _noisy(forward, turn, noise, key):
    eps = noise * jax.random.normal(key, (2,))
    return forward + eps[0], turn + eps[1]


# --- knob families ----------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class GoalFamily:
    """Knob ranges of the Goal family. Each ranged knob is uniform in its range per episode,
    except `budget` (see `p_careful`).

    Attributes:
      speed: forward command, fraction of top speed (Point ~1.5 m/s, Car ~0.7 m/s).
      turn_gain: 1/s, commanded yaw rate per radian of heading error.
      lookahead: s, the robot steers from its position extrapolated this far ahead (anticipates
        drift, mostly the Point's).
      noise: std of Gaussian noise on the (forward, turn) commands, every step.
      budget: cost steps the episode may spend recklessly; 0 with probability `p_careful`, else
        skewed toward the low end (see `sample_knobs`).
      spread: fraction of the episode over which the budget is scheduled (see `schedule`); 1,
        a constant pace, by default. While behind the schedule the robot is reckless: straight
        for the goal at full agility, through any hazard on the way. (Collector v3 also
        detoured through hazards to keep up with the schedule; a CDT trained on that data
        averaged the goal and the hazard directions and reached no goal: return ~0.)
      avoid: careful: weight of the avoidance field against the unit pull toward the goal (at
        least 1, so that at full strength the field never points into an obstacle).
      clearance: careful: m beyond an obstacle's edge where avoidance starts; it reaches full
        strength `ramp` closer, so small clearances graze hazards, large ones keep well clear.
      caution: careful: fraction of speed and of turn rate shed; half of the remaining speed is
        shed too near an obstacle, linearly from `zone` away to its edge (inside one it leaves
        at full agility by the shortest way). Careful drivers are slower
        drivers: in an open layout avoidance alone costs no return, so this is what makes
        safety cost return.
      p_careful: probability of a careful episode (budget 0).
      ramp: m, see `clearance`. zone: m, see `caution` (constants, not drawn).
    """

    speed: Range = (0.25, 1.0)
    turn_gain: Range = (2.0, 8.0)
    lookahead: Range = (0.0, 0.4)
    noise: Range = (0.0, 0.5)
    budget: Range = (2.0, 120.0)
    spread: Range = (1.0, 1.0)
    avoid: Range = (1.0, 2.5)
    clearance: Range = (-0.1, 0.4)
    caution: Range = (0.3, 0.7)
    p_careful: float = 0.15
    ramp: float = 0.25
    zone: float = 0.6


@dataclasses.dataclass(frozen=True)
class CircleFamily:
    """Knob ranges of the Circle family. Each ranged knob is uniform in its range per episode,
    except `budget` (see `p_careful`).

    The robot chases a point `lead` radians ahead on a circle, running counter-clockwise.
    Reckless, it runs a circle through the walls (the reward peaks at radius 1.5, outside the
    walls at 1.125). Careful, it chases a circle of radius `radius` with the chased point's
    coordinates softly clamped to the walls (`x -> wall * tanh(x / wall)`, and y too where
    y-walls cost), and drives slower, more so near the walls.

    Attributes:
      speed, turn_gain, lookahead, noise: as in `GoalFamily`.
      budget: cost steps the episode may spend recklessly; 0 with probability `p_careful`, else
        skewed toward the low end (see `sample_knobs`).
      spread: fraction of the episode over which the budget is scheduled (1, a constant pace,
        by default): the robot runs the wide circle while behind the schedule (see
        `schedule`), the careful one otherwise.
      lead: rad, how far ahead (in polar angle) the chased point is. Chasing a point ahead cuts
        inside the circle: the robot runs a smaller one (about radius * cos(lead)).
      reach: reckless: m, radius of the circle run (always beyond the walls at 1.125: a reckless
        robot that happened to stay inside would be safe at full speed).
      radius: careful: m, radius of the chased circle.
      wall: careful: m, soft clamp scale of the chased point's coordinates.
      caution: careful: half of it is the fraction of speed shed everywhere, all of it the
        fraction shed at a costly wall (linearly from `zone` inside it; none beyond it, where
        the robot heads straight back in). Without the general slowdown, a small careful
        circle at full speed would earn most of what crossing the walls earns, and cost would
        buy little return.
      p_careful: probability of a careful episode (budget 0).
      zone: m, see `caution` (a constant, not drawn).
      full_rate: 0 (the default) switches between the two circles by the schedule. Positive,
        the robot is graded instead (collector v5, the Point's default): every step it blends
        the careful and the reckless circle (radius, wall clamp, slow-down, return push) by a
        boldness `clip(remaining budget / steps left / full_rate, 0, 1)`, full_rate in cost
        steps per step (a constant, not drawn). A switch overshoots small budgets when one
        reckless excursion costs much (the Point's: about 60, so a budget of 0.5-10 cost 62);
        graded, the cost follows the budget (0.5-5: 3.4, 5-10: 14, 10-30: 30).
    """

    speed: Range = (0.3, 1.0)
    turn_gain: Range = (2.0, 8.0)
    lookahead: Range = (0.0, 0.4)
    noise: Range = (0.0, 0.5)
    budget: Range = (2.0, 120.0)
    spread: Range = (1.0, 1.0)
    lead: Range = (0.3, 0.8)
    reach: Range = (1.25, 1.75)
    radius: Range = (0.6, 1.8)
    wall: Range = (0.8, 1.5)
    caution: Range = (0.4, 0.9)
    p_careful: float = 0.15
    zone: float = 0.6
    full_rate: float = 0.0


# The Car turns at most 1.26 rad/s and its turn command takes room from the forward one, so high
# steering gains saturate the turn and stall it; the Point's servo turns 3 rad/s and likes more.
CAR_TURN_GAIN: Range = (1.0, 3.0)
# The Point circles at 1.5 m/s and its momentum carries it far beyond a wall: graded, reckless
# at a remaining rate of 0.25 cost steps per step (see `CircleFamily.full_rate`).
POINT_CIRCLE_FULL_RATE = 0.25


def family(task: str) -> GoalFamily | CircleFamily:
    """The default knob family of a task name (raises ValueError naming the valid names)."""
    if task not in envs.NAMES:
        raise ValueError(f"unknown task {task!r}; valid names: {', '.join(envs.NAMES)}")
    fam = GoalFamily() if "Goal" in task else CircleFamily()
    if task.startswith("Car"):
        fam = dataclasses.replace(fam, turn_gain=CAR_TURN_GAIN)
    elif isinstance(fam, CircleFamily):
        fam = dataclasses.replace(fam, full_rate=POINT_CIRCLE_FULL_RATE)
    return fam


def knob_names(fam: GoalFamily | CircleFamily) -> tuple[str, ...]:
    """The per-episode knobs of a family (its ranged fields), in storage order."""
    return tuple(f.name for f in dataclasses.fields(fam) if isinstance(getattr(fam, f.name), tuple))


def sample_knobs(key: jax.Array, task: str, n: int,
                 fam: GoalFamily | CircleFamily | None = None) -> Knobs:
    """Draws the knobs of `n` episodes: a dict of float32 [n] arrays (units as in the family).

    Every ranged knob is uniform in its range, except `budget`: 0 with probability `p_careful`,
    else `lo + (hi - lo) u^2` with u uniform, so small budgets (where cost targets lie) are common.
    """
    fam = family(task) if fam is None else fam
    names = knob_names(fam)
    keys = jax.random.split(key, len(names) + 1)
    knobs = {name: jax.random.uniform(k, (n,), minval=getattr(fam, name)[0],
                                      maxval=getattr(fam, name)[1])
             for name, k in zip(names, keys[:-1], strict=True)}
    k_careful, k_budget = jax.random.split(keys[-1])
    lo, hi = fam.budget
    budget = lo + (hi - lo) * jax.random.uniform(k_budget, (n,)) ** 2
    knobs["budget"] = jnp.where(jax.random.bernoulli(k_careful, fam.p_careful, (n,)), 0.0, budget)
    return knobs


# --- policies -------------------------------------------------------------------------------

def schedule(knobs: Knobs, steps: jax.Array, horizon: int) -> jax.Array:
    """Cost steps the episode should have spent by step `steps`: the budget times
    min(1, (steps + 1) / (spread * horizon)), a ramp reaching the whole budget at `spread` of the
    episode (`horizon` steps)."""
    ramp = (steps + 1.0) / (knobs["spread"] * horizon)
    return knobs["budget"] * jnp.minimum(ramp, 1.0)


def goal_policy(drive: Drive, params: EnvParams, horizon: int,
                fam: GoalFamily = GoalFamily()) -> Policy:
    """Goal family: reckless (behind the cost schedule), head straight for the goal; careful,
    head for it through an avoidance field around hazards (and vases where they cost).

    In the field each obstacle within reach pushes the desired direction away from itself, and
    sideways as much as it blocks the way to the goal, with a weight growing from 0 at
    `clearance` beyond its edge to `avoid` at `ramp` closer; obstacles beyond the goal are
    ignored. About 20 distance computations a step. `horizon`: the episode length in steps.
    """

    def policy(knobs: Knobs, state: State, spent: jax.Array, key: jax.Array) -> jax.Array:
        xy, heading, vel = pose(drive, state)
        p = xy + knobs["lookahead"] * vel
        goal = state.task["goal"]
        to_goal = goal - p
        goal_dist = jnp.linalg.norm(to_goal)
        g = _unit(to_goal)
        # Obstacles: hazards (cost inside radius 0.2) and, where they cost, vases (the robot
        # touches one when within about VASE_RADIUS + 0.15 of its centre).
        centres = jnp.concatenate([state.task["hazards"], state.task["vases"]])
        radii = jnp.concatenate([jnp.full(params.hazard_mask.shape, HAZARD_RADIUS),
                                 jnp.full(params.vase_mask.shape, VASE_RADIUS + 0.15)])
        is_hazard = jnp.concatenate([params.hazard_mask, jnp.zeros_like(params.vase_mask)])
        active = is_hazard + jnp.concatenate([jnp.zeros_like(params.hazard_mask),
                                              params.vase_mask * params.vases_constrained])
        rel = p - centres
        dist = jnp.linalg.norm(rel, axis=-1)
        away = _unit(rel)
        edge = dist - radii

        # Careful: obstacles push away, and those blocking the way to the goal push sideways,
        # all to the side away from their weighted centre: per-obstacle sides would trap the
        # robot in the notch between two touching hazards.
        weight = jnp.clip((knobs["clearance"] - edge) / fam.ramp + 1.0, 0.0, 1.0) ** 2
        weight = weight * active * (dist < goal_dist + 0.2)
        block = weight * jnp.maximum(-(away @ g), 0.0)
        left = jnp.stack([-g[1], g[0]])
        side = jnp.where(jnp.sum(block * (-away @ left)) > 0, -left, left)
        push = jnp.sum(weight[:, None] * away, axis=0) + 1.5 * jnp.sum(block) * side
        careful_dir = g + knobs["avoid"] * push
        # Inside obstacles (after a reckless spell, or pushed in): leave by the shortest way out
        # of all of them (depth-weighted), since the field may balance the goal's pull there. The
        # heading breaks the tie where two overlapping hazards cancel.
        depth = jnp.maximum(-edge, 0.0) * active
        inside = jnp.any(depth > 0)
        forward_dir = jnp.stack([jnp.cos(heading), jnp.sin(heading)])
        exit_dir = jnp.sum(depth[:, None] * away, axis=0) + 0.01 * forward_dir
        careful_dir = jnp.where(inside, exit_dir, careful_dir)

        # Reckless (behind the cost schedule): straight for the goal at full agility. The
        # schedule spreads the cost over the episode, so the cost-to-go stays informative.
        reckless = spent < schedule(knobs, state.info["steps"], horizon)
        desired = jnp.where(reckless, to_goal, careful_dir)
        forward, turn = steer(drive, heading, desired, knobs["speed"], knobs["turn_gain"])
        closeness = jnp.max(jnp.clip(1.0 - edge / fam.zone, 0.0, 1.0) * active)
        slow = (1.0 - knobs["caution"]) * (1.0 - 0.5 * closeness)
        # Full agility when reckless, and when careful but inside: the way out is to safety.
        agile = reckless | inside
        forward = forward * jnp.where(agile, 1.0, slow)
        turn = turn * jnp.where(agile, 1.0, 1.0 - knobs["caution"])
        forward, turn = _noisy(forward, turn, knobs["noise"], key)
        return actuate(drive, forward, turn)

    return policy


def circle_policy(drive: Drive, params: EnvParams, horizon: int,
                  fam: CircleFamily = CircleFamily()) -> Policy:
    """Circle family: chase a point running counter-clockwise on a circle: reckless (behind the
    cost schedule), a wide one through the walls; careful, a chosen one softly clamped inside the
    costly walls, slower.

    The chased point sits `lead` rad ahead of the polar angle of the robot's extrapolated
    position. `horizon`: the episode length in steps.
    """

    def policy(knobs: Knobs, state: State, spent: jax.Array, key: jax.Array) -> jax.Array:
        xy, heading, vel = pose(drive, state)
        p = xy + knobs["lookahead"] * vel
        steps = state.info["steps"]
        if fam.full_rate > 0:  # graded: boldness from the remaining budget's rate
            rate = jnp.maximum(knobs["budget"] - spent, 0.0) / jnp.maximum(horizon - steps, 1)
            bold = jnp.clip(rate / fam.full_rate, 0.0, 1.0)
        else:  # switched: reckless exactly while behind the schedule
            bold = (spent < schedule(knobs, steps, horizon)).astype(jnp.float32)
        angle = jnp.arctan2(p[1], p[0]) + knobs["lead"]
        # Chasing a point ahead cuts inside the circle (to about radius * cos(lead)); the
        # reckless chase corrects for it, so that its `reach` is the circle it really runs.
        radius = (1.0 - bold) * knobs["radius"] + bold * knobs["reach"] / jnp.cos(knobs["lead"])
        target = radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)])
        costly = jnp.stack([jnp.float32(1.0), params.boundary_y]) > 0  # which axes have walls
        wall = knobs["wall"]
        clamped = (1.0 - bold) * wall * jnp.tanh(target / wall) + bold * target
        target = jnp.where(costly, clamped, target)
        # Careful but out of bounds (after a reckless spell): head back in across the wall, at
        # full agility; the chased point alone would lead along the wall, outside.
        out_axes = costly & (jnp.abs(xy) > params.boundary)
        out = jnp.any(out_axes)
        back = jnp.where(out_axes, -2.0 * jnp.sign(xy), 0.0)
        desired = target - p + (1.0 - bold) * back
        forward, turn = steer(drive, heading, desired, knobs["speed"], knobs["turn_gain"])
        near = jnp.clip((jnp.abs(p) - (params.boundary - fam.zone)) / fam.zone, 0.0, 1.0)
        near = jnp.max(jnp.where(costly, near, 0.0))
        slow = 1.0 - knobs["caution"] * (0.5 + 0.5 * near)
        forward = forward * jnp.where(out, 1.0, bold + (1.0 - bold) * slow)
        forward, turn = _noisy(forward, turn, knobs["noise"], key)
        return actuate(drive, forward, turn)

    return policy


def make_policy(task: str, params: EnvParams | None = None,
                fam: GoalFamily | CircleFamily | None = None) -> Policy:
    """The behaviour policy of a task: `policy(knobs, state, spent, key) -> action [2]`.

    `knobs` holds one episode's scalars as drawn by `sample_knobs`; `spent` is the episode's cost
    so far (the sum of `state.cost` over its earlier steps). `params` defaults to the task's own
    level: it tells the policy which objects and walls cost. Pure and jit/vmap-able; actions lie
    in [-1, 1]^2.
    """
    fam = family(task) if fam is None else fam
    env, own_params = envs.make(task)
    params = own_params if params is None else params
    drive = robot_drive(task)
    if isinstance(fam, GoalFamily):
        return goal_policy(drive, params, env.episode_length, fam)
    return circle_policy(drive, params, env.episode_length, fam)


__all__ = [
    "CAR_DRIVE",
    "POINT_DRIVE",
    "CircleFamily",
    "Drive",
    "GoalFamily",
    "Knobs",
    "Policy",
    "actuate",
    "family",
    "knob_names",
    "make_policy",
    "pose",
    "robot_drive",
    "sample_knobs",
    "schedule",
    "steer",
]
