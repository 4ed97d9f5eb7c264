"""Writing files safely: atomically, with one-line errors, leaving nothing half-written.

Every file the project writes goes through here: data is written to ``NAME.tmp`` beside the
target, flushed to disk, then renamed over the target, so a crash or a full disk never leaves
a truncated file under the real name; on failure the temporary file is removed and the error
is a :class:`~vrs_jax.errors.VrsError` naming the path (permission denied, disk full, ...).
Files get mode 0644 (umask applied), whatever the writer.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import hashlib
import json
import math
import os
import shutil
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any

import numpy as np

from vrs_jax.errors import VrsError

_MODE = 0o644


def _reason(e: OSError) -> str:
    if e.errno == errno.ENOSPC:
        return "no space left on the device"
    if e.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return "permission denied (read-only folder?)"
    if e.errno == errno.EFBIG:
        return "file too large for this file system or limit (disk full?)"
    if e.errno == errno.ENOTDIR:
        return "a parent of this path is a file, not a folder"
    return e.strerror or type(e).__name__


def os_error_in(e: BaseException) -> OSError | None:
    """The first OSError with an errno in ``e``'s cause/context chain (libraries such as orbax
    wrap the file system's error), or None."""
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno is not None:
            return e
        e = e.__cause__ or e.__context__
    return None


def reason(e: BaseException) -> str:
    """A short human reason for a failed write/read: from the OSError in ``e``'s chain, else
    the first line of the message."""
    os_e = os_error_in(e)
    if os_e is not None:
        return _reason(os_e)
    text = str(e).splitlines()[0][:160] if str(e) else ""
    low = str(e).lower()
    if "no space left" in low:
        return "no space left on the device"
    if "file too large" in low:
        return "file too large for this file system or limit (disk full?)"
    if "permission denied" in low or "read-only file system" in low:
        return "permission denied (read-only folder?)"
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def write_atomic(path: str | Path, write: Callable[[IO[bytes]], Any]) -> Path:
    """Call ``write(f)`` on a temporary file, then rename it to ``path`` (VrsError on failure)."""
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, _MODE & ~_umask())
        os.replace(tmp, p)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise VrsError(f"cannot write: {_reason(e)}", p) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return p


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    return write_atomic(path, lambda f: f.write(data))


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return write_bytes(path, text.encode())


def write_image(path: str | Path, image: np.ndarray) -> Path:
    """Encode ``image`` (uint8 BGR [H, W, 3], or uint8/uint16 [H, W]) in the format of
    ``path``'s suffix (OpenCV) and write it atomically."""
    import cv2

    p = Path(path)
    ok, buf = cv2.imencode(p.suffix or ".png", np.ascontiguousarray(image))
    if not ok:
        raise VrsError("cannot encode the image for this file type", p)
    return write_bytes(p, buf.tobytes())


