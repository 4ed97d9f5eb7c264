"""Explicit geometric map (EGM): reference pairs, triangulation, retrieval, save/load."""
