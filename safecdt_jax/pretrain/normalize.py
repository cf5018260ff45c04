"""Optional input/output normalisation of pretraining, folded into the CDT's weights afterwards.

With `PretrainConfig.scale_actions` the CDT trains on actions divided by the data's largest
|action| per dimension; with `standardize_obs`, on observations standardised by the data's mean
and std. Then its first and last linear layers absorb both transforms, so the checkpoint's
params read raw observations and emit raw actions: the rollout, the LoRA finetuning and the
deployment loop never see the normalisation.

Why: the Car's wheel commands live in +-0.02 (its actuators saturate there) and its sensors
span 0.001-16, while the CDT's heads and embeddings start at N(0, 0.02^2). A context-1 `cpu`
CDT network fitted to careful CarGoal1 driving (Adam 3e-4, MSE, 10,000 updates of 256) costs
49 per episode on raw observations and 22 standardised, a per-step MLP's 21, both with actions
scaled (docs/METHOD.md, section 8, for these numbers and what else normalisation changed).

    norm = fit_io_norm(data)                     # statistics of the valid steps
    train_on = normalise_dataset(data, norm)     # what the optimiser sees
    raw_params = fold_io_norm(params, norm)      # the same function of raw inputs
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from safecdt_jax.data.dataset import Dataset
from safecdt_jax.model.cdt import Params


class IONorm(NamedTuple):
    """Normalised observation = (obs - obs_mean) / obs_std; normalised action = action /
    act_scale. Arrays [obs_dim], [obs_dim] and [act_dim], raw units."""

    obs_mean: np.ndarray
    obs_std: np.ndarray
    act_scale: np.ndarray

    def to_json(self) -> dict[str, list[float]]:
        """Plain lists, as a checkpoint's JSON metadata stores them."""
        return {name: np.asarray(value, np.float64).tolist()
                for name, value in self._asdict().items()}

    @classmethod
    def from_json(cls, record: dict[str, Any]) -> IONorm:
        """Inverse of `to_json`."""
        return cls(*(np.asarray(record[name], np.float32) for name in cls._fields))


def identity_norm(obs_dim: int, act_dim: int) -> IONorm:
    """The transform that changes nothing (mean 0, std 1, scale 1)."""
    return IONorm(np.zeros(obs_dim, np.float32), np.ones(obs_dim, np.float32),
                  np.ones(act_dim, np.float32))


def transition_norm(observations, actions, std_floor: float = 0.01,
                    act_floor: float = 1e-3) -> IONorm:
    """Mean and std of each observation dimension and largest |action| of each action dimension
    of flat transitions `observations [N, obs_dim]`, `actions [N, act_dim]` (raw units).

    The std is floored at `std_floor` (sensors that never move, like the planar robots' vertical
    velocity, would otherwise be divided by 0) and the action scale at `act_floor`. Sums are
    accumulated in float64; the result is float32.
    """
    obs = np.asarray(observations)
    return IONorm(obs.mean(0, dtype=np.float64).astype(np.float32),
                  np.maximum(obs.std(0, dtype=np.float64), std_floor).astype(np.float32),
                  np.maximum(np.abs(np.asarray(actions)).max(0), act_floor).astype(np.float32))


def fit_io_norm(data: Dataset, observations: bool = True, actions: bool = True,
                std_floor: float = 0.01, act_floor: float = 1e-3) -> IONorm:
    """`transition_norm` of the valid steps of `data`, keeping the observation part only if
    `observations` and the action part only if `actions` (the identity otherwise)."""
    valid = data.valid_steps
    stats = transition_norm(np.asarray(data.observations)[valid],
                            np.asarray(data.actions)[valid], std_floor, act_floor)
    same = identity_norm(data.obs_dim, data.act_dim)
    return IONorm(stats.obs_mean if observations else same.obs_mean,
                  stats.obs_std if observations else same.obs_std,
                  stats.act_scale if actions else same.act_scale)


def normalise_dataset(data: Dataset, norm: IONorm) -> Dataset:
    """`data` with observations (and next observations) standardised and actions scaled by
    `norm`; padding stays zero. Rewards, costs and everything else are unchanged."""
    valid = data.valid_steps[..., None]

    def obs(x):
        return np.where(valid, (np.asarray(x) - norm.obs_mean) / norm.obs_std, 0.0).astype(
            np.float32)

    actions = np.where(valid, np.asarray(data.actions) / norm.act_scale, 0.0).astype(np.float32)
    return dataclasses.replace(data, observations=obs(data.observations),
                               next_observations=obs(data.next_observations), actions=actions)


def fold_io_norm(params: Params, norm: IONorm) -> Params:
    """CDT params that compute, from raw observations and actions, what `params` computes from
    normalised ones, with the action head (and next-state head) in raw units.

    Exact up to float rounding: the state embedding absorbs the standardisation, the action
    embedding the action scale, the action mean head multiplies by it and the log-std head
    adds its log; the next-state head, when present, un-standardises its prediction.
    """
    mu, sd = jnp.asarray(norm.obs_mean), jnp.asarray(norm.obs_std)
    scale = jnp.asarray(norm.act_scale)
    out = dict(params)
    w, b = params["embed_state"]["kernel"], params["embed_state"]["bias"]
    out["embed_state"] = {"kernel": w / sd[:, None], "bias": b - (mu / sd) @ w}
    w = params["embed_action"]["kernel"]
    out["embed_action"] = {**params["embed_action"], "kernel": w / scale[:, None]}
    w, b = params["action_mean"]["kernel"], params["action_mean"]["bias"]
    out["action_mean"] = {"kernel": w * scale[None], "bias": b * scale}
    b = params["action_log_std"]["bias"]
    out["action_log_std"] = {**params["action_log_std"], "bias": b + jnp.log(scale)}
    if "state_head" in params:
        w, b = params["state_head"]["kernel"], params["state_head"]["bias"]
        out["state_head"] = {"kernel": w * sd[None], "bias": b * sd + mu}
    return out


__all__ = ["IONorm", "fit_io_norm", "fold_io_norm", "identity_norm", "normalise_dataset",
           "transition_norm"]
