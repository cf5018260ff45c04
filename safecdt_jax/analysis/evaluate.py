"""Evaluate a pretrained CDT at several (return, cost) targets in one vmapped program, and say
how well its cost follows the cost target.

    res = evaluate_policy(ckpt, "PointCircle1", [(14.9, 10), (14.9, 20), (14.9, 40)], episodes=20)
    median = summarize_dataset(data_path)["cost_median"]          # the data's, cost steps
    summary = summarize_evaluation("PointCircle1", res, data_median=median)
    print(evaluation_table(summary))   # per-target means, Spearman, the data's median cost

The cost-following check of a pretrained CDT (docs/METHOD.md section 9) reads off the summary: the
Spearman rank correlation of the mean episode cost with the cost target at one return target
(>= 0.8 wanted), and the mean cost at a low target against the data's median episode cost.
"""

from __future__ import annotations

import os
from typing import Any

import jax
import numpy as np


def parse_targets(text: str) -> list[tuple[float, float]]:
    """`"40:20,40:40"` -> [(40.0, 20.0), (40.0, 40.0)]: RETURN:COST pairs in raw units."""
    out = []
    for item in (t.strip() for t in text.split(",")):
        parts = item.split(":")
        try:
            if len(parts) != 2:
                raise ValueError
            ret, cost = float(parts[0]), float(parts[1])
        except ValueError:
            raise ValueError(f"bad target {item!r}: expected RETURN:COST, e.g. 40:20") from None
        if not (np.isfinite(ret) and np.isfinite(cost)):
            raise ValueError(f"bad target {item!r}: targets must be finite numbers")
        if cost < 0:
            raise ValueError(f"bad target {item!r}: the cost target must be >= 0")
        out.append((ret, cost))
    return out


ACTION_MODES = {"checkpoint": None, "mean": False, "sample": True}

# How every entry point (the CLI's `--act`, `PaperPlan.act`, `api.deploy` / `api.evaluate`)
# makes the CDT act unless told: samples of its policy. Every data set's labels are outcomes of
# experts that acted with samples, and so are its recorded actions, so a clone acting with its
# mean is another policy than the one its tokens describe; acting with samples cut zero-shot's
# VR from 41.6 to 28.7% on CC1-CC2 and from 20.2 to 11.8% on PC1-PC2 (docs/METHOD.md
# section 1). The functions under them take None for the checkpoint's own
# `CDTConfig.stochastic_actions` (False, OSRL's mean, in every preset).
DEFAULT_ACTION_MODE = "sample"


def parse_action_mode(text: str) -> bool | None:
    """`--act` of `evaluate`, `deploy` and `run`: "checkpoint" -> None (the checkpoint's own
    `CDTConfig.stochastic_actions`), "mean" -> False, "sample" -> True."""
    if text not in ACTION_MODES:
        raise ValueError(f"unknown action mode {text!r}: expected one of "
                         f"{', '.join(ACTION_MODES)}")
    return ACTION_MODES[text]


def _evaluate_targets(key, env, env_params, params, cfg, target_returns, target_costs, episodes,
                      horizon):
    from safecdt_jax.deploy.rollout import evaluate_targets

    return evaluate_targets(key, env, env_params, params, cfg, target_returns, target_costs,
                            episodes, horizon=horizon)


# Params, env params and targets are arguments, not constants: every checkpoint of one shape
# shares one compiled program (a closure over the params recompiled per checkpoint).
_evaluate = jax.jit(_evaluate_targets, static_argnames=("env", "cfg", "episodes", "horizon"))


def evaluate_policy(ckpt: str | os.PathLike, task: str, targets: list[tuple[float, float]],
                    episodes: int, seed: int = 0, horizon: int | None = None,
                    dynamics: dict[str, float] | None = None,
                    stochastic_actions: bool | None = None) -> dict[str, np.ndarray]:
    """Episode returns and costs [n_targets, episodes] of checkpoint `ckpt` in `task`, its
    dynamics shifted by `dynamics` ({field: scale}, `envs.dynamics`; None: nominal).

    Every target runs on the same `episodes` layouts (keys from `seed`), in one jitted call,
    reading the tokens as the checkpoint's model config encodes them. `horizon` cuts every
    episode at that many steps (default: the task's time limit). `stochastic_actions` acts with
    samples of the policy (True) or its mean (False); None keeps the checkpoint's own setting
    (`CDTConfig.stochastic_actions`). Also returns the targets as `target_return` and
    `target_cost` [n_targets] (raw units), how the policy acted (`stochastic_actions`) and
    `support_note` (`pretrain.support.support_note`: targets outside the training labels).
    """
    from safecdt_jax import envs
    from safecdt_jax.envs.dynamics import apply_dynamics
    from safecdt_jax.pretrain.checkpoint import load_policy, with_action_mode
    from safecdt_jax.pretrain.support import checkpoint_support, support_note

    env, params = envs.make(task)
    params = apply_dynamics(params, dynamics or {})
    policy = with_action_mode(load_policy(ckpt, task=task), stochastic_actions)
    rets = np.array([t[0] for t in targets])  # float64: reported as given
    costs = np.array([t[1] for t in targets])
    res = jax.device_get(_evaluate(jax.random.PRNGKey(seed), env, params, policy.params,
                                   policy.cfg, rets.astype(np.float32), costs.astype(np.float32),
                                   episodes, horizon=horizon))
    note = support_note(checkpoint_support(policy.meta), rets, costs)
    return {"target_return": rets, "target_cost": costs, "returns": np.asarray(res.returns),
            "costs": np.asarray(res.costs), "stochastic_actions": policy.cfg.stochastic_actions,
            "support_note": note}


