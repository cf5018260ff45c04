"""Shifted-dynamics targets as data: parse `--dynamics` strings into `EnvParams` shifts.

    shifts = parse_dynamics("friction_scale=1.0:0.5,gear_scale=0.8")
    # [{'friction_scale': 1.0, 'gear_scale': 0.8}, {'friction_scale': 0.5, 'gear_scale': 0.8}]
    params = stack_params([apply_dynamics(base, s) for s in shifts])  # leading axis: the shifts

A field with several values (`a:b:c`) is an axis; several such fields make a grid (their
product, the first field varying slowest). The shifted params feed one compiled program: the
scales are traced arrays, not static structure (`EnvParams`).
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp

from safecdt_jax.envs.types import EnvParams

# What each scale multiplies (docs/ENVIRONMENTS.md, "Shifted dynamics", has measured examples).
DYNAMICS_FIELDS: dict[str, str] = {
    "friction_scale": "tyre-floor friction: the Car's traction and side-grip caps, vase sliding",
    "gear_scale": "every actuator's gear: Point thrust and yaw servo, Car wheel torque",
    "damping_scale": "joint damping: Point joints, Car wheel damping and caster and scrub losses",
    "mass_scale": "the robot's mass and rotational inertia",
}


def parse_dynamics(text: str | None) -> list[dict[str, float]]:
    """The shifts a `--dynamics` string asks for: one dict {field: scale} per grid point.

    `None` or an empty string is one unshifted target (`[{}]`). Raises a one-line ValueError
    for an unknown field (naming the valid ones), a repeated field, a malformed item or value,
    and a scale that is not positive and finite.
    """
    if text is None or not text.strip():
        return [{}]
    axes: dict[str, list[float]] = {}
    for item in text.split(","):
        name, sep, values = item.strip().partition("=")
        name = name.strip()
        if not sep or not name or not values.strip():
            raise ValueError(f"bad --dynamics item {item.strip()!r}: expected FIELD=VALUE or "
                             f"FIELD=V1:V2:...; fields: {', '.join(DYNAMICS_FIELDS)}")
        if name not in DYNAMICS_FIELDS:
            raise ValueError(f"unknown dynamics field {name!r}; valid: "
                             f"{', '.join(DYNAMICS_FIELDS)}")
        if name in axes:
            raise ValueError(f"dynamics field {name!r} given twice")
        axes[name] = [_scale(name, v) for v in values.split(":")]
    return [dict(zip(axes, combo, strict=True)) for combo in itertools.product(*axes.values())]


def _scale(name: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"dynamics field {name!r}: {text.strip()!r} is not a number") from None
    if not 0.0 < value < float("inf"):
        raise ValueError(f"dynamics field {name!r} must be a positive scale, got {value:g}")
    return value


def apply_dynamics(params: EnvParams, shift: dict[str, float]) -> EnvParams:
    """`params` with the scales of `shift` set (fields not in `shift` keep their value)."""
    return params.replace(**{k: jnp.float32(v) for k, v in shift.items()})


def stack_params(params: list[EnvParams]) -> EnvParams:
    """Stack env params along a new leading axis (one entry per run of a sweep)."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *params)


def shift_label(shift: dict[str, float]) -> str:
    """`friction_scale=0.5,gear_scale=0.8`, or `nominal` for no shift."""
    return ",".join(f"{k}={v:g}" for k, v in shift.items()) or "nominal"


def params_record(params: EnvParams) -> dict[str, float | list[float]]:
    """`params` as JSON-ready plain numbers (scalars as floats, masks as lists)."""
    out = {}
    for field in EnvParams.__dataclass_fields__:
        value = jax.device_get(getattr(params, field))
        out[field] = value.tolist() if getattr(value, "ndim", 0) else float(value)
    return out


__all__ = ["DYNAMICS_FIELDS", "apply_dynamics", "params_record", "parse_dynamics",
           "shift_label", "stack_params"]
