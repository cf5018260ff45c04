"""The paper's deployment-time safety theory (its section 4), computable from measured episodes.

Per CTG condition c (the cost-to-go target an episode ran with): phi(c) is the mean episode
cost and sigma(c) the sub-Gaussian scale, estimated here by the sample standard deviation
(ddof = 1), which is what makes the bounds usable at all and also what makes them optimistic
for skewed, capped costs: beside every bound stands the empirical rate it bounds, so a user
sees where the assumptions fail. Costs are in cost steps, budgets in the same unit.

    table = certificate(costs_by_condition, budget=30.0, episodes=50, alpha=0.05)
    print(certificate_table(table))
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np


def condition_stats(costs_by_condition: Mapping[float, Sequence[float]]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(conditions c, phi(c), sigma(c), episode counts), sorted by c, from the episode costs
    measured at each condition; sigma is the sample std (ddof 1; 0 for a single episode)."""
    if not costs_by_condition:
        raise ValueError("no CTG conditions given")
    cs = sorted(costs_by_condition)
    phi, sigma, n = [], [], []
    for c in cs:
        x = np.asarray(costs_by_condition[c], np.float64)
        if x.size == 0:
            raise ValueError(f"CTG condition {c:g} has no episodes")
        phi.append(x.mean())
        sigma.append(x.std(ddof=1) if x.size > 1 else 0.0)
        n.append(x.size)
    return np.asarray(cs, np.float64), np.asarray(phi), np.asarray(sigma), np.asarray(n)


def single_episode_bound(phi, sigma, budget: float) -> np.ndarray:
    """Theorem 4.1: a lower bound on P(C <= B | c), 1 - exp(-delta^2 / (2 sigma^2)) with
    delta = B - phi(c) > 0; 0 (nothing certified) where delta <= 0; 1 where sigma = 0 < delta."""
    phi, sigma = np.asarray(phi, np.float64), np.asarray(sigma, np.float64)
    delta = budget - phi
    with np.errstate(divide="ignore", invalid="ignore"):
        tail = np.where(sigma > 0, np.exp(-delta**2 / (2 * sigma**2)), 0.0)
    return np.where(delta > 0, 1.0 - tail, 0.0)


def multi_episode_bound(phi, sigma, budget: float, episodes: int) -> np.ndarray:
    """Theorem 4.2: a lower bound on P(every one of N episodes costs <= B | c), the single
    bound to the power N."""
    return single_episode_bound(phi, sigma, budget) ** episodes


def sufficient_margin(sigma, episodes: int, alpha: float) -> np.ndarray:
    """Theorem 4.2: the margin delta >= sigma sqrt(2 log(N / alpha)) that makes all N episodes
    safe with probability >= 1 - alpha."""
    _check_alpha(alpha, episodes)
    return np.asarray(sigma, np.float64) * math.sqrt(2.0 * math.log(episodes / alpha))


def critical_budget(conditions, phi, sigma, kappa: float = 1.0) -> tuple[float, float]:
    """Definition 4.1: (B*, the condition attaining it), B* = min_c phi(c) + kappa sigma(c)."""
    score = np.asarray(phi, np.float64) + kappa * np.asarray(sigma, np.float64)
    i = int(np.argmin(score))
    return float(score[i]), float(np.asarray(conditions)[i])


def certified_budget(conditions, phi, sigma, episodes: int, alpha: float,
                     kappa: float = 1.0) -> float:
    """Theorem 4.3(c): B* + sigma_max sqrt(2 log(N / alpha)), the smallest budget at which the
    theory certifies P(any of N episodes > B) <= alpha."""
    _check_alpha(alpha, episodes)
    b_star, _ = critical_budget(conditions, phi, sigma, kappa)
    return b_star + float(np.max(sigma)) * math.sqrt(2.0 * math.log(episodes / alpha))


def threshold_bound(budget: float, b_star: float, sigma_max: float, episodes: int) -> float:
    """Theorem 4.3(b) with the union bound: P(some of N episodes > B) <=
    N exp(-(B - B*)^2 / (2 sigma_max^2)) for B > B* (1.0, nothing certified, otherwise)."""
    if budget <= b_star:
        return 1.0
    if sigma_max == 0:
        return 0.0
    return min(1.0, episodes * math.exp(-(budget - b_star) ** 2 / (2 * sigma_max**2)))


