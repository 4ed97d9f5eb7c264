"""Query-time settings: one frozen dataclass (hashable, so a static jit argument).

Only what may change between queries of one map lives here: where the reference descriptors
come from, retrieval, matching, patch rendering samples and PnP. The keypoint detector, the
patch geometry and the descriptor are the map's (``map.config.features``): query descriptors
are compared with descriptors of the map keypoints' patches, so they must be computed alike.
The authors released no code, so every value here except the patch size (15, the paper's) is
ours; each carries its reason.
"""

from __future__ import annotations

import dataclasses

from vrs_jax import configio
from vrs_jax.errors import VrsError
from vrs_jax.features.patches import PatchConfig
from vrs_jax.localize.confidence import VERDICTS, ConfidenceConfig
from vrs_jax.localize.pnp import PnPConfig

# "render": describe NeRF-rendered patches of the reference keypoints (VRS-NeRF);
# "real": match against the map's stored descriptors of the real reference patches (the
# hierarchical-method baseline, the paper's "GT" row). "gt" is accepted for "real".
SOURCES = ("render", "real")
ALIASES = {"gt": "real"}


@dataclasses.dataclass(frozen=True)
class TrackConfig:
    """Tracking a stream (``Localizer.track``, :mod:`vrs_jax.localize.track`): a frame with
    a pose prior (constant velocity from the last good poses) skips retrieval and the first
    pass and runs one tracking pass, the guided pass started from the predicted pose, then
    the config's own guided passes; it keeps the tracked pose only if all the tests below
    pass, else it is localized in full."""

    # Reference images whose map points the tracking pass renders and matches: the k images
    # with the most map points in view of the predicted camera (projected inside the image,
    # in front, seen from the reference within max_ray_angle_deg of the predicted ray). 0:
    # the config's top_k, as many as retrieval hands the first pass.
    top_k: int = 0
    # A reference's map point counts as in view only if its ray from the reference and the
    # ray from the predicted camera meet at it within this angle: SIFT-like descriptors (and
    # the keypoint frame transferred to the predicted view) hold up to ~45 deg of viewpoint
    # change, beyond which a point seen from that reference is rarely matched.
    max_ray_angle_deg: float = 45.0
    # Search radius (pixels) of the tracking pass around the map points projected with the
    # predicted pose: the constant-velocity prediction of a smooth stream is off by a few
    # pixels, more where the motion changes. The radius also sets what the pass renders (the
    # points with a query keypoint that close), so the smallest that tracks: on the
    # synthetic stream at 160x120 (4.7 cm and 3.5 deg between frames, test map) 8 px and
    # 12 px both track 19 of 20 frames (benchmarks.track --track radius_px=12); the full
    # guided pass uses 8 px for a first pose a few pixels off as well.
    radius_px: float = 8.0
    # Inlier threshold (pixels) of the tracking pass's refinement; None: the PnP config's
    # (the RANSAC seed's 6 px), since the pass starts from a prediction, not a refined pose.
    # The re-matching passes then tighten it (guided_threshold_px).
    threshold_px: float | None = None
    # Guided passes from the tracked pose on the patches the tracking pass rendered (they
    # were rendered a few pixels from there; nothing is rendered again), matched within the
    # config's guided_radius and refined with its guided_threshold_px: the tight gates of a
    # guided pass for the cost of matching and refinement (milliseconds). A second
    # rendering pass would cost as much as the tracking pass again (the guided pass is the
    # largest stage: README), so the config's own guided_passes are not run.
    refine_passes: int = 1
    # A tracked pose with fewer inliers is relocalized in full: the map seen from the right
    # pose matches many points near their projections, a wrong prediction few; 20 is above
    # PnP's 12 (a chance pose's inliers) with a margin.
    min_inliers: int = 20
    # A tracked pose is kept only if the references its pass used (those nearest the
    # predicted pose) share at least this many images with the frame's top_k retrieved by
    # its global descriptor, the one piece of evidence that does not come from the
    # prediction: the tracking pass matches near the projections of the predicted pose, so
    # a wrong prediction can gather 30-40 inliers of its own (fox in capture order, 52-181%
    # of the scale off). 0: not checked. `cpu-small` asks for 2 (its comment).
    min_retrieval_overlap: int = 1
    # A tracked pose farther from its prediction than this fraction of the scene scale, or
    # turned more than max_jump_deg from it, is relocalized: the search radius lets the pose
    # move only as far as the projections move within radius_px, so a larger jump came from
    # matches the radius should not have allowed (a wrong convergence). A relocalized pose
    # that far from the prediction also re-anchors the motion prior (the stream jumped).
    max_jump: float = 0.1
    max_jump_deg: float = 10.0
    # A tracked pose is kept only if the check pass (the frame matched to the tracking
    # pass's candidates without the prediction, then RANSAC and refinement:
    # track.check_pass) finds a pose within this fraction of the scene scale and this angle
    # of it: inliers gathered near the predicted projections can agree with a wrong
    # prediction, matches made anywhere in the image do not. 2% / 2 deg is the benchmarks'
    # outer recall threshold. 0: not checked.
    max_disagreement: float = 0.02
    max_disagreement_deg: float = 2.0
    # When the tracked pose is rejected, keep the check pass's pose instead if it passes the
    # tests a tracked pose passes on its own (a "localized" verdict, min_inliers, the
    # retrieval overlap; not the jump: the check pass does not start from the prediction),
    # before localizing the frame in full: it is a first pass plus re-matching on the
    # references nearest the prediction, for the patches already rendered.
    keep_check: bool = True
    # Also keep a check pass's pose whose verdict is "uncertain" (reported uncertain, not
    # localized) instead of localizing the frame in full, whose pose on the same frames is
    # mostly uncertain too; and do not ask the check pass's pose for min_retrieval_overlap,
    # a test that guards the tracking pass's pose (its inliers gather near the prediction)
    # while the check pass matches without it. Both were off before; on the phone walk's
    # held-out leg in render mode (50 frames in order, benchmarks.track, README "Tracking
    # keeps the check pass's pose") the tracking pass's own pose was 10-80% of the scale off
    # on 24 of 42 attempts (the frames are 2-17% of the scale and up to 37 deg apart, so the
    # constant-velocity prediction misses by more than the search radius) while the check
    # pass's was within 1-5% on most of them, yet only 5 frames were kept.
    keep_uncertain_check: bool = True
    check_needs_overlap: bool = False
    # Run the guided pass (the config's, as full localization does after its first pass) from
    # the check pass's pose: map points rendered there and matched near their projections.
    # On the walk's held-out leg rebuilt with the whitened retrieval (render mode, README
    # "Re-run on the leg's map rebuilt") tracking went from 8% / 20% to 12% / 26% within
    # 1% / 2% (full localization 20% / 36%), on fox from 90% / 90% to 90% / 100%; a tracked
    # frame there 0.199 -> 0.219 s (one run each). A similar pass tried on the earlier leg
    # map (leg_new) had gained nothing. It renders anew the points the tracking pass
    # rendered near the prediction (no reuse of the check pass's inliers yet).
    check_guided: bool = True
    # Map points the tracking pass renders (render mode; the longest tracks near a query
    # keypoint, as the guided pass's guided_keypoints): the check pass matches the frame to
    # these only, so more than a guided pass (started from a refined pose) needs. 0: the
    # config's guided_keypoints (cpu-small sets 160: its comment).
    keypoints: int = 0
    # Frames since the last good pose beyond which a frame is localized in full instead of
    # predicted: constant velocity extrapolates its error with the gap; after a few lost
    # frames a full pass is cheaper than a failed tracking step plus a full pass.
    max_gap: int = 3
    # Verdicts of a pose that may seed the motion prior. "uncertain" too: the confidence
    # still calls some right poses uncertain (on real photographs it is calibrated in
    # real-patch mode only: README), and a wrong seed only costs one tracking step, whose
    # own acceptance (a "localized" verdict, inliers, jump) then fails and relocalizes the
    # frame.
    prior_verdicts: tuple[str, ...] = ("localized", "uncertain")
    # Render mode: the frames localized in full keep their references' rendered first-pass
    # descriptors in a cache of this many MB for the rest of the stream (Localizer.track
    # makes one when its Localizer has none; localize.cache): a reference is rendered from
    # its own camera, so a later frame that retrieves it again renders nothing for it. 0:
    # none. cpu-small sets 64 (its comment).
    cache_mb: float = 0.0
    # Render mode: the tracking and check passes match the frame to the step's references'
    # first-pass descriptors rendered from their own cameras (query-independent: kept in the
    # stream's cache, so a reference is rendered once per stream) instead of to their map
    # points rendered at the predicted pose; the check pose's guided pass (check_guided)
    # still renders at that pose. Where the prediction misses by more than the search
    # radius (the walk's held-out leg: frames 2-17% of the scale apart) the check pass is
    # then the first pass of a full localization on those references. cpu-small: on (its
    # comment).
    reference_views: bool = False
    # The frame pass: when the previous frame's verdict was "localized" (and it was not
    # relocalized: a pose the stream's tracking did not confirm), the frame is first
    # matched to that frame's keypoints that sat on map points (each keypoint paired with
    # the map point projected nearest it at that frame's pose, within associate_px, mutual
    # nearest), its pose solved from those points (RANSAC and refinement, no prediction)
    # and the guided pass rendered at that pose (kept with as many inliers), as a SLAM
    # tracker follows the last frame's map points: nothing is rendered from the references'
    # cameras. Kept when its verdict is "localized" (and min_inliers) and the guided pass's
    # own pose lies within frame_disagreement of the scene scale and frame_disagreement_deg
    # of the frame pass's (the frame pass inherits its anchor's error; the map rendered at
    # its pose does not); else the tracking step above runs as without it. cpu-small: on.
    # Render mode, benchmarks.track on 4c0efca and 535beb8 (README "Tracking against the
    # previous frame"): the walk's held-out leg 20 / 34% within 1% / 2% at 0.220 and 0.308 s
    # per frame (full localization in the same runs 20 / 36% at 0.779 and 0.751 s; without
    # it, on 23df8bb, 22 / 30% at 0.368 s), no wrong pose localized, the jump tracked after
    # 1 frame and right after 2; fox 100% at 0.146 and 0.231 s (full 0.199 and 0.307 s;
    # without it 0.447 s). Variants (one run each):
    # anchoring on "uncertain" frames too, 20 / 36% at 0.238-0.274 s with 1 wrong pose
    # localized (5.1% off); keeping uncertain frame-pass poses as well, 10 / 18% with 6.
    frame_pass: bool = False
    associate_px: float = 2.0
    frame_disagreement: float = 0.05
    frame_disagreement_deg: float = 5.0

    def __post_init__(self):
        if not (isinstance(self.cache_mb, (int, float)) and 0 <= self.cache_mb < float("inf")):
            raise VrsError(f"TrackConfig.cache_mb must be a finite number >= 0, got "
                           f"{self.cache_mb!r}")
        if (self.top_k < 0 or self.min_inliers < 1 or self.max_gap < 1 or self.keypoints < 0
                or self.refine_passes < 0 or self.min_retrieval_overlap < 0):
            raise VrsError("TrackConfig.top_k and keypoints must be >= 0, min_inliers >= 1, "
                           "max_gap >= 1, refine_passes >= 0, min_retrieval_overlap >= 0")
        if self.max_disagreement < 0 or self.max_disagreement_deg <= 0:
            raise VrsError("TrackConfig.max_disagreement must be >= 0 (0: not checked) and "
                           "max_disagreement_deg > 0")
        if not (self.radius_px > 0 and self.max_jump > 0 and self.max_jump_deg > 0
                and 0 < self.max_ray_angle_deg <= 180):
            raise VrsError("TrackConfig.radius_px, max_jump and max_jump_deg must be > 0, "
                           "max_ray_angle_deg in (0, 180]")
        if self.threshold_px is not None and self.threshold_px <= 0:
            raise VrsError("TrackConfig.threshold_px must be > 0 (or None)")
        if not self.associate_px > 0:
            raise VrsError(f"TrackConfig.associate_px must be > 0, got {self.associate_px!r}")
        bad = set(self.prior_verdicts) - set(VERDICTS[:2])
        if bad:
            raise VrsError(f"TrackConfig.prior_verdicts must be among {VERDICTS[:2]}, got "
                           f"{sorted(bad)}")


