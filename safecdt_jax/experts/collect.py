"""Source data from expert snapshots, as DSRL makes it: roll every snapshot out stochastically,
then grid-filter the episodes in (cost, return) space to DSRL's count and cost cap.

    data = expert_dataset(key, "CarGoal1")          # the committed snapshots of the task
    write_collected(path, data)                     # DSRL-format HDF5, provenance in attrs

DSRL kept every trajectory its experts met while training under an annealed cost limit; here the
training episodes are not stored (12M transitions would not fit), so each kept snapshot (the
actor after a training round, with its observation normaliser) is rolled out again with its own
exploration noise, which is what the training saw at that point.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safecdt_jax import envs
from safecdt_jax.data.collect import (
    DEFAULT_CHUNK,
    env_params_attrs,
    full_length_dataset,
    run_episodes,
)
from safecdt_jax.data.dataset import Attrs, Dataset, select_episodes
from safecdt_jax.data.relabel import RelabelConfig
from safecdt_jax.data.relabel import grid_filter as relabel_grid_filter
from safecdt_jax.experts.config import ExpertConfig
from safecdt_jax.experts.export import load_snapshots
from safecdt_jax.experts.ppo_lag import make_train
from safecdt_jax.paths import DEFAULT_ACTIONS

SNAPSHOT_DIR = Path(__file__).parent / "snapshots"
# 2: executed actions, unless the 'actions' attribute says otherwise; 3: each episode carries
# its policy's mean return and cost over all of the policy's rollouts, before the filter;
# 4: the careful floor (`CAREFUL_FLOOR`) after the grid filter.
EXPERT_COLLECTOR_VERSION = 4

# How an episode's actions are recorded: 'sampled' (the default, `paths.DEFAULT_ACTIONS`: the
# policy's Gaussian sample clipped to the action box [-1, 1], DSRL's convention) or 'executed'
# (`Robot.executed_action`: the Car's wheel torques clipped to +-0.02). Both step the env
# identically; they differ in what a clone's action executes (docs/EXPERTS.md "Actions"). The
# Point's actions are the same under both.
ACTION_RECORDINGS = ("executed", "sampled")


def _check_actions(actions: str) -> None:
    if actions not in ACTION_RECORDINGS:
        raise ValueError(f"unknown action recording {actions!r}; choose one of "
                         f"{', '.join(ACTION_RECORDINGS)}")


class DsrlSize(NamedTuple):
    """A DSRL source data set's size: episodes kept and the cost cap of its grid filter."""

    episodes: int
    max_cost: float


class CarefulFloor(NamedTuple):
    """The least share of the kept episodes that come from careful policies: those whose mean
    episode cost (over all their rollouts, `policy_cost`) is at most `max_policy_cost`."""

    max_policy_cost: float
    share: float


# Why a floor: the grid filter balances episode outcomes, not behaviour policies. A careful
# policy's episodes pile into the few cells at cost ~0, where the per-cell cap drops most of
# them, so the careful experts of CarGoal1 / CarCircle1 supplied 8.4% / 1.8% of the episodes
# (physics 6), too few for a clone to learn what a low cost token asks for.
CAREFUL_FLOOR = CarefulFloor(max_policy_cost=5.0, share=0.10)

# Tasks whose data take another floor than `CAREFUL_FLOOR`. CarCircle1: none. Its careful
# policies are not careful in CarCircle2 (physics 7's limit-5 expert pays 150.6 there with mean
# actions, its limit-20 one 145.7), and the floor's episodes made the CC1-CC2 deployments run
# over the budget more often with either expert file: physics 7's (Safe-CDT VR 67.8 -> 91.3%,
# 3 checkpoints x 3 seeds) and the physics-6 one used now (zero-shot 73 -> 92% on physics 6;
# docs/research/cdt-findings.md sections 25 and 27).
CAREFUL_FLOORS = {"CarCircle1": CarefulFloor(max_policy_cost=5.0, share=0.0)}


def floor_for(task: str) -> CarefulFloor:
    """The careful floor `expert_dataset` applies to `task`'s data (`CAREFUL_FLOORS`, else
    `CAREFUL_FLOOR`)."""
    return CAREFUL_FLOORS.get(task, CAREFUL_FLOOR)

