"""``python -m experiments.train_cambridge`` from a checkout.

The command lives in :mod:`vrs_jax.cli.train_cambridge` (installed as ``vrs-jax-train-cambridge``).
"""

from vrs_jax.errors import program_main

main = program_main("vrs_jax.cli.train_cambridge", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
