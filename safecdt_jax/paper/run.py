"""Run the paper suite: prepare each pair's checkpoint, run every experiment of a `PaperPlan`
that is not already finished, and keep each result in its own file.

Each experiment writes `OUT/experiments/PAIR_NAME.json` atomically with its spec (what made it:
counts, runs, task, the checkpoint's identity), its wall time and its results. A rerun loads
every file whose spec equals the current one and runs only the rest, so an interrupted suite
continues where it stopped and a changed plan reruns only what it changes. A checkpoint of
collected expert data is identified by the data's recipe, not its bits, so a suite continues on
another kind of CPU, where the same recipe collects episodes that differ in float rounding
(`checkpoint_identity`); a record keyed the older way on the bits is upgraded where the bits
here are the same. Under N cooperating processes (`safecdt_jax.distributed`, on a shared disk)
the deployment sweeps shard their seeds over every process; process 0 alone prepares
checkpoints, trains baselines and writes files.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from safecdt_jax.distributed import is_writer, process_zero_first
from safecdt_jax.paper.plan import Experiment, PaperPlan, experiments

RECORD_FORMAT = 1


def source_data(pair: str, plan: PaperPlan) -> Path:
    """The cached expert data of `pair`'s source task, collected first if missing or stale."""
    from safecdt_jax.experts.collect import ensure_source_data
    from safecdt_jax.pairs import parse_pair

    return ensure_source_data(parse_pair(pair)[0], seed=plan.seed)


def prepare_pair(pair: str, plan: PaperPlan, progress: bool = True,
                 data: str | os.PathLike | None = None) -> Path:
    """The pretrained CDT of `pair`'s source task (plan.preset), as `safecdt-jax run` makes it:
    the cached expert data (`data`, default `source_data`) and checkpoint reused, collected or
    trained if missing."""
    from safecdt_jax.pairs import parse_pair
    from safecdt_jax.pretrain.run import ensure_checkpoint

    source, _ = parse_pair(pair)
    return ensure_checkpoint(data or source_data(pair, plan), source, plan.preset,
                             seed=plan.seed, overwrite=True, progress=progress)


def prepare_checkpoints(pair: str, plan: PaperPlan, progress: bool = True) -> list[Path]:
    """Every pretrained checkpoint the pair's experiments read: `prepare_pair`'s, then the other
    pretraining seeds' (`prepare_seeds`), all on one check of the source data."""
    data = source_data(pair, plan)
    return prepare_seeds(pair, plan, prepare_pair(pair, plan, progress, data), progress, data)


def prepare_seeds(pair: str, plan: PaperPlan, first: Path, progress: bool = True,
                  data: str | os.PathLike | None = None) -> list[Path]:
    """The pair's `plan.pretrain_seeds` checkpoints: `first` (pretraining seed `plan.seed`,
    from `prepare_pair`) and seeds `plan.seed + 1`.. beside it (`pretrain.seeds.default_outs`),
    trained together in one vmapped call on `data` (default: the file `first` names) where
    missing, stale or of another run."""
    from safecdt_jax.pretrain.checkpoint import configs_from_meta, read_meta
    from safecdt_jax.pretrain.seeds import default_outs, pretrain_seeds

    extra = list(range(plan.seed + 1, plan.seed + plan.pretrain_seeds))
    if not extra:
        return [first]
    meta = read_meta(first)
    _, optim, config = configs_from_meta(meta)
    outs = default_outs(meta["task"], plan.preset, extra)
    # The data `first` trained on, where the cache has it now (the path in its metadata is
    # where it was then); `pretrain_seeds` checks the fingerprint through the configs.
    data = data or meta["dataset"]["path"]
    pretrain_seeds(data, extra, outs, preset=plan.preset, config=config,
                   optim=optim, task=meta["task"], progress=progress, overwrite=True)
    return [first, *outs]