# DSRL's source data sets (file names `{task}-{max cost}-{trajectories}.hdf5`).
DSRL_SIZES = {
    "CarGoal1": DsrlSize(1671, 120.0),
    "CarCircle1": DsrlSize(1271, 250.0),
    "PointCircle1": DsrlSize(1098, 200.0),
    "PointGoal1": DsrlSize(2022, 100.0),
}


def snapshot_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a snapshot file (hex): the data's provenance, and what a cache check compares."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def snapshot_path(task: str) -> Path:
    """The committed snapshot file of `task` (ValueError if the task has none)."""
    path = SNAPSHOT_DIR / f"{task}.npz"
    if not path.is_file():
        have = sorted(p.stem for p in SNAPSHOT_DIR.glob("*.npz"))
        raise ValueError(f"no expert snapshots for {task!r} (have: {', '.join(have) or 'none'})")
    return path


@functools.cache
def _rollout_fn(cfg: ExpertConfig, horizon: int, actions: str = DEFAULT_ACTIONS) -> Callable:
    """jit(vmap(episode)): (keys [c], snapshots {leaves [c, ...]}) -> (obs, final obs, actions
    as `actions` says ('executed': `Robot.executed_action`, the Car's torques clipped to
    +-0.02; 'sampled': the Gaussian sample clipped to [-1, 1]), rewards, costs), every episode
    `horizon` steps of the snapshot's stochastic policy."""
    env, params = envs.make(cfg.task)
    policy = make_train(cfg).policy

    def episode(key: jax.Array, snapshot: dict):
        k_reset, k_steps = jax.random.split(key)

        def step(state, k):
            # A Gaussian expert's sampled Car torques saturate (|a| > 0.02) almost always:
            # executed, their average is the expert's mean command; sampled, a clone's mean is
            # the policy mean, which executes as a saturated (bang-bang) command.
            action = jnp.clip(policy(snapshot, state.obs, k), -1, 1)
            if actions == "executed":
                action = env.robot.executed_action(action)
            nxt = env.step(state, action, params)
            return nxt, (state.obs, action, nxt.reward, nxt.cost)

        final, (obs, recorded, rewards, costs) = jax.lax.scan(
            step, env.reset(k_reset, params), jax.random.split(k_steps, horizon))
        return obs, final.obs, recorded, rewards, costs

    return jax.jit(jax.vmap(episode))


def rollout_snapshots(key: jax.Array, path: str | os.PathLike, per_snapshot: int,
                      horizon: int | None = None, chunk: int = DEFAULT_CHUNK,
                      progress: Callable[[int], None] | None = None,
                      actions: str = DEFAULT_ACTIONS) -> Dataset:
    """`per_snapshot` stochastic episodes of every snapshot in file `path`, as a `Dataset`,
    actions recorded as `actions` says (`ACTION_RECORDINGS`; attrs 'actions').

    episode_info: 'snapshot' (index in the file), 'run', 'round', and 'policy_return' /
    'policy_cost': the mean episode return and cost of that snapshot over all its episodes
    here (raw units), its expected outcome, kept with each episode so that a filter that drops
    some episodes (the grid filter keeps few of a careful policy's many near-zero-cost ones)
    does not change what its episodes are labelled with (`policy_mean_labels`). attrs: task,
    env params, physics version, the expert config, the snapshot file's name and SHA-256, and
    per snapshot its schedule, seed and round (`snapshots`). Episodes run `horizon` steps
    (default: the episode length the experts trained on, the task's time limit unless
    shortened).
    ValueError when the file's physics version is not the current one.
    """
    snaps, meta = load_snapshots(path)
    version = envs.physics_version(meta["task"])
    if meta["physics_version"] != version:
        raise ValueError(f"{os.fspath(path)} was trained under physics version "
                         f"{meta['physics_version']}, {meta['task']} is at {version}: "
                         f"retrain the experts (safecdt-jax expert)")
    if per_snapshot < 1:
        raise ValueError(f"per_snapshot must be >= 1, got {per_snapshot}")
    _check_actions(actions)
    cfg = ExpertConfig.from_json(meta["expert"])
    env = envs.make(cfg.task)[0]
    t = cfg.horizon if horizon is None else int(horizon)
    n_snap = len(meta["snapshots"])
    which = np.repeat(np.arange(n_snap), per_snapshot)
    inputs = jax.tree.map(lambda x: x[which], snaps)
    keys = jax.random.split(key, which.size)
    arrays = run_episodes(_rollout_fn(cfg, t, actions), keys, inputs, env.observation_size,
                          env.action_size, chunk, progress)
    totals = {k: np.asarray(arrays[k], np.float64).sum(axis=1) for k in ("rewards", "costs")}
    means = {k: np.bincount(which, v) / per_snapshot for k, v in totals.items()}
    info = {"snapshot": which.astype(np.float32),
            "policy_return": means["rewards"][which].astype(np.float32),
            "policy_cost": means["costs"][which].astype(np.float32),
            "run": np.asarray([meta["snapshots"][i]["run"] for i in which], np.float32),
            "round": np.asarray([meta["snapshots"][i]["round"] for i in which], np.float32)}
    attrs = {"task": cfg.task, "env_params": env_params_attrs(cfg.task),
             "physics_version": envs.physics_version(cfg.task), "behaviour": "expert",
             "expert_collector_version": EXPERT_COLLECTOR_VERSION, "expert": meta["expert"],
             "snapshot_file": Path(path).name,
             "snapshot_sha256": snapshot_sha256(path),
             "snapshots": meta["snapshots"], "per_snapshot": per_snapshot, "horizon": t,
             "actions": actions}
    return full_length_dataset(arrays, info, attrs)


