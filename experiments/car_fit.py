"""Fit the Car's traction constants to native Safety-Gymnasium's turning and speed-up (issue 48).

    python -m experiments.car_fit [--saturation-power 2] [--rounds 25]
        [--start FIELD=VALUE ...] [--out PATH]

Targets, native CarCircle1 (`experiments.sim2sim.native`, cached): the mean forward speed
(m/s) and yaw rate (rad/s) over steps 100-500 of each `sim2sim.TURNS` script, of two held
drives below the torque limit and of uniform random actions (the forward drift that
`tests/test_envs_physics.py` pins; 4 layouts), and
the forward speed over the 10 steps after a start from rest and the 12 after a 45-step spin
(`car_slide.SWITCHES`, 8 layouts): how fast the car regains speed decides how far a spin pulse
carries it. Ours: the bare Car from rest (the floor is flat, so one run per script), every
candidate of a round in one vmapped program. Search: the cross-entropy method over the logs of
`FIELDS` (48 candidates a round, the 10 best refit the sampler), from the `CarRobot` defaults
or the `--start` values, with `saturation_power` held at its flag or searched too
(`--fit-power`); a local search: a second run from the first one's result can still improve.
Loss: the root-mean-square error over all those numbers, the switching scripts' yaw rates
weighted `SWITCH_WEIGHT` times (the turning that brings a Circle expert's car back inside) and
the low-torque speeds `LOW_WEIGHT` times; the random-action row is reported but not fitted
unless `--random-weight W` > 0 weights its speed (fitting it costs the Circle:
docs/research/environment-fidelity.md). Writes JSON and markdown (default
`experiments/results/car_fit.{json,md}`).

`--plus-y` adds the other travel direction: every turning script negated (positive torques
drive toward body -y, where the targets above all drive; an expert may prefer +y, as the
CarGoal1 one does) and `drive_stats.recovery_scripts`' four turns and recoveries (onset peak,
turn and leftover yaw rates, regained speed), native over 8 layouts. `--cone pyramidal` fits
`CarRobot.friction_cone = "pyramidal"`, whose forces depend on the heading: ours then runs
every script from each of `HEADINGS` and averages, as native's layouts average over theirs.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json, write_markdown

FIELDS = ("sliding", "load_transfer", "slip_gain", "side_gain", "caster_gain", "caster_sliding",
          "yaw_scrub")
BOUNDS = {"sliding": (0.4, 1.2), "load_transfer": (0.0, 0.8), "slip_gain": (0.08, 1.5),
          "side_gain": (0.2, 5.0), "caster_gain": (0.1, 1.0), "caster_sliding": (0.3, 1.2),
          "yaw_scrub": (0.0, 0.02)}
# Physics 5's constants (a clipped friction circle), the table's reference column.
PHYSICS_5 = {"sliding": 0.78, "load_transfer": 0.45, "slip_gain": 0.25, "side_gain": 0.557,
             "caster_gain": 0.3, "caster_sliding": 0.65, "yaw_scrub": 0.005}
STEPS = 500  # per turning script, as `sim2sim.turning`
# Held drives below the torque limit (0.02): the rolling regime a clone's mean action can
# reach and where the shifted gears and masses drive.
LOW_TORQUES = (0.01, 0.005)
SWITCH_WEIGHT = 3.0
LOW_WEIGHT = 3.0  # the held low-torque drives' speeds: two numbers stand for a whole regime
LOW_KEYS = frozenset(f"({level}, {level})" for level in LOW_TORQUES)
HEADINGS = (0.35, 1.05)  # rad: our starting yaws when the cone is pyramidal (20 and 60 deg)
PLUS_Y = " toward +y"
LATERAL = ", sideways"  # the key suffix of a script's mean sideways velocity (`metrics`)
# Native's wheels hold the axle almost still sideways while the car turns (0.004 m/s in a
# (1, 0.01) arc, where physics 7's slips at 0.026): the sideways velocities are small numbers
# beside speeds and yaw rates, so they weigh this much in the loss.
LATERAL_WEIGHT = 3.0
# CarRobot fields `--fit-field` may add to the search, with their bounds.
EXTRA_BOUNDS = {"load_transfer_lead": (0.0, 2.0)}


@functools.cache
def scripts(plus_y: bool = False) -> tuple[tuple[str, np.ndarray], ...]:
    """`sim2sim.turning`'s action scripts [STEPS, 2], the `LOW_TORQUES` held on both wheels,
    with `plus_y` every turning script negated (named `PLUS_Y`) and the recovery scripts
    (padded with their last action), then uniform random actions in [-1, 1]^2 (their own
    generator, seed 1). Cached: every candidate's `metrics` reads their names."""
    from experiments.drive_stats import recovery_scripts
    from experiments.sim2sim import turn_scripts

    turns = [(name, acts.astype(np.float32)) for name, acts in turn_scripts(STEPS)]
    out = list(turns)
    for level in LOW_TORQUES:
        out.append((f"({level}, {level})", np.full((STEPS, 2), level, np.float32)))
    if plus_y:
        out += [(name + PLUS_Y, -acts) for name, acts in turns]
        out += [(f"recovery: {name}", np.pad(acts, ((0, STEPS - len(acts)), (0, 0)),
                                             mode="edge").astype(np.float32))
                for name, acts in recovery_scripts()]
    uniform = np.random.default_rng(1).uniform(-1.0, 1.0, (STEPS, 2))
    return (*out, ("random", uniform.astype(np.float32)))


