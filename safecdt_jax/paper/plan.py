"""What `safecdt-jax paper` runs: the counts of every experiment (a frozen `PaperPlan`) and the
list of experiments it implies (`experiments(plan)`), each one vmapped sweep call.

Experiments per pair (names are `PAIR_NAME`; each writes `experiments/PAIR_NAME.json`):
- `main`: Safe-CDT at the budget (Table 1; CG1-CG2's row is also Table 4's).
- `studies` (the study pair only, CG1-CG2): Safe-CDT at every budget of Table 2 beside the
  ablation variants of Table 3 at the budget, one sweep of (variant, budget) runs.
- `ctg`: zero-shot fixed CTG ratios and the two step changes (Tables 5 and 6, Figure 2), each
  run `intervention_episodes` long; Table 5 reads the fixed runs' first `episodes` episodes.
- `source_ctg`: the same fixed ratios in the source task (the certificate's transfer check).
- `baselines`: the offline baselines of Tables 4 and 7 (`safecdt-jax baselines`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from safecdt_jax import validate as check

ABLATIONS = ("safe_cdt", "no_reweight", "scheduler_only", "zero_shot", "naive_lora")


@dataclass(frozen=True)
class PaperPlan:
    """Counts and settings of the paper suite (defaults: the paper's section 5 protocol).

    Attributes:
        pairs: deployment pairs to run (the paper's three).
        budget: cost budget B of every table but Table 2 (30, cost units).
        pretrain_seeds: pretrained checkpoints per pair behind every deployment (3; the
            paper reports one): a row of N seeds runs as P checkpoints (pretraining seeds
            `seed`..`seed + P - 1`, trained in one vmapped call) x ceil(N / P) deployment
            seeds, the same deployment seeds on every checkpoint, and Tables 1-3 report the
            spread between checkpoints beside that across deployment seeds. Tables 5 and 6
            and the certificate pool the checkpoints' runs (one checkpoint does not decide
            how cost follows the CTG target: three CarGoal1 checkpoints cost 14.8, 16.7 and 20.2
            in CarGoal2 at CR 0.2).
        main_seeds: seeds of the study pair's Table 1 row (15, as the paper's CG1-CG2).
        other_seeds: seeds of the other pairs' Table 1 rows (3).
        study_pair: the pair of Tables 2 and 3 (CG1-CG2).
        study_seeds: seeds of Tables 2 and 3 (3).
        budgets: Table 2's budgets.
        ablations: Table 3's variants.
        ctg_ratios: Table 5's fixed CTG ratios CR (CTG target = CR * B).
        ctg_seeds: seeds of Tables 5 and 6 (5).
        episodes: deployment episodes per seed (50).
        intervention_episodes: Table 6's episodes per seed (100; the switch at half).
        step_low, step_high: Table 6's low and high CTG ratios (0.2 and 1.0).
        source_seeds: seeds of the fixed-ratio sweep in the source task (3).
        baseline_algos: Tables 4 and 7's methods (OSRL's three plus BC-All and BC-Safe).
        baseline_seeds, baseline_episodes: the baselines' seeds and evaluation episodes (3, 20).
        baseline_preset: the baselines' preset (`cpu`: 1,500 updates each, OSRL's networks).
        train_baselines: train baselines that are not cached (True); False reuses cached
            results only and leaves the tables' baseline rows empty otherwise (`--quick`).
        preset: the CDT preset pretrained on each source task (`cpu`).
        horizon: cut every episode at this many steps (None: the task's time limit).
        alpha, kappa: the certificate's tolerated probability of any violation and B*'s
            confidence coefficient (docs/METHOD.md section 7).
        seed: base PRNG seed of every experiment.
        lora_labels: `DeployConfig.lora_labels` of every deployment with LoRA steps
            ("auto": "target" acting with samples, "stage" with the mean; "hindsight" is the
            paper's rule; a spec holds the rule `act` resolves it to). Each LoRA experiment
            records it in its spec, beside how its seeds' LoRA gradients ran
            (`DeployConfig.lora_in_turn` as the devices resolve it: in turn on one CPU device,
            batched elsewhere).
        replay_excess: `DeployConfig.replay_excess` of every deployment ("projected";
            "realised" is the paper's reading); an adapting experiment's spec holds it.
        act: how the CDT acts in every deployment: "sample" (samples of its policy, the
            default since 2026-12-07: `analysis.evaluate.DEFAULT_ACTION_MODE`), "mean" or
            "checkpoint" (its own `CDTConfig.stochastic_actions`, the mean in every preset;
            docs/METHOD.md section 1). A spec holds it unless "checkpoint", so the records
            made before it existed are reused under `--act checkpoint`.
    """

    pairs: tuple[str, ...] = ("CG1-CG2", "CC1-CC2", "PC1-PC2")
    budget: float = 30.0
    pretrain_seeds: int = 3
    main_seeds: int = 15
    other_seeds: int = 3
    study_pair: str = "CG1-CG2"
    study_seeds: int = 3
    budgets: tuple[float, ...] = (25.0, 30.0, 35.0, 40.0, 50.0)
    ablations: tuple[str, ...] = ABLATIONS
    ctg_ratios: tuple[float, ...] = (0.2, 0.4, 0.6, 0.8, 1.0)
    ctg_seeds: int = 5
    episodes: int = 50
    intervention_episodes: int = 100
    step_low: float = 0.2
    step_high: float = 1.0
    source_seeds: int = 3
    baseline_algos: tuple[str, ...] = ("bcql", "bearl", "cpq", "bc_all", "bc_safe")
    baseline_seeds: int = 3
    baseline_episodes: int = 20
    baseline_preset: str = "cpu"
    train_baselines: bool = True
    preset: str = "cpu"
    horizon: int | None = None
    alpha: float = 0.05
    kappa: float = 1.0
    seed: int = 0
    lora_labels: str = "auto"
    replay_excess: str = "projected"
    act: str = "sample"

    def __post_init__(self) -> None:
        from safecdt_jax.pairs import PAIRS

        check.integers(self, "pretrain_seeds", "main_seeds", "other_seeds", "study_seeds",
                       "ctg_seeds",
                       "episodes", "intervention_episodes", "source_seeds", "baseline_seeds",
                       "baseline_episodes")
        check.integers(self, "horizon", optional=True)
        check.integers(self, "seed", minimum=0)
        check.positive(self, "budget", "kappa")
        check.booleans(self, "train_baselines")
        from safecdt_jax.deploy.config import REPLAY_EXCESS
        from safecdt_jax.deploy.labels import LABEL_CHOICES

        check.one_of(self, "lora_labels", LABEL_CHOICES)
        check.one_of(self, "replay_excess", REPLAY_EXCESS)
        from safecdt_jax.analysis.evaluate import ACTION_MODES

        check.one_of(self, "act", tuple(ACTION_MODES))
        bad = [p for p in self.pairs if p not in PAIRS]
        if bad or not self.pairs:
            raise ValueError(f"PaperPlan.pairs: unknown pair {', '.join(bad) or '(none)'}; "
                             f"valid pairs: {', '.join(PAIRS)}")
        if self.intervention_episodes % 2 or self.intervention_episodes < self.episodes:
            raise ValueError("PaperPlan.intervention_episodes must be even and >= episodes, got "
                             f"{self.intervention_episodes!r}")
        if not 0 < self.alpha < 1:
            raise ValueError(f"PaperPlan.alpha must lie in (0, 1), got {self.alpha!r}")
        if not all(b > 0 for b in self.budgets) or not self.budgets:
            raise ValueError(f"PaperPlan.budgets must be positive, got {self.budgets!r}")

    def record(self) -> dict[str, Any]:
        """The plan as JSON-ready data."""
        return dataclasses.asdict(self)


# `--quick`: every table and figure from few seeds and episodes (a first look and the test).
# The baselines keep the full counts: quick never trains them, it reuses the full suite's.
QUICK = dict(pretrain_seeds=1, main_seeds=2, other_seeds=2, study_seeds=2, ctg_seeds=2,
             episodes=10,
             intervention_episodes=20, source_seeds=2, train_baselines=False)


def quick_plan(**overrides: Any) -> PaperPlan:
    """The `--quick` plan (QUICK's counts), with `overrides` on top."""
    return PaperPlan(**(QUICK | overrides))


@dataclass(frozen=True)
class Experiment:
    """One experiment: a deployment sweep (`kind` 'deploy', in the pair's `task`: 'target' or
    'source') of (variant, budget) `runs` x `pretrain_seeds` checkpoints x `seeds` deployment
    seeds x `episodes`, or the pair's baselines (`kind` 'baselines')."""

    pair: str
    name: str
    kind: str
    task: str = "target"
    runs: tuple[tuple[str, float], ...] = ()
    seeds: int = 0
    episodes: int = 0
    pretrain_seeds: int = 1

    @property
    def key(self) -> str:
        """The experiment's file stem, e.g. `CG1-CG2_main`."""
        return f"{self.pair}_{self.name}"


def ctg_variants(plan: PaperPlan) -> list[str]:
    """The fixed-ratio variants of Table 5, then Table 6's low->high and high->low changes."""
    fixed = [f"fixed_ctg({r:g})" for r in plan.ctg_ratios]
    lo, hi = f"{plan.step_low:g}", f"{plan.step_high:g}"
    return [*fixed, f"step_change({lo},{hi})", f"step_change({hi},{lo})"]


def experiments(plan: PaperPlan) -> list[Experiment]:
    """Every experiment of `plan`, in run order (pair by pair)."""
    out = []
    b = plan.budget
    n_ckpt = plan.pretrain_seeds
    per_ckpt = lambda seeds: -(-seeds // n_ckpt)  # ceil: at least the requested runs
    for pair in plan.pairs:
        study = pair == plan.study_pair
        out.append(Experiment(pair, "main", "deploy", runs=(("safe_cdt", b),),
                              seeds=per_ckpt(plan.main_seeds if study else plan.other_seeds),
                              episodes=plan.episodes, pretrain_seeds=n_ckpt))
        if study:
            runs = [("safe_cdt", x) for x in plan.budgets]
            runs += [(v, b) for v in plan.ablations if (v, b) not in runs]
            out.append(Experiment(pair, "studies", "deploy", runs=tuple(runs),
                                  seeds=per_ckpt(plan.study_seeds), episodes=plan.episodes,
                                  pretrain_seeds=n_ckpt))
        out.append(Experiment(pair, "ctg", "deploy", runs=tuple((v, b) for v in ctg_variants(plan)),
                              seeds=per_ckpt(plan.ctg_seeds), episodes=plan.intervention_episodes,
                              pretrain_seeds=n_ckpt))
        fixed = tuple((f"fixed_ctg({r:g})", b) for r in plan.ctg_ratios)
        out.append(Experiment(pair, "source_ctg", "deploy", task="source", runs=fixed,
                              seeds=per_ckpt(plan.source_seeds), episodes=plan.episodes,
                              pretrain_seeds=n_ckpt))
        out.append(Experiment(pair, "baselines", "baselines", seeds=plan.baseline_seeds,
                              episodes=plan.baseline_episodes))
    return out