def checkpoint_identity(ckpt: str | os.PathLike, recipe: str | None = None,
                        legacy: bool = False) -> dict[str, Any]:
    """What identifies a pretrained checkpoint in an experiment's spec: its task, preset,
    update count, its data, the spans of its token edges, and a digest of how it was made (not
    its folder, so a clone whose cache lives elsewhere reuses the committed experiments).

    The data are named by their recipe (`recipe`, else the one in the checkpoint's metadata;
    `experts.collect.data_recipe`) and the model by its config without the token edges plus
    the pretraining and optimiser settings: both the same on every CPU, while the collected
    episodes' bits, and with them the edges fitted to their labels, are not. Data without a
    recipe, or `legacy`, give the bit-level identity records were keyed on before 2026-12-07:
    the data's fingerprint and a digest of the whole model config (edges included)."""
    import hashlib

    from safecdt_jax.pretrain.checkpoint import read_meta

    def digest(value: Any) -> str:
        text = json.dumps(value, sort_keys=True).encode()
        return hashlib.blake2b(text, digest_size=8).hexdigest()

    meta = read_meta(ckpt)
    recipe = None if legacy else recipe or meta["dataset"].get("recipe")
    out = {"task": meta["task"], "preset": meta["preset"], "step": int(meta["step"])}
    if recipe is None:
        out |= {"data": meta["dataset"]["fingerprint"], "model": digest(meta["model"])}
    else:
        model = {k: v for k, v in meta["model"].items() if k not in _FITTED}
        pretrain = {k: v for k, v in meta.get("pretrain", {}).items() if k not in _BOOKKEEPING}
        out |= {"data": recipe, "model": digest([model, pretrain, meta.get("optim")])}
    pretrain = meta.get("pretrain", {})
    spans = {k: pretrain[k] for k in ("return_span", "cost_span") if pretrain.get(k)}
    return out | spans


# Model fields fitted to the data's labels, and pretraining fields that do not change the model.
_FITTED = ("return_edges", "cost_edges")
_BOOKKEEPING = ("seed", "checkpoint_every", "max_to_keep")


def seeded_identity(ckpts: list[Path], recipe: str | None = None,
                    legacy: bool = False) -> dict[str, Any]:
    """`checkpoint_identity` of the first checkpoint, plus under `seeds` every checkpoint's
    identity with its pretraining seed (what a multi-checkpoint experiment's spec records)."""
    from safecdt_jax.pretrain.checkpoint import read_meta

    ids = [checkpoint_identity(c, recipe, legacy) | {"seed": read_meta(c)["pretrain"]["seed"]}
           for c in ckpts]
    return checkpoint_identity(ckpts[0], recipe, legacy) | {"seeds": ids}


def experiment_spec(e: Experiment, plan: PaperPlan, ckpt_id: Mapping[str, Any]) -> dict[str, Any]:
    """Everything that decides an experiment's result, as JSON-ready data (two runs with equal
    specs give the same result, so a finished one is reused)."""
    from safecdt_jax.deploy.config import DeployConfig
    from safecdt_jax.envs import env_version
    from safecdt_jax.pairs import parse_pair

    source, target = parse_pair(e.pair)
    spec = {"format": RECORD_FORMAT, "pair": e.pair, "name": e.name, "kind": e.kind,
            "seeds": e.seeds, "episodes": e.episodes, "budget": plan.budget}
    seeded = ckpt_id.get("seeds")
    ckpt_id = {k: v for k, v in ckpt_id.items() if k != "seeds"}
    if e.kind == "deploy":
        task = source if e.task == "source" else target
        if e.pretrain_seeds > 1:  # the identities of every pretraining seed's checkpoint
            spec |= {"pretrain_seeds": e.pretrain_seeds,
                     "checkpoints": None if seeded is None else seeded[:e.pretrain_seeds]}
        spec |= {"task": task, "env": env_version(task),
                 "runs": [[v, float(b)] for v, b in e.runs], "horizon": plan.horizon,
                 "seed": plan.seed, "stop_over_budget": True, "checkpoint": dict(ckpt_id)}
        if plan.act != "checkpoint":  # acting as the checkpoint says keeps the older specs
            spec["act"] = plan.act
        # How LoRA ran changes the bits of a LoRA run only: runs without LoRA share records.
        if _has_lora(e):
            in_turn = DeployConfig().resolved().lora_in_turn
            spec |= {"lora_in_turn": in_turn, "lora_labels": _label_rule(plan)}
        if _adapts(e):  # every scheduler and LoRA setting decides an adapting run's result,
            # so a changed default is a new experiment, never a stale record reused
            settings = dataclasses.asdict(DeployConfig(replay_excess=plan.replay_excess))
            spec["deploy_config"] = {k: v for k, v in settings.items() if k not in _IN_SPEC
                                     and (k, v) not in _ADDED_AT.items()}
        return spec
    return spec | {"algos": list(plan.baseline_algos), "preset": plan.baseline_preset,
                   "stop_over_budget": True, "data": ckpt_id["data"], "env": env_version(target)}


