"""VisualSFM NVM_V3 models (Cambridge Landmarks ``reconstruction.nvm``, Aachen's database).

Only the first model of a file is read. A camera line is
``name focal qw qx qy qz cx cy cz radial 0``: the quaternion (w first) is the world-to-camera
rotation and ``(cx, cy, cz)`` the camera centre, so ``t = -R c``. A point line is
``x y z r g b n (image feature u v)*n`` with ``(u, v)`` measured from the principal point
(VisualSFM puts it at the image centre) in the pixels of the image the model was built from.

NVM's radial distortion ``r`` undistorts measurements: ``x_u = x_d (1 + r |x_d|^2)`` in
focal-normalised coordinates. To first order its inverse is OpenCV's ``k1 = -r``
(``x_d = x_u (1 - r |x_u|^2 + O(r^2))``), which is also what COLMAP's NVM import/export uses;
:func:`nvm_k1` returns that approximation.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from vrs_jax import geometry
from vrs_jax.data.readers import _common as C
from vrs_jax.errors import VrsError


@dataclasses.dataclass
class NvmModel:
    """The first model of an NVM file.

    Attributes:
      names: [N] image names as written in the file.
      focal: [N] focal lengths (pixels of the images the model was built from).
      R: [N, 3, 3] world-to-camera rotations; t: [N, 3] translations (t = -R c).
      radial: [N] NVM radial distortion parameters (see module docstring).
      points: [M, 3] 3D points; colors: [M, 3] uint8.
      obs_point, obs_image: [O] int point and camera index of every measurement.
      obs_uv: [O, 2] measurement relative to the principal point (pixels).
    """

    names: list[str]
    focal: np.ndarray
    R: np.ndarray
    t: np.ndarray
    radial: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    obs_point: np.ndarray
    obs_image: np.ndarray
    obs_uv: np.ndarray

    @property
    def centers(self) -> np.ndarray:
        return geometry.camera_center(self.R, self.t)

    def index(self) -> dict[str, int]:
        """Name -> camera index."""
        return {n: i for i, n in enumerate(self.names)}


def nvm_k1(radial: np.ndarray | float) -> np.ndarray:
    """First-order OpenCV ``k1`` of an NVM radial parameter (see module docstring)."""
    return -np.asarray(radial, np.float64)


def _count(lines, pos, path, what):
    while pos < len(lines) and not lines[pos][1]:
        pos += 1
    if pos >= len(lines):
        raise VrsError(f"unexpected end of file: expected the number of {what}", path)
    lineno, text = lines[pos]
    parts = text.split()
    try:
        n = int(parts[0])
    except (ValueError, IndexError):
        raise VrsError(f"malformed NVM file: expected the number of {what}, got {text[:40]!r}",
                       path, lineno) from None
    if n < 0 or len(parts) != 1:
        raise VrsError(f"malformed NVM file: expected the number of {what}", path, lineno)
    return n, pos + 1


def read_nvm(path: str | Path, read_points: bool = True) -> NvmModel:
    """Parse an NVM_V3 file (first model only). Raises VrsError naming file and line."""
    path = Path(path)
    raw = C.read_text(path, "NVM model").splitlines()
    lines = [(i + 1, s.strip()) for i, s in enumerate(raw)]
    if not lines or not lines[0][1].startswith("NVM_V3"):
        raise VrsError("not an NVM_V3 file (first line must start with 'NVM_V3')", path, 1)
    if lines[0][1].startswith("NVM_V3_R9T"):
        raise VrsError("NVM_V3_R9T (rotation-matrix cameras) is not supported; convert it to "
                       "NVM_V3 (quaternions)", path, 1)
    # ``NVM_V3 FixedK fx cx fy cy`` (shared intrinsics) still has a focal on every camera
    # line; the principal point is left to the callers (they use the image centre).
    n_cams, pos = _count(lines, 1, path, "cameras")
    names, focal, quat, centre, radial = [], [], [], [], []
    for _ in range(n_cams):
        while pos < len(lines) and not lines[pos][1]:
            pos += 1
        if pos >= len(lines):
            raise VrsError(f"unexpected end of file: expected {n_cams} camera lines", path)
        lineno, text = lines[pos]
        parts = text.split()
        if len(parts) < 10:
            raise VrsError("malformed NVM camera line: expected 'name focal qw qx qy qz cx cy "
                           f"cz radial 0', got {len(parts)} fields", path, lineno)
        v = C.parse_floats(parts[1:10], path, lineno, "NVM camera line")
        if not np.all(np.isfinite(v)) or v[0] <= 0 or np.linalg.norm(v[1:5]) < 1e-9:
            raise VrsError("malformed NVM camera line: non-finite values, focal <= 0 or zero "
                           "quaternion", path, lineno)
        names.append(parts[0])
        focal.append(v[0])
        quat.append(v[1:5])
        centre.append(v[5:8])
        radial.append(v[8])
        pos += 1
    R = geometry.quat_to_rot(np.asarray(quat).reshape(-1, 4))
    c = np.asarray(centre).reshape(-1, 3)
    t = -(R @ c[..., None])[..., 0]

    points, colors, obs_p, obs_i, obs_uv = [], [], [], [], []
    if read_points and pos < len(lines):
        n_pts, pos = _count(lines, pos, path, "points")
        for k in range(n_pts):
            while pos < len(lines) and not lines[pos][1]:
                pos += 1
            if pos >= len(lines):
                raise VrsError(f"unexpected end of file: expected {n_pts} point lines", path)
            lineno, text = lines[pos]
            parts = text.split()
            ok = len(parts) >= 7
            if ok:
                v = C.parse_floats(parts[:7], path, lineno, "NVM point line")
                nm = int(v[6])
                ok = nm >= 0 and len(parts) == 7 + 4 * nm
            if not ok:
                raise VrsError("malformed NVM point line: expected 'x y z r g b n' and n "
                               "measurements 'image feature u v'", path, lineno)
            m = C.parse_floats(parts[7:], path, lineno, "NVM point line").reshape(nm, 4)
            if nm and (m[:, 0].min() < 0 or m[:, 0].max() >= n_cams):
                raise VrsError("NVM point measurement refers to a camera index out of range",
                               path, lineno)
            points.append(v[:3])
            colors.append(v[3:6])
            obs_p.append(np.full(nm, k))
            obs_i.append(m[:, 0].astype(np.int64))
            obs_uv.append(m[:, 2:4])
            pos += 1
    cat = lambda a, shape, dt: (np.concatenate(a).astype(dt) if a  # noqa: E731
                                else np.zeros(shape, dt))
    return NvmModel(
        names=names, focal=np.asarray(focal, np.float64), R=np.asarray(R, np.float64), t=t,
        radial=np.asarray(radial, np.float64),
        points=np.asarray(points, np.float64).reshape(-1, 3),
        colors=np.clip(np.asarray(colors), 0, 255).astype(np.uint8).reshape(-1, 3),
        obs_point=cat(obs_p, (0,), np.int64), obs_image=cat(obs_i, (0,), np.int64),
        obs_uv=cat(obs_uv, (0, 2), np.float64),
    )
