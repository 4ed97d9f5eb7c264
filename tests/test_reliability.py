"""Issue 13, "no traceback and no lost result": the bad-input matrix as tests.

Every command-line case asserts the same contract: exit status 2, exactly one stderr line
starting ``error:`` that names the offending path, no traceback, no ``*.tmp`` left behind and
nothing that existed before modified. Unwritable folders are simulated in ways that hold for
root too (tests often run as root, where ``chmod`` stops nothing): a path whose parent is a
regular file (mkdir fails with ENOTDIR) and a folder under ``/proc``; a full disk is simulated
in a subprocess with ``RLIMIT_FSIZE`` (SIGXFSZ ignored, so writes fail with EFBIG).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from vrs_jax import fileio
from vrs_jax.errors import VrsError

REPO = Path(__file__).resolve().parents[1]
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


# ----------------------------------------------------------------------------- helpers


def snapshot(*roots: Path) -> dict[str, tuple[int, str]]:
    """{file: (mode, sha256)} of every file under ``roots``."""
    snap = {}
    for root in roots:
        for p in sorted(Path(root).rglob("*")):
            if p.is_file():
                snap[str(p)] = (p.stat().st_mode, hashlib.sha256(p.read_bytes()).hexdigest())
    return snap


def tmp_files(*roots: Path) -> list[Path]:
    return [p for r in roots if Path(r).exists() for p in Path(r).rglob("*.tmp")]


def assert_one_error_line(rc: int, err: str, names: str | Path) -> str:
    """Exit status 2, one ``error:`` line naming ``names``, no traceback."""
    assert rc == 2, err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, err
    assert str(names) in lines[0], (names, lines[0])
    return lines[0]


def run_cli(module: str, args: list[str], fsize: int | None = None, timeout: float = 240
            ) -> subprocess.CompletedProcess:
    """``python -m MODULE ARGS`` in a subprocess, optionally with files capped at ``fsize``
    bytes (a full disk: writes past it fail with EFBIG)."""
    pre = ""
    if fsize is not None:
        pre = (f"import resource, signal; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
               f"resource.setrlimit(resource.RLIMIT_FSIZE, ({fsize}, resource.RLIM_INFINITY)); ")
    code = f"{pre}import runpy, sys; sys.argv = ['{module}'] + {args!r}; " \
           f"runpy.run_module('{module}', run_name='__main__')"
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, text=True,
                          capture_output=True, timeout=timeout)


def interrupt_program(code: str, first_line: str, wait: float = 0.5,
                      path: Path | None = None) -> tuple[int, str, str]:
    """Run ``python -c CODE``, send SIGINT ``wait`` s after it prints ``first_line``:
    (exit status, rest of stdout, stderr)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(map(str, [REPO, path] if path else
                                                          [REPO]))}
    p = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env=env, text=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert p.stdout.readline() == first_line + "\n"
        time.sleep(wait)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=30)
    finally:
        p.kill()
    return p.returncode, out, err


def assert_interrupted(rc: int, err: str) -> None:
    """Status 130 and one 'interrupted' line, no traceback."""
    assert rc == 130, err
    assert err.startswith("interrupted") and err.count("\n") == 1 and "Traceback" not in err


def unwritable(tmp_path: Path, kind: str) -> Path:
    """An output path that cannot be created, even by root."""
    if kind == "parent_is_file":
        blocker = tmp_path / "blocker"
        blocker.write_text("a regular file\n")
        return blocker / "out"
    if kind == "proc":
        return Path("/proc/self/vrs_jax_out")
    d = tmp_path / "readonly"  # chmod: only stops non-root users
    d.mkdir()
    d.chmod(0o555)
    return d / "out"


UNWRITABLE = ["parent_is_file", "proc",
              pytest.param("chmod", marks=pytest.mark.skipif(
                  IS_ROOT, reason="running as root: chmod 0o555 does not stop writes (the "
                                  "parent_is_file and proc cases cover it)"))]


def nerf_args(root: Path, out: Path, steps: int, *extra: str) -> list[str]:
    return ["--format", "nerf", "--root", str(root), "--query-every", "4", "--near", "2",
            "--far", "6", "--config", "test", "--steps", str(steps), "--out", str(out),
            "--quiet", *extra]


# ----------------------------------------------------------------------------- --out unwritable


@pytest.mark.parametrize("kind", UNWRITABLE)
def test_unwritable_out_is_one_line_for_every_command(kind, tmp_path, capsys, tiny_map,
                                                      small_synthetic_scene, toy_nerf):
    from vrs_jax.cli import build_egm, localize, make_synthetic, train, train_nerf

    out = unwritable(tmp_path, kind)
    before = snapshot(tiny_map, small_synthetic_scene, toy_nerf, tmp_path)
    scene = ["--format", "7scenes", "--root", str(small_synthetic_scene)]
    cases = {
        "train": (train.main, scene + ["--out", str(out), "--config", "test", "--quiet"]),
        "build_egm": (build_egm.main, scene + ["--out", str(out), "--config", "test",
                                               "--quiet"]),
        "localize": (localize.main, ["--map", str(tiny_map), "--out", str(out), "--config",
                                     "test", "--quiet"]),
        "make_synthetic": (make_synthetic.main, ["--out", str(out), "--size", "16x12",
                                                 "--n-ref", "2", "--n-query", "0"]),
        "train_nerf": (train_nerf.main, nerf_args(toy_nerf, out, 1)),
    }
    for name, (main, args) in cases.items():
        rc = main(args)
        err = capsys.readouterr().err
        line = assert_one_error_line(rc, err, out if kind != "parent_is_file" else out.parent)
        print(f"{name}: {line}")
    assert snapshot(tiny_map, small_synthetic_scene, toy_nerf, tmp_path) == before
    assert not tmp_files(tmp_path)


@pytest.mark.parametrize("kind", UNWRITABLE)
def test_evaluate_json_into_unwritable_folder(kind, tmp_path, capsys, small_synthetic_scene):
    from vrs_jax.cli import evaluate

    res = tmp_path / "results.txt"
    res.write_text("seq-02/frame-000000.color.png 1 0 0 0 0 0 0\n")
    js = unwritable(tmp_path, kind) / "eval.json"
    before = snapshot(tmp_path)
    rc = evaluate.main(["--results", str(res), "--format", "7scenes", "--root",
                        str(small_synthetic_scene), "--json", str(js)])
    assert_one_error_line(rc, capsys.readouterr().err, js.parent.parent
                          if kind == "parent_is_file" else js.parent)
    assert snapshot(tmp_path) == before and not tmp_files(tmp_path)


def test_unreadable_results_file(capsys, small_synthetic_scene):
    from vrs_jax.cli import evaluate

    # /proc/self/mem is a regular file whose plain read fails (EIO), for root too
    rc = evaluate.main(["--results", "/proc/self/mem", "--format", "7scenes", "--root",
                        str(small_synthetic_scene)])
    line = assert_one_error_line(rc, capsys.readouterr().err, "/proc/self/mem")
    assert "cannot read" in line


# ----------------------------------------------------------------------------- corrupt inputs


@pytest.mark.parametrize("damage", ["map.json garbage", "map.json empty", "egm.npz truncated",
                                    "ilm.npz byte flipped", "descriptors.npz missing"])
