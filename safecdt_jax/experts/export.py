"""An expert run's products on disk: learning curves (JSON, PNG) and the snapshot file that
the collector rolls out (`.npz`: stacked actor weights and normalisers, plus provenance)."""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from safecdt_jax import envs
from safecdt_jax.experts.config import ExpertConfig
from safecdt_jax.experts.networks import ObsNorm
from safecdt_jax.experts.run import ExpertRun
from safecdt_jax.io import atomic_path, write_text_atomic

SNAPSHOT_FORMAT = 1


def write_curves(path: str | os.PathLike, run: ExpertRun) -> Path:
    """Per-run learning curves as JSON (atomically): env steps per round and each curve."""
    steps_per_round = run.cfg.num_envs * run.cfg.horizon
    rounds = run.curves["return"].shape[1]
    record = {"task": run.cfg.task, "expert": run.cfg.to_json(),
              "env_steps": [steps_per_round * (i + 1) for i in range(rounds)],
              "runs": [{"label": label, "schedule": s.as_array().tolist(), "seed": seed,
                        **{k: v[i].tolist() for k, v in run.curves.items()}}
                       for i, (label, s, seed) in enumerate(zip(run.labels, run.schedules,
                                                                run.seeds, strict=True))]}
    return write_text_atomic(path, json.dumps(record, indent=1))


def write_tensorboard(folder: str | os.PathLike, run: ExpertRun) -> Path:
    """The learning curves as TensorBoard events, one folder per run (`folder/<label>`), each
    curve tagged `expert/<name>` against env steps. Returns `folder`."""
    from safecdt_jax.tensorboard import run_folder, write_scalars

    rounds = run.curves["return"].shape[1]
    steps = [run.cfg.num_envs * run.cfg.horizon * (i + 1) for i in range(rounds)]
    for i, label in enumerate(run.labels):
        write_scalars(Path(folder) / run_folder(label),
                      {f"expert/{k}": v[i] for k, v in run.curves.items()}, steps)
    return Path(folder)


