"""Incremental structure from motion with pycolmap, for image sets that come without poses.

The EGM is normally triangulated with the dataset's KNOWN poses (:mod:`vrs_jax.egm.triangulate`).
When a set of images has no poses (hloc's sacre coeur, a phone capture), COLMAP's incremental
mapper recovers them first: pycolmap's own SIFT extraction, exhaustive matching with geometric
verification, and incremental mapping with bundle adjustment, all into a work folder. The
result is turned into a :class:`~vrs_jax.data.scene.Scene` (world-to-camera poses, COLMAP pixel
convention -- the project's conventions are COLMAP's, so nothing is converted), which the
known-pose pipeline then consumes like any other dataset.

Work folder layout (re-running reuses a finished model, hloc style)::

    work_dir/database.db          COLMAP database (features, matches, two-view geometries)
    work_dir/sparse/<k>/          the reconstructions pycolmap wrote
    work_dir/model/               the largest one, copied; its presence means "done"
"""

from __future__ import annotations

import dataclasses
import shutil
import warnings
from pathlib import Path

import numpy as np
import pycolmap

from vrs_jax import geometry
from vrs_jax.data.images import image_size
from vrs_jax.data.readers.colmap import quiet_pycolmap
from vrs_jax.data.scene import Scene
from vrs_jax.errors import VrsError, require_dir

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".ppm", ".pgm")

# COLMAP camera models whose distortion maps onto OpenCV's (k1, k2, p1, p2, k3).
_SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


@dataclasses.dataclass(frozen=True)
class SfmConfig:
    """Options of the incremental SfM run (all passed to pycolmap)."""

    # Images are resized so that their longer side is at most this (COLMAP's default is 3200);
    # 1024 keeps sacre coeur (about 1000 px photos) at full size and bounds CPU time elsewhere.
    max_image_size: int = 1024
    # SIFT features per image: 8192 is COLMAP's default; Internet photos need many.
    max_num_features: int = 8192
    # SIMPLE_RADIAL (f, cx, cy, k) is COLMAP's default for unknown cameras; its distortion is
    # OpenCV's k1, so the Scene gets dist = (k, 0, 0, 0, 0) without any conversion.
    camera_model: str = "SIMPLE_RADIAL"
    # One shared camera for all images (a video) or one per image (Internet photos).
    single_camera: bool = False
    # Minimum number of verified matches for an image pair to count (COLMAP's default 15).
    min_num_matches: int = 15
    # Threads for extraction/matching/mapping (-1: all cores).
    num_threads: int = -1
    # Fixed seed for the RANSAC / mapper randomness, so that runs are repeatable.
    seed: int = 0


def list_images(image_dir: str | Path) -> list[str]:
    """Image file names (relative to ``image_dir``, sorted) of every image under it."""
    root = require_dir(image_dir, "image folder")
    names = sorted(
        p.relative_to(root).as_posix()
        for p in root.rglob("*")
        if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
    )
    if not names:
        raise VrsError("no images (" + ", ".join(IMAGE_EXTENSIONS) + ") in folder", root)
    return names


def run_sfm(image_dir: str | Path, work_dir: str | Path, image_names: list[str] | None = None,
            cfg: SfmConfig = SfmConfig(), overwrite: bool = False, verbose: bool = False
            ) -> pycolmap.Reconstruction:
    """Run pycolmap's incremental SfM on the images of ``image_dir`` (largest model returned).

    Args:
      image_dir: folder of images (searched recursively when ``image_names`` is None).
      work_dir: folder for the database and models; a finished ``work_dir/model`` is reused
        unless ``overwrite``.
      image_names: names relative to ``image_dir`` to use (default: all images).
      cfg: :class:`SfmConfig`.
      verbose: keep COLMAP's log lines.
    Returns:
      The reconstruction with the most registered images.
    Raises:
      VrsError if the folder has fewer than 2 images or SfM registers no image pair at all.
    """
    image_dir = require_dir(image_dir, "image folder")
    names = list_images(image_dir) if image_names is None else list(image_names)
    for n in names:
        if not (image_dir / n).is_file():
            raise VrsError("image not found", image_dir / n)
    if len(names) < 2:
        raise VrsError(f"SfM needs at least 2 photos of the scene, found {len(names)}",
                       image_dir)
    if cfg.camera_model not in _SUPPORTED_MODELS:
        raise VrsError(f"SfmConfig.camera_model must be one of {_SUPPORTED_MODELS}, "
                       f"got {cfg.camera_model!r}")
    work = Path(work_dir)
    model_dir = work / "model"
    if model_dir.is_dir() and not overwrite:
        rec = pycolmap.Reconstruction()
        try:
            rec.read(model_dir)
        except Exception as e:  # a truncated model from a killed run
            raise VrsError(f"cannot read the SfM model ({e}); re-run with overwrite",
                           model_dir) from e
        return rec
    if work.exists():
        # A database from an interrupted run may hold half the features: start clean.
        for p in (work / "database.db", work / "sparse", model_dir):
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    work.mkdir(parents=True, exist_ok=True)
    with quiet_pycolmap(verbose):
        try:
            best = _run_pipeline(image_dir, work / "database.db", work / "sparse", names, cfg)
        except (RuntimeError, ValueError) as e:  # a COLMAP check on unexpected input
            raise VrsError(f"pycolmap SfM failed: {e}", image_dir) from e
    tmp = work / "model.tmp"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    best.write(tmp)
    tmp.replace(model_dir)
    return best


