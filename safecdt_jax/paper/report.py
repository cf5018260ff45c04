"""`REPORT.md` and its figures from the suite's experiment records (generated, never edited).

The report holds every table of the paper's evaluation in its layout with the paper's numbers
beside ours, each claim of that section with whether our run supports it, the safety
certificate per pair, Figure 2, per-episode traces and a reward-cost scatter per pair, and a
header with the machine, versions, counts and the time each experiment took.
"""

from __future__ import annotations

import itertools
import math
import os
import platform
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from safecdt_jax.paper import reference as ref
from safecdt_jax.paper import tables as T
from safecdt_jax.paper.plan import PaperPlan, experiments

# The paper's protocol: the plan's defaults, on one pretrained checkpoint per pair.
PAPER_COUNTS = PaperPlan(pretrain_seeds=1)


def _claim(section: str, text: str, paper: str, ours: str | None, ok: bool | None
           ) -> dict[str, Any]:
    return {"section": section, "claim": text, "paper": paper,
            "ours": "(not run)" if ours is None else ours, "supported": ok}


def claims(data: Mapping[str, dict], plan: PaperPlan) -> list[dict[str, Any]]:
    """Each claim of the paper's section 5 checked on our tables' numbers (`supported` is None
    when the experiments it needs were not run)."""
    b, sp = plan.budget, plan.study_pair
    t1, t2, t3, t4, t5, t6 = (data[k] for k in ("t1", "t2", "t3", "t4", "t5", "t6"))
    out = []
    s = t1.get(sp)
    out.append(_claim("5.2", f"Safe-CDT's mean cost on {sp} is well below B (at most B/2)",
                      "8.56 at B = 30", None if s is None else f"{s['mean_cost_mean']:.2f}",
                      None if s is None else s["mean_cost_mean"] <= b / 2))
    base = {a: t4.get(sp, {}).get(a) for a in ("bcql", "bearl", "cpq")}
    have = s is not None and all(v is not None for v in base.values())
    for what, key, paper in (("VR", "vr_mean", "14.4 vs 28.3-95.0"),
                             ("cost", "mean_cost_mean", "8.56 vs 11.75-30.75")):
        out.append(_claim("5.2/5.5", f"Safe-CDT has the lowest {what} of Safe-CDT, BCQL, BEARL "
                          f"and CPQ on {sp}", paper,
                          None if not have else f"{s[key]:.2f} vs " + ", ".join(
                              f"{a} {v[key]:.2f}" for a, v in base.items()),
                          None if not have else s[key] < min(v[key] for v in base.values())))
    vrs = {p: v["vr_mean"] for p, v in t1.items()}
    out.append(_claim("5.2", "VR depends on the pair (spread of at least 10 pp across pairs)",
                      "14.4 / 24.7 / 56.0", " / ".join(f"{v:.1f}" for v in vrs.values())
                      if len(vrs) > 1 else None,
                      max(vrs.values()) - min(vrs.values()) >= 10 if len(vrs) > 1 else None))
    if t2:
        low = min(plan.budgets)
        rest = [t2[x]["vr_mean"] for x in plan.budgets if x >= b]
        out.append(_claim("5.3", f"VR at B = {low:g} exceeds VR at every B >= {b:g}",
                          "24.7 vs 9.3-14.0", f"{t2[low]['vr_mean']:.1f} vs " + ", ".join(
                              f"{v:.1f}" for v in rest), all(t2[low]["vr_mean"] > v for v in rest)))
        mono = all(x >= y for x, y in itertools.pairwise(rest)) or all(
            x <= y for x, y in itertools.pairwise(rest))
        out.append(_claim("5.3", f"VR is non-monotone in B over B >= {b:g}",
                          "12.7, 14.0, 9.3, 10.0", ", ".join(f"{v:.1f}" for v in rest), not mono))
    else:
        out += [_claim("5.3", "VR at the lowest budget exceeds VR at every B >= 30", "", None,
                       None), _claim("5.3", "VR is non-monotone in B", "", None, None)]
    if t3:
        means = [v["vr_mean"] for v in t3.values()]
        spread, std = max(means) - min(means), max(v["vr_std"] for v in t3.values())
        out.append(_claim("5.4", "All variants reach similar VR (spread within the largest "
                          "seed std)", "14.0-16.7, std up to 7.2",
                          f"{min(means):.1f}-{max(means):.1f}, std up to {std:.1f}",
                          spread <= std))
        zs, full = t3.get("zero_shot"), t3.get("safe_cdt")
        ok = None if zs is None or full is None else abs(zs["vr_mean"] - full["vr_mean"]) <= \
            full["vr_std"]
        out.append(_claim("5.4", "Zero-shot VR lies within one seed std of Safe-CDT's",
                          "15.6 vs 16.7 ± 5.8", None if ok is None else
                          f"{zs['vr_mean']:.1f} vs {full['vr_mean']:.1f} ± {full['vr_std']:.1f}",
                          ok))
    else:
        out += [_claim("5.4", "All variants reach similar VR", "", None, None),
                _claim("5.4", "Zero-shot VR within one std of Safe-CDT's", "", None, None)]
    sat = [base[a] for a in ("bcql", "bearl")]
    out.append(_claim("5.5", f"BCQL and BEARL saturate the budget on {sp} (cost >= 0.8 B)",
                      "24.72, 30.75", None if None in sat else ", ".join(
                          f"{v['mean_cost_mean']:.2f}" for v in sat),
                      None if None in sat else all(v["mean_cost_mean"] >= 0.8 * b for v in sat)))
    cpq = base["cpq"]
    out.append(_claim("5.5", f"CPQ is over-conservative on {sp} (cost <= B/2, reward <= 1)",
                      "cost 11.75, reward -0.55", None if cpq is None else
                      f"cost {cpq['mean_cost_mean']:.2f}, reward {cpq['mean_return_mean']:.2f}",
                      None if cpq is None else cpq["mean_cost_mean"] <= b / 2
                      and cpq["mean_return_mean"] <= 1))
    pc = data["per_seed_vr"].get(("PC1-PC2", "cpq"))
    out.append(_claim("5.5", "CPQ on PC1-PC2 is seed-unstable (per-seed VR spans >= 50 pp)",
                      "0-100%", None if pc is None else
                      f"{min(pc):.0f}-{max(pc):.0f}%", None if pc is None else
                      max(pc) - min(pc) >= 50))
    rhos = {p: v["spearman"] for p, v in t5.items()}
    full5 = len(rhos) == len(plan.pairs) and len(rhos) > 0
    out.append(_claim("5.6", "Cost rises with the CTG ratio on every pair (Spearman > 0.5)",
                      "0.6 / 0.9 / 0.6", " / ".join(f"{r:.2f}" for r in rhos.values()) or None,
                      all(r > 0.5 for r in rhos.values()) if full5 else None))
    out.append(_claim("5.6", "CC1-CC2 shows the strongest cost response", "rho 0.9",
                      None if "CC1-CC2" not in rhos or len(rhos) < 2 else
                      f"CC {rhos['CC1-CC2']:.2f}, max {max(rhos.values()):.2f}",
                      None if "CC1-CC2" not in rhos or len(rhos) < 2 else
                      rhos["CC1-CC2"] >= max(rhos.values())))
    moves = {k: v for k, v in t6.items() if v["direction"] is not None}
    # the paper's 3 of 5, as a share of the runs a row has (checkpoints x deployment seeds)
    out.append(_claim("5.6/C", "Every step change moves cost the expected way in >= 60% of its "
                      "seeds (3 of 5), on every pair", "3/5 to 5/5",
                      ", ".join(f"{p} {lab} {v['direction']}/{v['seeds']}" for (p, lab), v in
                                moves.items()) or None,
                      all(v["direction"] >= math.ceil(0.6 * v["seeds"]) for v in moves.values())
                      if moves else None))
    pcm = t5.get("PC1-PC2")
    out.append(_claim("5.6", "PC1-PC2's cost saturates near B (every ratio's cost >= 0.8 B)",
                      "27.2-28.7", None if pcm is None else
                      f"{min(pcm['means'].values()):.2f}-{max(pcm['means'].values()):.2f}",
                      None if pcm is None else min(pcm["means"].values()) >= 0.8 * b))
    return out


