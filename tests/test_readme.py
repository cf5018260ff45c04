"""The README is a contract: its Python example runs as written, and its results block is the
report's, generated, never typed."""

import re
from pathlib import Path

import numpy as np
import pytest

from safecdt_jax.paper.readme import END, START, results_block, sync_readme
from safecdt_jax.results import METRIC_NAMES

ROOT = Path(__file__).resolve().parents[1]


def _python_example() -> str:
    readme = (ROOT / "README.md").read_text()
    section = readme.split("\n## Python\n", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


@pytest.mark.slow
def test_readme_python_example_runs_and_returns_arrays(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("SAFECDT_CACHE", str(tmp_path / "cache"))
    scope: dict = {}
    exec(compile(_python_example(), "README.md", "exec"), scope)
    result, table = scope["result"], scope["table"]
    assert [r.variant for r in result.runs] == ["safe_cdt", "zero_shot"]
    for run in result.runs:
        assert tuple(run.metrics) == METRIC_NAMES
        assert run.cost.shape == run.reward.shape == run.violation.shape == (2, 2)
        assert np.array_equal(run.violation, run.cost > 30)
        assert run.summary["mean_cost_mean"] == pytest.approx(run.cost.mean(axis=1).mean())
    assert result.run("zero_shot") is result.runs[1]
    with pytest.raises(KeyError, match="no run 'naive_lora'; runs: safe_cdt B=30"):
        result.run("naive_lora")
    assert table.costs.shape == (3, 4) and list(table.target_cost) == [5, 20, 40]
    assert (tmp_path / "example" / "PointCircle1.hdf5").is_file()
    assert "safe_cdt" in capsys.readouterr().out
    written = result.write(tmp_path / "out")
    assert tmp_path / "out" / "results.json" in written


def test_readme_results_block_is_the_reports_table():
    readme = (ROOT / "README.md").read_text()
    block = readme.split(START, 1)[1].split(END, 1)[0].strip()
    assert block == results_block((ROOT / "report" / "REPORT.md").read_text())


def test_sync_readme_rewrites_only_between_the_markers(tmp_path):
    report = tmp_path / "REPORT.md"
    report.write_text((ROOT / "report" / "REPORT.md").read_text())
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{START}\nold table\n{END}\noutro\n")
    assert sync_readme(readme, report) is True
    text = readme.read_text()
    assert text.startswith("intro\n") and text.endswith(f"{END}\noutro\n")
    assert "old table" not in text and "| CG1→CG2 |" in text
    assert sync_readme(readme, report) is False  # already in sync: untouched
    readme.write_text("no markers\n")
    with pytest.raises(ValueError, match="lacks the results markers"):
        sync_readme(readme, report)
