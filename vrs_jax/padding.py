"""Padded sizes for jitted code: one rule, so that a jitted function compiles once per size.

Variable-length arrays (keypoints, descriptors of an image) are padded to the next power of
two, at least 16: at most log2(K_max) shapes ever reach the compiler, and at most half of a
padded array is padding.
"""

from __future__ import annotations

MIN_PADDED = 16


def padded_size(n: int, minimum: int = MIN_PADDED) -> int:
    """The next power of two >= ``n``, at least ``minimum`` (a power of two)."""
    return max(minimum, 1 << max(0, int(n) - 1).bit_length())