def claims_table(rows: list[dict[str, Any]]) -> str:
    """The claims as markdown, with yes / no / not run."""
    from safecdt_jax.results.tables import markdown_table

    verdict = {True: "yes", False: "**no**", None: "not run"}
    return markdown_table(["section", "claim", "paper", "ours", "supported"],
                          [[c["section"], c["claim"], c["paper"], c["ours"],
                            verdict[c["supported"]]] for c in rows])


def plot_figure2(data: Mapping[str, dict], plan: PaperPlan, path: str | os.PathLike) -> Path:
    """Figure 2: left, mean cost against the CTG ratio per pair (ours solid with seed std bars,
    the paper's dashed); right, the step changes' cost deltas with seeds in the expected
    direction annotated."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from safecdt_jax.results.figures import save_png

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    for pair, d in data["t5"].items():
        rs = list(d["means"])
        line = left.errorbar(rs, list(d["means"].values()), yerr=[d["stds"][r] for r in rs],
                             marker="o", capsize=3, label=f"{pair} (rho {d['spearman']:.2f})")
        paper = ref.TABLE5.get(pair)
        if paper:
            left.plot(list(paper), list(paper.values()), ls="--", color=line[0].get_color(),
                      alpha=0.6, label=f"{pair} paper")
    left.axhline(plan.budget, color="k", lw=1, ls=":", label=f"budget {plan.budget:g}")
    left.set_xlabel("CTG target ratio")
    left.set_ylabel("mean episode cost")
    left.set_title("static sweep (zero-shot)")
    left.legend(fontsize=7)
    moves = [(k, v) for k, v in data["t6"].items() if v["direction"] is not None]
    x = np.arange(len(moves))
    right.bar(x, [v["cost"] for _, v in moves], yerr=[v["cost_std"] for _, v in moves],
              capsize=3, color=["tab:red" if "low->high" in lab else "tab:blue"
                                for (_, lab), _ in moves])
    for i, ((_, _), v) in enumerate(moves):
        right.annotate(f"{v['direction']}/{v['seeds']}", (i, v["cost"]), ha="center",
                       va="bottom" if v["cost"] >= 0 else "top", fontsize=8)
    right.set_xticks(x, [f"{p}\n{lab}" for (p, lab), _ in moves], fontsize=7)
    right.axhline(0, color="k", lw=0.8)
    right.set_ylabel("cost change, second half - first")
    right.set_title("runtime step change")
    fig.tight_layout()
    return save_png(fig, path, dpi=110)


def _figures(records: T.Records, data: dict, plan: PaperPlan, out: Path) -> list[str]:
    """Figure 2, each pair's Safe-CDT traces and reward-cost scatter; returns markdown lines."""
    from safecdt_jax.baselines.job import plot_scatter
    from safecdt_jax.results.figures import plot_deployment

    fig_dir = out / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    lines = []
    if data["t5"] or data["t6"]:
        plot_figure2(data, plan, fig_dir / "figure2.png")
        lines.append("![Figure 2](figures/figure2.png)")
    for pair in plan.pairs:
        main = records.get(f"{pair}_main")
        if main is None:
            continue
        run = T.find_run(main, "safe_cdt")
        plot_deployment({"safe_cdt": run["metrics"]}, plan.budget, fig_dir / pair,
                        f"Safe-CDT {pair}, B={plan.budget:g}",
                        main["results"]["deploy_config"]["stage_len"])
        methods = [{"algo": "safe_cdt", "returns": run["metrics"]["return"],
                    "costs": run["metrics"]["cost"]}]
        studies = records.get(f"{pair}_studies")
        for v in plan.ablations if studies is not None else ():
            if v != "safe_cdt":
                r = T.find_run(studies, v, plan.budget)["metrics"]
                methods.append({"algo": "safe_cdt", "label": v, "returns": r["return"],
                                "costs": r["cost"]})
        methods += T.baseline_methods(records, pair)
        plot_scatter(methods, plan.budget, f"{pair}: reward and cost per seed",
                     fig_dir / f"{pair}_scatter.png")
        lines.append(f"{pair}: [episode costs](figures/{pair}/cost.png), "
                     f"[CTG targets](figures/{pair}/ctg_target.png), "
                     f"[violation rate](figures/{pair}/violation_rate.png)\n\n"
                     f"![{pair} scatter](figures/{pair}_scatter.png)")
    return lines


