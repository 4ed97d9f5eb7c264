"""Build a vrs-jax map of Aachen Day-Night: database images of the NVM model, 16 clusters.

    python -m experiments.train_aachen --root ROOT --out DIR [--config C] [--clusters 16]

ROOT holds 3D-models/aachen_cvpr2018_db.nvm, images_upright/ and queries/ (official layout).
The paper divides Aachen into 16 NeRF clusters; that is the default here. The city is
unbounded: the NeRF contracts the far field by default (``--set contraction=false`` turns it
off).
"""

from __future__ import annotations

import argparse

from vrs_jax.cli.train import build_parser, run
from vrs_jax.errors import cli_main


def parser() -> argparse.ArgumentParser:
    p = build_parser("aachen", default_config="paper", description=__doc__.split("\n\n")[0])
    p.set_defaults(clusters=16)
    p.set_defaults(set=["contraction=true"])  # a city: unbounded (a later --set wins)
    return p


@cli_main
def main(argv: list[str] | None = None) -> int:
    return run(parser().parse_args(argv), "aachen", argv=argv)


if __name__ == "__main__":
    raise SystemExit(main())
