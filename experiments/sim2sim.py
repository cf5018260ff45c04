"""Sim-to-sim: our MJX envs against native Safety-Gymnasium 1.0.0, sensor by sensor and policy by
policy.

    python -m experiments.sim2sim [--tasks CarGoal1,PointGoal1,CarCircle1,PointCircle1]
        [--episodes 4] [--policy-episodes 64] [--parts sensors,...,transfer]
        [--out experiments/results/sim2sim.json]

1. Sensors: per observation dimension of the robot's sensors, the mean and std of ours and of
   Safety-Gymnasium's under uniform random actions (`episodes` x 500 steps each side), their std
   ratio and the 1-Wasserstein distance between the two marginals (in the dimension's units);
   and under one open-loop script from rest (`SCRIPT`), the readings at a few steps.
2. Turning (Car only): under open-loop action scripts from rest (constant, and i.i.d. switching
   between straight (1, 1) and spin (1, -1) with probability p of straight, the regime a trained
   Car expert drives in, its torques being saturated), the mean forward speed (-velocimeter y,
   m/s) and yaw rate (gyro z, rad/s) over steps 100-500, ours against theirs; and (CarGoal)
   each ground contact's force, normal load and speed under held actions, ours
   (`CarRobot.contact_forces`) against native MuJoCo's `mj_contactForce`, and the top speed,
   acceleration and spin rate under each dynamics shift (`SHIFTS`) against native MuJoCo's
   model scaled the same way.
3. Transfer: the last snapshot of each task's cost-limit-25 (Circle: 20) expert from the committed
   snapshot files, `policy_episodes` episodes deterministic and stochastic in each simulator:
   return, cost (mean and median: a Circle expert's rare escapes from the circle cost 250-280
   each, so the mean of 32 episodes swings with one or two of them) and goals, and the ratio
   theirs / ours with a 95% bootstrap interval (the two samples resampled independently). The
   Point robot, whose sensors agree with Safety-Gymnasium's to three decimals, is the control:
   its intervals show how far the ratios move when the physics is the same.
Needs the peer venv (`python -m benchmarks.peers.setup`); writes a JSON and a markdown table.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json
from safecdt_jax.io import atomic_path
from safecdt_jax.stats import ratio_interval

ROOT = Path(__file__).resolve().parents[1]
NATIVE = ROOT / "benchmarks" / "peers" / "native.py"
SCRIPT = [(1.0, 1.0)] * 50 + [(1.0, -1.0)] * 30 + [(-1.0, -1.0)] * 30 + [(0.3, 0.8)] * 40
SCRIPT_STEPS = (0, 20, 49, 65, 79, 110, 139)
SENSOR_NAMES = {
    "Point": [f"{s}_{a}" for s in ("acc", "vel", "gyro", "mag") for a in "xyz"],
    "Car": [f"{s}_{a}" for s in ("acc", "vel", "gyro", "mag", "ballangvel") for a in "xyz"]
    + [f"ballquat_{i}{j}" for i in range(3) for j in range(3)],
}
LIMIT = {"Goal": 25.0, "Circle": 20.0}
TERMS = ("cost_hazards", "cost_vases_contact", "cost_vases_velocity", "cost_out_of_boundary")
PARTS = ("sensors", "script", "turning", "contacts", "shifts", "layouts", "transfer")


def native(request: dict) -> dict[str, np.ndarray]:
    """Runs one request of `benchmarks/peers/native.py` in the peer venv; its arrays.

    Results are cached under `.peers/cache/`, keyed by the request, the contents of its
    `weights` file and native.py itself (the native side is deterministic given its seed, and
    a 128-episode CarGoal2 run takes minutes)."""
    from benchmarks.peers.setup import ROOT as PEERS
    from benchmarks.peers.setup import venv_python

    python = venv_python("safety-gymnasium")
    if not python.exists():
        raise SystemExit("no peer venv: run `python -m benchmarks.peers.setup` first")
    key = {k: v for k, v in request.items() if k != "weights"}  # its path is a temp folder
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode() + NATIVE.read_bytes())
    if request.get("weights"):
        digest.update(Path(request["weights"]).read_bytes())
    cached = PEERS / "cache" / f"{request['cmd']}-{digest.hexdigest()[:20]}.npz"
    if cached.exists():
        with np.load(cached) as z:
            return dict(z)
    out = _run_native(python, request)
    cached.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(cached) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **out)
    return out


def _run_native(python: Path, request: dict) -> dict[str, np.ndarray]:
    with tempfile.TemporaryDirectory() as tmp:
        req, out = Path(tmp) / "request.json", Path(tmp) / "out.npz"
        req.write_text(json.dumps(request))
        proc = subprocess.run([str(python), str(NATIVE), str(req), str(out)],
                              capture_output=True, text=True)
        if proc.returncode:
            raise RuntimeError(f"native {request['cmd']} failed:\n{proc.stderr[-3000:]}")
        with np.load(out) as z:
            return dict(z)


def ours_trace(task: str, episodes: int, steps: int, seed: int, actions=None) -> np.ndarray:
    """Our observations after each step [episodes, steps, obs_dim], random or scripted actions."""
    import jax
    import jax.numpy as jnp

    keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    if actions is None:
        return np.asarray(_trace_program(task, steps, False)(keys, jnp.zeros((steps, 2))))
    return np.asarray(_trace_program(task, steps, True)(keys, jnp.asarray(actions, jnp.float32)))


@functools.cache
def _trace_program(task: str, steps: int, scripted: bool):
    """Jitted `(keys, script) -> observations`; the script is an argument, so every script of
    a task runs one compiled program."""
    import jax

    from safecdt_jax import envs
    from safecdt_jax.envs.rollout import scan_episode, uniform_policy

    env, params = envs.make(task)

    def run(keys, script):
        def policy(key, state):
            return script[state.info["steps"]] if scripted else uniform_policy(key, state)

        def episode(key):
            return scan_episode(env, params, key, policy, lambda s: s.obs, steps)[1]

        return jax.vmap(episode)(keys)

    return jax.jit(run)


def wasserstein1(a: np.ndarray, b: np.ndarray) -> float:
    """1-Wasserstein distance between two 1-D samples (quantile matching on 200 quantiles)."""
    q = np.linspace(0.0025, 0.9975, 200)
    return float(np.mean(np.abs(np.quantile(a, q) - np.quantile(b, q))))


def sensor_stats(task: str, episodes: int, seed: int = 0) -> list[dict]:
    """Per sensor dimension: mean/std ours and theirs under random actions, std ratio, W1."""
    robot = "Car" if task.startswith("Car") else "Point"
    names = SENSOR_NAMES[robot]
    ours = ours_trace(task, episodes, 500, seed)[..., :len(names)].reshape(-1, len(names))
    theirs = native({"cmd": "trace", "task": task, "episodes": episodes, "steps": 500,
                     "seed": seed, "actions": None})["obs"][..., :len(names)]
    theirs = theirs.reshape(-1, len(names))
    rows = []
    for i, name in enumerate(names):
        so, st = float(ours[:, i].std()), float(theirs[:, i].std())
        rows.append({"dim": i, "name": name, "ours_mean": float(ours[:, i].mean()),
                     "ours_std": so, "theirs_mean": float(theirs[:, i].mean()), "theirs_std": st,
                     "std_ratio": so / st if st > 0 else (1.0 if so == 0 else float("inf")),
                     "w1": wasserstein1(ours[:, i], theirs[:, i])})
    return rows


def script_readings(task: str) -> dict:
    """Sensor readings of both simulators at `SCRIPT_STEPS` of the open-loop script from rest."""
    robot = "Car" if task.startswith("Car") else "Point"
    n = len(SENSOR_NAMES[robot])
    ours = ours_trace(task, 1, len(SCRIPT), 0, SCRIPT)[0, :, :n]
    theirs = native({"cmd": "trace", "task": task, "episodes": 1, "steps": len(SCRIPT),
                     "seed": 0, "actions": SCRIPT})["obs"][0, :, :n]
    return {"steps": list(SCRIPT_STEPS), "ours": ours[list(SCRIPT_STEPS)].tolist(),
            "theirs": theirs[list(SCRIPT_STEPS)].tolist()}


# Open-loop turning scripts: (name, probability of straight (1, 1) against spin (1, -1) per step),
# or (name, constant action).
TURNS = [("straight (1, 1)", (1.0, 1.0)), ("spin (1, -1)", (1.0, -1.0)),
         ("one wheel (1, 0)", (1.0, 0.0)), ("(1, 0.01)", (1.0, 0.01)),
         ("(1, -0.01)", (1.0, -0.01)), ("switching, p = 0.3", 0.3), ("switching, p = 0.5", 0.5),
         ("switching, p = 0.7", 0.7), ("switching, p = 0.9", 0.9)]


def turn_scripts(steps: int = 500, seed: int = 0) -> list[tuple[str, np.ndarray]]:
    """Each `TURNS` script as actions [steps, 2]: a held action, or straight (1, 1) with the
    row's probability and spin (1, -1) otherwise, drawn step by step from one generator."""
    rng = np.random.default_rng(seed)
    out = []
    for name, spec in TURNS:
        if isinstance(spec, float):
            straight = rng.uniform(size=steps) < spec
            acts = np.where(straight[:, None], [[1.0, 1.0]], [[1.0, -1.0]])
        else:
            acts = np.tile([spec], (steps, 1))
        out.append((name, acts))
    return out


