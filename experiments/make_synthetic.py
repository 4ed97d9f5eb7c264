"""``python -m experiments.make_synthetic`` from a checkout.

The command lives in :mod:`vrs_jax.cli.make_synthetic` (installed as ``vrs-jax-make-synthetic``).
"""

from vrs_jax.cli.make_synthetic import main

if __name__ == "__main__":
    raise SystemExit(main())