def test_corrupt_map_files_are_one_line(damage, tiny_map, tmp_path, capsys):
    from vrs_jax.cli import localize

    m = tmp_path / "map"
    shutil.copytree(tiny_map, m, ignore=shutil.ignore_patterns("nerf"))
    name, what = damage.split(" ", 1)
    p = m / name
    if what == "garbage":
        p.write_bytes(b"{not json")
    elif what == "empty":
        p.write_bytes(b"")
    elif what == "truncated":
        p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    elif what == "byte flipped":
        raw = bytearray(p.read_bytes())
        raw[len(raw) // 2] ^= 0xFF
        p.write_bytes(bytes(raw))
    else:
        p.unlink()
    before = snapshot(m)
    out = tmp_path / "loc"
    rc = localize.main(["--map", str(m), "--out", str(out), "--config", "test", "--mode",
                        "real", "--quiet"])
    assert_one_error_line(rc, capsys.readouterr().err, p)
    assert snapshot(m) == before and not tmp_files(tmp_path)
    assert not (out / "results.txt").exists()


def test_image_contradicting_its_intrinsics_names_the_image(small_synthetic_scene, tmp_path):
    """An 8x8 image in a scene whose intrinsics say 160x120 is an error, not a silent
    rescale; a uniformly downscaled image (and --downscale) still works."""
    import cv2

    from vrs_jax.data import images
    from vrs_jax.data.readers import load_scene

    root = tmp_path / "room"
    shutil.copytree(small_synthetic_scene, root)
    ref = load_scene("7scenes", root)
    bad = ref.image_paths[3]
    img = cv2.imread(str(bad))
    # legitimate: the same image stored at half resolution (intrinsics scaled to match)
    cv2.imwrite(str(bad), cv2.resize(img, (80, 60), interpolation=cv2.INTER_AREA))
    half = load_scene("7scenes", root)
    np.testing.assert_allclose(half.K[3][:2], ref.K[3][:2] / 2, rtol=1e-9)
    # legitimate: --downscale 2 reads every image at 80x60 (K halved)
    down = load_scene("7scenes", root, downscale=2)
    assert tuple(down.sizes[0]) == (80, 60)
    assert images.read_image(down.image_paths[0], size=tuple(down.sizes[0])).shape == (60, 80,
                                                                                         3)
    # contradiction: another aspect ratio
    cv2.imwrite(str(bad), img[:8, :8])
    with pytest.raises(VrsError, match=r"8x8 pixels but its intrinsics are for 160x120") as e:
        load_scene("7scenes", root)
    assert e.value.path == str(bad)
    # the consumers check too (a file replaced after the scene was read)
    with pytest.raises(VrsError, match="another aspect ratio") as e:
        images.read_image(bad, size=(160, 120))
    assert e.value.path == str(bad)


# ----------------------------------------------------------------------------- disk full


def test_disk_full_while_saving_the_map(small_synthetic_scene, tmp_path):
    """The map's first data file hits the limit: one line naming it, nothing half-written."""
    out = tmp_path / "map"
    r = run_cli("experiments.train", ["--format", "7scenes", "--root",
                                      str(small_synthetic_scene), "--out", str(out),
                                      "--config", "test", "--quiet"], fsize=4096)
    line = assert_one_error_line(r.returncode, r.stderr, out / "egm.npz")
    assert "disk full" in line
    assert not tmp_files(out) and not (out / "map.json").exists()


def test_disk_full_at_the_first_nerf_checkpoint(toy_nerf, tmp_path):
    out = tmp_path / "run"
    r = run_cli("experiments.train_nerf", nerf_args(toy_nerf, out, 20, "--set",
                                                    "checkpoint_every=10"), fsize=1024)
    line = assert_one_error_line(r.returncode, r.stderr, out.absolute() / "checkpoints")
    assert "step 10" in line and "disk full" in line
    assert len(r.stderr.splitlines()) < 10, r.stderr  # not hundreds of orbax traceback lines
    assert not list((out / "checkpoints").glob("*.orbax-checkpoint-tmp*"))
    assert not tmp_files(out)


def test_rerun_of_a_finished_map_under_a_full_disk_changes_nothing(tiny_map, tmp_path):
    m = tmp_path / "map"
    shutil.copytree(tiny_map, m)
    meta = fileio.read_json(m / "map.json")
    before = snapshot(m)
    r = run_cli("experiments.train", ["--format", "7scenes", "--root",
                                      meta["source"]["root"], "--out", str(m), "--config",
                                      "test", "--quiet"], fsize=0)
    assert r.returncode == 0, r.stderr
    assert "already trained" in r.stdout + r.stderr  # progress lines are log lines
    assert snapshot(m) == before


@pytest.mark.skipif(IS_ROOT, reason="running as root: chmod 0o555 does not stop writes")
def test_rerun_of_a_finished_map_in_a_read_only_folder(tiny_map, tmp_path, capsys):
    from vrs_jax.cli import train

    m = tmp_path / "map"
    shutil.copytree(tiny_map, m)
    meta = fileio.read_json(m / "map.json")
    before = snapshot(m)
    for d in [m, *[p for p in m.rglob("*") if p.is_dir()]]:
        d.chmod(0o555)
    try:
        rc = train.main(["--format", "7scenes", "--root", meta["source"]["root"], "--out",
                         str(m), "--config", "test", "--quiet"])
        err = capsys.readouterr().err
        assert rc == 0 or (rc == 2 and "Traceback" not in err), err
    finally:
        for d in [m, *[p for p in m.rglob("*") if p.is_dir()]]:
            d.chmod(0o755)
    assert snapshot(m) == before


# ----------------------------------------------------------------------------- re-runs, resume


def test_longer_steps_continue_a_finished_map(tiny_map, small_synthetic_scene, tmp_path):
    """``train --steps N`` on a finished map of fewer steps continues training from the last
    checkpoint (not: 'already trained')."""
    import jax

    from vrs_jax import maps
    from vrs_jax.data.readers import load_scene

    m = tmp_path / "map"
    shutil.copytree(tiny_map, m)
    old = maps.load_map(m)
    steps = old.config.nerf.max_steps
    logs = []
    cfg = maps.get_config("test", max_steps=steps + 20)
    maps.build_map(load_scene("7scenes", small_synthetic_scene), m, cfg, progress=False,
                   log=logs.append)
    new = maps.load_map(m)
    assert new.config.nerf.max_steps == steps + 20
    assert maps.read_stats(m)["ilm"]["steps"] == steps + 20
    assert not any("already trained" in s for s in logs), logs
    changed = [not np.array_equal(np.asarray(x), np.asarray(y)) for x, y in
               zip(jax.tree.leaves(old.ilm.fields.params), jax.tree.leaves(new.ilm.fields.params),
                   strict=True)]
    assert any(changed)
    # and a shorter --steps is refused with one line
    with pytest.raises(VrsError, match="can only extend"):
        maps.build_map(load_scene("7scenes", small_synthetic_scene), m,
                       maps.get_config("test", max_steps=steps), progress=False,
                       log=logs.append)


def test_corrupt_latest_checkpoint_falls_back_to_the_previous(tmp_path):
    from vrs_jax.nerf import train as T
    from vrs_jax.nerf.config import get_config
    from vrs_jax.nerf.toy import make_toy_scene

    cfg = get_config("test", checkpoint_every=10, keep_checkpoints=3, eval_every=1000)
    scene = make_toy_scene(tmp_path / "toy", n_images=8, size=16, query_every=4)
    prep = T.prepare(scene, cfg, near=2.0, far=6.0)
    run = tmp_path / "run"
    T.train(prep, run, steps=30, progress=False)
    ckpt = run / "checkpoints"
    for p in (ckpt / "30" / "state").rglob("*"):
        if p.is_file():
            p.write_bytes(b"\x00garbage")
    logs: list[str] = []
    res = T.train(prep, run, steps=40, progress=False, log=logs.append)
    warn = [s for s in logs if s.startswith("warning:")]
    assert any(str(ckpt.absolute() / "30") in s for s in warn), logs
    assert any("resumed from step 20" in s for s in logs), logs
    assert int(res.state.step) == 40
    assert (ckpt.parent / "checkpoints-damaged").is_dir()  # set aside, not deleted
    # every checkpoint damaged: one VrsError naming the folder
    for d in ckpt.iterdir():
        for p in (d / "state").rglob("*"):
            if p.is_file():
                p.write_bytes(b"\x00garbage")
    with pytest.raises(VrsError, match="none of the .* checkpoint") as e:
        T.train(prep, run, steps=50, progress=False, log=logs.append)
    assert e.value.path == str(ckpt.absolute())


def start_training(args: list[str]) -> subprocess.Popen:
    """``train_nerf ARGS`` in a subprocess (stdout dropped, stderr piped as text)."""
    code = f"import sys; sys.argv = ['x'] + {args!r}; from vrs_jax.cli import train_nerf; " \
           "raise SystemExit(train_nerf.main())"
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env=env, text=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def wait_for_checkpoint(proc: subprocess.Popen, ckpt: Path, step: int) -> None:
    """Wait (2 minutes at most) until ``ckpt`` holds a checkpoint of ``step`` or later; the
    training must still be running."""
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        steps = [int(p.name) for p in ckpt.glob("*") if p.name.isdigit()] \
            if ckpt.is_dir() else []
        if steps and max(steps) >= step:
            break
        time.sleep(0.2)
    assert proc.poll() is None, "training finished before it could be stopped"


def test_kill9_during_training_then_resume(toy_nerf, tmp_path):
    """SIGKILL mid-training leaves whole checkpoints only; the same command resumes to the
    final step."""
    out = tmp_path / "run"
    args = nerf_args(toy_nerf, out, 150, "--set", "checkpoint_every=10", "--views", "1")
    proc = start_training(args)
    try:
        ckpt = out / "checkpoints"
        wait_for_checkpoint(proc, ckpt, 20)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "metrics.json").exists()
    r = run_cli("experiments.train_nerf", args)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    assert json.loads((out / "metrics.json").read_text())["steps"] == 150


def test_localize_bad_query_among_good_and_no_overwrite(tiny_map, small_synthetic_scene,
                                                        tmp_path):
    """A truncated query image is flagged in summary.json while the others are localized; a
    second run into the same --out refuses to overwrite the results."""
    root = tmp_path / "room"
    shutil.copytree(small_synthetic_scene, root)
    from vrs_jax.data.readers import load_scene

    q = load_scene("7scenes", root).queries()
    bad = q.image_paths[2]
    bad.write_bytes(bad.read_bytes()[:200])
    out = tmp_path / "loc"
    args = ["--map", str(tiny_map), "--out", str(out), "--config", "test", "--format",
            "7scenes", "--root", str(root), "--mode", "real", "--no-timing", "--quiet"]
    r = run_cli("experiments.localize", args)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    summary = json.loads((out / "summary.json").read_text())
    rows = {row["name"]: row for row in summary["per_query"]}
    assert rows[q.names[2]].get("error") and str(bad) in rows[q.names[2]]["error"]
    assert sum(1 for row in rows.values() if str(bad) in (row["error"] or "")) == 1
    assert sum(1 for row in rows.values() if row["success"]) == len(q) - 1
    before = snapshot(out)
    r2 = run_cli("experiments.localize", args)
    assert_one_error_line(r2.returncode, r2.stderr, out)
    assert "--overwrite" in r2.stderr
    assert snapshot(out) == before and not tmp_files(out)


# ----------------------------------------------------------------------------- file modes


