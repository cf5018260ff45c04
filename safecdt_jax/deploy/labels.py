"""Return and cost labels of the online buffer's episodes for LoRA finetuning (docs/METHOD.md
section 4).

Pretraining (the `cpu` preset) teaches the tokens the mean outcome of the policy that drove an
episode, not the episode's own luck. The online labels have to mean the same thing, or the
adapters learn a second meaning of the tokens (docs/METHOD.md section 4 says what it did).
Three rules, chosen by `DeployConfig.lora_labels`:

- `"stage"`: every episode run under the same (RTG, CTG) targets gets the same labels: the mean
  return and cost per full episode of those episodes, the policy-mean analogue. The means are
  pooled rates, `sum(totals) / sum(lengths) * horizon`, so an episode cut at the budget counts
  for the steps it ran at the rate it ran them, and a group whose episodes were cut is labelled
  above the budget rather than at B + 1 with a truncated return.
- `"target"`: every episode is labelled with the targets it was run under.
- `"hindsight"`: each episode's own realised return and cost (the paper's rule, OSRL's labels).

`"auto"` (`DeployConfig`'s default) picks by how the CDT acts (`resolve_label_rule`): `"target"`
when it acts with samples, where the replay weights make the finetuning a weighted cloning of
its own in-budget samples, and `"stage"` when it acts with its mean, where `"target"` labels
teach nothing (docs/METHOD.md section 4).

Everything here is a pure function of arrays, jit- and vmap-able.
"""

from __future__ import annotations

import jax.numpy as jnp

LABEL_RULES: tuple[str, ...] = ("stage", "target", "hindsight")
LABEL_CHOICES: tuple[str, ...] = ("auto", *LABEL_RULES)


def resolve_label_rule(rule: str, stochastic_actions: bool) -> str:
    """The rule of `LABEL_RULES` that `rule` (`LABEL_CHOICES`) names for a CDT acting with
    samples (`stochastic_actions` True) or its mean: `"auto"` is `"target"` or `"stage"`."""
    if rule != "auto":
        return rule
    return "target" if stochastic_actions else "stage"


def same_targets(rtg, ctg, valid, tolerance: float = 1e-3):
    """[E, E] bool: episodes i and j were run under the same targets and j is `valid`.

    `rtg`, `ctg` [E] raw targets; targets count as equal within `tolerance` (relative to the
    larger magnitude, at least 1), so that a ratio that left and came back compares equal."""
    def close(x):
        x = jnp.asarray(x, jnp.float32)
        scale = jnp.maximum(jnp.maximum(jnp.abs(x[:, None]), jnp.abs(x[None, :])), 1.0)
        return jnp.abs(x[:, None] - x[None, :]) <= tolerance * scale

    return close(rtg) & close(ctg) & jnp.asarray(valid, bool)[None, :]


def online_labels(rule: str, returns, costs, lengths, rtg, ctg, valid, horizon: int):
    """Per-episode `(return_label, cost_label)` [E] in raw units under `rule` (`LABEL_RULES`).

    Args:
        rule: `"stage"`, `"target"` or `"hindsight"` (static).
        returns, costs: [E] each episode's realised return and cost (raw units).
        lengths: [E] its steps (fewer than `horizon` when cut at the budget).
        rtg, ctg: [E] the raw targets it was run under.
        valid: [E] bool, the episodes run so far (the others' labels are 0).
        horizon: steps of a full episode.
    """
    valid = jnp.asarray(valid, bool)
    returns, costs = jnp.asarray(returns, jnp.float32), jnp.asarray(costs, jnp.float32)
    if rule == "hindsight":
        ret, cost = returns, costs
    elif rule == "target":
        ret, cost = jnp.asarray(rtg, jnp.float32), jnp.asarray(ctg, jnp.float32)
    elif rule == "stage":
        group = same_targets(rtg, ctg, valid)  # [E, E]
        # Masked sums, not a matmul: exact in float32 on every backend (an accelerator's
        # default matmul precision may round the step counts).
        pooled = lambda x: jnp.where(group, x[None, :], 0.0).sum(axis=1)
        per_step = horizon / jnp.maximum(pooled(jnp.asarray(lengths, jnp.float32)), 1.0)
        ret, cost = pooled(returns) * per_step, pooled(costs) * per_step
    else:
        raise ValueError(f"unknown LoRA label rule {rule!r}; choose one of "
                         f"{', '.join(LABEL_RULES)}")
    return jnp.where(valid, ret, 0.0), jnp.where(valid, cost, 0.0)
