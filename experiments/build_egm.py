"""``python -m experiments.build_egm`` from a checkout.

The command lives in :mod:`vrs_jax.cli.build_egm` (installed as ``vrs-jax-build-egm``).
"""

from vrs_jax.errors import program_main

main = program_main("vrs_jax.cli.build_egm", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
