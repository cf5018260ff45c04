"""`safecdt-jax run` end to end on tiny settings, its reuse of cached artefacts, its errors."""

import json

import pytest
from typer.testing import CliRunner

from safecdt_jax.cli import app

ARGS = ["run", "--pair", "PC1-PC2", "--preset", "tiny", "--data-episodes", "32", "--steps", "20",
        "--seeds", "2", "--episodes", "2", "--set", "horizon=20", "--variant", "safe_cdt,zero_shot"]


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SAFECDT_CACHE", str(tmp_path / "cache"))
    return tmp_path


@pytest.mark.slow
def test_run_end_to_end_then_reuses_data_and_checkpoint(cache):
    out = cache / "run"
    result = CliRunner().invoke(app, [*ARGS, "--out", str(out)])
    assert result.exit_code == 0, result.output
    res = json.loads((out / "results.json").read_text())
    assert [r["variant"] for r in res["runs"]] == ["safe_cdt", "zero_shot"]
    for run in res["runs"]:
        assert len(run["metrics"]["cost"]) == 2 and len(run["metrics"]["cost"][0]) == 2
        assert run["summary"]["seeds"] == 2
    assert res["source"] == "PointCircle1" and res["target"] == "PointCircle2"
    assert "| safe_cdt |" in (out / "table.md").read_text()
    for name in ("cost.png", "ctg_target.png", "violation_rate.png"):
        assert (out / name).stat().st_size > 1000
    assert sorted(p.name for p in (out / "tensorboard").iterdir()) == ["safe_cdt", "zero_shot"]
    pretrain_curves = cache / "cache" / "checkpoints" / "PointCircle1-tiny-tensorboard"
    assert any(pretrain_curves.glob("events.out.tfevents.*"))

    data = cache / "cache" / "datasets" / "PointCircle1.hdf5"
    ckpt = cache / "cache" / "checkpoints" / "PointCircle1-tiny"
    stamps = data.stat().st_mtime_ns, sorted(p.name for p in ckpt.iterdir())
    again = CliRunner().invoke(app, [*ARGS, "--out", str(out)])
    assert again.exit_code == 0, again.output
    assert (data.stat().st_mtime_ns, sorted(p.name for p in ckpt.iterdir())) == stamps
    assert json.loads((out / "results.json").read_text())["runs"][0]["metrics"]["cost"] == \
        res["runs"][0]["metrics"]["cost"]  # same seed, same data and checkpoint -> same result


@pytest.mark.parametrize("flag,value,message", [
    ("--pair", "XX-YY", "unknown pair"),
    ("--variant", "bogus", "unknown variant"),
    ("--budget", "-3", "budget must be positive"),
    ("--set", "lora_labels=luck", "DeployConfig.lora_labels must be one of"),
    ("--set", "nope=1", "--set 'nope=1': expected FIELD=VALUE with a field of DeployConfig"),
])
def test_run_bad_input_is_one_clear_line(cache, flag, value, message):
    args = [a if a != "PC1-PC2" or flag != "--pair" else value for a in ARGS]
    if flag != "--pair":
        args += [flag, value]
    result = CliRunner().invoke(app, [*args, "--out", str(cache / "run")])
    assert result.exit_code == 1
    assert message in result.output
    assert "Traceback" not in result.output


def test_deployment_uses_the_checkpoints_token_scales(tmp_path):
    # A model only understands the RTG / CTG token scales it was trained with: they are part of
    # its config, saved with the checkpoint, and the deployment has no scales of its own.
    from data_helpers import write_expert_episodes

    from safecdt_jax.deploy.config import DeployConfig
    from safecdt_jax.deploy.job import run_deployment
    from safecdt_jax.pretrain import default_pretrain, pretrain

    data = write_expert_episodes(tmp_path / "PointCircle1.hdf5")
    cfg = default_pretrain("tiny", steps=2, chunk=2)
    ckpt = pretrain(data, tmp_path / "ckpt", preset="tiny", config=cfg, progress=False,
                    model_overrides={"reward_scale": 0.2, "cost_scale": 0.25}).path
    res = run_deployment(ckpt, "PointCircle2", ["zero_shot"], [30.0], 1,
                         cfg=DeployConfig(episodes=1, horizon=5), progress=False)
    assert (res["model_config"]["reward_scale"], res["model_config"]["cost_scale"]) == (0.2, 0.25)
    assert "cost_scale" not in res["deploy_config"]


