"""Settings of the offline safe-RL baselines (BCQ-Lag, BEAR-Lag, CPQ), with OSRL's defaults.

One frozen dataclass serves the three algorithms: the fields they share (data, critics, targets,
the VAE) and the few each adds (marked below). `preset(algo, name)` returns the `osrl`, `cpu`
or `tiny` settings of one algorithm; the `cpu` preset keeps OSRL's networks and every rule, and
trades away updates (docs/BASELINES.md says how the result moves as they grow).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from safecdt_jax import validate as check

ALGOS = ("bcql", "bearl", "cpq")


@dataclass(frozen=True)
class BaselineConfig:
    """One offline run of one algorithm (numbers per run; seeds are vmapped side by side).

    Attributes:
        algo: 'bcql', 'bearl' or 'cpq'.
        steps: gradient steps (OSRL: 100k BCQL, 300k BEARL, 100k CPQ).
        batch: transitions per step, drawn uniformly with replacement (512).
        chunk: steps per jitted `lax.scan` call (progress, checkpoints).
        gamma: discount of the reward and the cost values (0.99).
        tau: soft target update rate, every step, of actor and both critics (0.005).
        reward_scale: rewards are multiplied by this in the critic targets (0.1).
        cost_scale: costs likewise (1).
        hidden: width of the two hidden layers of actor and critics (256).
        vae_hidden: width of the VAE's two hidden layers (400); its latent is 2 x act_dim.
        num_q: critics per ensemble (2); BCQL/BEARL use two ensembles (Q1, Q2) per value.
        next_actions: next-state action samples in the critic targets (10).
        lmbda: soft-clipped double Q, lmbda min + (1 - lmbda) max (0.75; BCQL, BEARL).
        actor_lr, critic_lr, vae_lr: Adam learning rates (1e-3; CPQ's actor 1e-4).
        vae_beta: weight of the VAE's KL term, averaged over elements (0.5).
        pid: (KP, KI, KD) of the Lagrangian on the per-step cost value (0.1, 0.003, 0.001;
            BCQL, BEARL), updated every step.
        phi: BCQL's perturbation range, as a fraction of the action range (0.05).
        mmd_sigma: BEAR's Gaussian-kernel width (50); kernel exp(-|x - y|^2 / (2 sigma)).
        mmd_threshold: BEAR's target MMD (0.05).
        alpha_lr: learning rate of the hand-updated log alpha (BEAR's MMD dual 1e-3; CPQ 1e-4).
        qc_scalar: CPQ's cost threshold is qc_scalar x the per-step threshold (1.5).
        ood_quantile: CPQ flags as out of distribution the actions whose VAE KL reaches this
            quantile of the batch (0.75).
        cpq_ood_grad: False (OSRL's code): CPQ's OOD term uses the target cost critic under no
            gradient, so the cost critic learns by plain TD. True (the CPQ paper): the term's
            gradient reaches the online cost critic and pushes OOD cost values up.
        obs_std_floor: observations are standardised by the data's mean and std, the std floored
            here (constant channels stay 0); actions are learnt in units of the data's largest
            |action| per dimension, so max_action is 1 inside the networks.
        cost_limit: the episode cost budget B the per-step threshold is derived from (30).
        episode_len: L of `qc_thres = B (1 - gamma^L) / ((1 - gamma) L)`; None = the data's.
    """

    algo: str = "bcql"
    steps: int = 100_000
    batch: int = 512
    chunk: int = 500
    gamma: float = 0.99
    tau: float = 0.005
    reward_scale: float = 0.1
    cost_scale: float = 1.0
    hidden: int = 256
    vae_hidden: int = 400
    num_q: int = 2
    next_actions: int = 10
    lmbda: float = 0.75
    actor_lr: float = 1e-3
    critic_lr: float = 1e-3
    vae_lr: float = 1e-3
    vae_beta: float = 0.5
    pid: tuple[float, float, float] = (0.1, 0.003, 0.001)
    phi: float = 0.05
    mmd_sigma: float = 50.0
    mmd_threshold: float = 0.05
    alpha_lr: float = 1e-3
    qc_scalar: float = 1.5
    ood_quantile: float = 0.75
    cpq_ood_grad: bool = False
    obs_std_floor: float = 0.01
    cost_limit: float = 30.0
    episode_len: int | None = None

    def __post_init__(self):
        check.one_of(self, "algo", ALGOS)
        check.integers(self, "steps", "batch", "chunk", "hidden", "vae_hidden", "num_q",
                       "next_actions")
        check.integers(self, "episode_len", optional=True)
        check.positive(self, "tau", "reward_scale", "cost_scale", "actor_lr", "critic_lr",
                       "vae_lr", "mmd_sigma", "alpha_lr", "qc_scalar", "obs_std_floor")
        check.non_negative(self, "vae_beta", "phi", "mmd_threshold", "cost_limit")
        check.unit_interval(self, "gamma", "lmbda", "ood_quantile")
        check.booleans(self, "cpq_ood_grad")
        if len(self.pid) != 3 or not all(g >= 0 for g in self.pid):
            raise ValueError(f"BaselineConfig.pid must be three gains >= 0, got {self.pid!r}")

    def record(self) -> dict[str, Any]:
        """The config as JSON-able values (checkpoint metadata, results.json)."""
        return {k: list(v) if isinstance(v, tuple) else v
                for k, v in dataclasses.asdict(self).items()}


# OSRL's per-algorithm settings (bcql_configs.py, bearl_configs.py, cpq_configs.py).
_OSRL: dict[str, dict[str, Any]] = {
    "bcql": dict(steps=100_000),
    "bearl": dict(steps=300_000),
    "cpq": dict(steps=100_000, actor_lr=1e-4, alpha_lr=1e-4),
}

# `cpu`: OSRL's networks and rules with 1,500 updates each, sized from the measured step times
# (BCQL 200 ms, BEARL 264 ms, CPQ 107 ms per update on one core, about 15 GFLOP for BCQL: the
# updates are matmul-bound), so that the three algorithms x 3 seeds on one source task train
# in about 30 min on a 2-core CPU, 43 on one core (docs/BASELINES.md). `tiny`: every code path
# in seconds, for tests.
_SIZES: dict[str, dict[str, Any]] = {
    "osrl": {},
    "cpu": dict(steps=1_500, chunk=250),
    "tiny": dict(steps=20, batch=16, chunk=10, hidden=16, vae_hidden=16, next_actions=3),
}
PRESET_NAMES = tuple(_SIZES)


def preset(algo: str, name: str = "cpu", **overrides: Any) -> BaselineConfig:
    """The `name` preset ('osrl', 'cpu', 'tiny') of algorithm `algo`, with `overrides`."""
    if algo not in ALGOS:
        raise ValueError(f"unknown baseline {algo!r}; choose from {', '.join(ALGOS)}")
    if name not in _SIZES:
        raise ValueError(f"unknown baseline preset {name!r}; choose one of {', '.join(_SIZES)}")
    fields = {"algo": algo} | _OSRL[algo] | _SIZES[name]
    return BaselineConfig(**(fields | overrides))


__all__ = ["ALGOS", "PRESET_NAMES", "BaselineConfig", "preset"]