def test_written_files_are_0644_minus_umask(tmp_path):
    from vrs_jax import runrecord
    from vrs_jax.data import images

    old = os.umask(0o027)
    try:
        fileio.write_text(tmp_path / "a.txt", "x")
        fileio.write_json(tmp_path / "b.json", {"x": 1})
        images.write_image(tmp_path / "c.png", np.zeros((4, 4, 3), np.float32))
        images.write_depth(tmp_path / "d.png", np.ones((4, 4), np.float32))
        rec = runrecord.write_run_record(tmp_path, {"x": 1})
    finally:
        os.umask(old)
    for p in [tmp_path / n for n in ("a.txt", "b.json", "c.png", "d.png")] + [rec]:
        assert (p.stat().st_mode & 0o777) == 0o640, (p, oct(p.stat().st_mode))
    assert not tmp_files(tmp_path)


def test_no_raw_writes_outside_fileio():
    """Every file vrs_jax/ and experiments/ write goes through vrs_jax.fileio (atomic, 0644,
    one-line errors); orbax and pycolmap write their own files (lines marked
    ``fileio-exempt``)."""
    import re

    pat = re.compile(r"\.write_text\(|\.write_bytes\(|open\([^)]*[\"'][wax]b?[\"']|np\.save|"
                     r"os\.replace\(|tempfile\.|cv2\.imwrite")
    allowed = {"vrs_jax/fileio.py", "vrs_jax/runrecord.py"}
    found = []
    for p in sorted([*(REPO / "vrs_jax").rglob("*.py"), *(REPO / "experiments").rglob("*.py")]):
        rel = p.relative_to(REPO).as_posix()
        if rel in allowed:
            continue
        for i, line in enumerate(p.read_text().splitlines(), 1):
            code = line.split("#", 1)[0]
            if (pat.search(code) and "fileio." not in code and "np.savez(buf" not in code
                    and "fileio-exempt" not in line):
                found.append(f"{rel}:{i}: {line.strip()}")
    assert not found, "\n".join(found)


def test_save_checkpoint_failure_is_one_line(tmp_path):
    """Orbax raising on save (here: the checkpoint folder replaced by a file) becomes one
    VrsError naming the folder."""
    from vrs_jax.nerf import train as T
    from vrs_jax.nerf.config import get_config

    cfg = get_config("test")
    blocker = tmp_path / "checkpoints"
    blocker.write_text("x")
    with pytest.raises(VrsError, match="not a folder") as e:
        T.checkpoint_manager(blocker, cfg)
    assert e.value.path == str(blocker.absolute())


# ----------------------------------------------------------------------------- issue 23: inputs


def test_unknown_config_field_suggests_the_close_one():
    """A misspelt field of any config kind names the field and suggests the closest ones."""
    from vrs_jax import localize, maps
    from vrs_jax.nerf.config import get_config, parse_overrides

    with pytest.raises(VrsError, match=r"unknown NeRF config field 'netwidth'; did you mean "
                                       r"'net_width'"):
        parse_overrides(["netwidth=64"])
    with pytest.raises(VrsError, match="did you mean 'net_width'"):
        get_config("test", netwidth=64)
    with pytest.raises(VrsError, match="did you mean 'net_width'"):
        maps.get_config("test", netwidth=64)
    with pytest.raises(VrsError, match=r"unknown localize config field 'topk'; did you mean "
                                       r"'top_k'"):
        localize.get_config("test", topk=3)
    with pytest.raises(VrsError, match=r"unknown NeRF config field 'zzzz'$"):
        parse_overrides(["zzzz=1"])  # nothing close: no suggestion


@pytest.mark.parametrize("version", ["4", 4.0, True, None])
def test_map_format_version_must_be_an_integer(version, tiny_map, tmp_path):
    """``"format_version": "4"`` is not read as version 4 (nor reported as 'version 4;
    this vrs-jax reads version 4')."""
    from vrs_jax import maps

    m = tmp_path / "map"
    m.mkdir()
    meta = fileio.read_json(tiny_map / "map.json")
    if version is None:
        del meta["format_version"]
    else:
        meta["format_version"] = version
    (m / "map.json").write_text(json.dumps(meta))
    want = "lacks 'format_version'" if version is None else \
        f"format_version must be an integer, got {version!r}"
    with pytest.raises(VrsError, match=re.escape(want)) as e:
        maps.load_map(m)
    assert e.value.path == str(m / "map.json")


def test_localize_zero_byte_and_non_image_queries_are_flagged(tiny_map, small_synthetic_scene,
                                                              tmp_path, capsys):
    """An empty and a non-image query file (a dataset folder, then a query list) are flagged
    with their reason in summary.json while the other queries are localized (not: the run
    aborted with exit 2)."""
    from vrs_jax.cli import localize as cli
    from vrs_jax.data.readers import load_scene

    root = tmp_path / "room"
    shutil.copytree(small_synthetic_scene, root)
    q = load_scene("7scenes", root).queries()
    q.image_paths[1].write_bytes(b"")
    q.image_paths[4].write_text("not an image\n")
    bad = {q.names[1]: q.image_paths[1], q.names[4]: q.image_paths[4]}
    listed = tmp_path / "queries.txt"
    listed.write_text("".join(f"{n} PINHOLE {w} {h} {K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n"
                              for n, (w, h), K in zip(q.names, q.sizes, q.K, strict=True)))
    common = ["--map", str(tiny_map), "--config", "test", "--mode", "real", "--no-timing",
              "--quiet"]
    for i, where in enumerate((["--format", "7scenes", "--root", str(root)],
                               ["--images", str(root), "--queries", str(listed)])):
        out = tmp_path / f"loc{i}"
        rc = cli.main(common + ["--out", str(out)] + where)
        err = capsys.readouterr().err
        assert rc == 0, err
        assert "Traceback" not in err
        rows = {r["name"]: r for r in
                json.loads((out / "summary.json").read_text())["per_query"]}
        assert len(rows) == len(q)
        for name, path in bad.items():
            assert not rows[name]["success"]
            assert str(path) in rows[name]["error"] and "unreadable image" in rows[name]["error"]
        good = [r for n, r in rows.items() if n not in bad]
        assert all(r["error"] is None for r in good)
        assert sum(r["success"] for r in good) >= len(good) - 1


@pytest.fixture(scope="module")
def real_localizer(tiny_map, small_synthetic_scene):
    """(Localizer in real mode, a query's grey image [120, 160], its K [3, 3])."""
    from vrs_jax.data.images import read_gray
    from vrs_jax.data.readers import load_scene
    from vrs_jax.localize import Localizer

    q = load_scene("7scenes", small_synthetic_scene).queries()
    return Localizer(tiny_map, "test", source="real"), read_gray(q.image_paths[0]), q.K[0]


def _bad_inputs(gray, K):
    """(case, image, K, dist, message regex) of query inputs every entry point refuses."""
    nan_K, tiny_K, row_K = K.copy(), K.copy(), K.copy()
    nan_K[0, 0] = np.nan
    tiny_K[0, 0] = tiny_K[1, 1] = 1e-6
    row_K[2, 2] = 2.0
    return [
        ("float 0-255", gray.astype(np.float64) * 255, K, None, "look like 0-255.*uint8"),
        ("int64 0-255", np.round(gray * 255).astype(np.int64), K, None, "look like 0-255"),
        ("ragged list", [[0.0, 0.1], [0.2]], K, None, "ragged nested list"),
        ("complex", gray.astype(np.complex64), K, None, "dtype complex64"),
        ("0x0", np.zeros((0, 0), np.float32), K, None, r"image is empty \(0x0"),
        ("NaN pixel", np.where(gray > 0.5, np.nan, gray), K, None, "non-finite values"),
        ("transposed", np.ascontiguousarray(gray.T), K, None,
         r"image is 120x160 but K's principal point is \(80, 60\)"),
        ("NaN K", gray, nan_K, None, "K has non-finite entries"),
        ("K 2x3", gray, K[:2], None, r"K must be a \[3, 3\] matrix, got shape \(2, 3\)"),
        ("fx 1e-6", gray, tiny_K, None, "below 1 pixel"),
        ("K last row", gray, row_K, None, r"K's last row must be \[0, 0, 1\]"),
        ("dist NaN", gray, K, [0, np.nan, 0, 0, 0], "dist has non-finite"),
        ("dist [3]", gray, K, [0.1, 0, 0], r"dist must be .*got shape \(3,\)"),
    ]


def test_every_localize_entry_point_validates_its_inputs(real_localizer):
    """Images of another dtype or range (a 0-255 float image was taken for [0, 1] and
    silently gave a fallback), shape, K and dist: one VrsError naming the argument from
    localize_image, localize_batch (flagged, the others localized), prepare_query and
    localize; a NaN K is not blamed on its shape, nor a 0x0 image on K's principal point."""
    from vrs_jax import localize

    loc, gray, K = real_localizer
    cases = _bad_inputs(gray, K)
    for case, image, K_, dist, msg in cases:
        with pytest.raises(VrsError, match=msg) as e:
            loc.localize_image(image, K_, dist)
        assert "\n" not in str(e.value), case
        with pytest.raises(VrsError, match=msg):
            localize.prepare_query(loc.map, image, K_, dist, loc.cfg)
    assert "shape" not in _message(loc, gray, cases[7][2])
    assert "principal point" not in _message(loc, cases[4][1], K)
    results, errors = loc.localize_batch([gray] + [c[1] for c in cases],
                                         [K] + [c[2] for c in cases],
                                         [None] + [c[3] for c in cases])
    assert errors[0] is None and results[0] is not None
    for i, (case, *_, msg) in enumerate(cases, 1):
        assert results[i] is None and re.search(msg, errors[i]), (case, errors[i])
        assert errors[i].startswith(f"image {i}: "), errors[i]
    # localize itself: a Query whose K is not a camera, arguments of another type
    q = localize.prepare_query(loc.map, gray, K, None, loc.cfg)
    with pytest.raises(VrsError, match="K has non-finite entries"):
        localize.localize(loc.map, q.replace(K=q.K.at[1, 1].set(np.inf)), loc.cfg)
    with pytest.raises(VrsError, match="query must be a Query, got ndarray"):
        localize.localize(loc.map, gray, loc.cfg)