def transfer_check(phi_source, phi_target, sigma_target, condition_index: int, budget: float,
                   kappa: float = 1.0) -> dict[str, Any]:
    """Theorem 4.4 from source and target sweeps at the same conditions: delta_1 = B -
    phi_1(c*), Delta_M = max_c |phi_1(c) - phi_2(c)|, sigma_2 = max_c sigma_2(c); the transfer
    holds when Delta_M < delta_1 - kappa sigma_2, and then P(C > B | c*, target) <=
    exp(-kappa^2 / 2)."""
    p1, p2 = np.asarray(phi_source, np.float64), np.asarray(phi_target, np.float64)
    if p1.shape != p2.shape:
        raise ValueError(f"source and target sweeps have {p1.size} and {p2.size} conditions; "
                         f"the transfer check needs the same conditions")
    delta1 = budget - float(p1[condition_index])
    shift = float(np.max(np.abs(p1 - p2)))
    sigma2 = float(np.max(sigma_target))
    return {"delta_1": delta1, "delta_M": shift, "sigma_2": sigma2,
            "margin_needed": delta1 - kappa * sigma2, "holds": shift < delta1 - kappa * sigma2,
            "target_margin_at_least": delta1 - shift, "bound": math.exp(-kappa**2 / 2)}


def _check_alpha(alpha: float, episodes: int) -> None:
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha!r}")
    if not (isinstance(episodes, int) and episodes >= 1):
        raise ValueError(f"the episode count N must be a positive integer, got {episodes!r}")


def certificate(costs_by_condition: Mapping[float, Sequence[float]], budget: float,
                episodes: int, alpha: float = 0.05, kappa: float = 1.0) -> dict[str, Any]:
    """Every quantity of the theory for one environment: per condition phi, sigma, the
    empirical violation rate (cost > B) and the Theorem 4.1 / 4.2 bounds on it, the sufficient
    margin; overall B*, the certified budget and the Theorem 4.3 bound at `budget`, with the
    empirical rate of a violation among N episodes beside it."""
    if not budget > 0:
        raise ValueError(f"the budget must be positive, got {budget!r}")
    _check_alpha(alpha, episodes)
    cs, phi, sigma, n = condition_stats(costs_by_condition)
    single = single_episode_bound(phi, sigma, budget)
    vr = np.asarray([np.mean(np.asarray(costs_by_condition[c]) > budget) for c in cs])
    b_star, c_dagger = critical_budget(cs, phi, sigma, kappa)
    rows = [{"ctg": float(c), "episodes": int(k), "phi": float(p), "sigma": float(s),
             "margin": float(budget - p), "violation_rate": float(v),
             "thm41_violation_bound": float(1.0 - b1),
             # The bound assumes sub-Gaussian costs with this sigma; mostly-zero costs with a
             # tail at B + 1 (the runtime budget) can break it, and the user should see that.
             "thm41_holds": bool(v <= 1.0 - b1),
             "thm42_all_safe_bound": float(b1**episodes),
             "empirical_all_safe": float((1.0 - v) ** episodes),
             "sufficient_margin": float(m)}
            for c, k, p, s, v, b1, m in zip(cs, n, phi, sigma, vr, single,
                                            sufficient_margin(sigma, episodes, alpha),
                                            strict=True)]
    sigma_max = float(sigma.max())
    certified = certified_budget(cs, phi, sigma, episodes, alpha, kappa)
    return {"budget": budget, "episodes": episodes, "alpha": alpha, "kappa": kappa,
            "sigma_estimator": "sample std (ddof 1)", "conditions": rows,
            "critical_budget": b_star, "critical_condition": c_dagger, "sigma_max": sigma_max,
            "certified_budget": certified,
            "thm43_any_violation_bound": threshold_bound(budget, b_star, sigma_max, episodes),
            "certified": budget >= certified}


def costs_by_ctg(results: Mapping[str, Any], budget: float | None = None,
                 decimals: int = 3) -> dict[float, list[float]]:
    """Episode costs of a deployment `results.json` grouped by the CTG target each episode ran
    with (rounded to `decimals`), over every run (of `budget` only, when given) and seed."""
    out: dict[float, list[float]] = {}
    runs = results.get("runs")
    if not runs:
        raise ValueError("the results hold no runs (expected a deployment results.json)")
    for run in runs:
        if budget is not None and float(run["budget"]) != float(budget):
            continue
        ctg = np.round(np.asarray(run["metrics"]["ctg_target"], np.float64), decimals)
        cost = np.asarray(run["metrics"]["cost"], np.float64)
        for c, x in zip(ctg.ravel(), cost.ravel(), strict=True):
            out.setdefault(float(c), []).append(float(x))
    if not out:
        raise ValueError(f"no run at budget {budget:g} in the results")
    return out