def metrics(speed: np.ndarray, yaw: np.ndarray, plus_y: bool = False,
            lateral: np.ndarray | None = None) -> dict[str, list[float]]:
    """Per script [n_scripts + 1, STEPS] of forward speed and yaw rate (the last row: the
    `SWITCHES` script): the turning table's means and the two speed-up curves; a recovery
    script's onset peak, turn and leftover yaw rates (signed by the turn) and regained speed
    (`drive_stats.recovery`). With `lateral` (the body-frame sideways velocity at the chassis
    origin, m/s, as the velocimeter's x), also each held or switching script's mean sideways
    velocity over steps 100-500 under `name + LATERAL`: where the car pivots while it turns."""
    names = [name for name, _ in scripts(plus_y)]
    out = {}
    for i, name in enumerate(names):
        if name.startswith("recovery: "):
            y = np.sign(yaw[i, 120:130].mean()) * yaw[i]
            out[name] = [float(y[100:110].max()), float(y[120:130].mean()),
                         float(y[135:195].mean()), float(np.abs(speed[i, 130:160]).mean())]
        else:
            out[name] = [float(speed[i, 100:].mean()), float(yaw[i, 100:].mean())]
            if lateral is not None and name != "random":
                out[name + LATERAL] = [float(lateral[i, 100:].mean())]
    out["random"][1] = float(np.abs(yaw[names.index("random"), 100:]).mean())  # mean |yaw|
    out["from rest"] = speed[-1, 2:12].tolist()
    out["after a spin"] = speed[-1, 60:72].tolist()
    return out


def loss(ours: dict, native: dict, random_weight: float = 0.0) -> float:
    """Root-mean-square error over every number of `metrics` in `native`, switching yaw rates,
    low-torque speeds and sideways velocities weighted; the random-action row's speed weighted
    `random_weight`, its yaw not at all."""
    err = []
    for key, value in native.items():
        w = np.ones(len(value))
        if key.endswith(LATERAL):
            w = np.array([LATERAL_WEIGHT])
        elif key.startswith("switching"):
            w[1] = SWITCH_WEIGHT
        if key in LOW_KEYS:
            w[0] = LOW_WEIGHT
        if key == "random":
            w = np.array([random_weight, 0.0])
        err.extend(w * (np.asarray(ours[key]) - np.asarray(value)))
    return float(np.sqrt(np.mean(np.square(err))))


