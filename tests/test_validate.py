"""`--set FIELD=VALUE` parsing: values typed as the config field wants them, bad items named."""

import pytest

from safecdt_jax.deploy.config import DeployConfig
from safecdt_jax.model.config import CDTConfig
from safecdt_jax.pretrain.config import PretrainConfig
from safecdt_jax.validate import field_overrides


def test_set_values_are_typed_by_text_and_by_the_field():
    got = field_overrides(["horizon=20", "lora_lr=3e-5", "lora_in_turn=none",
                           "stop_over_budget=False", "lora_labels=hindsight", "budget=30"],
                          DeployConfig)
    assert got == {"horizon": 20, "lora_lr": 3e-5, "lora_in_turn": None,
                   "stop_over_budget": False, "lora_labels": "hindsight", "budget": 30.0}
    assert type(got["budget"]) is float and type(got["horizon"]) is int  # float field: 30.0
    assert DeployConfig(**got).stop_over_budget is False


def test_set_spans_several_configs_and_names_a_bad_item():
    got = field_overrides(["cost_offset=1", "labels=policy"], PretrainConfig, CDTConfig)
    assert got == {"cost_offset": 1.0, "labels": "policy"}
    for item in ("nope=1", "horizon"):
        with pytest.raises(ValueError, match=f"--set '{item}': expected FIELD=VALUE with a "
                                             "field of PretrainConfig/CDTConfig"):
            field_overrides([item], PretrainConfig, CDTConfig)
