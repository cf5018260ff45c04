"""The peer benchmark in one command: this project against Safety-Gymnasium + OSRL.

Installs the peers into `.peers/` if missing (`benchmarks/peers/setup.py`), starts one worker
per peer environment, then measures the same work on both sides, alternating A B A B, at the
same thread count: (1) env steps/s, (2) CDT training step, (3) inference latency, (4) the
15-seed x 50-episode CarGoal2 deployment, (5) the FLOP floor. Writes BENCHMARKS.md and
benchmarks/results/peers.json (atomically). With a GPU, our side is measured there too and
added as separate tables (the peers stay on CPU).

    python -m benchmarks.run_all [--quick] [--skip-setup] [--threads 1] [--episodes 5]
    python -m benchmarks.run_all --render-only   # BENCHMARKS.md again from the saved JSON
"""

import argparse
import json
import os
import platform
import subprocess
import time
from pathlib import Path

import jax

from benchmarks.common import machine, pin_threads, stats, write_json
from benchmarks.peers import setup
from benchmarks.peers.page import render
from safecdt_jax.io import atomic_path
from safecdt_jax.presets import CPU_MICRO_BATCH

ROOT = Path(__file__).resolve().parents[1]
WORKER = Path(__file__).resolve().parent / "peers" / "worker.py"
TASKS = ("CarGoal1", "CarGoal2", "CarCircle2", "PointCircle2")
SIZES = {"CarGoal": (72, 2, 1000), "CarCircle": (40, 2, 500), "PointCircle": (28, 2, 500)}
DEPLOY_TASK, SEEDS, EPISODES, TARGET = "CarGoal2", 15, 50, (30.0, 20.0)  # OSRL's CarGoal2 first
# CPU seconds per wall second of every timed call, per side: the check that both sides really ran
# on the same number of threads (1.0 = one thread busy the whole time).
CPU_PER_WALL: dict[str, list[float]] = {"ours": [], "safety-gymnasium": [], "osrl": []}


class Peer:
    """A worker process in a peer environment; `peer(cmd, **args)` returns its answer."""

    def __init__(self, name: str, log: Path):
        self.name = name
        self.proc = subprocess.Popen([str(setup.venv_python(name)), str(WORKER)], text=True,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=log.open("a"), cwd=ROOT)

    def __call__(self, cmd: str, **args) -> dict:
        self.proc.stdin.write(json.dumps({"cmd": cmd, **args}) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"peer worker {self.name} died; see its log")
        answer = json.loads(line)
        if cmd not in ("versions", "flops"):
            CPU_PER_WALL[self.name].append(answer["cpu_per_wall"])
        if not answer.pop("ok"):
            raise RuntimeError(f"peer {self.name}, {cmd}: {answer['error']}")
        return answer

    def close(self) -> None:
        """Ends the worker (closing stdin ends its loop)."""
        self.proc.stdin.close()
        self.proc.wait(timeout=60)


def dims(task: str) -> dict:
    """obs_dim, act_dim, episode_len of a task, as the worker's model commands take them."""
    obs, act, horizon = SIZES[task.rstrip("0123456789")]
    return {"obs_dim": obs, "act_dim": act, "episode_len": horizon}


def alternate(peer_run, our_runs: dict, repeats: int) -> dict:
    """Runs peer, then each of ours, `repeats` times in that order (A B A B); raw answers."""
    out = {"peer": [], **{k: [] for k in our_runs}}
    for _ in range(repeats):
        out["peer"].append(peer_run())
        for k, run in our_runs.items():
            wall, cpu = time.perf_counter(), time.process_time()
            out[k].append(run())
            CPU_PER_WALL["ours"].append((time.process_time() - cpu) / (time.perf_counter() - wall))
    return out


def rates(answers: list[dict], work: str) -> list[float]:
    """Per-call rate: `work` units (env steps, updates, calls) per second."""
    return [a[work] / a["seconds"] for a in answers]


def pair_ratios(ours: list[float], peer: list[float]) -> dict:
    """Stats of the per-pair ratios ours / peer (pair i = the i-th call of each side)."""
    return stats([o / p for o, p in zip(ours, peer, strict=True)])


