"""``python -m experiments.train_nerf`` from a checkout.

The command lives in :mod:`vrs_jax.cli.train_nerf` (installed as ``vrs-jax-train-nerf``).
"""

from vrs_jax.cli.train_nerf import main

if __name__ == "__main__":
    raise SystemExit(main())
