"""The two seams of an environment: what a robot and what a task must provide.

`SafetyEnv` composes one of each. A third robot or task is one new class that satisfies its
protocol (structurally: no base class is required), registered in `safecdt_jax.envs.make`.
Everything is a pure function of its arguments; state lives in `State` (`data` for the MJX
physics, `robot` for the robot's own arrays, `task` for the task's).
"""

from __future__ import annotations

from typing import Protocol

import jax
import mujoco
from mujoco import mjx

from safecdt_jax.envs.types import EnvParams


class RobotLike(Protocol):
    """A robot: its MJX model, its physics step, its sensors, and the arrays it keeps."""

    name: str
    n_sensors: int  # length of `sensors`' output
    circles: tuple[tuple[float, float, float], ...]  # body-frame (x, y, r) outline, metres
    keepout: float  # placement keepout radius, metres

    @property
    def mj_model(self) -> mujoco.MjModel: ...

    @property
    def timestep(self) -> float: ...

    def init_data(self, model: mjx.Model, xy: jax.Array, yaw: jax.Array) -> mjx.Data:
        """MJX data at rest at `xy` (m), heading `yaw` (rad)."""

    def init_state(self) -> dict[str, jax.Array]:
        """The robot's own arrays at reset (`State.robot`; empty for a robot without any)."""

    def executed_action(self, action: jax.Array) -> jax.Array:
        """The action as the actuators execute it, where that is state-free (data record it)."""

    def physics(self, model: mjx.Model, data: mjx.Data, action: jax.Array, params: EnvParams,
                state: dict[str, jax.Array],
                key: jax.Array) -> tuple[mjx.Data, dict[str, jax.Array]]:
        """One env step of physics under `action` in [-1, 1]: (data, robot state); `key` for
        any randomness of the robot's own (the Car's caster stick-slip)."""

    def sensors(self, data: mjx.Data, state: dict[str, jax.Array], key: jax.Array) -> jax.Array:
        """The `n_sensors` body-frame sensor readings; `key` for any sensor noise."""


class TaskLike(Protocol):
    """A task: layout, reward, costs and the task's part of the observation."""

    episode_length: int  # time limit in env steps

    def observation_size(self, robot: RobotLike) -> int:
        """Length of the whole observation (robot sensors + task observation)."""

    def cost_terms(self) -> tuple[str, ...]:
        """Names of the per-step cost indicators `step` returns (in `State.info`)."""

    def reset(self, key: jax.Array, params: EnvParams,
              robot: RobotLike) -> tuple[jax.Array, jax.Array, dict[str, jax.Array]]:
        """A new layout: the robot's start (xy [2] in m, yaw in rad) and the task's arrays."""

    def step(self, key: jax.Array, params: EnvParams, robot: RobotLike, data: mjx.Data,
             task: dict[str, jax.Array], dt: float):
        """After the physics: (reward, {cost term: 0/1}, goal_met 0/1, task arrays)."""

    def observe(self, params: EnvParams, data: mjx.Data, task: dict[str, jax.Array]) -> jax.Array:
        """The task's part of the observation (lidars), after the robot's sensors."""


__all__ = ["RobotLike", "TaskLike"]
