"""``python -m experiments.train_7scenes`` from a checkout.

The command lives in :mod:`vrs_jax.cli.train_7scenes` (installed as ``vrs-jax-train-7scenes``).
"""

from vrs_jax.cli.train_7scenes import main

if __name__ == "__main__":
    raise SystemExit(main())
