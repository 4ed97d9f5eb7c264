"""Generate the embedded synthetic scene (a textured room) in the 7Scenes layout.

    python -m experiments.make_synthetic --out DIR [--seed S] [--size WxH] [--n-ref N]
        [--n-query N] [--overwrite]

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

from vrs_jax.cli.common import record_run, start_run
from vrs_jax.data.synthetic import SyntheticConfig, generate, is_generated
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


def _count(minimum: int):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid count {text!r}: not an integer") from None
        if v < minimum:
            raise argparse.ArgumentTypeError(f"invalid count {v}: must be >= {minimum}")
        return v

    return parse


def build_parser() -> argparse.ArgumentParser:
    d = SyntheticConfig()
    p = argparse.ArgumentParser(
        prog="python -m experiments.make_synthetic",
        description="Ray-cast the embedded synthetic indoor scene (procedurally textured room "
                    "with boxes) from a reference and a query trajectory, and write it in the "
                    "7Scenes layout (colour PNG, 16-bit millimetre depth PNG, camera-to-world "
                    "pose.txt, TrainSplit/TestSplit, intrinsics.txt).")
    p.add_argument("--out", required=True, help="output folder (created; an existing folder "
                   "must be empty or hold a synthetic scene written by this tool)")
    p.add_argument("--seed", type=int, default=d.seed,
                   help=f"random seed of the room, boxes, textures and paths (default {d.seed})")
    p.add_argument("--size", type=_size, default=(d.width, d.height), metavar="WxH",
                   help=f"image size (default {d.width}x{d.height})")
    p.add_argument("--n-ref", type=_count(2), default=d.n_reference, metavar="N",
                   help=f"reference frames on the loop (default {d.n_reference})")
    p.add_argument("--n-query", type=_count(0), default=d.n_query, metavar="N",
                   help=f"query frames on the offset path (default {d.n_query})")
    p.add_argument("--overwrite", action="store_true",
                   help="regenerate even if DIR already holds this scene, or replace a synthetic "
                        "scene of other settings")
    p.add_argument("--verbose", action="store_true", help="debug log lines")
    return p


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    start_run(args)
    cfg = dataclasses.replace(SyntheticConfig(), seed=args.seed, width=args.size[0],
                              height=args.size[1], n_reference=args.n_ref,
                              n_query=args.n_query)
    if not args.overwrite and is_generated(args.out, cfg):
        print(f"{args.out} already holds this synthetic scene; nothing to do (--overwrite to "
              "regenerate)")
        return 0
    t0 = time.perf_counter()
    out = generate(args.out, cfg, overwrite=args.overwrite, progress=True)
    print(f"synthetic scene ({cfg.n_reference} reference + {cfg.n_query} query frames, "
          f"{cfg.width}x{cfg.height}) in {out} [{time.perf_counter() - t0:.1f} s]")
    record_run(out, args, cfg, {"total": time.perf_counter() - t0}, argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
