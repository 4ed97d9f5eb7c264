"""Benchmarks: python -m benchmarks.NAME --help; each prints a table and writes JSON."""

from vrs_jax.errors import interrupt_while_starting_is_one_line

interrupt_while_starting_is_one_line()
