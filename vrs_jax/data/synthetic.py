"""The embedded default scene: a ray-cast, procedurally textured indoor room in 7Scenes layout.

The room is an axis-aligned box (walls, floor, ceiling) holding a few boxes rotated about the
vertical axis. Every face carries its own non-repeating procedural texture (multi-octave noise
under random coloured rectangles, triangles, discs, rings and line segments whose sizes span
2 to 40 cm), defined on the face's 2D surface coordinate in metres, so the appearance of a
surface point is exactly the same from every view. Shading is Lambertian from two point
lights (view-independent, so a NeRF can represent it exactly), without shadows. Cameras move
on a smooth loop looking across the room (references) and on an offset path with perturbed
angles (queries).

Images are rendered by vectorised numpy ray casting at ``supersample``-times the resolution with
mip-mapped (trilinear) texture lookups and box-averaged down, so that they look like a camera's
(no aliasing). Depth is the exact z-depth of the ray through each pixel centre, so the
16-bit millimetre depth PNGs agree with the geometry up to the 0.5 mm rounding.

World frame: metres, z up, floor at z = 0, room centred on the origin in x and y. Cameras follow
OpenCV axes (x right, y down, z forward); ``pose.txt`` holds camera-to-world matrices as 7Scenes
does. Pixel convention is COLMAP's: the centre of the top-left pixel is (0.5, 0.5), so
``cx = width / 2`` and ``cy = height / 2`` for a centred principal point.

Output layout (``generate``)::

    DIR/synthetic.json        generator version + config (lets a re-run skip or resume)
    DIR/intrinsics.txt        fx fy cx cy width height
    DIR/TrainSplit.txt        sequence1
    DIR/TestSplit.txt         sequence2
    DIR/README.txt            what the scene holds
    DIR/seq-01/frame-XXXXXX.{color.png,depth.png,pose.txt}   reference trajectory
    DIR/seq-02/frame-XXXXXX.{color.png,depth.png,pose.txt}   query trajectory
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import shutil
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from vrs_jax import fileio, geometry
from vrs_jax.data.images import write_depth, write_image
from vrs_jax.errors import VrsError

GENERATOR = "vrs_jax.data.synthetic"
# Bump when the rendered output of a given config changes, so that old folders are not
# mistaken for complete outputs of the new generator.
GENERATOR_VERSION = 1
MARKER = "synthetic.json"


@dataclasses.dataclass(frozen=True)
class SyntheticConfig:
    """Everything that defines a synthetic scene; the same config gives byte-identical files."""

    seed: int = 0  # drives box placement, trajectory phases and every texture
    width: int = 320  # 7Scenes at half resolution: NeRF training on a CPU stays affordable
    height: int = 240
    n_reference: int = 60  # one loop at ~12 cm / ~6 deg spacing: every wall point in ~6 views
    n_query: int = 20  # between the references, off the reference path
    # Horizontal field of view: 7Scenes' Kinect RGB camera (f = 525 px at 640 px width).
    fov_deg: float = 2.0 * math.degrees(math.atan(320.0 / 525.0))
    # Room (x, y, z) in metres: a small office. Cameras look across it, so surfaces are
    # 1-4 m away (7Scenes-like depths).
    room_size: tuple[float, float, float] = (5.0, 4.0, 2.6)
    n_boxes: int = 5  # occluders with depth edges; a few are enough for parallax
    box_footprint_range: tuple[float, float] = (0.3, 0.7)  # box width/depth in metres
    box_height_range: tuple[float, float] = (0.3, 1.2)  # below most camera heights
    box_clearance: float = 0.35  # minimum horizontal distance of a box to any camera (m)
    # Reference path: an ellipse (semi-axes in metres) around the room centre, the camera
    # looking inwards across the room (every surface seen from many views with wide
    # baselines, as in an inward-facing NeRF capture), at a hand-held height.
    path_radii: tuple[float, float] = (1.3, 0.9)
    camera_height: float = 1.45  # mean camera height (m)
    camera_height_amp: float = 0.15  # +- smooth height variation (m)
    pitch_deg: float = -14.0  # mean pitch: the far wall, the boxes and the floor in view
    pitch_amp_deg: float = 6.0
    # The look-at direction swings left/right of "inwards" by up to this much; with 60
    # references consecutive views differ by at most ~12 deg (typically 6).
    yaw_amp_deg: float = 25.0
    roll_amp_deg: float = 3.0
    # Query path: offsets from the reference loop. Positions move up to ~0.25 m (radial and
    # vertical) and angles a few degrees, so the queries see the surfaces of nearby references
    # from new viewpoints (the localization demo needs > 90% within 5 cm / 5 deg).
    query_radial_offset: float = 0.15  # amplitude (m); plus a constant 0.05 m outward
    query_height_offset: float = 0.10  # amplitude (m)
    query_angle_offset_deg: float = 6.0  # amplitude of yaw/pitch offsets (deg)
    # 0: the queries sit at random fractions between reference loop parameters, spread over
    # the whole loop (the localization benchmark's queries, far apart). > 0: an ordered
    # stream, as a robot's video: n_query frames evenly spaced along this fraction of the
    # loop (on the same offset path), from a random start (tracking, localize.track).
    query_arc: float = 0.0
    # Textures: 256 texels per metre (3.9 mm) -- finer than a pixel at every distance in the
    # room at 320x240, so detail is limited by the camera, not the texture.
    texels_per_m: float = 256.0
    shape_density: float = 60.0  # procedural shapes per square metre of surface
    # Log-uniform shape sizes (m): 2 cm is ~2 px at 3 m (the smallest SIFT blob), 40 cm
    # gives structure at the coarsest octaves.
    shape_size_range: tuple[float, float] = (0.02, 0.4)
    # 2x2 samples per pixel, each a trilinear mip-map lookup: edges and textures anti-aliased.
    supersample: int = 2
    # Several rooms (the large scene): ``n_rooms`` rooms side by side along x, the same depth
    # and height (room_size[1:]), separated by partition walls with a doorway. Each room has
    # its own camera loop (x radius min(path_radii[0], width / 2 - 1 m)), boxes and two
    # lights; n_reference and n_query count the frames of a loop of the path_radii and scale
    # with each loop's size (a + b), so the view spacing stays the same. A single room (the
    # default) is unchanged.
    n_rooms: int = 1
    room_widths: tuple[float, ...] = ()  # x extent (m) of each room; (): room_size[0] each
    door_width: float = 1.0  # doorway in each partition wall, centred in y (m)
    wall_thickness: float = 0.12  # partition walls (m)

    def __post_init__(self) -> None:
        if self.width < 8 or self.height < 8:
            raise VrsError(f"image size {self.width}x{self.height} is too small (min 8x8)")
        if self.n_reference < 2 or self.n_query < 0:
            raise VrsError("need at least 2 reference frames and a non-negative query count")
        if not 10.0 < self.fov_deg < 150.0:
            raise VrsError(f"field of view {self.fov_deg} deg out of range (10, 150)")
        if self.supersample < 1:
            raise VrsError("supersample must be >= 1")
        lx, ly, _ = self.room_size
        if self.path_radii[0] + 0.5 > lx / 2 or self.path_radii[1] + 0.5 > ly / 2:
            raise VrsError("camera path must stay 0.5 m inside the room walls")
        if self.n_rooms < 1:
            raise VrsError("n_rooms must be >= 1")
        if not 0 <= self.seed < 2**32:
            raise VrsError(f"seed must be an integer in 0..2^32-1, got {self.seed}")
        if not 0.0 <= self.query_arc <= 1.0:
            raise VrsError(f"query_arc must be in [0, 1] (a fraction of the loop), got "
                           f"{self.query_arc}")
        if self.room_widths and len(self.room_widths) != self.n_rooms:
            raise VrsError(f"room_widths lists {len(self.room_widths)} widths for "
                           f"{self.n_rooms} rooms")
        if any(w < 2.6 for w in self.room_widths):
            raise VrsError("every room must be at least 2.6 m wide")
        if self.n_rooms > 1 and not 0.3 <= self.door_width <= ly - 0.4:
            raise VrsError(f"door width {self.door_width} m out of range [0.3, {ly - 0.4}]")

    @property
    def widths(self) -> tuple[float, ...]:
        """x extent (m) of each room (``room_widths`` or room_size[0] for every room)."""
        return tuple(float(w) for w in self.room_widths) or (float(self.room_size[0]),
                                                            ) * self.n_rooms

    def loop_radius_x(self, width: float) -> float:
        """x semi-axis (m) of the camera loop of a room ``width`` metres wide."""
        if self.n_rooms == 1:
            return self.path_radii[0]
        return min(self.path_radii[0], width / 2 - 1.0)

    def room_frames(self) -> tuple[list[int], list[int]]:
        """Reference and query frame counts of each room (scaled with its loop's size)."""
        if self.n_rooms == 1:
            return [self.n_reference], [self.n_query]
        a, b = self.path_radii
        scale = [(self.loop_radius_x(w) + b) / (a + b) for w in self.widths]
        return ([max(2, round(self.n_reference * f)) for f in scale],
                [round(self.n_query * f) for f in scale])

    @property
    def total_reference(self) -> int:
        return sum(self.room_frames()[0])

    @property
    def total_query(self) -> int:
        return sum(self.room_frames()[1])


# Fields of the multi-room extension: left out of the config record (synthetic.json, README)
# while at their defaults, so a single-room scene's files are byte-identical to those written
# before the extension existed.
_ROOM_FIELDS = ("n_rooms", "room_widths", "door_width", "wall_thickness")
# Left out likewise while at its default (0: queries spread over the loop).
_STREAM_FIELDS = ("query_arc",)


CONFIGS: dict[str, SyntheticConfig] = {
    # The embedded default scene used by experiments.demo.
    "default": SyntheticConfig(),
    # Tiny images and few frames for unit tests; coarser textures (1.6 cm texels are still
    # finer than a pixel at 96x72) so that building them takes a fraction of a second.
    "test": SyntheticConfig(width=96, height=72, n_reference=12, n_query=3, texels_per_m=64.0),
    # The large scene: an 8 m hall and three 3.5 m offices in a row (18.5 x 4 m), joined by
    # doorways; 160x120 images; 20 references + 5 queries in the hall, 15 + 4 in each office
    # (65 + 17). Four rooms of unequal widths: K-means on the camera centres finds the four
    # rooms, while a uniform grid of four cells along the row cuts through two offices.
    "rooms4": SyntheticConfig(width=160, height=120, n_reference=20, n_query=5,
                              texels_per_m=128.0, n_rooms=4, room_widths=(8.0, 3.5, 3.5, 3.5)),
}


def get_config(name: str) -> SyntheticConfig:
    """The named config (``default``, ``test`` or ``rooms4``); VrsError for an unknown
    name."""
    if name not in CONFIGS:
        raise VrsError(f"unknown synthetic config {name!r}; known: {', '.join(CONFIGS)}")
    return CONFIGS[name]


# ----------------------------------------------------------------------------- layout


class Box(NamedTuple):
    """A box standing on the floor, rotated by ``yaw`` about the vertical axis.

    center: [3] world centre (z = half height); half: [3] half extents in the box frame;
    yaw: rotation (radians) of the box frame about world z.
    """

    center: np.ndarray
    half: np.ndarray
    yaw: float


class Layout(NamedTuple):
    """Geometry and cameras of a synthetic scene (no textures).

    room_min, room_max: [3] corners of the room; boxes: the boxes; K: [3, 3] intrinsics;
    c2w_ref: [N, 4, 4] reference camera-to-world poses; c2w_query: [M, 4, 4] query poses.
    """

    room_min: np.ndarray
    room_max: np.ndarray
    boxes: tuple[Box, ...]
    K: np.ndarray
    c2w_ref: np.ndarray
    c2w_query: np.ndarray
    # [R + 1] x of the room boundaries (partition walls at the inner ones); None: one room.
    room_x: np.ndarray | None = None
    ref_room: np.ndarray | None = None  # [N] int room of each reference camera
    query_room: np.ndarray | None = None  # [M] int room of each query camera

    def room_centers(self) -> np.ndarray:
        """[R] x of each room's centre."""
        x = np.asarray(self.room_x if self.room_x is not None
                       else [self.room_min[0], self.room_max[0]])
        return 0.5 * (x[:-1] + x[1:])


def intrinsics(cfg: SyntheticConfig) -> np.ndarray:
    """[3, 3] pinhole intrinsics: square pixels, principal point at the image centre."""
    f = (cfg.width / 2.0) / math.tan(math.radians(cfg.fov_deg) / 2.0)
    return geometry.intrinsics_matrix(f, f, cfg.width / 2.0, cfg.height / 2.0)


def _rng(cfg: SyntheticConfig, stream: int, room: int = 0) -> np.random.Generator:
    """Independent random streams (0: layout phases, 1: boxes, 2: textures, 3: query
    fractions) from the seed; rooms after the first have their own streams."""
    key = [int(cfg.seed), stream] + ([room] if room else [])
    return np.random.default_rng(np.random.SeedSequence(key))


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def look_rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Camera-to-world rotations [N, 3, 3] (OpenCV axes) from angles [N] in radians.

    yaw: heading of the optical axis about world z (0 = +x); pitch: elevation of the optical
    axis (negative looks down); roll: rotation about the optical axis.
    """
    fwd = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], -1)
    right = np.cross(fwd, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    down = np.cross(fwd, right)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    r2, d2 = c * right + s * down, -s * right + c * down
    return np.stack([r2, d2, fwd], axis=-1)


def _trajectory(cfg: SyntheticConfig, s: np.ndarray, phases: np.ndarray,
                offsets: dict[str, np.ndarray] | None = None, center_x: float = 0.0,
                width: float | None = None) -> np.ndarray:
    """Camera-to-world poses [N, 4, 4] at loop parameters s [N] (radians around the loop).

    Smooth in s: positions on a wobbling ellipse with varying height; the optical axis looks
    outwards with a slowly swinging yaw, pitch and roll. ``offsets`` (query path) adds radial
    (m), height (m), yaw/pitch/roll (rad) offsets, each [N]. ``center_x``, ``width``: the
    room's centre and width (:meth:`SyntheticConfig.loop_radius_x`).
    """
    p = phases
    a, b = cfg.path_radii
    if width is not None:
        a = cfg.loop_radius_x(width)
    wobble = 1.0 + 0.08 * np.sin(3 * s + p[0])
    radial = np.stack([a * np.cos(s), b * np.sin(s)], -1) * wobble[:, None]
    normal = np.stack([np.cos(s) / a, np.sin(s) / b], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    height = cfg.camera_height + cfg.camera_height_amp * np.sin(2 * s + p[1])
    # Looking inwards, across the room (as in an inward-facing NeRF capture), swinging.
    yaw = np.arctan2(-normal[:, 1], -normal[:, 0]) + math.radians(cfg.yaw_amp_deg) * (
        0.8 * np.sin(2 * s + p[2]) + 0.2 * np.sin(3 * s + p[3]))
    pitch = math.radians(cfg.pitch_deg) + math.radians(cfg.pitch_amp_deg) * np.sin(3 * s + p[4])
    roll = math.radians(cfg.roll_amp_deg) * np.sin(4 * s + p[5])
    if offsets is not None:
        radial = radial + offsets["radial"][:, None] * normal
        height = height + offsets["height"]
        yaw, pitch, roll = yaw + offsets["yaw"], pitch + offsets["pitch"], roll + offsets["roll"]
    c2w = np.tile(np.eye(4), (len(s), 1, 1))
    c2w[:, :3, :3] = look_rotation(yaw, pitch, roll)
    c2w[:, :2, 3] = radial
    if center_x:
        c2w[:, 0, 3] += center_x
    c2w[:, 2, 3] = height
    return c2w


def _query_parameters(cfg: SyntheticConfig, n: int, rng: np.random.Generator) -> np.ndarray:
    """Loop parameters [n] (radians) of a room's queries: at random fractions between
    reference loop parameters (never on a reference), or with ``cfg.query_arc`` an ordered
    stream evenly spaced along that fraction of the loop from a random start."""
    if cfg.query_arc > 0:
        start = rng.uniform(0.0, 2 * math.pi)
        return start + 2 * math.pi * cfg.query_arc * np.arange(n) / max(n - 1, 1)
    frac = rng.uniform(0.25, 0.75, size=n)
    return 2 * math.pi * (np.arange(n) + frac) / max(n, 1)


def _query_offsets(cfg: SyntheticConfig, s: np.ndarray, p: np.ndarray) -> dict[str, np.ndarray]:
    """Smooth offsets [N] of the query path from the reference loop at parameters s [N]."""
    ang = math.radians(cfg.query_angle_offset_deg)
    return {
        "radial": 0.05 + cfg.query_radial_offset * np.sin(3 * s + p[6]),
        "height": cfg.query_height_offset * np.sin(2 * s + p[7]),
        "yaw": ang * np.sin(4 * s + p[8]),
        "pitch": 0.7 * ang * np.cos(3 * s + p[9]),
        "roll": 0.3 * ang * np.sin(5 * s + p[10]),
    }


def _box_footprint(center: np.ndarray, half: np.ndarray, yaw: float) -> np.ndarray:
    """[4, 2] corners (x, y) of a box's footprint."""
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * half[:2]
    return corners @ _rot_z(yaw)[:2, :2].T + center[:2]


def _point_box_distance(xy: np.ndarray, center: np.ndarray, half: np.ndarray,
                        yaw: float) -> np.ndarray:
    """Horizontal distance [N] of points xy [N, 2] to a box footprint (0 inside)."""
    local = (xy - center[:2]) @ _rot_z(yaw)[:2, :2]
    excess = np.maximum(np.abs(local) - half[:2], 0.0)
    return np.linalg.norm(excess, axis=-1)


def _place_boxes(cfg: SyntheticConfig, rng: np.random.Generator,
                 cam_xy: np.ndarray, x_range: tuple[float, float] | None = None
                 ) -> tuple[Box, ...]:
    """Rejection-sample non-overlapping boxes inside the room, clear of the camera paths.

    Box b is first tried in its own angular sector around the room centre (so that the boxes
    spread around the room), then anywhere. ``x_range``: the room's free x interval (between
    its walls) when it is one of several rooms.
    """
    lx, ly, _ = cfg.room_size
    x_lo, x_hi = (-lx / 2, lx / 2) if x_range is None else x_range
    cx = 0.5 * (x_lo + x_hi) if x_range is not None else 0.0
    lx = x_hi - x_lo if x_range is not None else lx
    n = cfg.n_boxes
    sector0 = rng.uniform(0.0, 2 * math.pi)
    boxes: list[Box] = []
    for b in range(n):
        for attempt in range(4000):
            w, d = rng.uniform(*cfg.box_footprint_range, size=2)
            h = rng.uniform(*cfg.box_height_range)
            center = np.array([rng.uniform(x_lo, x_hi), rng.uniform(-ly / 2, ly / 2),
                               h / 2])
            half = np.array([w / 2, d / 2, h / 2])
            yaw = float(rng.uniform(0.0, math.pi / 2))
            if attempt < 2000:
                ang = (math.atan2(center[1] / ly, (center[0] - cx) / lx) - sector0
                       ) % (2 * math.pi)
                if int(ang / (2 * math.pi) * n) != b:
                    continue
            fp = _box_footprint(center, half, yaw)
            if ((fp[:, 0] < x_lo + 0.03).any() or (fp[:, 0] > x_hi - 0.03).any()
                    or (np.abs(fp[:, 1]) > ly / 2 - 0.03).any()):
                continue
            if _point_box_distance(cam_xy, center, half, yaw).min() <= cfg.box_clearance:
                continue
            radius = np.linalg.norm(half[:2])
            if any(np.linalg.norm(center[:2] - o.center[:2]) <= radius
                   + np.linalg.norm(o.half[:2]) + 0.05 for o in boxes):
                continue
            boxes.append(Box(center, half, yaw))
            break
        else:
            raise VrsError(f"could not place {n} boxes in the room clear of the cameras; use "
                           "fewer or smaller boxes or a larger room")
    return tuple(boxes)


def room_bounds(cfg: SyntheticConfig) -> np.ndarray:
    """[R + 1] x of the room boundaries: the rooms side by side, centred on x = 0."""
    w = np.asarray(cfg.widths, float)
    return np.concatenate([[0.0], np.cumsum(w)]) - w.sum() / 2


def _partition_walls(cfg: SyntheticConfig, bounds: np.ndarray) -> list[Box]:
    """Two floor-to-ceiling boxes per inner boundary, leaving a doorway centred in y."""
    _, ly, lz = cfg.room_size
    t, door = cfg.wall_thickness, cfg.door_width
    seg = (ly - door) / 2  # wall length on each side of the door
    walls = []
    for x in bounds[1:-1]:
        for sign in (-1.0, 1.0):
            y = sign * (door / 2 + seg / 2)
            walls.append(Box(np.array([x, y, lz / 2]), np.array([t / 2, seg / 2, lz / 2]), 0.0))
    return walls


def build_layout(cfg: SyntheticConfig) -> Layout:
    """Room(s), boxes, intrinsics and both trajectories of the scene for ``cfg``
    (deterministic). Several rooms: one loop, its queries and its boxes per room, then the
    partition walls."""
    bounds = room_bounds(cfg)
    n_ref, n_q = cfg.room_frames()
    refs, queries, boxes, ref_room, q_room = [], [], [], [], []
    half_t = cfg.wall_thickness / 2
    for r in range(cfg.n_rooms):
        cx = float(0.5 * (bounds[r] + bounds[r + 1])) if cfg.n_rooms > 1 else 0.0
        w = float(bounds[r + 1] - bounds[r])
        traj = functools.partial(_trajectory, cfg, center_x=cx, width=w)
        phases = _rng(cfg, 0, r).uniform(0.0, 2 * math.pi, size=11)
        s_ref = 2 * math.pi * np.arange(n_ref[r]) / n_ref[r]
        refs.append(traj(s_ref, phases))
        s_q = _query_parameters(cfg, n_q[r], _rng(cfg, 3, r))
        queries.append(traj(s_q, phases, _query_offsets(cfg, s_q, phases)))
        # Boxes must clear every camera of a densely sampled reference and query path.
        s_dense = np.linspace(0.0, 2 * math.pi, 720, endpoint=False)
        dense = np.concatenate([
            traj(s_dense, phases)[:, :2, 3],
            traj(s_dense, phases, _query_offsets(cfg, s_dense, phases))[:, :2, 3]])
        x_range = None
        if cfg.n_rooms > 1:
            x_range = (float(bounds[r]) + (half_t if r > 0 else 0.0),
                       float(bounds[r + 1]) - (half_t if r < cfg.n_rooms - 1 else 0.0))
        boxes += _place_boxes(cfg, _rng(cfg, 1, r), dense, x_range)
        ref_room += [r] * n_ref[r]
        q_room += [r] * n_q[r]
    boxes += _partition_walls(cfg, bounds)
    size = np.array([bounds[-1] - bounds[0], cfg.room_size[1], cfg.room_size[2]], float)
    room_min = np.array([-size[0] / 2, -size[1] / 2, 0.0])
    return Layout(room_min, room_min + size, tuple(boxes), intrinsics(cfg),
                  np.concatenate(refs), np.concatenate(queries), bounds,
                  np.asarray(ref_room, np.int64), np.asarray(q_room, np.int64))


# ----------------------------------------------------------------------------- faces


class Face(NamedTuple):
    """One textured rectangle of the world.

    body: -1 for the room, else the box index; axis: 0/1/2 local axis of its normal; side: 0
    for the minus side, 1 for the plus side (of the room or box, in the body's local frame);
    u_axis, v_axis: local axes spanning the face; size: (width, height) in metres along them;
    normal: [3] world normal pointing into the visible half-space.
    """

    body: int
    axis: int
    side: int
    u_axis: int
    v_axis: int
    size: tuple[float, float]
    normal: np.ndarray


_TANGENTS = {0: (1, 2), 1: (0, 2), 2: (0, 1)}


def faces(layout: Layout) -> list[Face]:
    """All faces: 6 room faces (index 2*axis + side), then 6 per box (6 + 6*b + 2*axis + side)."""
    out = []
    extent = layout.room_max - layout.room_min
    for axis in range(3):
        for side in range(2):
            u, v = _TANGENTS[axis]
            n = np.zeros(3)
            n[axis] = 1.0 if side == 0 else -1.0  # the room is seen from inside
            out.append(Face(-1, axis, side, u, v, (extent[u], extent[v]), n))
    for b, box in enumerate(layout.boxes):
        rot = _rot_z(box.yaw)
        for axis in range(3):
            for side in range(2):
                u, v = _TANGENTS[axis]
                n = rot[:, axis] * (-1.0 if side == 0 else 1.0)  # boxes are seen from outside
                out.append(Face(b, axis, side, u, v, (2 * box.half[u], 2 * box.half[v]), n))
    return out


def _safe(c: np.ndarray) -> np.ndarray:
    """Direction components with exact zeros nudged (so 1 / c is finite)."""
    return np.where(np.abs(c) < 1e-12, 1e-12, c)


def _hit_room(layout: Layout, origin: np.ndarray, d: tuple[np.ndarray, ...]
              ) -> tuple[np.ndarray, np.ndarray]:
    """Exit of rays (components [...] each, nudged) from the room: (t [...], face [...]).

    The nearest exit plane; its face index is 2 * axis + side (side 1 = the max plane).
    """
    t_best = face = None
    for k in range(3):
        pos = d[k] > 0
        tk = (np.where(pos, layout.room_max[k], layout.room_min[k]) - origin[k]) / d[k]
        fk = 2 * k + pos.astype(np.int64)
        if t_best is None:
            t_best, face = tk, fk
        else:
            closer = tk < t_best
            t_best = np.where(closer, tk, t_best)
            face = np.where(closer, fk, face)
    return t_best, face


def _hit_box(box: Box, origin: np.ndarray, d: tuple[np.ndarray, ...]
             ) -> tuple[np.ndarray, np.ndarray]:
    """Entry of rays (components [...] each) into a box: (t [...], local face [...]).

    Slab test in the box frame; t is +inf where the ray misses the box (or starts inside or
    beyond it). The local face index is 2 * axis + side (side 1 = the plus face).
    """
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    rel = origin - box.center
    o_l = (c * rel[0] + s * rel[1], -s * rel[0] + c * rel[1], rel[2])
    dl = (c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2])
    t_near = t_far = face = None
    for k in range(3):
        dk = _safe(dl[k])
        ta = (-box.half[k] - o_l[k]) / dk
        tb = (box.half[k] - o_l[k]) / dk
        lo, hi = np.minimum(ta, tb), np.maximum(ta, tb)
        # Entering through the minus face (side 0) when moving towards +axis.
        fk = 2 * k + (dk < 0).astype(np.int64)
        if t_near is None:
            t_near, t_far, face = lo, hi, fk
        else:
            later = lo > t_near
            t_near = np.where(later, lo, t_near)
            face = np.where(later, fk, face)
            t_far = np.minimum(t_far, hi)
    hit = (t_near <= t_far) & (t_near > 0)
    return np.where(hit, t_near, np.inf), face


