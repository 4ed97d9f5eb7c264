"""Results files: one line per query ``name qw qx qy qz tx ty tz`` (world-to-camera).

The format hloc writes and the Aachen/Cambridge/7Scenes evaluations read: the quaternion is
(w, x, y, z), Hamilton, of the world-to-camera rotation, and t is the world-to-camera
translation in the scene's units (metres). Names are image paths relative to the dataset
root (they may contain '/', e.g. ``seq-03/frame-000000.color.png``) or, for benchmarks that
want them, bare file names. Names cannot contain whitespace (the format splits on it).
Blank lines and lines starting with '#' are ignored when reading.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path, PurePosixPath

import numpy as np

from vrs_jax import fileio, geometry
from vrs_jax.errors import VrsError, require_file


def _format_float(x: float) -> str:
    return repr(float(x))  # shortest string that round-trips exactly


def write_results(path: str | Path, names: Sequence[str], R: np.ndarray, t: np.ndarray, *,
                  basename: bool = False) -> Path:
    """Write a results file atomically (a temporary file in the same folder, then rename).

    Args:
      path: output file; its folder must exist.
      names: [N] image names (relative to the dataset root).
      R: [N, 3, 3] world-to-camera rotations; t: [N, 3] translations.
      basename: write only the file name of each image (Aachen's benchmark wants that);
        names that then collide raise VrsError.
    Returns:
      the path written.
    """
    path = Path(path)
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
    names = [str(n) for n in names]
    if not (len(names) == len(R) == len(t)):
        raise ValueError(f"{len(names)} names but {len(R)} rotations and {len(t)} translations")
    out_names = [PurePosixPath(n.replace(os.sep, "/")).name if basename else n for n in names]
    seen: dict[str, str] = {}
    for orig, n in zip(names, out_names, strict=True):
        if not n or any(c.isspace() for c in n):
            raise VrsError(f"image name {orig!r} is empty or contains whitespace; the results "
                           "format cannot hold it", path)
        if n in seen:
            raise VrsError(f"two queries would be written as {n!r} ({seen[n]!r} and {orig!r})"
                           + ("; write full names instead of --basename" if basename else ""),
                           path)
        seen[n] = orig
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise ValueError("results poses must be finite (write the fallback pose for failures)")
    q = geometry.rot_to_quat(R)
    lines = [" ".join([n, *map(_format_float, qi), *map(_format_float, ti)])
             for n, qi, ti in zip(out_names, q, t, strict=True)]
    text = "".join(line + "\n" for line in lines)
    if not path.parent.is_dir():
        raise VrsError("output folder not found", path.parent)
    return fileio.write_text(path, text)


def read_results(path: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Read a results file -> {name: (R [3, 3], t [3])} in file order (float64).

    Raises VrsError naming the file and line for: a wrong number of fields, a value that is
    not a finite number, a zero quaternion, or a name given twice; and for a missing file.
    """
    path = require_file(path, "results file")
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark is not a name
    except UnicodeDecodeError as e:
        raise VrsError(f"not a text file ({e.reason})", path) from None
    except OSError as e:
        raise VrsError(f"cannot read: {fileio.reason(e)}", path) from None
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    first_line: dict[str, int] = {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        fields = s.split()
        if len(fields) != 8:
            raise VrsError(f"expected 8 fields 'name qw qx qy qz tx ty tz', found "
                           f"{len(fields)}", path, lineno)
        name = fields[0]
        try:
            values = [float(v) for v in fields[1:]]
        except ValueError:
            bad = next(v for v in fields[1:] if not _is_float(v))
            raise VrsError(f"{bad!r} is not a number", path, lineno) from None
        if not all(math.isfinite(v) for v in values):
            raise VrsError("pose values must be finite", path, lineno)
        qv = np.asarray(values[:4])
        if np.linalg.norm(qv) < 1e-12:
            raise VrsError("quaternion is zero", path, lineno)
        if name in out:
            raise VrsError(f"query {name!r} appears twice (first on line {first_line[name]})",
                           path, lineno)
        first_line[name] = lineno
        out[name] = (geometry.quat_to_rot(qv), np.asarray(values[4:]))
    return out


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True
