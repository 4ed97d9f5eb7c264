"""``python -m experiments.train_aachen`` from a checkout.

The command lives in :mod:`vrs_jax.cli.train_aachen` (installed as ``vrs-jax-train-aachen``).
"""

from vrs_jax.cli.train_aachen import main

if __name__ == "__main__":
    raise SystemExit(main())
