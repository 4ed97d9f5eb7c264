"""Multi-process training (jax.distributed): 2 CPU processes on localhost vs 1 process."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from vrs_jax.data.readers import load_scene
from vrs_jax.errors import VrsError
from vrs_jax.nerf import distributed
from vrs_jax.nerf import train as T
from vrs_jax.nerf.config import get_config
from vrs_jax.nerf.ilm import load_ilm

REPO = Path(__file__).resolve().parents[1]
STEPS = 6
# evaluation, checkpoints and metric reads mid-run (every 3 steps): the collective paths
EVERY = {"eval_every": 3, "checkpoint_every": 3, "log_every": 3}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _start(args: list[str], ids) -> list[subprocess.Popen]:
    """The processes ``args + --process-id I`` for I in ``ids``, one CPU device each."""
    from conftest import xla_flags_with

    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO))
    env["XLA_FLAGS"] = xla_flags_with()  # one CPU device per process
    return [subprocess.Popen(args + ["--process-id", str(i)], cwd=REPO, env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            for i in ids]


def _finish(procs: list[subprocess.Popen], timeout: int, what: str) -> list[str]:
    """Each process's output once all exited with status 0 (test failure otherwise)."""
    logs = []
    for p in procs:
        try:
            logs.append(p.communicate(timeout=timeout)[0])
        except subprocess.TimeoutExpired:
            for q in procs:
                q.kill()
            pytest.fail(f"{what} did not finish in {timeout} s")
    for p, log in zip(procs, logs, strict=True):
        assert p.returncode == 0, log[-3000:]
    return logs


def test_two_processes_train_the_same_map_as_one(toy_nerf, tmp_path):
    root = toy_nerf
    out = tmp_path / "two"
    port = _free_port()
    args = [sys.executable, "-m", "experiments.train_nerf", "--format", "nerf", "--root",
            str(root), "--query-every", "4", "--near", "2", "--far", "6", "--config", "test",
            "--clusters", "2", "--steps", str(STEPS), "--views", "1", "--quiet",
            "--minutes", "10", *[a for k, v in EVERY.items() for a in ("--set", f"{k}={v}")],
            "--out", str(out), "--coordinator", f"localhost:{port}", "--num-processes", "2"]
    procs = _start(args, range(2))
    # Meanwhile, the single-process reference: same scene, config, seed and steps.
    cfg = get_config("test", n_clusters=2, **EVERY)
    scene = load_scene("nerf", root, query_every=4)
    ref = T.train(T.prepare(scene, cfg, near=2.0, far=6.0), None, steps=STEPS, progress=False)
    logs = _finish(procs, 240, "2-process training")
    assert "process 0 of 2: 1 local / 2 global device(s)" in logs[0]
    assert "process 1 of 2" in logs[1]
    # Both processes wrote one orbax checkpoint together; process 0 wrote the map.
    for step in (3, STEPS):
        assert (out / "checkpoints" / str(step) / "commit_success.txt").is_file()
    two = load_ilm(out / "ilm.npz")
    a, b = jax.tree.leaves(ref.ilm.fields.params), jax.tree.leaves(two.fields.params)
    assert len(a) == len(b)
    # Equal up to float rounding (one device runs both clusters batched, two run one each;
    # Adam's normalised steps carry the rounding: ~1e-4 after 6 steps). Another seed or a
    # cluster trained on the other process's data differs by ~1e-1.
    diff = max(float(np.max(np.abs(np.asarray(x) - np.asarray(y))))
               for x, y in zip(a, b, strict=True))
    assert diff < 2e-3, diff
    swapped = max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)[::-1])))
                  for x, y in zip(a, b, strict=True))
    assert swapped > 50 * diff  # the comparison tells the clusters apart
    m = json.loads((out / "metrics.json").read_text())
    assert m["steps"] == STEPS
    assert [h["step"] for h in m["history"]] == [h["step"] for h in ref.history] == [3, 6]
    for h2, h1 in zip(m["history"], ref.history, strict=True):
        assert abs(h2["loss"] - h1["loss"]) < 1e-3
        assert abs(h2["heldout_psnr"] - h1["heldout_psnr"]) < 0.05


def test_single_process_and_bad_settings(monkeypatch):
    for var in (distributed.ENV_COORDINATOR, distributed.ENV_NUM_PROCESSES,
                distributed.ENV_PROCESS_ID):
        monkeypatch.delenv(var, raising=False)
    assert distributed.initialize(None, None, None) is False
    assert distributed.initialize(None, 1, 0) is False
    with pytest.raises(VrsError, match="need --coordinator"):
        distributed.initialize(None, 2, 0)
    with pytest.raises(VrsError, match="not in 0..1"):
        distributed.initialize("localhost:1234", 2, 5)
    with pytest.raises(VrsError, match="HOST:PORT"):
        distributed.initialize("localhost", 2, 0)
    with pytest.raises(VrsError, match="single-process"):
        distributed.initialize(None, None, 3)
    assert not distributed.is_multiprocess()
    assert len(distributed.mesh_devices(2)) in (1, 2)


def test_two_processes_build_a_whole_map_in_one_command(small_synthetic_scene, tmp_path):
    """``experiments.train --num-processes 2``: process 0 builds the EGM while process 1
    waits for it, both train their cluster, process 0 writes the map, which loads with both
    clusters trained for every step."""
    from vrs_jax import maps

    out = tmp_path / "map"
    port = _free_port()
    args = [sys.executable, "-m", "experiments.train", "--format", "7scenes", "--root",
            str(small_synthetic_scene), "--config", "test", "--clusters", "2", "--steps",
            str(STEPS), "--quiet", *[a for k, v in EVERY.items() for a in ("--set", f"{k}={v}")],
            "--out", str(out), "--coordinator", f"localhost:{port}", "--num-processes", "2"]
    logs = _finish(_start(args, (1, 0)), 300, "2-process map build")
    assert "process 1 of 2" in logs[0] and "process 0 of 2" in logs[1]
    assert "EGM: features" in logs[1] and "EGM: features" not in logs[0]
    assert (out / "nerf" / "checkpoints" / str(STEPS) / "commit_success.txt").is_file()
    m = maps.load_map(out)
    assert m.ilm.fields.params is not None and int(m.cluster.max()) == 1
    assert json.loads((out / "map.json").read_text())["stats"]["ilm"]["steps"] == STEPS
    assert not (tmp_path / "map.lock").exists()