def json_ready(obj: Any) -> Any:
    """A copy of nested dicts/lists/numbers with non-finite floats as None (strict JSON) and
    numpy scalars/arrays as Python numbers/lists."""
    if isinstance(obj, Mapping):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def write_json(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as indented strict JSON (:func:`json_ready`: inf/nan become null)
    atomically."""
    return write_text(path, json.dumps(json_ready(obj), indent=1, allow_nan=False) + "\n")


def read_json(path: str | Path, what: str = "JSON file") -> Any:
    """Parse a JSON file; VrsError naming it when missing, unreadable or corrupt."""
    p = Path(path)
    try:
        return json.loads(p.read_text())
    except FileNotFoundError:
        raise VrsError(f"{what} not found", p) from None
    except OSError as e:
        raise VrsError(f"cannot read: {_reason(e)}", p) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise VrsError(f"corrupt {what}: {e}", p) from None


def format_version(meta: Mapping[str, Any], path: str | Path, what: str = "map") -> int:
    """``meta["format_version"]`` of a file's header; VrsError naming ``path`` when it is
    missing or not an integer (``"4"``, ``4.0``, ``true``: an edited or foreign file)."""
    v = meta.get("format_version")
    if v is None:
        raise VrsError(f"{what} metadata lacks 'format_version'", path)
    if isinstance(v, bool) or not isinstance(v, int):
        raise VrsError(f"{what} format_version must be an integer, got {v!r} "
                       f"({type(v).__name__})", path)
    return v


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def check_writable(folder: str | Path) -> Path:
    """Create ``folder`` if needed and check that files can be written there, before any work
    starts (VrsError naming it otherwise)."""
    d = Path(folder)
    if d.exists() and not d.is_dir():
        raise VrsError("output path exists and is not a folder", d)
    # one probe per process: processes of one multi-process run check the same folder at once
    probe = d / f".vrs_jax_write_test.{os.getpid()}"
    try:
        d.mkdir(parents=True, exist_ok=True)
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise VrsError(f"cannot write here: {_reason(e)}", d) from None
    return d


def umask() -> int:
    """The process's umask (read without changing it)."""
    return _umask()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# ----------------------------------------------------------------------------- output rules


def check_new(path: str | Path, overwrite: bool = False) -> Path:
    """The one rule for every output path: an existing file, or a folder that is not empty,
    is refused (one VrsError line naming it) unless ``overwrite``."""
    p = Path(path)
    taken = p.is_file() or p.is_symlink() or (p.is_dir() and any(p.iterdir()))
    if taken and not overwrite:
        raise VrsError("already exists; pass --overwrite to replace it or choose another path",
                       p)
    if taken:
        refuse_map_part(p)
    return p


MAP_WORK_FOLDERS = ("nerf", "sfm")
"""Folders of a map folder that belong to the map (NeRF checkpoints, SfM work files)."""


def map_folder_of(path: str | Path) -> Path | None:
    """The vrs-jax map folder that ``path`` is, or lies in (a folder holding ``map.json``,
    ``path`` itself or one of its parents), else None."""
    p = Path(path).resolve()
    for d in (p, *p.parents):
        if (d / "map.json").is_file():
            return d
    return None


def refuse_map_part(path: str | Path) -> None:
    """VrsError when ``path`` is a vrs-jax map folder, one of its files or lies in its
    :data:`MAP_WORK_FOLDERS`: no output of a run,
    evaluation or benchmark replaces (part of) a map, even with --overwrite (only
    ``experiments.train``/``build_egm`` write maps, as transactions)."""
    d = map_folder_of(path)
    if d is None:
        return
    rel = Path(path).resolve().relative_to(d).parts
    if len(rel) > 1 and rel[0] not in MAP_WORK_FOLDERS:
        return  # a run's own folder that happens to sit inside the map folder
    if not rel:
        raise VrsError("is a vrs-jax map folder (map.json); an output never replaces a map, "
                       "even with --overwrite: choose another path", path)
    raise VrsError(f"lies in the vrs-jax map folder {d}; an output never replaces part of a "
                   "map, even with --overwrite: choose another path", path)


def check_apart(out: str | Path, inputs: Iterable[str | Path | None]) -> Path:
    """The output ``out`` must not be one of this run's ``inputs`` (a dataset root, a map, a
    results file, a query list) nor a folder holding one: writing it would replace what the
    run reads. Refused whatever --overwrite says (VrsError naming ``out`` and the input)."""
    o = Path(out).resolve()
    for inp in inputs:
        if inp is None or str(inp) == "":
            continue
        i = Path(inp).resolve()
        if o == i:
            raise VrsError(f"is an input of this run ({inp}); an output never replaces an "
                           "input, even with --overwrite: choose another path", out)
        if o in i.parents:
            raise VrsError(f"holds an input of this run ({inp}); an output never replaces an "
                           "input, even with --overwrite: choose another path", out)
    return Path(out)


def pid_alive(pid: int) -> bool:
    """Whether a process with this id exists on this host."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by another user
    return True


def _sibling(folder: Path, tag: str, pid: int | None = None) -> Path:
    """``folder``'s sibling ``NAME.TAG-PID`` (this process's pid by default)."""
    return folder.with_name(f"{folder.name}.{tag}-{os.getpid() if pid is None else pid}")


def lock_path(folder: str | Path) -> Path:
    """The lock file of an output folder: ``NAME.lock`` beside it (outside the folder, which
    a run may replace as a whole)."""
    d = Path(folder)
    return d.with_name(d.name + ".lock")


def _lock_owner(lock: Path) -> tuple[int, str]:
    """(pid, host) recorded in a lock file ((0, "") when unreadable or half-written)."""
    try:
        pid, _, host = lock.read_text().strip().partition(" ")
        return int(pid), host
    except (OSError, ValueError):
        return 0, ""


def _take_lock(lock: Path) -> bool:
    """Create ``lock`` holding ``PID HOST`` atomically (O_CREAT|O_EXCL); False if it exists.
    OSError (after removing it) when the pid cannot be written (a full disk)."""
    try:
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, _MODE)
    except FileExistsError:
        return False
    try:
        with os.fdopen(fd, "w") as f:
            f.write(f"{os.getpid()} {os.uname().nodename}\n")
    except OSError:
        lock.unlink(missing_ok=True)
        raise
    return True


def _acquire(d: Path, lock: Path, warn: Callable[[str], None]) -> bool:
    """Take the lock of ``d`` (a dead owner's is taken over with a warning); False when the
    disk is too full to record it (the run goes on unlocked: it cannot write either)."""
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
        while not _take_lock(lock):
            pid, host = _lock_owner(lock)
            if host == os.uname().nodename and pid > 0 and not pid_alive(pid):
                warn(f"warning: {d}: taking over the lock of process {pid}, which is gone")
                lock.unlink(missing_ok=True)
                continue
            raise VrsError(f"in use by process {pid} on {host or 'another host'} (its lock "
                           f"is {lock}; remove it if that process is gone)", d)
    except OSError as e:
        if e.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT) and lock.parent.is_dir():
            warn(f"warning: {d}: cannot lock the folder: {_reason(e)}")
            return False
        raise VrsError(f"cannot write here: {_reason(e)}", d) from None
    return True


@contextlib.contextmanager
def folder_lock(folder: str | Path, warn: Callable[[str], None] | None = None
                ) -> Iterator[Path]:
    """Hold the lock of output folder ``folder`` for the ``with`` block.

    A second process asking for it fails with one VrsError line naming the folder and the
    owner's pid; a lock whose process is gone on this host (a killed run) is taken over with
    a warning. The lock file is removed on exit.
    """
    d = Path(folder)
    lock = lock_path(d)
    held = _acquire(d, lock, warn or (lambda s: print(s, file=sys.stderr)))
    try:
        yield d
    finally:
        if held and _lock_owner(lock)[0] == os.getpid():
            lock.unlink(missing_ok=True)


def _link_tree(src: Path, dst: Path) -> None:
    """``src`` (file or folder) recreated at ``dst`` with hard links (copies where links are
    not supported)."""

    def link(a, b):
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)

    if src.is_dir():
        shutil.copytree(src, dst, copy_function=link, symlinks=True)
    else:
        link(src, dst)


def _recover(folder: Path) -> None:
    """Finish or undo what a killed :func:`staged_folder` of a dead process left: its
    staging folder is removed; the earlier folder set aside comes back if none replaced it."""
    for p in sorted(folder.parent.glob(f"{glob.escape(folder.name)}.*-*")):
        tag, _, pid = p.name[len(folder.name) + 1:].rpartition("-")
        if tag not in ("tmp", "old") or not pid.isdigit() or pid_alive(int(pid)):
            continue
        if tag == "old" and not folder.exists():
            os.replace(p, folder)  # the swap was cut between its two renames
        else:
            shutil.rmtree(p, ignore_errors=True)


def _swap_in(new: Path, folder: Path) -> None:
    """Replace ``folder`` by ``new``: the old one renamed aside, the new one in, the old one
    deleted."""
    old = _sibling(folder, "old")
    if folder.exists():
        os.replace(folder, old)
    try:
        os.replace(new, folder)
    except OSError:
        if old.exists():
            os.replace(old, folder)
        raise
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def staged_folder(folder: str | Path, carry: Iterable[str] = ()) -> Iterator[Path]:
    """A run folder as a transaction: yields a fresh sibling ``NAME.tmp-PID`` to write into,
    which replaces ``folder`` only when the ``with`` block completes; on any failure it is
    removed and ``folder`` is left as it was.

    Args:
      carry: names of entries of the existing ``folder`` to keep (hard-linked into the new
        one first: checkpoints, work files).
    Raises:
      VrsError naming ``folder`` (errors about files in the staging folder are reported
      under ``folder``'s name).
    """
    d = Path(folder)
    if d.exists() and not d.is_dir():
        raise VrsError("output path exists and is not a folder", d)
    tmp = _sibling(d, "tmp")
    try:
        _recover(d)
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        for name in carry:
            _link_tree(d / name, tmp / name)
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise VrsError(f"cannot write here: {_reason(e)}", d) from None
    try:
        yield tmp
        _swap_in(tmp, d)
    except VrsError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        if e.path is None or not e.path.startswith(str(tmp)):
            raise
        raise VrsError(e.problem, str(d) + e.path[len(str(tmp)):], e.line) from None
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise VrsError(f"cannot write here: {_reason(e)}", d) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
