"""Aachen Day-Night: an NVM database model plus query lists with intrinsics.

Layout of ``root``::

    root/3D-models/aachen_cvpr2018_db.nvm           database cameras (and points)
    root/queries/*_queries_with_intrinsics.txt      ``name MODEL w h params...`` (COLMAP)
    root/images_upright/db/*.jpg, root/images_upright/query/...

Database images get their world-to-camera pose from the NVM (quaternion w first + centre,
``t = -R c``); queries have no ground truth (``has_pose`` False, ``is_query`` True) and their
intrinsics from the query list (SIMPLE_RADIAL etc., scaled if the file's image size differs
from the actual one).

Database intrinsics: the NVM stores one focal per image, in the pixels of the image the model
was built from, and VisualSFM puts the principal point at the image centre. ASSUMPTION: that
image is the one on disk (``nvm_size=None``): the Aachen database images are distributed at
the resolution of the reconstruction (the sample's 1600x1067 frames with f = 1084.6 px give a
plausible 73 degree horizontal field of view, and kapture's conversion of the same files uses
the same numbers). If your images were downscaled after the reconstruction, pass
``nvm_size=(w, h)`` (one size for all) or ``nvm_max_side=M`` (the longer side of the images
the NVM was built from); the focal is then scaled by ``actual / original``. The NVM radial
parameter becomes OpenCV ``k1 = -r`` (first-order inverse of NVM's undistortion model, as
COLMAP's NVM import does); it is small (|r| < 0.1) on Aachen, so the approximation error is
of order r^2 |x|^5, well under a pixel inside the image.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vrs_jax.data.readers import _common as C
from vrs_jax.data.readers import nvm as nvm_reader
from vrs_jax.data.readers.query_list import read_query_list
from vrs_jax.errors import VrsError, require_dir

DEFAULT_NVM = Path("3D-models") / "aachen_cvpr2018_db.nvm"


def load(root: str | Path, *, nvm: str | Path | None = None, images: str | Path | None = None,
         queries: list[str | Path] | str | Path | None = None,
         nvm_size: tuple[int, int] | None = None, nvm_max_side: int | None = None,
         read_points: bool = True, query_every: int = 0):
    """Read Aachen Day-Night (see the module docstring for the intrinsics assumptions).

    Args:
      root: dataset folder.
      nvm: database NVM model (default ``root/3D-models/aachen_cvpr2018_db.nvm``).
      images: image folder the names are relative to (default ``root/images_upright``).
      queries: query list file(s) (default: every ``root/queries/*_queries_with_intrinsics.txt``;
        an empty list loads the database only).
      nvm_size, nvm_max_side: the original image size of the NVM focals (module docstring).
      read_points: put the NVM's points into ``Scene.points3d``.
      query_every: also hold out every N-th database image (by name) as a query; these keep
        their NVM pose, so they can be evaluated (Aachen's own queries have no ground truth).
    Returns:
      Scene with database images (references, posed) then queries (unposed); names relative
      to the images folder (``db/1045.jpg``, ``query/day/...``). Queries whose image is
      missing are skipped with a warning; a missing database image is an error.
    """
    root = require_dir(root, "Aachen folder")
    img_dir = require_dir(Path(images) if images is not None else root / "images_upright",
                          "images folder")
    model = nvm_reader.read_nvm(Path(nvm) if nvm is not None else root / DEFAULT_NVM,
                                read_points=read_points)

    db_paths = [img_dir / n for n in model.names]
    for p in db_paths:
        if not p.is_file():
            raise VrsError("database image of the NVM model not found", p)
    db_sizes = C.image_sizes(db_paths)
    K_db = np.zeros((len(db_paths), 3, 3))
    for i, (w, h) in enumerate(db_sizes):
        if nvm_size is not None:
            s = w / float(nvm_size[0])
        elif nvm_max_side is not None:
            s = max(w, h) / float(nvm_max_side)
        else:
            s = 1.0
        f = model.focal[i] * s
        K_db[i] = C.pinhole(f, f, w / 2, h / 2)
    dist_db = np.zeros((len(db_paths), 5))
    dist_db[:, 0] = nvm_reader.nvm_k1(model.radial)

    if queries is None:
        qdir = root / "queries"
        query_files = sorted(qdir.glob("*_queries_with_intrinsics.txt")) if qdir.is_dir() else []
    elif isinstance(queries, (str, Path)):
        query_files = [Path(queries)]
    else:
        query_files = [Path(q) for q in queries]
    q_names, q_paths, q_K, q_dist, q_sizes, missing = [], [], [], [], [], []
    for qf in query_files:
        for e in read_query_list(qf):
            p = img_dir / e.name
            if not p.is_file():
                missing.append(e.name)
                continue
            q_names.append(e.name)
            q_paths.append(p)
            q_K.append(e.K)
            q_dist.append(e.dist)
            q_sizes.append((e.width, e.height))
    C.warn_list(f"Aachen queries whose image is missing under {img_dir}, skipped", missing)
    actual = C.image_sizes(q_paths, tolerate=[True] * len(q_paths), declared=q_sizes)
    q_K = [C.scale_to_size(K, s0, s, p)
           for K, s0, s, p in zip(q_K, q_sizes, actual, q_paths, strict=True)]

    nq, nd = len(q_names), len(db_paths)
    R = np.concatenate([model.R, np.tile(np.eye(3), (nq, 1, 1))])
    t = np.concatenate([model.t, np.zeros((nq, 3))])
    return C.make_scene(
        root, list(model.names) + q_names, db_paths + q_paths,
        np.concatenate([K_db, np.asarray(q_K).reshape(nq, 3, 3)]),
        np.concatenate([dist_db, np.asarray(q_dist).reshape(nq, 5)]),
        np.concatenate([db_sizes, actual]), R, t,
        np.arange(nd + nq) < nd,
        np.concatenate([C.query_mask(model.names, query_every), np.ones(nq, bool)]), "aachen",
        points3d=model.points if read_points else None)
