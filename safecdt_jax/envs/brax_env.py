"""Any of our tasks as a `brax.envs.base.Env`, so Brax's own agents (e.g. `ppo.train`) train on it.

    env = BraxSafetyEnv("CarGoal1")      # safecdt_jax.envs.brax_env; level 1, default dynamics
    env = BraxSafetyEnv("CarGoal2", friction_scale=0.5)           # a shifted target
    state = env.reset(rng); state = env.step(state, action)
    state.metrics["cost"]                                         # the step's cost (0 or 1)

Brax's env state wraps ours: `pipeline_state` is our `State` (MJX data, task, per-episode key),
`obs`, `reward` and `done` are copied out of it, and the cost and its terms (hazards, vases,
boundary...) go to `metrics`, which Brax's training wrappers sum per episode. Level and dynamics
come from our `EnvParams`, fixed when the adapter is built. Episodes end by time limit only
(`done` at the task's horizon); Brax's `EpisodeWrapper` and `AutoResetWrapper` then reset.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State

from safecdt_jax import envs as _envs


def _device_put_replicated(x, devices):
    """What `jax.device_put_replicated` did: `x` stacked once per device on a new leading axis
    (`jax.pmap` spreads that axis over the devices itself)."""
    return jax.tree.map(lambda a: jnp.stack([jnp.asarray(a)] * len(devices)), x)


# Brax 0.14.2 (the newest) still calls `jax.device_put_replicated`, which jax 0.10 removed, so its
# own `ppo.train` fails on the jax this project pins; restore the function if it is missing.
try:
    jax.device_put_replicated  # noqa: B018
except AttributeError:
    jax.device_put_replicated = _device_put_replicated


class BraxSafetyEnv(Env):
    """`name` (one of `envs.NAMES`) with its level's params, dynamics scales overridden by
    keyword (friction_scale, gear_scale, damping_scale, mass_scale, ...: `EnvParams` fields)."""

    def __init__(self, name: str, **param_overrides: float):
        self._env, params = _envs.make(name)
        fields = {f.name for f in dataclasses.fields(params)}
        unknown = sorted(set(param_overrides) - fields)
        if unknown:
            raise ValueError(f"unknown EnvParams field(s) {', '.join(unknown)}; valid: "
                             f"{', '.join(sorted(fields))}")
        self._params = params.replace(**{k: jnp.float32(v) for k, v in param_overrides.items()})
        self.name = name

    def _metrics(self, ours) -> dict[str, jax.Array]:
        terms = {k: ours.info[k] for k in self._env.task.cost_terms()}  # "cost_hazards", ...
        return {"cost": ours.cost, "goal_met": ours.info["goal_met"], **terms}

    def reset(self, rng: jax.Array) -> State:
        """A new episode of our env, as Brax's State (reward, done and cost 0)."""
        ours = self._env.reset(rng, self._params)
        return State(pipeline_state=ours, obs=ours.obs, reward=ours.reward, done=ours.done,
                     metrics=self._metrics(ours))

    def step(self, state: State, action: jax.Array) -> State:
        """One step of our env (action clipped to [-1, 1] there)."""
        ours = self._env.step(state.pipeline_state, action, self._params)
        # Merged: Brax's wrappers keep metrics of their own in the same dict.
        return state.replace(pipeline_state=ours, obs=ours.obs, reward=ours.reward,
                             done=ours.done, metrics={**state.metrics, **self._metrics(ours)})

    @property
    def observation_size(self) -> int:
        """Length of the observation vector (72 CarGoal, 60 PointGoal, 40 / 28 Circle)."""
        return self._env.observation_size

    @property
    def action_size(self) -> int:
        """2 (both robots)."""
        return self._env.action_size

    @property
    def backend(self) -> str:
        """'mjx'."""
        return "mjx"

    @property
    def episode_length(self) -> int:
        """The task's time limit in steps (pass it to Brax's trainers as `episode_length`)."""
        return self._env.episode_length


__all__ = ["BraxSafetyEnv"]
