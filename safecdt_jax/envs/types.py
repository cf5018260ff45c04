"""Pytrees shared by every task: the per-level parameters and the environment state."""

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

MAX_HAZARDS = 10  # Goal2 has the most hazards (10); level 1 masks two of them out.
MAX_VASES = 10  # Goal2 has 10 vases; level 1 activates one.


@struct.dataclass
class EnvParams:
    """Everything that differs between levels and domains, as data: one program serves all.

    Lengths in metres. Dynamics scales are dimensionless multipliers on the reference model.

    Attributes:
      extent: half-width of the square placement area ([-extent, extent]^2): Goal1 1.5, Goal2 2.0.
      hazard_mask: [MAX_HAZARDS] 1.0 for an active hazard disc, 0.0 for an absent one.
      vase_mask: [MAX_VASES] 1.0 for an active (physical, lidar-visible) vase.
      vases_constrained: 1.0 when vase contact and vase motion cost (Goal2), else 0.0.
      boundary_y: Circle tasks: 1.0 when |y| > boundary also costs (Circle2), else 0.0 (x only).
      boundary: Circle tasks: the sigwall position (1.125 m).
      friction_scale: multiplies tyre-floor friction (Car traction, side grip) and vase-floor
        friction.
      gear_scale: multiplies every actuator's gear (Point thrust and yaw servo, Car wheel torque).
      damping_scale: multiplies joint damping (Point joints; Car wheel and caster losses).
      mass_scale: multiplies the robot's mass and rotational inertia.
    """

    extent: jax.Array = struct.field(default_factory=lambda: jnp.float32(1.5))
    hazard_mask: jax.Array = struct.field(default_factory=lambda: jnp.zeros(MAX_HAZARDS))
    vase_mask: jax.Array = struct.field(default_factory=lambda: jnp.zeros(MAX_VASES))
    vases_constrained: jax.Array = struct.field(default_factory=lambda: jnp.float32(0.0))
    boundary_y: jax.Array = struct.field(default_factory=lambda: jnp.float32(0.0))
    boundary: jax.Array = struct.field(default_factory=lambda: jnp.float32(1.125))
    friction_scale: jax.Array = struct.field(default_factory=lambda: jnp.float32(1.0))
    gear_scale: jax.Array = struct.field(default_factory=lambda: jnp.float32(1.0))
    damping_scale: jax.Array = struct.field(default_factory=lambda: jnp.float32(1.0))
    mass_scale: jax.Array = struct.field(default_factory=lambda: jnp.float32(1.0))


@struct.dataclass
class State:
    """One environment step's outcome and everything needed to take the next one.

    Attributes:
      obs: [observation_size] float32 observation (body-frame sensors, then lidars).
      reward: scalar reward of the step that produced this state (0 after reset).
      cost: scalar 0.0/1.0, the indicator that any cost term is positive.
      done: scalar 0.0/1.0, 1.0 once the episode's time limit is reached.
      info: dict of scalars: per-term cost indicators, `goal_met`, `steps`, `nonfinite_actions`.
      data: the MJX physics data of the robot.
      robot: dict of the robot's own arrays (the Car's caster orientation and drive level; empty
        for the Point).
      task: dict of task arrays (object positions, goal, vase velocities...).
      key: PRNG key for the episode's own randomness (goal re-sampling).
    """

    obs: jax.Array
    reward: jax.Array
    cost: jax.Array
    done: jax.Array
    info: dict[str, jax.Array]
    data: Any
    robot: dict[str, jax.Array]
    task: dict[str, jax.Array]
    key: jax.Array