def compare_env(sg: Peer, ours, tasks, batches, repeats: int) -> list[dict]:
    """(1) Env steps/s with resets: one SG env and its sync vector env vs ours at each batch."""
    rows = []
    for task in tasks:
        steps = dims(task)["episode_len"]
        our_runs = {b: ours.make_env_steps(task, b) for b in batches}
        single = alternate(lambda t=task, s=steps: sg("env_steps", task=t, n_envs=0, steps=s),
                           {b: r for b, r in our_runs.items() if b != 15}, repeats)
        vector = alternate(lambda t=task, s=steps: sg("env_steps", task=t, n_envs=15, steps=s),
                           {b: r for b, r in our_runs.items() if b == 15}, repeats)
        row = {"task": task, "peer_single": stats(rates(single["peer"], "env_steps")),
               "peer_vector15": stats(rates(vector["peer"], "env_steps")), "ours": {}}
        for b in batches:
            runs, peer = (vector, vector["peer"]) if b == 15 else (single, single["peer"])
            r = rates(runs[b], "env_steps")
            ratio = pair_ratios(r, rates(peer, "env_steps"))
            row["ours"][str(b)] = {"rate": stats(r), "ratio": ratio}
        rows.append(row)
        print(f"env {task}: {json.dumps(row)}", flush=True)
    return rows


