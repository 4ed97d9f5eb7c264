"""Benchmarks: python -m benchmarks.NAME --help; each prints a table and writes JSON."""