def _message(loc, image, K) -> str:
    with pytest.raises(VrsError) as e:
        loc.localize_image(image, K)
    return str(e.value)


def test_valid_query_inputs_still_pass(real_localizer):
    """uint8 RGB, float grey in [0, 1] and nested lists of them, a [4] distortion, a K of a
    uniformly downscaled image: accepted, the same arrays as before."""
    from vrs_jax.localize.query import validate

    _, gray, K = real_localizer
    g8 = np.round(gray * 255).astype(np.uint8)
    rgb8 = np.repeat(g8[..., None], 3, axis=-1)
    np.testing.assert_allclose(validate(rgb8, K, None)[0], g8 / 255.0, atol=1e-6)
    np.testing.assert_array_equal(validate(gray.astype(np.float64).tolist(), K, None)[0], gray)
    _, K2, d = validate(gray, K.tolist(), [0.1, 0.01, 0, 0])
    np.testing.assert_array_equal(K2, K)
    np.testing.assert_array_equal(d, [0.1, 0.01, 0, 0, 0])
    half = K.copy()
    half[:2] /= 2
    validate(gray[::2, ::2], half, np.zeros(5))


# ----------------------------------------------------------------------------- issue 23


def test_evaluate_json_never_overwrites(tmp_path, capsys, small_synthetic_scene):
    """``--json`` pointed at an existing file (here the results file itself) is refused with
    one line unless --overwrite."""
    from vrs_jax.cli import evaluate

    res = tmp_path / "results.txt"
    res.write_text("seq-02/frame-000000.color.png 1 0 0 0 0 0 0\n")
    base = ["--results", str(res), "--format", "7scenes", "--root", str(small_synthetic_scene)]
    before = snapshot(tmp_path)
    line = assert_one_error_line(evaluate.main([*base, "--json", str(res)]),
                                 capsys.readouterr().err, res)
    assert "--overwrite" in line and snapshot(tmp_path) == before
    other = tmp_path / "eval.json"
    other.write_text("{}\n")
    assert evaluate.main([*base, "--json", str(other), "--overwrite"]) == 0
    assert "median" in json.dumps(json.loads(other.read_text()))


def test_output_folder_lock(tmp_path):
    """The lock is exclusive; a lock of a dead process is taken over with a warning."""
    out = tmp_path / "run"
    with fileio.folder_lock(out) as d:
        assert d == out and fileio.lock_path(out).is_file()
        with pytest.raises(VrsError, match=f"in use by process {os.getpid()}") as e:
            with fileio.folder_lock(out):
                pass
        assert e.value.path == str(out)
    assert not fileio.lock_path(out).exists()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    fileio.lock_path(out).write_text(f"{dead.pid} {os.uname().nodename}\n")
    warned = []
    with fileio.folder_lock(out, warn=warned.append):
        assert fileio.lock_path(out).read_text().split()[0] == str(os.getpid())
    assert len(warned) == 1 and str(dead.pid) in warned[0]


@pytest.mark.parametrize("command", ["localize", "train", "train_nerf"])
def test_second_run_into_a_locked_folder_is_refused(command, tmp_path, capsys, tiny_map,
                                                    small_synthetic_scene):
    from vrs_jax.cli import localize, train, train_nerf

    out = tmp_path / "out"
    owner = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        fileio.lock_path(out).write_text(f"{owner.pid} {os.uname().nodename}\n")
        args = {"localize": (localize.main, ["--map", str(tiny_map), "--out", str(out),
                                             "--config", "test", "--quiet"]),
                "train": (train.main, ["--format", "7scenes", "--root",
                                       str(small_synthetic_scene), "--out", str(out),
                                       "--config", "test", "--quiet"]),
                "train_nerf": (train_nerf.main, ["--format", "7scenes", "--root",
                                                 str(small_synthetic_scene), "--out", str(out),
                                                 "--config", "test", "--quiet"])}
        main, argv = args[command]
        line = assert_one_error_line(main(argv), capsys.readouterr().err, out)
        assert f"process {owner.pid}" in line
        assert not out.exists()
    finally:
        owner.kill()
        owner.wait()


