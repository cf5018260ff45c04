"""Native Safety-Gymnasium rollouts for `experiments.sim2sim`; runs inside the peer venv.

    .peers/safety-gymnasium/bin/python benchmarks/peers/native.py REQUEST.json OUT.npz

It imports only the peer's packages, never this project. Requests (JSON):
- `{"cmd": "trace", "task": "CarGoal1", "episodes": 4, "steps": 500, "seed": 0,
  "actions": null | [[a0, a1], ...]}`: observations [episodes, steps, obs_dim] under uniform
  random actions in [-1, 1]^2 (`actions` null) or the given open-loop script (from rest).
  `trace` and `policy` also take `"cone": "elliptic"`, which switches MuJoCo's friction cone
  (`opt.cone`) from its default, pyramidal, after every reset (an experiment: which of
  native's behaviours the cone makes).
- `{"cmd": "policy", "task": ..., "weights": "policy.npz", "episodes": 16, "seed": 0,
  "deterministic": true, "record": false}`: an exported expert (a tanh MLP on normalised
  observations, see `experiments.sim2sim.export_policy`; `weights` null: uniform random
  actions); per-episode return, cost and goals, and per cost term (`TERMS`, absent terms 0) the
  number of steps it was positive. With `record`, also every step's observation before the
  action, the action and whether a goal was met: `obs` [E, T, obs_dim], `actions` [E, T, 2],
  `goal_met` [E, T].
- `{"cmd": "contacts", "task": "CarGoal1", "actions": [[a0, a1], ...], "steps": 300,
  "start": 150, "seed": 0}`: per constant action (held from rest), the mean over steps
  `start`..`steps` of each ground contact's force on the car in the chassis frame (left wheel,
  right wheel, caster: x, y, normal; N, summed over that geom's contacts), its point's velocity
  (m/s, x, y) and the wheels' rim speeds (hinge rate x radius, m/s).
- `{"cmd": "pulse", "task": "CarCircle1", "lead": [1, 1], "lead_steps": 100, "actions":
  [[1, -1], [1, 1], ...], "episodes": 4, "seed": 0}`: `lead` held from rest for `lead_steps`
  env steps, then `actions` one env step each, recorded after every physics substep (Car):
  the wheels' and caster's normal loads, yaw rate, forward speed, chassis height, pitch and
  roll (`pulse`).
- `{"cmd": "shifts", "task": "CarGoal1", "shifts": [{"friction_scale": 0.5}, ...],
  "layouts": 3}`: per shift (this project's `EnvParams` scales applied to the native model:
  every geom's sliding friction, the actuators' gear, the robot's joint dampings, its bodies'
  masses and inertias), from rest: the mean speed over steps 40-100 at a = (1, 1), the speed
  after 10 steps, and the mean gyro z over steps 40-100 at a = (1, -1), averaged over
  `layouts` resets; [n_shifts, 3].
- `{"cmd": "layouts", "task": "CarGoal2", "episodes": 256, "seed": 0}`: object positions
  after each reset and the placement constants (see `layouts`).
The observation is Safety-Gymnasium's flattened one, checked against the key order that this
project's envs use (sensors, caster angular velocity, caster orientation, then lidars).
"""

import json
import sys

import numpy as np

TERMS = ("cost_hazards", "cost_vases_contact", "cost_vases_velocity", "cost_out_of_boundary")
ORDER = ("accelerometer", "velocimeter", "gyro", "magnetometer", "ballangvel_rear",
         "ballquat_rear", "goal_lidar", "hazards_lidar", "vases_lidar", "circle_lidar")


def make(task: str):
    """The native env and a check that its flattened observation has our layout."""
    import safety_gymnasium

    env = safety_gymnasium.make(f"Safety{task}-v0")
    keys = list(env.unwrapped.task.obs_info.obs_space_dict.spaces)
    ours = [k for k in ORDER if k in keys]
    if keys != ours:
        raise RuntimeError(f"{task}: observation keys {keys}, expected the order {ours}")
    return env


