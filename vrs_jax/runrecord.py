"""Run records: what ran, on what, with which code and libraries; and the package's logging.

A run record is one JSON document written beside a run's outputs (``run.json``) so that a
result can be traced back to its command line, configuration, vrs-jax commit, library
versions and machine::

    rec = run_record(dataclasses.asdict(cfg), sys.argv, {"build_s": 12.3})
    write_run_record(out_dir, rec)      # out_dir/run.json, or run-1.json, run-2.json, ...

Nothing here fails because of the environment: a library that is not installed has version
None, a checkout that is not a git repository (or no git) gives commit None.
"""

from __future__ import annotations

import dataclasses
import datetime
import enum
import json
import logging
import os
import platform
import shlex
import subprocess
import sys
import tempfile
from collections.abc import Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

from vrs_jax import fileio
from vrs_jax.errors import VrsError

RECORD_FORMAT = "vrs-jax run record"
RECORD_VERSION = 1
RECORD_NAME = "run.json"

# (key in the record, distribution names to try in order).
LIBRARIES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("jax", ("jax",)),
    ("jaxlib", ("jaxlib",)),
    ("flax", ("flax",)),
    ("optax", ("optax",)),
    ("optimistix", ("optimistix",)),
    ("orbax-checkpoint", ("orbax-checkpoint",)),
    ("pycolmap", ("pycolmap",)),
    ("opencv", ("opencv-python-headless", "opencv-python", "opencv-contrib-python",
                "opencv-contrib-python-headless")),
    ("numpy", ("numpy",)),
)

# The vrs-jax checkout: the folder holding the vrs_jax package.
CHECKOUT = Path(__file__).resolve().parent.parent

_LOG_FORMAT = "vrs_jax: %(message)s"


