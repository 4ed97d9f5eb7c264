"""``python -m experiments.localize`` from a checkout.

The command lives in :mod:`vrs_jax.cli.localize` (installed as ``vrs-jax-localize``).
"""

from vrs_jax.errors import program_main

main = program_main("vrs_jax.cli.localize", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
