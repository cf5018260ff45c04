"""How online LoRA finetuning changes the CDT's cost-target response (an analysis, not a timing).

Deploys a pretrained checkpoint in a target task for each variant (all seeds in one vmapped
call), then evaluates the base model and every seed's finetuned model (base + that seed's final
adapters) in the target task at a grid of cost-to-go targets, on the same layouts. It prints
the mean episode cost per stage of the deployment and per target before and after, and writes
JSON (`experiments/results/lora_response.json` by default).

    python -m experiments.lora_response --ckpt ~/.cache/safecdt-jax/checkpoints/CarCircle1-cpu \
        --target CarCircle2 [--variants naive_lora,safe_cdt] [--seeds 4] [--budget 30]

The replay windows of the finetuning carry hindsight tokens (the costs-to-go the episodes
realised, docs/METHOD.md section 4), so this shows whether the adapters move the model's response
toward the costs realised at the deployment's targets.
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import machine, markdown_table, write_json
from safecdt_jax.deploy import make_spec, make_variant, seed_keys, stack_specs, sweep
from safecdt_jax.deploy.job import load_deployment
from safecdt_jax.deploy.rollout import evaluate_targets
from safecdt_jax.model.lora import merge_lora


def stage_means(x, stage_len: int) -> list[float]:
    """Mean over seeds and over each stage's episodes of a [seeds, episodes] metric."""
    x = np.asarray(x, np.float64)
    stages = x.shape[1] // stage_len
    return x[:, :stages * stage_len].reshape(len(x), stages, stage_len).mean((0, 2)).round(
        2).tolist()


def response(ckpt: str, target: str, variants: list[str], seeds: int, budget: float,
             cost_targets: list[float], return_ratio: float, episodes: int) -> dict:
    """Per-stage deployment costs and the cost at each CTG target, before and after finetuning.

    Costs are mean episode costs (cost steps); the return target of the evaluation is
    `return_ratio` x the checkpoint's reference return (RR_0 = 0.5 is the deployment's start).
    """
    env, env_params, policy, cfg, r_ref = load_deployment(ckpt, target)
    static = dict(env=env, model_cfg=policy.cfg, cfg=cfg)
    c_t = jnp.asarray(cost_targets, jnp.float32)
    r_t = jnp.full_like(c_t, return_ratio * r_ref)
    evaluate = jax.jit(lambda p: evaluate_targets(
        jax.random.PRNGKey(11), env, env_params, p, policy.cfg, r_t, c_t, episodes,
        clip_ctg=cfg.clip_ctg).costs.mean(1))
    keys = seed_keys(0, seeds)
    out = {"base": np.asarray(evaluate(policy.params)).tolist(), "variants": {}}
    for name in variants:
        specs = stack_specs([make_spec(make_variant(name, cfg), budget, r_ref)])
        start = time.perf_counter()
        metrics, carry = jax.device_get(sweep(keys, policy.params, env_params, specs, **static,
                                              return_carry=True))
        wall = time.perf_counter() - start
        metrics = jax.tree.map(lambda x: x[0], metrics)  # the one run
        after = [np.asarray(evaluate(merge_lora(policy.params, jax.tree.map(
            lambda x, s=s: x[0, s], carry.lora), policy.cfg))).tolist() for s in range(seeds)]
        out["variants"][name] = {"stage_cost": stage_means(metrics.costs, cfg.stage_len),
                                 "stage_ctg_target": stage_means(metrics.ctg_target,
                                                                 cfg.stage_len),
                                 "after": after, "deploy_s": wall}
    return out


def main() -> None:
    """Parses the command line, runs `response`, prints the tables and writes the JSON."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", required=True)
    p.add_argument("--target", required=True)
    p.add_argument("--variants", default="naive_lora,safe_cdt")
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--budget", type=float, default=30.0)
    p.add_argument("--targets", default="5,10,20,40,80", help="cost-to-go targets to evaluate")
    p.add_argument("--return-ratio", type=float, default=0.5)
    p.add_argument("--episodes", type=int, default=10, help="evaluation episodes per target")
    p.add_argument("--out", default="experiments/results/lora_response.json")
    a = p.parse_args()
    targets = [float(x) for x in a.targets.split(",")]
    res = response(a.ckpt, a.target, a.variants.split(","), a.seeds, a.budget, targets,
                   a.return_ratio, a.episodes)
    rows = [["base", "-", *[f"{c:.1f}" for c in res["base"]]]]
    for name, v in res["variants"].items():
        rows += [[name, f"seed {s}", *[f"{c:.1f}" for c in costs]]
                 for s, costs in enumerate(v["after"])]
        print(f"{name}: cost per stage {v['stage_cost']}, CTG target {v['stage_ctg_target']}")
    print(markdown_table(["model", "seed", *[f"CTG {t:g}" for t in targets]], rows))
    write_json(a.out, {"args": vars(a), "machine": machine(), **res})


if __name__ == "__main__":
    main()
