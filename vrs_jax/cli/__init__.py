"""The command-line entry points (installed as ``vrs-jax-NAME`` console scripts; from a
checkout also ``python -m experiments.NAME`` or ``python -m vrs_jax.cli.NAME``). This is the top
layer: it may import every stage; no stage imports it."""
