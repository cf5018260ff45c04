"""CDT pretraining on a small synthetic data set: learning, chunking, checkpoints, resume, CLI.

The data: 24 episodes of 16 steps, observations N(0, 1) in 5 dims, actions `tanh(obs @ W)`
(a learnable target), per-step costs Bernoulli(0.1), rewards uniform. The `tiny` preset, one
shared run config, so the whole file compiles the training program only a few times.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from safecdt_jax.cli import app
from safecdt_jax.data import episode_returns, load_dataset, make_dataset, write_dataset
from safecdt_jax.model import OptimConfig, init_train_state
from safecdt_jax.paths import checkpoint_dir
from safecdt_jax.presets import CPU_MICRO_BATCH
from safecdt_jax.pretrain import (
    CheckpointError,
    PretrainConfig,
    checkpoint_steps,
    configs_from_meta,
    default_pretrain,
    ensure_checkpoint,
    load_checkpoint,
    load_policy,
    make_train_chunk,
    make_update,
    prepare_data,
    pretrain,
    run_key,
)
from safecdt_jax.pretrain.loop import stream_key
from safecdt_jax.pretrain.normalize import IONorm, fold_io_norm

TASK = "Synthetic"
OPTIM = OptimConfig(learning_rate=1e-3, warmup_steps=5)  # fast enough to learn in 60 updates
# Normalised, so that saving, loading and resuming are tested with the fold in the way.
CFG = PretrainConfig(steps=60, batch_size=16, chunk=20, checkpoint_every=20, max_to_keep=5,
                     scale_actions=True, standardize_obs=True)


def synthetic_dataset(seed: int = 0, n: int = 24, horizon: int = 16, obs_dim: int = 5):
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n, horizon, obs_dim)).astype(np.float32)
    w = rng.normal(size=(obs_dim, 2)) / np.sqrt(obs_dim)
    actions = np.tanh(obs @ w).astype(np.float32)
    rewards = rng.uniform(0.0, 1.0, (n, horizon)).astype(np.float32)
    costs = (rng.uniform(size=(n, horizon)) < 0.1).astype(np.float32)
    return make_dataset(obs, actions, rewards, costs, np.full(n, horizon), attrs={"task": TASK})


@pytest.fixture(scope="module")
def data_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "synthetic.hdf5"
    write_dataset(path, synthetic_dataset())
    return path


@pytest.fixture(scope="module")
def full_run(data_file, tmp_path_factory):
    """One uninterrupted 60-update run, checkpointed every 20 updates."""
    out = tmp_path_factory.mktemp("ckpt") / "full"
    return pretrain(data_file, out, preset="tiny", config=CFG, optim=OPTIM, progress=False)


def _raw_params(result):
    """The run's final params as `load_checkpoint` returns them: normalisation folded in."""
    return fold_io_norm(result.state.params, IONorm.from_json(result.meta["io_norm"]))


