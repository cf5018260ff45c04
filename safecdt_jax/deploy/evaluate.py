"""Evaluate a pretrained CDT at several (return, cost) targets in one vmapped program."""

from __future__ import annotations

import os

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
        if cost < 0:
            raise ValueError(f"bad target {item!r}: the cost target must be >= 0")
        out.append((ret, cost))
    return out


def evaluate_policy(ckpt: str | os.PathLike, task: str, targets: list[tuple[float, float]],
                    episodes: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Episode returns and costs [n_targets, episodes] of checkpoint `ckpt` in `task`.

    Every target runs on the same `episodes` layouts (keys from `seed`), in one jitted call,
    with the checkpoint's own token scales.
    """
    import envs
    from safecdt_jax.deploy.rollout import evaluate_targets
    from safecdt_jax.pretrain.checkpoint import load_policy, token_scales

    env, params = envs.make(task)
    policy = load_policy(ckpt, task=task)
    reward_scale, cost_scale = token_scales(policy.meta)
    rets = np.array([t[0] for t in targets], np.float32)
    costs = np.array([t[1] for t in targets], np.float32)
    fn = jax.jit(lambda k, r, c: evaluate_targets(k, env, params, policy.params, policy.cfg, r, c,
                                                  episodes, reward_scale=reward_scale,
                                                  cost_scale=cost_scale))
    res = jax.device_get(fn(jax.random.PRNGKey(seed), rets, costs))
    return {"target_return": rets, "target_cost": costs, "returns": np.asarray(res.returns),
            "costs": np.asarray(res.costs)}


def evaluate_checkpoint(ckpt: str | os.PathLike, task: str, targets: list[tuple[float, float]],
                        episodes: int, seed: int = 0) -> str:
    """A markdown table: per target, mean return, mean cost and VR (% of episodes whose cost
    exceeds the target's cost)."""
    res = evaluate_policy(ckpt, task, targets, episodes, seed)
    lines = [f"{task}, {episodes} episodes per target", "",
             "| target return | target cost | mean return | mean cost | VR (%) |",
             "|---|---|---|---|---|"]
    for i, (ret, cost) in enumerate(targets):
        r, c = res["returns"][i], res["costs"][i]
        lines.append(f"| {ret:g} | {cost:g} | {r.mean():.2f} | {c.mean():.1f} | "
                     f"{100 * (c > cost).mean():.0f} |")
    return "\n".join(lines)
