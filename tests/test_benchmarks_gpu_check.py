"""`python -m benchmarks.gpu_check --tiny`: every measurement runs and lands in JSON and a table."""

import json

import pytest


@pytest.mark.slow
def test_tiny_gpu_check_measures_everything_and_writes_json_and_markdown(tmp_path):
    from benchmarks.gpu_check import TINY, main

    out = tmp_path / "gpu_check.json"
    result = main(["--tiny", "--repeats", "1", "--out", str(out)])
    whats = [row["what"] for row in result["rows"]]
    assert len(whats) == len(TINY.env_batches) + len(TINY.presets) + 2
    assert any(w.startswith("deploy zero_shot, 2 seeds x 2 episodes") for w in whats)
    assert any(w.startswith("deploy safe_cdt") for w in whats)
    assert all(row["value"] > 0 and row["first_call_s"] > 0 for row in result["rows"])
    saved = json.loads(out.read_text())
    assert saved["rows"] == json.loads(json.dumps(result["rows"]))
    assert saved["machine"]["backend"] == "cpu"
    page = out.with_suffix(".md").read_text()
    assert page.startswith("# GPU check") and "| CDT updates/s, tiny, batch 16 |" in page


def test_gpu_check_rejects_a_negative_repeat_count(capsys):
    from benchmarks.gpu_check import main

    with pytest.raises(SystemExit):
        main(["--tiny", "--repeats", "-1"])
    assert "--repeats must be >= 0" in capsys.readouterr().err
