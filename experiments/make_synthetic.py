"""``python -m experiments.make_synthetic`` from a checkout.

The command lives in :mod:`vrs_jax.cli.make_synthetic` (installed as ``vrs-jax-make-synthetic``).
"""

from vrs_jax.errors import program_main

main = program_main("vrs_jax.cli.make_synthetic", __name__)

if __name__ == "__main__":
    raise SystemExit(main())
