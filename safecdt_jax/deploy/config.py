"""Deployment settings (docs/METHOD.md sections 1-5) and the method variants as data.

`DeployConfig` is a frozen, hashable dataclass: every number of the deployment loop, static under
`jax.jit`. `Variant` is a pytree of arrays: which parts of Safe-CDT are on (scheduler,
reweighting, LoRA) and the fixed cost ratios of the non-adaptive baselines, so that every variant
of docs/METHOD.md section 5 runs through ONE compiled program and a stack of variants can be
vmapped.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp

from safecdt_jax import validate as check
from safecdt_jax.deploy.labels import LABEL_CHOICES, resolve_label_rule

# What the replay weights' excess reads (`DeployConfig.replay_excess`).
REPLAY_EXCESS: tuple[str, ...] = ("realised", "projected")


@dataclass(frozen=True)
class DeployConfig:
    """Every number of the Safe-CDT deployment loop (defaults = docs/METHOD.md).

    Attributes:
        episodes: deployment length E in episodes (50; step-change runs use 100).
        horizon: steps per episode; None (default) = the env's own time limit (Goal 1000,
            Circle 500). A shorter horizon cuts every episode there (tests, quick looks).
        stage_len: U, episodes per scheduler stage; the targets change only every U episodes.
        window: W, the number of most recent finished episodes the scheduler and the lambda
            update look at (fewer at the start of a deployment).
        z: Wilson-score z. 1.0 by default: with z = 1.96 the lower bound of 10/10 successes is
            0.722, so for n <= 10 (the window) "relax" (A_C > 0.9) is unreachable and the
            scheduler could only ever tighten.
        tighten_below: an achievability below this tightens the cost ratio (A_C) or lowers the
            return ratio (A_R) (0.5).
        relax_above: an achievability above this relaxes the cost ratio (A_C), opens the
            return-ratio gate (A_C) and raises the return ratio (A_R) (0.9).
        cr_step: base step of the cost ratio per stage (0.1), multiplied by the momentum d.
        momentum_factor: d <- min(momentum_factor * d, momentum_max) on a repeated direction (1.5).
        momentum_max: cap of the momentum d (3.0).
        cr_min, cr_max: bounds of the cost ratio CR (0.05, 1.0); CTG target = CR * B.
        cr0: initial cost ratio CR_0 (0.6); also the fixed CR of `zero_shot` / `naive_lora`.
        rr0: initial return ratio RR_0 (0.5); RTG target = RR * R_ref. Fixed when the scheduler
            is off.
        rr_step: step of the return ratio per stage (0.1), no momentum.
        rr_min, rr_max: bounds of RR; docs/METHOD.md leaves them open. 0.1 keeps a positive return
            target (asking for nothing makes the CDT's return token uninformative); 1.5 allows
            asking 50% above the source's 95th-percentile return, far enough to probe the return
            the target domain allows but not so far that the RTG token leaves the pretraining
            support (where a DT's behaviour is unreliable). Assumes R_ref > 0.
        budget: default cost budget B (30): the CLI's `--budget` default. The loop's functions
            take the budget as an argument (a traced scalar, so budgets are swept with vmap).
        lambda_warmup: the reweighting multiplier is frozen until this many episodes have
            finished (10); it first updates after episode index lambda_warmup - 1, when the
            window is full for W = 10.
        violation_target: v*, the tolerated violation rate over the window (0.1).
        lambda_rise: lambda <- lambda + lambda_rise * (v - v*) when v > v* (5.0).
        lambda_max: cap of lambda (20.0).
        lambda_decay: lambda <- lambda_decay * lambda when v <= v* (0.95).
        lambda0: initial lambda (1.0); variants without reweighting hold lambda = 0.
        weight_floor: lower clip of the unnormalised replay weight exp(-lambda e / B) (0.1).
        replay_excess: which cost-to-go C the replay weights' excess e = max(0, C - B) reads
            (`REPLAY_EXCESS`). `"projected"` (default): a cut episode's cost-to-go is extended
            over the steps it did not run at the rate it ran
            (`deploy.reweight.projected_cost_to_go`), so the weights see how far the episode
            overran, as they would without the runtime budget; full-length episodes read their
            realised value. `"realised"`: the window's realised cost-to-go, the paper's
            reading, under which `stop_over_budget` caps e at 1 and a violating window keeps
            at least exp(-lambda_max / B) of its weight (docs/METHOD.md section 3).
        lora_steps: Adam steps on the adapters after every episode (10).
        lora_batch: replay sequences per step (32), each of the model's context length K.
        lora_lr: Adam learning rate of the adapters (1e-4).
        lora_rank: rank r of the adapters (0: the checkpoint's `CDTConfig.lora_rank`, 16 in
            the `cpu` preset). The adapters start at deployment, so any rank deploys any
            checkpoint; the update keeps the checkpoint's `lora_alpha / r` scale rule.
        lora_labels: what the finetuning windows' return and cost tokens read
            (`deploy.labels`, docs/METHOD.md section 4). `"auto"` (default): `"target"` for a
            CDT acting with samples, `"stage"` for one acting with its mean (resolved per
            policy: `for_acting`; results.json records the rule that ran). `"stage"`: every
            episode run under the same targets is labelled with their mean return and cost per full
            episode (pooled over their steps, so an episode cut at the budget counts at the
            rate it ran), the meaning the `cpu` preset's policy-mean pretraining labels give
            the tokens. `"target"`: the targets the episode was run under. `"hindsight"`: the
            episode's own realised totals, the paper's and OSRL's rule, under which the
            finetuning drove the cost up on CC1->CC2 (docs/METHOD.md section 4).
        lora_dropout: run the CDT with its dropout during adapter training. The paper is
            silent; default False (deterministic forward pass): with 10 steps of 32 sequences per
            episode, dropout noise would dominate the small gradient signal, and the adapters are
            trained for exactly the forward pass the deployment uses (evaluation mode).
        lora_in_turn: under the sweep's vmap over runs and seeds, compute their adapter gradients
            one after another (`jax.custom_batching.sequential_vmap`) instead of as one batched
            product. None (default): on where the sweep runs on one CPU device (per process, when
            several cooperate), off on an accelerator or with a process's seeds sharded over several
            devices (resolved by `resolved`). On a CPU each seed's 32 windows keep their activations
            in cache: the LoRA steps of a 15-seed sweep ran 1.5x (`cpu` preset, 2 threads) and 2.2x
            (`osrl`, 1 thread) faster, the whole sweep 1.19x and 1.46x (docs/PERFORMANCE.md). The
            adapters agree to float rounding (summation order), but a rollout that follows them can
            leave the other's path: results made before 2026-12-05 ran batched, and
            `lora_in_turn=False` (`--set lora_in_turn=false`) reproduces them bit for bit.
        lora_micro_batch: compute each LoRA step's gradient in passes of at most this many of
            its `lora_batch` windows, summed (0, the default: one pass, as every published
            result ran). The same gradient up to float summation order; on a CPU small passes
            keep their activations in cache (docs/PERFORMANCE.md). Per seed under the sweep's
            vmap, so 15 seeds in passes of 8 multiply 120 windows at a time.
        clip_ctg: clip the rollout's cost-to-go at 0 once the budget is spent (True); False is
            OSRL's rule (it may go negative, which no training window contains).
        stop_over_budget: the paper's "consistent runtime-budget protocol" (True): a wrapper
            ends each episode after the step at which its cost first exceeds the budget B, so
            a violating episode costs B + 1 (0/1 costs) and keeps the return it had made by
            then. The paper's tables show it: BCQL and BEARL on CC1->CC2 cost 31.00 +- 0.00 at
            B = 30 with VR 100%. False runs every episode to the time limit.
    """

    episodes: int = 50
    horizon: int | None = None
    stage_len: int = 5
    window: int = 10
    z: float = 1.0
    tighten_below: float = 0.5
    relax_above: float = 0.9
    cr_step: float = 0.1
    momentum_factor: float = 1.5
    momentum_max: float = 3.0
    cr_min: float = 0.05
    cr_max: float = 1.0
    cr0: float = 0.6
    rr0: float = 0.5
    rr_step: float = 0.1
    rr_min: float = 0.1
    rr_max: float = 1.5
    budget: float = 30.0
    lambda_warmup: int = 10
    violation_target: float = 0.1
    lambda_rise: float = 5.0
    lambda_max: float = 20.0
    lambda_decay: float = 0.95
    lambda0: float = 1.0
    weight_floor: float = 0.1
    replay_excess: str = "projected"
    lora_steps: int = 10
    lora_batch: int = 32
    lora_lr: float = 1e-4
    lora_rank: int = 0
    lora_labels: str = "auto"
    lora_dropout: bool = False
    lora_in_turn: bool | None = None
    lora_micro_batch: int = 0
    clip_ctg: bool = True
    stop_over_budget: bool = True

    def __post_init__(self) -> None:
        check.integers(self, "episodes", "stage_len", "window", "lora_steps", "lora_batch")
        check.integers(self, "horizon", optional=True)
        check.integers(self, "lambda_warmup", "lora_micro_batch", "lora_rank", minimum=0)
        check.positive(self, "z", "cr_step", "rr_step", "budget", "lambda_rise", "lora_lr")
        check.booleans(self, "lora_dropout", "clip_ctg", "stop_over_budget")
        check.booleans(self, "lora_in_turn", optional=True)
        check.one_of(self, "lora_labels", LABEL_CHOICES)
        check.one_of(self, "replay_excess", REPLAY_EXCESS)
        if not 0 <= self.tighten_below <= self.relax_above <= 1:
            raise ValueError("DeployConfig needs 0 <= tighten_below <= relax_above <= 1")
        if not 1 <= self.momentum_factor <= self.momentum_max:
            raise ValueError("DeployConfig needs 1 <= momentum_factor <= momentum_max")
        if not 0 < self.cr_min <= self.cr0 <= self.cr_max:
            raise ValueError("DeployConfig needs 0 < cr_min <= cr0 <= cr_max")
        if not 0 < self.rr_min <= self.rr0 <= self.rr_max:
            raise ValueError("DeployConfig needs 0 < rr_min <= rr0 <= rr_max")
        if not 0 <= self.violation_target <= 1:
            raise ValueError("DeployConfig.violation_target must be in [0, 1]")
        if not 0 < self.lambda_decay <= 1:
            raise ValueError("DeployConfig.lambda_decay must be in (0, 1]")
        if not 0 <= self.lambda0 <= self.lambda_max:
            raise ValueError("DeployConfig needs 0 <= lambda0 <= lambda_max")
        if not 0 < self.weight_floor <= 1:
            raise ValueError("DeployConfig.weight_floor must be in (0, 1]")

    def replace(self, **changes: Any) -> DeployConfig:
        """Return a copy with `changes` applied (validated again)."""
        return dataclasses.replace(self, **changes)

    def for_acting(self, stochastic_actions: bool) -> DeployConfig:
        """This config with `lora_labels` "auto" made the rule for a CDT that acts with
        samples (`stochastic_actions`) or its mean (`deploy.labels.resolve_label_rule`)."""
        return self.replace(lora_labels=resolve_label_rule(self.lora_labels,
                                                           bool(stochastic_actions)))

    def resolved(self, devices: list | None = None) -> DeployConfig:
        """This config with its per-device choices made: `lora_in_turn` None becomes True
        where `devices` (default: the default backend's) hold one CPU device of this process
        (one process alone, or each of several cooperating ones with one CPU device: every
        process then runs its seeds' LoRA steps on one device, as alone), else False."""
        if self.lora_in_turn is not None:
            return self
        devices = jax.devices() if devices is None else list(devices)
        local = [d for d in devices if d.process_index == jax.process_index()]
        one_cpu = len(local) == 1 and local[0].platform == "cpu"
        return self.replace(lora_in_turn=one_cpu)


@dataclass(frozen=True)
class Variant:
    """Which parts of Safe-CDT run, as arrays (a pytree; stack with `stack_variants`).

    Attributes:
        scheduler: bool []: adapt CR and RR with the Wilson-score scheduler; when False, CR is
            `cr_first` / `cr_second` and RR stays `DeployConfig.rr0`.
        reweight: bool []: cost-aware replay weights; when False lambda = 0 and every weight 1.
        lora: bool []: finetune the adapters after every episode; when False they never change.
        cr_first: float32 []: fixed cost ratio for episodes < switch_episode (scheduler off).
        cr_second: float32 []: fixed cost ratio for episodes >= switch_episode (scheduler off).
        switch_episode: int32 []: first episode index that uses `cr_second`.
    """

    scheduler: Any
    reweight: Any
    lora: Any
    cr_first: Any
    cr_second: Any
    switch_episode: Any


jax.tree_util.register_dataclass(Variant)

VARIANT_SPECS: tuple[str, ...] = (
    "safe_cdt", "no_reweight", "scheduler_only", "zero_shot", "naive_lora",
    "fixed_ctg(r)", "step_change(r1,r2)", "step_change(r1,r2,switch)",
)

# (scheduler, reweight, lora) of the named variants; docs/METHOD.md section 5. A "-" in that
# table (reweighting without LoRA has no effect) is off here, so lambda is logged as 0 there.
_FLAGS = {
    "safe_cdt": (True, True, True),
    "no_reweight": (True, False, True),
    "scheduler_only": (True, False, False),
    "zero_shot": (False, False, False),
    "naive_lora": (False, False, True),
}
_NUM = r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*"
_FIXED = re.compile(rf"fixed_ctg\({_NUM}\)")
_STEP = re.compile(rf"step_change\({_NUM}(?:,|->|→){_NUM}(?:,\s*(\d+)\s*)?\)")


def _variant(flags, cr_first: float, cr_second: float, switch: int) -> Variant:
    scheduler, reweight, lora = flags
    return Variant(
        scheduler=jnp.asarray(scheduler, jnp.bool_),
        reweight=jnp.asarray(reweight, jnp.bool_),
        lora=jnp.asarray(lora, jnp.bool_),
        cr_first=jnp.asarray(cr_first, jnp.float32),
        cr_second=jnp.asarray(cr_second, jnp.float32),
        switch_episode=jnp.asarray(switch, jnp.int32),
    )


def make_variant(spec: str, cfg: DeployConfig | None = None) -> Variant:
    """Parse a variant name of docs/METHOD.md section 5 into a `Variant`.

    `safe_cdt`, `no_reweight`, `scheduler_only`, `zero_shot`, `naive_lora`, `fixed_ctg(r)`
    (CR = r throughout, no adaptation) and `step_change(r1,r2)` (also `r1->r2`; CR = r1 before
    episode `cfg.episodes // 2`, r2 from it on, no adaptation; `step_change(r1,r2,s)` switches
    at episode s).
    Ratios must lie in [cfg.cr_min, cfg.cr_max]. Raises ValueError listing the valid specs.
    """
    cfg = DeployConfig() if cfg is None else cfg
    name = spec.strip()
    off = (False, False, False)
    never = cfg.episodes  # cr_second == cr_first, so the switch is immaterial
    if name in _FLAGS:
        return _variant(_FLAGS[name], cfg.cr0, cfg.cr0, never)
    if m := _FIXED.fullmatch(name):
        r = _ratio(float(m.group(1)), spec, cfg)
        return _variant(off, r, r, never)
    if m := _STEP.fullmatch(name):
        r1, r2 = _ratio(float(m.group(1)), spec, cfg), _ratio(float(m.group(2)), spec, cfg)
        switch = cfg.episodes // 2 if m.group(3) is None else int(m.group(3))
        return _variant(off, r1, r2, switch)
    raise ValueError(f"unknown variant {spec!r}; valid specs: {', '.join(VARIANT_SPECS)}")


def _ratio(r: float, spec: str, cfg: DeployConfig) -> float:
    if not cfg.cr_min <= r <= cfg.cr_max:
        raise ValueError(
            f"variant {spec!r}: cost ratio {r} outside [cr_min, cr_max] = "
            f"[{cfg.cr_min}, {cfg.cr_max}]"
        )
    return r


def stack_variants(variants: list[Variant] | tuple[Variant, ...]) -> Variant:
    """Stack variants along a new leading axis (for `jax.vmap` over variants)."""
    if not variants:
        raise ValueError("stack_variants needs at least one variant")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *variants)
