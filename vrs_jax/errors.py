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
        program = not args and not kwargs  # the program itself (main() reads sys.argv)
        if program and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, _interrupt)
        try:
            try:
                with sigterm_stops():
                    rc = fn(*args, **kwargs)
            except Exception as e:
                stop = _stop_in(e)  # Ctrl-C / SIGTERM raised inside a jax host callback
                if stop is None:
                    raise
                raise stop from None
        except VrsError as e:
            print(f"error: {e}", file=sys.stderr)
            return _finished(2, program)
        except Terminated:
            print("terminated (SIGTERM); what was saved is kept: re-run the same command to "
                  "continue", file=sys.stderr)
            return _stopped(128 + signal.SIGTERM, program)
        except KeyboardInterrupt:
            print("interrupted (Ctrl-C); what was saved is kept: re-run the same command to "
                  "continue", file=sys.stderr)
            return _stopped(130, program)
        return _finished(0 if rc is None else int(rc), program)

    return wrapper


def _interrupt(signum, frame) -> None:
    """SIGINT handler of a program: KeyboardInterrupt, as Python's own, except inside a
    garbage-collector callback (jax has one), where Python would print the exception as
    "ignored" and go on working: the signal is then sent again a moment later."""
    import gc

    if frame is not None and any(frame.f_code is getattr(cb, "__code__", None)
                                 for cb in gc.callbacks):
        threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGINT)).start()
        return
    raise KeyboardInterrupt


def _finished(code: int, program: bool) -> int:
    """Exit status ``code`` of a program that ran to its end: a Ctrl-C during the
    interpreter's teardown that follows (jax clears its caches at exit, which takes a
    moment) stops it with one line and status 130, not a traceback from an exit handler."""
    if program and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _interrupted_at_exit)
    return code


def _interrupted_at_exit(signum, frame) -> None:
    print("interrupted (Ctrl-C) while exiting; the command had finished", file=sys.stderr)
    _stopped(130, True)


def program_main(module: str, caller: str) -> Callable[..., int]:
    """The ``main`` of CLI module ``module``, imported for a ``python -m`` wrapper whose
    ``__name__`` is ``caller``: when that wrapper is the program, a Ctrl-C while the module
    and its libraries are imported (jax takes seconds) stops with one line and status 130,
    not a traceback through the imports."""
    import importlib

    if caller != "__main__":
        return importlib.import_module(module).main
    try:
        return importlib.import_module(module).main
    except KeyboardInterrupt:
        print("interrupted (Ctrl-C) while starting; nothing was done", file=sys.stderr)
        return _stopped(130, True)


def interrupt_while_starting_is_one_line() -> None:
    """For a package whose modules run as programs (``python -m benchmarks.NAME``): called
    from the package's ``__init__`` while ``python -m`` is still locating the module
    (``sys.argv[0] == "-m"``, Python's documented value), a Ctrl-C during the seconds the
    module's imports take (jax) ends with one line and status 130 instead of a traceback
    through the imports. Anything else, and any other use of the package (imported by a test
    or a script), is left as it was."""
    if not sys.argv or sys.argv[0] != "-m":
        return
    previous = sys.excepthook

    def hook(kind, value, tb):
        if issubclass(kind, KeyboardInterrupt):
            print("interrupted (Ctrl-C) while starting; nothing was done", file=sys.stderr)
            _stopped(130, True)
        previous(kind, value, tb)

    sys.excepthook = hook


def _stop_in(e: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt (or :class:`Terminated`) that ``e`` wraps: a signal raised
    inside a jax host callback (OpenCV's RANSAC in ``localize``) comes back as an XLA runtime
    error whose cause, or only whose message, is the interrupt."""
    seen = set()
    x: BaseException | None = e
    while x is not None and id(x) not in seen:
        seen.add(id(x))
        if isinstance(x, KeyboardInterrupt):
            return x
        x = x.__cause__ or x.__context__
    text = str(e)
    if "Terminated" in text and "vrs_jax" in text:
        return Terminated()
    if "KeyboardInterrupt" in text:
        return KeyboardInterrupt()
    return None


def _stopped(code: int, program: bool) -> int:
    """Exit status ``code`` of a clean stop. For the program itself, the ``finally`` blocks
    have run (checkpoints closed, staging folders removed): the interpreter's teardown is
    skipped, where tensorstore's callback threads print tracebacks of their closed event loop
    and pycolmap's failure handler can dump a native stack (SIGSEGV) after a Ctrl-C."""
    if program:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


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