def turning(task: str, episodes: int = 4, steps: int = 500, seed: int = 0) -> list[dict]:
    """Mean forward speed (m/s) and yaw rate (rad/s) over steps 100..`steps` per `TURNS` script,
    ours and Safety-Gymnasium's (Car tasks: velocimeter y is dim 4, gyro z dim 8)."""
    rows = []
    for name, acts in turn_scripts(steps, seed):
        script = acts.tolist()
        ours = ours_trace(task, episodes, steps, seed, script)[:, 100:]
        theirs = native({"cmd": "trace", "task": task, "episodes": episodes, "steps": steps,
                         "seed": seed, "actions": script})["obs"][:, 100:]
        row = {"script": name}
        for side, x in (("ours", ours), ("theirs", theirs)):
            row[f"{side}_speed"] = float(-x[..., 4].mean())
            row[f"{side}_yaw_rate"] = float(x[..., 8].mean())
        rows.append(row)
    return rows


# Held actions for the contact table: the calibration points, the turning regime, and drives
# below the torque limit (the wheels' rolling, unsaturated regime).
CONTACT_SCRIPTS = [("straight (1, 1)", (1.0, 1.0)), ("backward (-1, -1)", (-1.0, -1.0)),
                   ("spin (1, -1)", (1.0, -1.0)), ("one wheel (1, 0)", (1.0, 0.0)),
                   ("(1, 0.01)", (1.0, 0.01)), ("(0.01, 0.01)", (0.01, 0.01)),
                   ("(0.005, 0.005)", (0.005, 0.005))]
