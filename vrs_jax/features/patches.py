"""Canonical patches: the sample grid of a keypoint and reading it from a real image (pure JAX).

A keypoint ``(x, y, scale, angle)`` (see keypoints.py) defines a P x P grid of sample
positions. ``patch_grid`` is the one generator of that grid; it feeds both the real-image
reader below and, later, the NeRF ray caster (one cone per sample, radius from ``footprint``),
so that real and rendered patches describe the same piece of the scene.

Canonical mode (default): the grid is centred on the keypoint, rotated by its angle and
spaced in proportion to its scale. It covers a square of side
``window_per_scale * scale`` = 12 * scale by default, the support of SIFT's descriptor
(4 x 4 cells of 3 * scale each), whatever P is: P only sets how finely that square is
sampled (spacing = 12 * scale / P, 0.8 * scale for P = 15). Sample (i, j) of the patch,
row i and column j, sits at

    (x, y) + spacing * (u * (cos a, sin a) + v * (-sin a, cos a)),
    u = j - (P - 1) / 2,  v = i - (P - 1) / 2,

in pixel axes (x right, y down): the patch's column axis is the keypoint direction and its
row axis that direction turned by +90 degrees in pixel axes. Hence the grid of a keypoint
transformed by an image similarity is exactly the transformed grid (tested).

Literal mode (the paper's): an axis-aligned P x P block of whole pixels around the pixel
holding the keypoint, no scale, no rotation: centre (floor(x) + 0.5, floor(y) + 0.5),
spacing 1 pixel, so every sample is an exact pixel value.

Reading real images, with anti-aliasing: a sample spaced ``s`` pixels from its neighbours
should see the image low-passed to about that resolution, or a large keypoint aliases. The
image is therefore blurred into a small stack of levels (fixed Gaussian sigmas, level l
meant for spacing 2^(l / levels_per_octave)), and each keypoint reads its samples by
trilinear interpolation in (level, y, x): bilinear within a level, linear between the two
levels bracketing log2(spacing). Level 0 is the unblurred image (spacing <= 1 px).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy import ndimage

from vrs_jax.errors import VrsError

PATCH_SIZES = (9, 11, 13, 15, 31)
PATCH_MODES = ("canonical", "literal")


@dataclasses.dataclass(frozen=True)
class PatchConfig:
    """Patch geometry and anti-aliasing (single source of truth; hashable, so jit-static)."""

    # P: samples per side. 15 is the paper's patch size (31 on Aachen); 9/11/13/15/31 are the
    # ablation's sizes. Odd, so the centre sample sits on the keypoint.
    size: int = 15
    # "canonical" (scaled + rotated grid, ours) or "literal" (paper: whole pixels, no
    # scale or rotation).
    mode: str = "canonical"
    # Side of the canonical square in units of keypoint scale: SIFT's descriptor support,
    # 4 cells x 3 sigma (Lowe 2004, SIFT_DESCR_SCL_FCTR = 3). The support, not the sample
    # count, is what makes descriptors comparable, so it does not change with P.
    window_per_scale: float = 12.0
    # Spacing between samples in units of scale; None derives it as window_per_scale / size
    # (0.8 for P = 15). Setting it explicitly makes the support grow with P instead.
    spacing_per_scale: float | None = None
    # Anti-aliasing: a grid of spacing s reads the image blurred to a total Gaussian sigma of
    # blur_per_spacing * s (0.5 s: the usual pre-filter before decimating by s, as a 2x
    # Gaussian pyramid uses sigma ~ 1 px); the image itself is assumed to carry input_blur
    # (0.5 px, the camera's own blur, as SIFT assumes), so a level adds
    # sqrt((0.5 s)^2 - 0.5^2). For s <= 1 nothing is added (level 0 = the raw image).
    blur_per_spacing: float = 0.5
    input_blur: float = 0.5
    # Stack of blur levels: level l serves spacing 2^(l / levels_per_octave). Two levels
    # per octave keep the blur within a factor 2^0.25 of the ideal after linear blending;
    # 11 levels reach spacing 32 px (keypoint scale 40 px at P = 15). Larger keypoints
    # read the top level (slightly under-blurred), which is rare for SIFT on <= 1 MP images.
    levels_per_octave: int = 2
    n_levels: int = 11

    def __post_init__(self):
        if self.size not in PATCH_SIZES:
            raise VrsError(f"PatchConfig.size must be one of {PATCH_SIZES}, got {self.size}")
        if self.mode not in PATCH_MODES:
            raise VrsError(f"PatchConfig.mode must be one of {PATCH_MODES}, got {self.mode!r}")
        if self.levels_per_octave < 1 or self.n_levels < 1:
            raise VrsError("PatchConfig.levels_per_octave and n_levels must be >= 1")
        if self.window_per_scale <= 0 or (self.spacing_per_scale is not None
                                          and self.spacing_per_scale <= 0):
            raise VrsError("PatchConfig window/spacing per scale must be positive")

    @property
    def spacing(self) -> float:
        """Sample spacing in units of keypoint scale (canonical mode)."""
        if self.spacing_per_scale is not None:
            return float(self.spacing_per_scale)
        return self.window_per_scale / self.size

    def level_sigmas(self) -> tuple[float, ...]:
        """Extra Gaussian sigma (pixels) that each level adds to the raw image; level 0: 0."""
        out = []
        for lev in range(self.n_levels if self.mode == "canonical" else 1):
            s = 2.0 ** (lev / self.levels_per_octave)
            out.append(math.sqrt(max((self.blur_per_spacing * s) ** 2 - self.input_blur ** 2,
                                     0.0)))
        return tuple(out)


# ----------------------------------------------------------------------------- grid


def _xp(*arrays):
    """numpy for numpy inputs, jax.numpy when any input is a jax array or tracer."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