@functools.cache
def native_metrics(plus_y: bool = False, lateral: bool = False) -> dict[str, list[float]]:
    """`metrics` of native Safety-Gymnasium's car (CarCircle1, cached native traces); read
    it, do not change it (one dict per process). The original scripts over 4 layouts, the
    `plus_y` ones over 8 (native's car drifts with its heading there); with `lateral`, the
    sideways velocities too."""
    from experiments.car_slide import SWITCHES
    from experiments.sim2sim import native

    rows = []
    original = {name for name, _ in scripts()}
    runs = [(4 if n in original else 8, a.tolist()) for n, a in scripts(plus_y)]
    for episodes, acts in [*runs, (8, SWITCHES)]:
        obs = native({"cmd": "trace", "task": "CarCircle1", "episodes": episodes,
                      "steps": len(acts), "seed": 0, "actions": acts})["obs"]
        rows.append(np.pad(obs.mean(0), ((0, STEPS - len(acts)), (0, 0))))
    obs = np.stack(rows)
    return metrics(-obs[..., 4], obs[..., 8], plus_y, obs[..., 3] if lateral else None)


@functools.cache
def _program(power: float | None, cone: str = "elliptic", plus_y: bool = False,
             extra: tuple[str, ...] = ()):
    """Jitted `thetas [n, len(FIELDS) + len(extra) (+ 1)] -> (speed, yaw, sideways)
    [n, scripts + 1, STEPS]`: our bare Car from rest under every script, one candidate set of
    `FIELDS` and then the `extra` fields per row (and its `saturation_power` in a last column
    when `power` is None), friction cone `cone`; a pyramidal cone's runs start from each of
    `HEADINGS` and are averaged."""
    import jax
    import jax.numpy as jnp
    from mujoco import mjx

    from experiments.car_slide import SWITCHES
    from safecdt_jax.envs.geometry import rot2
    from safecdt_jax.envs.robots import CAR
    from safecdt_jax.envs.types import EnvParams

    model, params = mjx.put_model(CAR.mj_model), EnvParams()
    switches = np.pad(np.asarray(SWITCHES, np.float32), ((0, STEPS - len(SWITCHES)), (0, 0)))
    acts = jnp.asarray(np.stack([*(a for _, a in scripts(plus_y)), switches]))
    headings = jnp.asarray(HEADINGS if cone == "pyramidal" else (0.0,), jnp.float32)

    def run(theta, script, heading):
        car = dataclasses.replace(CAR, saturation_power=theta[-1] if power is None else power,
                                  friction_cone=cone,
                                  **{f: theta[i] for i, f in enumerate((*FIELDS, *extra))})

        def step(carry, action):
            data, state = car.physics(model, carry[0], action, params, carry[1],
                                        jax.random.PRNGKey(0))  # the caster's draw: no force
            v = rot2(data.qpos[2]).T @ data.qvel[:2]
            return (data, state), jnp.stack([-v[1], data.qvel[2], v[0]])

        start = (car.init_data(model, jnp.zeros(2), heading), car.init_state())
        return jax.lax.scan(step, start, script)[1]

    def candidate(theta):
        per_heading = jax.vmap(lambda h: jax.vmap(lambda s: run(theta, s, h))(acts))(headings)
        return per_heading.mean(0)

    return jax.jit(jax.vmap(candidate))


def evaluate(thetas: np.ndarray, power: float | None, cone: str = "elliptic",
             plus_y: bool = False, extra: tuple[str, ...] = (),
             lateral: bool = False) -> list[dict]:
    """`metrics` of each candidate row of `thetas` [n, len(FIELDS) + len(extra)] (power None:
    one more column, each row's `saturation_power`) under friction cone `cone`; with `lateral`,
    the sideways velocities too."""
    out = np.asarray(_program(power, cone, plus_y, extra)(thetas.astype(np.float32)))
    return [metrics(o[..., 0], o[..., 1], plus_y, o[..., 2] if lateral else None) for o in out]