def cast_rays(layout: Layout, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray,
                                                                             np.ndarray]:
    """First hit of rays from one origin (inside the room, outside every box).

    Args:
      layout: the scene; origin: [3]; dirs: [N, 3] directions (any length).
    Returns:
      t: [N] ray parameter of the hit (hit point = origin + t * dirs); with directions whose
        camera z component is 1, ``t`` is the z-depth; face: [N] int face index (see ``faces``).
    """
    d = tuple(_safe(np.ascontiguousarray(dirs[:, k])) for k in range(3))
    t_best, face = _hit_room(layout, origin, d)
    for b, box in enumerate(layout.boxes):
        tb, fb = _hit_box(box, origin, d)
        closer = tb < t_best
        t_best = np.where(closer, tb, t_best)
        face = np.where(closer, 6 + 6 * b + fb, face)
    return t_best, face


def _box_pixel_window(box: Box, K: np.ndarray, c2w: np.ndarray, width: int, height: int
                      ) -> tuple[int, int, int, int] | None:
    """Pixel rows/cols (r0, r1, c0, c1) that may see the box, or None if it is out of view.

    The projection of the 8 corners bounds the box's image (when all are in front of the
    camera; otherwise the whole image is returned). One pixel of margin.
    """
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    world = (corners * box.half) @ _rot_z(box.yaw).T + box.center
    cam = (world - c2w[:3, 3]) @ c2w[:3, :3]
    if (cam[:, 2] <= 1e-3).any():
        return (0, height, 0, width)
    u = K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2]
    v = K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]
    c0, c1 = int(math.floor(u.min())) - 1, int(math.ceil(u.max())) + 1
    r0, r1 = int(math.floor(v.min())) - 1, int(math.ceil(v.max())) + 1
    c0, c1, r0, r1 = max(c0, 0), min(c1, width), max(r0, 0), min(r1, height)
    if c0 >= c1 or r0 >= r1:
        return None
    return (r0, r1, c0, c1)


