"""Settings of a PPO-Lagrangian behaviour expert, and the cost-limit schedule it trains under."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from safecdt_jax import validate as check


@dataclass(frozen=True)
class ExpertConfig:
    """One PPO-Lagrangian run on one task (numbers are per run; runs are vmapped side by side).

    Training proceeds in *rounds*: every env of the run is reset at once, drives exactly one
    episode (the tasks have a fixed horizon and no early termination), and the episode is cut
    into rollouts of `rollout_len` steps, one PPO update after each. A round's episode totals are
    the run's learning curve, and the actor at the end of each round is a snapshot.

    Attributes:
        task: source task, e.g. 'CarGoal1'.
        steps: env steps per run (rounded up to whole rounds of `num_envs` episodes).
        num_envs: parallel envs per run.
        rollout_len: env steps between updates; must divide the episode length (1000 Goal,
            500 Circle), so that every episode ends on an update boundary.
        episode_len: steps per episode; None = the task's time limit (shorter for tests).
        epochs: passes over each rollout batch.
        minibatches: minibatches per epoch.
        hidden: widths of the tanh hidden layers of the actor and of both critics.
        lr: Adam learning rate of all three networks.
        max_grad_norm: global-norm gradient clip, per network.
        gamma: discount of both the reward and the cost returns.
        gae_lambda: GAE lambda of both advantages.
        clip_eps: PPO ratio clip.
        ent_coef: entropy bonus weight (per action dimension, nats).
        init_std: initial action standard deviation (state-independent, per dimension).
        min_std: floor of the action standard deviation, so exploration cannot collapse while
            the cost limit moves (the log-std parameter is clipped at log(min_std)).
        pid_kp, pid_ki, pid_kd: PID Lagrangian gains on the episode-cost error (DSRL's experts:
            0.05, 0.005, 0.1).
        pid_ema: smoothing of the cost signal that the derivative term differences.
        obs_var_floor: observation channels whose running variance stays below this read as 0
            (a constant channel, e.g. the Car's accelerometer z, must not become a +-10 input
            the moment another simulator or a shifted target moves it).
        obs_clip: normalised observations are clipped to +-this.
    """

    task: str = "CarGoal1"
    steps: int = 5_000_000
    num_envs: int = 128
    rollout_len: int = 125
    episode_len: int | None = None
    epochs: int = 10
    minibatches: int = 8
    hidden: tuple[int, ...] = (64, 64)
    lr: float = 3e-4
    max_grad_norm: float = 0.5
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    ent_coef: float = 0.0
    init_std: float = 0.6
    min_std: float = 0.1
    pid_kp: float = 0.05
    pid_ki: float = 0.005
    pid_kd: float = 0.1
    pid_ema: float = 0.9
    obs_var_floor: float = 1e-6
    obs_clip: float = 10.0

    def __post_init__(self) -> None:
        from safecdt_jax import envs
        if self.task not in envs.NAMES:
            raise ValueError(f"ExpertConfig.task: unknown task {self.task!r}; valid names: "
                             f"{', '.join(envs.NAMES)}")
        check.integers(self, "steps", "num_envs", "rollout_len", "epochs", "minibatches")
        check.integers(self, "episode_len", optional=True)
        if self.horizon % self.rollout_len:
            raise ValueError(f"ExpertConfig.rollout_len ({self.rollout_len}) must divide the "
                             f"episode length ({self.horizon})")
        if (self.num_envs * self.rollout_len) % self.minibatches:
            raise ValueError(f"ExpertConfig.minibatches ({self.minibatches}) must divide "
                             f"num_envs * rollout_len ({self.num_envs * self.rollout_len})")
        if not self.hidden or any(not isinstance(h, int) or h <= 0 for h in self.hidden):
            raise ValueError(f"ExpertConfig.hidden must be positive integers, got {self.hidden!r}")
        check.positive(self, "lr", "max_grad_norm", "clip_eps", "init_std", "min_std", "obs_clip")
        check.unit_interval(self, "gamma", "gae_lambda", "pid_ema")
        check.non_negative(self, "ent_coef", "pid_kp", "pid_ki", "pid_kd", "obs_var_floor")

    @property
    def horizon(self) -> int:
        """Steps per episode: `episode_len`, or the task's time limit."""
        from safecdt_jax import envs
        return self.episode_len or envs.make(self.task)[0].episode_length

    @property
    def rounds(self) -> int:
        """Rounds per run: `steps` in whole rounds of `num_envs` episodes (at least 1)."""
        return max(1, math.ceil(self.steps / (self.num_envs * self.horizon)))

    @property
    def updates_per_round(self) -> int:
        """PPO updates per round (rollouts per episode)."""
        return self.horizon // self.rollout_len

    def replace(self, **changes: Any) -> ExpertConfig:
        """A copy with `changes` applied (validated again)."""
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict[str, Any]:
        """Plain JSON fields (tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v
                for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_json(cls, record: dict[str, Any]) -> ExpertConfig:
        """Inverse of `to_json`."""
        return cls(**{k: tuple(v) if k == "hidden" else v for k, v in record.items()})


# Presets: `tiny` exercises every code path in seconds (tests); `cpu` (the dataclass defaults:
# 128 envs, 8 minibatches of 2,000 samples) is what made the committed experts on a 2-core CPU.
_PRESETS: dict[str, dict[str, Any]] = {
    "tiny": dict(steps=2 * 8 * 20, num_envs=8, rollout_len=10, episode_len=20, epochs=2,
                 minibatches=2, hidden=(16, 16)),
    "cpu": dict(),
}
PRESET_NAMES = tuple(_PRESETS)


def expert_preset(name: str, **overrides: Any) -> ExpertConfig:
    """The `ExpertConfig` of preset `name` with `overrides`; ValueError for an unknown name."""
    if name not in _PRESETS:
        raise ValueError(f"unknown expert preset {name!r}; choose one of {', '.join(_PRESETS)}")
    return ExpertConfig(**(_PRESETS[name] | overrides))


NO_LIMIT = 1e9  # a cost limit that never binds (the PID multiplier stays 0)


@dataclass(frozen=True)
class CostSchedule:
    """The episode-cost limit as a function of training progress p in [0, 1] (fraction of the
    run's updates): `start` until p = `begin`, then linear to `end` at p = `finish`, then `end`.
    A constant limit has start == end. DSRL's CarGoal1 experts anneal 80 -> 5 over epochs
    200-1000 of 1200: `CostSchedule(80, 5, 1/6, 5/6)`. Costs are episode totals (raw units)."""

    start: float
    end: float
    begin: float = 0.0
    finish: float = 1.0

    def __post_init__(self) -> None:
        if not (self.start >= 0 and self.end >= 0):
            raise ValueError(f"CostSchedule: limits must be >= 0, got {self.start}, {self.end}")
        if not 0.0 <= self.begin <= self.finish <= 1.0:
            raise ValueError(f"CostSchedule: need 0 <= begin <= finish <= 1, got "
                             f"{self.begin}, {self.finish}")

    @classmethod
    def parse(cls, text: str) -> CostSchedule:
        """'25' (constant), 'none' (unconstrained) or 'A:B' / 'A:B:begin:finish' (anneal)."""
        parts = text.strip().lower().split(":")
        try:
            if parts == ["none"]:
                return cls(NO_LIMIT, NO_LIMIT)
            values = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"bad cost limit {text!r}: expected a number, 'none', 'A:B' or "
                             f"'A:B:begin:finish'") from None
        if len(values) == 1:
            return cls(values[0], values[0])
        if len(values) in (2, 4):
            return cls(*values)
        raise ValueError(f"bad cost limit {text!r}: expected a number, 'none', 'A:B' or "
                         f"'A:B:begin:finish'")

    def as_array(self) -> np.ndarray:
        """[start, end, begin, finish] float32, the form `train` takes (vmappable)."""
        return np.asarray([self.start, self.end, self.begin, self.finish], np.float32)

    def label(self) -> str:
        """Short name: 'none', '25' or '80:5'."""
        fmt = lambda x: "none" if x >= NO_LIMIT else f"{x:g}"
        return fmt(self.start) if self.start == self.end else f"{fmt(self.start)}:{fmt(self.end)}"


__all__ = ["NO_LIMIT", "PRESET_NAMES", "CostSchedule", "ExpertConfig", "expert_preset"]
