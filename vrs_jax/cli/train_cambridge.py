"""Build a vrs-jax map of one Cambridge Landmarks scene from dataset_train.txt.

    python -m experiments.train_cambridge --root ROOT --scene NAME --out DIR [--config C]

ROOT/NAME holds dataset_train.txt, dataset_test.txt, the sequence folders and
reconstruction.nvm (intrinsics). The scenes are outdoor and unbounded (facades, streets,
sky): the NeRF contracts the far field by default (``--set contraction=false`` turns it off).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from vrs_jax.cli.train import build_parser, run
from vrs_jax.errors import cli_main


def parser() -> argparse.ArgumentParser:
    p = build_parser("cambridge", description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", required=True, help="scene folder under --root (e.g. ShopFacade)")
    p.set_defaults(set=["contraction=true"])  # outdoor: unbounded (a later --set wins)
    return p


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    args.root = str(Path(args.root) / args.scene)
    return run(args, "cambridge", argv=argv)


if __name__ == "__main__":
    raise SystemExit(main())
