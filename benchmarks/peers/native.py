"""Native Safety-Gymnasium rollouts for `benchmarks.sim2sim`; runs inside the peer venv.

    .peers/safety-gymnasium/bin/python benchmarks/peers/native.py REQUEST.json OUT.npz

It imports only the peer's packages, never this project. Requests (JSON):
- `{"cmd": "trace", "task": "CarGoal1", "episodes": 4, "steps": 500, "seed": 0,
  "actions": null | [[a0, a1], ...]}`: observations [episodes, steps, obs_dim] under uniform
  random actions in [-1, 1]^2 (`actions` null) or the given open-loop script (from rest).
- `{"cmd": "policy", "task": ..., "weights": "policy.npz", "episodes": 16, "seed": 0,
  "deterministic": true}`: an exported expert (a tanh MLP on normalised observations, see
  `benchmarks.sim2sim.export_policy`); per-episode return, cost and goals.
The observation is Safety-Gymnasium's flattened one, checked against the key order that this
project's envs use (sensors, caster angular velocity, caster orientation, then lidars).
"""

import json
import sys

import numpy as np

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


def trace(task: str, episodes: int, steps: int, seed: int, actions=None) -> dict:
    """Observations after each step, [episodes, steps, obs_dim] float32."""
    env, rng = make(task), np.random.default_rng(seed)
    out = []
    for ep in range(episodes):
        env.reset(seed=seed + ep)
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


def policy(task: str, weights: str, episodes: int, seed: int, deterministic: bool) -> dict:
    """Per-episode return, cost (cost steps) and goals reached of an exported expert."""
    env, rng = make(task), np.random.default_rng(seed)
    with np.load(weights) as z:
        act = _policy(dict(z), deterministic, rng)
    rets, costs, goals = [], [], []
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        ret = cost = goal = 0.0
        done = False
        while not done:
            obs, r, c, term, trunc, info = env.step(act(obs))
            ret, cost = ret + r, cost + float(c > 0)
            goal += float(info.get("goal_met", False))
            done = term or trunc
        rets.append(ret)
        costs.append(cost)
        goals.append(goal)
    return {"return": np.asarray(rets), "cost": np.asarray(costs), "goals": np.asarray(goals)}


def main() -> None:
    """Reads the request, writes the arrays."""
    request = json.loads(open(sys.argv[1]).read())
    cmd = request.pop("cmd")
    result = {"trace": trace, "policy": policy}[cmd](**request)
    np.savez(sys.argv[2], **result)


if __name__ == "__main__":
    main()
