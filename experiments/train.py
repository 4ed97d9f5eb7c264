"""``python -m experiments.train`` from a checkout.

The command lives in :mod:`vrs_jax.cli.train` (installed as ``vrs-jax-train``).
"""

from vrs_jax.cli.train import main

if __name__ == "__main__":
    raise SystemExit(main())
