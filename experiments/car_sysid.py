"""Fit the Car's traction constants to native Safety-Gymnasium's own transitions under the
experts' actions (issue 48).

    python -m experiments.car_sysid [--data CarGoal1:25:64,CarCircle1:5:128] [--horizon 8]
        [--segments 800] [--rounds 12] [--bias-weight 0] [--lateral-weight 0]
        [--out experiments/results/car_sysid.json]

`experiments.car_fit` fits the Car to scripted drives (held actions, straight/spin switching,
turns and recoveries). The experts that make the data drive otherwise: the CarGoal1 expert's
mean action flips between full straight and full spin nearly every step, in both travel
directions. This fit asks the model for what those drives need: from native's state, under
native's next actions, the next steps.

Data: each `--data` TASK:LIMIT:EPISODES expert (`sim2sim.pick_expert`) in native
Safety-Gymnasium, mean and sampled actions, each step's observation and action recorded
(`benchmarks/peers/native.py` `policy` with `record`; cached, the same requests as
`experiments.drive_stats`). Segments: every `STRIDE` steps of every episode, `--segments` of them
drawn per expert and action mode; a segment starts from native's body velocity (velocimeter
x, y, m/s) and yaw rate (gyro z, rad/s), replays the next `--horizon` actions in our bare Car
(heading 0, at rest otherwise), and compares each step's body velocity and heading change
(rad; native's from its magnetometer) with native's. The heading change rather than the yaw
rate: native's chassis rattles on its contacts (its gyro z jumps by 0.6 rad/s step to step
under these drives), and where the car goes follows the heading.

Loss: the root-mean-square error per segment (velocities in m/s, heading changes x
`HEADING_WEIGHT`), averaged per expert and action mode, plus `--bias-weight` times the error of
the mean heading change (the curvature the expert's laps are made of) and `--lateral-weight`
times the error of the mean sideways velocity over every predicted step (m/s: where the car
pivots under these drives, which the experts read off the velocimeter), then averaged over
them. Search: the
cross-entropy method of `car_fit` over `car_fit.FIELDS`, `load_transfer_lead` and
`saturation_power` from the `CarRobot` defaults. Also reported: the fitted and current
constants' `car_fit` script loss over both travel directions (`--plus-y --lateral`'s targets),
which the fit never sees, and `pulse_response`: the heading change after a single spin pulse
by travel direction, the sharpness of the answer that the experts' driving is made of. Writes
JSON (in `car_fit`'s form, so `experiments.car_variants --fit NAME=PATH` runs the experts
under it) and markdown.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json, write_markdown
from experiments import car_fit
from experiments.drive_stats import GYRO_Z, VELOCIMETER, heading, native_recorded

STRIDE = 25  # steps between segment starts
HEADING_WEIGHT = 2.0  # the heading change (rad) against velocities (m/s) in the loss
SEARCHED = (*car_fit.FIELDS, "load_transfer_lead", "saturation_power")


def parse_data(text: str) -> list[tuple[str, float, int]]:
    """`TASK:LIMIT:EPISODES,...` -> [(task, limit, episodes)]; SystemExit naming a bad item."""
    out = []
    for item in filter(None, text.split(",")):
        parts = item.split(":")
        if len(parts) != 3 or not parts[0].startswith("Car"):
            raise SystemExit(f"--data: {item!r} is not CarTASK:LIMIT:EPISODES")
        out.append((parts[0], float(parts[1]), int(parts[2])))
    return out


def segments(obs: np.ndarray, actions: np.ndarray, horizon: int, stride: int = STRIDE):
    """Segments of recorded episodes (`obs` [E, T, D] before each action, `actions` [E, T, 2]):
    start states [n, 3] (body vx, vy in m/s, yaw rate rad/s at the start), the next `horizon`
    actions [n, horizon, 2] and the targets [n, horizon, 3] (body vx, vy after each action, and
    the heading change since the start, rad). Starts every `stride` steps from step 1."""
    psi = heading(obs)
    starts = np.arange(1, obs.shape[1] - horizon, stride)
    state = obs[:, starts][..., [VELOCIMETER, VELOCIMETER + 1, GYRO_Z]]
    acts = np.stack([actions[:, t:t + horizon] for t in starts], 1)
    vel = np.stack([obs[:, t + 1:t + horizon + 1, VELOCIMETER:VELOCIMETER + 2]
                    for t in starts], 1)
    turn = np.stack([psi[:, t + 1:t + horizon + 1] - psi[:, t:t + 1] for t in starts], 1)
    target = np.concatenate([vel, turn[..., None]], axis=-1)
    n = len(starts) * obs.shape[0]
    return (state.reshape(n, 3).astype(np.float32), acts.reshape(n, horizon, 2).astype(np.float32),
            target.reshape(n, horizon, 3).astype(np.float32))


@functools.cache
def _program(fields: tuple[str, ...]):
    """Jitted `(thetas [c, len(fields)], states [n, 3], actions [n, K, 2]) -> [c, n, K, 3]`:
    each candidate's bare Car from each start state under the actions, per step its body vx,
    vy and heading change."""
    import jax
    import jax.numpy as jnp
    from mujoco import mjx

    from safecdt_jax.envs.geometry import rot2
    from safecdt_jax.envs.robots import CAR
    from safecdt_jax.envs.types import EnvParams

    model, params = mjx.put_model(CAR.mj_model), EnvParams()

    def run(theta, state, acts):
        car = dataclasses.replace(CAR, **{f: theta[i] for i, f in enumerate(fields)})
        data = car.init_data(model, jnp.zeros(2), jnp.float32(0.0))
        data = data.replace(qvel=data.qvel.at[:3].set(state))

        def step(carry, action):
            data, robot_state = car.physics(model, carry[0], action, params, carry[1],
                                            jax.random.PRNGKey(0))  # the caster: no force
            v = rot2(data.qpos[2]).T @ data.qvel[:2]
            return (data, robot_state), jnp.stack([v[0], v[1], data.qpos[2]])

        return jax.lax.scan(step, (data, car.init_state()), acts)[1]

    per_segment = jax.vmap(run, in_axes=(None, 0, 0))
    return jax.jit(jax.vmap(per_segment, in_axes=(0, None, None)))


def prediction_loss(thetas: np.ndarray, fields: tuple[str, ...], data: list[tuple],
                    bias_weight: float = 0.0, lateral_weight: float = 0.0) -> np.ndarray:
    """Per candidate row of `thetas` and per dataset (start states, actions, targets) of
    `data`: the mean over segments of the weighted RMS prediction error, plus `bias_weight`
    times the error of the mean heading change at the horizon (rad): the RMS is ruled by each
    segment's scatter, while how tight a loop the expert drives is the mean), plus
    `lateral_weight` times the error of the mean sideways velocity over all predicted steps
    (m/s). [c, len(data)]."""
    return np.stack([_loss(np.asarray(_program(fields)(thetas.astype(np.float32), state, acts)),
                           target, bias_weight, lateral_weight)
                     for state, acts, target in data], axis=-1)


def _loss(pred: np.ndarray, target: np.ndarray, bias_weight: float,
          lateral_weight: float = 0.0) -> np.ndarray:
    """`prediction_loss` of one dataset's predictions [c, n, K, 3] against its targets."""
    err = (pred - target[None]) * np.array([1.0, 1.0, HEADING_WEIGHT], np.float32)
    bias = np.abs(pred[:, :, -1, 2].mean(-1) - target[:, -1, 2].mean())
    lateral = np.abs(pred[..., 0].mean((1, 2)) - target[..., 0].mean())
    return (np.sqrt(np.mean(err ** 2, axis=(2, 3))).mean(-1) + bias_weight * bias
            + lateral_weight * lateral)


