"""Is the online LoRA update too strong (or too weak) for the `cpu` model? Rank x learning rate.

    python -m experiments.lora_strength [--pairs CC1-CC2,CG1-CG2] [--ckpt-seeds 0,1,2]
        [--seeds 2] [--configs 16:1e-4,4:1e-4,16:3e-5,16:3e-4] [--act sample|mean|checkpoint]
        [--work DIR] [--out PATH]

Per pair, the cache's `cpu` checkpoints of the pretraining seeds (`TASK-cpu`, `-seedK`, as
`safecdt-jax paper` makes them) x `--seeds` deployment seeds x 50 episodes at B = 30, all
checkpoints in one sweep (`run_deployment([...])`): zero-shot and scheduler-only once (they do
not finetune), then Safe-CDT and naive LoRA at every adapter (rank, learning rate) of
`--configs` (`DeployConfig.lora_rank`, `lora_lr`; the default labels). Per (pair, config,
variant): VR, mean cost, cost over episodes 41-50 and the drift (41-50 minus 1-10), each the
mean over checkpoints x seeds with the spread between checkpoints / across seeds. `--act` picks
how every run acts (`analysis.evaluate.ACTION_MODES`; default samples, as every command; the
sweeps of research section 24 acted as the checkpoint says, with the mean, and are cached under
names without a suffix). Every sweep's results.json lives under `--work` (default
`runs/lora_strength`) and is reused on the same env version (`experiments.levers.reusable`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json, write_markdown
from experiments.cost_terms import checkpoints
from experiments.levers import act_suffix, cached_sweep
from safecdt_jax.analysis.evaluate import ACTION_MODES, DEFAULT_ACTION_MODE
from safecdt_jax.stats import per_seed_metrics, seed_spread

BUDGET = 30.0


def sweep(pair: str, ckpts: list[Path], name: str, variants: list[str], seeds: int,
          work: Path, act: str = "checkpoint", **deploy) -> dict:
    """One deployment sweep's results record, from `work` or run and written there; `act` is
    how the CDT acts (an `analysis.evaluate.ACTION_MODES` name)."""
    from safecdt_jax.analysis.evaluate import parse_action_mode
    from safecdt_jax.deploy.config import DeployConfig
    from safecdt_jax.deploy.job import run_deployment
    from safecdt_jax.pairs import parse_pair

    target = parse_pair(pair)[1]
    return cached_sweep(
        work / f"{pair}_{name}{act_suffix(act)}", target,
        lambda: run_deployment(ckpts, target, variants, [BUDGET], seeds,
                               cfg=DeployConfig(**deploy),
                               stochastic_actions=parse_action_mode(act), progress=False),
        f"lora_strength {pair} {name}")


def per_checkpoint(run: dict, n_ckpt: int) -> dict[str, list[np.ndarray]]:
    """`per_seed_metrics` split into one [seeds] array per checkpoint (rows checkpoint-major)."""
    m = per_seed_metrics(run)
    return {k: list(np.asarray(v).reshape(n_ckpt, -1)) for k, v in m.items()}


def main(argv: list[str] | None = None) -> None:
    from safecdt_jax.pairs import parse_pair

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", default="CC1-CC2,CG1-CG2")
    ap.add_argument("--ckpt-seeds", default="0,1,2")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--configs", default="16:1e-4,4:1e-4,16:3e-5,16:3e-4")
    ap.add_argument("--act", default=DEFAULT_ACTION_MODE, choices=tuple(ACTION_MODES),
                    help="how every run acts: as the checkpoint says, its mean, or samples")
    ap.add_argument("--work", type=Path, default=Path("runs/lora_strength"))
    ap.add_argument("--out", type=Path, default=Path("experiments/results/lora_strength.json"))
    args = ap.parse_args(argv)
    configs = [(int(r), float(lr)) for r, lr in (c.split(":") for c in args.configs.split(","))]
    rows = []
    for pair in args.pairs.split(","):
        ckpts = checkpoints(parse_pair(pair)[0], [int(s) for s in args.ckpt_seeds.split(",")])
        found = {("-", r["variant"]): r for r in sweep(
            pair, ckpts, "reference", ["zero_shot", "scheduler_only"], args.seeds,
            args.work, args.act)["runs"]}
        for rank, lr in configs:
            res = sweep(pair, ckpts, f"r{rank}_lr{lr:g}", ["safe_cdt", "naive_lora"],
                        args.seeds, args.work, args.act, lora_rank=rank, lora_lr=lr)
            found |= {(f"r {rank}, lr {lr:g}", r["variant"]): r for r in res["runs"]}
        for (config, variant), run in found.items():
            m = per_checkpoint(run, len(ckpts))
            rows.append({"pair": pair, "lora": config, "variant": variant,
                         **{k: seed_spread(v) for k, v in m.items()}})
        print(f"{pair}: done", file=sys.stderr, flush=True)
    command = "python -m experiments.lora_strength " + " ".join(sys.argv[1:] if argv is None
                                                                else argv)
    write_json(args.out, {"command": command, "machine": machine(), "seeds": args.seeds,
                          "act": args.act, "budget": BUDGET, "rows": rows})
    fmt = lambda s: f"{s['mean']:.1f} ({s['ckpt_std']:.1f} / {s['seed_std']:.1f})"
    body = markdown_table(
        ["pair", "LoRA", "run", "VR %", "cost", "cost 41-50", "drift", "reward"],
        [[r["pair"], r["lora"], r["variant"], fmt(r["vr"]), fmt(r["cost"]), fmt(r["late"]),
          fmt(r["drift"]), fmt(r["reward"])] for r in rows])
    body += ("\n\nmean over checkpoints x deployment seeds (spread between checkpoints / across "
             "deployment seeds); drift: cost of episodes 41-50 minus 1-10.\n")
    write_markdown(args.out.with_suffix(".md"), "Online LoRA strength", command, body)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