def _ranks(values: np.ndarray) -> np.ndarray:
    """1-based ranks of `values`; tied values share the mean of the ranks they span."""
    order = np.argsort(values, kind="stable")
    ranks = np.empty(len(values))
    ranks[order] = np.arange(1, len(values) + 1)
    for v in np.unique(values):
        tied = values == v
        ranks[tied] = ranks[tied].mean()
    return ranks


def spearman(x, y) -> float:
    """Spearman's rank correlation of two equal-length sequences, in [-1, 1]: the Pearson
    correlation of their ranks (ties share their mean rank). NaN when either sequence has fewer
    than two distinct values, where the correlation is undefined. Exact to 12 decimals."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f"spearman needs two 1-d sequences of one length, got {x.shape} and "
                         f"{y.shape}")
    if len(np.unique(x)) < 2 or len(np.unique(y)) < 2:
        return float("nan")
    # Rounded: the rank correlation of n points is a ratio of small integers, and float
    # summation left 0.8 at 0.7999999999999999, failing a ">= 0.8" criterion it meets.
    return round(float(np.corrcoef(_ranks(x), _ranks(y))[0, 1]), 12)


def summarize_evaluation(task: str, res: dict[str, np.ndarray],
                         data_median: float | None = None) -> dict[str, Any]:
    """A JSON-ready summary of an `evaluate_policy` result.

    Holds the per-target rows (mean return, mean cost, VR: % of episodes whose cost exceeds the
    target's cost), the per-episode returns and costs, and, for every return target run at two
    or more distinct cost targets, the Spearman correlation of mean cost with cost target (None
    where the mean costs all tie).
    `data_median` (the data set's median episode cost, cost steps) is kept for comparison.
    """
    rets, costs = res["target_return"], res["target_cost"]
    mean_cost = res["costs"].mean(axis=1)
    rows = [{"target_return": float(r), "target_cost": float(c),
             "mean_return": float(res["returns"][i].mean()), "mean_cost": float(mean_cost[i]),
             "vr_percent": float(100 * (res["costs"][i] > c).mean())}
            for i, (r, c) in enumerate(zip(rets, costs, strict=True))]
    following = []
    for r in dict.fromkeys(rets.tolist()):  # return targets in the order given
        at = rets == r
        if len(np.unique(costs[at])) >= 2:
            rho = spearman(costs[at], mean_cost[at])  # NaN (JSON null) if all costs tie
            following.append({"target_return": float(r),
                              "spearman": None if np.isnan(rho) else rho})
    return {"task": task, "episodes": int(res["costs"].shape[1]), "rows": rows,
            "cost_following": following,
            "data_median_cost": None if data_median is None else float(data_median),
            "returns": res["returns"].tolist(), "costs": res["costs"].tolist()}


def evaluation_table(summary: dict[str, Any]) -> str:
    """Markdown: the per-target table of `summarize_evaluation`, then one line per return target
    with the Spearman correlation of mean cost with cost target, and the data's median cost."""
    from safecdt_jax.envs.dynamics import shift_label

    shift = summary.get("dynamics", {})
    lines = [f"{summary['task']}" + (f" ({shift_label(shift)})" if shift else "")
             + f", {summary['episodes']} episodes per target"
             + (", sampled actions" if summary.get("stochastic_actions") else ""), "",
             "| target return | target cost | mean return | mean cost | VR (%) |",
             "|---|---|---|---|---|"]
    lines += [f"| {row['target_return']:g} | {row['target_cost']:g} | {row['mean_return']:.2f} | "
              f"{row['mean_cost']:.1f} | {row['vr_percent']:.0f} |" for row in summary["rows"]]
    if summary["cost_following"]:
        lines.append("")
    for f in summary["cost_following"]:
        rho = "undefined (equal mean costs)" if f["spearman"] is None else f"{f['spearman']:.2f}"
        lines.append(f"cost follows the target at return {f['target_return']:g}: Spearman {rho}")
    median = summary["data_median_cost"]
    if median is not None:
        below = [f"{row['target_return']:g}:{row['target_cost']:g}" for row in summary["rows"]
                 if row["mean_cost"] < median]
        lines.append(f"data median episode cost {median:.1f}; mean cost below it at targets "
                     f"(RETURN:COST): {', '.join(below) or 'none'}")
    return "\n".join(lines)


def evaluate_checkpoint(ckpt: str | os.PathLike, task: str, targets: list[tuple[float, float]],
                        episodes: int, seed: int = 0, horizon: int | None = None,
                        data_median: float | None = None,
                        dynamics: dict[str, float] | None = None,
                        stochastic_actions: bool | None = None) -> dict[str, Any]:
    """`evaluate_policy` then `summarize_evaluation`: the summary dict, with the checkpoint
    folder, seed, horizon, dynamics shift and whether the actions were sampled added (see
    `evaluation_table` to print it)."""
    res = evaluate_policy(ckpt, task, targets, episodes, seed, horizon, dynamics,
                          stochastic_actions)
    summary = summarize_evaluation(task, res, data_median)
    return {"checkpoint": os.fspath(ckpt), "seed": seed, "horizon": horizon,
            "dynamics": dict(dynamics or {}), "stochastic_actions": res["stochastic_actions"],
            "support_note": res["support_note"], **summary}
