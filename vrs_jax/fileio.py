"""Writing files safely: atomically, with one-line errors, leaving nothing half-written.

Every file the project writes goes through here: data is written to ``NAME.tmp`` beside the
target, flushed to disk, then renamed over the target, so a crash or a full disk never leaves
a truncated file under the real name; on failure the temporary file is removed and the error
is a :class:`~vrs_jax.errors.VrsError` naming the path (permission denied, disk full, ...).
Files get mode 0644 (umask applied), whatever the writer.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
from collections.abc import Callable, Mapping
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
    probe = d / ".vrs_jax_write_test"
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
