"""``python -m experiments.evaluate`` from a checkout.

The command lives in :mod:`vrs_jax.cli.evaluate` (installed as ``vrs-jax-evaluate``).
"""

from vrs_jax.cli.evaluate import main

if __name__ == "__main__":
    raise SystemExit(main())
