"""Scene division: K-means++ on camera centres, shared border images, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from vrs_jax.errors import VrsError
from vrs_jax.nerf import clusters


def _blobs(seed=0, n=30):
    rng = np.random.default_rng(seed)
    centres = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 1.0]])
    pts = np.concatenate([c + 0.5 * rng.standard_normal((n, 3)) for c in centres])
    return pts, np.repeat(np.arange(3), n), centres


def test_border_images_are_shared_and_zero_overlap_partitions():
    x = np.array([[0.0, 0, 0], [0.2, 0, 0], [-0.2, 0, 0], [10.0, 0, 0], [10.2, 0, 0],
                  [9.8, 0, 0], [5.5, 0, 0]])  # the last one is near the border
    cl = clusters.cluster_cameras(x, 2, overlap=0.7, seed=0)
    # Centres 0 and 8.875: image 6 is 3.375 from its own, 5.5 = 1.63 x 3.375 from the other.
    assert cl.membership.shape == (2, 7) and cl.centers.shape == (2, 3)
    assert cl.membership[:, 6].all()  # shared by both
    assert cl.membership[:, :6].sum() == 6  # the others belong to one cluster
    assert np.all(cl.membership[cl.primary, np.arange(7)])
    part = clusters.cluster_cameras(x, 2, overlap=0.0, seed=0)
    np.testing.assert_array_equal(part.membership.sum(0), 1)
    assert not clusters.cluster_cameras(x, 2, overlap=0.6, seed=0
                                        ).membership[:, 6].all()


def test_single_cluster_holds_everything():
    x = np.random.default_rng(0).standard_normal((5, 3))
    cl = clusters.cluster_cameras(x, 1)
    assert cl.membership.all() and np.all(cl.primary == 0)


def test_empty_cluster_is_an_error():
    x = np.zeros((6, 3))  # one distinct position, two clusters
    with pytest.raises(VrsError, match="cluster .* no reference images"):
        clusters.cluster_cameras(x, 2)


def test_more_clusters_than_images_is_an_error():
    with pytest.raises(VrsError, match="cannot make 4 clusters from 3"):
        clusters.cluster_cameras(np.eye(3), 4)


def test_assign_to_nearest_centre():
    c = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    np.testing.assert_array_equal(clusters.assign_to_clusters(np.array([[1.0, 0, 0],
                                                                         [7.0, 1, 0]]), c),
                                  [0, 1])