CONTACTS = ("left wheel", "right wheel", "caster")


@functools.cache
def _contact_program(task: str, steps: int, start: int):
    """Jitted `(key, action) -> (forces [3, 2], normals [3], velocities [3, 2])`: our contact
    forces (`CarRobot.contact_forces`) and contact-point velocities, chassis frame, averaged
    over steps `start`..`steps` of a held action from rest."""
    import jax
    import jax.numpy as jnp

    from safecdt_jax import envs
    env, params = envs.make(task)
    robot = env.robot
    loads = jnp.asarray(robot._loads(), jnp.float32)

    def run(key, action):
        torque = params.gear_scale * robot.executed_action(action)

        def body(state, _):
            state = env.step(state, action, params)
            forces, normal = robot.contact_forces(state.data, torque, params, loads)
            return state, (forces, normal, robot.contact_velocities(state.data))

        _, (f, n, v) = jax.lax.scan(body, env.reset(key, params), None, steps)
        return f[start:].mean(0), n[start:].mean(0), v[start:].mean(0)

    return jax.jit(run)


def contact_table(task: str = "CarGoal1", steps: int = 300, start: int = 150,
                  seed: int = 0) -> list[dict]:
    """Per `CONTACT_SCRIPTS` action and contact: mean longitudinal and lateral ground force on
    the car (N, chassis frame; longitudinal positive forward), normal load (N) and the contact
    point's forward speed (m/s), ours against native MuJoCo's (`mj_contactForce`)."""
    import jax

    theirs = native({"cmd": "contacts", "task": task, "steps": steps, "start": start,
                     "seed": seed, "actions": [list(a) for _, a in CONTACT_SCRIPTS]})
    program = _contact_program(task, steps, start)
    rows = []
    for i, (name, action) in enumerate(CONTACT_SCRIPTS):
        f, n, v = (np.asarray(x) for x in program(jax.random.PRNGKey(seed), np.asarray(
            action, np.float32)))
        for k, contact in enumerate(CONTACTS):
            rows.append({"script": name, "contact": contact,
                         "ours_long": float(-f[k, 1]), "theirs_long": float(
                             -theirs["force"][i, k, 1]),
                         "ours_lat": float(f[k, 0]), "theirs_lat": float(theirs["force"][i, k, 0]),
                         "ours_normal": float(n[k]), "theirs_normal": float(
                             theirs["force"][i, k, 2]),
                         "ours_speed": float(-v[k, 1]),
                         "theirs_speed": float(-theirs["velocity"][i, k, 1])})
    return rows


SHIFTS = [{}, {"friction_scale": 0.5}, {"friction_scale": 0.25}, {"gear_scale": 0.8},
          {"damping_scale": 0.5}, {"mass_scale": 2.0}]


@functools.cache
def _shift_program(task: str):
    """Jitted `(params, action, key) -> (mean speed over steps 40-100, speed after 10 steps,
    mean gyro z over steps 40-100)` from rest under a held action."""
    import jax
    import jax.numpy as jnp

    from safecdt_jax import envs

    env, _ = envs.make(task)

    def run(params, action, key):
        def body(s, _):
            s = env.step(s, action, params)
            return s, (jnp.linalg.norm(s.data.qvel[:2]), s.obs[8])

        _, (v, g) = jax.lax.scan(body, env.reset(key, params), None, 100)
        return v[40:].mean(), v[9], g[40:].mean()

    return jax.jit(run)


