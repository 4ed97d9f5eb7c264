"""``python -m experiments.train`` from a checkout.

The command lives in :mod:`vrs_jax.cli.train` (installed as ``vrs-jax-train``).
"""

from vrs_jax.errors import program_main

main = program_main("vrs_jax.cli.train", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
