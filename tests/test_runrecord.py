"""Run records and logging (vrs_jax.runrecord)."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import subprocess
from importlib import metadata
from pathlib import Path

import jax
import numpy as np
import pytest

from vrs_jax import runrecord


@dataclasses.dataclass(frozen=True)
class _Cfg:
    steps: int = 3
    path: Path = Path("a/b")
    sizes: tuple[int, int] = (4, 5)


def _git_head(where: Path) -> str | None:
    try:
        r = subprocess.run(["git", "-C", str(where), "rev-parse", "HEAD"], capture_output=True,
                           text=True, timeout=10)
    except OSError:
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def test_run_record_contents():
    argv = ["python", "-m", "experiments.x", "--out", "a dir", "--k=2"]
    rec = runrecord.run_record({"cfg": _Cfg(), "lr": np.float32(0.5), "bad": math.nan,
                                "root": Path("/data/x")}, argv, {"build": 1.25})
    assert rec["format"] == "vrs-jax run record" and rec["format_version"] == 1
    assert rec["command"] == "python -m experiments.x --out 'a dir' --k=2"
    assert rec["argv"] == argv
    assert rec["config"] == {"cfg": {"steps": 3, "path": "a/b", "sizes": [4, 5]}, "lr": 0.5,
                             "bad": None, "root": "/data/x"}
    assert rec["timings_s"] == {"build": 1.25}
    v = rec["versions"]
    assert set(v) == {"jax", "jaxlib", "flax", "optax", "optimistix", "orbax-checkpoint",
                      "pycolmap", "opencv", "numpy", "python"}
    assert v["jax"] == jax.__version__ == metadata.version("jax")
    assert v["numpy"] == np.__version__ and v["pycolmap"] == metadata.version("pycolmap")
    assert v["opencv"] is not None and v["python"].count(".") == 2
    assert rec["time_utc"].endswith("+00:00")
    assert rec["device"]["backend"] == jax.default_backend()
    assert rec["machine"]["cpu_count"] >= 1
    json.dumps(rec, allow_nan=False)  # strict JSON as it is
    # the commit of this checkout, when it is a git checkout
    head = _git_head(runrecord.CHECKOUT)
    if head is not None and Path(subprocess.run(
            ["git", "-C", str(runrecord.CHECKOUT), "rev-parse", "--show-toplevel"],
            capture_output=True, text=True).stdout.strip()).resolve() == runrecord.CHECKOUT:
        assert rec["code"]["commit"] == head and isinstance(rec["code"]["dirty"], bool)
    assert runrecord.run_record({}, [], None)["timings_s"] == {}


def test_git_info_outside_a_checkout(tmp_path):
    assert runrecord.git_info(tmp_path) == {"commit": None, "dirty": None}
    # a folder inside a repository is not that repository's top: no foreign commit
    assert runrecord.git_info(runrecord.CHECKOUT / "vrs_jax") == {"commit": None,
                                                                   "dirty": None}


def test_git_info_leaves_the_index_alone(tmp_path):
    """git_info never rewrites the checkout's index (``git --no-optional-locks``): a plain
    ``git status`` refreshes stale stat data in .git/index under .git/index.lock, and a run
    killed meanwhile left the lock behind in the user's checkout."""
    import os
    import shutil

    if shutil.which("git") is None:
        pytest.skip("git not installed")
    repo = tmp_path / "repo"
    repo.mkdir()
    env = dict(os.environ, GIT_AUTHOR_NAME="t", GIT_AUTHOR_EMAIL="t@t",
               GIT_COMMITTER_NAME="t", GIT_COMMITTER_EMAIL="t@t")
    f = repo / "a.txt"
    f.write_text("x\n")
    for args in (["init", "-q"], ["add", "a.txt"], ["commit", "-q", "-m", "a"]):
        subprocess.run(["git", "-C", str(repo), *args], check=True, env=env,
                       capture_output=True)
    st = f.stat()
    os.utime(f, ns=(st.st_atime_ns + 5 * 10**9, st.st_mtime_ns + 5 * 10**9))  # stale index
    index = (repo / ".git" / "index").read_bytes()
    info = runrecord.git_info(repo)
    assert info["commit"] == _git_head(repo) and info["dirty"] is False
    assert (repo / ".git" / "index").read_bytes() == index
    assert not (repo / ".git" / "index.lock").exists()


def test_write_run_record_never_overwrites(tmp_path):
    out = tmp_path / "run_out"
    recs = [{"n": k, "x": math.inf} for k in range(3)]
    paths = [runrecord.write_run_record(out, r) for r in recs]
    assert [p.name for p in paths] == ["run.json", "run-1.json", "run-2.json"]
    for k, p in enumerate(paths):
        assert json.loads(p.read_text()) == {"n": k, "x": None}
    assert sorted(q.name for q in out.iterdir()) == ["run-1.json", "run-2.json", "run.json"]
    # a gap is filled, an existing file is kept as it was
    (out / "run-1.json").unlink()
    (out / "run.json").write_text("keep")
    assert runrecord.write_run_record(out, {"n": 9}).name == "run-1.json"
    assert (out / "run.json").read_text() == "keep"


def test_setup_logging(capsys):
    log = logging.getLogger("vrs_jax.some.module")
    runrecord.setup_logging(verbose=False)
    runrecord.setup_logging(verbose=False)
    top = logging.getLogger("vrs_jax")
    assert sum(isinstance(h, runrecord._Handler) for h in top.handlers) == 1
    log.info("hello %d", 3)
    log.debug("hidden")
    err = capsys.readouterr().err
    assert err == "vrs_jax: hello 3\n"
    runrecord.setup_logging(verbose=True)
    log.debug("shown")
    assert capsys.readouterr().err == "vrs_jax: shown\n"
    runrecord.setup_logging(verbose=False)


@pytest.mark.parametrize("dists, found", [(("no-such-dist-xyz", "numpy"), True),
                                          (("no-such-dist-xyz",), False)])
def test_package_version(dists, found):
    assert (runrecord.package_version(*dists) == np.__version__) if found else \
        runrecord.package_version(*dists) is None
