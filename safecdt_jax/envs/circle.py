"""The Circle task: run counter-clockwise around radius 1.5 while staying inside the sigwalls."""

import dataclasses

import jax
import jax.numpy as jnp

from safecdt_jax.envs.geometry import N_LIDAR_BINS, pseudo_lidar
from safecdt_jax.envs.protocols import RobotLike
from safecdt_jax.envs.types import EnvParams

CIRCLE_RADIUS = 1.5  # m: the reward-optimal radius
START_HALF_WIDTH = 0.8  # m: the agent starts uniformly in [-0.8, 0.8]^2
LIDAR_RANGE = 6.0  # m


@dataclasses.dataclass(frozen=True)
class CircleTask:
    """Circle1/Circle2 on top of a robot; the level (x or x-and-y walls) lives in EnvParams."""

    episode_length: int = 500

    def observation_size(self, robot: RobotLike) -> int:
        """Sensors then the circle lidar (the circle seen as one point at the origin)."""
        return robot.n_sensors + N_LIDAR_BINS

    def cost_terms(self) -> tuple[str, ...]:
        """Names of the per-term cost indicators reported in `info`."""
        return ("cost_out_of_boundary",)

    def reset(self, key: jax.Array, params: EnvParams, robot: RobotLike):
        """Uniform start in [-0.8, 0.8]^2 with a uniform heading; no objects."""
        k_xy, k_yaw = jax.random.split(key)
        xy = jax.random.uniform(k_xy, (2,), minval=-START_HALF_WIDTH, maxval=START_HALF_WIDTH)
        yaw = jax.random.uniform(k_yaw, (), maxval=2 * jnp.pi)
        return xy, yaw, {}

    def step(self, key, params: EnvParams, robot: RobotLike, data, task: dict, dt: float):
        """Reward 0.1 (-u y + v x) / rho / (1 + |rho - 1.5|) after the step; boundary cost."""
        x, y = data.qpos[0], data.qpos[1]
        u, v = data.qvel[0], data.qvel[1]
        rho = jnp.sqrt(x * x + y * y)
        tangential = (-u * y + v * x) / jnp.maximum(rho, 1e-9)
        reward = 0.1 * tangential / (1 + jnp.abs(rho - CIRCLE_RADIUS))
        out = (jnp.abs(x) > params.boundary) | (
            (params.boundary_y > 0) & (jnp.abs(y) > params.boundary))
        costs = {"cost_out_of_boundary": out.astype(jnp.float32)}
        return jnp.clip(reward, -10.0, 10.0), costs, jnp.float32(0.0), task

    def observe(self, params: EnvParams, data, task: dict) -> jax.Array:
        """Circle lidar [16], range 6 m, of the origin."""
        return pseudo_lidar(jnp.zeros((1, 2)), jnp.ones(1), data.qpos[:2], data.qpos[2],
                            LIDAR_RANGE)


def circle_params(level: int) -> EnvParams:
    """Circle level 1 (walls at x = +-1.125) or level 2 (also y = +-1.125)."""
    return EnvParams(boundary_y=jnp.float32(1.0 if level == 2 else 0.0))