def patch_grid(kp, cfg: PatchConfig = PatchConfig(), side: int | None = None):
    """Sample positions of the patches of keypoints (numpy in -> numpy out, jax -> jax).

    Args:
      kp: [..., 4] keypoints (x, y, scale, angle), COLMAP pixel convention.
      cfg: patch settings (size P, mode, spacing).
      side: canonical mode only: S >= 2 evenly spaced samples per row and column over the
        same extent as the P samples (both ends shared), e.g. the corners for S = 2; None:
        the P samples.
    Returns:
      positions: [..., P, P, 2] (or [..., S, S, 2]) float32 (x, y) pixel coordinates of
        sample (row i, column j).
      footprint: [...] float32 spacing between neighbouring samples of the full P grid in
        pixels (canonical: cfg.spacing * scale; literal: 1). The ray caster turns it into a
        cone radius.
    """
    xp = _xp(kp)
    kp = xp.asarray(kp, dtype=xp.float32)
    P = cfg.size
    if side is None or side == P:
        off = xp.arange(P, dtype=xp.float32) - xp.float32((P - 1) / 2.0)
    elif cfg.mode == "literal" or side < 2:
        raise VrsError(f"a patch grid of {side} samples per side needs canonical patches and "
                       f"at least 2 (P = {P}, mode {cfg.mode})")
    else:  # the P grid's offsets at S evenly spaced fractional indices
        step = (P - 1) / (side - 1)
        off = xp.asarray(np.arange(side) * step - (P - 1) / 2.0, dtype=xp.float32)
    v, u = xp.meshgrid(off, off, indexing="ij")  # [P, P]: v along rows, u along columns
    x, y = kp[..., 0, None, None], kp[..., 1, None, None]
    if cfg.mode == "literal":
        cx, cy = xp.floor(x) + 0.5, xp.floor(y) + 0.5
        pos = xp.stack([cx + u, cy + v], axis=-1)
        foot = xp.ones(kp.shape[:-1], xp.float32)
        return pos.astype(xp.float32), foot
    foot = xp.float32(cfg.spacing) * kp[..., 2]
    s = foot[..., None, None]
    c, sn = xp.cos(kp[..., 3])[..., None, None], xp.sin(kp[..., 3])[..., None, None]
    px = x + s * (c * u - sn * v)
    py = y + s * (sn * u + c * v)
    return xp.stack([px, py], axis=-1).astype(xp.float32), foot.astype(xp.float32)


def grid_inside(positions, width: int, height: int):
    """[..., P, P, 2] sample positions -> [...] bool: every sample lies inside the image.

    The image covers [0, width] x [0, height] in COLMAP pixel coordinates; samples outside
    read clamped border values, so callers may prefer to drop such patches.
    """
    xp = _xp(positions)
    x, y = positions[..., 0], positions[..., 1]
    ok = (x >= 0) & (x <= width) & (y >= 0) & (y <= height)
    return xp.all(ok, axis=(-2, -1))


# ----------------------------------------------------------------------------- image side


def _gaussian_kernel(sigma: float) -> np.ndarray:
    """Sampled, normalised 1-D Gaussian with radius ceil(4 sigma) (as cv2.getGaussianKernel
    for an explicit ksize = 2 * radius + 1)."""
    r = max(1, int(math.ceil(4.0 * sigma)))
    t = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (t / sigma) ** 2)
    return (k / k.sum()).astype(np.float32)


def _kernel_spectrum(sigma: float, n: int, real_fft: bool) -> np.ndarray:
    """DFT (length n, or n // 2 + 1 for a real FFT) of the centred sampled kernel."""
    row = np.zeros(n, np.float64)
    if sigma <= 0:
        row[0] = 1.0
    else:
        k = _gaussian_kernel(sigma).astype(np.float64)
        r = (len(k) - 1) // 2
        row[np.arange(-r, r + 1) % n] += k
    f = np.fft.rfft(row) if real_fft else np.fft.fft(row)
    return f.real.astype(np.float32)  # symmetric kernel: real spectrum


def fft_size(n: int) -> int:
    """The smallest 5-smooth integer (2^a 3^b 5^c) >= n: an FFT length without large prime
    factors (the reflect-padded 270-row image is 398 = 2 x 199 rows)."""
    m = n
    while True:
        r = m
        for p in (2, 3, 5):
            while r % p == 0:
                r //= p
        if r == 1:
            return m
        m += 1