def _reset(env, seed: int, cone: str):
    """`env.reset(seed=seed)` with the friction cone `cone` set on the rebuilt model."""
    import mujoco

    out = env.reset(seed=seed)
    if cone != "pyramidal":
        env.unwrapped.task.model.opt.cone = {"elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC}[cone]
    return out


def trace(task: str, episodes: int, steps: int, seed: int, actions=None,
          cone: str = "pyramidal") -> dict:
    """Observations after each step, [episodes, steps, obs_dim] float32."""
    env, rng = make(task), np.random.default_rng(seed)
    out = []
    for ep in range(episodes):
        _reset(env, seed + ep, cone)
        obs = []
        for t in range(steps):
            a = rng.uniform(-1, 1, 2) if actions is None else np.asarray(actions[t], float)
            o, *_ = env.step(a)
            obs.append(o)
        out.append(obs)
    return {"obs": np.asarray(out, np.float32)}


def _policy(weights: dict, deterministic: bool, rng):
    w = {k: np.asarray(v, np.float64) for k, v in weights.items()}
    live = w["var"] >= float(w["var_floor"])
    std_obs = np.sqrt(np.where(live, w["var"], 1.0))
    n_layers = sum(k.startswith("kernel_") for k in w)

    def act(obs):
        x = np.clip(np.where(live, (obs - w["mean"]) / std_obs, 0.0), -w["clip"], w["clip"])
        for i in range(n_layers):
            x = x @ w[f"kernel_{i}"] + w[f"bias_{i}"]
            if i < n_layers - 1:
                x = np.tanh(x)
        if not deterministic:
            x = x + w["std"] * rng.standard_normal(x.shape)
        return np.clip(x, -1.0, 1.0)

    return act


def policy(task: str, weights: str, episodes: int, seed: int, deterministic: bool,
           record: bool = False, cone: str = "pyramidal") -> dict:
    """Per-episode return, cost (cost steps), goals reached and cost steps per term (`TERMS`) of
    an exported expert (`weights`), or of uniform random actions (`weights` None); with
    `record`, the per-step observations, actions and goal indicators too."""
    env, rng = make(task), np.random.default_rng(seed)
    if weights is None:
        def act(obs):
            return rng.uniform(-1, 1, 2)
    else:
        with np.load(weights) as z:
            act = _policy(dict(z), deterministic, rng)
    rets, costs, goals, terms, trace = [], [], [], [], ([], [], [])
    for ep in range(episodes):
        obs, _ = _reset(env, seed + ep, cone)
        ret = cost = goal = 0.0
        steps = dict.fromkeys(TERMS, 0.0)
        done = False
        if record:
            for part in trace:
                part.append([])
        while not done:
            a = act(obs)
            if record:
                trace[0][-1].append(obs)
                trace[1][-1].append(a)
            obs, r, c, term, trunc, info = env.step(a)
            ret, cost = ret + r, cost + float(c > 0)
            goal += float(info.get("goal_met", False))
            if record:
                trace[2][-1].append(bool(info.get("goal_met", False)))
            for k in TERMS:
                steps[k] += float(info.get(k, 0.0) > 0)
            done = term or trunc
        rets.append(ret)
        costs.append(cost)
        goals.append(goal)
        terms.append([steps[k] for k in TERMS])
    terms = np.asarray(terms).reshape(episodes, len(TERMS))
    out = {"return": np.asarray(rets), "cost": np.asarray(costs), "goals": np.asarray(goals),
           **{k: terms[:, i] for i, k in enumerate(TERMS)}}
    if record:
        out.update(obs=np.asarray(trace[0], np.float32), actions=np.asarray(trace[1], np.float32),
                   goal_met=np.asarray(trace[2]))
    return out


def contacts(task: str, actions: list, steps: int, start: int, seed: int) -> dict:
    """Mean contact forces, contact-point velocities and rim speeds per held action (Car)."""
    import mujoco

    env = make(task)
    forces, speeds, rims = [], [], []
    for action in actions:
        env.reset(seed=seed)
        m, d = env.unwrapped.task.model, env.unwrapped.task.data  # rebuilt by reset
        geoms = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)
                 for n in ("left", "right", "rear")]
        agent = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "agent")
        hinges = [m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)]
                  for n in ("left", "right")]
        f_sum, v_sum, rim_sum, v6 = np.zeros((3, 3)), np.zeros((3, 2)), np.zeros(2), np.zeros(6)
        for t in range(steps):
            env.step(np.asarray(action, float))
            if t < start:
                continue
            rot = d.xmat[agent].reshape(3, 3)
            f_sum += _ground_forces(m, d, geoms, rot)
            for k, g in enumerate(geoms):
                mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_GEOM, g, v6, 0)
                v_sum[k] += (rot.T @ v6[3:])[:2]
            rim_sum += d.qvel[hinges] * 0.05
        n = steps - start
        forces.append(f_sum / n)
        speeds.append(v_sum / n)
        rims.append(rim_sum / n)
    return {"force": np.asarray(forces), "velocity": np.asarray(speeds), "rim": np.asarray(rims)}