def _seconds(record: Mapping[str, Any]) -> str:
    """An experiment's wall time; for cached baselines, also the time they took to make."""
    text = f"{record['seconds']:.0f}"
    results = record["results"]
    if results.get("cached"):
        made = sum(m.get("train_seconds", 0) + m.get("eval_seconds", 0) for m in results["methods"])
        text += f" (cached; made in {made:.0f} s on {results.get('created', '?')})"
    return text


def _machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, {platform.system()} {platform.release()}"


def _seeds(plan: PaperPlan, seeds: int) -> str:
    """How a row of `seeds` runs: '15 seeds', or '5 checkpoints x 3 seeds' with several
    pretraining seeds (each checkpoint deployed with the same deployment seeds)."""
    n = plan.pretrain_seeds
    if n == 1:
        return f"{seeds} seeds"
    per = -(-seeds // n)
    return f"{n} pretrained checkpoints x {per} deployment seed{'s' if per > 1 else ''}"


def _counts(plan: PaperPlan) -> str:
    """The plan's counts, with the paper's beside every one that differs."""
    skip = {"pairs", "train_baselines"}
    cells = []
    for k, v in plan.record().items():
        if k in skip:
            continue
        paper = getattr(PAPER_COUNTS, k)
        cells.append(f"{k} {v}" + ("" if v == paper else f" (paper: {paper})"))
    return "; ".join(cells)


def build_tables(records: T.Records, plan: PaperPlan) -> tuple[dict[str, str], dict]:
    """Every table's markdown (`t1`..`t7`, `cert`) and the numbers behind them."""
    texts, data = {}, {}
    for name, fn in (("t1", T.table1), ("t2", T.table2), ("t3", T.table3), ("t4", T.table4),
                     ("t5", T.table5), ("t6", T.table6), ("t7", T.table7),
                     ("cert", T.certificates)):
        texts[name], data[name] = fn(records, plan)
    data["per_seed_vr"] = {
        (pair, m["algo"]): (100 * (np.asarray(m["costs"]) > plan.budget).mean(1)).tolist()
        for pair in plan.pairs for m in T.baseline_methods(records, pair)}
    return texts, data


def write_report(out: str | os.PathLike, plan: PaperPlan, summary: Mapping[str, Any]) -> Path:
    """Writes `out/REPORT.md` and `out/figures/` from `run_paper`'s summary; returns the path."""
    from safecdt_jax.io import write_text_atomic
    from safecdt_jax.results.tables import markdown_table

    out = Path(out)
    records = summary["records"]
    texts, data = build_tables(records, plan)
    checked = claims(data, plan)
    figures = _figures(records, data, plan, out)
    versions = next((r["results"]["versions"] for r in records.values()
                     if "versions" in r["results"]), {})
    timing = [[e.key, e.kind, _seconds(records[e.key]), records[e.key]["finished"]]
              if e.key in records else [e.key, e.kind, "-", "not run"]
              for e in experiments(plan)]
    total = sum(r["seconds"] for r in records.values())
    ok = sum(c["supported"] is True for c in checked)
    no = sum(c["supported"] is False for c in checked)
    n_ep = f"{plan.episodes} episodes"
    md = [
        "# Safe-CDT: the paper's evaluation, reproduced",
        "",
        "Generated by `safecdt-jax paper` (never edit by hand); every number below is ours "
        "unless its column says paper. Each episode ends at the first step over the budget "
        "(the paper's runtime-budget protocol). Reward, cost and VR are the mean ± population "
        "std over seeds of the per-seed means; where a row ran on several pretrained "
        "checkpoints (seeds `C×D`: C checkpoints, each with the same D deployment seeds), "
        "'VR sd: ckpt / deploy' is the std of the checkpoints' mean VR / the mean over "
        "checkpoints of the std across deployment seeds.",
        "",
        f"- Generated {time.strftime('%Y-%m-%d %H:%M')} on {_machine()}; JAX backend "
        f"{versions.get('backend', '?')}.",
        "- Versions: " + ", ".join(f"{k} {v}" for k, v in versions.items() if k != "backend"),
        f"- CDT preset `{plan.preset}`, baselines preset `{plan.baseline_preset}`; counts: "
        f"{_counts(plan)}.",
        f"- Experiment time: {total / 60:.1f} min, the sum over the experiments below (the "
        f"invocation that wrote this report took {summary['seconds'] / 60:.1f} min, reusing "
        f"finished experiments; data and pretraining "
        f"{sum(summary['prepare_seconds'].values()) / 60:.1f} min of it). Claims supported: "
        f"{ok}, not supported: {no}, not run: {len(checked) - ok - no}.",
        "",
        "## Claims of the paper's section 5",
        "",
        claims_table(checked),
        "",
        f"## Table 1: Safe-CDT at B = {plan.budget:g}",
        f"({n_ep}; {_seeds(plan, plan.main_seeds)} on {plan.study_pair}, "
        f"{_seeds(plan, plan.other_seeds)} elsewhere)",
        "",
        texts["t1"],
        "",
        f"## Table 2: budget sensitivity on {plan.study_pair}",
        f"(Safe-CDT, {_seeds(plan, plan.study_seeds)} x {n_ep})",
        "",
        texts["t2"],
        "",
        f"## Table 3: ablations on {plan.study_pair} at B = {plan.budget:g}",
        f"({_seeds(plan, plan.study_seeds)} x {n_ep}; the same sweep as Table 2)",
        "",
        texts["t3"],
        "",
        f"## Table 4: methods on {plan.study_pair}",
        f"(Safe-CDT online as in Table 1; baselines offline, {plan.baseline_seeds} seeds x "
        f"{plan.baseline_episodes} episodes, `{plan.baseline_preset}` preset)",
        "",
        texts["t4"],
        "",
        "## Table 5: CTG target controllability",
        f"(zero-shot, RTG ratio 0.5, fixed CTG = CR x B, {_seeds(plan, plan.ctg_seeds)} x the "
        f"first {n_ep} of the Table 6 fixed runs; cost mean ± std over all runs; Spearman of the "
        f"means; CR {plan.ctg_ratios[0]:g} / CR {plan.ctg_ratios[-1]:g}: the ratio of their "
        f"mean costs)",
        "",
        texts["t5"],
        "",
        "## Table 6: runtime CTG intervention",
        f"(zero-shot, {_seeds(plan, plan.ctg_seeds)} x {plan.intervention_episodes} episodes, "
        f"the switch at episode {plan.intervention_episodes // 2}: CR {plan.step_low:g} <-> "
        f"{plan.step_high:g}; deltas: second half minus first; fixed rows show the drift)",
        "",
        texts["t6"],
        "",
        "## Table 7: baselines per pair",
        f"(offline, {plan.baseline_seeds} seeds x {plan.baseline_episodes} episodes)",
        "",
        texts["t7"],
        "",
        "## Safety certificate (docs/METHOD.md section 7)",
        f"Per pair from Table 5's fixed-ratio episodes (N = {plan.episodes}), and the transfer "
        f"check against the same ratios run in the source task "
        f"({_seeds(plan, plan.source_seeds)}).",
        "",
        texts["cert"],
        "## Figures",
        "",
        *[line + "\n" for line in figures],
        "## Experiments",
        "",
        markdown_table(["experiment", "kind", "seconds", "finished"], timing),
        "",
    ]
    return write_text_atomic(out / "REPORT.md", "\n".join(md))