@dataclasses.dataclass(frozen=True)
class LocalizeConfig:
    """Everything ``localize`` needs besides the map and the query."""

    source: str = "render"
    # Retrieved reference images per query. The paper (like hloc on 7Scenes) uses a handful;
    # each one costs K_max * P^2 rendered rays, so 5 balances recall and render time.
    top_k: int = 5
    # Retrieval ranks skipped: the references used are those ranked retrieval_offset ..
    # retrieval_offset + top_k - 1 by global descriptor (fewer where the map has fewer). A
    # retry (below) sets it; 0 otherwise.
    retrieval_offset: int = 0
    # A query whose pose is not "localized" (localize.confidence: uncertain, or failed) is
    # localized again with the next top_k references by global descriptor, up to this many
    # times while the map has references left; the result with the highest confidence is
    # kept (localize.retry; hloc tries its retrieved images' covisibility clusters in turn).
    # 0: one attempt (cpu-small retries once; measured there).
    retries: int = 0
    # Query keypoints kept (by SIFT response), padded to this static count (the detector's
    # other settings are the map's).
    query_keypoints: int = 1024
    # Render mode only: patches rendered (and query patches read) with another geometry than
    # the map's, e.g. the patch-size ablation; None uses the map's.
    patches: PatchConfig | None = None
    # Lowe ratio for query-to-reference matching. Rendered patches are slightly blurrier than
    # real ones, so distances are larger overall; 0.9 with the mutual check keeps enough
    # matches while RANSAC removes the rest (measured on the synthetic scene).
    ratio: float = 0.9
    mutual: bool = True
    # Depth-guided rendering: sample each patch ray only within +-depth_margin (relative)
    # around its keypoint's 3D point depth: narrow_samples evenly spaced samples, then
    # narrow_fine resampled from their weights inside the interval (0: one pass), instead of
    # the full ray's coarse + fine. The margin covers the depth change across a patch on
    # oblique surfaces.
    depth_guided: bool = True
    depth_margin: float = 0.2
    narrow_samples: int = 24
    narrow_fine: int = 0
    # Probes (depth-guided only): the first, evenly spaced pass above runs on probe_grid x
    # probe_grid rays spread over each patch (both ends of every row and column of the patch
    # grid: its corners for 2), and every rendered ray draws its narrow_fine
    # samples from their weights interpolated over the patch (needs narrow_fine >= 1). A
    # patch then costs probe_grid^2 x narrow_samples + rays x narrow_fine evaluations
    # instead of rays x (narrow_samples + narrow_fine). 0: off (every ray its own passes).
    probe_grid: int = 0
    # Render mode: keypoints per retrieved image that the first pass renders and matches,
    # those of the longest tracks first (render.first_pass_keypoints); 0: every one.
    first_pass_keypoints: int = 0
    # With a first-pass budget: spread it over a first_pass_spread_grid x
    # first_pass_spread_grid grid over each reference's keypoints (every cell's longest track
    # first, then every cell's second, ...: render.spread_tracks); 0: the longest tracks
    # wherever they are.
    first_pass_spread_grid: int = 0
    # Render mode: a candidate's first-pass keypoint whose 3D point an earlier candidate
    # already renders is not rendered again (nor matched: each point once a pass, as the
    # guided pass renders it). False: every candidate its own selection.
    first_pass_unique_points: bool = False
    # Guided passes (render where the query is): after a successful pose, the retrieved
    # images' map points are projected with it and each query keypoint is matched only to
    # points predicted within guided_radius pixels (mutual nearest neighbour, ratio test
    # against other points), then the pose is refined on those matches and kept only if it
    # has at least as many inliers. Render mode describes the points' patches rendered FROM
    # THE ESTIMATED POSE (their keypoint frames moved there) when guided_render, else the
    # first pass's; real mode its stored descriptors. 0 passes: off. 8 px covers a first
    # pose a few pixels off; the ratio is the first pass's.
    guided_passes: int = 0
    # The sources that make the guided passes (a fair comparison runs both; a default keeps
    # them where they measurably help).
    guided_sources: tuple[str, ...] = ("render", "real")
    guided_radius: float = 8.0
    guided_ratio: float = 0.9
    # Inlier threshold (pixels) of the guided pass's refinement; None: the PnP config's
    # (the RANSAC seed's). The guided pass starts from a pose, not from random samples, so it
    # can gate its matches tighter than the seed.
    guided_threshold_px: float | None = None
    guided_render: bool = True
    # Re-matching passes after the guided passes: the last guided pass's descriptors matched
    # again from its refined pose within guided_radius and refined (kept if no fewer
    # inliers), rendering nothing (stages.guided_rematch, as tracking's refine_passes).
    guided_rematch_passes: int = 0
    # Render mode: the map points that are inliers of the first pass's pose keep the
    # descriptor of their first-pass patch (rendered from the reference that matched) in the
    # guided pass instead of being rendered again from the pose; the pass renders only the
    # points the first pass did not place. False: every candidate point rendered again.
    guided_reuse_inliers: bool = False
    # Render mode: map points the guided pass renders at most (of those it would render),
    # the longest tracks first; 0: no limit.
    guided_keypoints: int = 0
    # With a guided budget: spread it over a guided_spread_grid x guided_spread_grid grid
    # over the query keypoints' box (the points' projections at the pose): every cell's
    # longest track first, then every cell's second, ... (render.spread_tracks); 0: the
    # longest tracks wherever they are.
    guided_spread_grid: int = 0
    # Early exit over the retrieved list (render mode): the candidates are rendered best
    # first, and after each one the correspondences so far go to RANSAC; once its seed has
    # early_exit_inliers distinct inliers, the remaining candidates are not rendered. 0: all
    # top_k are rendered.
    early_exit_inliers: int = 0
    # Render render_grid x render_grid rays spread evenly over each patch (both ends of every
    # row and column included) and interpolate the P x P samples from them bilinearly; the
    # rays keep the full grid's cone radius, so the render carries the real patch's
    # anti-aliasing blur. 0: every sample (P per side); otherwise 2..P, canonical patches.
    render_grid: int = 0
    # Rays rendered per jitted chunk (bounds memory: chunk x samples x MLP width floats).
    render_chunk: int = 8192
    # Cells per side of the grid over the query keypoints' bounding box on which
    # LocalizeResult.inlier_coverage counts the cells holding inliers (a diagnostic only).
    coverage_grid: int = 8
    pnp: PnPConfig = PnPConfig()
    # Thresholds of the confidence and verdict of each result (localized / uncertain /
    # failed), computed after the jitted pipeline from its outputs (localize.confidence;
    # measured there). No pose depends on them.
    confidence: ConfidenceConfig = ConfidenceConfig()
    # Tracking a stream with a motion prior (Localizer.track; see TrackConfig).
    track: TrackConfig = TrackConfig()

    def __post_init__(self):
        src = ALIASES.get(self.source, self.source)
        if src not in SOURCES:
            raise VrsError(f"localize source must be one of {SOURCES}, got {self.source!r}")
        object.__setattr__(self, "source", src)
        if self.top_k < 1:
            raise VrsError("LocalizeConfig.top_k must be >= 1")
        if self.retrieval_offset < 0 or self.retries < 0:
            raise VrsError("LocalizeConfig.retrieval_offset and retries must be >= 0")
        if self.narrow_samples < 1 or self.narrow_fine < 0:
            raise VrsError("LocalizeConfig.narrow_samples must be >= 1 and narrow_fine >= 0")
        if not set(self.guided_sources) <= set(SOURCES):
            raise VrsError(f"LocalizeConfig.guided_sources must be among {SOURCES}")
        if self.guided_passes < 0 or self.guided_radius <= 0 or self.guided_rematch_passes < 0:
            raise VrsError("LocalizeConfig.guided_passes and guided_rematch_passes must be >= 0 "
                           "and guided_radius > 0")
        if self.guided_threshold_px is not None and self.guided_threshold_px <= 0:
            raise VrsError("LocalizeConfig.guided_threshold_px must be > 0 (or None)")
        if self.probe_grid < 0 or self.probe_grid == 1:
            raise VrsError("LocalizeConfig.probe_grid must be 0 (off) or >= 2")
        if self.render_grid < 0 or self.render_grid == 1:
            raise VrsError("LocalizeConfig.render_grid must be 0 (every sample) or >= 2")
        if self.first_pass_keypoints < 0 or self.guided_keypoints < 0:
            raise VrsError("LocalizeConfig.first_pass_keypoints and guided_keypoints must be "
                           ">= 0 (0: all)")
        if self.guided_spread_grid < 0 or self.first_pass_spread_grid < 0:
            raise VrsError("LocalizeConfig.guided_spread_grid and first_pass_spread_grid must "
                           "be >= 0 (0: off)")
        if self.early_exit_inliers < 0:
            raise VrsError("LocalizeConfig.early_exit_inliers must be >= 0 (0: off)")
        if self.coverage_grid < 1:
            raise VrsError("LocalizeConfig.coverage_grid must be >= 1")
        if self.query_keypoints < 1:
            raise VrsError("LocalizeConfig.query_keypoints must be >= 1")
        if self.source == "real" and self.patches is not None:
            raise VrsError("real-patch mode uses the patches stored in the map; a patch "
                           "override applies to render mode only")


