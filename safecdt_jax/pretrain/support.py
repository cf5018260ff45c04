"""The support of a checkpoint's training labels, and the note a deployment or an evaluation
prints when it asks for targets outside it ("targets outside the support of offline data", the
failure mode the Safe-CDT paper names)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from safecdt_jax.data.windows import episode_costs, episode_returns, trajectory_weights


def label_support(data, c0: float) -> dict[str, list[float]]:
    """`{"return": [lo, hi], "cost": [lo, hi]}`: the range of the t = 0 return and cost labels
    (raw units) of the episodes pretraining samples (OSRL weight `max(0, c0 - C_i)` > 0), the
    labels already applied (`pretrain.loop.labelled`); relabelled copies not included."""
    drawn = trajectory_weights(data, c0=c0) > 0
    ret, cost = episode_returns(data)[drawn], episode_costs(data)[drawn]
    return {"return": [float(ret.min()), float(ret.max())],
            "cost": [float(cost.min()), float(cost.max())]}


def checkpoint_support(meta: dict[str, Any]) -> dict[str, list[float]] | None:
    """The label support a checkpoint's `meta` records (`token_support`: the lowest and highest
    return and cost label it was trained on, raw units), or None where it has none."""
    return meta.get("token_support")


def _outside(values: Iterable[float], lo: float, hi: float) -> list[float]:
    return sorted({round(float(v), 2) for v in values if not lo - 1e-6 <= v <= hi + 1e-6})


def support_note(support: dict[str, list[float]] | None, returns: Iterable[float],
                 costs: Iterable[float]) -> str | None:
    """One line naming the return and cost targets (raw) outside `support`, or None when every
    target lies inside it (or the support is unknown). The model still reads such a target as
    its own input (the ramps' end bins), but no training episode was labelled with it."""
    if not support:
        return None
    (r_lo, r_hi), (c_lo, c_hi) = support["return"], support["cost"]
    bad_r, bad_c = _outside(returns, r_lo, r_hi), _outside(costs, c_lo, c_hi)
    if not (bad_r or bad_c):
        return None
    parts = [f"cost targets {', '.join(f'{c:g}' for c in bad_c)}" if bad_c else "",
             f"return targets {', '.join(f'{r:g}' for r in bad_r)}" if bad_r else ""]
    asked = " and ".join(p for p in parts if p)
    return (f"note: {asked} lie outside the labels the model was trained on (return "
            f"{r_lo:.1f} to {r_hi:.1f}, cost {c_lo:.1f} to {c_hi:.1f}); it extrapolates there")


def requested_targets(runs, cfg, reference_return: float) -> tuple[np.ndarray, np.ndarray]:
    """The raw return and cost targets a deployment's runs ask for: each run's fixed cost
    targets, and for a scheduled run the ends of the range its cost target moves in (`cr_min B`
    to `cr_max B`); every run's return target starts at `rr0 R_ref` (the scheduler raises it
    only while the runs are safe, so its range is not counted). `runs`: (Variant, budget)
    pairs; `cfg` the `DeployConfig`."""
    returns, costs = [], []
    for variant, budget in runs:
        if bool(variant.scheduler):
            costs += [cfg.cr_min * budget, cfg.cr_max * budget]
        else:
            costs += [float(variant.cr_first) * budget, float(variant.cr_second) * budget]
        returns.append(cfg.rr0 * reference_return)
    return np.asarray(returns), np.asarray(costs)
