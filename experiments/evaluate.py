"""``python -m experiments.evaluate`` from a checkout.

The command lives in :mod:`vrs_jax.cli.evaluate` (installed as ``vrs-jax-evaluate``).
"""

from vrs_jax.errors import program_main

main = program_main("vrs_jax.cli.evaluate", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