def cast_image(layout: Layout, K: np.ndarray, c2w: np.ndarray, width: int, height: int
               ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
    """Cast the rays through every pixel centre of an image.

    Args:
      K: [3, 3] intrinsics (COLMAP convention); c2w: [4, 4] camera-to-world; width, height.
    Returns:
      t: [H, W] z-depth of the first hit; face: [H, W] int face index; dirs: the 3 world
      direction components [H, W] each (camera z = 1, so hit = centre + t * dir).
    """
    R, o = c2w[:3, :3], c2w[:3, 3]
    xn = (np.arange(width) + 0.5 - K[0, 2]) / K[0, 0]
    yn = (np.arange(height) + 0.5 - K[1, 2]) / K[1, 1]
    d = tuple(_safe(R[k, 0] * xn[None, :] + R[k, 1] * yn[:, None] + R[k, 2]) for k in range(3))
    t_best, face = _hit_room(layout, o, d)
    for b, box in enumerate(layout.boxes):
        win = _box_pixel_window(box, K, c2w, width, height)
        if win is None:
            continue
        r0, r1, c0, c1 = win
        tb, fb = _hit_box(box, o, tuple(c[r0:r1, c0:c1] for c in d))
        sub_t, sub_f = t_best[r0:r1, c0:c1], face[r0:r1, c0:c1]
        closer = tb < sub_t
        t_best[r0:r1, c0:c1] = np.where(closer, tb, sub_t)
        face[r0:r1, c0:c1] = np.where(closer, 6 + 6 * b + fb, sub_f)
    return t_best, face, d


# ----------------------------------------------------------------------------- textures


def _noise(rng: np.random.Generator, h: int, w: int, cell: float, channels: int) -> np.ndarray:
    """Smooth value noise [h, w, channels] (unit-ish variance) with feature size ``cell`` texels.

    A random grid upsampled with bicubic interpolation; never tiles.
    """
    gh, gw = int(math.ceil(h / cell)) + 3, int(math.ceil(w / cell)) + 3
    grid = rng.standard_normal((gh, gw, channels)).astype(np.float32)
    big = cv2.resize(grid, (int(round(gw * cell)), int(round(gh * cell))),
                     interpolation=cv2.INTER_CUBIC)
    if big.ndim == 2:
        big = big[..., None]
    o = int(cell)  # skip the border cells, where bicubic clamps
    return big[o:o + h, o:o + w]


def _random_colour(rng: np.random.Generator, sat: tuple[float, float],
                   val: tuple[float, float]) -> np.ndarray:
    """An RGB colour [3] in [0, 1] from a random hue and the given saturation/value ranges."""
    hsv = np.array([[[rng.uniform(0, 360), rng.uniform(*sat), rng.uniform(*val)]]], np.float32)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0].astype(np.float64)


