"""Settings of offline CDT pretraining, and the default run length of each model preset."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from safecdt_jax import validate as check
from safecdt_jax.presets import CPU_MICRO_BATCH, PRETRAIN

LABELS = ("episode", "policy", "auto")  # what the return- and cost-to-go tokens count from


@dataclass(frozen=True)
class PretrainConfig:
    """How long and on what batches the CDT is pretrained (OSRL's `train_cdt.py` where it applies).

    Attributes:
        steps: total optimiser updates (OSRL: 100,000; see `default_pretrain` for the presets).
        batch_size: K-step windows per update (OSRL: 2048; far too slow on a CPU).
        micro_batch: the most windows per forward/backward pass. A larger batch is split into
            the fewest equal passes that fit, and the update sums their gradients before its
            one optimiser step (`model.batch_gradients`); 0 is always one pass. The same update
            up to float summation order, except that each pass draws its own dropout masks.
        chunk: updates per jitted call, one `lax.scan`; the host only sees the state (progress
            bar, checkpoints) between chunks. Larger chunks amortise dispatch, smaller ones give a
            finer progress bar and checkpoint grid.
        seed: the run's PRNG seed. Parameter init, Pareto relabelling and the key of update `i`
            (`fold_in(key(seed), i)`, batch and dropout) derive from it, so a resumed run is
            bit-identical to an uninterrupted one.
        c0: trajectory weights are `max(0, c0 - C_i)`, C_i the episode's total cost (raw units);
            episodes costing c0 or more are never sampled (OSRL: 70).
        relabel: append OSRL's Pareto-relabelled copies (infeasible high-return targets paired with
            safer episodes) before sampling. On by default, as in OSRL (`augment_percent=0.2`):
            it teaches the model to stay inside a cost target when the return target is
            unreachable, which is exactly how deployment conditions it.
        relabel_percent: relabelled copies per grid-filtered episode (OSRL's `augment_percent`,
            0.2).
        labels: what an episode's return- and cost-to-go count from. `"episode"`: its own
            realised return and cost (OSRL). `"policy"`: the mean return and cost of the
            policy that drove it (`data.policy_mean_labels`, grouping by the expert data's
            `episode_info/snapshot`), so that the tokens name the driving rather than the
            layout's luck; the tokens still fall by the realised rewards and costs (unless
            `CDTConfig.constant_targets`). `"auto"`: `"policy"` when the data name each
            episode's behaviour policy (`episode_info/snapshot`, as expert data do), else
            `"episode"` (e.g. downloaded DSRL data, which do not name them).
        scale_actions: train on actions divided by the data's largest |action| per dimension,
            then fold the scale into the saved weights (`safecdt_jax.pretrain.normalize`), which
            emit raw actions either way. Off by default, as in OSRL, whose agents' actions fill
            [-1, 1]; executed Car wheel commands stay within +-0.02 (its actuators
            saturate there). Measured effects: docs/METHOD.md section 8.
        standardize_obs: train on observations standardised by the data's mean and std (also
            folded into the weights). Off by default: on CarCircle1 it loses the cost response.
        return_span: raw returns (lo, hi) the return token's ramp edges cover at least, whatever
            the data hold (`model.tokens.fit_edges`: an end of the span beyond the data's labels
            takes one of the bins); () for the data's own range. Only with `token_bins`.
        cost_span: the same for the cost token, raw cost units. Why (the `cpu` preset's
            (0, 100) and (-50, 100)): with edges at the data's quantiles alone every cost target
            below the data's lowest label was one input (CarGoal1: 12.7), so the scheduler's
            tightening below it could not reach the model, and the negative returns of the
            level-2 tasks' episodes all read as the lowest return (docs/METHOD.md section 0).
        checkpoint_every: write a checkpoint whenever a chunk ends at or past a multiple of this
            many updates (the final step is always saved); 0 saves only at the end.
        max_to_keep: checkpoints kept in the folder (oldest deleted first).
    """

    steps: int = 10_000
    batch_size: int = 32
    micro_batch: int = 0
    chunk: int = 100
    seed: int = 0
    c0: float = 70.0
    relabel: bool = True
    relabel_percent: float = 0.2
    labels: str = "episode"
    scale_actions: bool = False
    standardize_obs: bool = False
    return_span: tuple[float, ...] = ()
    cost_span: tuple[float, ...] = ()
    checkpoint_every: int = 2000
    max_to_keep: int = 2

    def __post_init__(self) -> None:
        check.integers(self, "steps", "batch_size", "chunk", "max_to_keep")
        check.integers(self, "seed", "checkpoint_every", "micro_batch", minimum=0)
        check.positive(self, "c0")
        check.booleans(self, "relabel", "scale_actions", "standardize_obs")
        check.positive(self, "relabel_percent")
        for name in ("return_span", "cost_span"):
            span = getattr(self, name)
            if span != () and not (isinstance(span, tuple) and len(span) == 2
                                   and all(isinstance(x, int | float) for x in span)
                                   and span[0] < span[1]):
                raise ValueError(f"PretrainConfig.{name} must be () or (lo, hi) with lo < hi, "
                                 f"got {span!r}")
        check.one_of(self, "labels", LABELS)

    def replace(self, **changes: Any) -> PretrainConfig:
        """A copy with `changes` applied (validated again)."""
        return dataclasses.replace(self, **changes)


def default_pretrain(
    preset: str, *, backend: str | None = None, **overrides: Any
) -> PretrainConfig:
    """The default `PretrainConfig` for model preset `preset`, with `overrides` applied.

    On a CPU backend (`backend`, default `jax.default_backend()`) the presets named in
    `CPU_MICRO_BATCH` compute each update in passes of that many windows unless `overrides` set
    `micro_batch`: the same update up to summation order, with each pass's own dropout draws.
    Raises ValueError for an unknown preset name.
    """
    if preset not in PRETRAIN:
        raise ValueError(f"unknown CDT preset {preset!r}; choose one of {', '.join(PRETRAIN)}")
    cfg = PretrainConfig(**PRETRAIN[preset]).replace(**overrides)
    if "micro_batch" not in overrides and preset in CPU_MICRO_BATCH:
        import jax

        if (backend or jax.default_backend()) == "cpu":
            cfg = cfg.replace(micro_batch=CPU_MICRO_BATCH[preset])
    return cfg
