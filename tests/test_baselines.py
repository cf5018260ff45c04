"""Offline baselines: known values of the pure pieces, determinism, vmap == loop, chunked ==
one scan, the algorithms' defining behaviour on hand-made data, and the errors of bad input."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safecdt_jax.baselines import common, cpq
from safecdt_jax.baselines.config import BaselineConfig, preset
from safecdt_jax.baselines.train import make_algorithm, make_chunk, make_train
from safecdt_jax.data.dataset import DatasetError, make_dataset


def test_qc_threshold_known_values():
    # B (1 - 0.99^L) / (0.01 L): OSRL's table, 2.0 / 4.0 / 8.0 at L = 1000 and 3.97 at L = 500.
    assert common.qc_threshold(20, 0.99, 1000) == pytest.approx(20 * (1 - 0.99**1000) / 10)
    assert common.qc_threshold(20, 0.99, 1000) == pytest.approx(2.0, abs=1e-3)
    assert common.qc_threshold(80, 0.99, 1000) == pytest.approx(8.0, abs=1e-3)
    assert common.qc_threshold(20, 0.99, 500) == pytest.approx(3.973, abs=1e-3)


def test_pid_step_by_hand():
    pid = common.PID(jnp.float32(0.0), jnp.float32(1.0), jnp.float32(0.5))
    qc = jnp.array([3.0, 5.0])  # mean 4, threshold 2: e = 2
    new = common.pid_step(pid, qc, 2.0, (0.1, 0.003, 0.001))
    # I = relu(1 + 2) = 3, D = relu(2 - 0.5) = 1.5, lambda = 0.1 * 2 + 0.003 * 3 + 0.001 * 1.5.
    assert float(new.integral) == pytest.approx(3.0)
    assert float(new.prev_error) == pytest.approx(2.0)
    assert float(new.lam) == pytest.approx(0.2 + 0.009 + 0.0015)
    below = common.pid_step(common.PID.create(), jnp.array([0.5]), 2.0, (0.1, 0.003, 0.001))
    assert float(below.lam) == 0.0 and float(below.integral) == 0.0


def test_gaussian_mmd_of_hand_made_sets():
    x = jnp.zeros((1, 2, 1))
    y = jnp.ones((1, 1, 1)) * 2.0
    sigma = 2.0
    kxy = math.exp(-4.0 / (2 * sigma))
    expected = math.sqrt(1.0 + 1.0 - 2 * kxy + 1e-6)
    assert float(common.mmd_gaussian(x, y, sigma)[0]) == pytest.approx(expected, rel=1e-5)
    assert float(common.mmd_gaussian(x, x, sigma)[0]) == pytest.approx(1e-3, rel=1e-3)


def test_vae_loss_and_soft_clipped_values():
    recon, action = jnp.array([[0.5, 0.0]]), jnp.array([[0.0, 0.0]])
    mu, log_std = jnp.array([[1.0, 0.0]]), jnp.zeros((1, 2))
    # MSE 0.125; KL per element 0.5 * mu^2 = [0.5, 0], mean 0.25.
    assert float(common.vae_loss(recon, action, mu, log_std, 0.5)) == pytest.approx(0.25)
    assert float(common.soft_clipped(jnp.array(1.0), jnp.array(3.0), 0.75)) == pytest.approx(1.5)


def test_cpq_ood_mask_flags_the_top_quarter():
    kl = jnp.arange(8.0).reshape(2, 4)
    np.testing.assert_array_equal(cpq.ood_mask(kl, 0.75), (np.arange(8) >= 5.25).reshape(2, 4))


def _data(n=6, t=30, obs_dim=6, act=None, cost=None, seed=0):
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n, t, obs_dim))
    actions = rng.uniform(-1, 1, (n, t, 2)) if act is None else act
    costs = (rng.uniform(size=(n, t)) < 0.2).astype(float) if cost is None else cost
    return make_dataset(obs, actions, rng.normal(size=(n, t)), costs, np.full(n, t),
                        attrs={"task": "PointCircle1"})


@functools.cache
def _tiny_transitions():
    return common.transitions(_data())


@pytest.mark.parametrize("algo", ["bcql", "bearl", "cpq"])
def test_same_key_same_bits_vmap_equals_loop_and_chunks_equal_one_scan(algo):
    data, _ = _tiny_transitions()
    cfg = preset(algo, "tiny")
    train = jax.jit(make_train(cfg, data, 30))
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    a, ma = train(keys[0])
    b, _ = train(keys[0])
    jax.tree.map(np.testing.assert_array_equal, a, b)
    batched, _ = jax.jit(jax.vmap(make_train(cfg, data, 30)))(keys)
    single = [train(k)[0] for k in keys]
    for i in range(2):
        jax.tree.map(lambda x, y, i=i: np.testing.assert_allclose(x[i], y, rtol=2e-4, atol=2e-5),
                     batched, single[i])
    # The runner's form: one chunk per call from the same keys takes the same steps.
    algo_fns = make_algorithm(cfg, 6, 2, 30)
    chunk = jax.jit(make_chunk(cfg, algo_fns))
    k_init, k_train = jax.random.split(keys[0])
    state = algo_fns.init(k_init)
    for _ in range(-(-cfg.steps // cfg.chunk)):
        state, _ = chunk(state, k_train, data)
    jax.tree.map(np.testing.assert_array_equal, state.params, a)
    assert set(ma) >= {"critic_loss", "cost_critic_loss", "actor_loss", "vae_loss"}
    assert all(np.isfinite(np.asarray(v)).all() for v in ma.values())


def _one_state_data(good, n=8, t=25):
    """One observation everywhere, actions uniform in [-0.8, 0.8]^2, reward `good` x a_0: the
    best in-support action is a_0 = 0.8 `good`."""
    act = np.random.default_rng(0).uniform(-0.8, 0.8, (n, t, 2))
    return make_dataset(np.zeros((n, t, 3)), act, good * act[..., 0], np.zeros((n, t)),
                        np.full(n, t))


def _train_on_one_state(algo, good):
    data, _ = common.transitions(_one_state_data(good=good))
    cfg = preset(algo, "tiny", steps=600, chunk=200, batch=32, hidden=32, vae_hidden=32)
    params, _ = jax.jit(make_train(cfg, data, 25))(jax.random.PRNGKey(1))
    return cfg, params


def test_bearl_actor_moves_toward_the_best_in_support_action():
    """...and the same data with the reward reversed send it the other way."""
    acts = {}
    for good in (1.0, -1.0):
        cfg, params = _train_on_one_state("bearl", good)
        acts[good] = float(make_algorithm(cfg, 3, 2, 25).act(params, jnp.zeros((1, 3)),
                                                             None)[0, 0])
    assert acts[1.0] > 0.15 and acts[-1.0] < -0.15, acts


def test_bcql_perturbs_vae_samples_toward_the_best_action():
    """OSRL's BCQL acts on one VAE sample (no argmax over candidates), so it cannot pick the
    good mode; its perturbation (at most phi) must push the samples toward it on average, and
    the other way when the reward sits on the other action."""
    from safecdt_jax.baselines.networks import VAE, Perturbation

    shift = {}
    for good in (1.0, -1.0):
        cfg, params = _train_on_one_state("bcql", good)
        obs = jnp.zeros((256, 3))
        a_vae = VAE(cfg.vae_hidden, 2).apply(params["vae"], jax.random.PRNGKey(2), obs,
                                             method=VAE.sample)
        a = Perturbation(cfg.hidden, 2, cfg.phi).apply(params["actor"], obs, a_vae)
        shift[good] = float(jnp.mean(a[:, 0] - a_vae[:, 0]))
    assert shift[1.0] > 0.5 * cfg.phi and shift[-1.0] < -0.5 * cfg.phi, shift


def test_cpq_gives_no_future_value_past_unsafe_next_states():
    """Every step costs 1, far above the per-step threshold: the cost critic learns a value
    above it, so the reward critic's target drops the future term and Q stays near r."""
    n, t = 4, 20
    obs = np.random.default_rng(0).normal(size=(n, t, 3)) * 0.1
    act = np.random.default_rng(1).uniform(-0.5, 0.5, (n, t, 2))
    base = make_dataset(obs, act, np.ones((n, t)), np.ones((n, t)), np.full(n, t))
    data, _ = common.transitions(base)
    cfg = preset("cpq", "tiny", steps=400, chunk=200, batch=32, hidden=32, vae_hidden=32,
                 cost_limit=1.0)
    params, _ = jax.jit(make_train(cfg, data, t))(jax.random.PRNGKey(0))
    from safecdt_jax.baselines.networks import QEnsemble

    q = QEnsemble(cfg.hidden, cfg.num_q)
    qc = q.apply(params["cost_critic"], data.obs[:64], data.action[:64]).min(0)
    qr = q.apply(params["critic"], data.obs[:64], data.action[:64]).min(0)
    thres = common.qc_threshold(1.0, cfg.gamma, t)
    assert float(qc.mean()) > thres
    # With future value, Q would head for 0.1 / (1 - 0.99) = 10; without it, 0.1 (r x 0.1).
    assert float(qr.mean()) < 0.5, qr.mean()


