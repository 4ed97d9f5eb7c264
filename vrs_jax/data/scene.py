"""The one host-side scene structure that every dataset reader returns.

All conventions are converted at the reader boundary (docs/design.md, section 3): poses are
world-to-camera in OpenCV axes, intrinsics in COLMAP's pixel convention, metres.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from vrs_jax import geometry


@dataclasses.dataclass
class Scene:
    """N images with their cameras, poses and split.

    Attributes:
      root: dataset root folder.
      names: [N] unique image names, used in results files: relative to the dataset root
        (7Scenes, Cambridge, NeRF), to the images folder (Aachen, COLMAP: as hloc and the
        benchmarks name them), or bare file names (LLFF).
      image_paths: [N] absolute paths of the colour images.
      K: [N, 3, 3] float64 intrinsics (COLMAP pixel convention: pixel centres at +0.5).
      dist: [N, 5] float64 OpenCV distortion ``(k1, k2, p1, p2, k3)``; zeros if none.
      sizes: [N, 2] int (width, height) in pixels of the images as read.
      R: [N, 3, 3] float64 world-to-camera rotations (identity where ``has_pose`` is False).
      t: [N, 3] float64 world-to-camera translations in metres (zeros where no pose).
      has_pose: [N] bool; False for queries without ground truth (Aachen) or unposed sets.
      is_query: [N] bool; True for held-out query images, False for reference images.
      depth_paths: [N] paths of depth images (None where absent), or None for the scene.
      depth_K: [N, 3, 3] intrinsics of the depth images (7Scenes: the depth camera), or None.
      depth_scale: metres per unit of the stored depth (0.001 for millimetre PNGs).
      bounds: [N, 2] near/far depth bounds given by the dataset (LLFF), or None.
      points3d: [M, 3] sparse points shipped with the dataset (COLMAP/NVM), or None.
      background: RGB in [0, 1] that RGBA images were composited on, or None.
      format: name of the reader that produced it.
    """

    root: Path
    names: list[str]
    image_paths: list[Path]
    K: np.ndarray
    dist: np.ndarray
    sizes: np.ndarray
    R: np.ndarray
    t: np.ndarray
    has_pose: np.ndarray
    is_query: np.ndarray
    depth_paths: list[Path | None] | None = None
    depth_K: np.ndarray | None = None
    depth_scale: float = 0.001
    bounds: np.ndarray | None = None
    points3d: np.ndarray | None = None
    background: tuple[float, float, float] | None = None
    format: str = ""

    def __post_init__(self) -> None:
        n = len(self.names)
        for field in ("image_paths", "K", "dist", "sizes", "R", "t", "has_pose", "is_query"):
            if len(getattr(self, field)) != n:
                raise ValueError(f"Scene.{field} has {len(getattr(self, field))} entries, not {n}")
        if len(set(self.names)) != n:
            raise ValueError("Scene.names must be unique")

    def __len__(self) -> int:
        return len(self.names)

    @property
    def centers(self) -> np.ndarray:
        """[N, 3] camera centres in world coordinates."""
        return geometry.camera_center(self.R, self.t)

    def subset(self, idx: np.ndarray | list[int]) -> Scene:
        """A new Scene with the images at integer indices or boolean mask ``idx``."""
        idx = np.asarray(idx)
        if idx.dtype == bool:
            idx = np.flatnonzero(idx)
        pick = lambda seq: None if seq is None else [seq[i] for i in idx]  # noqa: E731
        arr = lambda a: None if a is None else np.asarray(a)[idx]  # noqa: E731
        return dataclasses.replace(
            self,
            names=[self.names[i] for i in idx],
            image_paths=[self.image_paths[i] for i in idx],
            K=arr(self.K), dist=arr(self.dist), sizes=arr(self.sizes), R=arr(self.R),
            t=arr(self.t), has_pose=arr(self.has_pose), is_query=arr(self.is_query),
            depth_paths=pick(self.depth_paths), depth_K=arr(self.depth_K),
            bounds=arr(self.bounds),
        )

    def references(self) -> Scene:
        """The reference (mapping) images."""
        return self.subset(~self.is_query)

    def queries(self) -> Scene:
        """The query images."""
        return self.subset(self.is_query)


def hold_out_every(n_images: int, every: int, offset: int = 0) -> np.ndarray:
    """Query mask [n_images] bool holding out every ``every``-th frame (starting at ``offset``).

    ``every <= 0`` holds out nothing.
    """
    mask = np.zeros(n_images, dtype=bool)
    if every > 0:
        mask[offset::every] = True
    return mask