def compare_train(osrl: Peer, ours, batches, repeats: int,
                  micro_batch: int = CPU_MICRO_BATCH["osrl"]) -> list[dict]:
    """(2) One CDT update (`osrl` preset, CarGoal sizes): OSRL's train_one_step vs our chunk.

    A batch larger than `micro_batch` (default: the pass size the `osrl` preset pretrains with
    on a CPU) is also timed micro-batched (the gradient in passes of `micro_batch` windows,
    `PretrainConfig.micro_batch`), in the same alternation."""
    rows = []
    for batch in batches:
        steps = max(1, 512 // batch)  # about a second of work per call on either side
        runs = {"ours": ours.make_train("CarGoal1", batch, steps)}
        if batch > micro_batch:
            runs["micro"] = ours.make_train("CarGoal1", batch, steps, micro_batch)
        res = alternate(lambda b=batch, s=steps: osrl("train", batch=b, steps=s,
                                                      **dims("CarGoal1")), runs, repeats)
        ms = {k: [1e3 * a["seconds"] / a["steps"] for a in v] for k, v in res.items()}
        rows.append({"batch": batch, "steps_per_call": steps, "peer_ms": stats(ms["peer"]),
                     "ours_ms": stats(ms["ours"]), "speedup": pair_ratios(ms["peer"], ms["ours"])})
        if "micro" in ms:
            rows[-1].update(micro_batch=micro_batch, micro_ms=stats(ms["micro"]),
                            speedup_micro=pair_ratios(ms["peer"], ms["micro"]))
        print(f"train {batch}: {json.dumps(rows[-1])}", flush=True)
    return rows


def compare_infer(osrl: Peer, ours, batches, repeats: int) -> list[dict]:
    """(3) Per-step action latency on a full 10-step window, batch 1 and 15."""
    rows = []
    for batch in batches:
        calls = 200 if batch == 1 else 50
        runs = {"trimmed": ours.make_infer("CarGoal1", batch, calls, trimmed=True),
                "full": ours.make_infer("CarGoal1", batch, calls, trimmed=False)}
        res = alternate(lambda b=batch, c=calls: osrl("infer", batch=b, calls=c,
                                                      **dims("CarGoal1")), runs, repeats)
        ms = {k: [1e3 * a["seconds"] / a["calls"] for a in v] for k, v in res.items()}
        rows.append({"batch": batch, "calls": calls, **{f"{k}_ms": stats(v) for k, v in ms.items()},
                     "speedup_trimmed": pair_ratios(ms["peer"], ms["trimmed"]),
                     "speedup_full": pair_ratios(ms["peer"], ms["full"])})
        print(f"infer {batch}: {json.dumps(rows[-1])}", flush=True)
    return rows


def compare_deploy(osrl: Peer, ours, episodes: int, peer_episodes: int, repeats: int) -> dict:
    """(4) 15 seeds x 50 episodes of CarGoal2, extrapolated linearly from the episodes run.

    Peer: OSRL's evaluation loop, `peer_episodes` episodes of one seed per call; ours:
    `SEEDS x episodes` episodes per call, zero-shot (one vmapped call) and the full Safe-CDT
    sweep. Every time is scaled to the whole 15 x 50 deployment.
    """
    total = SEEDS * EPISODES
    runs = {"zero_shot": ours.make_zero_shot(DEPLOY_TASK, SEEDS, episodes, *TARGET),
            "safe_cdt": ours.make_safe_cdt(DEPLOY_TASK, SEEDS, episodes)}
    res = alternate(lambda: osrl("deploy", task=DEPLOY_TASK, seeds=1, episodes=peer_episodes,
                                 target_return=TARGET[0], target_cost=TARGET[1],
                                 **dims(DEPLOY_TASK)), runs, repeats)
    whole = {k: [a["seconds"] * total / a["episodes"] for a in v] for k, v in res.items()}
    out = {"seeds": SEEDS, "episodes": EPISODES, "ours_episodes_run": episodes,
           "peer_episodes_run": peer_episodes, "raw": res,
           "whole_s": {k: stats(v) for k, v in whole.items()},
           "peer_env_fraction": stats([a["env_seconds"] / a["seconds"] for a in res["peer"]]),
           "speedup": {k: pair_ratios(whole["peer"], whole[k]) for k in runs}}
    print(f"deploy: {json.dumps({k: v for k, v in out.items() if k != 'raw'})}", flush=True)
    return out


def floor(osrl: Peer, ours, deploy: dict, infer: list[dict], repeats: int) -> dict:
    """(5) FLOPs per deployment step against this CPU's measured float32 matmul rate."""
    from benchmarks.peers import flops

    res = alternate(lambda: osrl("gemm", n=1024, calls=20), {"ours": ours.make_gemm(1024, 20)},
                    repeats)
    gemm = {k: stats([r / 1e9 for r in rates(v, "flops")]) for k, v in res.items()}  # GFLOP/s
    peak = 1e9 * max(g["median"] for g in gemm.values())  # FLOP/s
    cfg = ours.model_config(DEPLOY_TASK)
    horizon = cfg.episode_len
    step = {"peer": flops.rollout_step_flops(cfg, horizon, trimmed=False),
            "zero_shot": flops.rollout_step_flops(cfg, horizon, trimmed=True)}
    step["safe_cdt"] = step["zero_shot"] + flops.lora_flops_per_step(cfg, horizon, 10, 32)
    steps_total = SEEDS * EPISODES * horizon
    sides = {k: {"flops_per_step": f, "floor_s": f * steps_total / peak,
                 "measured_s": deploy["whole_s"][k]["median"]} for k, f in step.items()}
    for s in sides.values():
        s["fraction_of_peak"] = s["floor_s"] / s["measured_s"]
    models = []
    for row in infer:
        b = row["batch"]
        for side, n, trimmed in (("peer", "peer_ms", False), ("ours full", "full_ms", False),
                                 ("ours trimmed", "trimmed_ms", True)):
            f = flops.forward_flops(cfg, b, cfg.seq_len, 1 if trimmed else None)
            models.append({"side": side, "batch": b, "flops": f, "ms": row[n]["median"],
                           "gflops": f / row[n]["median"] / 1e6,
                           "fraction_of_peak": f / (row[n]["median"] / 1e3) / peak})
    cross = {"analytic_full": flops.forward_flops(cfg, 1, cfg.seq_len),
             "analytic_trimmed": flops.forward_flops(cfg, 1, cfg.seq_len, 1),
             "xla_full": ours.compiled_flops(DEPLOY_TASK, 1, trimmed=False),
             "xla_trimmed": ours.compiled_flops(DEPLOY_TASK, 1, trimmed=True),
             "torch_counter_full": osrl("flops", context=cfg.seq_len, **dims(DEPLOY_TASK))["flops"]}
    out = {"gemm": gemm, "peak": peak, "deploy": sides, "models": models, "cross_check": cross}
    print(f"floor: {json.dumps(out)}", flush=True)
    return out


def run_side(device, args, sg: Peer | None, osrl: Peer | None) -> dict:
    """Every comparison with our side on `device` (arrays and programs placed there)."""
    from benchmarks.peers import ours

    tasks = TASKS[::3] if args.quick else TASKS  # quick: CarGoal1 and PointCircle2
    long_reps = 1 if args.quick else args.long_repeats
    reps = 2 if args.quick else args.repeats
    episodes = 1 if args.quick else args.episodes
    out = {"device": str(device), "platform": device.platform}
    with jax.default_device(device):
        out["env"] = compare_env(sg, ours, tasks, (1, 15, 256), long_reps)
        out["train"] = compare_train(osrl, ours, (64, 256, 2048), reps)
        out["infer"] = compare_infer(osrl, ours, (1, 15), reps)
        out["deploy"] = compare_deploy(osrl, ours, episodes, 1 if args.quick else 2, long_reps)
        out["floor"] = floor(osrl, ours, out["deploy"], out["infer"], reps)
    return out


def facts(peer_setup: list[dict], workers: dict, threads: int, started: float) -> dict:
    """Machine, versions, thread setting and load, for the report's header."""
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text()
                .splitlines() if line.startswith("model name")), platform.processor())
    return {"machine": {**machine(), "cpu_model": cpu}, "threads": threads,
            "xla_flags": os.environ.get("XLA_FLAGS", ""), "peer_setup": peer_setup,
            "peer_versions": {k: w("versions") for k, w in workers.items()},
            "loadavg_end": os.getloadavg(), "minutes": (time.perf_counter() - started) / 60,
            "cores": sorted(os.sched_getaffinity(0)),
            "cpu_per_wall": {k: stats(v) for k, v in CPU_PER_WALL.items() if v}}


