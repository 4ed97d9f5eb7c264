"""Command-line pieces shared by the experiments: dataset arguments and scene loading."""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Callable
from pathlib import Path

from vrs_jax.errors import VrsError


def prog(module: str) -> str:
    """The program name of usage lines: the console script's own name when run as one
    (``vrs-jax-localize``), else ``python -m MODULE`` (``experiments.localize``)."""
    script = Path(sys.argv[0]).name
    return script if script.startswith("vrs-jax") else f"python -m {module}"


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows ``(default: X)`` only where there is a default worth naming: not for None,
    False or an empty list, and not where the help text already says what the default is."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text or action.default in (None, False, [], argparse.SUPPRESS):
            return text
        return super()._get_help_string(action)


class RawHelpFormatter(HelpFormatter, argparse.RawDescriptionHelpFormatter):
    """:class:`HelpFormatter` that keeps the description's line breaks (usage examples)."""


def _parse_value(text: str):
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def count_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse ``type``: an integer >= ``minimum`` (else argparse's one error line)."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid count {text!r}: not an integer") from None
        if v < minimum:
            raise argparse.ArgumentTypeError(f"invalid count {v}: must be >= {minimum}")
        return v

    return parse


def positive_float(what: str = "value") -> Callable[[str], float]:
    """An argparse ``type``: a finite number > 0 (``--minutes nan``, ``--minutes -1``,
    ``--near inf`` are refused at parsing, not run as a no-op or an odd error later)."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid {what} {text!r}: not a number") from None
        if not math.isfinite(v) or v <= 0:
            raise argparse.ArgumentTypeError(f"invalid {what} {text!r}: must be a finite "
                                             "number > 0")
        return v

    return parse


def parse_opts(items: list[str]) -> dict:
    """``["key=value", ...]`` -> {key: int | float | bool | str}."""
    opts = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise VrsError(f"--opt expects KEY=VALUE, got {item!r}")
        opts[key.strip().replace("-", "_")] = _parse_value(value.strip())
    return opts


def add_scene_args(p: argparse.ArgumentParser, fmt: str | None = None,
                   required: bool = True) -> None:
    """--format (unless fixed), --root, --query-every, --downscale, --opt."""
    if fmt is None:
        p.add_argument("--format", required=required, dest="fmt",
                       help="dataset format: 7scenes, cambridge, aachen, nerf, llff, colmap, "
                            "or images (a folder of unposed photos: SfM first)")
    p.add_argument("--root", required=required,
                   help="dataset root folder (its official layout)")
    p.add_argument("--query-every", type=count_at_least(0), default=None, metavar="N",
                   help="hold out every N-th image as a query (formats without a split)")
    p.add_argument("--downscale", type=count_at_least(1), default=None, metavar="N",
                   help="read images downscaled by N (intrinsics scaled to match)")
    p.add_argument("--opt", action="append", default=[], metavar="KEY=VALUE",
                   help="further reader option, repeatable (e.g. --opt pgt=PATH for 7Scenes)")


def scene_opts(args: argparse.Namespace) -> dict:
    """Reader options from the parsed --query-every/--downscale/--opt arguments."""
    opts = parse_opts(args.opt)
    if args.query_every is not None:
        opts["query_every"] = args.query_every
    if args.downscale is not None:
        opts["downscale"] = args.downscale
    return opts


def load_scene_from_args(args: argparse.Namespace, fmt: str | None = None,
                         sfm_dir: Path | None = None):
    """The Scene named by the parsed arguments (VrsError for bad input).

    ``--format images`` (a folder of unposed photos) runs pycolmap's incremental SfM first,
    with its work files in ``sfm_dir``; every N-th photo is then held out with --query-every.
    """
    from vrs_jax.data.readers import FORMATS, load_scene

    fmt = fmt or args.fmt
    if fmt not in (*FORMATS, "images"):
        raise VrsError(f"unknown dataset format {fmt!r} (known: {', '.join(FORMATS)}, images)")
    if fmt == "images":
        from vrs_jax.egm import sfm

        if sfm_dir is None:
            raise VrsError("--format images needs an output folder for its SfM work files")
        if args.downscale:
            raise VrsError("--downscale does not apply to --format images")
        scene = sfm.scene_from_images(args.root, sfm_dir,
                                      verbose=getattr(args, "verbose", False))
        import dataclasses

        scene = dataclasses.replace(scene, format="images")  # what a map records
        if args.query_every:
            from vrs_jax.data.readers._common import query_mask

            scene = dataclasses.replace(scene, is_query=query_mask(scene.names,
                                                                   args.query_every))
        return scene
    return load_scene(fmt, args.root, **scene_opts(args))


def start_run(args: argparse.Namespace) -> None:
    """Configure the ``vrs_jax`` logger (DEBUG with ``--verbose``)."""
    from vrs_jax.runrecord import setup_logging

    setup_logging(bool(getattr(args, "verbose", False)))


def record_run(out_dir: str | Path, args: argparse.Namespace, config=None,
               timings: dict | None = None, argv: list[str] | None = None) -> Path | None:
    """Write the run record (``out_dir/run.json``, never overwriting an earlier one). A record
    that cannot be written (disk full) is a warning: the run's own results are complete.

    Args:
      args: the parsed arguments (recorded under ``args``).
      config: the resolved config dataclass (recorded under ``config``), or None.
      timings: {stage: seconds}.
      argv: the command line as passed to ``main`` (None: ``sys.argv``).
    """
    import dataclasses
    import sys

    from vrs_jax.configio import to_dict
    from vrs_jax.runrecord import run_record, write_run_record

    values: dict = {"args": vars(args)}
    if config is not None:
        values["config"] = to_dict(config) if dataclasses.is_dataclass(config) else config
    cmd = sys.argv if argv is None else [sys.argv[0], *argv]
    try:
        return write_run_record(out_dir, run_record(values, cmd, timings))
    except VrsError as e:
        logging.getLogger("vrs_jax").warning("%s", e)
        return None


def add_distributed_args(p: argparse.ArgumentParser) -> None:
    """--coordinator / --num-processes / --process-id / --local-devices (jax.distributed)."""
    g = p.add_argument_group(
        "multi-process training (jax.distributed; one process per host or per GPU)")
    g.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="address of process 0's coordinator service, the same for every "
                        "process (default: $JAX_COORDINATOR_ADDRESS)")
    g.add_argument("--num-processes", type=count_at_least(1), default=None, metavar="N",
                   help="number of processes (default: $JAX_NUM_PROCESSES, else 1: a "
                        "single-process run)")
    g.add_argument("--process-id", type=count_at_least(0), default=None, metavar="I",
                   help="this process's index 0..N-1 (default: $JAX_PROCESS_ID)")
    g.add_argument("--local-devices", default=None, metavar="IDS",
                   help="comma-separated local device ids this process uses (e.g. 0 for one "
                        "GPU per process; default: all visible devices)")


def init_distributed(args: argparse.Namespace) -> bool:
    """Start jax.distributed from the parsed flags (before any JAX computation); True when
    this is a multi-process run."""
    from vrs_jax.nerf import distributed

    ids = None
    if args.local_devices:
        try:
            ids = [int(x) for x in args.local_devices.split(",")]
        except ValueError:
            raise VrsError(f"--local-devices {args.local_devices!r}: expected comma-separated "
                           "integers") from None
    return distributed.initialize(args.coordinator, args.num_processes, args.process_id, ids)