def _ground_forces(m, d, geoms: list, rot: np.ndarray) -> np.ndarray:
    """Each of `geoms`' ground contact forces on the car in the chassis frame (x, y, normal;
    N, summed over that geom's contacts) [len(geoms), 3]."""
    import mujoco

    out, f6 = np.zeros((len(geoms), 3)), np.zeros(6)
    for i in range(d.ncon):
        c = d.contact[i]
        for k, g in enumerate(geoms):
            if g in (c.geom1, c.geom2):
                mujoco.mj_contactForce(m, d, i, f6)
                world = c.frame.reshape(3, 3).T @ f6[:3]  # on geom2, from geom1
                out[k] += rot.T @ (world if c.geom2 == g else -world)
    return out


def pulse(task: str, lead: list, lead_steps: int, actions: list, episodes: int,
          seed: int) -> dict:
    """Per physics substep while `actions` play (one per env step) after `lead` was held for
    `lead_steps` env steps from rest (Car), per episode (layout): the normal loads (N) on the
    left wheel, right wheel and caster, the yaw rate (rad/s), the forward speed (m/s, toward
    body -y), the chassis height (m), and its pitch and roll (rad, from the body z axis):
    `substeps` [episodes, len(actions) * frameskip, 8]."""
    import mujoco

    env = make(task)
    out = []
    for e in range(episodes):
        _reset(env, seed + e, "pyramidal")
        m, d = env.unwrapped.task.model, env.unwrapped.task.data
        geoms = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)
                 for n in ("left", "right", "rear")]
        agent = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "agent")
        for _ in range(lead_steps):
            env.step(np.asarray(lead, float))
        rows = []
        for action in actions:
            # env.step's physics, one substep at a time (frameskip_binom_p is 1: always n)
            env.unwrapped.task.agent.apply_action(np.asarray(action, float))
            for _ in range(env.unwrapped.task.sim_conf.frameskip_binom_n):
                mujoco.mj_step(m, d)
                rot = d.xmat[agent].reshape(3, 3)
                loads = _ground_forces(m, d, geoms, rot)[:, 2]
                rows.append([*loads, d.qvel[5], -(rot.T @ d.qvel[:3])[1], d.xpos[agent][2],
                             np.arcsin(np.clip(rot[2, 1], -1, 1)),
                             np.arcsin(np.clip(rot[2, 0], -1, 1))])
        out.append(rows)
    return {"substeps": np.asarray(out)}


