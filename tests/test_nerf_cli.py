"""End to end through the command lines: experiments.train_nerf and benchmarks.nerf."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks import nerf as bench
from vrs_jax.cli import train_nerf


@pytest.fixture(scope="module")
def dataset(toy_nerf):
    """The toy scene as a Blender-style NeRF dataset (conftest)."""
    return toy_nerf


def test_train_nerf_cli_writes_map_renders_metrics(dataset, tmp_path, capsys):
    out = tmp_path / "run"
    args = ["--format", "nerf", "--root", str(dataset), "--query-every", "4", "--near", "2",
            "--far", "6", "--config", "test", "--steps", "20", "--out", str(out), "--quiet"]
    assert train_nerf.main(args) == 0
    assert (out / "ilm.npz").is_file() and (out / "metrics.json").is_file()
    assert json.loads((out / "run.json").read_text())["config"]["args"]["steps"] == 20
    m = json.loads((out / "metrics.json").read_text())
    assert m["steps"] == 20 and m["held_out"] and len(m["views"]) == 2
    assert len(list((out / "renders").glob("*.png"))) == 2
    assert "held-out views: PSNR" in capsys.readouterr().out
    # A second run resumes (nothing left to do); --no-resume refuses to overwrite.
    assert train_nerf.main(args) == 0
    assert train_nerf.main(args + ["--no-resume"]) == 2
    assert "holds checkpoints" in capsys.readouterr().err
    # Missing near/far prior: a one-line error, exit status 2.
    assert train_nerf.main(["--format", "nerf", "--root", str(dataset), "--out",
                            str(tmp_path / "x"), "--config", "test", "--steps", "1"]) == 2
    assert "no depth prior" in capsys.readouterr().err


def test_benchmark_cli_table_and_json(dataset, tmp_path, capsys):
    js = tmp_path / "bench.json"
    assert bench.main(["--data", str(dataset), "--format", "nerf", "--near", "2", "--far", "6",
                       "--minutes", "0.1", "--config", "test", "--hold-out", "4", "--json",
                       str(js), "--quiet"]) == 0
    res = json.loads(js.read_text())
    r = res["results"][0]
    assert res["machine"]["versions"]["jax"] and r["config"] == "test" and r["steps"] >= 1
    for key in ("train_steps_per_s", "render_rays_per_s", "mlp_evals_per_s", "heldout_psnr"):
        assert np.isfinite(r[key]) and r[key] > 0
    assert -1 <= r["heldout_ssim"] <= 1 and r["eval"] == "2/2 full views"
    assert "render rays/s" in capsys.readouterr().out
    assert bench.main(["--data", str(dataset), "--format", "nerf", "--minutes", "0",
                       "--json", str(js)]) == 2