def shift_table(task: str = "CarGoal1", layouts: int = 3) -> list[dict]:
    """Per `SHIFTS` dynamics shift: top speed (m/s, a = (1, 1)), speed after 0.4 s and spin rate
    (rad/s, a = (1, -1)), ours against native MuJoCo with the same scales applied to its model."""
    import jax
    import jax.numpy as jnp

    from safecdt_jax import envs
    from safecdt_jax.envs.dynamics import apply_dynamics

    theirs = native({"cmd": "shifts", "task": task, "shifts": SHIFTS, "layouts": layouts})
    _, params = envs.make(task)
    program, rows = _shift_program(task), []
    for i, shift in enumerate(SHIFTS):
        p = apply_dynamics(params, shift)
        runs = [[np.asarray(x) for x in program(p, jnp.asarray(a), jax.random.PRNGKey(k))]
                for k in range(layouts) for a in ((1.0, 1.0), (1.0, -1.0))]
        straight, spin = np.mean(runs[0::2], axis=0), np.mean(runs[1::2], axis=0)
        ours, other = (straight[0], straight[1], spin[2]), theirs["values"][i]
        rows.append({"shift": ",".join(f"{k}={v:g}" for k, v in shift.items()) or "nominal",
                     "ours_top": float(ours[0]), "ours_early": float(ours[1]),
                     "ours_yaw": float(ours[2]), "theirs_top": float(other[0]),
                     "theirs_early": float(other[1]), "theirs_yaw": float(other[2])})
    return rows


def export_policy(snapshot_file: Path, index: int, path: Path) -> dict:
    """Writes snapshot `index` of an expert snapshot file as plain arrays for the native side
    (kernel_i, bias_i, std, mean, var, var_floor, clip); returns its metadata."""
    import jax

    from safecdt_jax.experts.config import ExpertConfig
    from safecdt_jax.experts.export import load_snapshots

    snaps, meta = load_snapshots(snapshot_file)
    cfg = ExpertConfig.from_json(meta["expert"])
    one = jax.tree.map(lambda x: np.asarray(x[index]), snaps)
    dense = one["actor"]["mean"]["params"]
    arrays = {}
    for i in range(len(dense)):
        arrays[f"kernel_{i}"] = dense[f"Dense_{i}"]["kernel"]
        arrays[f"bias_{i}"] = dense[f"Dense_{i}"]["bias"]
    arrays["std"] = np.exp(np.maximum(one["actor"]["log_std"], np.log(cfg.min_std)))
    arrays["mean"], arrays["var"] = one["norm"].mean, one["norm"].var
    arrays["var_floor"], arrays["clip"] = np.float64(cfg.obs_var_floor), np.float64(cfg.obs_clip)
    np.savez(path, **arrays)
    return meta["snapshots"][index]


def pick_expert(task: str, limit: float | None = None) -> int:
    """Index of the last snapshot of the task's cost-limit-`limit` run (default `LIMIT`)."""
    from safecdt_jax.experts.collect import snapshot_path
    from safecdt_jax.experts.export import load_snapshots

    meta = load_snapshots(snapshot_path(task))[1]
    limit = LIMIT["Goal" if "Goal" in task else "Circle"] if limit is None else limit
    mine = [i for i, s in enumerate(meta["snapshots"]) if s["schedule"][0] == limit]
    if not mine:
        limits = sorted({s["schedule"][0] for s in meta["snapshots"]})
        raise SystemExit(f"{task} has no expert of cost limit {limit:g}; it has {limits}")
    return max(mine, key=lambda i: meta["snapshots"][i]["round"])


def target_task(task: str) -> str:
    """The deployment target of a source task: the same robot and task at level 2."""
    return task[:-1] + "2"


def expert_act(snapshot_file: Path, index: int, deterministic: bool):
    """`act(key, obs) -> action` of snapshot `index` of an expert snapshot file: the policy's
    mean, or a sample of its Gaussian (as the expert explored), from raw observations."""
    import jax

    from safecdt_jax.experts.config import ExpertConfig
    from safecdt_jax.experts.export import load_snapshots
    from safecdt_jax.experts.networks import action_dist

    snaps, meta = load_snapshots(snapshot_file)
    cfg = ExpertConfig.from_json(meta["expert"])
    one = jax.tree.map(lambda x: x[index], snaps)

    def act(key, obs):
        z = one["norm"].apply(obs, cfg.obs_var_floor, cfg.obs_clip)
        mean, std = action_dist(one["actor"], z, cfg.hidden, cfg.min_std)
        return mean if deterministic else mean + std * jax.random.normal(key, mean.shape)

    return act


def ours_policy(task: str, snapshot_file: Path, index: int, episodes: int, seed: int,
                deterministic: bool, run_in: str | None = None,
                robot=None) -> dict[str, np.ndarray]:
    """Per-episode return, cost, goals and cost steps per term (`TERMS`, absent terms 0) of one
    snapshot of `task`'s experts, run in task `run_in` (default `task`), with `robot` (a variant
    of the task's robot) in place of its own if given."""
    return ours_episodes(run_in or task, expert_policy(snapshot_file, index, deterministic),
                         episodes, seed, robot=robot)