def _assert_trees_equal(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_config_defaults_and_validation():
    cpu = default_pretrain("cpu")
    assert cpu.relabel and (cpu.c0, cpu.steps, cpu.batch_size) == (70.0, 10_000, 32)
    assert (cpu.relabel_percent, cpu.labels) == (1.0, "auto")  # docs/METHOD.md section 8
    assert cpu.scale_actions and cpu.standardize_obs
    osrl = default_pretrain("osrl")
    assert (osrl.relabel_percent, osrl.labels) == (0.2, "episode")  # OSRL's
    assert not (osrl.scale_actions or osrl.standardize_obs)
    assert (osrl.batch_size, osrl.steps) == (2048, 100_000)
    # Cache-sized passes on a CPU only, unless asked; the cpu preset's batch stays one pass.
    assert default_pretrain("osrl", backend="cpu").micro_batch == CPU_MICRO_BATCH["osrl"] == 16
    assert default_pretrain("paper", backend="gpu").micro_batch == 0
    assert default_pretrain("osrl", backend="cpu", micro_batch=0).micro_batch == 0
    assert default_pretrain("cpu", backend="cpu", batch_size=64).micro_batch == 0
    assert default_pretrain("cpu", steps=7).steps == 7
    bad = [dict(steps=0), dict(batch_size=-1), dict(chunk=1.5), dict(seed=-1), dict(c0=0.0),
           dict(max_to_keep=0), dict(checkpoint_every=-5), dict(relabel=1),
           dict(scale_actions="yes"), dict(standardize_obs=0), dict(relabel_percent=0.0),
           dict(labels="luck")]
    for kwargs in bad:
        with pytest.raises(ValueError) as err:
            PretrainConfig(**kwargs)
        assert "\n" not in str(err.value) and "PretrainConfig." in str(err.value)
    with pytest.raises(ValueError, match="unknown CDT preset"):
        default_pretrain("huge")


def test_loss_decreases(full_run):
    loss = full_run.history.metrics["loss"]
    assert full_run.history.step == [20, 40, 60]
    assert loss[-1] < loss[0] - 0.3, loss  # Gaussian NLL falls as the tanh target is fitted
    assert int(full_run.state.step) == 60


def test_chunked_scan_equals_step_loop(data_file):
    """Two chunks of 20 == 40 single jitted updates with the same per-update keys."""
    from safecdt_jax.pretrain.run import plan

    spec = plan(data_file, preset="tiny", config=CFG, optim=OPTIM)
    data, weights, _ = prepare_data(spec.data, CFG)
    state0 = init_train_state(stream_key(0, "init"), spec.cdt_cfg, OPTIM)
    chunk = make_train_chunk(spec.cdt_cfg, OPTIM, CFG)
    key, stop = run_key(0), jnp.int32(40)
    chunked = state0
    for _ in range(2):
        chunked, metrics = chunk(chunked, key, data, weights, stop)
    assert int(metrics["updates"]) == 20
    update = jax.jit(make_update(spec.cdt_cfg, OPTIM, CFG))
    looped = state0
    for _ in range(40):
        looped, _ = update(looped, key, data, weights)
    assert int(chunked.step) == int(looped.step) == 40
    for x, y in zip(jax.tree.leaves(chunked), jax.tree.leaves(looped), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6)


def test_save_load_round_trip(full_run, data_file):
    assert checkpoint_steps(full_run.path) == [20, 40, 60]
    ckpt = load_checkpoint(full_run.path)
    _assert_trees_equal(ckpt.params, _raw_params(full_run))
    _assert_trees_equal(full_run.policy().params, ckpt.params)  # raw units, not the state's
    cdt_cfg, optim, cfg = configs_from_meta(ckpt.meta)
    assert ckpt.cfg == cdt_cfg and optim == OPTIM and cfg == CFG
    assert cdt_cfg.episode_len == 16 and cdt_cfg.obs_dim == 5  # no env named Synthetic: data's
    meta = ckpt.meta
    assert meta["task"] == TASK and meta["step"] == 60 and meta["finished"]
    returns = episode_returns(load_dataset(data_file))
    assert meta["dataset"]["reference_return"] == pytest.approx(np.percentile(returns, 95))
    assert {"cost_median", "fingerprint", "n_episodes"} <= set(meta["dataset"])
    assert meta["versions"]["jax"] == jax.__version__
    assert meta["history"]["step"] == [20, 40, 60] and meta["wall_time_s"] > 0
    older = load_checkpoint(full_run.path, step=20)
    assert older.meta["step"] == 20 and not older.meta["finished"]


def test_resume_is_bit_identical(full_run, data_file, tmp_path):
    """Stop at 30 (mid-chunk), resume to 60: same params and optimiser state as one run."""
    out = tmp_path / "resumed"
    first = pretrain(data_file, out, preset="tiny", config=CFG.replace(steps=30), optim=OPTIM,
                     progress=False)
    assert int(first.state.step) == 30 and checkpoint_steps(out) == [20, 30]
    resumed = pretrain(data_file, out, preset="tiny", config=CFG, optim=OPTIM, resume=True,
                       progress=False)
    _assert_trees_equal(resumed.state, full_run.state)
    assert resumed.history.step == [20, 30, 50, 60]
    assert resumed.meta["finished"] and resumed.meta["step"] == 60


def test_resume_rejects_other_config_and_existing_folder(full_run, data_file):
    with pytest.raises(CheckpointError, match=r"pretrain\.batch_size: 16 -> 8") as err:
        pretrain(data_file, full_run.path, preset="tiny", config=CFG.replace(batch_size=8),
                 optim=OPTIM, resume=True, progress=False)
    assert "\n" not in str(err.value)
    with pytest.raises(CheckpointError, match="already holds a checkpoint"):
        pretrain(data_file, full_run.path, preset="tiny", config=CFG, optim=OPTIM,
                 progress=False)


def test_load_policy_checks_the_task(full_run):
    ckpt = load_policy(full_run.path, task=TASK, obs_dim=5)
    _assert_trees_equal(ckpt.params, _raw_params(full_run))
    with pytest.raises(CheckpointError, match="does not fit observation size 7"):
        load_policy(full_run.path, obs_dim=7)
    with pytest.raises(CheckpointError, match=r"does not fit task CarGoal1 \(obs 72") as err:
        load_policy(full_run.path, task="CarGoal1")
    assert "\n" not in str(err.value)
    with pytest.raises(CheckpointError, match="another task"):
        load_policy(full_run.path, task="OtherTask")


def test_missing_checkpoint_raises(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="no complete checkpoint"):
        load_policy(tmp_path / "empty", task="CarGoal1")


def test_cli_pretrain_and_ensure_checkpoint(data_file, tmp_path, monkeypatch):
    monkeypatch.setenv("SAFECDT_CACHE", str(tmp_path))
    runner = CliRunner()
    args = ["pretrain", "--data", str(data_file), "--preset", "tiny", "--steps", "20",
            "--batch", "16"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    out = checkpoint_dir(TASK, "tiny")
    assert str(out) in result.output and checkpoint_steps(out) == [20]
    # A second plain run refuses to clobber it, with a one-line error and exit code 1.
    again = runner.invoke(app, args)
    assert again.exit_code == 1 and "already holds a checkpoint" in again.output

    # Same config and steps reached: reused untouched. More steps: resumed in place.
    stamp = (out / "20").stat().st_mtime_ns
    kw = dict(batch_size=16, progress=False)
    assert ensure_checkpoint(data_file, TASK, "tiny", 20, **kw) == out
    assert (out / "20").stat().st_mtime_ns == stamp
    assert ensure_checkpoint(data_file, TASK, "tiny", 40, **kw) == out
    assert checkpoint_steps(out)[-1] == 40
    with pytest.raises(CheckpointError, match=r"pretrain\.seed: 0 -> 1"):
        ensure_checkpoint(data_file, TASK, "tiny", 40, seed=1, **kw)

    # A checkpoint of an older format is not read: an error, or retrained with overwrite.
    from safecdt_jax.pretrain.checkpoint import FORMAT, read_meta, restore_state, save_checkpoint

    meta = read_meta(out)
    model, optim, _ = configs_from_meta(meta)
    save_checkpoint(out, restore_state(out, model, optim), {**meta, "format": FORMAT - 1})
    with pytest.raises(CheckpointError, match=f"checkpoint format {FORMAT - 1}, this code "
                                              f"reads {FORMAT}"):
        ensure_checkpoint(data_file, TASK, "tiny", 40, **kw)
    assert ensure_checkpoint(data_file, TASK, "tiny", 40, overwrite=True, **kw) == out
    assert read_meta(out)["format"] == FORMAT


def test_plan_task_and_default_folder(data_file, tmp_path, monkeypatch):
    from safecdt_jax.pretrain.run import plan

    with pytest.raises(ValueError, match="holds task Synthetic, not CarGoal1"):
        plan(data_file, task="CarGoal1")
    monkeypatch.setenv("SAFECDT_CACHE", str(tmp_path))
    spec = plan(data_file, preset="tiny")
    assert spec.out == tmp_path / "checkpoints" / "Synthetic-tiny"
    assert spec.cfg == default_pretrain("tiny") and spec.meta["n_params"] > 0


def test_shuffle_gaps_are_zero_for_a_token_the_model_cannot_see(full_run, data_file):
    from safecdt_jax.analysis.diagnose import conditioning_gaps, shuffle_gaps

    gaps = conditioning_gaps(full_run.path, data_file, windows=64, seed=3)
    assert gaps == conditioning_gaps(full_run.path, data_file, windows=64, seed=3)
    assert 0.0 <= gaps["share_ctg_positive"] <= 1.0
    # Blind the model to its cost-to-go input (zero embedding kernel): shuffling the CTG tokens
    # then changes nothing, while the return-to-go still matters.
    ckpt = load_checkpoint(full_run.path)
    blind = dict(ckpt.params, embed_cost=dict(ckpt.params["embed_cost"],
                                              kernel=jnp.zeros_like(
                                                  ckpt.params["embed_cost"]["kernel"])))
    rng = np.random.default_rng(0)
    k, b = ckpt.cfg.seq_len, 32
    batch = {"states": rng.normal(size=(b, k, 5)).astype(np.float32),
             "actions": rng.uniform(-1, 1, (b, k, 2)).astype(np.float32),
             "returns_to_go": rng.uniform(0, 3, (b, k)).astype(np.float32),
             "costs_to_go": rng.uniform(0, 20, (b, k)).astype(np.float32),
             "costs": np.zeros((b, k), np.float32),
             "timesteps": np.tile(np.arange(k, dtype=np.int32), (b, 1)),
             "mask": np.ones((b, k), np.float32)}
    out = shuffle_gaps(blind, ckpt.cfg, batch, jax.random.key(0))
    assert out["costs_to_go"] == 0.0 and out["returns_to_go"] != 0.0
    with pytest.raises(ValueError, match="windows must be >= 2"):
        conditioning_gaps(full_run.path, data_file, windows=1)
    cli = CliRunner().invoke(app, ["analyze", "diagnose", "--ckpt", str(full_run.path), "--data",
                                   str(data_file), "--windows", "64", "--seed", "3"])
    assert cli.exit_code == 0, cli.output
    assert f"| costs_to_go | {gaps['costs_to_go']:.5f} |" in cli.output


def test_cli_cost_token_options_reach_the_checkpoint(data_file, tmp_path):
    runner, out = CliRunner(), tmp_path / "token"
    args = ["pretrain", "--data", str(data_file), "--preset", "tiny", "--steps", "3",
            "--batch", "4", "--set", "chunk=1", "--out", str(out)]
    result = runner.invoke(app, [*args, "--set", "cost_scale=0.025", "--set", "cost_offset=1"])
    assert result.exit_code == 0, result.output
    meta = load_checkpoint(out).meta
    assert meta["model"]["cost_scale"] == 0.025 and meta["model"]["cost_offset"] == 1.0
    # The summary line ends on the mean of the last chunks (here all 3), not on the last one.
    loss = meta["history"]["loss"]
    assert len(loss) == 3 and f"{sum(loss) / 3:.3f}" != f"{loss[-1]:.3f}"
    assert f"-> {sum(loss) / 3:.3f}, action" in result.output
    assert "(first chunk -> mean of the last 3)" in result.output
    model = configs_from_meta(meta)[0]  # what evaluate and deploy will use
    assert (model.reward_scale, model.cost_scale) == (0.1, 0.025)
    bad = runner.invoke(app, [*args, "--overwrite", "--set", "cost_scale=0"])
    assert bad.exit_code == 1 and "error: CDTConfig.cost_scale" in bad.output


def _two_policy_data(tmp_path):
    """8 synthetic episodes of two behaviour policies (episode_info/snapshot), written to HDF5:
    (dataset, path)."""
    data = synthetic_dataset(n=8)
    data = make_dataset(data.observations, data.actions, data.rewards, data.costs,
                        data.lengths, episode_info={"snapshot": np.arange(8) % 2},
                        attrs={"task": TASK})
    path = tmp_path / "policies.hdf5"
    write_dataset(path, data)
    return data, path


def test_cli_token_encoding_and_policy_labels_reach_the_checkpoint(data_file, tmp_path):
    # Two behaviour policies (episode_info/snapshot): edges are fitted to the policy-mean labels,
    # saved with the model, and read back by what evaluation loads.
    data, path = _two_policy_data(tmp_path)
    runner, out = CliRunner(), tmp_path / "ramps"
    args = ["pretrain", "--data", str(path), "--preset", "tiny", "--steps", "2", "--batch", "4",
            "--set", "chunk=1", "--out", str(out)]
    result = runner.invoke(app, [*args, "--set", "token_bins=4", "--set", "token_rates=true",
                                 "--set", "labels=policy"])
    assert result.exit_code == 0, result.output
    ckpt = load_checkpoint(out)
    model, _, pre = configs_from_meta(ckpt.meta)
    assert model == ckpt.cfg and pre.labels == "policy"
    assert model.token_bins == 4 and model.token_rates
    assert 2 <= len(model.return_edges) <= 5 and 2 <= len(model.cost_edges) <= 5
    # Policy-mean labels: every episode of a policy starts from the same return-to-go.
    means = [episode_returns(data)[np.arange(8) % 2 == k].mean() * 0.1 for k in (0, 1)]
    assert model.return_edges[0] <= min(means) and model.return_edges[-1] >= max(means)
    policy = load_policy(out, TASK)
    assert policy.cfg.return_edges == model.return_edges
    bad = runner.invoke(app, [*args, "--overwrite", "--set", "labels=luck"])
    assert bad.exit_code == 1 and "error: PretrainConfig.labels" in bad.output
    no_policies = runner.invoke(app, [*args[:2], str(data_file), *args[3:], "--overwrite",
                                      "--set", "labels=policy"])
    assert no_policies.exit_code == 1 and "episode_info['snapshot']" in no_policies.output


def test_relabel_percent_sets_the_number_of_copies():
    # 200 episodes: enough for the grid filter to keep bins (it drops those under 3 episodes).
    data = synthetic_dataset(n=200)
    copies = [prepare_data(data, CFG.replace(relabel_percent=p))[2] for p in (0.2, 1.0)]
    assert copies == [14, 71]  # int(0.2 |F|) and int(1.0 |F|), |F| = 71 filtered episodes


def test_constant_targets_fit_the_token_edges_on_each_episode_t0_tokens():
    from safecdt_jax.model import CDTConfig
    from safecdt_jax.pretrain.run import fit_token_edges

    rewards = np.array([[1, 2, 3, 0], [1, 1, 1, 1]], np.float32)  # returns 6 and 4
    costs = np.array([[0, 1, 1, 0], [1, 0, 0, 1]], np.float32)  # costs 2 and 2
    data = make_dataset(np.zeros((2, 4, 3), np.float32), np.zeros((2, 4, 1), np.float32),
                        rewards, costs, [3, 4])
    cfg = CDTConfig(obs_dim=3, act_dim=1, episode_len=4, token_bins=4, cost_scale=0.5)
    run_cfg = PretrainConfig(c0=10.0)
    const = fit_token_edges(cfg.replace(constant_targets=True), data, run_cfg)
    assert const.return_edges[0] == pytest.approx(0.4) and const.return_edges[-1] == \
        pytest.approx(0.6)  # RTG * 0.1 of the t=0 steps only
    assert const.cost_edges == pytest.approx((1.0, 2.0))  # one value, 2 * 0.5: (v, v + 1)
    to_go = fit_token_edges(cfg, data, run_cfg)
    assert to_go.return_edges[0] == pytest.approx(0.1)  # the last step of episode 1: 1
    assert to_go.cost_edges[0] == pytest.approx(0.5)
    # With spans the edges reach past the data at both ends, in raw units times the scales.
    spans = run_cfg.replace(return_span=(-50.0, 100.0), cost_span=(0.0, 100.0))
    wide = fit_token_edges(cfg.replace(constant_targets=True), data, spans)
    assert wide.return_edges[0] == pytest.approx(-5.0) and wide.return_edges[-1] == \
        pytest.approx(10.0)
    assert wide.cost_edges == pytest.approx((0.0, 1.0, 50.0))


def test_auto_labels_use_the_policies_only_where_the_data_name_them():
    from safecdt_jax.data import episode_costs
    from safecdt_jax.pretrain.loop import labelled

    data = synthetic_dataset(n=8)
    named = make_dataset(data.observations, data.actions, data.rewards, data.costs,
                         data.lengths, episode_info={"snapshot": np.arange(8) % 2})
    auto = PretrainConfig(labels="auto")
    np.testing.assert_allclose(episode_costs(labelled(named, auto)),
                               episode_costs(labelled(named, auto.replace(labels="policy"))))
    assert len(set(np.round(episode_costs(labelled(named, auto)), 4))) == 2  # one per policy
    np.testing.assert_array_equal(episode_costs(labelled(data, auto)), episode_costs(data))


def test_cli_pretrain_keeps_the_cpu_presets_defaults_unless_told(tmp_path):
    _, path = _two_policy_data(tmp_path)
    args = ["pretrain", "--data", str(path), "--preset", "cpu", "--steps", "1", "--batch", "2",
            "--set", "chunk=1"]
    result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "a")])
    assert result.exit_code == 0, result.output
    model, _, pre = configs_from_meta(load_checkpoint(tmp_path / "a").meta)
    assert (pre.labels, pre.relabel_percent, pre.scale_actions, pre.standardize_obs) == (
        "auto", 1.0, True, True)
    assert model.token_bins == 16 and model.constant_targets and not model.stochastic_actions
    result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "b"), "--set",
                                      "scale_actions=false", "--set", "labels=episode", "--set",
                                      "relabel_percent=0.2", "--set", "stochastic_actions=true"])
    assert result.exit_code == 0, result.output
    model, _, pre = configs_from_meta(load_checkpoint(tmp_path / "b").meta)
    assert (pre.labels, pre.relabel_percent, pre.scale_actions) == ("episode", 0.2, False)
    assert model.stochastic_actions