def face_texture(rng: np.random.Generator, size_m: tuple[float, float],
                 cfg: SyntheticConfig) -> np.ndarray:
    """Procedural RGB texture [H, W, 3] float32 in [0, 1] for a face of ``size_m`` metres.

    Texel (i, j) covers surface coordinates [j, j+1) x [i, i+1) / texels_per_m. Content:
    a base colour with multi-octave luminance noise (features 40, 12 and 4 cm) and
    low-frequency colour noise, then shapes
    (filled rotated rectangles, triangles, ellipses, rings, line segments) with log-uniform
    sizes drawn largest first (small details stay on top), then a low-frequency shading
    variation over everything; finally a slight blur (0.6 texel) so edges are not jagged.
    """
    tpm = cfg.texels_per_m
    w = max(4, int(math.ceil(size_m[0] * tpm)))
    h = max(4, int(math.ceil(size_m[1] * tpm)))
    base = _random_colour(rng, (0.05, 0.4), (0.35, 0.8)).astype(np.float32)
    tex = np.broadcast_to(base, (h, w, 3)).copy()
    # Mostly luminance noise (SIFT sees grey) with a little low-frequency colour variation.
    for cell_m, amp in ((0.40, 0.08), (0.12, 0.07), (0.04, 0.06)):
        tex += amp * _noise(rng, h, w, cell_m * tpm, 1)
    tex += 0.04 * _noise(rng, h, w, 0.3 * tpm, 3)
    n = rng.poisson(cfg.shape_density * size_m[0] * size_m[1])
    lo, hi = cfg.shape_size_range
    sizes = np.sort(np.exp(rng.uniform(math.log(lo), math.log(hi), n)))[::-1] * tpm
    shift = 4  # cv2 fixed-point coordinates: 1/16 texel precision
    one = 1 << shift
    for sz in sizes:
        kind = rng.integers(0, 6)
        colour = tuple(float(c) for c in _random_colour(rng, (0.0, 0.9), (0.05, 1.0)))
        cx, cy = rng.uniform(-0.1 * w, 1.1 * w), rng.uniform(-0.1 * h, 1.1 * h)
        ang = rng.uniform(0, 2 * math.pi)
        if kind == 0 or kind == 1:  # rotated rectangle (kind 1: elongated)
            aspect = rng.uniform(0.3, 1.0) if kind == 0 else rng.uniform(0.08, 0.3)
            hw, hh = sz / 2, sz * aspect / 2
            c, s = math.cos(ang), math.sin(ang)
            pts = np.array([[-hw, -hh], [hw, -hh], [hw, hh], [-hw, hh]]) @ np.array(
                [[c, s], [-s, c]]) + [cx, cy]
            cv2.fillPoly(tex, [np.round(pts * one).astype(np.int32)], colour, cv2.LINE_8, shift)
        elif kind == 2:  # triangle
            r = sz / 2
            angles = ang + np.sort(rng.uniform(0, 2 * math.pi, 3))
            pts = np.stack([cx + r * np.cos(angles), cy + r * np.sin(angles)], -1)
            cv2.fillPoly(tex, [np.round(pts * one).astype(np.int32)], colour, cv2.LINE_8, shift)
        elif kind == 3:  # ellipse / disc
            axes = (int(round(sz / 2 * one)), int(round(sz / 2 * rng.uniform(0.4, 1.0) * one)))
            cv2.ellipse(tex, (int(round(cx * one)), int(round(cy * one))), axes,
                        math.degrees(ang), 0, 360, colour, -1, cv2.LINE_8, shift)
        elif kind == 4:  # ring
            thick = max(1, int(round(sz * rng.uniform(0.08, 0.25))))
            cv2.circle(tex, (int(round(cx * one)), int(round(cy * one))),
                       int(round(sz / 2 * one)), colour, thick, cv2.LINE_8, shift)
        else:  # line segment
            thick = max(1, int(round(sz * rng.uniform(0.04, 0.12))))
            dx, dy = math.cos(ang) * sz, math.sin(ang) * sz
            p0 = (int(round((cx - dx) * one)), int(round((cy - dy) * one)))
            p1 = (int(round((cx + dx) * one)), int(round((cy + dy) * one)))
            cv2.line(tex, p0, p1, colour, thick, cv2.LINE_8, shift)
    tex *= 1.0 + 0.15 * _noise(rng, h, w, 0.3 * tpm, 1)
    tex = cv2.GaussianBlur(tex, (0, 0), 0.6)
    return np.clip(tex, 0.02, 0.98).astype(np.float32)