def certify_results(results: Mapping[str, Any], budget: float, alpha: float = 0.05,
                    kappa: float = 1.0, source: Mapping[str, Any] | None = None
                    ) -> dict[str, Any]:
    """The certificate of a deployment results record (`results.json`'s content) at `budget`
    (its runs at that budget; N = the deployment's episodes per seed); with `source`, a second
    record measured at the same CTG conditions in the source task, the transfer check too (at
    the condition of the target's critical budget)."""
    episodes = int(results.get("deploy_config", {}).get("episodes", 50))
    by_c = costs_by_ctg(results, budget)
    cert = certificate(by_c, budget, episodes, alpha, kappa)
    if source is not None:
        src = costs_by_ctg(source)
        common = sorted(set(src) & set(by_c))
        if not common:
            raise ValueError("source and target results share no CTG condition")
        _, p1, _, _ = condition_stats({c: src[c] for c in common})
        _, p2, s2, _ = condition_stats({c: by_c[c] for c in common})
        i = common.index(cert["critical_condition"]) if cert["critical_condition"] in common \
            else int(np.argmin(p1))
        cert["transfer"] = transfer_check(p1, p2, s2, i, budget, kappa) | {
            "condition": common[i], "conditions": common}
    return cert


def certify_file(path: str | os.PathLike, budget: float, alpha: float = 0.05,
                 kappa: float = 1.0, source: str | os.PathLike | None = None) -> dict[str, Any]:
    """`certify_results` of the results file `path` (and of the source results file `source`,
    when given)."""
    src = None if source is None else json.loads(Path(source).read_text())
    return certify_results(json.loads(Path(path).read_text()), budget, alpha, kappa, src)


def certificate_table(cert: Mapping[str, Any]) -> str:
    """The certificate as markdown: one row per CTG condition, then the budget lines."""
    from safecdt_jax.results.tables import markdown_table

    rows = [[f"{r['ctg']:g}", r["episodes"], f"{r['phi']:.2f}", f"{r['sigma']:.2f}",
             f"{r['margin']:.2f}", f"{100 * r['violation_rate']:.1f}",
             f"{100 * r['thm41_violation_bound']:.1f}", "yes" if r["thm41_holds"] else "**no**",
             f"{r['thm42_all_safe_bound']:.3f}",
             f"{r['empirical_all_safe']:.3f}", f"{r['sufficient_margin']:.2f}"]
            for r in cert["conditions"]]
    table = markdown_table(
        ["CTG", "episodes", "phi", "sigma", "margin B - phi", "VR (%)",
         "Thm 4.1 bound on VR (%)", "VR within it", f"Thm 4.2 P(all {cert['episodes']} safe) >=",
         "empirical (1 - VR)^N", f"sufficient margin (alpha {cert['alpha']:g})"], rows)
    lines = [table, "",
             f"Critical budget B* = {cert['critical_budget']:.2f} (at CTG "
             f"{cert['critical_condition']:g}, kappa {cert['kappa']:g}); certified budget for "
             f"N = {cert['episodes']}, alpha = {cert['alpha']:g}: "
             f"{cert['certified_budget']:.2f} ({'met' if cert['certified'] else 'not met'} at "
             f"B = {cert['budget']:g}); Thm 4.3 bound on a violation among N episodes at "
             f"B: {cert['thm43_any_violation_bound']:.3g}. sigma: {cert['sigma_estimator']}."]
    if "transfer" in cert:
        t = cert["transfer"]
        lines.append(f"Transfer (Thm 4.4, CTG {t['condition']:g}): delta_1 = {t['delta_1']:.2f}, "
                     f"Delta_M = {t['delta_M']:.2f}, sigma_2 = {t['sigma_2']:.2f}: "
                     f"{'holds' if t['holds'] else 'does not hold'} (needs Delta_M < "
                     f"{t['margin_needed']:.2f}); target margin >= "
                     f"{t['target_margin_at_least']:.2f}.")
    return "\n".join(lines) + "\n"


__all__ = ["certificate", "certificate_table", "certified_budget", "certify_file",
           "certify_results", "condition_stats", "costs_by_ctg", "critical_budget",
           "multi_episode_bound", "single_episode_bound", "sufficient_margin", "threshold_bound",
           "transfer_check"]
