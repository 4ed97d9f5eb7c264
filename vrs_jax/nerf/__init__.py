"""Implicit learning map (ILM): Mip-NeRF per cluster of reference cameras."""
