"""``python -m experiments.train_aachen`` from a checkout.

The command lives in :mod:`vrs_jax.cli.train_aachen` (installed as ``vrs-jax-train-aachen``).
"""

from vrs_jax.errors import program_main

main = program_main("vrs_jax.cli.train_aachen", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
