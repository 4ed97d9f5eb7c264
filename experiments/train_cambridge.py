"""``python -m experiments.train_cambridge`` from a checkout.

The command lives in :mod:`vrs_jax.cli.train_cambridge` (installed as ``vrs-jax-train-cambridge``).
"""

from vrs_jax.cli.train_cambridge import main

if __name__ == "__main__":
    raise SystemExit(main())
