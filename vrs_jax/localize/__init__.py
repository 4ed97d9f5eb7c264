"""Localization: patch rays, patch rendering, PnP seed and refinement, localize()."""