def expert_policy(snapshot_file: Path, index: int, deterministic: bool):
    """`expert_act` as an env policy, `policy(key, state) -> action`."""
    act = expert_act(snapshot_file, index, deterministic)
    return lambda key, state: act(key, state.obs)


def ours_random(task: str, episodes: int, seed: int) -> dict[str, np.ndarray]:
    """`ours_policy`'s statistics under uniform random actions in [-1, 1]^2, in `task`."""
    from safecdt_jax.envs.rollout import uniform_policy

    return ours_episodes(task, uniform_policy, episodes, seed)


def ours_episodes(task: str, policy, episodes: int, seed: int,
                  shifts: list[dict[str, float]] | None = None,
                  robot=None) -> dict[str, np.ndarray]:
    """Per-episode return, cost, goals and cost steps per term of `policy(key, state) -> action`
    in our `task`, `episodes` episodes from `seed`'s keys, one jitted vmap. With `shifts`
    (`envs.dynamics` scales), every array gains a leading shift axis and each shift runs the
    same keys (paired: the same layouts and policy noise under each dynamics). `robot`: a
    variant of the task's robot (e.g. a `CarRobot` with other constants) in its place."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from safecdt_jax import envs
    from safecdt_jax.envs.dynamics import apply_dynamics, stack_params
    from safecdt_jax.envs.rollout import scan_episode

    env, params = envs.make(task)
    if robot is not None:
        env = dataclasses.replace(env, robot=robot)
    zero = jnp.float32(0.0)

    def record(s):
        terms = jnp.stack([(s.info.get(k, zero) > 0).astype(jnp.float32) for k in TERMS])
        return s.reward, s.cost, s.info["goal_met"], terms

    def episode(params, key):
        _, (r, c, g, terms) = scan_episode(env, params, key, policy, record)
        return {"return": r.sum(), "cost": c.sum(), "goals": g.sum(),
                **{k: terms[:, i].sum() for i, k in enumerate(TERMS)}}

    keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    run = jax.vmap(episode, in_axes=(None, 0))
    if shifts is not None:
        params = stack_params([apply_dynamics(params, shift) for shift in shifts])
        run = jax.vmap(run, in_axes=(0, None))
    return {k: np.asarray(v) for k, v in jax.jit(run)(params, keys).items()}


def transfer(task: str, episodes: int, limits: list[float] | None = None,
             targets: bool = True) -> list[dict]:
    """The task's experts (last snapshot per cost limit; default `LIMIT`) in both simulators,
    deterministic and stochastic, in the source task and (`targets`) its level-2 target: mean
    and median return, cost and goals, ratios theirs / ours with 95% bootstrap intervals, and
    per cost term the mean number of cost steps on each side."""
    from safecdt_jax.experts.collect import snapshot_path

    rows = []
    for limit in limits or [None]:
        index = pick_expert(task, limit)
        with tempfile.TemporaryDirectory() as tmp:
            weights = Path(tmp) / "policy.npz"
            info = export_policy(snapshot_path(task), index, weights)
            for run_in in (task, target_task(task)) if targets else (task,):
                for det in (True, False):
                    o = ours_policy(task, snapshot_path(task), index, episodes, 0, det, run_in)
                    t = native({"cmd": "policy", "task": run_in, "weights": str(weights),
                                "episodes": episodes, "seed": 0, "deterministic": det})
                    rows.append(_transfer_row(task, run_in, index, info, det, episodes, o, t))
    return rows


def _transfer_row(task, run_in, index, info, det, episodes, o, t) -> dict:
    row = {"task": task, "run_in": run_in, "snapshot": index, "limit": info["schedule"][0],
           "round": info["round"], "deterministic": det, "episodes": episodes}
    for k in ("return", "cost", "goals"):
        row[f"ours_{k}"], row[f"theirs_{k}"] = float(o[k].mean()), float(t[k].mean())
    row["ours_median_cost"] = float(np.median(o["cost"]))
    row["theirs_median_cost"] = float(np.median(t["cost"]))
    row["return_ratio"] = row["theirs_return"] / row["ours_return"]
    row["cost_ratio"] = row["theirs_cost"] / max(row["ours_cost"], 1e-9)
    row["return_ratio_ci"] = ratio_interval(t["return"], o["return"])
    row["cost_ratio_ci"] = ratio_interval(t["cost"], o["cost"])
    row["terms"] = {}
    for k in TERMS:
        if o[k].any() or t[k].any():
            row["terms"][k] = {"ours": float(o[k].mean()), "theirs": float(t[k].mean()),
                               "ratio_ci": ratio_interval(t[k], o[k])}
    for k in ("return", "cost"):  # kept so that the intervals can be recomputed
        row[f"ours_{k}s"] = [round(float(x), 4) for x in o[k]]
        row[f"theirs_{k}s"] = [round(float(x), 4) for x in t[k]]
    return row


def in_band(row: dict) -> bool:
    """Issue 48's agreement test for a transfer row: mean cost ratio within 0.7-1.43 with a 95%
    interval containing 1, the median cost ratio in the same band (or both medians 0), and the
    return ratio within 0.8-1.25."""
    lo, hi = row.get("cost_ratio_ci") or (0.0, np.inf)
    mo, mt = row["ours_median_cost"], row["theirs_median_cost"]
    cost_ok = 0.7 <= row["cost_ratio"] <= 1.43 and lo <= 1.0 <= hi
    if row["ours_cost"] == 0 and row["theirs_cost"] == 0:
        cost_ok = True
    median_ok = (mo == mt == 0) or (mo > 0 and 0.7 <= mt / mo <= 1.43)
    return bool(cost_ok and median_ok and 0.8 <= row["return_ratio"] <= 1.25)


def ours_layouts(task: str, episodes: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Our positions after `episodes` resets, as native.py's `layouts` returns them (agent and
    goal [E, 2], the task's active hazards and vases [E, n, 2], m)."""
    import jax

    from safecdt_jax import envs

    env, params = envs.make(task)
    states = jax.jit(jax.vmap(lambda k: env.reset(k, params)))(
        jax.random.split(jax.random.PRNGKey(seed), episodes))
    task_state = {k: np.asarray(v) for k, v in states.task.items()}
    out = {"agent": np.asarray(states.data.qpos[:, :2]),
           "goal": task_state.get("goal", np.zeros((episodes, 2)))}
    for name, mask in (("hazards", params.hazard_mask), ("vases", params.vase_mask)):
        active = np.asarray(mask) > 0 if name in task_state else np.zeros(0, bool)
        out[name] = task_state[name][:, active] if name in task_state else np.zeros(
            (episodes, 0, 2))
    return out


