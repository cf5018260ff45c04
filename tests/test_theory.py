"""The paper's safety theory (section 4) against hand-computed values, and `certify`."""

import json
import math

import numpy as np
import pytest

from safecdt_jax import theory


def test_single_and_multi_episode_bounds():
    # delta = 2 sigma: 1 - exp(-4 sigma^2 / (2 sigma^2)) = 1 - e^-2.
    assert theory.single_episode_bound(10.0, 5.0, 20.0) == pytest.approx(1 - math.exp(-2))
    assert theory.multi_episode_bound(10.0, 5.0, 20.0, 3) == pytest.approx((1 - math.exp(-2))**3)
    # No margin, nothing certified; no spread, certain.
    np.testing.assert_array_equal(theory.single_episode_bound([30.0, 10.0], [1.0, 0.0], 25.0),
                                  [0.0, 1.0])


def test_sufficient_margin_for_50_episodes_at_alpha_005():
    assert float(theory.sufficient_margin(2.0, 50, 0.05)) == pytest.approx(
        2.0 * math.sqrt(2 * math.log(1000)))
    assert float(theory.sufficient_margin(1.0, 50, 0.05)) == pytest.approx(3.7169, abs=1e-4)
    with pytest.raises(ValueError, match="alpha must lie in"):
        theory.sufficient_margin(1.0, 50, 1.5)


def test_critical_and_certified_budget_of_a_hand_made_table():
    c, phi, sigma = [0.2, 0.6, 1.0], [5.0, 8.0, 20.0], [6.0, 2.0, 1.0]
    b_star, at = theory.critical_budget(c, phi, sigma, kappa=1.0)
    assert (b_star, at) == (10.0, 0.6)  # scores 11, 10, 21
    assert theory.certified_budget(c, phi, sigma, 50, 0.05) == pytest.approx(
        10.0 + 6.0 * math.sqrt(2 * math.log(1000)))
    assert theory.threshold_bound(9.0, b_star, 6.0, 50) == 1.0
    assert theory.threshold_bound(22.0, b_star, 6.0, 50) == 1.0  # 50 e^-2 > 1: clipped
    assert theory.threshold_bound(40.0, b_star, 6.0, 50) == pytest.approx(50 * math.exp(-12.5))


def test_transfer_check_holds_and_fails():
    ok = theory.transfer_check([5.0, 10.0], [6.0, 11.0], [1.0, 1.0], 0, budget=30.0)
    assert ok["holds"] and ok["delta_1"] == 25.0 and ok["delta_M"] == 1.0
    assert ok["bound"] == pytest.approx(math.exp(-0.5))
    bad = theory.transfer_check([5.0, 10.0], [29.0, 35.0], [1.0, 1.0], 0, budget=30.0)
    assert not bad["holds"] and bad["delta_M"] == 25.0 and bad["margin_needed"] == 24.0
    with pytest.raises(ValueError, match="same conditions"):
        theory.transfer_check([1.0], [1.0, 2.0], [1.0, 1.0], 0, 30.0)


def _results(costs, ctg, budget=30.0):
    return {"deploy_config": {"episodes": 4},
            "runs": [{"budget": budget, "metrics": {"cost": costs, "ctg_target": ctg}}]}


def test_certify_a_hand_written_results_file(tmp_path):
    # Two seeds x 4 episodes; CTG 6 for the first two episodes, 18 for the last two.
    costs = [[0.0, 10.0, 31.0, 20.0], [4.0, 6.0, 25.0, 31.0]]
    ctg = [[6.0, 6.0, 18.0, 18.0]] * 2
    path = tmp_path / "results.json"
    path.write_text(json.dumps(_results(costs, ctg)))
    cert = theory.certify_file(path, budget=30.0)
    low, high = cert["conditions"]
    assert (low["ctg"], low["episodes"], low["phi"]) == (6.0, 4, 5.0)
    assert low["sigma"] == pytest.approx(np.std([0, 10, 4, 6], ddof=1))
    assert high["violation_rate"] == 0.5 and low["violation_rate"] == 0.0
    assert high["thm41_violation_bound"] == pytest.approx(
        math.exp(-(30 - 26.75) ** 2 / (2 * np.var([31, 20, 25, 31], ddof=1))))
    assert cert["episodes"] == 4 and cert["critical_condition"] == 6.0
    assert high["thm41_holds"] and low["thm41_holds"]  # 0.5 <= 0.83
    # one episode of ten at B + 1: VR 0.1 against a bound exp(-26.9^2 / (2 * 96.1)) = 0.023
    tail = theory.certificate({6.0: [0.0] * 9 + [31.0]}, 30.0, episodes=10)["conditions"][0]
    assert tail["thm41_violation_bound"] == pytest.approx(0.0232, abs=1e-3)
    assert not tail["thm41_holds"]
    table = theory.certificate_table(cert)
    assert "Critical budget B* =" in table and "| 18 | 4 |" in table
    source = tmp_path / "source.json"
    source.write_text(json.dumps(_results([[1.0, 3.0, 10.0, 12.0]], [[6.0, 6.0, 18.0, 18.0]])))
    transfer = theory.certify_file(path, 30.0, source=source)["transfer"]
    assert transfer["condition"] == 6.0 and transfer["delta_M"] == pytest.approx(26.75 - 11.0)
    with pytest.raises(ValueError, match="no run at budget 25"):
        theory.certify_file(path, budget=25.0)


def test_certify_command_prints_the_table(tmp_path):
    from typer.testing import CliRunner

    from safecdt_jax.cli import app

    path = tmp_path / "results.json"
    path.write_text(json.dumps(_results([[0.0, 40.0]], [[6.0, 6.0]])))
    res = CliRunner().invoke(app, ["analyze", "certify", str(path), "--budget", "30",
                                   "--out", str(tmp_path / "cert.json")])
    assert res.exit_code == 0, res.output
    assert "Critical budget" in res.output
    assert json.loads((tmp_path / "cert.json").read_text())["conditions"][0]["phi"] == 20.0
    bad = CliRunner().invoke(app, ["analyze", "certify", str(tmp_path / "missing.json")])
    assert bad.exit_code == 1
