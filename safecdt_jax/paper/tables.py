"""The paper's tables from the suite's experiment records, ours beside the paper's numbers.

Each `tableN(records, plan)` returns `(markdown, data)`: the table in the paper's layout and the
numbers behind it (used by the claims and tests). A record is missing when its experiment was
not run (e.g. uncached baselines under `--quick`); its table then says so.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from safecdt_jax.paper import reference as ref
from safecdt_jax.paper.plan import PaperPlan, ctg_variants
from safecdt_jax.results.tables import markdown_table, summarize_runs

Records = Mapping[str, Mapping[str, Any]]
MISSING = "(not run: see the header)"


def cell(mean: float, std: float) -> str:
    """`mean ± std` with two decimals."""
    return f"{mean:.2f} ± {std:.2f}"


def find_run(record: Mapping[str, Any], variant: str, budget: float | None = None
             ) -> dict[str, Any]:
    """The run of `variant` (at `budget`, when given) in a deployment record; KeyError if none."""
    for run in record["results"]["runs"]:
        if run["variant"] == variant and (budget is None or float(run["budget"]) == budget):
            return run
    raise KeyError(f"no run {variant} at budget {budget} in {record['spec']['name']}")


def summary(run: Mapping[str, Any], episodes: int | None = None) -> dict[str, float]:
    """Across-seed mean and std of the per-seed mean return, mean cost and VR of a run, over
    its first `episodes` episodes (all when None)."""
    cut = slice(None, episodes)
    checkpoints = int(run.get("summary", {}).get("checkpoints", 1))
    return summarize_runs({k: np.asarray(run["metrics"][k], np.float64)[:, cut]
                           for k in ("return", "cost", "violation")}, checkpoints)


def _ours(s: Mapping[str, float]) -> list[str]:
    """Reward, cost, VR (mean ± std over all seeds), the seed count (checkpoints x deployment
    seeds when several checkpoints ran) and VR's spread between checkpoints / across
    deployment seeds."""
    n_ckpt = int(s.get("checkpoints", 1))
    per_ckpt = s["seeds"] // n_ckpt
    seeds = f"{n_ckpt}×{per_ckpt}" if n_ckpt > 1 else str(s["seeds"])
    spread = "-"
    if n_ckpt > 1:  # with one deployment seed per checkpoint there is no spread across them
        within = f"{s['vr_within_std']:.1f}" if per_ckpt > 1 else "-"
        spread = f"{s['vr_between_std']:.1f} / {within}"
    return [cell(s["mean_return_mean"], s["mean_return_std"]),
            cell(s["mean_cost_mean"], s["mean_cost_std"]), cell(s["vr_mean"], s["vr_std"]),
            seeds, spread]


def _paper(row: tuple | None) -> list[str]:
    if row is None:
        return ["-"] * 3
    vr = cell(row[4], row[5]) if len(row) > 5 else f"{row[4]:.1f}"
    return [cell(row[0], row[1]), cell(row[2], row[3]), vr]


HEAD = ["Reward", "Cost", "VR (%)", "seeds", "VR sd: ckpt / deploy", "paper reward",
        "paper cost", "paper VR (%)"]


def table1(records: Records, plan: PaperPlan) -> tuple[str, dict]:
    """Table 1: Safe-CDT at the budget on each pair."""
    rows, data = [], {}
    for pair in plan.pairs:
        rec = records.get(f"{pair}_main")
        if rec is None:
            rows.append([pair, MISSING, "", "", "", "", *_paper(ref.TABLE1.get(pair))])
            continue
        s = data[pair] = summary(find_run(rec, "safe_cdt"))
        rows.append([pair.replace("-", "→"), *_ours(s), *_paper(ref.TABLE1.get(pair))])
    return markdown_table(["Pair", *HEAD], rows), data


def table2(records: Records, plan: PaperPlan) -> tuple[str, dict]:
    """Table 2: Safe-CDT on the study pair at each budget."""
    rec = records.get(f"{plan.study_pair}_studies")
    if rec is None:
        return MISSING, {}
    rows, data = [], {}
    for b in plan.budgets:
        s = data[b] = summary(find_run(rec, "safe_cdt", b))
        rows.append([f"B={b:g}", *_ours(s), *_paper(ref.TABLE2.get(b))])
    return markdown_table(["Budget", *HEAD], rows), data


def table3(records: Records, plan: PaperPlan) -> tuple[str, dict]:
    """Table 3: the ablation variants on the study pair at the budget."""
    rec = records.get(f"{plan.study_pair}_studies")
    if rec is None:
        return MISSING, {}
    rows, data = [], {}
    for v in plan.ablations:
        s = data[v] = summary(find_run(rec, v, plan.budget))
        rows.append([v, *_ours(s), *_paper(ref.TABLE3.get(v))])
    return markdown_table(["Variant", *HEAD], rows), data


def baseline_methods(records: Records, pair: str) -> list[dict[str, Any]]:
    """The baselines record's method entries of `pair` ([] when not run)."""
    rec = records.get(f"{pair}_baselines")
    return [] if rec is None else list(rec["results"]["methods"])