def layout_stats(pos: dict[str, np.ndarray], keepouts: dict[str, float]) -> dict[str, float]:
    """Summary statistics of reset layouts (m): the agent's mean |x|, |y| and largest |x|, |y|;
    the mean agent-goal distance; the mean distance from the agent to its nearest hazard and
    vase; and the smallest keepout slack (distance minus both keepouts) over all pairs of
    placed objects (negative: a keepout was violated)."""
    agent, goal = pos["agent"], pos["goal"]
    stats = {"agent |x| mean": np.abs(agent[:, 0]).mean(), "agent |y| mean":
             np.abs(agent[:, 1]).mean(), "agent |x|,|y| max": np.abs(agent).max()}
    if pos["hazards"].shape[1] or pos["vases"].shape[1]:
        stats["agent-goal distance"] = np.linalg.norm(agent - goal, axis=-1).mean()
    for name in ("hazards", "vases"):
        if pos[name].shape[1]:
            d = np.linalg.norm(pos[name] - agent[:, None], axis=-1)
            stats[f"agent-nearest {name[:-1]}"] = d.min(1).mean()
    objects = [("agent", agent[:, None])] + [
        (n, pos[n]) for n in ("hazards", "vases") if pos[n].shape[1]]
    if len(objects) > 1:
        xy = np.concatenate([o for _, o in objects], 1)
        k = np.concatenate([np.full(o.shape[1], keepouts[n]) for n, o in objects])
        d = np.linalg.norm(xy[:, :, None] - xy[:, None], axis=-1) - k[:, None] - k[None]
        d[:, np.arange(len(k)), np.arange(len(k))] = np.inf
        stats["smallest keepout slack"] = d.min()
    return {k: float(v) for k, v in stats.items()}


def layout_table(task: str, episodes: int = 256) -> dict:
    """Our layouts against Safety-Gymnasium's: placement constants and `layout_stats` of
    `episodes` resets on each side."""
    from safecdt_jax import envs
    from safecdt_jax.envs import goal as goal_task

    theirs = native({"cmd": "layouts", "task": task, "episodes": episodes, "seed": 0})
    ours = ours_layouts(task, episodes)
    env, params = envs.make(task)
    robot = env.robot
    if "Circle" in task:
        from safecdt_jax.envs.circle import START_HALF_WIDTH
        constants = {"start half-width": (START_HALF_WIDTH,
                                          float(theirs["agent_placements"][0, 2]))}
    else:
        constants = {"extent": (float(params.extent), float(theirs["extents"][2])),
                     "agent keepout": (robot.keepout, float(theirs["agent_keepout"])),
                     "hazards": (int(np.sum(params.hazard_mask)),
                                 int(theirs["hazards_num"])),
                     "hazard radius": (goal_task.HAZARD_RADIUS, float(theirs["hazards_size"])),
                     "hazard keepout": (goal_task.HAZARD_KEEPOUT,
                                        float(theirs["hazards_keepout"])),
                     "vases": (int(np.sum(params.vase_mask)), int(theirs["vases_num"])),
                     "vase half-size": (goal_task.VASE_RADIUS, float(theirs["vases_size"])),
                     "vase keepout": (goal_task.VASE_KEEPOUT,
                                      float(theirs["vases_keepout"])),
                     "goal radius": (goal_task.GOAL_RADIUS, float(theirs["goal_size"])),
                     "goal keepout": (goal_task.GOAL_KEEPOUT,
                                      float(theirs["goal_keepout"]))}
    keepouts = {"agent": robot.keepout, "hazards": goal_task.HAZARD_KEEPOUT,
                "vases": goal_task.VASE_KEEPOUT}
    return {"episodes": episodes, "constants": constants,
            "ours": layout_stats(ours, keepouts), "theirs": layout_stats(theirs, keepouts)}


