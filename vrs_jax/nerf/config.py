"""NerfConfig: the single source of truth for the implicit map's hyper-parameters.

Named configurations (``get_config(name)``):

- ``paper``: the VRS-NeRF paper's implicit map is Mip-NeRF with 128 coarse + 128 fine
  samples, a batch of 1024 rays and Adam; its remaining values were never published, so
  they are mip-NeRF's own (Barron et al. 2021, ``configs/blender.gin``): an 8 x 256 MLP
  with the input skip after layer 4, a 1-layer 128-wide view-dependent head, IPE degrees
  0..16, view encoding degree 4, lr 5e-4 -> 5e-6 log-linear with a 2500-step warm-up at
  0.01x, coarse loss weight 0.1.
- ``cpu-small``: a configuration that trains on 2 CPU cores in minutes: a hash-grid field
  (the rendered keypoint patches localize better than an IPE MLP's, measured on dtu_scan24
  and lego), with the sampling and optimiser tuned on lego 200x200 (see the comments).
- ``test``: tiny, for unit tests only.

Every field's comment gives the reason for its value.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

from vrs_jax import configio
from vrs_jax.errors import VrsError

ENCODINGS = ("ipe", "hashgrid")
CLUSTER_METHODS = ("kmeans", "grid")  # nerf/clusters.py METHODS

# Valid ranges of NerfConfig's numeric fields (checked on construction).
_INT_AT_LEAST = {
    "net_depth": 1, "net_width": 1, "skip_layer": 0, "net_depth_condition": 0,
    "net_width_condition": 1, "min_deg_point": 0, "max_deg_point": 0, "deg_view": 0,
    "hash_levels": 1, "hash_features": 1, "hash_base_res": 1, "hash_max_res": 1,
    "num_samples_coarse": 1, "num_samples_fine": 0, "batch_size": 1, "lr_delay_steps": 0,
    "max_steps": 1, "n_clusters": 1, "patch_pool_max_rays": 0, "render_chunk": 1,
    "log_every": 1, "eval_every": 1, "eval_rays": 1, "checkpoint_every": 1,
    "keep_checkpoints": 1, "seed": 0, "hash_log2_table": 1, "window_samples": 1,
    "window_fine": 0,
}
_MAX_LOG2_TABLE = 24  # 2^24 entries x 16 levels x 2 features: 2 GB of float32 per cluster
_INF = math.inf
# field: (low, high, low excluded, high excluded)
_FLOAT_RANGES = {
    "hash_init_scale": (0.0, _INF, True, False), "resample_padding": (0.0, _INF, False, False),
    "density_bias": (-_INF, _INF, False, False), "rgb_padding": (0.0, 0.5, False, True),
    "density_noise": (0.0, _INF, False, False), "lr_init": (0.0, _INF, True, False),
    "lr_final": (0.0, _INF, True, False), "lr_delay_mult": (0.0, 1.0, True, False),
    "adam_b1": (0.0, 1.0, False, True), "adam_b2": (0.0, 1.0, False, True),
    "adam_eps": (0.0, _INF, True, False), "grad_max_norm": (0.0, _INF, False, False),
    "coarse_loss_mult": (0.0, _INF, False, False), "norm_radius": (0.0, _INF, True, False),
    "near_far_margin": (0.0, 1.0, False, True), "patch_ray_fraction": (0.0, 1.0, False, False),
    "cluster_overlap": (0.0, _INF, False, False),
    "depth_loss_mult": (0.0, _INF, False, False), "depth_loss_margin": (0.0, 1.0, True, True),
    "window_loss_mult": (0.0, _INF, False, False),
}


@dataclasses.dataclass(frozen=True)
class NerfConfig:
    """Mip-NeRF model, sampling, training and scene-preparation settings."""

    name: str = "paper"

    # --- MLP (mip-NeRF's architecture; one MLP shared by the coarse and fine levels)
    net_depth: int = 8  # trunk layers (mip-NeRF / NeRF)
    net_width: int = 256  # trunk width (mip-NeRF / NeRF)
    skip_layer: int = 4  # re-inject the encoded input after this layer; 0: no skip
    net_depth_condition: int = 1  # layers of the view-dependent colour head
    net_width_condition: int = 128  # its width (mip-NeRF)
    use_viewdirs: bool = True  # view-dependent colour (specularities)

    # --- encodings
    min_deg_point: int = 0  # lowest IPE frequency 2^0: coordinates in [-pi, pi] don't wrap
    max_deg_point: int = 16  # mip-NeRF; IPE itself switches off what the footprint can't see
    deg_view: int = 4  # view-direction encoding degrees (mip-NeRF)
    # Position encoding: "ipe" (mip-NeRF's integrated positional encoding, the paper's) or
    # "hashgrid" (Instant-NGP multiresolution hash grid, nerf/hashgrid.py, with Zip-NeRF's
    # footprint-weighted levels so the cone radius still anti-aliases). The hash grid moves
    # the capacity from the MLP into a table: a small MLP (e.g. 2 x 64) suffices after it.
    encoding: str = "ipe"
    hash_levels: int = 16  # L: Instant-NGP's default; resolutions base_res .. max_res
    hash_log2_table: int = 14  # T = 2^14 entries per level: the map-size knob (L*T*F floats)
    hash_features: int = 2  # F per level (Instant-NGP: 2 is the best quality per byte)
    hash_base_res: int = 16  # coarsest grid over the normalised cube [-norm_radius, +]^3
    # finest grid: 1024 cells over the cube ~ a pixel footprint of a 384-800 px view whose
    # frustum spans the cube; finer levels would be switched off by the footprint anyway
    hash_max_res: int = 1024
    hash_init_scale: float = 1e-4  # Instant-NGP: table initialised uniform(-1e-4, 1e-4)
    hash_antialias: bool = True  # Zip-NeRF level weights from the cone footprint

    # --- sampling
    num_samples_coarse: int = 128  # the paper: 128 coarse + 128 fine
    num_samples_fine: int = 128
    lindisp: bool = False  # sample linearly in disparity (forward-facing scenes)
    resample_padding: float = 0.01  # mip-NeRF: keeps a few fine samples everywhere
    density_bias: float = -1.0  # mip-NeRF: softplus(raw - 1) starts nearly transparent
    rgb_padding: float = 0.001  # mip-NeRF: sigmoid widened so 0 and 1 are reachable
    density_noise: float = 0.0  # regularising noise on raw density (mip-NeRF LLFF: 1)

    # --- optimisation
    batch_size: int = 1024  # rays per step per cluster (the paper)
    lr_init: float = 5e-4  # Adam as mip-NeRF: 5e-4 -> 5e-6 log-linear
    lr_final: float = 5e-6
    lr_delay_steps: int = 2500  # mip-NeRF Blender warm-up
    lr_delay_mult: float = 0.01
    # Training length in steps, and the horizon of the lr decay (one setting: the rate reaches
    # lr_final on the last step). mip-NeRF trains 1M steps of 4096 rays; the VRS-NeRF paper
    # does not say, so `paper` takes 200k steps of its 1024-ray batch (our choice: a GPU-day).
    max_steps: int = 200_000
    adam_b1: float = 0.9
    adam_b2: float = 0.999
    adam_eps: float = 1e-8
    grad_max_norm: float = 0.0  # 0: no clipping (mip-NeRF)
    coarse_loss_mult: float = 0.1  # loss = 0.1 coarse + fine (mip-NeRF)

    # --- scene preparation
    norm_radius: float = math.pi  # sampled region mapped into [-norm_radius, norm_radius]^3
    # Scene contraction for unbounded scenes (mip-NeRF 360, section 2): each cluster's inner
    # ball (its cameras plus the median depth of what they see, nerf/data.inner_ball) keeps
    # its resolution, and space beyond it is contracted, x -> (2 - 1/|x|) x/|x| in units of
    # the ball's radius, so the far field to infinity fits in a ball of twice the radius,
    # with a resolution that falls with distance as a pixel's footprint grows; the frustum
    # Gaussians are pushed through the contraction (isotropic Jacobian, as Zip-NeRF does) and
    # the ray samples are spaced linearly inside the ball and in disparity beyond it
    # (mipnerf.stratified_t_vals' pivot). False: the bounding box of every camera's sampled
    # region, near to far, is mapped into the cube (bounded and object-centric scenes).
    contraction: bool = False
    near_far_percentiles: tuple[float, float] = (1.0, 99.0)  # of the depth prior's samples
    near_far_margin: float = 0.2  # near *= 1 - m, far *= 1 + m around those percentiles
    n_clusters: int = 1  # K-means clusters of reference cameras (Aachen: 16 in the paper)
    # Keypoint-patch training rays (nerf/patch_pool.py): this fraction of every batch comes
    # from the canonical patch samples of the map's keypoints (targets: the anti-aliased real
    # patches), the rest from whole-image pixels. 0 trains on whole images only (the paper).
    # 0.5: the map's renders are only ever patches, but full views stay usable for
    # inspection and held-out PSNR. Measured: no gain on the synthetic room (README).
    patch_ray_fraction: float = 0.5
    patch_pool_max_rays: int = 4_000_000  # cap on the pool (memory: 52 B per ray)
    # Depth supervision of the keypoint-patch rays by the map's own 3D points: the loss adds
    # depth_loss_mult x the mean, over pool rays of 3D-linked keypoints and over both
    # levels, of the ray's weight outside +-depth_loss_margin (relative) around the
    # keypoint's point depth (model.depth_loss). The localizer renders patches inside that
    # window only (LocalizeConfig.depth_guided, depth_margin 0.2), so the field must put
    # their surface there. 0: colour loss only (the paper).
    depth_loss_mult: float = 0.0
    depth_loss_margin: float = 0.2
    # Window colour loss: the same patch rays (those with a point depth) rendered as the
    # localizer renders them, only inside +-depth_loss_margin around the keypoint's point
    # depth (model.render_rays_narrow: window_samples evenly spaced, then window_fine drawn
    # from their weights), and window_loss_mult x their colour MSE added to the loss. The
    # colour loss over the whole ray trains a render the localizer never makes; this one
    # trains the render it makes (what lies outside the window is the background there).
    # 0: off. The sample counts mirror LocalizeConfig's narrow_samples / narrow_fine.
    window_loss_mult: float = 0.0
    window_samples: int = 32
    window_fine: int = 8
    cluster_overlap: float = 0.2  # image also joins cluster b if |x-c_b| <= 1.2 |x-c_own|
    # How the reference cameras are divided (nerf/clusters.py): "kmeans" (K-means++ on the
    # camera centres, the paper's) or "grid" (a uniform grid of n_clusters equal cells over
    # the cameras' bounding box: the baseline benchmarks/clusters.py compares with).
    cluster_method: str = "kmeans"

    # --- loop / rendering
    render_chunk: int = 4096  # rays per jitted chunk when rendering full views
    log_every: int = 50  # steps between host reads of the loss (and the divergence check)
    eval_every: int = 500  # steps between held-out PSNR estimates
    eval_rays: int = 4096  # held-out pixels used for those estimates (fixed subset)
    checkpoint_every: int = 1000  # steps between orbax checkpoints
    keep_checkpoints: int = 2
    seed: int = 0

    # Fields added since maps were first written, with the value an earlier map meant
    # (configio.from_dict completes a file that lacks them).
    ADDED_FIELDS: ClassVar[dict[str, Any]] = {"contraction": False, "depth_loss_mult": 0.0,
                                            "depth_loss_margin": 0.2, "window_loss_mult": 0.0,
                                            "window_samples": 32, "window_fine": 8}

    @property
    def num_levels(self) -> int:
        """Coarse + fine (a config with no fine samples renders one level)."""
        return 2 if self.num_samples_fine > 0 else 1

    def __post_init__(self):
        if self.encoding not in ENCODINGS:
            raise VrsError(f"unknown NeRF encoding {self.encoding!r}; choose from "
                           f"{', '.join(ENCODINGS)}")
        if self.cluster_method not in CLUSTER_METHODS:
            raise VrsError(f"unknown cluster method {self.cluster_method!r}; choose from "
                           f"{', '.join(CLUSTER_METHODS)}")
        self._check_numbers()

    def _check_numbers(self) -> None:
        """Every numeric field in its valid range (``--set batch_size=0``, ``lr_init=nan``,
        ``hash_log2_table=40`` and a hand-edited map.json fail here, in one line, instead of
        as a ZeroDivisionError, a shape error or a map that silently never trains)."""

        def bad(key: str, want: str) -> VrsError:
            return VrsError(f"NeRF config field {key} = {getattr(self, key)!r}: must be {want}")

        for key, lo in _INT_AT_LEAST.items():
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise bad(key, f"an integer >= {lo}")
        if not 1 <= self.hash_log2_table <= _MAX_LOG2_TABLE:
            raise bad("hash_log2_table", f"an integer in 1..{_MAX_LOG2_TABLE} (2^T entries "
                                         "per level; Instant-NGP uses 14-24)")
        if self.hash_max_res < self.hash_base_res:
            raise bad("hash_max_res", f">= hash_base_res ({self.hash_base_res})")
        if self.max_deg_point < self.min_deg_point:
            raise bad("max_deg_point", f">= min_deg_point ({self.min_deg_point})")
        for key, (lo, hi, lo_open, hi_open) in _FLOAT_RANGES.items():
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v < lo or (lo_open and v == lo) or v > hi or (hi_open and v == hi):
                if hi == _INF and lo == -_INF:
                    want = "a finite number"
                elif hi == _INF:
                    want = f"a finite number {'>' if lo_open else '>='} {lo:g}"
                else:
                    want = (f"a number in {'(' if lo_open else '['}{lo:g}, {hi:g}"
                            f"{')' if hi_open else ']'}")
                raise bad(key, want)
        pct = self.near_far_percentiles
        if (not isinstance(pct, tuple) or len(pct) != 2
                or not all(isinstance(p, (int, float)) and math.isfinite(p) for p in pct)
                or not 0 <= pct[0] < pct[1] <= 100):
            raise bad("near_far_percentiles", "two percentiles LOW,HIGH with 0 <= LOW < HIGH "
                                              "<= 100")

    def to_dict(self) -> dict[str, Any]:
        return configio.to_dict(self)

    @staticmethod
    def from_dict(d: dict[str, Any], where=None) -> NerfConfig:
        """Exact inverse of :meth:`to_dict`; VrsError naming ``where`` on any mismatch."""
        return configio.from_dict(NerfConfig, d, where)


PAPER = NerfConfig(name="paper")

# cpu-small: tuned on lego 200x200 with short runs on 2 shared CPU cores (held-out PSNR,
# every 8th view; the measurements are listed in the README's NeRF section). In short:
# the learning rate mattered most (1000 steps of a 64x3 net: lr 2e-3 -> 20.0 dB, 2e-2 ->
# 22.2 dB), then small batches (same compute: 1024 -> 21.9, 512 -> 22.8, 256 -> 23.2 dB,
# 128 worse again), then width for longer runs (same wall time: 64x3 for 8000 steps 23.9 dB,
# 128x3 for 4000 steps 23.9 dB and still rising; 128-wide matrix products also use both
# cores better). Depth 4, 24+40 samples, or dropping view directions did not help.
# The field is then a hash grid, not IPE: the localizer renders small keypoint patches, and
# their descriptors matter, not PSNR. On dtu_scan24 (3000 steps, 6 reference views,
# benchmarks.fidelity) a rendered patch's nearest real descriptor is its own keypoint's
# 55.0% of the time with a 2 x 64 MLP after a 16-level 2^14 hash grid against 36.2% with the
# IPE 3 x 128 MLP (patch PSNR 17.0 vs 18.4 dB: the grid renders sharper gradients, slightly
# misplaced), and localization improves (benchmarks.localize, render mode, both fields with
# the same 16 + 8 samples and guided pass: dtu_scan24 first-pass inliers 65 vs 34, median
# 0.05 vs 0.12 cm; lego 69% vs 62% within 2 cm / 2 deg). It costs 1.09 MB float16 instead
# of 0.14 MB, and trained at 10.5 instead of 24 steps/s (on a shared, loaded machine).
CPU_SMALL = dataclasses.replace(
    PAPER,
    name="cpu-small",
    encoding="hashgrid",  # 16 levels x 2^15 entries x 2 features
    # 2^15 entries per level: with the tables stored as int8 (maps.map.NERF_HASH_INT8) the
    # field takes the bytes the 2^14 float16 one took (1.09 MB). Trained and localized with
    # three RANSAC seeds against 2^14 (README, "The saved bytes spent on a table twice as
    # large"): the phone walk 49.5 -> 58.1% within 1% of the scale (mean of the seeds), its
    # held-out leg 16.7 -> 25.3%, lego 61.5 -> 69.2%, fox, scan24 and fern unchanged; 2^16
    # (2.1 MB) gained no more on the walk. Training takes ~1.2x as long.
    hash_log2_table=15,
    net_depth=2,  # 2 x 64 after the grid (Instant-NGP's small MLP); the IPE field was 3 x 128
    net_width=64,
    skip_layer=0,  # no skip: a 2-layer trunk doesn't need one
    net_width_condition=64,
    max_deg_point=10,  # IPE only (unused by the grid): 200-500 px footprints blank out > ~9
    deg_view=2,  # lego/fern are nearly Lambertian; 2 degrees suffice
    num_samples_coarse=32,  # 32 + 32: samples are the main cost; 24 + 40 was no better
    num_samples_fine=32,
    batch_size=256,  # more, noisier steps beat fewer exact ones at equal compute
    lr_init=2e-2,  # small nets trained briefly: 10x the paper's lr (4e-2 is no better)
    lr_final=2e-3,  # decaying only 10x: 2e-2 -> 5e-4 lost 0.2 dB in short runs
    lr_delay_steps=100,  # short warm-up at 0.1x: no early collapse to empty space
    lr_delay_mult=0.1,
    max_steps=4_000,  # 3 minutes on 2 idle CPU cores (23.6 steps/s on the synthetic room);
    # a step budget, not a wall-clock one, so that a map does not depend on machine load
    eval_every=500,
    checkpoint_every=1000,
    # The depth loss (weight outside +-20% of the keypoint's point depth; NerfConfig above).
    # Without it the phone walk's field rendered the surface inside that window for 22% of
    # the keypoints (benchmarks.fidelity), so the localizer's depth-guided rendering sampled
    # empty space; with 0.02, 84%, and the walk's render recall within 1% / 2% of the scale
    # went from 29.0 / 45.2% to 51.6 / 61.3% (31 queries) while fox and scan24 stayed at
    # 100 / 100% (README); 0.1 gave 38.7 / 51.6% on the walk.
    depth_loss_mult=0.02,
)

# test: the smallest field whose rendered patches still localize the tests' 160x120 synthetic
# room (measured: 3x64 for 800 steps -> 8/8 queries within 5 cm in render mode, median 1.4 cm;
# 2x32 for 300 steps -> 0/8; the rate alone, 2x32 at lr 2e-2 for 600 steps -> 0/8).
TEST = dataclasses.replace(
    PAPER,
    name="test",
    net_depth=3,
    net_width=64,
    skip_layer=0,
    net_depth_condition=1,
    net_width_condition=32,
    max_deg_point=8,
    deg_view=2,
    num_samples_coarse=16,
    num_samples_fine=16,
    batch_size=256,
    lr_init=2e-2,  # as cpu-small: small nets trained briefly want a high rate
    lr_final=2e-3,
    lr_delay_steps=20,
    lr_delay_mult=0.1,
    max_steps=800,
    render_chunk=1024,
    eval_every=50,
    eval_rays=512,
    checkpoint_every=50,
)

CONFIGS: dict[str, NerfConfig] = {c.name: c for c in (PAPER, CPU_SMALL, TEST)}


def get_config(name: str, **overrides: Any) -> NerfConfig:
    """The named config, with field overrides (``get_config("cpu-small", n_clusters=4)``)."""
    if name not in CONFIGS:
        raise VrsError(f"unknown NeRF config {name!r}; choose from {', '.join(CONFIGS)}")
    cfg = CONFIGS[name]
    if overrides:
        configio.check_fields(NerfConfig, sorted(overrides), "NeRF config field")
        cfg = dataclasses.replace(cfg, **overrides)
    return cfg


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """CLI ``--set key=value`` pairs -> typed overrides (types from NerfConfig's fields)."""
    out: dict[str, Any] = {}
    defaults = NerfConfig()
    for item in items or []:
        if "=" not in item:
            raise VrsError(f"--set expects key=value, got {item!r}")
        key, val = item.split("=", 1)
        key = key.strip().replace("-", "_")
        if key == "name":
            raise VrsError("--set name=... is not a setting: choose the named config with "
                           "--config")
        configio.check_fields(NerfConfig, [key], "NeRF config field")
        cur = getattr(defaults, key)
        try:
            if isinstance(cur, bool):
                if val.lower() not in ("1", "0", "true", "false", "yes", "no"):
                    raise ValueError(val)
                out[key] = val.lower() in ("1", "true", "yes")
            elif isinstance(cur, int):
                out[key] = int(val)
            elif isinstance(cur, float):
                out[key] = float(val)
            elif isinstance(cur, tuple):
                out[key] = tuple(float(v) for v in val.split(","))
                if len(out[key]) != len(cur):
                    raise ValueError(val)
            else:
                out[key] = val
        except ValueError:
            raise VrsError(f"bad value for {key}: {val!r}") from None
    return out
