"""The Map: one unit saved and loaded with its configuration by value; every way a map folder
can be wrong gives one line naming the file."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import jax
import numpy as np
import pytest
from test_egm_map import _assert_same, _toy
from test_nerf_ilm import _ilm

from vrs_jax import configio, maps
from vrs_jax.errors import VrsError
from vrs_jax.maps.config import MapConfig
from vrs_jax.nerf.config import get_config as nerf_config


def _map(descriptors: bool = True) -> maps.Map:
    egm = _toy(baseline=descriptors)
    egm = egm.replace(names=("a.png", "b.png", "c.png"))
    base = maps.get_config("test")
    cfg = dataclasses.replace(base, nerf=nerf_config("test", n_clusters=2),
                              egm=dataclasses.replace(base.egm, features=dataclasses.replace(
                                  base.egm.features, descriptor=dataclasses.replace(
                                      base.egm.features.descriptor, n_cells=2, n_bins=2))))
    ilm = _ilm().replace(config=cfg.nerf)
    src = maps.MapSource("7scenes", "/data/room", (("query_every", "8"),), ("q0.png",))
    return maps.Map(egm=egm, ilm=ilm, config=cfg, source=src)


def test_config_round_trips_exactly():
    for cfg in maps.CONFIGS.values():
        assert configio.from_dict(MapConfig, configio.to_dict(cfg)) == cfg
    assert json.dumps(configio.to_dict(maps.get_config("paper")), allow_nan=False)


@pytest.mark.parametrize("descriptors", [False, True])
def test_save_load_roundtrip(tmp_path, descriptors):
    m = _map(descriptors)
    maps.save_map(m, tmp_path / "m", stats={"note": 1})
    back = maps.load_map(tmp_path / "m")
    assert back.config == m.config and back.source == m.source
    assert back.has_descriptors == descriptors and back.names == m.names
    np.testing.assert_array_equal(back.cluster, m.cluster)
    for a, b in zip(jax.tree.leaves(m.ilm), jax.tree.leaves(back.ilm), strict=True):
        a, b = np.asarray(a), np.asarray(b)
        assert b.dtype == a.dtype
        # the NeRF weights are stored as float16 (maps.map.NERF_FLOAT16), the rest exactly
        assert np.array_equal(a, b) or np.array_equal(a.astype(np.float16).astype(a.dtype), b)
    _assert_same(m.egm, back.egm)
    assert maps.read_stats(tmp_path / "m") == {"note": 1}
    assert not list((tmp_path / "m").glob("*.tmp"))
    b = maps.map_bytes(tmp_path / "m")
    d = tmp_path / "m"
    size = lambda n: (d / n).stat().st_size  # noqa: E731
    assert b["vrs"] == size("map.json") + size("egm.npz") + size("ilm.npz")
    if descriptors:
        assert b["real"] == size("map.json") + size("egm.npz") + size("descriptors.npz")
    assert not maps.load_map(d, descriptors=False).has_descriptors


def test_edited_config_field_that_keeps_shapes_is_refused(tmp_path):
    """A hand edit of a map.json config field that leaves every array's shape as it was (the
    patch's blur, the descriptor's clipping) loaded and localized with settings the map was
    not built with; now the config recorded inside egm.npz at build time refuses it, naming
    the field, and the restored value loads again."""
    d = maps.save_map(_map(), tmp_path / "m")
    original = (d / "map.json").read_text()
    meta = json.loads(original)
    meta["config"]["egm"]["features"]["patches"]["window_per_scale"] = 6.0
    (d / "map.json").write_text(json.dumps(meta))
    with pytest.raises(VrsError, match="changed after the map was built") as e:
        maps.load_map(d)
    msg = str(e.value)
    assert "egm.features.patches.window_per_scale" in msg and "map.json" in msg
    assert "\n" not in msg
    (d / "map.json").write_text(original)
    assert maps.load_map(d).config == _map().config


def test_map_without_recorded_build_config_still_loads(tmp_path):
    """Maps written before the build config was recorded inside egm.npz load as before."""
    import io

    d = maps.save_map(_map(), tmp_path / "m")
    with np.load(d / "egm.npz") as z:
        arrays = {k: z[k] for k in z.files if k != "map_config_json"}
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    (d / "egm.npz").write_bytes(buf.getvalue())
    meta = json.loads((d / "map.json").read_text())
    meta["files"]["egm.npz"] = {"sha256": hashlib.sha256(buf.getvalue()).hexdigest(),
                                "bytes": len(buf.getvalue())}
    (d / "map.json").write_text(json.dumps(meta))
    assert maps.load_map(d).config == _map().config


def test_edited_config_fails_instead_of_changing_meaning(tmp_path):
    d = maps.save_map(_map(), tmp_path / "m")
    meta = json.loads((d / "map.json").read_text())
    meta["config"]["egm"]["k_max"] = "many"  # hand-edited
    (d / "map.json").write_text(json.dumps(meta))
    # the value is read as written; the arrays then disagree with it
    with pytest.raises(VrsError) as e:
        maps.load_map(d)
    assert "map.json" in str(e.value) or "egm.npz" in str(e.value)
    meta["config"]["egm"]["k_max"] = _map().config.egm.k_max
    meta["config"]["nerf"]["net_width"] = 999  # not the width the weights were trained with
    (d / "map.json").write_text(json.dumps(meta))
    with pytest.raises(VrsError, match="changed after the map was built") as e:
        maps.load_map(d)
    assert "nerf.net_width" in str(e.value) and "map.json" in str(e.value)
    meta["config"]["nerf"]["net_width"] = _map().config.nerf.net_width
    meta["config"]["nerf"]["unheard_of"] = 1
    (d / "map.json").write_text(json.dumps(meta))
    with pytest.raises(VrsError, match="unknown fields") as e:
        maps.load_map(d)
    assert "map.json" in str(e.value)
    del meta["config"]["nerf"]["unheard_of"]
    del meta["config"]["nerf"]["lr_init"]
    (d / "map.json").write_text(json.dumps(meta))
    with pytest.raises(VrsError, match="lacks fields"):
        maps.load_map(d)


def test_corrupt_missing_and_foreign_files(tmp_path):
    d = maps.save_map(_map(), tmp_path / "m")
    raw = bytearray((d / "egm.npz").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (d / "egm.npz").write_bytes(bytes(raw))
    with pytest.raises(VrsError, match="does not match map.json") as e:
        maps.load_map(d)
    assert "egm.npz" in str(e.value)

    d = maps.save_map(_map(), tmp_path / "m2")
    (d / "ilm.npz").unlink()
    with pytest.raises(VrsError, match="map file missing"):
        maps.load_map(d)

    d = maps.save_map(_map(), tmp_path / "m3")
    (d / "map.json").write_text("{not json")
    with pytest.raises(VrsError, match="corrupt map metadata"):
        maps.load_map(d)

    d = maps.save_map(_map(), tmp_path / "m4")
    meta = json.loads((d / "map.json").read_text())
    meta["format_version"] = 1
    (d / "map.json").write_text(json.dumps(meta))
    with pytest.raises(VrsError, match="format version 1"):
        maps.load_map(d)
    with pytest.raises(VrsError, match="not found"):
        maps.load_map(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(VrsError, match="no map.json"):
        maps.load_map(tmp_path / "empty")


def test_partial_map_without_nerf(tmp_path):
    m = _map().replace(ilm=None)
    d = maps.save_map(m, tmp_path / "m")
    with pytest.raises(VrsError, match="no trained NeRF"):
        maps.load_map(d)
    assert maps.load_map(d, require_ilm=False).ilm is None


def test_named_config_comments_match_values():
    paper, cpu, test = (maps.get_config(n) for n in ("paper", "cpu-small", "test"))
    assert (paper.egm.features.keypoints.max_keypoints, paper.egm.k_max) == (2048, 1024)
    assert paper.features.patches.size == 15
    assert (paper.nerf.net_depth, paper.nerf.net_width, paper.nerf.num_samples_coarse,
            paper.nerf.num_samples_fine, paper.nerf.max_steps) == (8, 256, 128, 128, 200_000)
    assert (cpu.egm.features.keypoints.max_keypoints, cpu.egm.k_max) == (1024, 256)
    assert (cpu.egm.retrieval.n_words, cpu.egm.retrieval.local_dim) == (32, 32)  # 1024-D
    assert (cpu.nerf.encoding, cpu.nerf.net_depth, cpu.nerf.net_width,
            cpu.nerf.num_samples_coarse, cpu.nerf.max_steps) == ("hashgrid", 2, 64, 32, 4000)
    assert (cpu.nerf.hash_levels, cpu.nerf.hash_log2_table) == (16, 15)  # int8: 1.08 MB
    assert (test.egm.features.keypoints.max_keypoints, test.egm.k_max,
            test.features.patches.size, test.nerf.net_width, test.nerf.max_steps) == (
        128, 64, 9, 64, 800)


def test_named_localize_config_comments_match_values():
    from vrs_jax import localize

    paper, cpu, test = (localize.get_config(n) for n in ("paper", "cpu-small", "test"))
    assert (paper.top_k, paper.query_keypoints, paper.depth_guided, paper.guided_passes) == (
        5, 2048, False, 0)
    assert (cpu.top_k, cpu.query_keypoints, cpu.depth_guided, cpu.narrow_samples,
            cpu.narrow_fine, cpu.guided_passes, cpu.guided_sources, cpu.render_grid,
            cpu.early_exit_inliers, cpu.render_chunk, cpu.guided_radius,
            cpu.guided_threshold_px, cpu.pnp.threshold_px, cpu.probe_grid,
            cpu.first_pass_keypoints, cpu.guided_reuse_inliers, cpu.guided_keypoints,
            cpu.first_pass_unique_points, cpu.retries) == (
        5, 1024, True, 32, 8, 1, ("render",), 8, 24, 2048, 4.0, 2.0, 6.0, 2, 256, True, 96,
        True, 1)
    # "every keypoint a cpu-small map links per image": its k_max
    assert cpu.first_pass_keypoints == maps.get_config("cpu-small").egm.k_max
    assert (paper.retries, test.retries) == (0, 0)
    assert (test.top_k, test.query_keypoints, test.narrow_samples, test.narrow_fine,
            test.guided_passes) == (2, 256, 8, 4, 0)

def test_quantised_map_localizes_as_its_float_originals_would(tiny_map, small_synthetic_scene):
    """The stored map is a quantised copy of the float32 map it was built from: every
    keypoint, scale, angle, 3D point and NeRF weight within its storage bound of the value
    loaded. A map moved by those bounds (another float32 map that stores to the same bytes)
    localizes the queries to the same poses in render mode, which reads all of them."""
    from vrs_jax import localize
    from vrs_jax.data.readers import load_scene
    from vrs_jax.egm import map as egm_map
    from vrs_jax.localize.batch import localize_scene

    m = maps.load_map(tiny_map).without_descriptors()
    rng = np.random.default_rng(0)
    e = m.egm
    kp = np.asarray(e.keypoints, np.float64).copy()
    ls = np.log2(kp[np.asarray(e.kp_mask), 2])
    half = (ls.max() - ls.min()) / 510
    kp[..., :2] += rng.uniform(-1 / 32, 1 / 32, kp[..., :2].shape)
    kp[..., 2] *= np.exp2(rng.uniform(-half, half, kp.shape[:2]))
    kp[..., 3] += rng.uniform(-np.pi / 256, np.pi / 256, kp.shape[:2])
    X = np.asarray(e.points3d, np.float64)
    step = (X.max(0) - X.min(0)) / 65535
    X = X + rng.uniform(-step / 2, step / 2, X.shape)
    params = jax.tree.map(lambda p: p * (1 + rng.uniform(-2 ** -11, 2 ** -11, p.shape)
                                         ).astype(np.float32), m.ilm.fields.params)
    moved = m.replace(
        egm=e.replace(keypoints=jax.numpy.asarray(kp, np.float32),
                      points3d=jax.numpy.asarray(X, np.float32)),
        ilm=m.ilm.replace(fields=m.ilm.fields.replace(params=params)))
    assert np.abs(egm_map.reprojection_errors(moved.egm)
                  - egm_map.reprojection_errors(m.egm)).max() < 0.1
    queries = load_scene("7scenes", small_synthetic_scene).queries().subset(np.arange(3))
    cfg = localize.get_config("test")
    a, _ = localize_scene(m, queries, cfg, progress=False, timed=False)
    b, _ = localize_scene(moved, queries, cfg, progress=False, timed=False)
    for i, (ra, rb) in enumerate(zip(a, b, strict=True)):
        assert ra.success and rb.success
        # the same pose up to the localizer's own noise: the tiny field's ~20-inlier poses
        # are 1-3 cm off, and a 1e-6 change of the field's arithmetic moved one by 5.2 mm
        # (errors 16 and 22 mm); a storage bound that mattered would move them by more
        centre = lambda R, t: -np.asarray(R).T @ np.asarray(t)  # noqa: E731
        err = np.linalg.norm(centre(ra.R, ra.t) - centre(queries.R[i], queries.t[i]))
        assert np.linalg.norm(np.asarray(ra.t) - np.asarray(rb.t)) < max(0.005, 0.5 * err)
        assert abs(int(ra.n_inliers) - int(rb.n_inliers)) <= max(3, 0.1 * int(ra.n_inliers))


def _format2_folder(m: maps.Map, d):
    """``m`` written as format 2 wrote it (float32 keypoints and points, int32 links)."""
    import io as io_

    from vrs_jax import fileio
    from vrs_jax.nerf import ilm as ilm_lib

    e = m.egm
    mask = np.asarray(e.kp_mask)
    arrays = {"points3d": np.asarray(e.points3d), "R": np.asarray(e.R), "t": np.asarray(e.t),
              "K": np.asarray(e.K), "dist": np.asarray(e.dist), "sizes": np.asarray(e.sizes),
              "kp_counts": mask.sum(1).astype(np.int32),
              "keypoints": np.asarray(e.keypoints)[mask],
              "point_idx": np.asarray(e.point_idx)[mask],
              "global_desc": np.asarray(e.global_desc, np.float16),
              "vocab_centers": np.asarray(e.vocab.centers),
              "vocab_power": np.asarray(e.vocab.power, np.float32)}
    blobs = {}
    for name, arr in (("egm.npz", arrays),
                      ("descriptors.npz", {"local_desc": np.asarray(e.local_desc)[mask]
                                           .astype(np.float16)})):
        buf = io_.BytesIO()
        np.savez(buf, **arr)
        blobs[name] = buf.getvalue()
    blobs["ilm.npz"] = ilm_lib.to_bytes(m.ilm)
    d.mkdir(parents=True)
    for name, b in blobs.items():
        (d / name).write_bytes(b)
    conf = configio.to_dict(m.config)
    del conf["nerf"]["cluster_method"]  # format 2 predates it
    meta = {"kind": "vrs_jax.map", "format_version": 2, "config": conf,
            "source": configio.to_dict(m.source), "names": list(e.names), "k_max": e.k_max,
            "files": {n: {"sha256": fileio.sha256(b), "bytes": len(b)}
                      for n, b in blobs.items()}, "stats": {"kept": 1}}
    (d / "map.json").write_text(json.dumps(meta))
    return d


def test_upgrade_rewrites_a_format2_map(tmp_path):
    from vrs_jax.maps import upgrade

    m = _map(descriptors=True)
    old = _format2_folder(m, tmp_path / "old")
    with pytest.raises(VrsError, match="format version 2") as e:
        maps.load_map(old)
    assert "map.json" in str(e.value)
    assert upgrade.main([str(old), str(tmp_path / "new")]) == 0
    back = maps.load_map(tmp_path / "new")
    _assert_same(m.egm, back.egm)
    assert back.config == m.config and maps.read_stats(tmp_path / "new") == {"kept": 1}
    assert upgrade.main([str(tmp_path / "new"), str(tmp_path / "x")]) == 2  # not format 2
    (old / "egm.npz").write_bytes(b"tampered")
    assert upgrade.main([str(old), str(tmp_path / "y")]) == 2


def test_train_egm_from_reuses_the_egm_and_trains_another_nerf(tiny_map, small_synthetic_scene,
                                                               tmp_path, capsys):
    """``experiments.train --egm-from`` copies another map's EGM (same dataset, split and EGM
    settings) and trains a NeRF of other settings on it; other EGM settings, another split or
    a folder that is not a map are refused in one line, and nothing is written then."""
    from vrs_jax.cli.train import main

    out = tmp_path / "other_nerf"
    args = ["--format", "7scenes", "--root", str(small_synthetic_scene), "--config", "test",
            "--quiet", "--out", str(out), "--egm-from", str(tiny_map)]
    assert main([*args, "--set", "net_width=32", "--steps", "5"]) == 0
    said = capsys.readouterr().out
    assert "EGM taken from" in said
    # the NeRF settings that differ from the source map's are named (a --set is not inherited)
    assert "this NeRF trains with net_width=32 (that map's: 64)" in said
    assert "max_steps=5" in said
    src, new = maps.load_map(tiny_map), maps.load_map(out)
    for name in ("points3d", "point_idx", "keypoints", "R", "t", "global_desc"):
        np.testing.assert_allclose(np.asarray(getattr(new.egm, name)),
                                   np.asarray(getattr(src.egm, name)), rtol=1e-6, atol=1e-7)
    assert new.config.egm == src.config.egm
    assert new.config.nerf.net_width == 32 and new.config.nerf.max_steps == 5
    assert new.ilm.config.net_width == 32
    assert maps.read_stats(out)["egm_from"] == str(tiny_map.resolve())
    # a re-run of the same command resumes the map in --out (nothing is taken again)
    assert main([*args, "--set", "net_width=32", "--steps", "5"]) == 0
    assert "EGM taken from" not in capsys.readouterr().out
    # refused: other EGM settings, another split, not a map; no folder is left behind
    for extra, why in ((["--config", "cpu-small"], "EGM settings"),
                       (["--downscale", "2"], "another dataset, split or reader options"),
                       (["--egm-from", str(tmp_path)], "not a vrs-jax map")):
        bad = tmp_path / f"refused_{len(extra[1])}"
        cmd = [a if a != str(out) else str(bad) for a in args] + extra
        assert main(cmd) != 0
        assert why in capsys.readouterr().err
        assert not (bad / "map.json").exists()