def test_deployment_over_a_shift_axis_writes_rows_and_the_robustness_figure(tiny_run, tmp_path):
    from safecdt_jax.deploy.config import DeployConfig
    from safecdt_jax.deploy.job import run_deployment, write_results
    from safecdt_jax.envs.dynamics import parse_dynamics

    ckpt = tiny_run[1]
    shifts = parse_dynamics("friction_scale=1.0:0.5:0.25")
    res = run_deployment(ckpt, "PointCircle2", ["zero_shot", "safe_cdt"], [30.0], 1,
                         cfg=DeployConfig(episodes=2, horizon=5, stage_len=1), progress=False,
                         dynamics=shifts)
    assert [(r["variant"], r["dynamics"]) for r in res["runs"][:3]] == [
        ("zero_shot", {"friction_scale": 1.0}), ("zero_shot", {"friction_scale": 0.5}),
        ("zero_shot", {"friction_scale": 0.25})]
    assert [r["env_params"]["friction_scale"] for r in res["runs"]] == [1.0, 0.5, 0.25] * 2
    written = write_results(tmp_path / "out", res, "shifted")
    assert tmp_path / "out" / "robustness_friction_scale.png" in written
    table = (tmp_path / "out" / "table.md").read_text()
    assert "| safe_cdt [friction_scale=0.25] |" in table and table.count("| zero_shot [") == 3


def _tiny_deploy(ckpt, variant: str, episodes: int) -> list[str]:
    """A one-seed `deploy` command line of the tiny checkpoint in PointCircle2 (8-step episodes)."""
    return ["deploy", "--ckpt", str(ckpt), "--pair", "PC1-PC2", "--variant", variant,
            "--seeds", "1", "--episodes", str(episodes), "--set", "horizon=8"]


def _deploy_records(base: list[str], folder, extra: dict[str, list[str]]) -> dict:
    """Runs `base` plus each entry's extra arguments into `folder/name`; its results.json."""
    records = {}
    for name, args in extra.items():
        out = folder / name
        result = CliRunner().invoke(app, [*base, *args, "--out", str(out)])
        assert result.exit_code == 0, result.output
        records[name] = json.loads((out / "results.json").read_text())
    return records


def test_deploy_act_sample_overrides_the_checkpoint_and_is_recorded(tiny_run, tmp_path):
    """`deploy` acts with samples unless `--act` says otherwise, and the mode is recorded."""
    base = _tiny_deploy(tiny_run[1], "zero_shot", episodes=1)
    records = _deploy_records(base, tmp_path, {act: ["--act", act] if act else []
                                               for act in ("checkpoint", "sample", "")})
    assert records["checkpoint"]["stochastic_actions"] is False  # the tiny ckpt acts by the mean
    assert records["sample"]["stochastic_actions"] is True
    assert records["sample"]["runs"][0]["metrics"] != records["checkpoint"]["runs"][0]["metrics"]
    assert records[""]["runs"] == records["sample"]["runs"]  # the default
    result = CliRunner().invoke(app, [*base, "--act", "greedy", "--out", str(tmp_path / "x")])
    assert result.exit_code == 1 and "unknown action mode 'greedy'" in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_deploy_set_picks_the_lora_labels_and_records_them(tiny_run, tmp_path):
    """`--set lora_labels=...` reaches the deployment: the rule is named in results.json, and
    finetuning on other labels gives other adapters, so other episodes. The default "auto"
    runs, and records, "target" for a CDT acting with samples and "stage" for its mean."""
    base = _tiny_deploy(tiny_run[1], "naive_lora", episodes=3)
    # acting by the mean, as this test was written for: the tiny model's sampled episodes
    # here give both rules the same tokens
    records = _deploy_records(base, tmp_path, {rule: ["--set", f"lora_labels={rule}",
                                                      "--act", "mean"]
                                               for rule in ("stage", "hindsight")})
    for rule, record in records.items():
        assert record["deploy_config"]["lora_labels"] == rule
    auto = _deploy_records(base, tmp_path / "auto", {
        "sample": [], "mean": ["--act", "mean"], "target": ["--set", "lora_labels=target"]})
    assert auto["sample"]["deploy_config"]["lora_labels"] == "target"
    assert auto["sample"]["runs"] == auto["target"]["runs"]
    assert auto["mean"]["deploy_config"]["lora_labels"] == "stage"
    stage, hindsight = (records[r]["runs"][0]["metrics"] for r in ("stage", "hindsight"))
    assert stage["cost"][0] == hindsight["cost"][0]  # episode 0 runs before any finetuning
    assert stage["lora_loss"] != hindsight["lora_loss"]