def mip_pyramid(tex: np.ndarray, max_levels: int = 7) -> list[np.ndarray]:
    """Mip levels of a texture [H, W, C]: level l has texels 2^l times as large.

    Each level is the 2x2 box average of the previous one (so texel centres of level l sit
    exactly at (j + 0.5) * 2^l in level-0 texels), smoothed by a symmetric [1, 2, 1] / 4
    kernel (keeps the centres) for a better low-pass.
    """
    levels = [tex]
    while len(levels) < max_levels and min(levels[-1].shape[:2]) >= 8:
        t = levels[-1]
        if t.shape[0] % 2:
            t = np.concatenate([t, t[-1:]], 0)
        if t.shape[1] % 2:
            t = np.concatenate([t, t[:, -1:]], 1)
        t = 0.25 * (t[0::2, 0::2] + t[1::2, 0::2] + t[0::2, 1::2] + t[1::2, 1::2])
        t = cv2.sepFilter2D(t, -1, np.array([0.25, 0.5, 0.25], np.float32),
                            np.array([0.25, 0.5, 0.25], np.float32),
                            borderType=cv2.BORDER_REPLICATE)
        levels.append(t)
    return levels


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup of img [h, w, C] float32 at continuous texel coordinates x, y [N].

    Texel (i, j) is centred at (j + 0.5, i + 0.5); lookups outside clamp to the border.
    Uses cv2.remap (30x faster than numpy gathers); its interpolation weights are quantised
    to 1/32 texel, which keeps the texture a fixed function of the surface coordinate.
    Returns [N, C] float32.
    """
    n = len(x)
    cols = 1024  # cv2.remap needs both map dimensions below 32767
    rows = -(-n // cols)
    pad = rows * cols - n
    mx = np.concatenate([x - 0.5, np.zeros(pad)]).astype(np.float32).reshape(rows, cols)
    my = np.concatenate([y - 0.5, np.zeros(pad)]).astype(np.float32).reshape(rows, cols)
    out = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(rows * cols, -1)[:n]


class World(NamedTuple):
    """Layout plus faces, their mip-mapped textures and the lights."""

    layout: Layout
    faces: list[Face]
    textures: list[list[np.ndarray]]  # per face its mip levels [H_l, W_l, 3] float32
    lights: np.ndarray  # [L, 3] point light positions
    texels_per_m: float  # level-0 texture resolution


def build_world(cfg: SyntheticConfig, layout: Layout | None = None) -> World:
    """Layout, faces and textures for ``cfg`` (deterministic for the seed)."""
    layout = build_layout(cfg) if layout is None else layout
    fcs = faces(layout)
    rng = _rng(cfg, 2)
    textures = [mip_pyramid(face_texture(rng, fc.size, cfg)) for fc in fcs]
    lz = cfg.room_size[2]
    # Two lights per room, a quarter of its width either side of its centre.
    lights = np.array([[c + s * w / 4, 0.0, lz - 0.4]
                       for c, w in zip(layout.room_centers(), cfg.widths, strict=True)
                       for s in (-1.0, 1.0)])
    return World(layout, fcs, textures, lights, float(cfg.texels_per_m))


def _shade(world: World, px: np.ndarray, py: np.ndarray, pz: np.ndarray,
           normal: np.ndarray) -> np.ndarray:
    """View-independent Lambertian shading factor [N] at points (components [N]) with a
    normal [3]: ambient plus two point lights with a soft distance falloff, no shadows."""
    out = np.full(len(px), 0.55, np.float32)
    for light in world.lights:
        lx, ly, lz = light[0] - px, light[1] - py, light[2] - pz
        dist2 = lx * lx + ly * ly + lz * lz
        cos = np.maximum(lx * normal[0] + ly * normal[1] + lz * normal[2], 0.0) / np.sqrt(dist2)
        out += (0.45 * cos / (1.0 + dist2 / 9.0)).astype(np.float32)
    return out


def _face_uv(layout: Layout, fc: Face, px: np.ndarray, py: np.ndarray, pz: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Surface coordinates (metres) of hit points given as components [N] each."""
    if fc.body < 0:
        local = (px - layout.room_min[0], py - layout.room_min[1], pz - layout.room_min[2])
    else:
        box = layout.boxes[fc.body]
        c, s = math.cos(box.yaw), math.sin(box.yaw)
        rx, ry = px - box.center[0], py - box.center[1]
        local = (c * rx + s * ry + box.half[0], -s * rx + c * ry + box.half[1],
                 pz - box.center[2] + box.half[2])
    return local[fc.u_axis], local[fc.v_axis]