def _run_pipeline(image_dir: Path, db: Path, sparse: Path, names: list[str], cfg: SfmConfig
                  ) -> pycolmap.Reconstruction:
    """Extraction, exhaustive matching and incremental mapping; the largest model."""

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = cfg.max_image_size
    extraction.num_threads = cfg.num_threads
    extraction.sift.max_num_features = cfg.max_num_features
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    mode = pycolmap.CameraMode.SINGLE if cfg.single_camera else pycolmap.CameraMode.PER_IMAGE
    pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=mode,
                              reader_options=reader, extraction_options=extraction,
                              device=pycolmap.Device.cpu)

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = cfg.num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = cfg.seed
    pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                              device=pycolmap.Device.cpu)

    options = pycolmap.IncrementalPipelineOptions()
    options.min_num_matches = cfg.min_num_matches
    options.num_threads = cfg.num_threads
    options.random_seed = cfg.seed
    sparse.mkdir(exist_ok=True)
    recs = pycolmap.incremental_mapping(db, image_dir, sparse, options=options)
    if not recs:
        raise VrsError(f"incremental SfM registered no images out of {len(names)} "
                       "(too few matches between the photos?)", image_dir)
    return max(recs.values(), key=lambda r: r.num_reg_images())


def _camera_to_opencv(cam: pycolmap.Camera) -> tuple[np.ndarray, np.ndarray]:
    """pycolmap camera -> (K [3, 3], dist [5] OpenCV (k1, k2, p1, p2, k3))."""
    name = cam.model.name
    p = np.asarray(cam.params, np.float64)
    dist = np.zeros(5)
    if name == "SIMPLE_PINHOLE":
        K = geometry.intrinsics_matrix(p[0], p[0], p[1], p[2])
    elif name == "PINHOLE":
        K = geometry.intrinsics_matrix(p[0], p[1], p[2], p[3])
    elif name == "SIMPLE_RADIAL":
        K = geometry.intrinsics_matrix(p[0], p[0], p[1], p[2])
        dist[0] = p[3]
    elif name == "RADIAL":
        K = geometry.intrinsics_matrix(p[0], p[0], p[1], p[2])
        dist[:2] = p[3:5]
    elif name == "OPENCV":
        K = geometry.intrinsics_matrix(p[0], p[1], p[2], p[3])
        dist[:4] = p[4:8]
    else:
        raise VrsError(f"camera model {name} has no OpenCV (k1, k2, p1, p2, k3) equivalent")
    return np.asarray(K, np.float64), dist


def scene_from_reconstruction(rec: pycolmap.Reconstruction, image_dir: str | Path,
                              image_names: list[str] | None = None, fmt: str = "sfm") -> Scene:
    """A Scene of reference images from a reconstruction; unregistered images get no pose.

    Args:
      rec: reconstruction (e.g. from :func:`run_sfm`).
      image_dir: folder the image names are relative to.
      image_names: the images to include, in this order (default: those in ``rec``, sorted).
      fmt: value of ``Scene.format``.
    """
    image_dir = Path(image_dir)
    by_name = {im.name: im for im in rec.images.values()}
    names = sorted(by_name) if image_names is None else list(image_names)
    n = len(names)
    K = np.tile(np.eye(3), (n, 1, 1))
    dist = np.zeros((n, 5))
    sizes = np.zeros((n, 2), np.int64)
    R = np.tile(np.eye(3), (n, 1, 1))
    t = np.zeros((n, 3))
    has_pose = np.zeros(n, bool)
    for i, name in enumerate(names):
        im = by_name.get(name)
        if im is None:
            sizes[i] = image_size(image_dir / name)
            continue
        cam = rec.camera(im.camera_id)
        K[i], dist[i] = _camera_to_opencv(cam)
        sizes[i] = (cam.width, cam.height)
        if im.has_pose:
            pose = im.cam_from_world()
            R[i] = pose.rotation.matrix()
            t[i] = pose.translation
            has_pose[i] = True
    missing = [nm for nm, ok in zip(names, has_pose, strict=True) if not ok]
    if missing:
        warnings.warn(f"SfM did not register {len(missing)} of {n} images: "
                      + ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else ""),
                      stacklevel=2)
    pts = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    return Scene(root=image_dir, names=names, image_paths=[image_dir / nm for nm in names],
                 K=K, dist=dist, sizes=sizes, R=R, t=t, has_pose=has_pose,
                 is_query=np.zeros(n, bool), points3d=pts, format=fmt)


def scene_from_images(image_dir: str | Path, work_dir: str | Path, cfg: SfmConfig = SfmConfig(),
                      overwrite: bool = False, verbose: bool = False) -> Scene:
    """Poses for an unposed image folder by incremental SfM, as a Scene of references."""
    names = list_images(image_dir)
    rec = run_sfm(image_dir, work_dir, names, cfg, overwrite=overwrite, verbose=verbose)
    return scene_from_reconstruction(rec, image_dir, names, fmt="sfm")
