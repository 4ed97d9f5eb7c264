"""``python -m experiments.localize`` from a checkout.

The command lives in :mod:`vrs_jax.cli.localize` (installed as ``vrs-jax-localize``).
"""

from vrs_jax.cli.localize import main

if __name__ == "__main__":
    raise SystemExit(main())