@pytest.mark.parametrize("changes", [dict(algo="sac"), dict(steps=0), dict(gamma=1.5),
                                     dict(pid=(0.1, 0.2)), dict(lmbda=-0.1), dict(tau=0.0),
                                     dict(cpq_ood_grad="yes")])
def test_bad_config_names_its_field(changes):
    field = next(iter(changes))
    with pytest.raises(ValueError, match=f"BaselineConfig.{field}"):
        BaselineConfig(**changes)


def test_unknown_algorithm_and_preset_are_one_line_errors():
    with pytest.raises(ValueError, match="unknown baseline 'td3'"):
        preset("td3")
    with pytest.raises(ValueError, match="unknown baseline preset 'gpu'"):
        preset("bcql", "gpu")
    from safecdt_jax.baselines.job import parse_algos

    with pytest.raises(ValueError, match="unknown baseline sac"):
        parse_algos("bcql,sac")


def test_data_of_another_task_or_with_nan_is_rejected(tmp_path):
    from safecdt_jax.baselines.run import load_source
    from safecdt_jax.data.dsrl import write_dataset

    path = tmp_path / "pc.hdf5"
    write_dataset(path, _data(obs_dim=28), attrs={"task": "PointCircle1"})
    with pytest.raises(DatasetError, match="a PointCircle1 data set, but the baselines train on "
                                           "PointCircle2"):
        load_source(path, "PointCircle2")
    with pytest.raises(DatasetError, match="observation size 28 does not match obs_dim=40"):
        load_source(path, "CarCircle1")
    bad = _data()
    bad.rewards[0, 3] = np.nan
    with pytest.raises(DatasetError, match="rewards hold NaN"):
        common.transitions(bad)


