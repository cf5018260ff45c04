"""SafetyEnv: a robot and a task as one pure, jit- and vmap-able environment."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
from mujoco import mjx

from safecdt_jax.envs.protocols import RobotLike, TaskLike
from safecdt_jax.envs.robots import N_SUBSTEPS
from safecdt_jax.envs.types import EnvParams, State


@dataclasses.dataclass(frozen=True, eq=False)
class SafetyEnv:
    """A Safety-Gymnasium task in MJX. Methods are pure functions of (state/key, action, params).

    The env object holds only static structure (robot, task); everything that differs between
    levels or domains is in `EnvParams`, so level 1 and level 2 share one compiled program.
    """

    name: str
    robot: RobotLike
    task: TaskLike

    @functools.cached_property
    def model(self) -> mjx.Model:
        """The robot's MJX model (device arrays), built once, concretely even if first asked for
        inside a trace (a cached tracer would leak into later calls). Under several
        cooperating processes it goes on this process's first device: MJX's default is
        `jax.devices()[0]`, process 0's device in every process."""
        device = jax.local_devices()[0] if jax.process_count() > 1 else None
        with jax.ensure_compile_time_eval():
            return mjx.put_model(self.robot.mj_model, device=device)

    @property
    def observation_size(self) -> int:
        """Length of `State.obs`: 72/60 (Car/Point Goal), 40/28 (Car/Point Circle)."""
        return self.task.observation_size(self.robot)

    @property
    def action_size(self) -> int:
        """2 for both robots; actions are clipped to [-1, 1]."""
        return 2

    @property
    def episode_length(self) -> int:
        """Steps per episode (time limit): 1000 for Goal, 500 for Circle."""
        return self.task.episode_length

    @property
    def dt(self) -> float:
        """Seconds of simulated time per env step (0.02 Point, 0.04 Car)."""
        return N_SUBSTEPS * self.robot.timestep

    def reset(self, key: jax.Array, params: EnvParams) -> State:
        """A new episode: layout re-sampled with keepouts, robot at rest, zero reward and cost."""
        k_task, k_next = jax.random.split(key)
        xy, yaw, task = self.task.reset(k_task, params, self.robot)
        robot = self.robot.init_state()
        data = self.robot.init_data(self.model, xy, yaw)
        zero = jnp.float32(0.0)
        info = {name: zero for name in self.task.cost_terms()}
        info |= {"goal_met": zero, "steps": jnp.int32(0), "nonfinite_actions": jnp.int32(0)}
        obs = self._observe(params, data, robot, task, _noise_key(k_next))
        return State(obs=obs, reward=zero, cost=zero, done=zero, info=info, data=data,
                     robot=robot, task=task, key=k_next)

    def step(self, state: State, action: jax.Array, params: EnvParams) -> State:
        """One env step: clip the action to [-1, 1], 10 physics substeps, reward, cost, obs.

        A non-finite action component is replaced by 0 (so NaN never reaches the physics) and
        counted in `info['nonfinite_actions']` over the episode.
        """
        action = jnp.asarray(action, jnp.float32)
        finite = jnp.isfinite(action)
        action = jnp.clip(jnp.where(finite, action, 0.0), -1.0, 1.0)
        key, k_goal = jax.random.split(state.key)
        data, robot = self.robot.physics(self.model, state.data, action, params, state.robot,
                                         _physics_key(k_goal))
        reward, costs, goal_met, task = self.task.step(k_goal, params, self.robot, data,
                                                       state.task, self.dt)
        cost = jnp.any(jnp.stack(list(costs.values())) > 0).astype(jnp.float32)
        steps = state.info["steps"] + 1
        info = dict(costs, goal_met=goal_met, steps=steps,
                    nonfinite_actions=state.info["nonfinite_actions"] + jnp.any(~finite))
        done = (steps >= self.episode_length).astype(jnp.float32)
        obs = self._observe(params, data, robot, task, _noise_key(k_goal))
        return State(obs=obs, reward=reward, cost=cost, done=done, info=info, data=data,
                     robot=robot, task=task, key=key)

    def _observe(self, params: EnvParams, data: mjx.Data, robot: dict, task: dict,
                 key: jax.Array) -> jax.Array:
        sensors = self.robot.sensors(data, robot, key)
        return jnp.concatenate([sensors, self.task.observe(params, data, task)]).astype(
            jnp.float32)


def _physics_key(key: jax.Array) -> jax.Array:
    """The robot's own physics key of a step, folded off the step's key (as `_noise_key`)."""
    return jax.random.fold_in(key, 0xCA57E)


def _noise_key(key: jax.Array) -> jax.Array:
    """The sensor-noise key of a step, folded off the step's key so that the split chain (and with
    it every layout and goal sequence) is the same whether a robot draws noise or not."""
    return jax.random.fold_in(key, 0x5E115)