def grid_filter(rng: np.random.Generator, costs, returns, max_cost: float, cost_bins: int,
                reward_bins: int, per_bin: int) -> np.ndarray:
    """Sorted indices kept by DSRL's grid filter: episodes with cost <= `max_cost`, binned on a
    `cost_bins` x `reward_bins` grid over their (cost, return) range, at most `per_bin` per
    bin (a fuller bin keeps a random subset)."""
    costs, returns = np.asarray(costs, np.float64), np.asarray(returns, np.float64)
    ok = np.flatnonzero(costs <= max_cost)
    if ok.size == 0:
        return ok
    # OSRL's outlier grid over the capped episodes, with no minimum per cell.
    grid = RelabelConfig(cost_bins=cost_bins, reward_bins=reward_bins, max_per_bin=per_bin,
                         min_per_bin=1)
    return ok[relabel_grid_filter(rng, costs[ok], returns[ok], grid)]


def filter_to_size(rng: np.random.Generator, costs, returns, size: DsrlSize,
                   cost_bins: int = 60, reward_bins: int = 50) -> tuple[np.ndarray, int]:
    """(indices, per_bin): DSRL's grid filter (cbins 60, rbins 50) at the largest per-bin cap
    that keeps at most `size.episodes` episodes at cost <= `size.max_cost` (all of them if
    fewer qualify; a random subset of the cells' picks if even a cap of 1 keeps more)."""
    lo, hi = 1, max(1, len(costs))
    while lo < hi:  # largest cap whose kept count is <= the target
        mid = (lo + hi + 1) // 2
        n = grid_filter(np.random.default_rng(0), costs, returns, size.max_cost, cost_bins,
                        reward_bins, mid).size
        lo, hi = (mid, hi) if n <= size.episodes else (lo, mid - 1)
    kept = grid_filter(rng, costs, returns, size.max_cost, cost_bins, reward_bins, lo)
    if kept.size > size.episodes:  # even one per cell is too many: a random subset of them
        kept = np.sort(rng.choice(kept, size.episodes, replace=False))
    return kept, lo


def careful_floor(rng: np.random.Generator, kept, costs, policy_costs, policy_returns,
                  max_cost: float, floor: CarefulFloor = CAREFUL_FLOOR) -> np.ndarray:
    """Sorted indices: `kept` with episodes of careful policies (policy-mean cost <=
    `floor.max_policy_cost`, episode cost <= `max_cost`) swapped in until they are at least
    `floor.share` of the kept count (or every careful episode is in), the count unchanged.
    Swapped in: the most competent careful policies first (highest policy-mean return, its
    episodes in random order); swapped out: random non-careful episodes."""
    kept = np.asarray(kept, np.int64)
    careful = (np.asarray(policy_costs) <= floor.max_policy_cost) & (np.asarray(costs) <= max_cost)
    need = int(np.ceil(floor.share * kept.size)) - int(careful[kept].sum())
    pool = np.setdiff1d(np.flatnonzero(careful), kept)
    if need <= 0 or pool.size == 0:
        return kept
    order = np.lexsort((rng.permutation(pool.size), -np.asarray(policy_returns)[pool]))
    add = pool[order[:need]]
    others = kept[~careful[kept]]
    drop = rng.choice(others, min(add.size, others.size), replace=False)
    return np.sort(np.concatenate([np.setdiff1d(kept, drop), add[:drop.size]]))


