"""Shifted-dynamics targets: parsing `--dynamics`, their physical effect, and shift axes in one
compiled sweep."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from deploy_helpers import TINY_DEPLOY, tiny_setup
from env_helpers import hold
from typer.testing import CliRunner

from safecdt_jax import envs
from safecdt_jax.cli import app
from safecdt_jax.deploy import make_spec, make_variant, seed_keys, stack_specs, sweep
from safecdt_jax.deploy.sweep import _compiled
from safecdt_jax.envs.dynamics import (
    apply_dynamics,
    params_record,
    parse_dynamics,
    shift_label,
    stack_params,
)


def test_parse_builds_the_grid_in_order():
    assert parse_dynamics(None) == [{}] and parse_dynamics(" ") == [{}]
    assert parse_dynamics("gear_scale=0.8") == [{"gear_scale": 0.8}]
    grid = parse_dynamics("friction_scale=1.0:0.5, gear_scale=0.8:1.2")
    assert grid == [{"friction_scale": 1.0, "gear_scale": 0.8},
                    {"friction_scale": 1.0, "gear_scale": 1.2},
                    {"friction_scale": 0.5, "gear_scale": 0.8},
                    {"friction_scale": 0.5, "gear_scale": 1.2}]
    assert shift_label(grid[2]) == "friction_scale=0.5,gear_scale=0.8"
    assert shift_label({}) == "nominal"


@pytest.mark.parametrize("text, message", [
    ("fricton_scale=0.5", "unknown dynamics field 'fricton_scale'; valid: friction_scale"),
    ("friction_scale=0", "friction_scale' must be a positive scale, got 0"),
    ("mass_scale=-1:2", "mass_scale' must be a positive scale, got -1"),
    ("gear_scale=inf", "must be a positive scale"),
    ("gear_scale=fast", "'fast' is not a number"),
    ("gear_scale", "expected FIELD=VALUE"),
    ("gear_scale=0.5,gear_scale=0.7", "given twice"),
])
def test_bad_dynamics_get_one_line_errors(text, message):
    with pytest.raises(ValueError) as err:
        parse_dynamics(text)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_cli_rejects_bad_dynamics_before_loading_anything(tmp_path):
    result = CliRunner().invoke(app, ["deploy", "--ckpt", str(tmp_path / "none"), "--pair",
                                      "CG1-CG2", "--dynamics", "grip=0.5"])
    assert result.exit_code == 1 and "unknown dynamics field 'grip'" in result.output
    assert "Traceback" not in result.output


def _speed_and_yaw(params):
    """(speed after 4 s and after 0.4 s at a = (1, 1) in m/s, yaw rate after 4 s at a = (1, -1)
    in rad/s)."""
    top = float(jnp.linalg.norm(hold("CarCircle1", (1.0, 1.0), 4.0, params).data.qvel[:2]))
    early = float(jnp.linalg.norm(hold("CarCircle1", (1.0, 1.0), 0.4, params).data.qvel[:2]))
    return top, early, float(hold("CarCircle1", (1.0, -1.0), 4.0, params).data.qvel[2])


def test_friction_and_gear_shift_the_car_as_native_mujoco():
    """Native MuJoCo with the same shifts (docs/ENVIRONMENTS.md, means over 1.6-4 s): friction
    0.5 raises the top speed 0.778 -> 0.888 m/s (the caster's sliding drag halves) and halves
    the speed after 0.4 s (0.721 -> 0.421: the wheels' grip halves); gear 0.8 gives 0.80x the
    top speed and 0.87x the yaw rate. Ours: 0.820 -> 0.910, 0.820 -> 0.413; 0.76x, 0.93x."""
    _, params = envs.make("CarCircle1")
    top, early, yaw = _speed_and_yaw(params)
    top_slick, early_slick, _ = _speed_and_yaw(apply_dynamics(params, {"friction_scale": 0.5}))
    top_weak, _, yaw_weak = _speed_and_yaw(apply_dynamics(params, {"gear_scale": 0.8}))
    assert top_slick > 1.05 * top and early_slick < 0.6 * early
    assert top_weak == pytest.approx(0.8 * top, rel=0.08) and yaw_weak < 0.97 * yaw


def _specs(*names):
    return stack_specs([make_spec(make_variant(n, TINY_DEPLOY), 2.0, 4.0) for n in names])


def test_a_shift_grid_is_one_compilation_and_equals_single_shifts():
    env, params, model_cfg, base = tiny_setup()
    keys = seed_keys(0, 2)
    grid = parse_dynamics("friction_scale=1.0:0.5,gear_scale=1.0:0.7")
    batched = stack_params([apply_dynamics(params, s) for s in grid])
    static = dict(env=env, model_cfg=model_cfg, cfg=TINY_DEPLOY)
    fn = _compiled(env, model_cfg, TINY_DEPLOY, True)[1]
    out = jax.device_get(sweep(keys, base, batched, _specs(*["zero_shot"] * 4),
                               env_params_batched=True, **static))
    size = fn._cache_size()
    again = stack_params([apply_dynamics(params, s) for s in reversed(grid)])
    sweep(keys, base, again, _specs(*["safe_cdt"] * 4), env_params_batched=True, **static)
    assert fn._cache_size() == size  # other shifts and variants: the same program
    for r, shift in enumerate(grid):
        single = jax.device_get(sweep(keys, base, apply_dynamics(params, shift),
                                      _specs("zero_shot"), **static))
        for s in range(2):  # zero_shot has no adapters: only float fusion can differ
            np.testing.assert_allclose(out.costs[r, s], single.costs[0, s], atol=1e-5)
            np.testing.assert_allclose(out.returns[r, s], single.returns[0, s], rtol=1e-3,
                                       atol=1e-3)
    assert len({float(out.returns[r].sum()) for r in range(4)}) == 4  # shifts differ


def test_params_record_round_trips_through_json():
    _, params = envs.make("CarGoal2")
    shifted = apply_dynamics(params, {"friction_scale": 0.25, "mass_scale": 1.5})
    record = json.loads(json.dumps(params_record(shifted)))
    assert record["friction_scale"] == 0.25 and record["mass_scale"] == 1.5
    back = envs.EnvParams(**{k: jnp.asarray(v, jnp.float32) for k, v in record.items()})
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(shifted), strict=True):
        np.testing.assert_array_equal(a, b)
