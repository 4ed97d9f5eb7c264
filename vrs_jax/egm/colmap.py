"""COLMAP interoperability of the EGM: cameras and the map as a COLMAP sparse model.

:func:`export_colmap` writes a map so that COLMAP, hloc, pycolmap and our own COLMAP reader
(``vrs_jax.data.readers.colmap``) open it: one camera per image in the simplest model that
represents its intrinsics exactly (``data.readers.colmap.colmap_camera``), the EGM keypoints
as 2D points and the 3D points with their tracks.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import pycolmap

from vrs_jax import fileio
from vrs_jax.data.readers.colmap import MODEL_PARTS, check_model, colmap_camera
from vrs_jax.egm.map import EGM
from vrs_jax.errors import VrsError


def to_colmap(egm: EGM) -> pycolmap.Reconstruction:
    """The map as a pycolmap Reconstruction: one camera per image (PINHOLE / OPENCV /
    FULL_OPENCV), images with the EGM keypoints as 2D points, points3D with their tracks.

    Image i has camera/image id i + 1; points get ids in the order of ``points3d`` (a point
    that no keypoint links -- none in maps from build_egm -- is not exported).
    """
    rec = pycolmap.Reconstruction()
    mask = np.asarray(egm.kp_mask)
    kp = np.asarray(egm.keypoints, np.float64)
    pidx = np.asarray(egm.point_idx)
    R = np.asarray(egm.R, np.float64)
    t = np.asarray(egm.t, np.float64)
    for i, name in enumerate(egm.names):
        rec.add_camera_with_trivial_rig(colmap_camera(np.asarray(egm.K[i], np.float64),
                                                      np.asarray(egm.dist[i], np.float64),
                                                      np.asarray(egm.sizes[i]), i + 1))
        c = int(mask[i].sum())
        image = pycolmap.Image(name=name, keypoints=kp[i, :c, :2], camera_id=i + 1,
                               image_id=i + 1)
        # re-orthonormalise the float32 rotation (COLMAP stores a unit quaternion)
        u, _, vt = np.linalg.svd(R[i])
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(u @ vt), t[i])
        rec.add_image_with_trivial_frame(image, pose)
    X = np.asarray(egm.points3d, np.float64)
    obs_i, obs_k = np.nonzero(mask)
    obs_p = pidx[obs_i, obs_k]
    order = np.argsort(obs_p, kind="stable")
    obs_i, obs_k, obs_p = obs_i[order], obs_k[order], obs_p[order]
    bounds = np.searchsorted(obs_p, np.arange(len(X) + 1))
    for m in range(len(X)):
        a, b = bounds[m], bounds[m + 1]
        if a == b:
            continue
        track = pycolmap.Track()
        for i, k in zip(obs_i[a:b], obs_k[a:b], strict=True):
            track.add_element(int(i) + 1, int(k))
        rec.add_point3D(X[m], track)
    return rec


def export_colmap(egm: EGM, out_dir: str | Path, text: bool = True,
                  overwrite: bool = False) -> Path:
    """Write the map as a COLMAP model (cameras, images, points3D; .txt or .bin); a model
    already there, binary or text, is refused unless ``overwrite``, which also removes the
    other format's files (COLMAP reads a .bin model before a .txt one: a stale one left
    beside would be read instead)."""
    d = fileio.check_writable(out_dir)
    ext, other = ("txt", "bin") if text else ("bin", "txt")
    for name in (*MODEL_PARTS, "rigs", "frames"):
        for e in (ext, other):
            fileio.check_new(d / f"{name}.{e}", overwrite)
    rec = to_colmap(egm)
    with tempfile.TemporaryDirectory(dir=d, prefix=".export.tmp-") as tmp:  # fileio-exempt
        if text:
            rec.write_text(tmp)  # fileio-exempt: pycolmap writes its own files
        else:
            rec.write_binary(tmp)
        _check_written(rec, Path(tmp), d)
        for f in sorted(Path(tmp).iterdir()):
            os.replace(f, d / f.name)  # fileio-exempt: files checked whole, moved in
    for name in (*MODEL_PARTS, "rigs", "frames"):  # only the new model is left
        (d / f"{name}.{other}").unlink(missing_ok=True)
    return d


def _check_written(rec: pycolmap.Reconstruction, tmp: Path, d: Path) -> None:
    """VrsError naming ``d`` unless the model written to ``tmp`` reads back whole: pycolmap
    does not report a failed write (a full disk leaves truncated files)."""
    try:
        ix = check_model(tmp)
    except VrsError as e:
        raise VrsError(f"cannot write the COLMAP model (disk full?): {e.problem}", d) from None
    want = (rec.num_cameras(), rec.num_images(), rec.num_points3D())
    if (len(ix.cameras), len(ix.images), len(ix.point_id)) != want:
        raise VrsError("cannot write the COLMAP model (disk full?): it reads back with fewer "
                       "records", d)