def gaussian_blur_stack(image, sigmas: tuple[float, ...]):
    """[H, W] image -> [len(sigmas), H, W]: separable Gaussian blurs with static sigmas.

    Each level equals cv2.GaussianBlur(image, (k, k), sigma, borderType=BORDER_REFLECT_101)
    with k = 2 * ceil(4 sigma) + 1 (tested); sigma <= 0 gives the image itself. Computed as
    one FFT of the image reflect-padded by the largest kernel radius (so the circular
    convolution never wraps) times each level's kernel spectrum: a few FFTs instead of
    spatial kernels up to ~130 taps wide. The padded image is then zero-filled to 5-smooth
    sizes (:func:`fft_size`): the kept pixels read only the reflected border, never the fill,
    and the FFTs of a 480 x 270 image's 11 levels take ~30% less time.
    """
    image = jnp.asarray(image, jnp.float32)
    if all(s <= 0 for s in sigmas):
        return jnp.broadcast_to(image, (len(sigmas), *image.shape))
    H, W = image.shape
    r = max(max(1, int(math.ceil(4.0 * s))) for s in sigmas if s > 0)
    x = jnp.pad(image, r, mode="reflect")
    x = jnp.pad(x, ((0, fft_size(x.shape[0]) - x.shape[0]), (0, fft_size(x.shape[1]) - x.shape[1])))
    hp, wp = x.shape
    ty = np.stack([_kernel_spectrum(s, hp, False) for s in sigmas])  # [L, hp]
    tx = np.stack([_kernel_spectrum(s, wp, True) for s in sigmas])  # [L, wp // 2 + 1]
    spec = jnp.fft.rfft2(x)
    out = jnp.fft.irfft2(spec[None] * (ty[:, :, None] * tx[:, None, :]), s=(hp, wp))
    out = out[:, r:r + H, r:r + W]
    exact = jnp.asarray([s <= 0 for s in sigmas])[:, None, None]
    return jnp.where(exact, image[None], out)  # unblurred levels bit-exact


@functools.partial(jax.jit, static_argnames="cfg")
def blur_stack(image, cfg: PatchConfig = PatchConfig()):
    """[H, W] grey float image -> [L, H, W] stack of blur levels (L = 1 in literal mode).

    Level l is the image blurred by ``cfg.level_sigmas()[l]`` (0 for level 0), the blur that
    sampling at spacing 2^(l / levels_per_octave) needs. Compute it once per image and call
    ``sample_patches`` as often as needed.
    """
    image = jnp.asarray(image, jnp.float32)
    if image.ndim != 2:
        raise VrsError(f"patches are read from a grey image [H, W], got shape {image.shape}")
    return gaussian_blur_stack(image, cfg.level_sigmas())


def level_of(footprint, cfg: PatchConfig = PatchConfig()):
    """Fractional blur level [...] for a sample spacing [...] in pixels (0 for <= 1 px)."""
    xp = _xp(footprint)
    lev = xp.log2(xp.maximum(footprint, 1.0)) * cfg.levels_per_octave
    n = cfg.n_levels if cfg.mode == "canonical" else 1
    return xp.clip(lev, 0.0, n - 1)


@functools.partial(jax.jit, static_argnames="cfg")
def sample_patches(stack, kp, cfg: PatchConfig = PatchConfig()):
    """Read patches from a precomputed blur stack.

    Args:
      stack: [L, H, W] from ``blur_stack(image, cfg)``.
      kp: [K, 4] keypoints (any leading shape [..., 4] works).
      cfg: patch settings (must be the config that built the stack).
    Returns:
      [..., P, P] float32 patches. Sample (i, j) is the image at positions[i, j] (see
      ``patch_grid``), interpolated bilinearly with array element [r, c] at (c + 0.5, r + 0.5)
      and linearly between the two blur levels bracketing the keypoint's spacing. Samples
      outside the image take the value of the nearest border pixel.
    """
    stack = jnp.asarray(stack, jnp.float32)
    pos, foot = patch_grid(jnp.asarray(kp, jnp.float32), cfg)
    lev = jnp.broadcast_to(level_of(foot, cfg)[..., None, None], pos.shape[:-1])
    lev = jnp.minimum(lev, stack.shape[0] - 1)
    coords = [lev, pos[..., 1] - 0.5, pos[..., 0] - 0.5]
    return ndimage.map_coordinates(stack, coords, order=1, mode="nearest")


@functools.partial(jax.jit, static_argnames="cfg")
def extract_patches(image, kp, cfg: PatchConfig = PatchConfig()):
    """Patches of keypoints from a real grey image (jittable with cfg static, no loops).

    Args:
      image: [H, W] float32 grey image (e.g. in [0, 1]).
      kp: [K, 4] keypoints (x, y, scale, angle), COLMAP convention.
      cfg: patch settings.
    Returns:
      [K, P, P] float32 patches (canonical: anti-aliased by the blur level matching each
      keypoint's spacing; literal: exact pixel values).
    """
    return sample_patches(blur_stack(image, cfg), kp, cfg)