def table7(records: Records, plan: PaperPlan, pairs: tuple[str, ...] | None = None
           ) -> tuple[str, dict]:
    """Table 7 (and, for the study pair with Safe-CDT's row first, Table 4): every baseline per
    pair, ours beside the paper's."""
    from safecdt_jax.baselines.job import LABELS, PAPER_TABLE7

    rows, data = [], {}
    for pair in pairs or plan.pairs:
        methods = baseline_methods(records, pair)
        if not methods:
            rows.append([pair, "baselines", MISSING, "", "", "", "", "-", "-", "-"])
        for m in methods:
            s = data.setdefault(pair, {})[m["algo"]] = m["summary"]
            paper = PAPER_TABLE7.get(pair, {}).get(m["algo"])
            rows.append([pair.replace("-", "→"), LABELS[m["algo"]], *_ours(s), *_paper(paper)])
    return markdown_table(["Pair", "Method", *HEAD], rows), data


def table4(records: Records, plan: PaperPlan) -> tuple[str, dict]:
    """Table 4: the study pair's Safe-CDT row (Table 1's) above its baselines."""
    from safecdt_jax.baselines.job import PAPER_SAFE_CDT

    pair = plan.study_pair
    text, data = table7(records, plan, (pair,))
    rec = records.get(f"{pair}_main")
    if rec is None:
        return text, data
    s = summary(find_run(rec, "safe_cdt"))
    data.setdefault(pair, {})["safe_cdt"] = s
    label = f"Safe-CDT (online, {plan.episodes} episodes)"
    first = "| " + " | ".join([pair.replace("-", "→"), label, *_ours(s),
                               *_paper(PAPER_SAFE_CDT.get(pair))]) + " |"
    lines = text.split("\n")
    return "\n".join([*lines[:2], first, *lines[2:]]), data


def fixed_ratio_costs(record: Mapping[str, Any], plan: PaperPlan) -> dict[float, np.ndarray]:
    """Per fixed CTG ratio: the per-seed mean episode cost over the first `plan.episodes`
    episodes of the `ctg` experiment's fixed run ([seeds])."""
    out = {}
    for r in plan.ctg_ratios:
        cost = np.asarray(find_run(record, f"fixed_ctg({r:g})")["metrics"]["cost"], np.float64)
        out[r] = cost[:, :plan.episodes].mean(axis=1)
    return out


def table5(records: Records, plan: PaperPlan) -> tuple[str, dict]:
    """Table 5: mean cost per CTG ratio and the Spearman rho of cost against the ratio."""
    from safecdt_jax.analysis.evaluate import spearman

    ratios = list(plan.ctg_ratios)
    rows, data = [], {}
    for pair in plan.pairs:
        rec = records.get(f"{pair}_ctg")
        paper = ref.TABLE5.get(pair, {})
        prho = spearman(list(paper), list(paper.values())) if paper else float("nan")
        theirs = " / ".join(f"{paper[r]:.2f}" if r in paper else "-" for r in ratios)
        if rec is None:
            rows.append([pair, MISSING, *[""] * (len(ratios) + 2), theirs, f"{prho:.1f}", "-"])
            continue
        costs = fixed_ratio_costs(rec, plan)
        means = [float(costs[r].mean()) for r in ratios]
        rho = spearman(ratios, means)
        low_high = means[0] / means[-1] if means[-1] > 0 else float("nan")
        data[pair] = {"means": dict(zip(ratios, means, strict=True)), "spearman": rho,
                      "stds": {r: float(costs[r].std()) for r in ratios},
                      "low_high": low_high}
        rows.append([pair.replace("-", "→"), *(cell(m, costs[r].std()) for m, r in
                                               zip(means, ratios, strict=True)),
                     f"{rho:.2f}", f"{max(means) - min(means):.2f}", f"{low_high:.2f}", theirs,
                     f"{prho:.1f}",
                     f"{max(paper.values()) - min(paper.values()):.2f}" if paper else "-"])
    head = ["Pair", *(f"CR {r:g}" for r in ratios), "Spearman", "range",
            f"CR {ratios[0]:g} / CR {ratios[-1]:g}", "paper costs", "paper rho", "paper range"]
    return markdown_table(head, rows), data