def cross_entropy(objective, start: np.ndarray, lo: np.ndarray, hi: np.ndarray, rounds: int,
                  seed: int = 0, size: int = 48, elite: int = 10):
    """Minimises `objective(thetas [size, d]) -> losses [size]` over positive parameters in
    [lo, hi] by the cross-entropy method on their logs: from `start` (std 0.3 in log units),
    each round samples `size` candidates (the first: the sampler's mean), refits the sampler to
    the `elite` best. Returns ((best loss, best theta), the best loss after each round)."""
    rng = np.random.default_rng(seed)
    mean, std = np.log(start), np.full(len(start), 0.3)
    best, history = (np.inf, start), []
    for _ in range(rounds):
        thetas = np.clip(np.exp(mean + std * rng.standard_normal((size, len(start)))), lo, hi)
        thetas[0] = np.exp(mean)
        losses = objective(thetas)
        top = np.log(thetas[np.argsort(losses)[:elite]])
        mean, std = top.mean(0), np.maximum(top.std(0), 0.03)
        if losses.min() < best[0]:
            best = (float(losses.min()), thetas[np.argmin(losses)])
        history.append(best[0])
    return best, history


def default_value(field: str) -> float:
    """`CAR`'s value of a fitted field; an unset `load_transfer_lead` is `load_transfer`'s (the
    same physics)."""
    from safecdt_jax.envs.robots import CAR

    value = getattr(CAR, field)
    return CAR.load_transfer if value is None and field == "load_transfer_lead" else value


