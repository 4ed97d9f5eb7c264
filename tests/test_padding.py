"""The one padded-size rule against the three formulas it replaced."""

from __future__ import annotations

from vrs_jax.padding import padded_size


def test_padded_size_equals_the_former_formulas():
    for n in range(0, 5000):
        p = padded_size(n)
        assert p >= max(n, 16) and p & (p - 1) == 0 and (p == 16 or p < 2 * n)
        # features.extract._bucket and egm.retrieval._bucket
        assert p == max(16, 1 << max(0, int(n) - 1).bit_length())
        # egm.triangulate.pad_size([n])
        m = max([16, n])
        assert p == 1 << (m - 1).bit_length()
    assert padded_size(3, minimum=4) == 4 and padded_size(5, minimum=4) == 8