# DeployConfig fields the spec holds elsewhere (from the plan) or that the devices resolve.
_IN_SPEC = ("episodes", "horizon", "budget", "lora_labels", "lora_in_turn", "stop_over_budget")

# DeployConfig fields added after records were made, at the value that reproduces those records:
# a field at that value stays out of the spec, so the records it did not change are reused.
_ADDED_AT = {"replay_excess": "realised"}


def _label_rule(plan: PaperPlan) -> str:
    """The LoRA label rule the plan's deployments run: "auto" resolved where `plan.act` says
    how the CDT acts (kept "auto" under "checkpoint", where the checkpoint's identity decides)."""
    from safecdt_jax.analysis.evaluate import parse_action_mode
    from safecdt_jax.deploy.labels import resolve_label_rule

    acts = parse_action_mode(plan.act)
    return plan.lora_labels if acts is None else resolve_label_rule(plan.lora_labels, acts)


def _adapts(e: Experiment) -> bool:
    """Whether any run of deployment `e` retunes its targets or finetunes its adapters."""
    from safecdt_jax.deploy.config import make_variant

    return any(bool(make_variant(v).scheduler) or bool(make_variant(v).lora) for v, _ in e.runs)


def _has_lora(e: Experiment) -> bool:
    """Whether any run of deployment `e` finetunes its adapters."""
    from safecdt_jax.deploy.config import make_variant

    return any(bool(make_variant(v).lora) for v, _ in e.runs)


def _compact(results: dict[str, Any], decimals: int = 5) -> dict[str, Any]:
    """The deployment results with per-episode metrics rounded (float32 values carry about 7
    significant digits; 5 decimals keep costs and returns exact to 1e-5 and the files small)."""
    runs = [dict(run, metrics={k: np.round(np.asarray(v, np.float64), decimals).tolist()
                               for k, v in run["metrics"].items()}) for run in results["runs"]]
    return dict(results, runs=runs)


def baselines_folder(pair: str, preset: str) -> Path:
    """Where the suite keeps a pair's baselines (checkpoints and `baselines.json`): the cache,
    so that `paper` and `paper --quick` share them."""
    from safecdt_jax.paths import cache_root

    return cache_root() / "baselines" / f"{pair}-{preset}"


def _matching_baselines(folder: Path, spec: Mapping[str, Any]) -> dict[str, Any] | None:
    """The `baselines.json` in `folder` if it was made with the spec's settings and data (its
    recipe, or its fingerprint for data without one) and evaluated on the spec's target env
    version (a file without one predates the check and is evaluated again)."""
    path = folder / "baselines.json"
    if not path.is_file():
        return None
    saved = json.loads(path.read_text())
    same = (saved.get("pair") == spec["pair"] and saved.get("seeds") == spec["seeds"]
            and saved.get("episodes") == spec["episodes"]
            and float(saved.get("budget", -1)) == spec["budget"]
            and saved.get("preset") == spec["preset"]
            and saved.get("stop_over_budget") is True
            and saved.get("target_env") == spec["env"]
            and [m["algo"] for m in saved.get("methods", [])] == spec["algos"]
            and spec["data"] in (saved.get("data", {}).get("recipe"),
                                 saved.get("data", {}).get("fingerprint")))
    return saved if same else None