def fit(power: float | None, rounds: int, start: dict[str, float] | None = None,
        random_weight: float = 0.0, seed: int = 0, size: int = 48, elite: int = 10,
        cone: str = "elliptic", plus_y: bool = False, extra: tuple[str, ...] = (),
        lateral: bool = False):
    """Cross-entropy search from the `CarRobot` defaults updated by `start` (power None: the
    `saturation_power` is searched too; `extra`: more fields searched, from `EXTRA_BOUNDS`;
    `lateral`: the sideways velocities are fitted too); returns (best constants, its loss, the
    defaults' loss, the best loss after each round)."""
    from safecdt_jax.envs.robots import CAR

    fields = (*FIELDS, *extra)
    names = fields if power is not None else (*fields, "saturation_power")
    bounds = BOUNDS | EXTRA_BOUNDS | {"saturation_power": (1.0, 20.0)}
    target = native_metrics(plus_y, lateral)
    defaults = np.array([default_value(f) for f in fields])
    # a searched power starts from the defaults' own, or from 2 where they clip (n = 0)
    start = {"saturation_power": CAR.saturation_power or 2.0} | (start or {})
    start = np.array([start.get(f, default_value(f)) for f in names])
    lo, hi = (np.array([bounds[f][i] for f in names]) for i in (0, 1))

    def objective(thetas):
        return np.array([loss(m, target, random_weight)
                         for m in evaluate(thetas, power, cone, plus_y, extra, lateral)])

    best, history = cross_entropy(objective, start, lo, hi, rounds, seed, size, elite)
    default = loss(evaluate(defaults[None], CAR.saturation_power, CAR.friction_cone, plus_y,
                            extra, lateral)[0], target, random_weight)
    return dict(zip(names, best[1].round(4).tolist(), strict=True)), best[0], default, history


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--saturation-power", type=float, default=2.0)
    ap.add_argument("--fit-power", action="store_true",
                    help="search saturation_power too (from --saturation-power)")
    ap.add_argument("--rounds", type=int, default=25)
    ap.add_argument("--random-weight", type=float, default=0.0)
    ap.add_argument("--start", action="append", default=[], metavar="FIELD=VALUE",
                    help="a starting value of one of FIELDS (repeatable)")
    ap.add_argument("--cone", choices=("elliptic", "pyramidal"), default="elliptic",
                    help="the fitted Car's CarRobot.friction_cone")
    ap.add_argument("--plus-y", action="store_true",
                    help="add the scripts driving toward +y and the turn recoveries")
    ap.add_argument("--fit-field", action="append", default=[], choices=sorted(EXTRA_BOUNDS),
                    help="search this CarRobot field too (repeatable)")
    ap.add_argument("--lateral", action="store_true",
                    help="fit the scripts' sideways velocities too (LATERAL_WEIGHT)")
    ap.add_argument("--out", type=Path, default=Path("experiments/results/car_fit.json"))
    args = ap.parse_args(argv)
    from safecdt_jax.envs.robots import CAR

    extra, lateral = tuple(args.fit_field), args.lateral
    fields = (*FIELDS, *extra)
    start = {k: float(v) for k, v in (c.split("=", 1) for c in args.start)}
    unknown = sorted(set(start) - {*fields, "saturation_power"})
    if unknown:
        raise SystemExit(f"--start: unknown field(s) {', '.join(unknown)}; valid: "
                         f"{', '.join(fields)}, saturation_power")
    if args.fit_power:
        start.setdefault("saturation_power", args.saturation_power)
    power = None if args.fit_power else args.saturation_power
    cone, plus_y = args.cone, args.plus_y
    best, best_loss, default_loss, history = fit(power, args.rounds, start, args.random_weight,
                                                 cone=cone, plus_y=plus_y, extra=extra,
                                                 lateral=lateral)
    power = best.get("saturation_power", args.saturation_power)
    target = native_metrics(plus_y, lateral)
    # physics 5 had no leading-axle transfer: its load_transfer both ways
    physics_5 = evaluate(np.array([[PHYSICS_5.get(f, PHYSICS_5["load_transfer"])
                                    for f in fields]]), 0.0, "elliptic", plus_y, extra,
                         lateral)[0]
    before = evaluate(np.array([[default_value(f) for f in fields]]), CAR.saturation_power,
                      CAR.friction_cone, plus_y, extra, lateral)[0]
    after = evaluate(np.array([[best[f] for f in fields]]), power, cone, plus_y, extra,
                     lateral)[0]
    command = "python -m experiments.car_fit " + " ".join(sys.argv[1:] if argv is None else argv)
    write_json(args.out, {"command": command, "machine": machine(),
                          "saturation_power": power, "start": start, "cone": cone,
                          "plus_y": plus_y, "lateral": lateral,
                          "random_weight": args.random_weight,
                          "constants": best,
                          "loss": best_loss, "default_loss": default_loss, "history": history,
                          "native": target, "physics_5": physics_5, "defaults": before,
                          "after": after})
    f2 = lambda xs: ", ".join(f"{x:.2f}" for x in xs)
    rows = [[k, f2(physics_5[k]), f2(before[k]), f2(after[k]), f2(target[k])] for k in target]
    body = (f"Loss (RMS, switching yaw x{SWITCH_WEIGHT:g}, low torque x{LOW_WEIGHT:g}, "
            + (f"sideways velocities x{LATERAL_WEIGHT:g}, " if lateral else "") +
            f"random drift x{args.random_weight:g}): physics 5 "
            f"{loss(physics_5, target, args.random_weight):.4f}, the defaults {default_loss:.4f}, "
            f"fitted {best_loss:.4f}.\n\nFitted constants ({cone} cone, saturation_power "
            f"{power:g}): " + ", ".join(f"`{k}={v:g}`" for k, v in best.items())
            + "\n\n" + markdown_table(["script (speed m/s, yaw rad/s)", "physics 5",
                                       "defaults", "fitted", "native"], rows))
    write_markdown(args.out.with_suffix(".md"), "Car traction constants fitted to native "
                   "turning and speed-up", command, body)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
