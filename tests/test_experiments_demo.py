"""The README's first command, in its --quick form: the whole pipeline end to end."""

from __future__ import annotations

import json

import pytest


@pytest.mark.slow
def test_demo_quick_runs_end_to_end(tmp_path, capsys):
    from vrs_jax.cli import demo

    assert demo.main(["--quick", "--out", str(tmp_path / "demo"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "VRS-NeRF (rendered" in out and "Baseline (real" in out
    doc = json.loads((tmp_path / "demo" / "demo.json").read_text())
    rows = {r["mode"]: r for r in doc["rows"]}
    assert set(rows) == {"render", "real"}
    # the baseline (real patches) localizes the quick scene; render mode runs and reports
    assert rows["real"]["recall"]["5cm_5deg"] >= 0.75
    assert rows["render"]["n_queries"] == rows["real"]["n_queries"] == 8
    assert rows["render"]["map_bytes"]["total"] < rows["real"]["map_bytes"]["total"]
    # re-running skips every finished stage and gives the same baseline numbers
    assert demo.main(["--quick", "--out", str(tmp_path / "demo"), "--quiet"]) == 0
    doc2 = json.loads((tmp_path / "demo" / "demo.json").read_text())
    assert doc2["rows"][1]["recall"] == doc["rows"][1]["recall"]