def test_several_checkpoints_deploy_together_as_they_deploy_alone(tiny_run, tmp_path):
    """Two pretraining seeds' checkpoints x 2 deployment seeds in one sweep: each checkpoint's
    rows equal its own deployment; the summary splits the spread between checkpoints from the
    spread across deployment seeds; a checkpoint of another model is refused."""
    import numpy as np

    from safecdt_jax.deploy.config import DeployConfig
    from safecdt_jax.deploy.job import run_deployment
    from safecdt_jax.pretrain import default_pretrain, pretrain

    data, ckpt, _ = tiny_run
    other = pretrain(data, tmp_path / "seed1", preset="tiny", progress=False,
                     config=default_pretrain("tiny", steps=2, chunk=2, seed=1)).path
    cfg = DeployConfig(episodes=2, horizon=6, stage_len=1)
    kw = dict(cfg=cfg, progress=False, seed=3)
    both = run_deployment([ckpt, other], "PointCircle2", ["safe_cdt"], [30.0], 2, **kw)
    alone = [run_deployment(c, "PointCircle2", ["safe_cdt"], [30.0], 2, **kw)
             for c in (ckpt, other)]
    assert both["seeds"] == 4 and both["deploy_seeds"] == 2 and len(both["checkpoints"]) == 2
    for name, rows in both["runs"][0]["metrics"].items():
        want = alone[0]["runs"][0]["metrics"][name] + alone[1]["runs"][0]["metrics"][name]
        # Not bit-equal: with a base model per row the forward pass is a batched matmul
        # over per-row weights instead of one matmul of shared weights (another summation
        # order; after a LoRA step the returns differ by ~5e-5 relative). A swapped
        # checkpoint or key would differ by O(1).
        np.testing.assert_allclose(rows, want, rtol=1e-3, atol=1e-4, err_msg=name)
    s = both["runs"][0]["summary"]
    means = [a["runs"][0]["summary"]["mean_cost_mean"] for a in alone]
    stds = [a["runs"][0]["summary"]["mean_cost_std"] for a in alone]
    assert s["checkpoints"] == 2 and s["seeds"] == 4
    assert s["mean_cost_between_std"] == pytest.approx(np.std(means), abs=1e-5)
    assert s["mean_cost_within_std"] == pytest.approx(np.mean(stds), abs=1e-5)
    wide = pretrain(data, tmp_path / "wide", preset="tiny", progress=False,
                    config=default_pretrain("tiny", steps=2, chunk=2),
                    model_overrides={"cost_scale": 0.5}).path
    with pytest.raises(ValueError, match="must be pretraining seeds of one run"):
        run_deployment([ckpt, wide], "PointCircle2", ["zero_shot"], [30.0], 1, **kw)


def test_lora_rank_at_deployment_overrides_the_checkpoints(tiny_run):
    from safecdt_jax.deploy.config import DeployConfig
    from safecdt_jax.deploy.job import load_deployment
    from safecdt_jax.pretrain import read_meta

    ckpt = tiny_run[1]
    own = read_meta(ckpt)["model"]["lora_rank"]
    assert load_deployment(ckpt, "PointCircle2")[2].cfg.lora_rank == own
    _, _, policy, cfg, _ = load_deployment(ckpt, "PointCircle2", DeployConfig(lora_rank=own + 2))
    assert (policy.cfg.lora_rank, cfg.lora_rank) == (own + 2, own + 2)
    with pytest.raises(ValueError, match="lora_rank"):
        DeployConfig(lora_rank=-1)
