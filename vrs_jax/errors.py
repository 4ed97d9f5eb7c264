"""The one error type of the project.

Every problem with user input (a missing folder, a malformed line, an unreadable image, a map
of another format version) raises :class:`VrsError` with a one-line message naming the file,
the line when there is one, and the problem. Command-line entry points catch it and print
that line instead of a traceback (see :func:`cli_main`).
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
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
            rc = fn(*args, **kwargs)
        except VrsError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            return 130
        return 0 if rc is None else int(rc)

    return wrapper
