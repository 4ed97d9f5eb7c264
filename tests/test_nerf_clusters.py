"""Scene division: K-means++ on camera centres, shared border images, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from vrs_jax.errors import VrsError
from vrs_jax.kmeans import kmeans
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


# ----------------------------------------------------------------------------- grid


def test_grid_shape_prefers_square_cells():
    assert clusters.grid_shape(np.array([16.0, 2.0, 0.3]), 4) == (4, 1, 1)
    assert clusters.grid_shape(np.array([4.0, 4.0, 0.0]), 4) == (2, 2, 1)
    assert clusters.grid_shape(np.array([2.0, 9.0, 0.0]), 3) == (1, 3, 1)
    assert clusters.grid_shape(np.array([0.0, 0.0, 0.0]), 1) == (1, 1, 1)
    with pytest.raises(VrsError, match="grid cells"):
        clusters.grid_shape(np.array([0.0, 0.0]), 2)  # all cameras at one point


def test_grid_partition_cells_are_equal_and_voronoi():
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 8, 500), rng.uniform(0, 8, 500), np.zeros(500)])
    centers, labels = clusters.grid_partition(pts, 4)
    # independent reference: the 2 x 2 quadrants of the bounding box
    lo, hi = pts.min(0), pts.max(0)
    mid = (lo + hi) / 2
    quad = (pts[:, 0] >= mid[0]).astype(int) * 2 + (pts[:, 1] >= mid[1]).astype(int)
    np.testing.assert_array_equal(labels, quad)
    np.testing.assert_allclose(centers[:, :2], [[lo[0] + (hi[0] - lo[0]) * fx,
                                                  lo[1] + (hi[1] - lo[1]) * fy]
                                                 for fx in (0.25, 0.75) for fy in (0.25, 0.75)])
    # the cells are the centres' Voronoi cells: queries are assigned like the images
    np.testing.assert_array_equal(clusters.assign_to_clusters(pts, centers), labels)


def test_grid_method_in_cluster_cameras_and_config():
    from vrs_jax.nerf.config import NerfConfig

    # two dense blobs at one end, one sparse point at the other: K-means splits the blobs,
    # the grid puts them in one cell (and leaves a middle cell empty -> error)
    x = np.array([[0, 0, 0], [0.1, 0, 0], [1, 0, 0], [1.1, 0, 0], [10, 0, 0.0]])
    km = clusters.cluster_cameras(x, 3, overlap=0.0)
    assert len(set(km.primary[:4].tolist())) == 2
    g = clusters.cluster_cameras(x, 2, overlap=0.0, method="grid")
    np.testing.assert_array_equal(g.primary, [0, 0, 0, 0, 1])
    with pytest.raises(VrsError, match="no reference images"):
        clusters.cluster_cameras(x, 3, method="grid")
    with pytest.raises(VrsError, match="unknown clustering method"):
        clusters.cluster_cameras(x, 2, method="voronoi")
    with pytest.raises(VrsError, match="unknown cluster method"):
        NerfConfig(cluster_method="voronoi")


def test_kmeans_best_of_is_no_worse_than_any_seeding():
    rng = np.random.default_rng(3)
    # a long blob beside three small ones: single seedings can split the long one
    pts = np.concatenate([np.column_stack([rng.uniform(-2, 2, 40), rng.normal(0, .3, 40)]),
                          *(rng.normal((c, 0), 0.3, (15, 2)) for c in (5, 8.5, 12))])
    sse = lambda c, lab: float(np.sum((pts - c[lab]) ** 2))  # noqa: E731
    best = sse(*clusters.kmeans_best_of(pts, 4, seed=0, n_init=8))
    mean = pts.mean(0)

    def single(s):  # one seeding of the project's k-means, as kmeans_best_of runs it
        c = np.asarray(kmeans(pts - mean, 4, iters=clusters.KMEANS_ITERS, seed=s),
                       np.float64) + mean
        return sse(c, np.argmin(np.sum((pts[:, None] - c[None]) ** 2, -1), 1))

    singles = [single(s) for s in range(8)]
    assert best == pytest.approx(min(singles))
    assert max(singles) > 1.5 * best  # the case is a real one: seedings differ
