"""A first look at a new machine (meant for a GPU): device, versions and the headline speeds.

Env steps/s of random-policy CarGoal2 episodes at batch 256 and 4096; CDT updates/s of the
`osrl` and `paper` presets at batch 2048; and the main job's deployment, CarGoal2 for 15 seeds x
50 episodes, zero-shot (no LoRA steps) and full Safe-CDT, each one compiled sweep call: its
first call (tracing and compiling included) and, with `--repeats`, warm calls. The CDT has
random weights (`benchmarks.deploy_throughput`): what a deployment costs does not depend on
what the weights are. On a GPU the whole check takes a few minutes; `--tiny` shrinks every size
so that it runs on a CPU in well under a minute (a smoke test, not a measurement).

    python -m benchmarks.gpu_check [--tiny] [--repeats 1] [--deploy-preset cpu] [--out PATH]

Writes `benchmarks/results/gpu_check.json` (or `--out`) and the markdown table beside it.
"""

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import jax

from benchmarks.common import (
    machine,
    markdown_table,
    median,
    time_call,
    write_json,
    write_markdown,
)
from safecdt_jax import envs
from safecdt_jax.deploy import DeployConfig, make_spec, make_variant, seed_keys, stack_specs, sweep
from safecdt_jax.envs.rollout import run_episode
from safecdt_jax.model import CDTConfig, init_cdt, with_nominal_edges

TASK = "CarGoal2"


@dataclass(frozen=True)
class Sizes:
    """What the check runs: env batches, CDT presets and batch, and the deployment's size.

    Attributes:
        env_batches: parallel random-policy episodes per env measurement.
        env_length: steps per episode (None: the task's 1,000).
        presets: CDT presets whose update is timed.
        train_batch: windows per CDT update.
        seeds, episodes: the deployment's seeds and episodes (the paper's 15 x 50).
        horizon: steps per deployment episode (None: the task's 1,000).
        lora_steps, lora_batch: LoRA steps per episode and their windows (DeployConfig's).
    """

    env_batches: tuple[int, ...] = (256, 4096)
    env_length: int | None = None
    presets: tuple[str, ...] = ("osrl", "paper")
    train_batch: int = 2048
    seeds: int = 15
    episodes: int = 50
    horizon: int | None = None
    lora_steps: int = 10
    lora_batch: int = 32


FULL = Sizes()
TINY = Sizes(env_batches=(8,), env_length=20, presets=("tiny",), train_batch=16, seeds=2,
             episodes=2, horizon=10, lora_steps=1, lora_batch=2)


def env_speed(batch: int, length: int | None, repeats: int) -> dict:
    """Median env steps/s of `batch` random-policy TASK episodes of `length` steps."""
    env, params = envs.make(TASK)
    fn = jax.jit(jax.vmap(lambda k: run_episode(env, params, k, length=length)))
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    first, runs = time_call(fn, keys, repeats=repeats)
    steps = batch * (length or env.episode_length)
    return {"what": f"env steps/s, batch {batch}", "value": steps / median(runs),
            "first_call_s": first}


def train_speed(preset: str, batch: int, repeats: int) -> dict:
    """Median CDT updates/s of `preset` at `batch` windows (`train_throughput.measure_train`)."""
    from benchmarks.train_throughput import measure_train

    row = measure_train(preset, "CarGoal", batch, repeats, work=batch)
    return {"what": f"CDT updates/s, {preset}, batch {batch}", "value": row["steps_per_s"],
            "first_call_s": row["compile_s"] + row["ms_per_step"] * row["chunk"] / 1e3}


def deploy_speed(variant: str, sizes: Sizes, preset: str, repeats: int) -> dict:
    """Wall seconds of one `sweep` call deploying `variant` for the sizes' seeds x episodes."""
    env, params = envs.make(TASK)
    model_cfg = with_nominal_edges(CDTConfig.preset(preset, env.observation_size,
                                                    env.action_size, env.episode_length))
    base = init_cdt(jax.random.PRNGKey(0), model_cfg)
    cfg = DeployConfig(episodes=sizes.episodes, horizon=sizes.horizon,
                       lora_steps=sizes.lora_steps, lora_batch=sizes.lora_batch)
    specs = stack_specs([make_spec(make_variant(variant, cfg), 30.0, 20.0)])
    keys = seed_keys(0, sizes.seeds)
    call = lambda: sweep(keys, base, params, specs, env=env, model_cfg=model_cfg, cfg=cfg)
    first, runs = time_call(call, repeats=repeats)
    wall = median(runs) if runs else first
    steps = sizes.seeds * sizes.episodes * (sizes.horizon or env.episode_length)
    return {"what": f"deploy {variant}, {sizes.seeds} seeds x {sizes.episodes} episodes, "
                    f"{preset} preset ({'warm' if runs else 'first call'}), s",
            "value": wall, "first_call_s": first, "env_steps_per_s": steps / wall}


def run_check(sizes: Sizes, repeats: int, deploy_preset: str) -> dict:
    """Every measurement of the check, with the machine; rows of {what, value, first_call_s}."""
    start = time.perf_counter()
    rows = [env_speed(b, sizes.env_length, max(repeats, 1)) for b in sizes.env_batches]
    rows += [train_speed(p, sizes.train_batch, max(repeats, 1)) for p in sizes.presets]
    rows += [deploy_speed(v, sizes, deploy_preset, repeats) for v in ("zero_shot", "safe_cdt")]
    return {"machine": machine(), "devices": [str(d) for d in jax.devices()],
            "sizes": sizes.__dict__, "rows": rows, "total_s": time.perf_counter() - start}


def main(argv: list[str] | None = None) -> dict:
    """Command line: run the check, print and write its table and JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiny", action="store_true", help="CPU-sized smoke run.")
    parser.add_argument("--repeats", type=int, default=1,
                        help="Warm calls per measurement after the first (0: first call only).")
    parser.add_argument("--deploy-preset", default=None,
                        help="CDT preset of the deployment (default cpu; tiny with --tiny).")
    parser.add_argument("--out", default="benchmarks/results/gpu_check.json")
    args = parser.parse_args(argv)
    if args.repeats < 0:
        parser.error("--repeats must be >= 0")
    sizes = TINY if args.tiny else FULL
    preset = args.deploy_preset or ("tiny" if args.tiny else "cpu")
    result = run_check(sizes, args.repeats, preset)
    m = result["machine"]
    table = markdown_table(["measurement", "value", "first call (s)"], [
        [r["what"], f"{r['value']:,.4g}", f"{r['first_call_s']:.1f}"] for r in result["rows"]])
    body = (f"{m['device']} ({len(result['devices'])} device(s)), jax {m['jax']}, mujoco "
            f"{m['mujoco']}, Python {m['python']}; total {result['total_s']:.0f} s.\n\n{table}")
    print(body)
    out = Path(args.out)
    write_json(out, result)
    command = "python -m benchmarks.gpu_check" + (" --tiny" if args.tiny else "")
    write_markdown(out.with_suffix(".md"), "GPU check", command, body)
    return result


if __name__ == "__main__":
    main()
