"""The README's first command, in its --quick form: the whole pipeline end to end."""

from __future__ import annotations

import json

import pytest


@pytest.mark.slow
def test_demo_quick_runs_end_to_end_and_the_readme_example_after_it(tmp_path, capsys,
                                                                     monkeypatch):
    from test_readme import _example

    from vrs_jax.cli import demo

    monkeypatch.chdir(tmp_path)  # the demo's default --out, outputs/demo, below tmp_path
    assert demo.main(["--quick", "--quiet"]) == 0
    captured = capsys.readouterr()
    out = captured.out
    assert "[3/3] map outputs/demo/map" in captured.out + captured.err
    assert "VRS-NeRF (rendered" in out and "Baseline (real" in out
    doc = json.loads((tmp_path / "outputs" / "demo" / "demo.json").read_text())
    rows = {r["mode"]: r for r in doc["rows"]}
    assert set(rows) == {"render", "real"}
    # the baseline (real patches) localizes the quick scene; render mode runs and reports
    assert rows["real"]["recall"]["5cm_5deg"] >= 0.75
    assert rows["render"]["n_queries"] == rows["real"]["n_queries"] == 8
    assert rows["render"]["map_bytes"]["total"] < rows["real"]["map_bytes"]["total"]
    # re-running skips every finished stage and gives the same baseline numbers
    assert demo.main(["--quick", "--quiet"]) == 0
    doc2 = json.loads((tmp_path / "outputs" / "demo" / "demo.json").read_text())
    assert doc2["rows"][1]["recall"] == doc["rows"][1]["recall"]
    # the README's Python block, pasted as printed after the demo
    ns: dict = {}
    exec(compile(_example(), "README.md", "exec"), ns)
    assert bool(ns["result"].success) != bool(ns["result"].fallback)
