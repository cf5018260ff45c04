"""Vase models for the Goal task: pushable discs in JAX against MJX contact bodies.

The issue asked for the cheapest vase model that keeps the vase costs meaningful (a robot touches
a vase; a vase still moves after a push). This script measures env steps/s of a Point robot with
10 vases on this machine (CPU) for three models, each as a jitted `lax.scan` of env steps (10
physics substeps of 0.002 s each) under `jax.vmap`, compile time reported separately, median of
3 timed runs:

  jax_discs     the project's env, `envs.make("PointGoal2")` (10 vases, level-2 costs), stepped
                with uniform random actions: planar MJX Point without contacts, vases as discs
                pushed in JAX (`GoalTask._push_vases`), plus the rest of the env (hazards, goal,
                reward, lidar observation).
  mjx_contacts  the same planar Point (`safecdt_jax.envs.robots.POINT_XML`, contacts re-enabled)
                plus 10 free-joint box vases (half-size 0.1 m, density 0.001, resting at z = 0.1 -
                4e-5) and a floor plane. contype/conaffinity bits let robot geoms touch vases and
                vases touch the floor, nothing else (no vase-vase, no robot-floor); condim 3, 4
                solver and line-search iterations, measured with the Newton and with the CG solver
                (`--solver`). Per env step it computes the same cost signals as the env: any robot-
                vase contact (penetrating `data._impl.contact` rows between a robot geom and a vase)
                and any vase linear speed >= 1e-4 m/s.
  mjx_no_vases  the plain planar Point (`POINT_XML`) stepped the same way: the floor of what an
                MJX step of this robot costs.

Only physics plus cost signals are timed for the two MJX models, while jax_discs runs the whole
env step (observation, reward, hazards), so the comparison is conservative for the disc model.
Initial states are built outside the timed function. The mjx_contacts model is ~100x slower than
the others on CPU, so it runs `--contact-steps` (default 20) env steps per timed scan instead of
`--steps` (200 at batch 256 would take minutes per run); the rate (steps/s) is what is compared.

`--check` runs a behavioural check instead of the benchmark: the Point drives straight into one
vase (forward thrust until contact and 5 steps more, then reverse), in both vase models, and the
script reports whether the vase moves and for how many env steps after the last contact its speed
stays >= 1e-4 m/s, and whether untouched vases ever move that fast (a spurious velocity cost:
MJX vases settle for a few steps after reset, and with CG at 4 iterations resting vases jitter
above 1e-4 m/s, which breaks the velocity cost's meaning).

Results (and the check, in its own key) are merged into the `--out` JSON, written atomically.

    python -m experiments.vase_models                # benchmark at batch 16 and 256
    python -m experiments.vase_models --check        # behavioural check
"""

import argparse
import datetime
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from benchmarks.common import write_json
from safecdt_jax import envs
from safecdt_jax.envs.goal import VASE_SPEED_COST
from safecdt_jax.envs.robots import N_SUBSTEPS, POINT, POINT_XML

N_VASES = 10
VASE_HALF = 0.1  # m: half-size of the vase cube, as Safety-Gymnasium's
VASE_Z = 0.1 - 4e-5  # m: Safety-Gymnasium rests vases slightly into the floor
VASE_DENSITY = 0.001  # kg/m^3 -> 8e-6 kg per vase
N_RUNS = 3
PUSH_STEPS = 5  # check: env steps of forward thrust after the first contact


# ----------------------------------------------------------------------------- models


def vase_layout(seed: int = 0, extent: float = 2.0, spacing: float = 0.3,
                clear: float = 0.5) -> np.ndarray:
    """N_VASES vase centres (x, y) in [-extent, extent]^2, `spacing` apart and `clear` from the
    robot's start at the origin (rejection sampling, fixed seed)."""
    rng = np.random.default_rng(seed)
    pos: list[np.ndarray] = []
    while len(pos) < N_VASES:
        p = rng.uniform(-extent, extent, 2)
        if np.linalg.norm(p) > clear and all(np.linalg.norm(p - q) > spacing for q in pos):
            pos.append(p)
    return np.array(pos)