def _apply_shift(m, shift: dict) -> None:
    """Scales the native model in place as this project's `EnvParams` scales do."""
    import mujoco

    agent = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "agent")
    robot = [b for b in range(m.nbody) if b == agent or m.body_parentid[b] == agent]
    m.geom_friction[:, 0] *= shift.get("friction_scale", 1.0)
    m.actuator_gear[:, 0] *= shift.get("gear_scale", 1.0)
    for b in robot:
        m.body_mass[b] *= shift.get("mass_scale", 1.0)
        m.body_inertia[b] *= shift.get("mass_scale", 1.0)
        if b != agent:  # the free joint has no damping; wheels' hinges and the caster's ball
            dofs = slice(m.body_dofadr[b], m.body_dofadr[b] + m.body_dofnum[b])
            m.dof_damping[dofs] *= shift.get("damping_scale", 1.0)


def shifts(task: str, shifts: list, layouts: int) -> dict:
    """Top speed, speed after 0.4 s (m/s) and spin rate (rad/s) per dynamics shift (Car)."""
    import mujoco

    env = make(task)
    out = []
    for shift in shifts:
        runs = []
        for seed in range(layouts):
            row = []
            for action in ((1.0, 1.0), (1.0, -1.0)):
                env.reset(seed=seed)
                m, d = env.unwrapped.task.model, env.unwrapped.task.data
                _apply_shift(m, shift)
                gyro = m.sensor_adr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SENSOR, "gyro")]
                speeds, yaws = [], []
                for _ in range(100):
                    env.step(np.asarray(action))
                    speeds.append(np.linalg.norm(d.qvel[:2]))
                    yaws.append(d.sensordata[gyro + 2])
                row.append((np.mean(speeds[40:]), speeds[9], np.mean(yaws[40:])))
            runs.append((row[0][0], row[0][1], row[1][2]))
        out.append(np.mean(runs, axis=0))
    return {"values": np.asarray(out)}


def layouts(task: str, episodes: int, seed: int) -> dict:
    """Positions after `episodes` resets (seeds seed, seed + 1, ...): agent and goal [E, 2],
    hazards and vases [E, n, 2] (m; n = 0 when the task has none), and the placement constants:
    extents, and per object kind (agent, goal, hazards, vases) its count, size and keepout."""
    env = make(task)
    agent, goal, hazards, vases = [], [], [], []
    for ep in range(episodes):
        env.reset(seed=seed + ep)
        t = env.unwrapped.task
        agent.append(t.agent.pos[:2])
        goal.append(t.goal.pos[:2] if hasattr(t, "goal") else np.zeros(2))
        hazards.append([p[:2] for p in t.hazards.pos] if hasattr(t, "hazards") else [])
        vases.append([p[:2] for p in t.vases.pos] if hasattr(t, "vases") else [])
    t = env.unwrapped.task
    out = {"agent": np.asarray(agent), "goal": np.asarray(goal),
           "hazards": np.asarray(hazards).reshape(episodes, -1, 2),
           "vases": np.asarray(vases).reshape(episodes, -1, 2),
           "extents": np.asarray(t.placements_conf.extents, float)}
    for name in ("agent", "goal", "hazards", "vases"):
        obj = getattr(t, name, None)
        out[f"{name}_num"] = np.asarray(getattr(obj, "num", 1 if obj is not None else 0))
        out[f"{name}_size"] = np.asarray(float(getattr(obj, "size", np.nan) or np.nan))
        out[f"{name}_keepout"] = np.asarray(float(getattr(obj, "keepout", np.nan)))
        placements = getattr(obj, "placements", None)
        out[f"{name}_placements"] = np.asarray(placements if placements else np.zeros((0, 4)),
                                                float).reshape(-1, 4)
    return out


def main() -> None:
    """Reads the request, writes the arrays."""
    request = json.loads(open(sys.argv[1]).read())
    cmd = request.pop("cmd")
    result = {"trace": trace, "policy": policy, "contacts": contacts, "shifts": shifts,
              "layouts": layouts, "pulse": pulse}[cmd](**request)
    np.savez(sys.argv[2], **result)


if __name__ == "__main__":
    main()