def utc_now() -> str:
    """Current UTC time, ISO 8601 to the second (``2026-01-31T12:00:00+00:00``)."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def package_version(*dists: str) -> str | None:
    """Installed version of the first of ``dists`` that is installed, else None."""
    for d in dists:
        try:
            return metadata.version(d)
        except metadata.PackageNotFoundError:
            continue
    return None


def versions() -> dict[str, str | None]:
    """{library: version or None} for :data:`LIBRARIES`, plus ``python``."""
    out = {key: package_version(*dists) for key, dists in LIBRARIES}
    if out["opencv"] is None:  # a cv2 built from source has no distribution metadata
        try:
            import cv2

            out["opencv"] = str(cv2.__version__)
        except ImportError:
            pass
    out["python"] = platform.python_version()
    return out


def git_info(checkout: str | Path = CHECKOUT) -> dict[str, Any]:
    """{"commit": sha or None, "dirty": bool or None} of ``checkout``.

    None (no failure) when git is missing or ``checkout`` is not the top of a git work tree
    (an installed copy inside some other repository does not report that repository).
    """
    def git(*args: str) -> str | None:
        # --no-optional-locks: ``git status`` otherwise refreshes the index under
        # .git/index.lock, and a run killed meanwhile (kill -9 of its process group, or this
        # timeout) left the lock behind, so the user's next commit in the checkout failed
        # (seen after the test suite's kill tests)
        try:
            r = subprocess.run(["git", "--no-optional-locks", "-C", str(checkout), *args],
                               capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return r.stdout.strip() if r.returncode == 0 else None

    top = git("rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != Path(checkout).resolve():
        return {"commit": None, "dirty": None}
    status = git("status", "--porcelain", "--untracked-files=no")
    return {"commit": git("rev-parse", "HEAD"),
            "dirty": None if status is None else bool(status)}


def _proc_field(path: str, key: str) -> str | None:
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(key):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def machine() -> dict[str, Any]:
    """Host: platform, python, CPU model and counts, memory bytes, load average."""
    mem = _proc_field("/proc/meminfo", "MemTotal")
    try:
        load = list(os.getloadavg())
    except (OSError, AttributeError):
        load = None
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {"platform": platform.platform(), "python": platform.python_version(),
            "cpu": _proc_field("/proc/cpuinfo", "model name") or platform.processor() or None,
            "cpu_count": os.cpu_count(), "cpus_usable": usable,
            "memory_bytes": int(mem.split()[0]) * 1024 if mem else None,
            "load_avg_at_start": load}


def device() -> dict[str, Any]:
    """JAX backend and devices (``platform:device_kind``); None values if JAX fails."""
    try:
        import jax

        return {"backend": jax.default_backend(),
                "devices": [f"{d.platform}:{d.device_kind}" for d in jax.devices()]}
    except Exception as e:  # noqa: BLE001 - a broken accelerator setup must not stop a record
        return {"backend": None, "devices": None, "error": str(e).splitlines()[0][:200]}


def environment() -> dict[str, Any]:
    """Time, machine, device, library versions, code version and the JAX/XLA environment
    variables (the shared part of run records and benchmark JSON)."""
    return {
        "time_utc": utc_now(),
        "machine": machine(),
        "device": device(),
        "versions": versions(),
        "code": git_info(),
        "env": {k: os.environ[k] for k in ("XLA_FLAGS", "JAX_PLATFORMS", "OMP_NUM_THREADS",
                                           "CUDA_VISIBLE_DEVICES") if k in os.environ},
    }


def _plain(obj: Any) -> Any:
    """Dataclasses, paths, enums, sets, numpy values -> JSON-able values (non-finite: None)."""
    from vrs_jax.eval.metrics import json_ready

    def conv(o: Any) -> Any:
        if dataclasses.is_dataclass(o) and not isinstance(o, type):
            return {f.name: conv(getattr(o, f.name)) for f in dataclasses.fields(o)}
        if isinstance(o, Mapping):
            return {str(k): conv(v) for k, v in o.items()}
        if isinstance(o, (list, tuple, set, frozenset)):
            items = sorted(o, key=repr) if isinstance(o, (set, frozenset)) else o
            return [conv(v) for v in items]
        if isinstance(o, os.PathLike):
            return os.fspath(o)
        if isinstance(o, enum.Enum):
            return conv(o.value)
        return o

    return json_ready(conv(obj))


def run_record(config_values: Mapping[str, Any], argv: list[str],
               timings: Mapping[str, float] | None = None) -> dict[str, Any]:
    """A JSON-able record of one run.

    Args:
      config_values: the run's settings ({name: value}; dataclasses, paths, numpy values and
        enums are converted; non-finite floats become null).
      argv: the command line as a list (``sys.argv``, or a CLI's own argv).
      timings: {stage: seconds} or None.
    Returns:
      {"format", "format_version", "time_utc", "command" (shell-quoted string), "argv",
      "cwd", "config", "timings_s", "versions" ({library: version or None, python}), "code"
      ({"commit", "dirty"} of the vrs-jax checkout, None when not a git checkout),
      "machine" (platform, cpu model and counts, memory), "device" (JAX backend, devices),
      "env" (JAX/XLA/CUDA environment variables that are set)}.
    """
    argv = [str(a) for a in argv]
    return {
        "format": RECORD_FORMAT,
        "format_version": RECORD_VERSION,
        **environment(),
        "command": shlex.join(argv),
        "argv": argv,
        "cwd": os.getcwd(),
        "config": _plain(dict(config_values)),
        "timings_s": _plain(dict(timings or {})),
    }


def write_run_record(out_dir: str | Path, record: Mapping[str, Any]) -> Path:
    """Write ``record`` as strict JSON to ``out_dir/run.json``, never overwriting a file.

    If ``run.json`` exists the record goes to ``run-1.json``, else ``run-2.json``, ... (the
    first free name). The file appears complete or not at all: the JSON is written to a
    temporary file in ``out_dir`` and hard-linked to the free name (linking fails instead of
    replacing, so two concurrent writers get different names). On a file system without hard
    links the name is claimed with an exclusive create and then written.

    Returns:
      the path written.
    Raises:
      VrsError naming the folder when it cannot be written (permission, disk full); nothing
      is left behind.
    """
    try:
        return _write_record(Path(out_dir), record)
    except OSError as e:
        raise VrsError(f"cannot write the run record: {fileio.reason(e)}", out_dir) from None


def _write_record(d: Path, record: Mapping[str, Any]) -> Path:
    d.mkdir(parents=True, exist_ok=True)
    data = (json.dumps(_plain(record), indent=1, allow_nan=False, default=str) + "\n").encode()
    fd, tmp = tempfile.mkstemp(prefix=".run-", suffix=".json.tmp", dir=d)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644 & ~fileio.umask())  # mkstemp creates 0600; records are 0644
        n = 0
        while True:
            target = d / (RECORD_NAME if n == 0 else f"run-{n}.json")
            try:
                os.link(tmp, target)
                return target
            except FileExistsError:
                n += 1
            except OSError:  # no hard links here: claim the name exclusively, then write
                try:
                    with open(target, "xb") as f:
                        f.write(data)
                    return target
                except FileExistsError:
                    n += 1
    finally:
        Path(tmp).unlink(missing_ok=True)


class _Handler(logging.StreamHandler):
    """The handler :func:`setup_logging` installs (recognised so it is installed once)."""


def setup_logging(verbose: bool = False) -> logging.Logger:
    """Configure the ``vrs_jax`` logger: ``vrs_jax: message`` lines on stderr, level INFO
    (DEBUG when ``verbose``). Idempotent: calling it again only changes the level. The
    logger does not propagate to the root logger (no duplicate lines)."""
    logger = logging.getLogger("vrs_jax")
    handler = next((h for h in logger.handlers if isinstance(h, _Handler)), None)
    if handler is None:
        handler = _Handler(sys.stderr)
        handler.setFormatter(logging.Formatter(_LOG_FORMAT))
        logger.addHandler(handler)
    elif getattr(handler.stream, "closed", False):  # setStream would flush a closed stream
        handler.stream = sys.stderr
    else:
        handler.setStream(sys.stderr)  # the current stderr (it may have been replaced)
    level = logging.DEBUG if verbose else logging.INFO
    logger.setLevel(level)
    handler.setLevel(level)
    logger.propagate = False
    return logger