def _with_ci(ratio: float, ci) -> str:
    return f"{ratio:.2f}" + (f" ({ci[0]:.2f}-{ci[1]:.2f})" if ci else "")


def report(results: dict) -> str:
    """Markdown: the runs that made it, one sensor table per task, the Car's turning, contact
    and shift tables, then the transfer table."""
    out = [f"- `{r['command']}` ({', '.join(r['tasks'])}; {r['date']})"
           for r in results.get("runs", [])]
    out += [""] if out else []
    for task, rows in results.get("sensors", {}).items():
        out += [f"### {task}: sensors under uniform random actions", "", markdown_table(
            ["dim", "name", "ours mean", "ours std", "theirs mean", "theirs std", "std ratio",
             "W1"],
            [[r["dim"], r["name"], f"{r['ours_mean']:.3f}", f"{r['ours_std']:.3f}",
              f"{r['theirs_mean']:.3f}", f"{r['theirs_std']:.3f}", f"{r['std_ratio']:.2f}",
              f"{r['w1']:.3f}"] for r in rows]), ""]
        off = [r["name"] for r in rows if not 0.5 <= r["std_ratio"] <= 2.0]
        out += [f"std within a factor of 2: {len(rows) - len(off)} of {len(rows)}"
                + (f" (off: {', '.join(off)})" if off else ""), ""]
    for task, rows in results.get("turning", {}).items():
        out += [f"### {task}: turning under open-loop scripts (steps 100-500)", "", markdown_table(
            ["script", "speed ours", "speed theirs", "yaw rate ours", "yaw rate theirs"],
            [[r["script"], f"{r['ours_speed']:.3f}", f"{r['theirs_speed']:.3f}",
              f"{r['ours_yaw_rate']:.3f}", f"{r['theirs_yaw_rate']:.3f}"] for r in rows]), ""]
    for task, rows in results.get("contacts", {}).items():
        out += [f"### {task}: ground contact forces under held actions (steps 150-300)", "",
                markdown_table(
                    ["action", "contact", "forward force ours / theirs (N)",
                     "lateral ours / theirs", "normal ours / theirs",
                     "forward speed ours / theirs"],
                    [[r["script"], r["contact"], f"{r['ours_long']:.3f} / {r['theirs_long']:.3f}",
                      f"{r['ours_lat']:.3f} / {r['theirs_lat']:.3f}",
                      f"{r['ours_normal']:.3f} / {r['theirs_normal']:.3f}",
                      f"{r['ours_speed']:.3f} / {r['theirs_speed']:.3f}"] for r in rows]), ""]
    for task, rows in results.get("shifts", {}).items():
        out += [f"### {task}: shifted dynamics from rest", "", markdown_table(
            ["shift", "top speed ours / theirs (m/s)", "after 0.4 s", "spin rate (rad/s)"],
            [[r["shift"], f"{r['ours_top']:.3f} / {r['theirs_top']:.3f}",
              f"{r['ours_early']:.3f} / {r['theirs_early']:.3f}",
              f"{r['ours_yaw']:.3f} / {r['theirs_yaw']:.3f}"] for r in rows]), ""]
    for task, lay in results.get("layouts", {}).items():
        rows = [[k, f"{a:g} / {b:g}"] for k, (a, b) in lay["constants"].items()]
        rows += [[k, f"{lay['ours'][k]:.3f} / {lay['theirs'][k]:.3f}"] for k in lay["ours"]]
        out += [f"### {task}: layouts ({lay['episodes']} resets each side)", "",
                markdown_table(["quantity", "ours / theirs"], rows), ""]
    if results.get("transfer"):
        rows = results["transfer"]
        out += ["### Expert transfer, ours -> Safety-Gymnasium", "", markdown_table(
            ["expert", "limit", "run in", "episodes", "policy", "return ours / theirs",
             "ratio (95% CI)", "cost ours / theirs", "cost ratio (95% CI)",
             "median cost ours / theirs", "goals ours / theirs", "in band"],
            [[r["task"], f"{r['limit']:g}", r.get("run_in", r["task"]), r["episodes"],
              "deterministic" if r["deterministic"] else "stochastic",
              f"{r['ours_return']:.1f} / {r['theirs_return']:.1f}",
              _with_ci(r["return_ratio"], r.get("return_ratio_ci")),
              f"{r['ours_cost']:.1f} / {r['theirs_cost']:.1f}",
              _with_ci(r["cost_ratio"], r.get("cost_ratio_ci")),
              f"{r.get('ours_median_cost', float('nan')):.1f} / "
              f"{r.get('theirs_median_cost', float('nan')):.1f}",
              f"{r['ours_goals']:.1f} / {r['theirs_goals']:.1f}",
              "yes" if in_band(r) else "no"] for r in rows]), "",
            "In band: the cost ratio within 0.7-1.43 with its interval containing 1, the median "
            "cost ratio in the same band (or both medians 0), the return ratio within 0.8-1.25.",
            ""]
        terms = [[r["task"], f"{r['limit']:g}", r.get("run_in", r["task"]),
                  "deterministic" if r["deterministic"] else "stochastic", k,
                  f"{v['ours']:.1f} / {v['theirs']:.1f}",
                  _with_ci(v["theirs"] / max(v["ours"], 1e-9), v["ratio_ci"])]
                 for r in rows for k, v in r.get("terms", {}).items()]
        if terms:
            out += ["### Cost steps per term, ours / Safety-Gymnasium (mean per episode)", "",
                    markdown_table(["expert", "limit", "run in", "policy", "term",
                                    "steps ours / theirs", "ratio (95% CI)"], terms), ""]
    return "\n".join(out)