def switch_deltas(run: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Per seed: the mean cost and VR (pp) of the second half of a run minus the first's."""
    cost = np.asarray(run["metrics"]["cost"], np.float64)
    viol = np.asarray(run["metrics"]["violation"], np.float64)
    h = cost.shape[1] // 2
    return {"cost": cost[:, h:].mean(1) - cost[:, :h].mean(1),
            "vr": 100 * (viol[:, h:].mean(1) - viol[:, :h].mean(1))}


def table6(records: Records, plan: PaperPlan) -> tuple[str, dict]:
    """Table 6: cost and VR deltas (second half minus first) of the step changes, with the seeds
    whose cost moved the expected way, and of fixed controls beside them (drift)."""
    *_, up, down = ctg_variants(plan)
    controls = [r for r in (plan.step_low, 0.6, plan.step_high) if r in plan.ctg_ratios]
    rows, data = [], {}
    for pair in plan.pairs:
        rec = records.get(f"{pair}_ctg")
        if rec is None:
            rows.append([pair, MISSING, "", "", "", "-", "-", "-"])
            continue
        for label, variant, sign in [("low->high", up, 1), ("high->low", down, -1)] + [
                (f"fixed {r:g}", f"fixed_ctg({r:g})", 0) for r in controls]:
            d = switch_deltas(find_run(rec, variant))
            n = len(d["cost"])
            hits = int(np.sum(np.sign(d["cost"]) == sign)) if sign else None
            data[(pair, label)] = {"cost": float(d["cost"].mean()),
                                   "cost_std": float(d["cost"].std()),
                                   "vr": float(d["vr"].mean()), "direction": hits, "seeds": n}
            p = ref.TABLE6.get((pair, label))
            rows.append([pair.replace("-", "→"), label.replace("->", "→"),
                         cell(d["cost"].mean(), d["cost"].std()), f"{d['vr'].mean():+.1f}",
                         "-" if hits is None else f"{hits}/{n}",
                         "-" if p is None else cell(p[0], p[1]),
                         "-" if p is None else f"{p[2]:+.1f}", "-" if p is None else f"{p[3]}/5"])
    head = ["Pair", "Switch", "Δ Cost", "Δ VR (pp)", "Direction", "paper Δ cost",
            "paper Δ VR", "paper direction"]
    return markdown_table(head, rows), data


def certificate_inputs(records: Records, pair: str, plan: PaperPlan
                       ) -> tuple[dict, dict] | None:
    """(target, source) results records for `theory.certify_results`: the `ctg` experiment's
    fixed runs over the first `plan.episodes` episodes, and the `source_ctg` experiment."""
    rec, src = records.get(f"{pair}_ctg"), records.get(f"{pair}_source_ctg")
    if rec is None or src is None:
        return None
    runs = [dict(run, metrics={k: np.asarray(v)[:, :plan.episodes].tolist()
                               for k, v in run["metrics"].items()})
            for run in rec["results"]["runs"] if run["variant"].startswith("fixed_ctg")]
    target = {"deploy_config": {"episodes": plan.episodes}, "runs": runs}
    return target, src["results"]


def certificates(records: Records, plan: PaperPlan) -> tuple[str, dict]:
    """The safety certificate (docs/METHOD.md section 7) of every pair from its CTG sweeps."""
    from safecdt_jax.theory import certificate_table, certify_results

    parts, data = [], {}
    for pair in plan.pairs:
        inputs = certificate_inputs(records, pair, plan)
        if inputs is None:
            parts.append(f"#### {pair}\n\n{MISSING}\n")
            continue
        cert = data[pair] = certify_results(inputs[0], plan.budget, plan.alpha, plan.kappa,
                                            inputs[1])
        holds = sum(c["thm41_holds"] for c in cert["conditions"])
        parts.append(f"#### {pair.replace('-', '→')}\n\n{certificate_table(cert)}\n"
                     f"The measured VR lies within Theorem 4.1's bound at {holds} of "
                     f"{len(cert['conditions'])} conditions (the bound assumes sub-Gaussian "
                     f"episode costs with the sample sigma).\n")
    return "\n".join(parts), data
