"""OmniSafe's PPOLag on native Safety-Gymnasium for `benchmarks.expert_throughput`; runs inside
the `osrl` peer venv (OmniSafe 0.5.0, CPU torch).

    .peers/osrl/bin/python benchmarks/peers/omnisafe_ppolag.py REQUEST.json OUT.json

Request: `{"task": "CarGoal1", "steps": 4000, "envs": 1, "threads": 2}`. OmniSafe's default
PPOLag config except `total_steps = steps`, `steps_per_epoch = steps` (one epoch: one rollout of
`steps` env steps, then its update of 40 iterations over minibatches of 64), `vector_env_nums`,
`torch_threads`, and no logging to disk beyond OmniSafe's own run folder (under the system temp
directory). Writes `{"steps", "seconds", "rollout_s", "update_s"}`: wall seconds of
`agent.learn()` and OmniSafe's own split of them.
"""

import json
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    """Trains once and writes the timings."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import worker

    worker._allow_ndarray_dataclass_defaults()  # safety-gymnasium's configs on Python 3.11
    import omnisafe

    req = json.loads(Path(sys.argv[1]).read_text())
    steps = int(req["steps"])
    cfg = {"train_cfgs": {"total_steps": steps, "vector_env_nums": int(req["envs"]),
                          "torch_threads": int(req["threads"]), "device": "cpu"},
           "algo_cfgs": {"steps_per_epoch": steps},
           "logger_cfgs": {"use_wandb": False, "use_tensorboard": False,
                           "save_model_freq": 10**9,
                           "log_dir": tempfile.mkdtemp(prefix="omnisafe-")}}
    agent = omnisafe.Agent("PPOLag", f"Safety{req['task']}-v0", custom_cfgs=cfg)
    t = time.perf_counter()
    agent.learn()
    seconds = time.perf_counter() - t
    row = agent.agent._logger._current_row  # the last epoch's logged row
    stats = {k: float(row[k]) for k in ("Time/Rollout", "Time/Update")}
    Path(sys.argv[2]).write_text(json.dumps({
        "steps": steps, "seconds": seconds, "rollout_s": stats["Time/Rollout"],
        "update_s": stats["Time/Update"]}))


if __name__ == "__main__":
    main()