PULSES = ("toward +y", "toward -y", "near rest")  # a spin pulse's travel direction


def pulse_response(state: np.ndarray, acts: np.ndarray, turn: np.ndarray) -> dict[str, float]:
    """The mean heading change (rad) `turn` [n] at the horizon after segments whose first
    action is a spin pulse (the executed torques opposite and near their limit), signed by the
    pulse's direction, per `PULSES` class of the start's body velocity (toward +y: vy > 0.1 m/s,
    toward -y: vy < -0.1, near rest otherwise): how sharply the car answers one pulse."""
    from safecdt_jax.envs.robots import CAR

    executed = np.clip(acts[:, 0], -CAR.torque_limit, CAR.torque_limit) / CAR.torque_limit
    spin = np.abs(executed[:, 0] - executed[:, 1]) > 1.5
    signed = turn * np.sign(executed[:, 0] - executed[:, 1])
    vy = state[:, 1]
    classes = {"toward +y": vy > 0.1, "toward -y": vy < -0.1, "near rest": np.abs(vy) <= 0.1}
    return {name: float(signed[spin & m].mean()) if (spin & m).sum() >= 10 else float("nan")
            for name, m in classes.items()}


def current_constants() -> np.ndarray:
    """The `CarRobot` defaults of `SEARCHED`."""
    from safecdt_jax.envs.robots import CAR

    return np.array([car_fit.default_value(f) for f in SEARCHED[:-1]] + [CAR.saturation_power])