CONFIGS: dict[str, LocalizeConfig] = {
    # The paper's setting on a GPU: top-5 retrieval, 2048 query keypoints, every patch ray
    # rendered with the map's full coarse + fine sampling (depth_guided False); no guided
    # pass (the paper has none, and it has not been measured at this scale).
    "paper": LocalizeConfig(top_k=5, query_keypoints=2048, depth_guided=False),
    # Two CPU cores: top-5 retrieval (as the paper), 1024 query keypoints, depth-guided
    # sampling of every second patch sample (render_grid 8: 64 rays per 15 x 15 patch, the
    # rest interpolated; measured on dtu_scan24 with 16 + 8 samples: 55.4% own-keypoint rate
    # against 55.0% with every sample). Each patch's 4 corner rays (probe_grid 2) take 32 samples
    # around the keypoint's 3D point and every ray resamples 8 from their weights: 640 NeRF
    # evaluations per patch instead of 64 x (32 + 16) = 3072. benchmarks.fidelity --views 6
    # (own-keypoint rate, same maps): scan24 67.4% against 71.4% (16 resampled: 72.2% at
    # 1152), fern 68.0% against 71.4%, the synthetic room 95.7% against 97.9%; 3 x 3 probes
    # gain nothing (scan24 66.3%); 16 probe samples (576) kept lego's and the walk's rate and
    # recall on the six scenes but cost scan24 4.5 points (49.6% against 54.1%, 54 correct
    # matches per view against 64; README, "Each map point rendered once"). The first pass
    # renders each candidate's 256 keypoints of the longest tracks, best candidate first,
    # less those whose 3D point an earlier candidate renders (first_pass_unique_points: on
    # the walk 48-65% of the 2nd-5th candidates' points were the 1st's), and stops once
    # RANSAC has 24 inliers (benchmarks.localize on the six scenes, the same maps, README
    # "Each map point rendered once": the walk's mean NeRF evaluations per query 226 k ->
    # 181 k; recall the same on the synthetic room, fox, scan24 and fern, lego one query
    # more and the walk one fewer within 1%). One
    # guided pass then renders from the first pose at most 96 map points near a query
    # keypoint (the longest tracks; the first pass's inliers keep their descriptors instead
    # of being rendered again), matched within 4 px of their projections and refined with a
    # 2 px inlier threshold (the seed's RANSAC keeps 6 px). 96 and 24 instead of 192 and 30
    # (benchmarks.localize --modes render,real on fox, scan24, fern, lego and the walk
    # together, 1024-keypoint maps): recall at 1% / 1 deg and 2% / 2 deg the same on fox,
    # scan24 and fern, lego 1 query more within 1%, the walk 1 fewer within 1% and 1 more
    # within 2% (2 poses more than 5% off instead of 5, none reported localized instead of
    # 1); 143-218 k NeRF evaluations per query instead of 179-285 k, render / real time per
    # query with preparation 3.1-3.5x instead of 3.7-4.3x (lego 5.4x instead of 6.4x; README,
    # "Render budget"). 256 first-pass keypoints instead of 128, which is every keypoint a
    # cpu-small map links per image (K_max 256 on all six benchmark maps; a map with more
    # keeps the budget; the median query still renders one candidate, 256 x 640 + 96 x 640
    # evaluations, before the early exit; benchmarks.localize
    # --modes render,real on the six scenes' maps rebuilt on 1c04ac5, with the retry below;
    # README "256 first-pass keypoints"): render mode's recall on the walk 64.5 / 74.2% ->
    # 80.6 / 83.9% within 1% / 2% (median 0.38% -> 0.21%), no wrong pose reported
    # localized instead of 1, right poses flagged 3 of 65 -> 1 of 66 on the real scenes, no
    # scene loses a query (fern and lego the same, scan24's median 0.20% -> 0.22%); mean NeRF
    # evaluations per query 141-145 k -> 205-224 k on the synthetic room, fox, scan24 and
    # fern, the walk 216 k -> 314 k; render / real time with preparation 2.5-3.8x (scan24
    # 3.8x) against 2.3-3.4x. (Without the retry, on fern, lego and the walk: 192 keypoints
    # gave the walk 71.0 / 77.4%, 256 77.4 / 80.6%; every keypoint without
    # first_pass_unique_points 74.2 / 80.6% at 320 k.) Earlier, 128 was kept over 96, which
    # (with the 96-point guided budget) lost the walk 3 more queries within 1%. The earlier
    # setting (192, 30; 48 samples before that), measured with benchmarks.localize
    # on the synthetic room, fern, lego, scan24 and fox together against the previous
    # setting (48 samples on every ray, every keypoint, an unbounded guided pass: 0.9-2.1 M
    # evaluations per query): 0.18-0.30 M evaluations, recall at 1% / 1 deg 35 of 37 real
    # queries against 33, at 2% / 2 deg 37 against 36; medians equal but on scan24 (0.28% of
    # the scale against 0.19%) and fern (0.66% against 0.59%): the guided budget costs
    # inliers there (README). Real mode makes no guided pass: the same pass with its stored
    # descriptors gained on fern and scan24 and lost on lego (61.5% instead of 69.2% within
    # 2 cm), as the IPE-era 8 px pass did. Chunks of 2048 rays. Tracking keeps a pose only if
    # 2 of the references nearest it are among the frame's top-5 retrieval: with 1, every
    # tracked pose kept on our real streams was wrong (fox in capture order: 1 of 1, 68% of the
    # scale off; the walk's held-out leg: 2 of 2 in each mode); with 2 none is kept there
    # (benchmarks.track on the depth-loss maps), so those frames are localized in full; the
    # check pass (TrackConfig.max_disagreement) keeps right poses there since (README). The
    # tracking pass renders 160 map points, not the guided pass's 96: the check pass matches
    # the frame to those only (benchmarks.track --mode render --modes track on the walk's
    # held-out leg, 50 frames, README "Tracking keeps the check pass's pose"): 96 points
    # kept 24 frames by tracking, 12.0 / 24.0% within 1% / 2%; 128: 26, 16.0 / 20.0%; 160:
    # 26, 18.0 / 28.0%; 192: 26, 18.0 / 24.0%; 256: 26,
    # 18.0 / 24.0%. A stream keeps the rendered reference descriptors of its full
    # localizations in 64 MB (track.cache_mb; a cpu-small reference's 256 float16
    # descriptors take 64 kB: a thousand references): on the walk's held-out leg (render,
    # benchmarks.track --modes full,cached, README "Tracking on the references' own views")
    # full localization of every frame went from 0.620 to 0.405 s per frame, 20 / 36% to
    # 22 / 34%.
    # The tracking and check passes match the frame to those cached own-view descriptors of
    # the references nearest the prediction (track.reference_views) instead of rendering 160
    # map points at the prediction: on that leg tracking went from 12 / 26% (0.251 s per
    # frame, a84e3c0) to 22 / 30% (0.326 s on 8e22999; full localization 20 / 36% at
    # 0.620 s, with the cache 22 / 34% at 0.405 s), no wrong pose localized; the jump
    # recovered in 2 frames instead of 4; fox's 10 far-apart frames 90 / 100% -> 100 / 100%
    # (0.281 s, full 0.258 s). Without the early exit when rendering a missing reference:
    # leg 24 / 40% at 0.444 s, fox 100% at 0.807 s.
    # A frame after a "localized" one is first matched to that frame's keypoints on map
    # points (track.frame_pass, its comment): the leg 20 / 34% at 0.220-0.308 s per frame
    # (full localization 20 / 36% at 0.779 and 0.751 s in the same two runs, 4c0efca and
    # 535beb8; without it 22 / 30% at 0.368 s on 23df8bb), fox 100% at 0.146-0.231 s (0.447 s
    # without).
    # A query that is not "localized" is retried once with the next 5 references
    # (retries=1; benchmarks.localize on the six scenes' rebuilt maps, README "Retrying a
    # doubtful query"): render mode gains the walk one query within 1% and one within 2%
    # (two uncertain poses, 2.05% and 4.21% off, become localized at 0.75% and 2.11%), right
    # poses flagged on the real scenes 5 -> 3 of 65, no scene loses a query; mean NeRF
    # evaluations per query on the walk 180 k -> 216 k (6 of 31 queries retried), lego 136 k
    # -> 152 k (1 of 13), the others unchanged; real mode retried none. A second retry
    # (retries=2) gained nothing more on lego and the walk (247 k on the walk).
    "cpu-small": LocalizeConfig(top_k=5, query_keypoints=1024, narrow_samples=32,
                                narrow_fine=8, probe_grid=2, first_pass_keypoints=256,
                                first_pass_unique_points=True,
                                guided_passes=1, guided_sources=("render",),
                                guided_radius=4.0, guided_threshold_px=2.0,
                                guided_reuse_inliers=True, guided_keypoints=96,
                                render_grid=8, early_exit_inliers=24, render_chunk=2048,
                                retries=1, track=TrackConfig(min_retrieval_overlap=2,
                                                             keypoints=160, cache_mb=64,
                                                             reference_views=True,
                                                             frame_pass=True)),
    # Unit tests: top-2 retrieval, 256 query keypoints, 8 + 4 depth-guided samples per ray,
    # no guided pass (tests ask for one where they check it).
    "test": LocalizeConfig(top_k=2, query_keypoints=256, narrow_samples=8, narrow_fine=4,
                           render_chunk=4096),
}


def get_config(name: str, **overrides) -> LocalizeConfig:
    """Named LocalizeConfig with optional field overrides; VrsError for an unknown name."""
    if name not in CONFIGS:
        raise VrsError(f"unknown localize config {name!r}; choose from {sorted(CONFIGS)}")
    configio.check_fields(LocalizeConfig, overrides, "localize config field")
    return dataclasses.replace(CONFIGS[name], **overrides)