def contact_xml(vase_xy: np.ndarray, solver: str, iterations: int) -> str:
    """POINT_XML with contacts on, a floor plane and free-joint box vases.

    Bits: robot geoms contype 1 / conaffinity 0, vases 2 / 1, floor 0 / 2, so robot-vase
    (1 & 1) and vase-floor (2 & 2) collide; vase-vase (2 & 1), robot-floor (1 & 2, 0 & 0) do not.
    """
    xml = POINT_XML.replace('<flag contact="disable"/>', "")
    xml = xml.replace("<option ", f'<option iterations="{iterations}" '
                      f'ls_iterations="{iterations}" solver="{solver}" ', 1)
    robot_bits = 'contype="0" conaffinity="0"'
    if xml.count(robot_bits) != 2:
        raise RuntimeError("POINT_XML changed: expected two contact-free robot geoms")
    xml = xml.replace(robot_bits, 'contype="1" conaffinity="0" condim="3"')
    floor = ('\n  <geom name="floor" type="plane" size="5 5 0.1" contype="0" conaffinity="2"'
             ' condim="3"/>')
    vases = "".join(
        f'\n  <body name="vase{i}" pos="{x:.5f} {y:.5f} {VASE_Z:.5f}"><freejoint/>'
        f'<geom name="vase{i}" type="box" size="{VASE_HALF} {VASE_HALF} {VASE_HALF}"'
        f' density="{VASE_DENSITY}" contype="2" conaffinity="1" condim="3"/></body>'
        for i, (x, y) in enumerate(vase_xy))
    xml = xml.replace("<worldbody>", "<worldbody>" + floor, 1)
    return xml.replace("\n </worldbody>", vases + "\n </worldbody>", 1)


