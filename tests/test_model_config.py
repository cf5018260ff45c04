"""CDTConfig presets, validation, and parameter counts (shapes only, via jax.eval_shape)."""

import dataclasses

import jax
import pytest

from safecdt_jax.model import (
    PRESET_NAMES,
    CDTConfig,
    count_params,
    init_lora,
    lora_param_count,
    param_shapes,
    with_nominal_edges,
)

CAR_GOAL = dict(obs_dim=72, act_dim=2, episode_len=1000)


def test_preset_sizes():
    sizes = {
        name: (c.embed_dim, c.num_layers, c.num_heads, c.seq_len)
        for name in PRESET_NAMES
        for c in [CDTConfig.preset(name, **CAR_GOAL)]
    }
    assert sizes == {
        "tiny": (16, 1, 2, 4),
        "cpu": (64, 2, 4, 10),
        "osrl": (128, 3, 8, 10),
        "paper": (256, 4, 8, 10),
    }


def test_defaults_are_osrl():
    c = CDTConfig(**CAR_GOAL)
    assert c == CDTConfig.preset("osrl", **CAR_GOAL)
    assert (c.cost_transform, c.cost_offset, c.cost_loss_weight, c.state_loss_weight) == (
        True, 50.0, 0.02, 0.0,
    )
    assert (c.lora_rank, c.lora_alpha, c.lora_scale) == (16, 32.0, 2.0)
    assert c.head_dim == 16 and c.num_timestep_rows == 1010


def test_preset_overrides_and_replace():
    # cpu reads OSRL's cost token divided by 10: 5 - 0.1 CTG; osrl reads 50 - CTG.
    cpu, osrl = CDTConfig.preset("cpu", **CAR_GOAL), CDTConfig.preset("osrl", **CAR_GOAL)
    assert (cpu.reward_scale, cpu.cost_scale, cpu.cost_offset) == (0.1, 0.1, 5.0)
    assert (osrl.reward_scale, osrl.cost_scale, osrl.cost_offset) == (0.1, 1.0, 50.0)
    c = CDTConfig.preset("cpu", **CAR_GOAL, seq_len=20)
    assert c.seq_len == 20 and c.embed_dim == 64
    assert c.replace(num_layers=5).num_layers == 5


def test_config_is_frozen_and_hashable():
    a = CDTConfig.preset("tiny", **CAR_GOAL)
    b = CDTConfig.preset("tiny", **CAR_GOAL)
    assert hash(a) == hash(b) and a == b
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.embed_dim = 8  # type: ignore[misc]


@pytest.mark.parametrize(
    "make",
    [
        lambda: CDTConfig.preset("huge", **CAR_GOAL),
        lambda: CDTConfig(**CAR_GOAL, embed_dim=100, num_heads=8),
        lambda: CDTConfig(**CAR_GOAL, num_layers=0),
        lambda: CDTConfig(obs_dim=-1, act_dim=2, episode_len=1000),
        lambda: CDTConfig(**CAR_GOAL, seq_len=2.5),
        lambda: CDTConfig(**CAR_GOAL, attention_dropout=1.0),
        lambda: CDTConfig(**CAR_GOAL, embedding_dropout=-0.1),
        lambda: CDTConfig(**CAR_GOAL, lora_rank=0),
        lambda: CDTConfig(**CAR_GOAL, lora_targets=("mlp",)),
        lambda: CDTConfig(**CAR_GOAL, use_state_head=False, state_loss_weight=1.0),
    ],
)
def test_invalid_configs_raise_one_line(make):
    with pytest.raises(ValueError) as err:
        make()
    assert "\n" not in str(err.value) and str(err.value)


@pytest.mark.parametrize(
    "obs, act, horizon, expected",
    [  # OSRL's default CDT instantiated in PyTorch, parameters counted
        (72, 2, 1000, 744_910),  # CarGoal1/2
        (60, 2, 1000, 741_826),  # PointGoal1/2
        (40, 2, 500, 672_686),  # CarCircle1/2
        (28, 2, 500, 669_602),  # PointCircle1/2
    ],
)
def test_osrl_param_count_matches_pytorch(obs, act, horizon, expected):
    n = count_params(param_shapes(CDTConfig.preset("osrl", obs, act, horizon)))
    assert abs(n - expected) <= 0.01 * expected
    assert n == expected  # the q/k/v split keeps in_proj's count exactly


def test_per_block_count_matches_osrl():
    shapes = param_shapes(CDTConfig.preset("osrl", **CAR_GOAL))
    assert count_params(shapes["block_0"]) == 198_272
    assert count_params(shapes["embed_time"]) == 1010 * 128


def test_other_preset_counts():
    counts = {n: count_params(param_shapes(with_nominal_edges(CDTConfig.preset(n, **CAR_GOAL))))
              for n in PRESET_NAMES}
    # 175,054 with linear tokens; the 16 return and 16 cost ramps add 2 x 15 x 64 weights.
    assert counts["cpu"] == 175_054 + 2 * 15 * 64
    assert counts["paper"] == 3_459_150
    assert 3.4e6 < counts["paper"] < 3.6e6


def test_paper_lora_count_and_share():
    cfg = CDTConfig.preset("paper", **CAR_GOAL)
    shapes = param_shapes(cfg)
    lora = jax.eval_shape(lambda k: init_lora(k, shapes, cfg), jax.random.key(0))
    n_lora = count_params(lora)
    assert n_lora == 65_536 == 4 * 2 * (256 * 16 + 16 * 256)
    assert n_lora == lora_param_count(cfg)
    share = n_lora / count_params(shapes)
    assert 0.018 < share < 0.020  # "about 1.9% of the model"


def test_count_params_on_arrays_and_structs():
    tree = {"a": jax.numpy.zeros((3, 4)), "b": [jax.ShapeDtypeStruct((5,), "float32"), 1.0]}
    assert count_params(tree) == 12 + 5 + 1
