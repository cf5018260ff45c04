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
import json
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json
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
PARTS = ("sensors", "script", "turning", "contacts", "shifts", "transfer")


def native(request: dict) -> dict[str, np.ndarray]:
    """Runs one request of `benchmarks/peers/native.py` in the peer venv; its arrays."""
    from benchmarks.peers.setup import venv_python

    python = venv_python("safety-gymnasium")
    if not python.exists():
        raise SystemExit("no peer venv: run `python -m benchmarks.peers.setup` first")
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


def turning(task: str, episodes: int = 4, steps: int = 500, seed: int = 0) -> list[dict]:
    """Mean forward speed (m/s) and yaw rate (rad/s) over steps 100..`steps` per `TURNS` script,
    ours and Safety-Gymnasium's (Car tasks: velocimeter y is dim 4, gyro z dim 8)."""
    rng = np.random.default_rng(seed)
    rows = []
    for name, spec in TURNS:
        if isinstance(spec, float):
            straight = rng.uniform(size=steps) < spec
            acts = np.where(straight[:, None], [[1.0, 1.0]], [[1.0, -1.0]])
        else:
            acts = np.tile([spec], (steps, 1))
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


def pick_expert(task: str) -> int:
    """Index of the last snapshot of the task's cost-limit-`LIMIT` run."""
    from safecdt_jax.experts.collect import snapshot_path
    from safecdt_jax.experts.export import load_snapshots

    meta = load_snapshots(snapshot_path(task))[1]
    limit = LIMIT["Goal" if "Goal" in task else "Circle"]
    mine = [i for i, s in enumerate(meta["snapshots"]) if s["schedule"][0] == limit]
    return max(mine, key=lambda i: meta["snapshots"][i]["round"])


def ours_policy(task: str, snapshot_file: Path, index: int, episodes: int, seed: int,
                deterministic: bool) -> dict[str, np.ndarray]:
    """Per-episode return, cost and goals of one snapshot in our env."""
    import jax

    from safecdt_jax import envs
    from safecdt_jax.envs.rollout import run_episode
    from safecdt_jax.experts.config import ExpertConfig
    from safecdt_jax.experts.export import load_snapshots
    from safecdt_jax.experts.networks import action_dist

    snaps, meta = load_snapshots(snapshot_file)
    cfg = ExpertConfig.from_json(meta["expert"])
    one = jax.tree.map(lambda x: x[index], snaps)
    env, params = envs.make(task)

    def policy(key, state):
        z = one["norm"].apply(state.obs, cfg.obs_var_floor, cfg.obs_clip)
        mean, std = action_dist(one["actor"], z, cfg.hidden, cfg.min_std)
        return mean if deterministic else mean + std * jax.random.normal(key, mean.shape)

    keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    out = jax.jit(jax.vmap(lambda k: run_episode(env, params, k, policy)))(keys)
    return {k: np.asarray(out[k]) for k in ("return", "cost", "goals")}


def transfer(task: str, episodes: int) -> list[dict]:
    """The task's limit-25 (Circle: 20) expert in both simulators, deterministic and stochastic."""
    from safecdt_jax.experts.collect import snapshot_path

    index = pick_expert(task)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        weights = Path(tmp) / "policy.npz"
        info = export_policy(snapshot_path(task), index, weights)
        for det in (True, False):
            o = ours_policy(task, snapshot_path(task), index, episodes, 0, det)
            t = native({"cmd": "policy", "task": task, "weights": str(weights),
                        "episodes": episodes, "seed": 0, "deterministic": det})
            row = {"task": task, "snapshot": index, "limit": info["schedule"][0],
                   "round": info["round"], "deterministic": det, "episodes": episodes}
            for k in ("return", "cost", "goals"):
                row[f"ours_{k}"], row[f"theirs_{k}"] = float(o[k].mean()), float(t[k].mean())
            row["ours_median_cost"] = float(np.median(o["cost"]))
            row["theirs_median_cost"] = float(np.median(t["cost"]))
            row["return_ratio"] = row["theirs_return"] / row["ours_return"]
            row["cost_ratio"] = row["theirs_cost"] / max(row["ours_cost"], 1e-9)
            row["return_ratio_ci"] = ratio_interval(t["return"], o["return"])
            row["cost_ratio_ci"] = ratio_interval(t["cost"], o["cost"])
            for k in ("return", "cost"):  # kept so that the intervals can be recomputed
                row[f"ours_{k}s"] = [round(float(x), 4) for x in o[k]]
                row[f"theirs_{k}s"] = [round(float(x), 4) for x in t[k]]
            rows.append(row)
    return rows


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
    if results.get("transfer"):
        out += ["### Expert transfer, ours -> Safety-Gymnasium", "", markdown_table(
            ["task", "limit", "episodes", "policy", "return ours", "return theirs",
             "ratio (95% CI)", "cost ours", "cost theirs", "cost ratio (95% CI)",
             "median cost ours", "median cost theirs", "goals ours", "goals theirs"],
            [[r["task"], f"{r['limit']:g}", r["episodes"], "deterministic" if r["deterministic"]
              else "stochastic", f"{r['ours_return']:.1f}", f"{r['theirs_return']:.1f}",
              _with_ci(r["return_ratio"], r.get("return_ratio_ci")),
              f"{r['ours_cost']:.1f}", f"{r['theirs_cost']:.1f}",
              _with_ci(r["cost_ratio"], r.get("cost_ratio_ci")),
              f"{r.get('ours_median_cost', float('nan')):.1f}",
              f"{r.get('theirs_median_cost', float('nan')):.1f}",
              f"{r['ours_goals']:.1f}", f"{r['theirs_goals']:.1f}"]
             for r in results["transfer"]]), ""]
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
    ap.add_argument("--parts", default=",".join(PARTS),
                    help=f"comma-separated subset of {','.join(PARTS)}")
    ap.add_argument("--out", type=Path, default=ROOT / "experiments/results/sim2sim.json")
    args = ap.parse_args()
    t = time.perf_counter()
    tasks, parts = args.tasks.split(","), args.parts.split(",")
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
        "transfer": lambda: [r for task in tasks for r in transfer(task, args.policy_episodes)]}
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