def _run_baselines(spec: Mapping[str, Any], plan: PaperPlan, progress: bool
                   ) -> dict[str, Any] | None:
    """The pair's baselines results: the cached `baselines.json` when it matches the spec
    (marked `cached`), else trained and evaluated now (`plan.train_baselines`), else None."""
    from safecdt_jax.baselines.job import run_baselines

    folder = baselines_folder(spec["pair"], spec["preset"])
    saved = _matching_baselines(folder, spec)
    if saved is not None or not plan.train_baselines:
        return None if saved is None else dict(saved, cached=True)
    return run_baselines(spec["pair"], spec["algos"], spec["seeds"], spec["budget"],
                         spec["preset"], spec["episodes"], out=folder, progress=progress)


def _run_deploy(e: Experiment, spec: Mapping[str, Any], plan: PaperPlan,
                ckpts: list[Path], progress: bool) -> dict[str, Any]:
    from safecdt_jax.analysis.evaluate import parse_action_mode
    from safecdt_jax.deploy.config import DeployConfig
    from safecdt_jax.deploy.job import run_deployment

    cfg = DeployConfig(episodes=e.episodes, horizon=plan.horizon, budget=plan.budget,
                       lora_labels=plan.lora_labels, replay_excess=plan.replay_excess)
    which = ckpts[:e.pretrain_seeds] if e.pretrain_seeds > 1 else ckpts[0]
    results = run_deployment(which, spec["task"], [], [], e.seeds, seed=plan.seed, cfg=cfg,
                             progress=progress, runs=e.runs,
                             stochastic_actions=parse_action_mode(plan.act))
    return _compact(results)


def load_record(path: Path, spec: Mapping[str, Any]) -> dict[str, Any] | None:
    """The finished experiment record at `path` if its spec equals `spec`, else None."""
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError:  # never written atomically by us: treat as unfinished
        return None
    return record if record.get("spec") == json.loads(json.dumps(spec)) else None


def run_experiment(e: Experiment, plan: PaperPlan, ckpt: Path | list[Path], folder: Path,
                   progress: bool = True, log: Callable[[str], None] = print,
                   ckpt_id: Mapping[str, Any] | None = None) -> dict[str, Any] | None:
    """The record of experiment `e` (`{"spec", "seconds", "finished", "results"}`), loaded from
    `folder/KEY.json` when finished with the same spec, else run and written there atomically.
    A record keyed on the bits of these very checkpoints' data (`checkpoint_identity(...,
    legacy=True)`) is reused too, its spec rewritten to the current one. None for baselines
    that are neither cached nor to be trained (`plan.train_baselines`). `ckpt`: the pair's
    checkpoint, or its pretraining seeds' checkpoints (the first is the one of
    single-checkpoint experiments); `ckpt_id`: `seeded_identity(ckpt, ...)`, when the caller
    has it."""
    from safecdt_jax.io import write_text_atomic

    ckpts = [Path(ckpt)] if isinstance(ckpt, str | os.PathLike) else [Path(c) for c in ckpt]
    if e.kind == "deploy" and e.pretrain_seeds > len(ckpts):
        raise ValueError(f"{e.key}: {e.pretrain_seeds} pretraining seeds, {len(ckpts)} "
                         f"checkpoint(s) given")
    spec = experiment_spec(e, plan, ckpt_id or seeded_identity(ckpts))
    path = folder / f"{e.key}.json"
    record = load_record(path, spec)
    if record is None:
        legacy = seeded_identity(ckpts, legacy=True)
        record = load_record(path, experiment_spec(e, plan, legacy))
        if record is not None and record["spec"] != spec:
            record = dict(record, spec=spec, data_fingerprint=legacy["data"])
            if is_writer():
                write_text_atomic(path, json.dumps(record))
            log(f"{e.key}: finished earlier on the same data's bits; its spec now names the "
                f"data's recipe")
    if record is not None:
        log(f"{e.key}: finished earlier ({record['seconds']:.0f} s), reused")
        return record
    log(f"{e.key}: running ({_describe(e)})")
    start = time.perf_counter()
    if e.kind == "deploy":  # a sweep: every cooperating process computes its seeds
        results = _run_deploy(e, spec, plan, ckpts, progress)
    else:  # not sharded: process 0 trains, the others wait and load what it cached
        results = process_zero_first(f"paper:{e.key}", lambda: _run_baselines(spec, plan,
                                                                               progress))
        if results is None:
            log(f"{e.key}: no cached baselines with these settings; skipped (train them with "
                f"the full `paper` or `safecdt-jax baselines`)")
            return None
    from safecdt_jax.pretrain.checkpoint import read_meta

    record = {"spec": spec, "seconds": time.perf_counter() - start,
              "finished": time.strftime("%Y-%m-%d %H:%M:%S"),
              "data_fingerprint": read_meta(ckpts[0])["dataset"]["fingerprint"],
              "results": results}
    if is_writer():  # among cooperating processes, process 0 writes
        folder.mkdir(parents=True, exist_ok=True)
        write_text_atomic(path, json.dumps(record))
    log(f"{e.key}: done in {record['seconds']:.0f} s")
    return record


