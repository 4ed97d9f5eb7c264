"""localize.render: the patch renderer's strided sampling and the guided pass's selection,
against the full renderer on the tests' tiny map."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from vrs_jax import localize, maps
from vrs_jax.errors import VrsError
from vrs_jax.localize import stages
from vrs_jax.localize.render import (
    first_pass_keypoints,
    nerf_evals_per_ray,
    rays_per_patch,
    render_at_pose,
    render_points_at_pose,
    render_reference,
    resample_matrix,
)


@pytest.fixture(scope="module")
def tiny(tiny_map):
    return maps.load_map(tiny_map)


@pytest.mark.parametrize("n_from,n_to", [(8, 15), (5, 9), (3, 15), (4, 4), (6, 15), (2, 8),
                                          (15, 6)])
def test_resample_matrix_is_exact_on_linear_ramps(n_from, n_to):
    W = resample_matrix(n_from, n_to)
    assert W.shape == (n_to, n_from)
    np.testing.assert_allclose(W.sum(1), 1.0, atol=1e-6)
    assert W.min() >= 0.0
    # a target on a source sample copies it (stride grids: every stride-th target)
    pos = np.arange(n_to) * (n_from - 1) / (n_to - 1)
    on = np.isclose(pos, np.round(pos))
    np.testing.assert_allclose(W[on], np.eye(n_from)[np.round(pos[on]).astype(int)],
                               atol=1e-6)
    ramp = 3.0 + 0.5 * np.arange(n_from)
    np.testing.assert_allclose(W @ ramp, 3.0 + 0.5 * pos, atol=1e-5)


@pytest.mark.parametrize("probes", [False, True])
def test_sparse_render_grid_keeps_its_samples_and_approximates_the_rest(tiny, probes):
    """render_grid (P + 1) / 2 renders every second sample of the P x P patches (those equal
    the full render's) and interpolates the rest; one ray fewer per side falls between the
    samples and still approximates the full render."""
    cfg1 = localize.get_config("test")
    if probes:
        cfg1 = dataclasses.replace(cfg1, probe_grid=2)
    patches = tiny.config.features.patches
    P = patches.size
    full = np.asarray(render_reference(tiny, jnp.int32(0), patches, cfg1))
    mask = np.asarray(tiny.egm.kp_mask[0])
    for side, min_psnr in (((P + 1) // 2, 25.0), ((P + 1) // 2 - 1, 22.0)):
        cfg2 = dataclasses.replace(cfg1, render_grid=side)
        part = np.asarray(render_reference(tiny, jnp.int32(0), patches, cfg2))[mask]
        if side == (P + 1) // 2:
            np.testing.assert_allclose(part[:, ::2, ::2], full[mask][:, ::2, ::2], atol=2e-4)
        mse = np.mean((part - full[mask]) ** 2)
        assert 10 * np.log10(1.0 / mse) > min_psnr  # the interpolated samples are close
        assert rays_per_patch(tiny, cfg2) == side * side
    for bad in (1, P + 1):
        with pytest.raises(VrsError, match="render_grid"):
            cfg = dataclasses.replace(cfg1, render_grid=bad)
            render_reference(tiny, jnp.int32(0), patches, cfg)


def test_patch_grid_side_spreads_the_full_grid_evenly():
    from vrs_jax.features.patches import PatchConfig, patch_grid

    kp = np.array([[40.3, 22.7, 2.5, 0.6]], np.float32)
    cfg = PatchConfig(size=15)
    full, foot = patch_grid(kp, cfg)
    for side in (2, 6, 8, 15):
        sub, foot_s = patch_grid(kp, cfg, side)
        assert sub.shape == (1, side, side, 2)
        np.testing.assert_array_equal(foot_s, foot)  # the full grid's spacing: same cones
        # an affine grid: the even subgrid is the bilinear resampling of the full one
        W = resample_matrix(15, side)
        want = np.einsum("ia,kabc,jb->kijc", W, full, W)
        np.testing.assert_allclose(sub, want, atol=1e-4)
    with pytest.raises(VrsError, match="canonical"):
        patch_grid(kp, PatchConfig(size=15, mode="literal"), 8)


def test_render_at_pose_renders_only_the_kept_keypoints(tiny):
    cfg = localize.get_config("test")
    patches = tiny.config.features.patches
    K, R, t = tiny.egm.K[1], tiny.egm.R[1], tiny.egm.t[1]
    g_all, kp_all, v_all = render_at_pose(tiny, jnp.int32(0), K, R, t, patches, cfg)
    rng = np.random.default_rng(0)
    keep = rng.random(tiny.egm.kp_mask.shape[1]) < 0.5
    g, kp, v = render_at_pose(tiny, jnp.int32(0), K, R, t, patches, cfg, jnp.asarray(keep))
    v, v_all = np.asarray(v), np.asarray(v_all)
    np.testing.assert_array_equal(v, v_all & keep)
    assert v.sum() > 0
    np.testing.assert_allclose(np.asarray(g)[v], np.asarray(g_all)[v], atol=2e-4)
    assert np.all(np.asarray(g)[~v] == 0)


@pytest.mark.parametrize("clusters", [1, 2])
def test_flat_render_at_pose_equals_the_per_image_render(tiny, clusters):
    """The guided pass renders its kept keypoints of several reference images as one flat
    list (one chunked render per cluster): each row equals the same keypoint rendered by
    its own image's :func:`render_at_pose`, with its own cluster's NeRF (two clusters: the
    second field's weights scaled, images alternating, so a row rendered by the wrong
    cluster differs)."""
    import jax

    m = tiny
    if clusters == 2:
        fields = jax.tree.map(lambda x: jnp.concatenate([x, 1.3 * x]), m.ilm.fields)
        cl = jnp.arange(len(m.names), dtype=jnp.int32) % 2
        m = m.replace(ilm=m.ilm.replace(fields=fields, image_cluster=cl))
    cfg = dataclasses.replace(localize.get_config("cpu-small"), render_chunk=256)
    patches = m.config.features.patches
    K, R, t = m.egm.K[2], m.egm.R[2], m.egm.t[2]
    k_max = m.egm.kp_mask.shape[1]
    rng = np.random.default_rng(1)
    imgs = np.array([0, 1, 3])
    keep = (rng.random((3, k_max)) < 0.3) & np.asarray(m.egm.kp_mask[imgs])
    rows = np.flatnonzero(keep.reshape(-1))
    img, slot = imgs[rows // k_max], rows % k_max
    g, v = render_points_at_pose(m, jnp.asarray(img), jnp.asarray(slot),
                                 jnp.ones(len(rows), bool), K, R, t, patches, cfg)
    g, v = np.asarray(g), np.asarray(v)
    assert v.sum() > 10
    for a, i in enumerate(imgs):
        want, _, ok = render_at_pose(m, jnp.int32(i), K, R, t, patches, cfg,
                                     jnp.asarray(keep[a]))
        sel = img == i
        np.testing.assert_array_equal(v[sel], np.asarray(ok)[slot[sel]])
        np.testing.assert_allclose(g[sel], np.asarray(want)[slot[sel]], atol=2e-4)
    assert np.all(g[~v] == 0)
    if clusters == 2:  # the other cluster's field renders these rows differently
        other = m.replace(ilm=m.ilm.replace(image_cluster=1 - m.ilm.image_cluster))
        g2, _ = render_points_at_pose(other, jnp.asarray(img), jnp.asarray(slot),
                                      jnp.ones(len(rows), bool), K, R, t, patches, cfg)
        assert np.max(np.abs(np.asarray(g2)[v] - g[v])) > 1e-2


def test_probes_at_every_sample_render_as_every_ray_searching(tiny):
    """With a probe at every sample of the patch grid (probe_grid = P) each ray resamples
    from its own first pass: the probed renderer gives the plain depth-guided patches."""
    patches = tiny.config.features.patches
    cfg = localize.get_config("test")
    every = dataclasses.replace(cfg, probe_grid=patches.size)
    i = int(np.argmax(np.asarray(tiny.egm.kp_mask).sum(1)))
    mask = np.asarray(tiny.egm.kp_mask[i])
    want = np.asarray(render_reference(tiny, jnp.int32(i), patches, cfg))[mask]
    got = np.asarray(render_reference(tiny, jnp.int32(i), patches, every))[mask]
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_a_few_probes_render_close_to_every_ray_searching(tiny):
    """3 x 3 probes per patch: the rays resample from their neighbours' weights; the
    patches stay close to the plain depth-guided ones, and every row, rendered or not, is
    finite (chunks of probes and of rays skipped alike; the tests' 4096-ray chunks are not
    a whole number of 81-ray patches)."""
    patches = tiny.config.features.patches
    cfg = localize.get_config("test")
    probed = dataclasses.replace(cfg, probe_grid=3)
    i = int(np.argmax(np.asarray(tiny.egm.kp_mask).sum(1)))
    mask = np.asarray(tiny.egm.kp_mask[i])
    want = np.asarray(render_reference(tiny, jnp.int32(i), patches, cfg))[mask]
    every = np.asarray(render_reference(tiny, jnp.int32(i), patches, probed))
    assert np.all(np.isfinite(every))
    got = every[mask]
    psnr = -10 * np.log10(np.mean((got - want) ** 2))
    assert psnr > 25.0, psnr


def test_probe_evaluations_and_grids_are_checked(tiny):
    cfg = localize.get_config("test")
    patches = tiny.config.features.patches  # P = 9
    c = dataclasses.replace(cfg, probe_grid=3)
    per_patch = 9 * cfg.narrow_samples + patches.size ** 2 * cfg.narrow_fine
    assert nerf_evals_per_ray(tiny, c) * rays_per_patch(tiny, c) == pytest.approx(per_patch)
    with pytest.raises(VrsError, match="probe_grid"):
        render_reference(tiny, jnp.int32(0), patches,
                         dataclasses.replace(cfg, probe_grid=patches.size + 1))
    with pytest.raises(VrsError, match="probe_grid"):
        render_reference(tiny, jnp.int32(0), patches,
                         dataclasses.replace(cfg, probe_grid=3, depth_guided=False))
    with pytest.raises(VrsError, match="probe_grid"):
        render_reference(tiny, jnp.int32(0), patches,
                         dataclasses.replace(cfg, probe_grid=3, narrow_fine=0))
    with pytest.raises(VrsError):
        localize.get_config("test", probe_grid=1)


def test_first_pass_budget_keeps_the_longest_tracks_and_renders_them_alike(tiny):
    """first_pass_keypoints keeps B keypoints per image, those whose 3D points are seen in
    the most reference images (numpy count); their patches are the ones every keypoint's
    render gives, and no other row is rendered."""
    egm = tiny.egm
    pid, mask = np.asarray(egm.point_idx), np.asarray(egm.kp_mask)
    track = np.bincount(pid[mask & (pid >= 0)], minlength=np.asarray(egm.points3d).shape[0])
    budget = 20
    cfg = localize.get_config("test", first_pass_keypoints=budget)
    idx = jnp.arange(mask.shape[0])
    keep = np.asarray(first_pass_keypoints(tiny, idx, cfg))
    for i in range(mask.shape[0]):
        valid = mask[i] & (pid[i] >= 0)
        assert keep[i].sum() == min(budget, mask[i].sum())
        assert not (keep[i] & ~mask[i]).any()
        if valid.sum() > budget:
            kept, dropped = track[pid[i][keep[i]]], track[pid[i][valid & ~keep[i]]]
            assert kept.min() >= dropped.max()
    np.testing.assert_array_equal(
        np.asarray(first_pass_keypoints(tiny, idx, localize.get_config("test"))), mask)
    i = int(np.argmax(mask.sum(1)))
    patches = tiny.config.features.patches
    full = np.asarray(render_reference(tiny, jnp.int32(i), patches, localize.get_config("test")))
    part = np.asarray(render_reference(tiny, jnp.int32(i), patches, cfg))
    np.testing.assert_allclose(part[keep[i]], full[keep[i]], atol=1e-5)
    assert np.all(part[~keep[i]] == 0)


def test_unique_points_render_each_map_point_once_a_pass(tiny):
    """With first_pass_unique_points a candidate drops the keypoints whose 3D points an
    earlier candidate's selection holds (a numpy walk over the candidates in order); the
    points the pass can match are the same as without it, each held once; the render
    stage renders exactly the kept rows."""
    pid = np.asarray(tiny.egm.point_idx)
    idx = jnp.asarray([3, 0, 1, 2], jnp.int32)
    cfg = localize.get_config("test", first_pass_keypoints=20)
    uniq = dataclasses.replace(cfg, first_pass_unique_points=True)
    every = np.asarray(first_pass_keypoints(tiny, idx, cfg))
    keep = np.asarray(first_pass_keypoints(tiny, idx, uniq))
    seen: set[int] = set()
    for c, i in enumerate(np.asarray(idx)):
        want = every[c].copy()
        for s in np.flatnonzero(every[c]):
            if pid[i, s] >= 0 and int(pid[i, s]) in seen:
                want[s] = False
            seen.add(int(pid[i, s]))
        np.testing.assert_array_equal(keep[c], want)
    assert keep[0].tolist() == every[0].tolist() and keep.sum() < every.sum()
    held = lambda k: {int(pid[i, s]) for c, i in enumerate(np.asarray(idx))  # noqa: E731
                      for s in np.flatnonzero(k[c]) if pid[i, s] >= 0}
    assert held(keep) == held(every)
    gray = np.asarray(stages.render(tiny, None, uniq, {"idx": idx})["gray"])
    assert np.all(gray[~keep] == 0) and np.all(np.abs(gray[keep]).sum(axis=(1, 2)) > 0)
    # a single image (render_reference, the cache's unit) keeps its own selection
    one = np.asarray(first_pass_keypoints(tiny, idx[1], uniq))
    np.testing.assert_array_equal(one, every[1])


def test_unique_points_keeps_keypoints_without_a_point():
    """unique_points drops repeated map points, earlier candidates first, and never a
    keypoint without one (pid -1), however many there are."""
    from vrs_jax.localize.render import unique_points

    pid = jnp.asarray([[4, -1, 7, -1], [7, 4, 9, -1]])
    mask = jnp.asarray([[True, True, True, False], [True, True, True, True]])
    got = np.asarray(unique_points(mask, pid))
    np.testing.assert_array_equal(got, [[True, True, True, False], [False, False, True, True]])


@pytest.mark.parametrize("cell_step", [1, 1000])
def test_spread_tracks_fills_the_budget_cell_by_cell(cell_step):
    """Every cell's longest track first, then every cell's second, ...; within a round the
    longest first; entries not kept or without a point never chosen (numpy reference);
    cell ids may exceed the entries' count (a grid of more cells than keypoints)."""
    from vrs_jax.localize.render import spread_tracks

    rng = np.random.default_rng(3)
    n, n_pts = 60, 40
    keep = rng.random(n) < 0.8
    pid = np.where(rng.random(n) < 0.9, rng.integers(0, n_pts, n), -1)
    track = rng.integers(2, 30, n_pts)
    cell = rng.integers(0, 5, n) * cell_step
    score = np.where(keep & (pid >= 0), track[np.maximum(pid, 0)], -1)
    rank = np.full(n, n)
    for c in set(cell):
        members = [i for i in np.argsort(-score, kind="stable") if cell[i] == c and score[i] >= 0]
        rank[members] = np.arange(len(members))
    want_order = sorted(np.flatnonzero(score >= 0), key=lambda i: (rank[i], -score[i], i))
    for budget in (1, 5, 17, n):
        got = np.asarray(spread_tracks(jnp.asarray(keep), jnp.asarray(pid), jnp.asarray(track),
                                       jnp.asarray(cell), budget))
        want = np.zeros(n, bool)
        want[want_order[:budget]] = True
        np.testing.assert_array_equal(got, want)
    # the first round holds one point of every non-empty cell
    first = np.asarray(spread_tracks(jnp.asarray(keep), jnp.asarray(pid), jnp.asarray(track),
                                     jnp.asarray(cell), 5))
    assert sorted(cell[first]) == sorted(set(cell[score >= 0]))


def test_first_pass_spread_keeps_the_budget_over_more_cells(tiny):
    """A spread first-pass budget keeps as many keypoints per image as the longest-track one,
    each cell of the reference's keypoint grid before any cell's second, so it covers at
    least as many cells; single images and candidate lists agree."""
    from vrs_jax.localize.render import grid_cells

    budget, g = 12, 3
    plain = localize.get_config("test", first_pass_keypoints=budget)
    spread = dataclasses.replace(plain, first_pass_spread_grid=g)
    idx = jnp.arange(min(4, tiny.egm.num_images))
    a = np.asarray(first_pass_keypoints(tiny, idx, plain))
    b = np.asarray(first_pass_keypoints(tiny, idx, spread))
    np.testing.assert_array_equal(a.sum(1), b.sum(1))
    np.testing.assert_array_equal(b[1], np.asarray(first_pass_keypoints(tiny, idx[1], spread)))
    valid = np.asarray(tiny.egm.kp_mask)[np.asarray(idx)]
    uv = tiny.egm.keypoints[idx][..., :2]
    for i in range(len(idx)):
        cells = np.asarray(grid_cells(uv[i], jnp.asarray(valid[i]), uv[i], g))
        assert len(set(cells[b[i]])) >= len(set(cells[a[i]]))
        occupied = len(set(cells[valid[i] & (np.asarray(tiny.egm.point_idx[idx[i]]) >= 0)]))
        assert len(set(cells[b[i]])) == min(occupied, int(b[i].sum()))