def main() -> None:
    """Sets up the peers, runs every comparison, writes BENCHMARKS.md and the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 tasks, 1 episode, fewer repeats")
    ap.add_argument("--skip-setup", action="store_true", help="use the .peers/ envs as they are")
    ap.add_argument("--threads", type=int, default=1, help="compute threads per side")
    ap.add_argument("--repeats", type=int, default=5, help="pairs for the short measurements")
    ap.add_argument("--long-repeats", type=int, default=2,
                    help="pairs for env steps and the deployment (long calls)")
    ap.add_argument("--episodes", type=int, default=5,
                    help="episodes per seed our deployment calls run (50 = the whole thing)")
    ap.add_argument("--out", default=str(ROOT / "BENCHMARKS.md"))
    ap.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "peers.json"))
    ap.add_argument("--render-only", action="store_true",
                    help="rewrite the markdown from the JSON of an earlier run, measure nothing")
    args = ap.parse_args()
    if args.render_only:
        write_markdown(json.loads(Path(args.json).read_text()), args.out)
        return
    pin_threads(args.threads)  # before JAX creates its CPU client; workers inherit it
    started = time.perf_counter()
    load_start = os.getloadavg()
    peer_setup = ([] if args.skip_setup else setup.ensure_all())
    setup.ROOT.mkdir(exist_ok=True)
    setup.ROOT.mkdir(exist_ok=True)
    log = setup.ROOT / "workers.log"  # what the peers print (git-ignored)
    log.write_text("")
    workers = {"safety-gymnasium": Peer("safety-gymnasium", log), "osrl": Peer("osrl", log)}
    try:
        sides = [run_side(jax.devices("cpu")[0], args, workers["safety-gymnasium"],
                          workers["osrl"])]
        accelerators = [d for d in jax.devices() if d.platform != "cpu"]
        if accelerators:  # ours on the accelerator, against the same CPU-bound peers
            sides.append(run_side(accelerators[0], args, workers["safety-gymnasium"],
                                  workers["osrl"]))
        payload = {**facts(peer_setup, workers, args.threads, started),
                   "loadavg_start": load_start, "args": vars(args), "sides": sides}
    finally:
        for w in workers.values():
            w.close()
    write_json(args.json, payload)
    write_markdown(json.loads(json.dumps(payload)), args.out)  # as read back: string keys


def write_markdown(payload: dict, out: str) -> None:
    """Renders the report and replaces `out` atomically."""
    with atomic_path(out, suffix=".md") as tmp:
        Path(tmp).write_text(render(payload))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