def test_localize_run_folder_is_a_transaction(tiny_map, tmp_path, capsys, monkeypatch):
    """A run that fails while writing (a full disk at summary.json) leaves the earlier run's
    files as they were (with --overwrite too) and no --out at all when there was none; a
    complete --overwrite run replaces the folder as a whole."""
    from vrs_jax.cli import localize

    out = tmp_path / "loc"
    args = ["--map", str(tiny_map), "--out", str(out), "--config", "test", "--mode", "real",
            "--no-timing", "--quiet"]
    real_write_json = fileio.write_json

    def full_disk(path, obj):
        if Path(path).name == "summary.json":
            raise VrsError("cannot write: no space left on the device", path)
        return real_write_json(path, obj)

    monkeypatch.setattr(fileio, "write_json", full_disk)
    assert_one_error_line(localize.main(args), capsys.readouterr().err, out / "summary.json")
    assert not out.exists() and list(tmp_path.iterdir()) == []
    monkeypatch.setattr(fileio, "write_json", real_write_json)
    assert localize.main(args) == 0
    (out / "note.txt").write_text("from the earlier run\n")
    before = snapshot(out)
    monkeypatch.setattr(fileio, "write_json", full_disk)
    assert_one_error_line(localize.main([*args, "--overwrite"]), capsys.readouterr().err,
                          out / "summary.json")
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["loc"]
    monkeypatch.setattr(fileio, "write_json", real_write_json)
    assert localize.main([*args, "--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["results.txt", "run.json", "summary.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["loc"]


def test_staged_folder_recovers_a_swap_cut_by_a_kill(tmp_path):
    """A kill between the swap's two renames leaves FOLDER.old-PID and no FOLDER: the next
    staged write puts the old folder back before it starts (and drops the dead staging)."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    d = tmp_path / "map"
    old = tmp_path / f"map.old-{dead.pid}"
    old.mkdir()
    (old / "a.txt").write_text("old\n")
    (tmp_path / f"map.tmp-{dead.pid}").mkdir()
    with fileio.staged_folder(d, carry=["a.txt"]) as tmp:
        assert (tmp / "a.txt").read_text() == "old\n"
        fileio.write_text(tmp / "b.txt", "new\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map"]
    assert sorted(p.name for p in d.iterdir()) == ["a.txt", "b.txt"]


def test_map_records_its_dataset_and_refuses_another(tiny_map, small_synthetic_scene,
                                                     tmp_path, capsys):
    """map.json records the dataset (resolved root, format, split, fingerprint of the
    reference names, sizes and poses); training into it from another dataset is one line,
    the same dataset (here copied elsewhere) resumes as before."""
    from vrs_jax.cli import train

    meta = fileio.read_json(tiny_map / "map.json")
    prov = meta["provenance"]
    assert prov["root"] == str(Path(small_synthetic_scene).resolve())
    assert prov["format"] == "7scenes" and len(prov["fingerprint"]) == 64
    assert prov["split"]["n_reference"] == len(meta["names"])
    m = tmp_path / "map"
    shutil.copytree(tiny_map, m)
    same, other = tmp_path / "same", tmp_path / "other"
    shutil.copytree(small_synthetic_scene, same)
    shutil.copytree(small_synthetic_scene, other)
    pose = other / "seq-01" / "frame-000003.pose.txt"
    rows = np.loadtxt(pose)
    rows[0, 3] += 0.01  # one reference pose moved by a centimetre
    np.savetxt(pose, rows)
    before = snapshot(m)
    args = ["--format", "7scenes", "--out", str(m), "--config", "test", "--quiet", "--root"]
    line = assert_one_error_line(train.main([*args, str(other)]), capsys.readouterr().err, m)
    assert f"{m} was built from {prov['root']} (fingerprint {prov['fingerprint'][:12]}" in line
    assert f"not {other.resolve()}" in line
    assert snapshot(m) == before
    assert train.main([*args, str(same)]) == 0
    assert "already trained" in capsys.readouterr().err


def test_steps_below_one_are_refused_at_parsing(capsys, tmp_path):
    from vrs_jax.cli import train, train_nerf

    for main in (train.main, train_nerf.main):
        for steps in ("0", "-5"):
            with pytest.raises(SystemExit) as e:
                main(["--format", "nerf", "--root", str(tmp_path), "--out",
                      str(tmp_path / "o"), "--steps", steps])
            assert e.value.code == 2
            err = capsys.readouterr().err
            assert f"--steps: invalid count {steps}: must be >= 1" in err
            assert "Traceback" not in err and not (tmp_path / "o").exists()


def test_psnr_collapse_stops_training(small_synthetic_scene, tmp_path):
    """lr 1e4 collapses the training PSNR (12.9 -> 3.9 dB on the room): stopped at the second
    host read (the level is a median of recent reads), and the collapsed state of the first
    is not saved although a checkpoint was due there."""
    from vrs_jax.data.readers import load_scene
    from vrs_jax.nerf import train as T
    from vrs_jax.nerf.config import get_config

    cfg = get_config("test", lr_init=1e4, lr_final=1e4, log_every=10, checkpoint_every=10,
                     eval_every=1000)
    prep = T.prepare(load_scene("7scenes", small_synthetic_scene), cfg)
    with pytest.raises(T.TrainingDiverged, match=r"diverged by step 20 \(cluster 0: training "
                                                 r"PSNR collapsed to .*no checkpoint"):
        T.train(prep, tmp_path / "run", steps=40, progress=False)
    assert not list((tmp_path / "run" / "checkpoints").glob("[0-9]*"))


def test_psnr_collapse_check_ignores_one_noisy_read():
    """One small batch's PSNR swings by several dB: a single low read (after a lucky high one)
    only holds back the checkpoint; a drop that persists stops training at its second read;
    a non-finite read stops at once."""
    from vrs_jax.nerf import train as T

    def read(*psnr):
        return {"psnr": np.array(psnr), "loss": np.zeros(len(psnr)),
                "finite": np.ones(len(psnr), bool)}

    h = T.Health()
    h.update(np.array([20.0, 20.0]))
    for p in (21.0, 27.0, 20.5, 14.5, 21.0, 20.0, 14.0, 20.5, 21.0):  # noise, two outliers
        suspect = T.check_health(read(20.0, p), h, 100, 0, "run")
        assert suspect == (p < 15.0)  # below the best level 21 - 6: held back, not stopped
    assert T.check_health(read(20.0, 12.0), h, 200, 100, "run")
    with pytest.raises(T.TrainingDiverged, match=r"step 300 \(cluster 1: training PSNR "
                                                 r"collapsed to 11.0 dB from 21.0\); .*step 100"):
        T.check_health(read(20.0, 11.0), h, 300, 100, "run")
    bad = read(20.0, 20.0)
    bad["finite"] = np.array([True, False])
    with pytest.raises(T.TrainingDiverged, match="cluster 1: loss"):
        T.check_health(bad, T.Health(), 10, None, "run")


def test_load_map_refuses_an_untrained_or_non_finite_nerf(tiny_map, tmp_path):
    import jax

    from vrs_jax import maps

    m = maps.load_map(tiny_map)
    stats = maps.read_stats(tiny_map)
    never = maps.save_map(m, tmp_path / "never", {**stats, "ilm": {"steps": 0}})
    with pytest.raises(VrsError, match="never trained") as e:
        maps.load_map(never)
    assert e.value.path == str(never / "ilm.npz")
    params = jax.tree.map(lambda x: x.at[(0,) * x.ndim].set(np.nan),
                          m.ilm.fields.params)
    nan = m.replace(ilm=m.ilm.replace(fields=m.ilm.fields.replace(params=params)))
    with pytest.raises(VrsError, match="non-finite"):
        maps.load_map(maps.save_map(nan, tmp_path / "nan", stats))


def test_sigterm_during_training_is_a_clean_stop(toy_nerf, tmp_path):
    """SIGTERM mid-training: one line on stderr (no native stack), exit status 143, whole
    checkpoints only."""
    out = tmp_path / "run"
    args = nerf_args(toy_nerf, out, 400, "--set", "checkpoint_every=10", "--views", "1")
    proc = start_training(args)
    ckpt = out / "checkpoints"
    try:
        wait_for_checkpoint(proc, ckpt, 10)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "Traceback" not in err and "Fatal" not in err, err
    assert [ln for ln in err.splitlines() if ln.strip()] == [
        "terminated (SIGTERM); what was saved is kept: re-run the same command to continue"]
    assert not list(ckpt.glob("*.orbax-checkpoint-tmp*"))


def test_two_builds_of_one_dataset_give_identical_maps(tiny_map, small_synthetic_scene, tmp_path):
    """The same dataset and config, built again in another process (another hash seed, another
    load on the machine): every array of the map is the same to the bit, and map.json differs
    only in its measured times and the byte counts of its own timing text."""
    out = tmp_path / "again"
    code = ("import sys; from vrs_jax import maps; from vrs_jax.data.readers import load_scene; "
            "maps.build_map(load_scene('7scenes', sys.argv[1]), sys.argv[2], "
            "maps.get_config('test'), progress=False, log=lambda s: None)")
    subprocess.run([sys.executable, "-c", code, str(small_synthetic_scene), str(out)],
                   check=True, timeout=600)
    for name in ("egm.npz", "descriptors.npz", "ilm.npz"):
        with np.load(tiny_map / name) as a, np.load(out / name) as b:
            assert sorted(a.files) == sorted(b.files), name
            for k in a.files:
                assert a[k].tobytes() == b[k].tobytes(), f"{name}:{k}"
    a, b = (fileio.read_json(d / "map.json") for d in (tiny_map, out))
    assert {k: v for k, v in a.items() if k != "stats"} == {k: v for k, v in b.items()
                                                            if k != "stats"}


def test_sigterm_waits_for_a_deferred_block_then_stops():
    """A SIGTERM inside ``sigterm_deferred`` (a checkpoint being written) lets the block end,
    then stops with Terminated; outside one it stops at once."""
    from vrs_jax.errors import Terminated, sigterm_deferred, sigterm_stops

    done = []
    with sigterm_stops():
        with pytest.raises(Terminated):
            with sigterm_deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)  # the handler runs: it only notes the signal
                done.append("whole")
        assert done == ["whole"]
        with pytest.raises(Terminated):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1.0)


# ----------------------------------------------------------------------------- issue 23, re-sweep


@pytest.mark.parametrize("item", [
    "batch_size=0", "batch_size=-5", "lr_init=nan", "lr_init=inf", "lr_init=-1", "lr_final=0",
    "hash_log2_table=40", "n_clusters=0", "num_samples_coarse=0", "net_width=0",
    "max_steps=0", "checkpoint_every=0", "log_every=0", "eval_every=0", "render_chunk=0",
    "eval_rays=0", "keep_checkpoints=0", "hash_levels=0", "adam_eps=nan", "norm_radius=0",
    "near_far_percentiles=nan,99", "near_far_percentiles=99,1", "near_far_percentiles=1,2,3",
    "cluster_overlap=-1", "patch_ray_fraction=1.5", "patch_ray_fraction=nan", "seed=-1",
    "contraction=maybe", "name=zzz"])
def test_set_values_out_of_range_are_one_line(item):
    """Each of these ran before as a ZeroDivisionError or shape traceback, or trained a map
    that silently never learned (lr nan, 3 steps: exit 0)."""
    from vrs_jax.nerf.config import get_config, parse_overrides

    with pytest.raises(VrsError) as e:
        get_config("test", **parse_overrides([item]))
    key = item.partition("=")[0]
    assert key in str(e.value) and "\n" not in str(e.value)


def test_set_values_in_range_still_pass():
    from vrs_jax.nerf.config import CONFIGS, get_config, parse_overrides

    assert all(get_config(n) is CONFIGS[n] for n in CONFIGS)
    get_config("test", **parse_overrides(["patch_ray_fraction=0", "grad_max_norm=0",
                                          "num_samples_fine=0", "lr_delay_steps=0",
                                          "hash_log2_table=20", "near_far_percentiles=0,100"]))


@pytest.mark.parametrize("edit", ["nerf batch_size 0", "null names", "null k_max",
                                  "null files", "files sha256 int", "stats str",
                                  "stats ilm steps str"])
def test_hand_edited_map_json_values_are_one_line(edit, tiny_map, tmp_path):
    from vrs_jax import maps

    d = tmp_path / "map"
    shutil.copytree(tiny_map, d, ignore=shutil.ignore_patterns("nerf"))
    meta = json.loads((d / "map.json").read_text())
    if edit == "nerf batch_size 0":
        meta["config"]["nerf"]["batch_size"] = 0
    elif edit == "files sha256 int":
        meta["files"]["egm.npz"]["sha256"] = 5
    elif edit == "stats str":  # was an AttributeError traceback
        meta["stats"] = "x"
    elif edit == "stats ilm steps str":  # was a TypeError traceback
        meta["stats"]["ilm"]["steps"] = "800"
    else:
        meta[edit.split()[1]] = None
    (d / "map.json").write_text(json.dumps(meta))
    with pytest.raises(VrsError) as e:
        maps.load_map(d)
    assert str(d / "map.json") in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("cmd,flags", [
    ("train", ["--minutes", "nan"]), ("train", ["--minutes", "-1"]),
    ("train", ["--query-every", "-1"]), ("train", ["--downscale", "0"]),
    ("train_nerf", ["--minutes", "0"]), ("train_nerf", ["--near", "nan"]),
    ("train_nerf", ["--far", "-1"]), ("train_nerf", ["--views", "0"]),
    ("train_nerf", ["--num-processes", "0"]), ("localize", ["--top-k", "0"]),
    ("evaluate", ["--query-every", "-2"])])
def test_numeric_flags_out_of_range_are_refused_at_parsing(cmd, flags, capsys, tmp_path):
    """--minutes nan/-1 ran 0 steps and exited 0; --views 0 wrote a nan PSNR."""
    import importlib

    main = importlib.import_module(f"vrs_jax.cli.{cmd}").main
    base = {"localize": ["--map", str(tmp_path / "m"), "--out", str(tmp_path / "o")],
            "evaluate": ["--results", str(tmp_path / "r.txt"), "--format", "nerf", "--root",
                         str(tmp_path)]}.get(cmd, ["--format", "nerf", "--root", str(tmp_path),
                                                   "--out", str(tmp_path / "o")])
    with pytest.raises(SystemExit) as e:
        main([*base, *flags])
    err = capsys.readouterr().err
    assert e.value.code == 2 and flags[0] in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_outputs_never_replace_an_input_even_with_overwrite(tiny_map, small_synthetic_scene,
                                                            tmp_path, capsys):
    """Before: ``localize --out MAP --overwrite`` replaced the map by the run folder,
    ``evaluate --json RESULTS --overwrite`` the results file, ``train_nerf --out MAP`` the
    map's ilm.npz (the map then refused to load)."""
    from vrs_jax.cli import build_egm, evaluate, localize, train_nerf

    m = tmp_path / "map"
    shutil.copytree(tiny_map, m)
    res = tmp_path / "run" / "results.txt"
    res.parent.mkdir()
    res.write_text("seq-02/frame-000000.color.png 1 0 0 0 0 0 0\n")
    scene = str(small_synthetic_scene)
    before = snapshot(m, res.parent, small_synthetic_scene)
    loc = ["--map", str(m), "--config", "test", "--mode", "real", "--quiet", "--overwrite"]
    ev = ["--results", str(res), "--format", "7scenes", "--root", scene, "--overwrite"]
    ds = ["--format", "7scenes", "--root", scene, "--config", "test", "--quiet"]
    cases = [
        (localize.main, [*loc, "--out", str(m)], m),
        (localize.main, [*loc, "--out", str(tmp_path)], tmp_path),  # holds the map
        (localize.main, [*loc, "--out", scene, "--format", "7scenes", "--root", scene], scene),
        (localize.main, [*loc, "--out", str(m / "nerf")], m / "nerf"),
        (evaluate.main, [*ev, "--json", str(res)], res),
        (evaluate.main, [*ev, "--json", str(res.parent)], res.parent),
        (evaluate.main, [*ev, "--json", str(m / "map.json")], m / "map.json"),
        (train_nerf.main, [*ds, "--out", str(m), "--steps", "2"], m),
        (train_nerf.main, [*ds, "--out", scene, "--steps", "2"], scene),
        (train_nerf.main, [*ds, "--out", str(res.parent), "--steps", "2"], res.parent),
        (build_egm.main, [*ds, "--out", str(tmp_path / "e"), "--export-colmap", scene,
                          "--overwrite"], scene),
    ]
    for main, args, named in cases:
        assert_one_error_line(main(args), capsys.readouterr().err, named)
    assert snapshot(m, res.parent, small_synthetic_scene) == before
    assert not (tmp_path / "e").exists()


def test_reader_bad_files_are_one_line(tmp_path):
    """A zero-byte or string poses_bounds.npy (EOFError, TypeError) and a transforms.json
    with ``w: 0`` (ZeroDivisionError) were tracebacks."""
    import cv2

    from vrs_jax.data.readers import load_scene

    llff = tmp_path / "llff"
    (llff / "images").mkdir(parents=True)
    cv2.imwrite(str(llff / "images" / "a.png"), np.zeros((6, 8, 3), np.uint8))
    for content in (b"", None):
        if content is None:
            np.save(llff / "poses_bounds.npy", np.full((1, 17), "a"))
        else:
            (llff / "poses_bounds.npy").write_bytes(content)
        with pytest.raises(VrsError, match="poses_bounds.npy"):
            load_scene("llff", llff)
    nerf = tmp_path / "nerf"
    nerf.mkdir()
    cv2.imwrite(str(nerf / "a.png"), np.zeros((6, 8, 3), np.uint8))
    (nerf / "transforms.json").write_text(json.dumps({
        "fl_x": 5, "cx": 4, "cy": 3, "w": 0, "h": 6,
        "frames": [{"file_path": "a", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(VrsError, match="w, h must be positive"):
        load_scene("nerf", nerf)


def test_localizer_keeps_the_config_source_and_checks_its_arguments(tiny_map):
    """``Localizer(m, cfg)`` replaced ``cfg.source = "real"`` by "render" (its ``source``
    default), so ``experiments.localize --sequence --mode real`` rendered; a negative cache
    size was accepted, ``warmup(-5, 3)`` was a numpy traceback."""
    from vrs_jax import localize, maps
    from vrs_jax.data.synthetic import SyntheticConfig

    m = maps.load_map(tiny_map)
    assert localize.Localizer(m, localize.get_config("test", source="real")).cfg.source == \
        "real"
    assert localize.Localizer(m, "test").cfg.source == "render"
    assert localize.Localizer(m, "test", source="real").cfg.source == "real"
    for mb in (-1, float("nan")):
        with pytest.raises(VrsError, match="cache_mb"):
            localize.Localizer(m, "test", cache_mb=mb)
    with pytest.raises(VrsError, match="width must be an integer >= 1"):
        localize.Localizer(m, "test").warmup(-5, 3)
    with pytest.raises(VrsError, match="seed"):
        SyntheticConfig(seed=-1)


def test_a_missing_query_image_is_flagged_not_dropped_or_fatal(tmp_path):
    """A query list naming one missing image stopped the whole run; a 7-Scenes test frame
    whose image was deleted vanished from the queries (its pose file skipped with a
    warning), so recall was computed without it. Both are now queries that localizing flags
    ("image not found"); a list none of whose images exists is still one error line."""
    import cv2

    from vrs_jax.data.images import read_gray
    from vrs_jax.data.readers import load_scene
    from vrs_jax.data.readers.query_list import query_scene

    img = tmp_path / "images"
    img.mkdir()
    cv2.imwrite(str(img / "a.png"), np.zeros((6, 8, 3), np.uint8))
    ql = tmp_path / "q.txt"
    ql.write_text("a.png PINHOLE 8 6 10 11 4 3\nb.png PINHOLE 8 6 10 11 4 3\n")
    s = query_scene(ql, img)
    assert s.names == ["a.png", "b.png"]
    with pytest.raises(VrsError, match="image not found"):
        read_gray(s.image_paths[1])
    ql.write_text("b.png PINHOLE 8 6 10 11 4 3\n")
    with pytest.raises(VrsError, match="image of query b.png"):
        query_scene(ql, img)

    root = tmp_path / "seven"
    pose = "1 0 0 0.5\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"
    for seq in ("seq-01", "seq-02"):
        (root / seq).mkdir(parents=True)
        for k in range(3):
            cv2.imwrite(str(root / seq / f"frame-{k:06d}.color.png"),
                        np.full((6, 8, 3), 90, np.uint8))
            (root / seq / f"frame-{k:06d}.pose.txt").write_text(pose)
    (root / "TrainSplit.txt").write_text("sequence1\n")
    (root / "TestSplit.txt").write_text("sequence2\n")
    (root / "seq-02" / "frame-000001.color.png").unlink()
    q = load_scene("7scenes", root).queries()
    assert "seq-02/frame-000001.color.png" in q.names and len(q) == 3
    with pytest.raises(VrsError, match="image not found"):
        read_gray(q.image_paths[q.names.index("seq-02/frame-000001.color.png")])


def test_ctrl_c_inside_a_host_callback_is_a_clean_stop(capsys):
    """Ctrl-C during ``experiments.localize`` lands in OpenCV's RANSAC, a jax host callback,
    and came back as an XLA runtime error: a traceback and exit status 1 (or, after the
    "interrupted" line, a SIGSEGV in the interpreter's teardown). Both wrappings stop
    cleanly now: exit status 130 and one line."""
    from vrs_jax.errors import cli_main

    class XlaRuntimeError(RuntimeError):
        pass

    def wrapped(_):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise XlaRuntimeError("INTERNAL: CpuCallback error") from e

    def message_only(_):
        raise XlaRuntimeError("INTERNAL: CpuCallback error: KeyboardInterrupt: <EMPTY MESSAGE>")

    for fn in (wrapped, message_only):
        assert cli_main(fn)(None) == 130
        err = capsys.readouterr().err
        assert err.startswith("interrupted") and err.count("\n") == 1 and "Traceback" not in err
    with pytest.raises(XlaRuntimeError):
        cli_main(lambda _: (_ for _ in ()).throw(XlaRuntimeError("another failure")))(None)


def test_write_checks_of_two_processes_do_not_collide(tmp_path, monkeypatch):
    """Processes of one multi-process run check the same output folder at once: each uses its
    own probe file, so one's clean-up never removes the other's (a race seen under load)."""
    import os

    from vrs_jax import fileio

    seen = []
    real_write = type(tmp_path).write_bytes

    def write(self, data):
        seen.append(self.name)
        return real_write(self, data)

    monkeypatch.setattr(type(tmp_path), "write_bytes", write)
    fileio.check_writable(tmp_path / "ckpt")
    assert seen == [f".vrs_jax_write_test.{os.getpid()}"]
    assert list((tmp_path / "ckpt").iterdir()) == []


# ----------------------------------------------------------------------------- benchmarks' outputs


def test_benchmark_outputs_are_never_replaced_silently(tiny_map, tmp_path, capsys):
    """Before: every ``python -m benchmarks.NAME --json F`` (and ``--plot``, ``--figure``,
    the figures of ``benchmarks.figures --out``) replaced an existing F without a word, and
    ``--plot``/``--figure`` into a map folder replaced the map's files. Now an existing file
    is refused before any work unless --overwrite; a map's file never, even with it."""
    from benchmarks import (
        ablation,
        clusters,
        confidence,
        fidelity,
        figures,
        localize,
        map_size,
        nerf,
        render,
        shard,
        sift_reference,
        stream,
        track,
    )

    old = tmp_path / "old.json"
    old.write_text("earlier results\n")
    png = tmp_path / "old.png"
    png.write_bytes(b"earlier figure")
    figs = tmp_path / "figs"
    figs.mkdir()
    (figs / "timing.png").write_bytes(b"earlier figure")
    m = tmp_path / "map"
    shutil.copytree(tiny_map, m)
    before = snapshot(tmp_path)
    js = ["--json", str(old)]
    ds = ["--format", "7scenes", "--root", str(tmp_path / "nowhere")]
    new = str(tmp_path / "new.json")
    cases = [
        (ablation.main, js, old), (localize.main, js, old), (render.main, js, old),
        (shard.main, js, old), (stream.main, js, old), (map_size.main, js, old),
        (clusters.main, js, old), (confidence.main, js, old),
        (sift_reference.main, [*ds, *js], old),
        (fidelity.main, ["--map", str(m), *js], old),
        (nerf.main, ["--data", "d", "--format", "nerf", "--minutes", "1", *js], old),
        (track.main, ["--map", str(m), *js], old),
        (track.main, ["--map", str(m), "--json", new, "--plot", str(png)], png),
        (track.main, ["--map", str(m), "--json", new, "--plot", str(m / "map.json"),
                      "--overwrite"], m / "map.json"),
        (map_size.main, ["--json", new, "--plot", str(png)], png),
        (map_size.main, ["--json", new, "--plot", str(m / "egm.npz"), "--overwrite"],
         m / "egm.npz"),
        (clusters.main, ["--json", new, "--figure", str(png)], png),
        (clusters.main, ["--json", new, "--figure", str(m / "ilm.npz"), "--overwrite"],
         m / "ilm.npz"),
        (figures.main, ["--out", str(figs), "--figures", "timing"], figs / "timing.png"),
        (figures.main, ["--out", str(m), "--figures", "timing", "--localize-json", str(old),
                        "--overwrite"], m),
        (confidence.main, ["--from-json", str(old), "--json", str(old), "--overwrite"], old),
        # not outputs, but tracebacks before (FileNotFoundError, JSONDecodeError)
        (confidence.main, ["--from-json", str(tmp_path / "nope.json")], "not found"),
        (confidence.main, ["--from-json", str(png)], "corrupt"),
    ]
    for main, args, named in cases:
        line = assert_one_error_line(main(args), capsys.readouterr().err, named)
        assert any(w in line for w in ("already exists", "map", "input", "found", "corrupt"))
    assert snapshot(tmp_path) == before
    assert not tmp_files(tmp_path)


def test_blank_query_failure_names_its_missing_keypoints(tiny_map, small_synthetic_scene,
                                                         tmp_path, capsys):
    """Before: a blank (featureless) query's summary.json said "PnP failed (too few matches or
    inliers)"; the Localizer's result said nothing. Now the reason names 0 keypoints, in the
    run's summary and from ``Localizer.failure_reason``; a good query still has none."""
    from vrs_jax.cli import localize as cli
    from vrs_jax.data.readers import load_scene
    from vrs_jax.localize import Localizer

    root = tmp_path / "room"
    shutil.copytree(small_synthetic_scene, root)
    q = load_scene("7scenes", root).queries()
    w, h = (int(s) for s in q.sizes[2])
    fileio.write_image(q.image_paths[2], np.full((h, w, 3), 128, np.uint8))
    out = tmp_path / "loc"
    rc = cli.main(["--map", str(tiny_map), "--config", "test", "--mode", "real", "--no-timing",
                   "--quiet", "--format", "7scenes", "--root", str(root), "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    rows = {r["name"]: r for r in json.loads((out / "summary.json").read_text())["per_query"]}
    assert not rows[q.names[2]]["success"]
    assert rows[q.names[2]]["error"].startswith("no keypoints in the query image"), rows
    assert rows[q.names[0]]["error"] is None
    loc = Localizer(tiny_map, "test", source="real")
    blank = loc.localize_image(np.full((h, w), 0.5, np.float32), q.K[2])
    assert int(blank.n_keypoints) == 0
    assert loc.failure_reason(blank).startswith("no keypoints in the query image")
    good = loc.localize_image(q.image_paths[0], q.K[0])
    assert bool(good.success) and loc.failure_reason(good) is None


def test_ctrl_c_while_the_interpreter_exits_is_one_line():
    """Ctrl-C after a command finished, while the interpreter runs its exit handlers (jax
    clears its caches at exit), printed a traceback from the exit handler (exit status 0 or
    killed by SIGINT). Now: one 'interrupted' line and status 130. The exit handler is a
    sleep here, so the signal lands in it whatever the machine's speed."""
    code = ("import atexit, time\n"
            "from vrs_jax.errors import cli_main\n"
            "atexit.register(time.sleep, 30)\n"
            "main = cli_main(lambda: print('done', flush=True))\n"
            "raise SystemExit(main())\n")
    assert_interrupted(*interrupt_program(code, "done")[::2])


# ----------------------------------------------------------------------------- COLMAP models


def _colmap_model(tiny_map, d: Path, text: bool) -> Path:
    from vrs_jax import maps
    from vrs_jax.egm.colmap import export_colmap

    return export_colmap(maps.load_map(tiny_map, require_ilm=False).egm, d, text=text)


def _edit_line(path: Path, k: int, fn) -> None:
    """Apply ``fn`` to the fields of the k-th data line (not a comment) of a text file."""
    lines = path.read_text().splitlines()
    data = [i for i, s in enumerate(lines) if s and not s.startswith("#")]
    lines[data[k]] = " ".join(fn(lines[data[k]].split()))
    path.write_text("\n".join(lines) + "\n")


def test_damaged_colmap_models_are_one_line(tiny_map, small_synthetic_scene, tmp_path):
    """Before: a truncated images.bin or points3D.bin hung pycolmap (minutes, no output); a
    truncated cameras.bin read as 'non-positive focal length'; the other damage came back as
    COLMAP's C++ check text without the file; a zero quaternion loaded as a pose; a duplicate
    image name was a ValueError traceback; a binary and a text model that disagree loaded the
    binary one silently. Now each is one VrsError naming the file (and line) and the problem,
    and damaged rigs/frames files (not needed: each image's pose is in the images file) do
    not matter."""
    from vrs_jax.data.readers import load_scene

    good = {t: _colmap_model(tiny_map, tmp_path / f"good_{t}", t) for t in (True, False)}

    def case(name, text, damage):
        d = tmp_path / name
        shutil.copytree(good[text], d)
        damage(d)
        return d

    def cut(fname, frac):
        return lambda d: (d / fname).write_bytes((d / fname).read_bytes()[:int(
            frac * (d / fname).stat().st_size)])

    def edit(fname, k, fn):
        return lambda d: _edit_line(d / fname, k, fn)

    def both(d):
        for f in good[False].iterdir():
            shutil.copy(f, d / f.name)
        _edit_line(d / "images.txt", 0, lambda t: t[:5] + ["5.0"] + t[6:])

    cases = [
        *[(f"cut_{f}_{x}", False, cut(f"{f}.bin", x), f"{f}.bin", "truncated")
          for f in ("cameras", "images", "points3D") for x in (0.0, 0.5, 0.97)],
        ("cut_points_txt", True, cut("points3D.txt", 0.5), "points3D.txt", "malformed"),
        ("cam_word", True, edit("cameras.txt", 0, lambda t: t[:4] + ["abc"] + t[5:]),
         "cameras.txt:4", "expected numbers"),
        ("cam_short", True, edit("cameras.txt", 0, lambda t: t[:-1]), "cameras.txt:4",
         "expected 8"),
        ("cam_size", True, edit("cameras.txt", 0, lambda t: t[:2] + ["0", "0"] + t[4:]),
         "cameras.txt:4", "size 0x0"),
        ("img_short", True, edit("images.txt", 0, lambda t: t[:5]), "images.txt:5",
         "expected 10"),
        ("img_camera", True, edit("images.txt", 0, lambda t: t[:8] + ["999"] + t[9:]),
         "images.txt:5", "camera 999, which is not in the model"),
        ("img_quat", True, edit("images.txt", 0, lambda t: t[:1] + ["0"] * 4 + t[5:]),
         "images.txt:5", "zero quaternion"),
        ("img_dup", True, edit("images.txt", 2, lambda t: t[:9] + [
            (good[True] / "images.txt").read_text().split("\n")[4].split()[9]]),
         "images.txt", "appears twice"),
        ("pt_image", True, edit("points3D.txt", 0, lambda t: t[:8] + ["999", "0"] + t[10:]),
         "points3D.txt:4", "image 999, which is not in the model"),
        ("pt_index", True, edit("points3D.txt", 0, lambda t: t[:9] + ["99999"] + t[10:]),
         "points3D.txt:4", "2D point 99999"),
        ("pt_nan", True, edit("points3D.txt", 0, lambda t: t[:1] + ["nan"] + t[2:]),
         "points3D.txt:4", "non-finite"),
        ("both", True, both, "", "disagree"),
    ]
    for name, text, damage, names, problem in cases:
        d = case(name, text, damage)
        with pytest.raises(VrsError) as e:
            load_scene("colmap", d, images=small_synthetic_scene)
        msg = str(e.value)
        assert "\n" not in msg and str(d / names if names else d) in msg, (name, msg)
        assert problem in msg, (name, msg)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(VrsError, match="no COLMAP model here"):
        load_scene("colmap", empty, images=small_synthetic_scene)
    for name, part in (("rigs", "rigs.bin"), ("frames", "frames.bin")):
        d = case(name, False, cut(part, 0.97))
        s = load_scene("colmap", d, images=small_synthetic_scene)
        ref = load_scene("colmap", good[False], images=small_synthetic_scene)
        assert s.names == ref.names and np.array_equal(s.R, ref.R)


def test_colmap_export_never_leaves_two_models(tiny_map, small_synthetic_scene, tmp_path,
                                               capsys):
    """Before: ``build_egm --export-colmap DIR`` (text) into a folder holding a binary model
    wrote the text model beside it; COLMAP (and the reader) then read the stale binary one.
    Now a model of either format is refused; with --overwrite the other format is removed,
    and the exported model reads back."""
    from vrs_jax.cli import build_egm
    from vrs_jax.data.readers import load_scene

    d = _colmap_model(tiny_map, tmp_path / "cm", text=False)
    args = ["--format", "7scenes", "--root", str(small_synthetic_scene), "--config", "test",
            "--out", str(tmp_path / "egm"), "--export-colmap", str(d), "--quiet"]
    assert_one_error_line(build_egm.main(args), capsys.readouterr().err, d / "cameras")
    assert not (d / "cameras.txt").exists()
    assert build_egm.main([*args, "--overwrite"]) == 0
    assert sorted(p.suffix for p in d.iterdir()) == [".txt"] * 5
    s = load_scene("colmap", d, images=small_synthetic_scene)
    assert len(s.names) == 24


@pytest.mark.parametrize("edit,problem", [
    (("format", "bogus"), "unknown dataset format 'bogus'"),
    (("options", [["query_every", "x"]]), "query_every must be an integer, got 'x'")])
def test_hand_edited_map_source_is_one_line_naming_map_json(edit, problem, tiny_map, tmp_path,
                                                            capsys):
    """``localize`` with the map's own queries reads the dataset the map records: an edited
    reader option there was a ValueError traceback, an edited format blamed no file."""
    from vrs_jax.cli import localize as cli

    d = tmp_path / "map"
    shutil.copytree(tiny_map, d, ignore=shutil.ignore_patterns("nerf"))
    meta = json.loads((d / "map.json").read_text())
    meta["source"][edit[0]] = edit[1]
    (d / "map.json").write_text(json.dumps(meta))
    rc = cli.main(["--map", str(d), "--config", "test", "--mode", "real", "--quiet",
                   "--out", str(tmp_path / "run")])
    line = assert_one_error_line(rc, capsys.readouterr().err, d / "map.json")
    assert problem in line
    assert not (tmp_path / "run").exists()


def test_sfm_of_a_single_photo_is_refused_before_colmap(tmp_path, capfd):
    """``train --format images`` on a folder of one photo ran COLMAP's SfM, which printed its
    own warning and error lines before ours; now one line before any SfM."""
    from vrs_jax.cli import train

    root = tmp_path / "photos"
    root.mkdir()
    fileio.write_image(root / "a.png", np.full((60, 80, 3), 128, np.uint8))
    rc = train.main(["--format", "images", "--root", str(root), "--out", str(tmp_path / "m"),
                     "--config", "test", "--steps", "2", "--quiet"])
    err = capfd.readouterr().err
    line = assert_one_error_line(rc, err, root)
    assert "at least 2 photos" in line and len(err.strip().splitlines()) == 1, err


def test_ctrl_c_inside_a_gc_callback_still_stops_the_program():
    """Ctrl-C landing in a garbage-collector callback (jax registers one; it runs often) was
    printed by Python as an "ignored" exception, and the command went on working. Now the
    program stops: one 'interrupted' line, status 130."""
    code = ("import gc, time\n"
            "from vrs_jax.errors import cli_main\n"
            "def slow(phase, info):\n"
            "    if phase == 'start':\n"
            "        print('in gc', flush=True)\n"
            "        time.sleep(2)\n"
            "def work():\n"
            "    gc.callbacks.append(slow)\n"
            "    gc.collect()\n"
            "    gc.callbacks.remove(slow)\n"
            "    time.sleep(20)\n"
            "    print('went on working', flush=True)\n"
            "raise SystemExit(cli_main(work)())\n")
    rc, out, err = interrupt_program(code, "in gc")
    assert "went on working" not in out, out
    assert_interrupted(rc, err)


def test_ctrl_c_while_a_command_starts_is_one_line(tmp_path):
    """Ctrl-C in the seconds ``python -m experiments.NAME`` spends importing jax printed a
    traceback through the imports (killed by SIGINT). The wrappers import their command with
    ``errors.program_main``: one line, status 130. The imported module sleeps here."""
    (tmp_path / "slow_cli.py").write_text("import time\nprint('importing', flush=True)\n"
                                          "time.sleep(30)\ndef main():\n    return 0\n")
    code = ("from vrs_jax.errors import program_main\n"
            "main = program_main('slow_cli', '__main__')\n"
            "raise SystemExit(main())\n")
    assert_interrupted(*interrupt_program(code, "importing", 0.3, tmp_path)[::2])
    from experiments import localize as wrapper
    from vrs_jax.cli import localize

    assert wrapper.main is localize.main


def test_ctrl_c_while_a_console_script_starts_is_one_line(tmp_path, monkeypatch):
    """The installed ``vrs-jax-NAME`` scripts imported their command (and jax) before any
    handler was in place: a Ctrl-C then printed a traceback through the imports. They now
    call ``vrs_jax.cli.scripts``, which imports the command behind ``program_main``: one
    line, status 130. The command module sleeps while it is imported here."""
    (tmp_path / "vrs_jax_cli_slow.py").write_text(
        "import time\nprint('importing', flush=True)\ntime.sleep(30)\n"
        "def main():\n    return 0\n")
    code = ("import sys\n"
            "import vrs_jax.cli.scripts as s\n"
            "run = s._command('x')\n"
            "s.program_main = (lambda real: lambda m, c: real('vrs_jax_cli_slow', c))("
            "s.program_main)\n"
            "sys.exit(run())\n")
    assert_interrupted(*interrupt_program(code, "importing", 0.3, tmp_path)[::2])


def test_ctrl_c_while_a_benchmark_starts_is_one_line(tmp_path):
    """``python -m benchmarks.NAME`` imports jax at module level: a Ctrl-C then printed a
    traceback through the imports. The package's ``__init__`` makes it one line, status
    130, for programs run with ``-m`` only. A benchmark-like module that sleeps while it
    is imported stands in for the real one."""
    pkg = tmp_path / "benchpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text((REPO / "benchmarks" / "__init__.py").read_text())
    (pkg / "slow.py").write_text("import time\nprint('importing', flush=True)\n"
                                 "time.sleep(30)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(tmp_path)])}
    p = subprocess.Popen([sys.executable, "-m", "benchpkg.slow"], cwd=tmp_path, env=env,
                         text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert p.stdout.readline() == "importing\n"
        time.sleep(0.3)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=30)
    finally:
        p.kill()
    assert_interrupted(p.returncode, err)
    # imported by a script or a test, the package leaves the interpreter's hook alone
    r = subprocess.run([sys.executable, "-c", "import sys, benchmarks; "
                        "print(sys.excepthook is sys.__excepthook__)"], cwd=REPO, env=env,
                       text=True, capture_output=True, timeout=120)
    assert r.stdout.strip() == "True", r.stderr


def test_colmap_export_on_a_full_disk_keeps_the_old_model(tiny_map, tmp_path):
    """pycolmap does not report a failed write: on a full disk the export left truncated
    model files and said it had written the model (exit 0). Now it is written aside, read
    back whole before it replaces anything, else one line; an earlier model stays."""
    d = _colmap_model(tiny_map, tmp_path / "cm", text=True)
    before = snapshot(d)
    code = ("import resource, signal\n"
            "from vrs_jax import maps\n"
            "from vrs_jax.egm.colmap import export_colmap\n"
            "from vrs_jax.errors import VrsError\n"
            f"egm = maps.load_map({str(tiny_map)!r}, require_ilm=False).egm\n"
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            "resource.setrlimit(resource.RLIMIT_FSIZE, (20000, resource.RLIM_INFINITY))\n"
            "for text in (True, False):\n"
            "    try:\n"
            f"        export_colmap(egm, {str(d)!r}, text=text, overwrite=True)\n"
            "        print('written')\n"
            "    except VrsError as e:\n"
            "        print('error:', e)\n")
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(REPO)}
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, text=True,
                       capture_output=True, timeout=240)
    lines = r.stdout.strip().splitlines()
    assert len(lines) == 2 and all(ln.startswith(f"error: {d}: cannot write the COLMAP model")
                                   for ln in lines), r.stdout + r.stderr
    assert snapshot(d) == before
