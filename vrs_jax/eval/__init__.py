"""Evaluation: pose errors, recall tables, results files."""