def _per_snapshot(n_snap: int, size: DsrlSize) -> int:
    """Episodes per snapshot (of `n_snap`) for twice the target count before filtering."""
    return max(1, -(-2 * size.episodes // n_snap))


def target_size(task: str, episodes: int | None = None) -> DsrlSize:
    """DSRL's size of `task`'s source data, with `episodes` instead of its count if given."""
    size = DSRL_SIZES.get(task) or DsrlSize(1000, 120.0)
    return size if episodes is None else size._replace(episodes=int(episodes))


def planned_episodes(task: str, episodes: int | None = None) -> int:
    """How many episodes `expert_dataset` rolls out (before filtering) for this target size."""
    n_snap = len(load_snapshots(snapshot_path(task))[1]["snapshots"])
    return _per_snapshot(n_snap, target_size(task, episodes)) * n_snap


def expert_dataset(key: jax.Array, task: str, per_snapshot: int | None = None,
                   size: DsrlSize | None = None, snapshots: str | os.PathLike | None = None,
                   horizon: int | None = None, progress: Callable[[int], None] | None = None,
                   seed: int | None = None, actions: str = DEFAULT_ACTIONS) -> Dataset:
    """The source data of `task` from its expert snapshots (default: the committed file),
    grid-filtered to DSRL's size (default `DSRL_SIZES[task]`), then careful policies' episodes
    swapped in up to the task's floor (`floor_for`, `careful_floor`), actions recorded as
    `actions` says (`ACTION_RECORDINGS`).

    `per_snapshot` episodes per snapshot (default: enough for twice the target count). attrs
    add the filter's settings ('grid_filter': cbins, rbins, per-bin cap, max cost, episodes
    before and after; 'careful_floor': the floor and how many episodes it swapped in) to
    `rollout_snapshots`' provenance, and `seed` (the seed of `key`) if given, which
    `ensure_source_data` checks.
    """
    from safecdt_jax.data.windows import episode_costs, episode_returns

    path = snapshot_path(task) if snapshots is None else Path(snapshots)
    size = size or target_size(task)
    per_snapshot = per_snapshot or _per_snapshot(
        len(load_snapshots(path)[1]["snapshots"]), size)
    k_roll, k_filter = jax.random.split(key)
    raw = rollout_snapshots(k_roll, path, per_snapshot, horizon=horizon, progress=progress,
                            actions=actions)
    costs, returns = episode_costs(raw), episode_returns(raw)
    rng = np.random.default_rng(np.asarray(jax.random.bits(k_filter, (2,)), np.uint64))
    gridded, per_bin = filter_to_size(rng, costs, returns, size)
    floor = floor_for(task)
    kept = careful_floor(rng, gridded, costs, raw.episode_info["policy_cost"],
                         raw.episode_info["policy_return"], size.max_cost, floor)
    data = select_episodes(raw, kept)
    attrs = dict(data.attrs) | {
        "episodes": int(kept.size),
        "grid_filter": {"cost_bins": 60, "reward_bins": 50, "per_bin": per_bin,
                        "max_cost": size.max_cost, "target": size.episodes,
                        "episodes_before": int(costs.size), "episodes_after": int(kept.size)},
        "careful_floor": {**floor._asdict(),
                          "swapped_in": int(np.setdiff1d(kept, gridded).size)}}
    if seed is not None:
        attrs["seed"] = int(seed)
    return dataclasses.replace(data, attrs=Attrs(attrs))


def recipe_fields(attrs: Mapping[str, Any]) -> dict[str, Any] | None:
    """The inputs an expert data set was collected from, as plain values: task, the snapshot
    file's SHA-256, collector and physics versions, seed, the filter's max cost and target count,
    and the action recording (files without it are 'executed'), and the careful floor where it
    is not `CAREFUL_FLOOR`. None for data that `expert_dataset` did not collect with a seed (raw
    rollouts, other behaviours)."""
    grid = attrs.get("grid_filter")
    if attrs.get("behaviour") != "expert" or "seed" not in attrs or grid is None:
        return None
    grid = json.loads(grid) if isinstance(grid, str) else grid
    fields = {"task": str(attrs["task"]), "snapshot_sha256": str(attrs["snapshot_sha256"]),
              "collector": int(attrs["expert_collector_version"]),
              "physics": int(attrs["physics_version"]), "seed": int(attrs["seed"]),
              "max_cost": float(grid["max_cost"]), "target": int(grid["target"]),
              "actions": str(attrs.get("actions", "executed"))}
    floor = attrs.get("careful_floor")
    floor = json.loads(floor) if isinstance(floor, str) else floor
    if floor is not None:
        floor = CarefulFloor(float(floor["max_policy_cost"]), float(floor["share"]))
    return fields | _floor_field(floor)


def _floor_field(floor: CarefulFloor | None) -> dict[str, Any]:
    """The recipe's floor entry: none for `CAREFUL_FLOOR`, which collector version 4 implies
    (so the recipes, and the records keyed on them, made before floors became per task still
    hold), else `careful_floor: [max policy cost, share]`."""
    if floor is None or floor == CAREFUL_FLOOR:
        return {}
    return {"careful_floor": [floor.max_policy_cost, floor.share]}


def data_recipe(attrs: Mapping[str, Any]) -> str | None:
    """A digest of `recipe_fields` ('recipe-' and 32 hex digits), or None where they are None.

    Equal recipes give the same episodes on the same kind of CPU, and episodes that differ only
    in float rounding on another kind (XLA's CPU kernels round differently, and the rollouts
    amplify it): what keys finished experiments across machines (`paper.run`)."""
    fields = recipe_fields(attrs)
    if fields is None:
        return None
    text = json.dumps(fields, sort_keys=True).encode()
    return "recipe-" + hashlib.blake2b(text, digest_size=16).hexdigest()


def is_current(path: str | os.PathLike, task: str, size: DsrlSize, seed: int,
               actions: str = DEFAULT_ACTIONS) -> bool:
    """Whether `path` holds expert data of `task` from the committed snapshots (same SHA-256),
    this collector and physics version, `seed`, the filter's target size and the action
    recording and the task's careful floor (`recipe_fields`)."""
    from safecdt_jax.data.collect import file_attrs

    attrs = file_attrs(path)
    want = {"task": task, "snapshot_sha256": snapshot_sha256(snapshot_path(task)),
            "collector": EXPERT_COLLECTOR_VERSION, "physics": envs.physics_version(task),
            "seed": seed, "max_cost": float(size.max_cost), "target": size.episodes,
            "actions": actions} | _floor_field(floor_for(task))
    return attrs is not None and recipe_fields(attrs) == want


def ensure_source_data(task: str, episodes: int | None = None, seed: int = 0,
                       path: str | os.PathLike | None = None,
                       progress: Callable[[int], None] | None = None,
                       actions: str = DEFAULT_ACTIONS) -> Path:
    """The path of a current source data set of `task` (default `paths.dataset_path(task,
    actions)`), collected there first unless the file is current: the task's committed expert
    snapshots rolled out with `PRNGKey(seed)` and grid-filtered to DSRL's size (`episodes`
    overrides its count), actions recorded as `actions` says (`ACTION_RECORDINGS`). ValueError
    for an unknown task, a task without snapshots or an unwritable path."""
    from safecdt_jax import paths
    from safecdt_jax.data.collect import check_writable, write_collected

    snapshot_path(task)  # validates the task before touching the disk
    _check_actions(actions)
    size = target_size(task, episodes)
    path = Path(paths.dataset_path(task, actions) if path is None else path).expanduser()
    if is_current(path, task, size, seed, actions):
        return path
    path = check_writable(path)
    data = expert_dataset(jax.random.PRNGKey(seed), task, size=size, progress=progress,
                          seed=seed, actions=actions)
    return write_collected(path, data)


__all__ = [
    "ACTION_RECORDINGS",
    "CAREFUL_FLOOR",
    "CAREFUL_FLOORS",
    "DSRL_SIZES",
    "EXPERT_COLLECTOR_VERSION",
    "SNAPSHOT_DIR",
    "CarefulFloor",
    "DsrlSize",
    "careful_floor",
    "data_recipe",
    "ensure_source_data",
    "expert_dataset",
    "filter_to_size",
    "floor_for",
    "grid_filter",
    "is_current",
    "planned_episodes",
    "recipe_fields",
    "rollout_snapshots",
    "snapshot_path",
    "target_size",
]