class MjxSim:
    """A planar Point MJX model (optionally with contact vases) stepped like the env's Point.

    `step` returns the data after N_SUBSTEPS `mjx.step`s and a final `mjx.forward` (as
    `PointRobot.physics`), whether a robot geom penetrates a vase, and each vase's linear speed.
    """

    def __init__(self, xml: str):
        self.mj_model = mujoco.MjModel.from_xml_string(xml)
        mj = self.mj_model
        agent = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_BODY, "agent")
        self.robot_geom = np.asarray(mj.geom_bodyid == agent)
        free = np.flatnonzero(mj.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
        # A free joint's first 3 dofs are the body's linear velocity in the world frame.
        self.vase_dofs = (mj.jnt_dofadr[free][:, None] + np.arange(3)[None]).astype(np.int32)
        self.model = mjx.put_model(mj)

    def init(self, yaw: jax.Array) -> mjx.Data:
        """Robot at the origin with heading `yaw`, vases where the XML puts them, all at rest."""
        data = mjx.make_data(self.model)
        data = data.replace(qpos=data.qpos.at[2].set(yaw))
        return mjx.forward(self.model, data)

    def step(self, data: mjx.Data, action: jax.Array):
        """One env step under `action` in [-1, 1]^2: (data, robot-vase contact, vase speeds)."""
        m = self.model
        data = data.replace(ctrl=jnp.clip(action, -1.0, 1.0))
        data = jax.lax.fori_loop(0, N_SUBSTEPS, lambda _, d: mjx.step(m, d), data)
        data = mjx.forward(m, data)
        con = data._impl.contact  # MJX keeps every candidate contact; dist < 0 penetrates
        robot = jnp.asarray(self.robot_geom)[con.geom]  # [ncon, 2]
        touching = jnp.any((robot[:, 0] != robot[:, 1]) & (con.dist < 0))
        speed = jnp.linalg.norm(data.qvel[jnp.asarray(self.vase_dofs)], axis=-1)
        return data, touching, speed


def probe_pairs() -> dict[str, str]:
    """Which geom-type pairs MJX collides ('ok') or refuses (the error), traced only."""
    shapes = {"plane": 'type="plane" size="5 5 0.1"', "sphere": 'type="sphere" size="0.1"',
              "box": 'type="box" size="0.1 0.1 0.1"', "cylinder": 'type="cylinder" size="0.1 .05"'}
    out = {}
    for a, b in [("sphere", "box"), ("box", "box"), ("plane", "box"), ("cylinder", "box"),
                 ("plane", "cylinder"), ("sphere", "cylinder")]:
        first = (f"<geom {shapes[a]}/>" if a == "plane"
                 else f'<body pos="0 0 0.2"><freejoint/><geom {shapes[a]}/></body>')
        xml = (f"<mujoco><worldbody>{first}<body pos=\"0.15 0 0.2\"><freejoint/>"
               f"<geom {shapes[b]}/></body></worldbody></mujoco>")
        try:
            m = mjx.put_model(mujoco.MjModel.from_xml_string(xml))
            jax.eval_shape(mjx.forward, m, mjx.make_data(m))
            out[f"{a}-{b}"] = "ok"
        except Exception as e:  # MJX raises NotImplementedError for missing pair functions
            out[f"{a}-{b}"] = f"refused: {type(e).__name__}: {e}"
    return out


# ----------------------------------------------------------------------------- benchmark


def uniform_actions(key: jax.Array, steps: int) -> jax.Array:
    """[steps, 2] uniform random actions in [-1, 1] (the env's random-policy statistics)."""
    return jax.random.uniform(key, (steps, 2), minval=-1.0, maxval=1.0)


def disc_rollout(steps: int) -> tuple[Callable, Callable]:
    """(init(keys), rollout(states, keys)) for the project's PointGoal2 env, batched."""
    env, params = envs.make("PointGoal2")

    def one(state, key):
        def body(carry, action):
            s, n_contact, n_moving = carry
            s = env.step(s, action, params)
            return (s, n_contact + s.info["cost_vases_contact"],
                    n_moving + s.info["cost_vases_velocity"]), None

        zero = jnp.float32(0.0)
        (s, nc, nm), _ = jax.lax.scan(body, (state, zero, zero), uniform_actions(key, steps))
        return s, nc, nm  # the final state is returned so nothing of the step is dead code

    return jax.vmap(lambda k: env.reset(k, params)), jax.vmap(one)


def mjx_rollout(sim: MjxSim, steps: int) -> tuple[Callable, Callable]:
    """(init(keys), rollout(datas, keys)) for an MjxSim, batched, with the env's cost signals."""

    def init(key):
        return sim.init(jax.random.uniform(key, (), maxval=2 * jnp.pi))

    def one(data, key):
        def body(carry, action):
            d, n_contact, n_moving = carry
            d, touching, speed = sim.step(d, action)
            moving = jnp.any(speed >= VASE_SPEED_COST)
            return (d, n_contact + touching, n_moving + moving), None

        zero = jnp.float32(0.0)
        (d, nc, nm), _ = jax.lax.scan(body, (data, zero, zero), uniform_actions(key, steps))
        return d, nc, nm

    return jax.vmap(init), jax.vmap(one)


def measure(name: str, init: Callable, rollout: Callable, batch: int, steps: int) -> dict:
    """Compile time and median steps/s of N_RUNS timed calls of the jitted batched rollout."""
    k_init, k_run = jax.random.split(jax.random.key(0))
    states = jax.block_until_ready(jax.jit(init)(jax.random.split(k_init, batch)))
    keys = jax.random.split(k_run, batch)
    t0 = time.perf_counter()
    compiled = jax.jit(rollout).lower(states, keys).compile()
    compile_s = time.perf_counter() - t0
    runs = []
    for _ in range(N_RUNS):
        t0 = time.perf_counter()
        _, n_contact, n_moving = jax.block_until_ready(compiled(states, keys))
        runs.append(time.perf_counter() - t0)
    median = statistics.median(runs)
    return {
        "model": name, "batch": batch, "steps": steps,
        "steps_per_s": batch * steps / median, "compile_s": compile_s, "run_s": runs,
        "contact_cost_rate": float(jnp.mean(n_contact)) / steps,
        "velocity_cost_rate": float(jnp.mean(n_moving)) / steps,
    }


def benchmark(args: argparse.Namespace) -> dict:
    """Runs every model at every batch size, prints the markdown table, returns the JSON part."""
    layout = vase_layout()
    contact_sims = {solver: MjxSim(contact_xml(layout, solver, args.iterations))
                    for solver in args.solver}
    plain_sim = MjxSim(POINT_XML)
    results = []
    for batch in args.batch:
        runs = [("jax_discs", None, args.steps)]
        runs += [("mjx_contacts", solver, args.contact_steps) for solver in args.solver]
        runs += [("mjx_no_vases", None, args.steps)]
        for name, solver, steps in runs:
            if name == "jax_discs":
                init, rollout = disc_rollout(steps)
            else:
                sim = contact_sims[solver] if solver else plain_sim
                init, rollout = mjx_rollout(sim, steps)
            row = {**measure(name, init, rollout, batch, steps), "solver": solver}
            results.append(row)
            print(f"  {name} {solver or ''} batch {batch}: {row['steps_per_s']:.0f} steps/s, "
                  f"compile {row['compile_s']:.1f} s", flush=True)
    print("\n| model | batch | steps/scan | steps/s | compile s | contact rate | moving rate |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in results:
        label = r["model"] + (f" ({r['solver']}, {args.iterations} it)" if r["solver"] else "")
        print(f"| {label} | {r['batch']} | {r['steps']} | {r['steps_per_s']:.0f} | "
              f"{r['compile_s']:.1f} | {r['contact_cost_rate']:.3f} | "
              f"{r['velocity_cost_rate']:.3f} |")
    con = next(iter(contact_sims.values()))
    return {
        "results": results,
        "mjx_contacts_model": {
            "solvers": args.solver, "iterations": args.iterations,
            "ls_iterations": args.iterations, "condim": 3, "nv": con.mj_model.nv,
            "ngeom": con.mj_model.ngeom,
            "ncon_slots": int(mjx.make_data(con.model)._impl.ncon),
            "vase_mass_kg": float(con.mj_model.body_mass[-1]),
            "vase_xy": layout.round(4).tolist(),
            "collision_bits": "robot 1/0, vase 2/1, floor 0/2 (contype/conaffinity)",
        },
        "mjx_pair_support": probe_pairs(),
    }


# ----------------------------------------------------------------------------- check


def check_layout() -> np.ndarray:
    """Vase 0 on the robot's path (0.45 m ahead); the other 9 far off it, at |y| = 1.5 m."""
    others = [(x, y) for y in (1.5, -1.5) for x in (-1.6, -0.8, 0.0, 0.8, 1.6)][:N_VASES - 1]
    return np.array([(0.45, 0.0), *others])


def drive_into_vase(step: Callable, state: Any, n_steps: int) -> dict:
    """Forward thrust until the first contact and PUSH_STEPS more, then reverse thrust.

    `step(state, action) -> (state, contact, speeds [N_VASES], vase0_xy)`. Returns a summary.
    """
    contact, speed0, others, xy = [], [], [], []
    first = None
    for t in range(n_steps):
        forward = first is None or t <= first + PUSH_STEPS
        state, c, s, p = step(state, jnp.array([1.0 if forward else -1.0, 0.0]))
        c, s = bool(c), np.asarray(s)
        if c and first is None:
            first = t
        contact.append(c)
        speed0.append(float(s[0]))
        others.append(float(s[1:].max()))
        xy.append(np.asarray(p))
    contact_steps = [t for t, c in enumerate(contact) if c]
    last = contact_steps[-1] if contact_steps else None
    after = 0
    if last is not None:
        for v in speed0[last + 1:]:
            if v < VASE_SPEED_COST:
                break
            after += 1
    fast = np.array(speed0) >= VASE_SPEED_COST
    fast_others = np.array(others) >= VASE_SPEED_COST
    before = slice(0, n_steps if first is None else first)
    return {
        "first_contact_step": first, "last_contact_step": last,
        "contact_steps": len(contact_steps),
        "vase_moved_m": float(np.linalg.norm(xy[-1] - xy[0])),
        "vase_max_speed": max(speed0),
        "moving_steps_after_last_contact": after,
        "moving_steps_total": int(fast.sum()),
        "vase_final_speed": speed0[-1],
        "moving_steps_before_first_contact": int((fast | fast_others)[before].sum()),
        "untouched_max_speed": max(others),
        "untouched_moving_steps": int(fast_others.sum()),
        "untouched_moving_steps_after_first_contact": int(fast_others[before.stop:].sum()),
        "vase_speed_trace": [float(f"{v:.3g}") for v in speed0],
        "untouched_max_speed_trace": [float(f"{v:.3g}") for v in others],
        "contact_trace": [int(c) for c in contact],
    }


def check(args: argparse.Namespace) -> dict:
    """The drive-into-a-vase experiment in both models (robot at the origin heading +x)."""
    layout = check_layout()
    n_steps = args.check_steps
    results: dict[str, dict] = {}
    for solver in args.solver:
        sim = MjxSim(contact_xml(layout, solver, args.iterations))

        def mjx_step(data, action, sim=sim):
            data, touching, speed = sim.step(data, action)
            return data, touching, speed, data.qpos[3:5]  # vase 0's free joint xy

        results[f"mjx_contacts_{solver}"] = drive_into_vase(
            jax.jit(mjx_step), jax.jit(sim.init)(jnp.float32(0.0)), n_steps)

    env, params = envs.make("PointGoal2")
    params = params.replace(hazard_mask=jnp.zeros_like(params.hazard_mask))
    state = env.reset(jax.random.key(0), params)
    data = POINT.init_data(env.model, jnp.zeros(2), jnp.float32(0.0))
    goal = jnp.array([0.0, 1.0])
    task = {**state.task, "vases": jnp.asarray(layout, jnp.float32),
            "vase_vel": jnp.zeros((N_VASES, 2)), "goal": goal,
            "last_dist": jnp.linalg.norm(goal)}
    state = state.replace(data=data, task=task)

    @jax.jit
    def disc_step(s, action):
        s = env.step(s, action, params)
        speed = jnp.linalg.norm(s.task["vase_vel"], axis=-1)
        return s, s.info["cost_vases_contact"] > 0, speed, s.task["vases"][0]

    results["jax_discs"] = drive_into_vase(disc_step, state, n_steps)
    for name, r in results.items():
        print(f"{name}: first contact at step {r['first_contact_step']}, "
              f"{r['contact_steps']} contact steps (last {r['last_contact_step']}), "
              f"vase moved {r['vase_moved_m']:.3f} m (max speed {r['vase_max_speed']:.3f} m/s), "
              f"speed >= {VASE_SPEED_COST} for {r['moving_steps_after_last_contact']} env steps "
              f"after the last contact ({r['moving_steps_total']} in all, final speed "
              f"{r['vase_final_speed']:.1e}); before any contact "
              f"{r['moving_steps_before_first_contact']} steps with a vase >= {VASE_SPEED_COST}; "
              f"untouched vases: max speed "
              f"{r['untouched_max_speed']:.1e} m/s, >= {VASE_SPEED_COST} in "
              f"{r['untouched_moving_steps']} steps "
              f"({r['untouched_moving_steps_after_first_contact']} after the first contact)")
    return {"protocol": f"robot at origin heading +x, vase 0 at (0.45, 0), 9 vases at |y| = 1.5; "
                        f"thrust +1 until first contact and {PUSH_STEPS} env steps more, then -1; "
                        f"{n_steps} env steps of {N_SUBSTEPS} x 0.002 s", **results}


# ----------------------------------------------------------------------------- main


def merge_json(path: str, update: dict) -> None:
    """Merges `update` into the JSON at `path` (if readable) and replaces it atomically."""
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, ValueError):
        data = {}
    data.update(update)
    write_json(path, data)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, nargs="+", default=[16, 256],
                        help="batch sizes (vmapped envs)")
    parser.add_argument("--steps", type=int, default=200,
                        help="env steps per timed scan (jax_discs, mjx_no_vases)")
    parser.add_argument("--contact-steps", type=int, default=20,
                        help="env steps per timed scan for mjx_contacts (slow on CPU)")
    parser.add_argument("--solver", nargs="+", default=["Newton", "CG"],
                        choices=["Newton", "CG"], help="MuJoCo solver(s) of the contact model")
    parser.add_argument("--iterations", type=int, default=4,
                        help="solver and line-search iterations of the contact model")
    parser.add_argument("--check", action="store_true",
                        help="run the drive-into-a-vase behavioural check instead")
    parser.add_argument("--check-steps", type=int, default=100, help="env steps of the check")
    parser.add_argument("--out", default="experiments/results/vase_models.json")
    args = parser.parse_args()

    meta = {"when": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "device": str(jax.devices()[0]), "cpu_count": os.cpu_count(),
            "machine": platform.machine(), "jax": jax.__version__,
            "mujoco": mujoco.__version__, "n_vases": N_VASES, "substeps": N_SUBSTEPS,
            "timestep": 0.002, "runs": N_RUNS, "args": vars(args)}
    if args.check:
        merge_json(args.out, {"check": {**meta, **check(args)}})
    else:
        merge_json(args.out, {"benchmark": {**meta, **benchmark(args)}})
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
