"""The one error type of the project.

Every problem with user input (a missing folder, a malformed line, an unreadable image, a map
of another format version) raises :class:`VrsError` with a one-line message naming the file,
the line when there is one, and the problem. Command-line entry points catch it and print
that line instead of a traceback (see :func:`cli_main`).
"""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path


class VrsError(Exception):
    """A problem with the user's input or environment, described in one line."""

    def __init__(self, problem: str, path: str | Path | None = None, line: int | None = None):
        self.problem = problem
        self.path = None if path is None else str(path)
        self.line = line
        where = ""
        if self.path is not None:
            where = self.path + (f":{line}" if line is not None else "") + ": "
        super().__init__(where + problem)


def require_file(path: str | Path, what: str = "file") -> Path:
    """Return ``Path(path)`` if it is an existing file, else raise VrsError naming it."""
    p = Path(path)
    if not p.is_file():
        raise VrsError(f"{what} not found" if not p.exists() else f"{what} is not a file", p)
    return p


def require_dir(path: str | Path, what: str = "folder") -> Path:
    """Return ``Path(path)`` if it is an existing directory, else raise VrsError naming it."""
    p = Path(path)
    if not p.is_dir():
        raise VrsError(f"{what} not found" if not p.exists() else f"{what} is not a folder", p)
    return p


def cli_main(fn: Callable[..., int | None]) -> Callable[..., int]:
    """Decorate a CLI ``main``: a VrsError becomes one line on stderr and exit status 2."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs) -> int:
        try:
            with sigterm_stops():
                rc = fn(*args, **kwargs)
        except VrsError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        except Terminated:
            print("terminated (SIGTERM); what was saved is kept: re-run the same command to "
                  "continue", file=sys.stderr)
            if not args and not kwargs:  # the program itself (main() reads sys.argv)
                # the ``finally`` blocks have run (checkpoints closed); skip the interpreter's
                # teardown, where tensorstore's callback threads print tracebacks of their
                # closed event loop
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(128 + signal.SIGTERM)
            return 128 + signal.SIGTERM
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            return 130
        return 0 if rc is None else int(rc)

    return wrapper


class Terminated(KeyboardInterrupt):
    """SIGTERM received: unwinds like Ctrl-C (``finally`` blocks close checkpoints)."""


_DEFERRED = {"depth": 0, "pending": False}


def _stop(signum, frame) -> None:
    """SIGTERM handler: raise :class:`Terminated`, or note it while :func:`sigterm_deferred`
    holds it back."""
    if _DEFERRED["depth"]:
        _DEFERRED["pending"] = True
        return
    raise Terminated


@contextlib.contextmanager
def sigterm_deferred() -> Iterator[None]:
    """Within the block a SIGTERM waits for the block's end (a checkpoint is written whole,
    not cut by the stop); :class:`Terminated` is raised then."""
    _DEFERRED["depth"] += 1
    try:
        yield
    finally:
        _DEFERRED["depth"] -= 1
    if not _DEFERRED["depth"] and _DEFERRED["pending"]:
        _DEFERRED["pending"] = False
        raise Terminated


@contextlib.contextmanager
def sigterm_stops() -> Iterator[None]:
    """Within the block SIGTERM raises :class:`Terminated` in the main thread: a clean stop
    instead of the native stack dump of the failure handler that XLA/tensorstore install
    when loaded (so code that loads them re-arms it: nerf.train's loop)."""

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGTERM, _stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)