def script_loss(theta: np.ndarray) -> float:
    """`car_fit`'s script loss over both travel directions with sideways velocities."""
    extra = ("load_transfer_lead",)
    metrics = car_fit.evaluate(theta[None, :-1], float(theta[-1]), "elliptic", True, extra,
                               True)[0]
    return car_fit.loss(metrics, car_fit.native_metrics(True, True))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="CarGoal1:25:64,CarCircle1:5:128")
    ap.add_argument("--horizon", type=int, default=8)
    ap.add_argument("--segments", type=int, default=800)
    ap.add_argument("--rounds", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bias-weight", type=float, default=0.0,
                    help="weight of the mean heading change's error (prediction_loss)")
    ap.add_argument("--lateral-weight", type=float, default=0.0,
                    help="weight of the mean sideways velocity's error (prediction_loss)")
    ap.add_argument("--out", type=Path, default=Path("experiments/results/car_sysid.json"))
    args = ap.parse_args(argv)
    if args.horizon < 1 or args.segments < 1:
        raise SystemExit("--horizon and --segments must be positive")
    rng = np.random.default_rng(args.seed)
    data, names = [], []
    for task, limit, episodes in parse_data(args.data):
        for mode, rec in native_recorded(task, limit, episodes).items():
            state, acts, target = segments(rec["obs"], rec["actions"], args.horizon)
            pick = rng.permutation(len(state))[:args.segments]
            data.append((state[pick], acts[pick], target[pick]))
            names.append(f"{task} limit {limit:g}, {mode}")
    bounds = car_fit.BOUNDS | car_fit.EXTRA_BOUNDS | {"saturation_power": (1.0, 20.0)}
    lo, hi = (np.array([bounds[f][i] for f in SEARCHED]) for i in (0, 1))
    start = current_constants()
    (best_loss, best), history = car_fit.cross_entropy(
        lambda th: prediction_loss(th, SEARCHED, data, args.bias_weight,
                                   args.lateral_weight).mean(-1), start, lo,
        hi, args.rounds, args.seed)
    losses, pulses, mean_turns, mean_sideways = [], [], [], []
    for name, (state, acts, target) in zip(names, data, strict=True):
        pred = np.asarray(_program(SEARCHED)(np.stack([start, best]).astype(np.float32), state,
                                             acts))
        losses.append(_loss(pred, target, args.bias_weight, args.lateral_weight))
        pulses.append({"data": name, "native": pulse_response(state, acts, target[:, -1, 2]),
                       "current": pulse_response(state, acts, pred[0, :, -1, 2]),
                       "fitted": pulse_response(state, acts, pred[1, :, -1, 2])})
        mean_turns.append({"data": name, "native": float(target[:, -1, 2].mean()),
                           "current": float(pred[0, :, -1, 2].mean()),
                           "fitted": float(pred[1, :, -1, 2].mean())})
        mean_sideways.append({"data": name, "native": float(target[..., 0].mean()),
                              "current": float(pred[0, ..., 0].mean()),
                              "fitted": float(pred[1, ..., 0].mean())})
    before, after = np.stack(losses, axis=-1)
    scripts = [script_loss(start), script_loss(best)]
    constants = dict(zip(SEARCHED, best.round(4).tolist(), strict=True))
    power = constants.pop("saturation_power")
    command = "python -m experiments.car_sysid " + " ".join(sys.argv[1:] if argv is None else argv)
    write_json(args.out, {"command": command, "machine": machine(), "cone": "elliptic",
                          "saturation_power": power, "constants": constants,
                          "loss": best_loss, "default_loss": float(before.mean()),
                          "history": history, "datasets": names,
                          "per_dataset": {"current": before.tolist(), "fitted": after.tolist()},
                          "script_loss": {"current": scripts[0], "fitted": scripts[1]},
                          "pulses": pulses,
                          "horizon": args.horizon, "segments": args.segments,
                          "bias_weight": args.bias_weight,
                          "lateral_weight": args.lateral_weight,
                          "mean_turn": mean_turns, "mean_sideways": mean_sideways})
    rows = [[name, f"{b:.4f}", f"{a:.4f}"] for name, b, a in zip(names, before, after,
                                                                   strict=True)]
    rows.append(["mean", f"{before.mean():.4f}", f"{best_loss:.4f}"])
    rows.append(["`car_fit` scripts, both directions (not fitted)", f"{scripts[0]:.4f}",
                 f"{scripts[1]:.4f}"])
    current = dict(zip(SEARCHED, start.round(4).tolist(), strict=True))
    fitted = constants | {"saturation_power": power}
    body = (f"Prediction loss ({args.horizon} steps from native's states under native's "
            f"actions, {args.segments} segments per row; velocities m/s, heading change x"
            f"{HEADING_WEIGHT:g} rad):\n\n"
            + markdown_table(["native expert transitions", "current", "fitted"], rows)
            + "\n\n" + markdown_table(["constant", "current", "fitted"],
                                      [[f, f"{current[f]:g}", f"{fitted[f]:g}"]
                                       for f in SEARCHED]))
    body += (f"\n\nHeading change (rad) {args.horizon} steps after a spin pulse, signed by "
             "the pulse, by the travel direction at its start (native / current / fitted):\n\n"
             + markdown_table(["native expert transitions", *PULSES], [
                 [r["data"], *(" / ".join(f"{r[side][c]:.3f}" for side in
                                          ("native", "current", "fitted")) for c in PULSES)]
                 for r in pulses]))
    body += (f"\n\nMean heading change (rad) {args.horizon} steps on, over all segments "
             "(native / current / fitted): " + "; ".join(
                 f"{m['data']} {m['native']:.4f} / {m['current']:.4f} / {m['fitted']:.4f}"
                 for m in mean_turns) + ".")
    body += ("\n\nMean sideways velocity (m/s) over every predicted step (native / current / "
             "fitted): " + "; ".join(
                 f"{m['data']} {m['native']:+.4f} / {m['current']:+.4f} / {m['fitted']:+.4f}"
                 for m in mean_sideways) + ".")
    write_markdown(args.out.with_suffix(".md"), "Car traction constants fitted to native "
                   "transitions under the experts' actions", command, body)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