def plot_curves(path: str | os.PathLike, run: ExpertRun) -> Path:
    """Return and cost against env steps, one line per run, each run's cost limit dashed."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    x = run.cfg.num_envs * run.cfg.horizon * (np.arange(run.curves["return"].shape[1]) + 1)
    fig = Figure(figsize=(10, 4))
    FigureCanvasAgg(fig)
    ax_r, ax_c = fig.subplots(1, 2)
    for i, label in enumerate(run.labels):
        line, = ax_r.plot(x, run.curves["return"][i], label=label)
        ax_c.plot(x, run.curves["cost"][i], color=line.get_color())
        limit = run.curves["cost_limit"][i]
        if limit.max() < 1e6:
            ax_c.plot(x, limit, "--", color=line.get_color(), lw=1)
    ax_r.set(xlabel="env steps", ylabel="episode return", title=f"{run.cfg.task} experts")
    ax_c.set(xlabel="env steps", ylabel="episode cost (dashed: limit)")
    ax_r.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100)
    return Path(path)


def select_rounds(rounds: int, keep: int) -> np.ndarray:
    """`keep` round indices evenly spaced over 0..rounds-1, the last round always included."""
    return np.unique(np.round(np.linspace(rounds - 1, 0, keep)[::-1]).astype(int)) \
        if keep < rounds else np.arange(rounds)


def write_snapshots(path: str | os.PathLike, run: ExpertRun, keep: int = 8) -> Path:
    """Writes `keep` snapshots per run (evenly spaced rounds) as one `.npz` (atomically):
    leaves stacked over snapshots, plus a JSON `meta` with the task, its physics version, the expert
    config, and per snapshot its run, cost schedule, seed, round and training-episode totals."""
    rounds = run.curves["return"].shape[1]
    pick = select_rounds(rounds, keep)
    runs = np.repeat(np.arange(len(run.seeds)), pick.size)
    rnds = np.tile(pick, len(run.seeds))
    snaps = jax.tree.map(lambda x: np.asarray(x)[runs, rnds], run.snapshots)
    meta = {"format": SNAPSHOT_FORMAT, "task": run.cfg.task,
            "physics_version": envs.physics_version(run.cfg.task), "expert": run.cfg.to_json(),
            "snapshots": [{"run": int(i), "schedule": run.schedules[i].as_array().tolist(),
                           "seed": run.seeds[i], "round": int(r),
                           "train_return": float(run.curves["return"][i, r]),
                           "train_cost": float(run.curves["cost"][i, r])}
                          for i, r in zip(runs, rnds, strict=True)]}
    return _write_snapshot_file(path, snaps, meta)


# ExpertConfig fields a snapshot's rollout reads (network shape, std floor, normaliser): the
# files merged into one must agree on them; training fields (limits, gains, steps) may differ.
ROLLOUT_FIELDS = ("task", "hidden", "min_std", "obs_var_floor", "obs_clip", "episode_len")


def _write_snapshot_file(path, snaps: dict, meta: dict) -> Path:
    leaves = jax.tree_util.tree_flatten_with_path(snaps)[0]
    arrays = {jax.tree_util.keystr(p): np.asarray(v, np.float32) for p, v in leaves}
    return _write_raw(path, meta, arrays)


def _write_raw(path, meta: dict, arrays: dict[str, np.ndarray]) -> Path:
    with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, meta=np.asarray(json.dumps(meta)), **arrays)
    return Path(path)


def _read_raw(path) -> tuple[dict, dict[str, np.ndarray]]:
    """(meta, arrays by leaf path) of a snapshot file; ValueError naming a file that is not one."""
    try:
        with np.load(path) as z:
            return json.loads(str(z["meta"])), {k: z[k] for k in z.files if k != "meta"}
    except (OSError, KeyError, ValueError) as e:
        raise ValueError(f"{os.fspath(path)} is not an expert snapshot file: {e}") from None


def merge_snapshots(out: str | os.PathLike, *files: str | os.PathLike) -> Path:
    """Writes the snapshots of `files`, in order, into one snapshot file `out` (atomically; `out`
    may be one of `files`). Each snapshot keeps its meta and gains `expert` (the config of
    the run that made it, where it differs from the first file's) and `run` renumbered so runs
    stay distinct. ValueError when the files disagree on the task, its physics version or a
    field the rollout reads (`ROLLOUT_FIELDS`)."""
    if not files:
        raise ValueError("merge_snapshots: no input files")
    loaded = [load_snapshots(f) for f in files]
    first = loaded[0][1]
    for f, (_, meta) in zip(files, loaded, strict=True):
        bad = [k for k in ROLLOUT_FIELDS if meta["expert"][k] != first["expert"][k]]
        if meta["physics_version"] != first["physics_version"]:
            bad.append("physics_version")
        if bad:
            raise ValueError(f"merge_snapshots: {os.fspath(f)} differs from "
                             f"{os.fspath(files[0])} in {', '.join(bad)}")
    entries, offset = [], 0
    for _, meta in loaded:
        for snap in meta["snapshots"]:
            config = snap.get("expert", meta["expert"])
            extra = {} if config == first["expert"] else {"expert": config}
            entries.append(snap | extra | {"run": snap["run"] + offset})
        offset += 1 + max(s["run"] for s in meta["snapshots"])
    snaps = jax.tree.map(lambda *xs: np.concatenate(xs), *(s for s, _ in loaded))
    return _write_snapshot_file(out, snaps, first | {"snapshots": entries})


def select_runs(out: str | os.PathLike, path: str | os.PathLike, runs: Sequence[int]) -> Path:
    """Writes the snapshots of `runs` of snapshot file `path`, runs in the order given and
    renumbered 0, 1, ..., into `out` (atomically; `out` may be `path`): how a run that failed
    (a collapsed seed) is left out before `merge_snapshots` joins a retrained one. ValueError
    naming a run the file lacks."""
    snaps, meta = load_snapshots(path)
    have = sorted({s["run"] for s in meta["snapshots"]})
    missing = [r for r in runs if r not in have]
    if missing or not runs:
        raise ValueError(f"select_runs: {os.fspath(path)} has runs {have}, not {missing or runs}")
    index = [i for r in runs for i, s in enumerate(meta["snapshots"]) if s["run"] == r]
    entries = [meta["snapshots"][i] | {"run": runs.index(meta["snapshots"][i]["run"])}
               for i in index]
    picked = jax.tree.map(lambda x: np.asarray(x)[np.asarray(index)], snaps)
    return _write_snapshot_file(out, picked, meta | {"snapshots": entries})


def retarget_physics(out: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Writes the snapshots of `path` into `out` (atomically; `out` may be `path`) labelled with
    the task's current physics version, the version they were trained under kept as
    `trained_physics_version`: how experts trained on an older physics become behaviour
    policies for data collected on the current one (the collector refuses a file labelled
    with another version). The policies' weights are unchanged."""
    meta, arrays = _read_raw(path)
    meta["trained_physics_version"] = meta.get("trained_physics_version",
                                               meta["physics_version"])
    meta["physics_version"] = envs.physics_version(meta["task"])
    return _write_raw(out, meta, arrays)


def load_snapshots(path: str | os.PathLike) -> tuple[dict[str, Any], dict]:
    """(snapshots, meta) from `write_snapshots`' file: snapshots {'actor', 'norm': ObsNorm} with
    leaves [n_snapshots, ...]. ValueError naming the file if it is not such a file."""
    meta, arrays = _read_raw(path)
    if meta.get("format") != SNAPSHOT_FORMAT:
        raise ValueError(f"{os.fspath(path)}: snapshot format {meta.get('format')!r}, this "
                         f"code reads {SNAPSHOT_FORMAT}")
    cfg = ExpertConfig.from_json(meta["expert"])
    obs_dim = envs.make(cfg.task)[0].observation_size
    template = jax.eval_shape(lambda: {"actor": _actor_template(cfg, obs_dim),
                                       "norm": ObsNorm.create(obs_dim)})
    paths_ = jax.tree_util.tree_flatten_with_path(template)
    leaves = [arrays[jax.tree_util.keystr(p)] for p, _ in paths_[0]]
    return jax.tree.unflatten(paths_[1], leaves), meta


def _actor_template(cfg: ExpertConfig, obs_dim: int):
    from safecdt_jax.experts.networks import init_networks

    return init_networks(jax.random.PRNGKey(0), obs_dim, 2, cfg.hidden, cfg.init_std)["actor"]


__all__ = ["ROLLOUT_FIELDS", "load_snapshots", "merge_snapshots", "plot_curves",
           "retarget_physics", "select_rounds", "select_runs", "write_curves", "write_snapshots"]
