"""Build a vrs-jax map of one 7Scenes scene from its training sequences.

    python -m experiments.train_7scenes --root ROOT --scene NAME --out DIR [--config C]

ROOT holds the scenes in Microsoft's raw layout (ROOT/NAME/seq-XX/frame-XXXXXX.color.png, ...);
the training split comes from NAME/TrainSplit.txt, the queries from TestSplit.txt. An SfM
pseudo-ground-truth pose file can replace the D-SLAM poses with --opt pgt=FILE.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from vrs_jax.cli.train import build_parser, run
from vrs_jax.errors import cli_main


def parser() -> argparse.ArgumentParser:
    p = build_parser("7scenes", description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", required=True, help="scene folder name under --root (e.g. chess)")
    return p


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    args.root = str(Path(args.root) / args.scene)
    return run(args, "7scenes", argv=argv)


if __name__ == "__main__":
    raise SystemExit(main())
