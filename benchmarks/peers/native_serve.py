"""Native Safety-Gymnasium envs stepped by a policy in another process; runs in the peer venv.

    .peers/safety-gymnasium/bin/python benchmarks/peers/native_serve.py TASK SEED N

Serves N native envs of TASK in lockstep over stdin/stdout, one JSON object per line, so that
a policy that needs this project (the CDT in JAX) acts in the native simulator. It resets env i
with seed SEED + i and answers the reset with `{"obs": [N, obs_dim]}`; then each request
`{"actions": [N, 2]}` steps every env that has not ended (the others keep their last
observation) and is answered with `{"obs", "reward" [N], "cost" [N] (0/1 per step), "terms"
{term: [N]} (cost steps of each term, `native.TERMS`), "done" [N]}`. EOF ends it.
"""

import json
import sys

import numpy as np
from native import TERMS, make


def main() -> None:
    """Serves the envs until stdin closes."""
    task, seed, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    envs = [make(task) for _ in range(n)]
    obs = [env.reset(seed=seed + i)[0] for i, env in enumerate(envs)]
    done = [False] * n
    print(json.dumps({"obs": np.asarray(obs).tolist()}), flush=True)
    for line in sys.stdin:
        actions = np.asarray(json.loads(line)["actions"], np.float64)
        reward, cost = np.zeros(n), np.zeros(n)
        terms = {k: [0.0] * n for k in TERMS}
        for i, env in enumerate(envs):
            if done[i]:
                continue
            obs[i], r, c, term, trunc, info = env.step(actions[i])
            reward[i], cost[i] = r, float(c > 0)
            for k in TERMS:
                terms[k][i] = float(info.get(k, 0.0) > 0)
            done[i] = bool(term or trunc)
        print(json.dumps({"obs": np.asarray(obs).tolist(), "reward": reward.tolist(),
                          "cost": cost.tolist(), "terms": terms, "done": done}), flush=True)


if __name__ == "__main__":
    main()
