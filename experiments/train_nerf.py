"""``python -m experiments.train_nerf`` from a checkout.

The command lives in :mod:`vrs_jax.cli.train_nerf` (installed as ``vrs-jax-train-nerf``).
"""

from vrs_jax.errors import program_main

main = program_main("vrs_jax.cli.train_nerf", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
