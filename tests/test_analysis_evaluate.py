"""`safecdt-jax evaluate`: target parsing, Spearman, the summary and its table, the CLI."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from safecdt_jax.analysis.evaluate import (
    evaluate_policy,
    evaluation_table,
    parse_targets,
    spearman,
    summarize_evaluation,
)
from safecdt_jax.cli import app
from safecdt_jax.data import episode_costs, load_dataset

TASK = "PointCircle1"


def test_parse_targets_and_its_errors():
    assert parse_targets("40:20, 14.9:0") == [(40.0, 20.0), (14.9, 0.0)]
    for text, message in [("40", "expected RETURN:COST"), ("40:x", "expected RETURN:COST"),
                          ("40:20:1", "expected RETURN:COST"), ("40:-1", "must be >= 0"),
                          ("nan:20", "finite")]:
        with pytest.raises(ValueError, match=message):
            parse_targets(text)


def test_spearman_known_values():
    targets = [10, 20, 40, 80]
    assert spearman(targets, [2.6, 5.3, 7.4, 18.2]) == pytest.approx(1.0)
    assert spearman(targets, [18.2, 7.4, 5.3, 2.6]) == pytest.approx(-1.0)
    # PointCircle1 seed 3 (docs/research/cdt-findings.md, section 5): ranks 3, 1, 2, 4.
    assert spearman(targets, [92.6, 72.7, 90.2, 133.7]) == pytest.approx(0.4)
    # One swapped pair of four: exactly 0.8, so a ">= 0.8" criterion passes.
    assert spearman(targets, [15.8, 22.4, 34.5, 28.0]) >= 0.8
    # Ties share their mean rank: ranks (1, 2, 3) against (1.5, 1.5, 3).
    assert spearman([1, 2, 3], [5, 5, 7]) == pytest.approx(1.5 / np.sqrt(3.0))
    assert np.isnan(spearman(targets, [5.0, 5.0, 5.0, 5.0]))
    with pytest.raises(ValueError, match="one length"):
        spearman([1, 2, 3], [1, 2])


def test_summary_rows_spearman_and_median_line():
    res = {"target_return": np.array([10.0, 10.0, 10.0, 20.0]),
           "target_cost": np.array([10.0, 20.0, 40.0, 10.0]),
           "returns": np.array([[1.0, 3.0], [2.0, 2.0], [4.0, 4.0], [5.0, 7.0]]),
           "costs": np.array([[0.0, 30.0], [50.0, 10.0], [20.0, 60.0], [5.0, 5.0]])}
    s = summarize_evaluation(TASK, res, data_median=25.0)
    assert [r["mean_cost"] for r in s["rows"]] == [15.0, 30.0, 40.0, 5.0]
    assert [r["mean_return"] for r in s["rows"]] == [2.0, 2.0, 4.0, 6.0]
    assert [r["vr_percent"] for r in s["rows"]] == [50.0, 50.0, 50.0, 0.0]
    # Only return 10 ran at several cost targets; its mean costs rise with them.
    assert s["cost_following"] == [{"target_return": 10.0, "spearman": pytest.approx(1.0)}]
    table = evaluation_table(s)
    assert "| 10 | 20 | 2.00 | 30.0 | 50 |" in table
    assert "cost follows the target at return 10: Spearman 1.00" in table
    assert ("data median episode cost 25.0; mean cost below it at targets (RETURN:COST): "
            "10:10, 20:10") in table
    json.dumps(s, allow_nan=False)  # strict JSON

    res["costs"][:3] = 7.0  # equal mean costs: the correlation is undefined, null in JSON
    s = summarize_evaluation(TASK, res)
    assert s["cost_following"][0]["spearman"] is None and s["data_median_cost"] is None
    assert "Spearman undefined" in evaluation_table(s)
    json.dumps(s, allow_nan=False)


def test_cli_evaluate_prints_and_writes_the_summary(tiny_run):
    data, ckpt, tmp = tiny_run
    out = tmp / "eval.json"
    args = ["evaluate", "--ckpt", str(ckpt), "--task", TASK, "--targets", "5:0,5:10,5:40",
            "--episodes", "2", "--horizon", "12", "--seed", "3"]
    result = CliRunner().invoke(app, [*args, "--data", str(data), "--out", str(out)])
    assert result.exit_code == 0, result.output
    summary = json.loads(out.read_text())
    assert np.shape(summary["costs"]) == (3, 2) and summary["horizon"] == 12
    assert summary["data_median_cost"] == float(np.median(episode_costs(load_dataset(data))))
    assert f"data median episode cost {summary['data_median_cost']:.1f}" in result.output
    assert "cost follows the target at return 5: Spearman" in result.output
    # The CLI's numbers are evaluate_policy's: same key, same layouts, same bits.
    res = evaluate_policy(ckpt, TASK, [(5.0, 0.0), (5.0, 10.0), (5.0, 40.0)], 2, seed=3,
                          horizon=12, stochastic_actions=True)
    np.testing.assert_array_equal(np.asarray(summary["costs"]), res["costs"])
    np.testing.assert_array_equal(np.asarray(summary["returns"]), res["returns"])
    assert not list(tmp.glob(".tmp-*"))  # written atomically: no temporary left behind
    assert summary["stochastic_actions"] is True  # the default: samples, not the ckpt's mean


def test_cli_evaluate_act_sample_draws_from_the_policy(tiny_run):
    _, ckpt, tmp = tiny_run
    args = ["evaluate", "--ckpt", str(ckpt), "--task", TASK, "--targets", "5:0,5:10",
            "--episodes", "2", "--horizon", "12", "--seed", "3"]
    outs = {}
    for act in ("mean", "sample"):
        out = tmp / f"eval-{act}.json"
        result = CliRunner().invoke(app, [*args, "--act", act, "--out", str(out)])
        assert result.exit_code == 0, result.output
        outs[act] = json.loads(out.read_text())
    assert "sampled actions" in result.output
    assert outs["sample"]["stochastic_actions"] and not outs["mean"]["stochastic_actions"]
    res = evaluate_policy(ckpt, TASK, [(5.0, 0.0), (5.0, 10.0)], 2, seed=3, horizon=12,
                          stochastic_actions=True)
    np.testing.assert_array_equal(np.asarray(outs["sample"]["returns"]), res["returns"])
    assert not np.array_equal(np.asarray(outs["mean"]["returns"]), res["returns"])


@pytest.mark.parametrize("flag,value,message", [
    ("--targets", "5:-1", "must be >= 0"),
    ("--data", "missing.hdf5", "file not found"),
    ("--task", "CarGoal1", "does not fit task CarGoal1"),
    ("--act", "greedy", "unknown action mode 'greedy'"),
])
def test_cli_evaluate_bad_input_is_one_clear_line(tiny_run, flag, value, message):
    _, ckpt, tmp = tiny_run
    args = {"--ckpt": str(ckpt), "--task": TASK, "--targets": "5:0,5:10", "--episodes": "1",
            "--horizon": "4"}
    args[flag] = str(tmp / value) if flag == "--data" else value
    result = CliRunner().invoke(app, ["evaluate", *[x for kv in args.items() for x in kv]])
    assert result.exit_code == 1
    assert message in result.output and "Traceback" not in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_cli_evaluate_notes_targets_outside_the_training_labels(tiny_run):
    """One line when a target lies above the labels the checkpoint was trained on, none for a
    target inside them."""
    from safecdt_jax.pretrain.checkpoint import load_checkpoint

    _, ckpt, _ = tiny_run
    support = load_checkpoint(ckpt).meta["token_support"]
    (r_lo, r_hi), (c_lo, c_hi) = support["return"], support["cost"]
    inside = f"{(r_lo + r_hi) / 2:.3f}:{(c_lo + c_hi) / 2:.3f}"
    args = ["evaluate", "--ckpt", str(ckpt), "--task", TASK, "--episodes", "1", "--horizon", "4"]
    result = CliRunner().invoke(app, [*args, "--targets", inside])
    assert result.exit_code == 0 and "outside the labels" not in result.output
    result = CliRunner().invoke(app, [*args, "--targets", f"{inside},{r_hi:.3f}:{c_hi + 50:.3f}"])
    assert result.exit_code == 0, result.output
    notes = [line for line in result.output.splitlines() if "outside the labels" in line]
    assert len(notes) == 1 and f"cost targets {round(c_hi + 50, 2):g}" in notes[0]
