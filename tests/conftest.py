"""Shared fixtures: the real data folder beside the checkout (tests skip cleanly without it)."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

# A suite started in the background (``cmd &`` without job control, as CI scripts are)
# inherits SIGINT ignored, and so would every program a test starts: Python then installs no
# KeyboardInterrupt handler and the ctrl-C tests (tests/test_reliability.py) sent SIGINT to
# programs that ignored it. A handler here is reset to the default in each child at exec.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def _xla_flags_for_tests() -> str:
    """XLA_FLAGS with XLA's LLVM back end at -O0, unless they name a level themselves. The
    suite's arrays are tiny, so its time is compiling (165 of 233 s in tests/test_localize.py
    at XLA's default level 3, 121 of 199 s in test_nerf_train.py + test_localize_render.py):
    at -O0 those two modules took 19% less time. The numerics tests run again at the default
    level in CI's second numeric setting (.ci/run)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_optimization_level" in flags:
        return flags
    return f"{flags} --xla_backend_optimization_level=0".strip()


os.environ["XLA_FLAGS"] = _xla_flags_for_tests()


def xla_flags_with(*extra: str) -> str:
    """The tests' XLA_FLAGS (this process's) with ``extra`` flags added, for subprocesses,
    minus any device count (a subprocess asks for its own)."""
    kept = [f for f in os.environ.get("XLA_FLAGS", "").split()
            if "xla_force_host_platform_device_count" not in f]
    return " ".join(kept + list(extra))

_DEFAULT = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
SHARED_DATA = Path(os.environ.get("VRS_SHARED_DATA", _DEFAULT)).resolve()


def _map_count_limit() -> int:
    """Half the kernel's memory-mapping limit (vm.max_map_count; 65,530 by default)."""
    try:
        return int(Path("/proc/sys/vm/max_map_count").read_text()) // 2
    except (OSError, ValueError):
        return 0


def _map_count() -> int | None:
    """This process's memory mappings now (None where /proc is not there)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return None


_MAP_LIMIT = _map_count_limit()


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """After a test module, drop JAX's compiled programs once this process holds more than
    half the kernel's memory mappings (every module where that cannot be read). Every XLA CPU
    executable holds about three mappings of its own (code, constants, data); jax's caches
    keep them all, so one pytest process running the whole suite reached 64,994 mappings
    against the kernel's vm.max_map_count of 65,530, an XLA compile then failed, and the C++
    exception's unwinding crashed and deadlocked in pycolmap's failure handler (the hang the
    README describes; tests/test_nerf_train.py alone ends with 4,444 mappings). Dropping them
    after every module instead recompiled the programs the modules share (the ``test``
    configs' localize on the session's tiny map) in each of them."""
    yield
    count = _map_count()
    if count is not None and count <= _MAP_LIMIT:
        return
    import gc

    import jax

    jax.clear_caches()
    gc.collect()


def _test_workers(cores: int, memory_bytes: int) -> int:
    """Worker processes for ``pytest -n auto``: one per core the process may use, at most
    4 and at most one per 4 GiB of memory. On two cores two workers ran the suite in 14.4
    instead of 20 minutes (the tests' XLA compiles are single-threaded; each worker builds
    the session's fixtures again); more than 4 was not measured."""
    return max(1, min(cores, 4, memory_bytes // (4 << 30)))


def pytest_xdist_auto_num_workers(config):
    """``-n auto``'s worker count (:func:`_test_workers`); PYTEST_XDIST_AUTO_NUM_WORKERS,
    when set, decides instead (pytest-xdist's own hook reads it)."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        memory = 8 << 30
    return _test_workers(cores, memory)


def shared_path(*parts: str) -> Path:
    """Path under ../shared/data, or skip the test if it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not available: {p}")
    return p


# ----------------------------------------------------------------------------- EGM (helper E)

SMALL_SYNTHETIC = dict(width=160, height=120, n_reference=24, n_query=8)
"""A small synthetic room (2 s to render): 24 references, 8 queries at 160x120."""


@pytest.fixture(scope="session")
def small_synthetic_scene(tmp_path_factory) -> Path:
    """Folder of a small synthetic scene in the 7Scenes layout (generated once per session)."""
    import dataclasses

    from vrs_jax.data import synthetic

    cfg = dataclasses.replace(synthetic.get_config("default"), **SMALL_SYNTHETIC)
    return synthetic.generate(tmp_path_factory.mktemp("small_synthetic") / "room", cfg)


STREAM_SYNTHETIC = dict(SMALL_SYNTHETIC, n_query=12, query_arc=0.063)
"""The small synthetic room with its queries as an ordered stream: 12 frames ~4.7 cm and
~3.5 deg apart along the loop (the same references, so ``tiny_map`` localizes them)."""


@pytest.fixture(scope="session")
def stream_scene(tmp_path_factory) -> Path:
    """Folder of the small synthetic room whose queries are a stream (``STREAM_SYNTHETIC``;
    its reference images are those of ``small_synthetic_scene``)."""
    import dataclasses

    from vrs_jax.data import synthetic

    cfg = dataclasses.replace(synthetic.get_config("default"), **STREAM_SYNTHETIC)
    return synthetic.generate(tmp_path_factory.mktemp("stream_synthetic") / "room", cfg)


# ----------------------------------------------------------------------------- maps (localize)


@pytest.fixture(scope="session")
def tiny_map(small_synthetic_scene, tmp_path_factory) -> Path:
    """A complete map (EGM + real-patch descriptors + tiny NeRF) of the small synthetic scene,
    test config."""
    from vrs_jax import maps
    from vrs_jax.data.readers import load_scene

    scene = load_scene("7scenes", small_synthetic_scene)
    out = tmp_path_factory.mktemp("tiny_map") / "map"
    maps.build_map(scene, out, maps.get_config("test"), progress=False, log=lambda s: None)
    return out


@pytest.fixture(scope="session")
def toy_nerf(tmp_path_factory) -> Path:
    """The toy sphere as a Blender-style NeRF dataset (transforms_train.json), read-only for
    the tests that train on it."""
    import json
    import math

    import numpy as np

    from vrs_jax import geometry
    from vrs_jax.nerf.toy import make_toy_scene

    root = tmp_path_factory.mktemp("toy_nerf")
    scene = make_toy_scene(root / "train", n_images=8, size=16, query_every=0)
    frames = []
    for i, name in enumerate(scene.names):
        R, c = geometry.pose_inverse(scene.R[i], scene.t[i])  # camera-to-world, OpenCV
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = R, c
        c2w = geometry.opengl_to_opencv_c2w(c2w)  # the same axis flip converts back
        frames.append({"file_path": f"./train/{name[:-4]}", "transform_matrix": c2w.tolist()})
    fov = 2 * math.atan(0.5 * 16 / scene.K[0, 0, 0])
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": fov,
                                                            "frames": frames}))
    return root
