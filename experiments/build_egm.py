"""``python -m experiments.build_egm`` from a checkout.

The command lives in :mod:`vrs_jax.cli.build_egm` (installed as ``vrs-jax-build-egm``).
"""

from vrs_jax.cli.build_egm import main

if __name__ == "__main__":
    raise SystemExit(main())
