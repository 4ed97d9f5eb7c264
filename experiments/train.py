"""Build a complete vrs-jax map (EGM + NeRF ILM) from any supported dataset.

    python -m experiments.train --format F --root DIR --out MAPDIR [--config C]
        [--downscale N] [--query-every N] [--steps N] [--minutes M]

The reference images (the dataset's training split, or all but every N-th frame) are mapped:
SIFT keypoints, covisible pairs matched and verified, 3D points triangulated with the known
poses (pycolmap), keypoints linked to points kept per image, VLAD global descriptors; the
baseline map also keeps the real-patch descriptors. Then one Mip-NeRF per K-means cluster of
reference cameras is trained (orbax checkpoints; re-running resumes). Everything is written
into --out only.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from experiments.common import add_scene_args, load_scene_from_args
from vrs_jax import pipeline
from vrs_jax.errors import cli_main
from vrs_jax.nerf.config import parse_overrides


def build_parser(fmt: str | None = None, default_config: str = "cpu-small",
                 description: str | None = None) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=f"python -m experiments.{'train' if fmt is None else 'train_' + fmt}",
        description=description or __doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add_scene_args(p, fmt)
    p.add_argument("--out", required=True, help="map folder to write (created; resumable)")
    p.add_argument("--config", default=default_config, choices=sorted(pipeline.CONFIGS),
                   help="named configuration of all stages")
    p.add_argument("--steps", type=int, default=None,
                   help="NeRF training steps (default: the config's)")
    p.add_argument("--minutes", type=float, default=None,
                   help="wall-clock cap on this run's NeRF training (resume continues)")
    p.add_argument("--clusters", type=int, default=None,
                   help="number of NeRF clusters (default: the config's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a NeRF config field, repeatable (e.g. patch_ray_fraction=0 "
                        "trains on whole images only, as the paper)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def run(args: argparse.Namespace, fmt: str | None = None) -> int:
    scene = load_scene_from_args(args, fmt)
    pcfg = pipeline.get_config(args.config)
    print(f"{scene.format} scene at {scene.root}: {int((~scene.is_query).sum())} reference and "
          f"{int(scene.is_query.sum())} query images")
    out = pipeline.build_map(scene, args.out, pcfg, progress=not args.quiet,
                             nerf_steps=args.steps, nerf_minutes=args.minutes,
                             n_clusters=args.clusters,
                             nerf_overrides=parse_overrides(args.set))
    meta = json.loads((Path(out) / "map.json").read_text())
    mb = meta["stats"]["map_bytes"]
    print(f"[3/3] map written to {out}: VRS map {mb['total'] / 1e6:.2f} MB "
          f"(EGM {mb['egm'] / 1e6:.2f} MB + NeRF {mb['ilm'] / 1e6:.2f} MB), baseline map "
          f"{mb['baseline_total'] / 1e6:.2f} MB")
    return 0


@cli_main
def main(argv: list[str] | None = None) -> int:
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
