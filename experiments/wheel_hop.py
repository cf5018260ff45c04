"""What one spin pulse does to native's Car, physics substep by substep (issue 48).

    python -m experiments.wheel_hop [--episodes 4] [--car FIELD=VALUE ...]
        [--out experiments/results/wheel_hop.json]

The Car experts turn in single spin pulses between straight steps, and under them native's car
yaws less right after a pulse and keeps more yaw after it than ours (`experiments.car_sysid`,
docs/research/environment-fidelity.md). Per lead speed (`LEADS`: a held drive from rest for
`LEAD_STEPS` env steps), one spin step (1, -1) and then straight steps (1, 1):
- native (the peer's `pulse` request, cached; `--episodes` layouts): after every 4 ms physics
  substep the normal loads (N) on both wheels and the caster, the yaw rate (rad/s), the forward
  speed (m/s), the chassis height (m) and its pitch and roll (rad). Reported: the yaw rate after
  the first substep and at the end of each env step, the substeps of the spin step and the
  next during which the reversed (right) wheel carries no load (and, as the reference, of the
  lead's last two env steps: native's wheels chatter on the floor even then), the peak normal
  load on it in the spin step, and the chassis' largest rise;
- ours (the same actions in our CarCircle1, qvel after each env step, `--car` constants on top
  of the `CarRobot` defaults): the yaw rate at the end of each env step.
Writes JSON and markdown.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json, write_markdown

# held drives before the pulse: native reaches 0.79 / 0.57 / 0.38 m/s
LEADS = {"fast": (1.0, 1.0), "mid": (0.016, 0.016), "slow": (0.011, 0.011)}
LEAD_STEPS = 100
PULSE = [(1.0, -1.0)] + [(1.0, 1.0)] * 3
BEFORE = 2  # the lead's last env steps, recorded too: the steady contacts to compare with
UNLOADED = 1e-3  # N: a wheel with less normal load is off the ground
COLUMNS = ("load_left", "load_right", "load_caster", "yaw_rate", "speed", "height", "pitch",
           "roll")


def native_pulse(lead: tuple[float, float], episodes: int) -> np.ndarray:
    """Native's `pulse` substeps [episodes, (BEFORE + len(PULSE)) * 10, len(COLUMNS)]: the
    lead's last `BEFORE` env steps, then `PULSE`."""
    from experiments.sim2sim import native

    return native({"cmd": "pulse", "task": "CarCircle1", "lead": list(lead),
                   "lead_steps": LEAD_STEPS - BEFORE,
                   "actions": [list(lead)] * BEFORE + [list(a) for a in PULSE],
                   "episodes": episodes, "seed": 0})["substeps"]


def ours_pulse(lead: tuple[float, float], fields: dict[str, float]) -> np.ndarray:
    """Our Car's forward speed before the pulse and its yaw rate (rad/s) at the end of each
    `PULSE` env step, [1 + len(PULSE)]."""
    import jax
    import jax.numpy as jnp

    from safecdt_jax import envs

    env, params = envs.make("CarCircle1")
    env = dataclasses.replace(env, robot=dataclasses.replace(env.robot, **fields))
    acts = jnp.asarray([lead] * LEAD_STEPS + PULSE, jnp.float32)

    def step(state, action):
        state = env.step(state, action, params)
        v = state.obs[4]  # velocimeter y: negative while driving toward body -y
        return state, jnp.stack([-v, state.data.qvel[2]])

    out = np.asarray(jax.jit(lambda a: jax.lax.scan(
        step, env.reset(jax.random.PRNGKey(0), params), a)[1])(acts))
    return np.concatenate([[out[LEAD_STEPS - 1, 0]], out[LEAD_STEPS:, 1]])


def summary(sub: np.ndarray, substeps: int = 10) -> dict:
    """The native pulse's numbers (see the module docstring) from `native_pulse` substeps;
    the unloaded substeps are counted over the spin step and the next (20 substeps) and, as the
    steady reference, over the lead's last `BEFORE` env steps."""
    col = {c: i for i, c in enumerate(COLUMNS)}
    lead, sub = sub[:, :BEFORE * substeps], sub[:, BEFORE * substeps:]
    mean = sub.mean(0)
    right = sub[..., col["load_right"]]
    return {"yaw_first_substep": float(mean[0, col["yaw_rate"]]),
            "yaw_step_end": mean[substeps - 1::substeps, col["yaw_rate"]].tolist(),
            "right_wheel_unloaded_substeps": float(
                (right[:, :2 * substeps] < UNLOADED).sum(1).mean()),
            "right_wheel_unloaded_substeps_before": float(
                (lead[..., col["load_right"]] < UNLOADED).sum(1).mean()),
            "right_wheel_peak_load": float(right[:, :substeps].max(1).mean()),
            "right_wheel_load_before": float(lead[..., col["load_right"]].mean()),
            "rise_mm": float(1000 * (mean[:, col["height"]].max()
                                     - lead[..., col["height"]].mean())),
            "speed_before": float(lead[:, -1, col["speed"]].mean())}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--car", action="append", default=[], metavar="FIELD=VALUE")
    ap.add_argument("--out", type=Path, default=Path("experiments/results/wheel_hop.json"))
    args = ap.parse_args(argv)
    fields = {}
    for item in args.car:
        name, _, value = item.partition("=")
        if not value:
            raise SystemExit(f"--car: {item!r} is not FIELD=VALUE")
        fields[name] = float(value)
    rows, out = [], {}
    for name, lead in LEADS.items():
        theirs = summary(native_pulse(lead, args.episodes))
        ours = ours_pulse(lead, fields)
        out[name] = {"native": theirs, "ours": {"speed_before": float(ours[0]),
                                                "yaw_step_end": ours[1:].tolist()}}
        rows.append([name, f"{theirs['speed_before']:.2f} / {ours[0]:.2f}",
                     f"{theirs['yaw_first_substep']:.2f}",
                     " / ".join(f"{x:.2f}" for x in theirs["yaw_step_end"]),
                     " / ".join(f"{x:.2f}" for x in ours[1:]),
                     f"{theirs['right_wheel_unloaded_substeps']:.1f} "
                     f"({theirs['right_wheel_unloaded_substeps_before']:.1f})",
                     f"{theirs['right_wheel_peak_load']:.2f} "
                     f"({theirs['right_wheel_load_before']:.2f})",
                     f"{theirs['rise_mm']:.1f}"])
    command = "python -m experiments.wheel_hop " + " ".join(sys.argv[1:] if argv is None else argv)
    write_json(args.out, {"command": command, "machine": machine(), "car": fields,
                          "episodes": args.episodes, "leads": out})
    body = ("One spin step (1, -1) after a held drive, then straight steps (1, 1); native: "
            f"mean of {args.episodes} layouts. Yaw rates in rad/s at the end of the spin step "
            "and of the next three; the right wheel is the reversed one.\n\n" + markdown_table(
                ["lead", "speed before (m/s), native / ours", "native yaw after 4 ms",
                 "native yaw, steps 1-4", "ours yaw, steps 1-4",
                 "native substeps with the right wheel off the ground, of the pulse step and "
                 "the next 20 (lead's last 20)",
                 "native peak load on the right wheel in the pulse step (lead's mean), N",
                 "native chassis rise (mm)"], rows))
    write_markdown(args.out.with_suffix(".md"), "One spin pulse, substep by substep", command,
                   body)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