def render_frame(world: World, K: np.ndarray, c2w: np.ndarray, width: int, height: int,
                 supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Render one view.

    Args:
      world: the scene; K: [3, 3] intrinsics (COLMAP pixel convention); c2w: [4, 4]
      camera-to-world (OpenCV axes); width, height: image size; supersample: samples per pixel
      per axis (each a trilinear mip-map lookup, box-averaged).
    Returns:
      rgb: [H, W, 3] float32 in [0, 1]; depth: [H, W] float64 z-depth (metres) of the ray
      through each pixel centre.
    """
    S = supersample
    o = c2w[:3, 3]
    layout = world.layout
    texels_per_m = world.texels_per_m

    # Sub-sample (jj, ii) of the S-times image sits at u = (jj + 0.5) / S: that image has
    # intrinsics diag(S, S, 1) K in the same pixel convention.
    Ks = geometry.scale_intrinsics(K, S)
    t, face, d = cast_image(layout, Ks, c2w, width * S, height * S)
    t, face, d = t.ravel(), face.ravel(), tuple(c.ravel() for c in d)
    # Footprint of a sample on the surface in texels: distance * angle / cos(incidence), the
    # obliquity capped at 1 / 0.3 (more would blur grazing floors to mush).
    dn = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    normals = np.stack([fc.normal for fc in world.faces])
    cos = np.abs(d[0] * normals[face, 0] + d[1] * normals[face, 1]
                 + d[2] * normals[face, 2]) / dn
    foot = t * dn * (texels_per_m / Ks[0, 0]) / np.maximum(cos, 0.3)
    lam = np.log2(np.maximum(foot, 1.0))  # level 0 when a sample is finer than a texel
    n_lev = np.array([len(p) for p in world.textures])
    lam = np.minimum(lam, n_lev[face] - 1)
    lev0 = np.floor(lam).astype(np.int64)
    frac = (lam - lev0).astype(np.float32)
    # One group per (face, level): each needs two bilinear lookups (levels l and l + 1).
    key = face * 16 + lev0
    order = np.argsort(key, kind="stable")
    keys_sorted = key[order]
    starts = np.flatnonzero(np.r_[True, keys_sorted[1:] != keys_sorted[:-1]])
    ends = np.r_[starts[1:], len(order)]
    colour = np.empty((len(t), 3), np.float32)
    for a, b in zip(starts, ends, strict=True):
        idx = order[a:b]
        f, lev = divmod(int(keys_sorted[a]), 16)
        fc, pyr = world.faces[f], world.textures[f]
        ti = t[idx]
        px, py, pz = (o[k] + ti * d[k][idx] for k in range(3))
        su, sv = _face_uv(layout, fc, px, py, pz)
        su, sv = su * texels_per_m, sv * texels_per_m
        val = _bilinear(pyr[lev], su * 2.0 ** -lev, sv * 2.0 ** -lev)
        if lev + 1 < len(pyr):
            w1 = frac[idx, None]
            val = val * (1 - w1) + w1 * _bilinear(pyr[lev + 1], su * 2.0 ** -(lev + 1),
                                                  sv * 2.0 ** -(lev + 1))
        colour[idx] = val * _shade(world, px, py, pz, fc.normal)[:, None]
    rgb = colour.reshape(height, S, width, S, 3).mean(axis=(1, 3))
    # Depth: the exact z-depth of the ray through each pixel centre.
    depth, _, _ = cast_image(layout, K, c2w, width, height)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32), depth


# ----------------------------------------------------------------------------- output


def config_dict(cfg: SyntheticConfig) -> dict:
    """The config as JSON values, the multi-room fields left out while at their defaults."""
    d = dataclasses.asdict(cfg)
    default = SyntheticConfig()
    for k in _ROOM_FIELDS:
        if d[k] == getattr(default, k) or (k in ("door_width", "wall_thickness")
                                           and cfg.n_rooms == 1):
            del d[k]
    for k in _STREAM_FIELDS:
        if d[k] == getattr(default, k):
            del d[k]
    return json.loads(json.dumps(d))


def _config_record(cfg: SyntheticConfig) -> dict:
    return {"generator": GENERATOR, "version": GENERATOR_VERSION, "config": config_dict(cfg)}


def _write_text(path: Path, text: str) -> None:
    """Write a text file atomically (:func:`vrs_jax.fileio.write_text`)."""
    fileio.write_text(path, text)


def _frame_paths(out: Path, seq: int, i: int) -> tuple[Path, Path, Path]:
    stem = out / f"seq-{seq:02d}" / f"frame-{i:06d}"
    return (stem.with_name(stem.name + ".color.png"), stem.with_name(stem.name + ".depth.png"),
            stem.with_name(stem.name + ".pose.txt"))


def _all_frames(cfg: SyntheticConfig) -> list[tuple[int, int]]:
    return ([(1, i) for i in range(cfg.total_reference)]
            + [(2, i) for i in range(cfg.total_query)])


def _is_complete(out: Path, cfg: SyntheticConfig) -> bool:
    fixed = ["intrinsics.txt", "TrainSplit.txt", "TestSplit.txt", "README.txt"]
    return all((out / n).is_file() for n in fixed) and all(
        p.is_file() for s, i in _all_frames(cfg) for p in _frame_paths(out, s, i))


def is_generated(out_dir: str | Path, cfg: SyntheticConfig) -> bool:
    """True if ``out_dir`` holds the complete output of ``cfg`` (``generate`` would skip)."""
    out = Path(out_dir)
    try:
        record = json.loads((out / MARKER).read_text())
        same = {k: record[k] for k in ("generator", "version", "config")} == _config_record(cfg)
        return same and bool(record.get("complete")) and _is_complete(out, cfg)
    except (OSError, ValueError, KeyError, TypeError):
        return False


def _prepare_out(out: Path, cfg: SyntheticConfig, overwrite: bool) -> str:
    """Decide what to do with ``out``: 'skip' (complete), 'resume' or 'fresh'.

    Raises VrsError if ``out`` is a file, or a non-empty folder that is not a synthetic scene,
    or a synthetic scene of another config (unless ``overwrite``).
    """
    if out.exists() and not out.is_dir():
        raise VrsError("output path exists and is not a folder", out)
    if not out.exists() or not any(out.iterdir()):
        return "fresh"
    marker = out / MARKER
    if not marker.is_file():
        raise VrsError("folder is not empty and holds no synthetic scene (no synthetic.json); "
                       "refusing to write into it, choose another output folder", out)
    try:
        record = json.loads(marker.read_text())
        same = {k: record[k] for k in ("generator", "version", "config")} == _config_record(cfg)
        complete = bool(record.get("complete", False))
    except (ValueError, KeyError, TypeError) as e:
        raise VrsError(f"malformed synthetic scene marker ({e})", marker) from e
    if same and not overwrite:
        return "skip" if complete and _is_complete(out, cfg) else "resume"
    if not same and not overwrite:
        raise VrsError("folder holds a synthetic scene of another configuration or generator "
                       "version; pass overwrite (--overwrite) to replace it", out)
    # Overwrite: remove only what a previous run of this generator wrote.
    for child in out.iterdir():
        if child.is_dir() and child.name.startswith("seq-"):
            shutil.rmtree(child)
        elif child.is_file() and (child.name in (MARKER, "intrinsics.txt", "TrainSplit.txt",
                                                 "TestSplit.txt", "README.txt")
                                  or child.name.endswith(".tmp")):
            child.unlink()
    return "fresh"


def pose_text(c2w: np.ndarray) -> str:
    """A 4x4 matrix as 7Scenes pose.txt text, full float64 precision (round-trips exactly)."""
    return "".join(" ".join(repr(float(x)) for x in row) + "\n" for row in c2w)


def query_offsets_to_references(layout: Layout) -> tuple[np.ndarray, np.ndarray]:
    """For each query: distance (m) to the nearest reference centre, and the rotation angle
    (deg) to that reference. Returns ([M], [M])."""
    cq, cr = layout.c2w_query[:, :3, 3], layout.c2w_ref[:, :3, 3]
    if len(cq) == 0:
        return np.zeros(0), np.zeros(0)
    dist = np.linalg.norm(cq[:, None] - cr[None], axis=-1)
    near = dist.argmin(axis=1)
    rel = np.swapaxes(layout.c2w_query[:, :3, :3], -1, -2) @ layout.c2w_ref[near, :3, :3]
    return dist[np.arange(len(cq)), near], np.degrees(geometry.rotation_angle(rel))


def _readme(cfg: SyntheticConfig, layout: Layout) -> str:
    dq, aq = query_offsets_to_references(layout)
    K = layout.K
    box_lines = "".join(
        f"  box {b}: centre ({bx.center[0]:.3f}, {bx.center[1]:.3f}) m, size "
        f"{2 * bx.half[0]:.3f} x {2 * bx.half[1]:.3f} x {2 * bx.half[2]:.3f} m, "
        f"yaw {math.degrees(bx.yaw):.1f} deg\n" for b, bx in enumerate(layout.boxes))
    qstats = (f"query offsets to the nearest reference: {dq.min() * 100:.1f}-{dq.max() * 100:.1f}"
              f" cm (median {np.median(dq) * 100:.1f}), {aq.min():.1f}-{aq.max():.1f} deg "
              f"(median {np.median(aq):.1f})\n" if len(dq) else "")
    if cfg.n_rooms == 1:
        what = (f"A procedurally textured room of {cfg.room_size[0]} x {cfg.room_size[1]} x "
                f"{cfg.room_size[2]} m with {len(layout.boxes)} boxes")
    else:
        what = (f"{cfg.n_rooms} procedurally textured rooms in a row along x (widths "
                f"{', '.join(f'{w:g}' for w in cfg.widths)} m, {cfg.room_size[1]} m deep, "
                f"{cfg.room_size[2]} m high) joined by {cfg.door_width:g} m doorways, with "
                f"{len(layout.boxes)} boxes (the last {2 * (cfg.n_rooms - 1)} are the partition "
                "walls); each room has its own camera loop")
    return (
        "vrs-jax embedded synthetic scene (generated by vrs_jax.data.synthetic)\n\n"
        f"{what}, ray-cast with {cfg.supersample}x"
        f"{cfg.supersample} supersampling and mip-mapped textures. Seed {cfg.seed}.\n"
        "World frame: metres, z up, floor at z = 0, room centred on x = y = 0.\n"
        f"{box_lines}\n"
        "Layout (7Scenes):\n"
        f"  seq-01/  {cfg.total_reference} reference frames on a smooth loop (TrainSplit: "
        "sequence1)\n"
        f"  seq-02/  {cfg.total_query} query frames on a different path near it (TestSplit: "
        "sequence2)\n"
        "  frame-XXXXXX.color.png  8-bit RGB\n"
        "  frame-XXXXXX.depth.png  16-bit z-depth in millimetres, registered to the colour "
        "image (0 = invalid; none here)\n"
        "  frame-XXXXXX.pose.txt   4x4 camera-to-world, OpenCV camera axes, metres\n"
        "  intrinsics.txt          fx fy cx cy width height (COLMAP convention: pixel (j, i) "
        "has centre (j + 0.5, i + 0.5))\n\n"
        f"Intrinsics: fx = fy = {K[0, 0]:.4f}, cx = {K[0, 2]:.2f}, cy = {K[1, 2]:.2f}, "
        f"{cfg.width} x {cfg.height}.\n"
        f"{qstats}"
        f"Config: {json.dumps(config_dict(cfg))}\n"
    )


def generate(out_dir: str | Path, cfg: SyntheticConfig | None = None, overwrite: bool = False,
             progress: bool = False) -> Path:
    """Write the synthetic scene for ``cfg`` in the 7Scenes layout under ``out_dir``.

    A folder already holding the complete output of the same config is left as it is (the
    work is skipped) unless ``overwrite``; an incomplete one is resumed (frames are written
    atomically, so existing frame files are whole). A non-empty folder that is not a
    synthetic scene raises VrsError; so does one of another config unless ``overwrite``.

    Returns:
      the output folder.
    """
    cfg = SyntheticConfig() if cfg is None else cfg
    out = Path(out_dir)
    state = _prepare_out(out, cfg, overwrite)
    if state == "skip":
        return out
    world = build_world(cfg)  # first: a config that cannot be built leaves no folder behind
    fileio.check_writable(out)
    record = _config_record(cfg)
    _write_text(out / MARKER, json.dumps({**record, "complete": False}, indent=1) + "\n")
    layout = world.layout
    K = layout.K
    fx, fy, cx, cy = (repr(float(v)) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    _write_text(out / "intrinsics.txt", f"{fx} {fy} {cx} {cy} {cfg.width} {cfg.height}\n")
    _write_text(out / "TrainSplit.txt", "sequence1\n")
    _write_text(out / "TestSplit.txt", "sequence2\n")
    frames = _all_frames(cfg)
    todo = [(s, i) for s, i in frames if not all(p.is_file() for p in _frame_paths(out, s, i))]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(frames), initial=len(frames) - len(todo), unit="frame",
                   desc="rendering")
    for s, i in todo:
        c2w = (layout.c2w_ref if s == 1 else layout.c2w_query)[i]
        rgb, depth = render_frame(world, K, c2w, cfg.width, cfg.height, cfg.supersample)
        color_p, depth_p, pose_p = _frame_paths(out, s, i)
        write_image(color_p, rgb)
        write_depth(depth_p, depth)
        _write_text(pose_p, pose_text(c2w))  # last: a frame with a pose file is complete
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    _write_text(out / "README.txt", _readme(cfg, layout))
    _write_text(out / MARKER, json.dumps({**record, "complete": True}, indent=1) + "\n")
    return out