def test_runner_checkpoints_reuses_and_evaluates_under_the_runtime_budget(tmp_path):
    from safecdt_jax.baselines.run import evaluate_trained, train_baseline

    data = _data(obs_dim=28)
    cfg = preset("bcql", "tiny", cost_limit=2.0)
    first = train_baseline(cfg, data, [0, 1], tmp_path / "ckpt", progress=False)
    again = train_baseline(cfg, data, [0, 1], tmp_path / "ckpt", progress=False)
    assert not first.reused and again.reused
    jax.tree.map(np.testing.assert_array_equal, first.params, again.params)
    with pytest.raises(ValueError, match="another config"):
        train_baseline(preset("bcql", "tiny", cost_limit=3.0), data, [0, 1], tmp_path / "ckpt",
                       progress=False)
    # A longer run resumes the saved one and ends with the bits of an uninterrupted run.
    longer = preset("bcql", "tiny", cost_limit=2.0, steps=30)
    extended = train_baseline(longer, data, [0, 1], tmp_path / "ckpt", progress=False)
    fresh = train_baseline(longer, data, [0, 1], None, progress=False)
    assert not extended.reused and extended.history["critic_loss"].shape == (2, 3)
    jax.tree.map(np.testing.assert_array_equal, extended.params, fresh.params)
    returns, costs = evaluate_trained(first, "PointCircle1", episodes=2, stop_cost=2.0)
    assert returns.shape == costs.shape == (2, 2)
    assert np.all(costs <= 3.0)  # ended at the first step over the budget


def test_baselines_command_writes_the_table_scatter_and_results(tiny_run, tmp_path):
    """`safecdt-jax baselines` end to end on the tiny data and preset: one line per method in
    the paper's Table 7 layout, the paper's numbers beside ours, reused checkpoints on rerun."""
    import json

    from typer.testing import CliRunner

    from safecdt_jax.cli import app

    data, _, _ = tiny_run
    args = ["baselines", "--pair", "PC1-PC2", "--algos", "cpq,bc_safe", "--seeds", "2",
            "--preset", "tiny", "--episodes", "2", "--steps", "10", "--data", str(data),
            "--out", str(tmp_path)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    table = (tmp_path / "baselines.md").read_text()
    assert "| PC1→PC2 | CPQ |" in table and "-1.05 ± 2.69" in table  # the paper's CPQ row
    assert "| PC1→PC2 | BC-Safe |" in table
    assert (tmp_path / "baselines_scatter.png").stat().st_size > 0
    results = json.loads((tmp_path / "baselines.json").read_text())
    cpq_run = results["methods"][0]
    assert np.asarray(cpq_run["costs"]).shape == (2, 2)
    assert np.all(np.asarray(cpq_run["costs"]) <= 31)  # the runtime budget
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 0 and "(reused)" in (tmp_path / "baselines.md").read_text()
    bad = CliRunner().invoke(app, ["baselines", "--pair", "XX-YY", "--out", str(tmp_path)])
    assert bad.exit_code == 1 and "unknown pair" in bad.output
