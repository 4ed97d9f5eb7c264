"""Generate the embedded synthetic scene (a textured room) in the 7Scenes layout.

    python -m experiments.make_synthetic --out DIR [--config default|test|rooms4]
        [--rooms N] [--seed S] [--size WxH] [--n-ref N] [--n-query N] [--query-arc F]
        [--overwrite]

``--config rooms4`` is the large scene (four rooms in a row joined by doorways, one camera
loop per room: the multi-cluster benchmark's scene); ``--rooms N`` puts N equal rooms in a row
(with ``--config rooms4``: N rooms, the first 8 m wide, the others 3.5 m). ``--query-arc F``
makes the queries an ordered stream (a robot's video, for ``experiments.localize
--sequence`` and ``benchmarks.track``): evenly spaced along the fraction F of the loop.

Writes DIR/seq-01 (reference frames), DIR/seq-02 (query frames), TrainSplit.txt,
TestSplit.txt, intrinsics.txt and README.txt; load it back with
``vrs_jax.data.readers.load_scene("7scenes", DIR)``. Re-running with the same settings on a
complete output does nothing; an interrupted run resumes.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import time

from vrs_jax.cli.common import count_at_least, prog, record_run, start_run
from vrs_jax.data.synthetic import CONFIGS, generate, get_config, is_generated
from vrs_jax.errors import cli_main


def _size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"invalid size {text!r}: expected WxH, e.g. 320x240")
    w, h = int(m.group(1)), int(m.group(2))
    if w < 8 or h < 8 or w > 4096 or h > 4096:
        raise argparse.ArgumentTypeError(f"invalid size {text!r}: width and height must be "
                                         "between 8 and 4096")
    return w, h


def build_parser() -> argparse.ArgumentParser:
    d = get_config("default")
    p = argparse.ArgumentParser(
        prog=prog("experiments.make_synthetic"),
        description="Ray-cast the embedded synthetic indoor scene (procedurally textured room "
                    "with boxes) from a reference and a query trajectory, and write it in the "
                    "7Scenes layout (colour PNG, 16-bit millimetre depth PNG, camera-to-world "
                    "pose.txt, TrainSplit/TestSplit, intrinsics.txt).")
    p.add_argument("--out", required=True, help="output folder (created; an existing folder "
                   "must be empty or hold a synthetic scene written by this tool)")
    p.add_argument("--config", default="default", choices=sorted(CONFIGS),
                   help="named scene config the other options override (default: the room; "
                        "rooms4: the large four-room scene at 160x120)")
    p.add_argument("--rooms", type=count_at_least(1), default=None, metavar="N",
                   help="rooms in a row joined by doorways, each with its own camera loop "
                        "(default: the config's; --n-ref/--n-query then count the frames "
                        "of a 5 m room's loop)")
    p.add_argument("--seed", type=int, default=d.seed,
                   help=f"random seed of the room, boxes, textures and paths (default {d.seed})")
    p.add_argument("--size", type=_size, default=None, metavar="WxH",
                   help=f"image size (default: the config's, {d.width}x{d.height} for the room)")
    p.add_argument("--n-ref", type=count_at_least(2), default=None, metavar="N",
                   help=f"reference frames on the loop (default: the config's, "
                        f"{d.n_reference} for the room)")
    p.add_argument("--n-query", type=count_at_least(0), default=None, metavar="N",
                   help=f"query frames on the offset path (default: the config's, {d.n_query} "
                        "for the room)")
    p.add_argument("--query-arc", type=float, default=None, metavar="F",
                   help="queries as an ordered stream evenly spaced along this fraction of "
                        "the camera loop, in (0, 1] (a video for tracking; default: spread "
                        "over the whole loop)")
    p.add_argument("--overwrite", action="store_true",
                   help="regenerate even if DIR already holds this scene, or replace a synthetic "
                        "scene of other settings")
    p.add_argument("--verbose", action="store_true", help="debug log lines")
    return p


def config_of(args: argparse.Namespace):
    """The SyntheticConfig of the parsed arguments: the named config with the overrides."""
    base = get_config(args.config)
    over = {"seed": args.seed}
    if args.size is not None:
        over.update(width=args.size[0], height=args.size[1])
    if args.n_ref is not None:
        over["n_reference"] = args.n_ref
    if args.n_query is not None:
        over["n_query"] = args.n_query
    if args.query_arc is not None:
        over["query_arc"] = args.query_arc
    if args.rooms is not None and args.rooms != base.n_rooms:
        widths = ()
        if base.room_widths:  # keep the config's pattern: first room as given, others as
            widths = (base.room_widths[0],) + (base.room_widths[-1],) * (args.rooms - 1)
            widths = widths[:args.rooms]
        over.update(n_rooms=args.rooms, room_widths=widths)
    return dataclasses.replace(base, **over)


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    start_run(args)
    cfg = config_of(args)
    if not args.overwrite and is_generated(args.out, cfg):
        print(f"{args.out} already holds this synthetic scene; nothing to do (--overwrite to "
              "regenerate)")
        return 0
    t0 = time.perf_counter()
    out = generate(args.out, cfg, overwrite=args.overwrite, progress=True)
    rooms = f"{cfg.n_rooms} rooms, " if cfg.n_rooms > 1 else ""
    print(f"synthetic scene ({rooms}{cfg.total_reference} reference + {cfg.total_query} query "
          f"frames, {cfg.width}x{cfg.height}) in {out} [{time.perf_counter() - t0:.1f} s]")
    record_run(out, args, cfg, {"total": time.perf_counter() - t0}, argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
