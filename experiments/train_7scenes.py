"""``python -m experiments.train_7scenes`` from a checkout.

The command lives in :mod:`vrs_jax.cli.train_7scenes` (installed as ``vrs-jax-train-7scenes``).
"""

from vrs_jax.errors import program_main

main = program_main("vrs_jax.cli.train_7scenes", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