def merge_previous(results: dict, path: Path, tasks: list[str]) -> dict:
    """`results` with the other tasks' entries of an earlier file at `path` kept (a run over
    some tasks updates their rows only); `runs` lists every contributing command and date."""
    if not path.exists():
        return {**results, "runs": [{"command": results["command"], "tasks": tasks,
                                     "date": results["machine"]["date"]}]}
    old = json.loads(path.read_text())
    merged = dict(results)
    for part in PARTS[:-1]:
        if part not in results:  # not measured this time: the earlier rows stand
            merged[part] = old.get(part, {})
            continue
        merged[part] = {**{k: v for k, v in old.get(part, {}).items() if k not in tasks},
                        **results[part]}
    if results.get("transfer"):
        merged["transfer"] = [r for r in old.get("transfer", []) if r["task"] not in tasks]
        merged["transfer"] += results["transfer"]
    else:
        merged["transfer"] = old.get("transfer", [])
    first = {"command": old.get("command"), "tasks": list(old.get("sensors", {})),
             "date": old.get("machine", {}).get("date")}
    this = {"command": results["command"], "tasks": tasks, "date": results["machine"]["date"]}
    merged["runs"] = [*old.get("runs", [first]), this]
    return merged


def main() -> None:
    """Command line: measure, print the tables, write JSON and markdown."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", default="CarGoal1,PointGoal1,CarCircle1,PointCircle1")
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--policy-episodes", type=int, default=64)
    ap.add_argument("--limits", default="",
                    help="comma-separated expert cost limits for the transfer (default 25, "
                         "Circle 20)")
    ap.add_argument("--source-only", action="store_true",
                    help="transfer: run the experts in their source task only")
    ap.add_argument("--parts", default=",".join(PARTS),
                    help=f"comma-separated subset of {','.join(PARTS)}")
    ap.add_argument("--out", type=Path, default=ROOT / "experiments/results/sim2sim.json")
    args = ap.parse_args()
    t = time.perf_counter()
    tasks, parts = args.tasks.split(","), args.parts.split(",")
    limits = [float(x) for x in args.limits.split(",") if x] or None
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        raise SystemExit(f"unknown --parts {unknown}; choose from {','.join(PARTS)}")
    measure = {
        "sensors": lambda: {task: sensor_stats(task, args.episodes) for task in tasks},
        "script": lambda: {task: script_readings(task) for task in tasks if task[:3] == "Car"},
        "turning": lambda: {task: turning(task) for task in tasks if task[:3] == "Car"},
        "contacts": lambda: {task: contact_table(task) for task in tasks
                             if task.startswith("CarGoal")},
        "shifts": lambda: {task: shift_table(task) for task in tasks
                           if task.startswith("CarGoal")},
        "layouts": lambda: {t: layout_table(t) for task in tasks
                            for t in (task, target_task(task))},
        "transfer": lambda: [r for task in tasks for r in transfer(
            task, args.policy_episodes, limits, not args.source_only)]}
    results = {"machine": machine(), "command": "python -m experiments.sim2sim " + " ".join(
        f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items() if k != "out")}
    results.update({part: measure[part]() for part in PARTS if part in parts})
    results["seconds"] = time.perf_counter() - t
    results = merge_previous(results, args.out, tasks)
    text = report(results)
    print(text)
    write_json(args.out, results)
    args.out.with_suffix(".md").write_text(text + "\n")


if __name__ == "__main__":
    main()
