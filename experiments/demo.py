"""``python -m experiments.demo`` from a checkout.

The command lives in :mod:`vrs_jax.cli.demo` (installed as ``vrs-jax-demo``).
"""

from vrs_jax.errors import program_main

main = program_main("vrs_jax.cli.demo", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