def _recipe(pair: str, plan: PaperPlan, checkpoints: Mapping[str, Any] | None) -> str | None:
    """The recipe of the source data the pair's prepared checkpoints trained on (None where the
    caller gave the checkpoints: their metadata says)."""
    from safecdt_jax.data.collect import file_attrs
    from safecdt_jax.experts.collect import data_recipe

    if checkpoints is not None and pair in checkpoints:
        return None
    return data_recipe(file_attrs(source_data(pair, plan)) or {})


def _describe(e: Experiment) -> str:
    if e.kind == "baselines":
        return f"baselines, {e.seeds} seeds x {e.episodes} episodes"
    return f"{len(e.runs)} run(s) x {e.seeds} seeds x {e.episodes} episodes in the {e.task}"


def run_paper(plan: PaperPlan, out: str | os.PathLike, *, progress: bool = True,
              checkpoints: Mapping[str, str | os.PathLike] | None = None,
              log: Callable[[str], None] = print) -> dict[str, Any]:
    """Runs (or reuses) every experiment of `plan` into `out/experiments`, then writes the
    report (`report.write_report`). `checkpoints` maps a pair to a pretrained checkpoint (or
    a list, one per pretraining seed) to use instead of the cached ones (tests). Returns
    `{"records": {key: record}, "seconds", "prepare_seconds": {pair: s}}`."""
    from safecdt_jax.paper.report import write_report

    out = Path(out)
    folder = out / "experiments"
    start = time.perf_counter()
    records: dict[str, Any] = {}
    prepare: dict[str, float] = {}
    for pair in plan.pairs:
        t0 = time.perf_counter()
        if checkpoints is not None and pair in checkpoints:
            given = checkpoints[pair]
            ckpt = ([Path(given)] if isinstance(given, str | os.PathLike)
                    else [Path(c) for c in given])
        else:
            log(f"{pair}: source data and {plan.pretrain_seeds} pretrained CDT(s) "
                f"({plan.preset} preset)")
            ckpt = process_zero_first(f"paper:prepare:{pair}",
                                      lambda pair=pair: prepare_checkpoints(pair, plan, progress))
        prepare[pair] = time.perf_counter() - t0
        ckpt_id = seeded_identity(ckpt, _recipe(pair, plan, checkpoints))
        for e in (x for x in experiments(plan) if x.pair == pair):
            record = run_experiment(e, plan, ckpt, folder, progress, log, ckpt_id)
            if record is not None:
                records[e.key] = record
    summary = {"records": records, "seconds": time.perf_counter() - start,
               "prepare_seconds": prepare}
    if is_writer():
        write_report(out, plan, summary)
    return summary
