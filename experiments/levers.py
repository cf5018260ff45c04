"""Do Safe-CDT's levers reach the model? Pretraining seeds x deployment seeds, per pair and rule.

    python -m experiments.levers [--pairs CC1-CC2,PC1-PC2,CG1-CG2] [--ckpt-seeds 0,1,2]
        [--seeds 5] [--rules stage,hindsight,target] [--variants safe_cdt,naive_lora]
        [--no-fixed] [--edges span|data] [--act sample|mean|checkpoint] [--work DIR]
        [--out PATH]

For each pair and pretraining seed: a `cpu`-preset CDT pretrained on the source task's default
data (`--edges data`: token ramp edges at the data's quantiles alone, as before 2026-12-06), then,
in the target task at B = 30 with `--seeds` deployment seeds x 50 episodes:
- zero-shot at the fixed cost ratios 0.2 / 0.4 / 0.6 / 0.8 / 1.0 (the paper's Table 5), one sweep;
- Safe-CDT and naive LoRA under each LoRA label rule (`DeployConfig.lora_labels`), optionally
  with `+`-separated changes: the replay weights' excess rule (`DeployConfig.replay_excess`) or
  any FIELD=VALUE of DeployConfig (`stage+projected+weight_floor=0.01`).
`--act` picks how every run acts: `sample` (the default, as every command since 2026-12-07),
`mean`, or `checkpoint` (as the checkpoint says: the mean for the `cpu` preset; the sweeps of before
that default, cached under names without a suffix). With `--edges span` the checkpoints are
the cache's, the ones `safecdt-jax paper` deploys.
Per (pair, rule, variant) the table gives the mean over checkpoints x seeds of VR, cost, cost
over episodes 41-50 and the drift (episodes 41-50 minus 1-10), each with its spread across
pretraining seeds (std of the checkpoints' means) and across deployment seeds (mean of the
checkpoints' seed stds). Every sweep's results.json (and `--edges data`'s checkpoints) live
under `--work` (default `runs/levers`) and are reused on the same env version (`envs.env_version`;
a record of older physics or task rules runs again), so an interrupted run continues.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from benchmarks.common import machine, markdown_table, write_json, write_markdown
from safecdt_jax.analysis.evaluate import ACTION_MODES, DEFAULT_ACTION_MODE
from safecdt_jax.stats import per_seed_metrics, seed_spread

RATIOS = (0.2, 0.4, 0.6, 0.8, 1.0)
BUDGET = 30.0


def checkpoint(pair: str, seed: int, edges: str, work: Path) -> Path:
    """The pair's source-task checkpoint for `seed`. `--edges span` (today's default tokens):
    the checkpoint `safecdt-jax paper` deploys for that pretraining seed, from the cache
    (`paper.run.prepare_checkpoints`, which trains the seeds up to it where missing), so this
    experiment and the report share checkpoints. `--edges data`: pretrained into `work`."""
    from safecdt_jax.experts.collect import ensure_source_data
    from safecdt_jax.pairs import parse_pair
    from safecdt_jax.paper.plan import PaperPlan
    from safecdt_jax.paper.run import prepare_checkpoints
    from safecdt_jax.pretrain import default_pretrain, pretrain

    if edges == "span":
        return prepare_checkpoints(pair, PaperPlan(pretrain_seeds=seed + 1), progress=False)[seed]
    source = parse_pair(pair)[0]
    out = work / "ckpt" / f"{pair}_{edges}_s{seed}"
    if not (out / "done").exists():
        cfg = default_pretrain("cpu", seed=seed).replace(return_span=(), cost_span=())
        pretrain(ensure_source_data(source), out, preset="cpu", config=cfg,
                 overwrite=True, progress=False)
        (out / "done").write_text("")
    return out


def deploy_config(rule: str):
    """The DeployConfig of a `--rules` entry: a LoRA label rule, then `+`-separated changes, each
    a replay-excess rule or a FIELD=VALUE (`stage+projected+weight_floor=0.01`:
    `lora_labels="stage"`, `replay_excess="projected"`, `weight_floor=0.01`)."""
    from safecdt_jax.deploy.config import DeployConfig
    from safecdt_jax.validate import field_overrides

    labels, *changes = rule.split("+")
    changes = [c if "=" in c else f"replay_excess={c}" for c in changes]
    return DeployConfig(lora_labels=labels, **field_overrides(changes, DeployConfig))


def act_suffix(act: str) -> str:
    """A sweep folder's suffix for an acting mode: none for "checkpoint" (the sweeps made before
    `--act` existed keep their names), else "_" + the mode."""
    return "" if act == "checkpoint" else f"_{act}"


def reusable(out: Path, target: str) -> dict | None:
    """The sweep record in `out` if one was made on `target`'s current env version (a record of
    older physics or task rules is run again), else None."""
    from safecdt_jax.envs import env_version

    path = out / "results.json"
    if not path.exists():
        return None
    record = json.loads(path.read_text())
    return record if record.get("target_env") == env_version(target) else None


def cached_sweep(out: Path, target: str, run, title: str) -> dict:
    """The sweep record in `out` (`reusable`), or `run()`'s deployment result written there
    under `title` and read back."""
    from safecdt_jax.deploy.job import write_results

    record = reusable(out, target)
    if record is None:
        write_results(out, run(), title)
        record = reusable(out, target)
    return record


def sweep(pair: str, seed: int, edges: str, name: str, variants: list[str], rule: str,
          seeds: int, work: Path, act: str = "checkpoint") -> dict:
    """One deployment sweep's results record, from `work` or run and written there; `act`
    picks how the CDT acts (`analysis.evaluate.ACTION_MODES`: the checkpoint's own mode, its
    mean or samples)."""
    from safecdt_jax.analysis.evaluate import parse_action_mode
    from safecdt_jax.deploy.job import run_deployment
    from safecdt_jax.pairs import parse_pair

    target = parse_pair(pair)[1]
    return cached_sweep(
        work / "res" / f"{pair}_{edges}_s{seed}_{name}{act_suffix(act)}", target,
        lambda: run_deployment(checkpoint(pair, seed, edges, work), target, variants, [BUDGET],
                               seeds, seed=seed, cfg=deploy_config(rule),
                               stochastic_actions=parse_action_mode(act), progress=False),
        f"levers {pair} {edges} seed {seed} {name}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", default="CC1-CC2,PC1-PC2,CG1-CG2")
    ap.add_argument("--ckpt-seeds", default="0,1,2")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--rules", default="stage,hindsight,target")
    ap.add_argument("--variants", default="safe_cdt,naive_lora",
                    help="the finetuning variants run under each rule")
    ap.add_argument("--no-fixed", action="store_true",
                    help="skip the fixed-ratio sweep (no zero-shot row and no Table 5)")
    ap.add_argument("--edges", default="span", choices=("span", "data"))
    ap.add_argument("--act", default=DEFAULT_ACTION_MODE, choices=tuple(ACTION_MODES),
                    help="how every run acts: as the checkpoint says, its mean, or samples")
    ap.add_argument("--work", type=Path, default=Path("runs/levers"))
    ap.add_argument("--out", type=Path, default=Path("experiments/results/levers.json"))
    args = ap.parse_args(argv)
    fixed = ["zero_shot" if r == 0.6 else f"fixed_ctg({r})" for r in RATIOS]
    table5, cells = [], {}
    variants = args.variants.split(",")
    suffix = "_".join(variants)
    for pair in args.pairs.split(","):
        for seed in (int(s) for s in args.ckpt_seeds.split(",")):
            runs = {}
            if not args.no_fixed:
                runs = {r["variant"]: per_seed_metrics(r) for r in sweep(
                    pair, seed, args.edges, "fixed", fixed, "stage", args.seeds,
                    args.work, args.act)["runs"]}
                costs = [float(runs[v]["cost"].mean()) for v in fixed]
                table5.append({"pair": pair, "ckpt_seed": seed, "costs": costs,
                               "ratio_02_10": costs[0] / costs[-1]})
            for rule in args.rules.split(","):
                # the default pair of variants keeps the cache names of earlier runs
                folder = rule if variants == ["safe_cdt", "naive_lora"] else f"{rule}_{suffix}"
                res = sweep(pair, seed, args.edges, folder, variants, rule, args.seeds,
                            args.work, args.act)
                found = {r["variant"]: per_seed_metrics(r) for r in res["runs"]}
                found |= {"zero_shot": runs["zero_shot"]} if runs else {}
                for variant, m in found.items():
                    key = (pair, "-" if variant == "zero_shot" else rule, variant)
                    for name, v in m.items():
                        cells.setdefault(key, {}).setdefault(name, {})[seed] = v
            print(f"{pair} seed {seed}: done", file=sys.stderr, flush=True)
    rows = [{"pair": p, "labels": r, "variant": v, "checkpoints": len(m["vr"]),
             **{k: seed_spread(list(m[k].values())) for k in m}}
            for (p, r, v), m in sorted(cells.items())]
    command = "python -m experiments.levers " + " ".join(sys.argv[1:] if argv is None else argv)
    write_json(args.out, {"command": command, "machine": machine(), "edges": args.edges,
                          "act": args.act,
                          "seeds": args.seeds, "budget": BUDGET, "table5": table5, "rows": rows})
    fmt = lambda s: f"{s['mean']:.1f} ({s['ckpt_std']:.1f} / {s['seed_std']:.1f})"
    body = markdown_table(
        ["pair", "labels", "run", "ckpts", "VR %", "cost", "cost 41-50", "drift", "reward"],
        [[r["pair"], r["labels"], r["variant"], r["checkpoints"], fmt(r["vr"]), fmt(r["cost"]),
          fmt(r["late"]), fmt(r["drift"]), fmt(r["reward"])] for r in rows])
    body += ("\n\nmean over checkpoints x deployment seeds (spread across pretraining seeds / "
             "across deployment seeds)\n")
    if table5:  # `--no-fixed` runs no fixed ratios
        body += "\n" + markdown_table(
            ["pair", "ckpt seed", *[f"cost @ CR {r:g}" for r in RATIOS], "CR 0.2 / CR 1"],
            [[t["pair"], t["ckpt_seed"], *[f"{c:.2f}" for c in t["costs"]],
              f"{t['ratio_02_10']:.2f}"] for t in table5])
    write_markdown(args.out.with_suffix(".md"), "Safe-CDT's levers", command, body)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
