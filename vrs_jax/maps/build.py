"""Build a map from a dataset: the EGM, then the ILM trained on the reference images.

Resumable, hloc style: re-running skips what is finished and continues NeRF training from the
last orbax checkpoint. A folder is only ever extended with the same configuration and the same
split; the one change accepted is a longer training run (``nerf.max_steps`` raised), which
continues from the last checkpoint.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from vrs_jax import configio, fileio
from vrs_jax.data.scene import Scene
from vrs_jax.egm import build as egm_build
from vrs_jax.errors import VrsError
from vrs_jax.features import rays as rays_mod
from vrs_jax.maps import map as map_io
from vrs_jax.maps.config import MapConfig
from vrs_jax.maps.map import Map, MapSource
from vrs_jax.nerf import train as nerf_train

log_ = logging.getLogger("vrs_jax")


def scene_source(scene: Scene, options: dict[str, Any] | None = None) -> MapSource:
    """The MapSource of a scene: its format, root, reader options and held-out queries."""
    return MapSource(format=scene.format, root=str(scene.root),
                     options=tuple(sorted((str(k), str(v)) for k, v in (options or {}).items())),
                     query_names=tuple(scene.queries().names))


def fingerprint(scene: Scene) -> str:
    """SHA-256 over the scene's reference images, sorted by name: each name, its file size
    and its pose (R, t rounded to 1e-9): what a map is built from."""
    refs = scene.references()
    h = hashlib.sha256()
    for i in sorted(range(len(refs.names)), key=lambda k: refs.names[k]):
        try:
            size = Path(refs.image_paths[i]).stat().st_size
        except OSError:
            size = -1
        pose = np.concatenate([np.ravel(refs.R[i]), np.ravel(refs.t[i])])
        h.update(f"{refs.names[i]}\0{size}\0".encode())
        h.update((np.round(np.asarray(pose, np.float64), 9) + 0.0).tobytes())
    return h.hexdigest()


def provenance(scene: Scene, source: MapSource) -> dict[str, Any]:
    """What a map records it was built from: the dataset root (resolved), format, split and
    :func:`fingerprint`."""
    return {"root": str(Path(scene.root).resolve()), "format": scene.format,
            "split": {"options": dict(source.options),
                      "n_reference": len(scene.references().names),
                      "query_names_sha256": fileio.sha256(
                          "\n".join(sorted(source.query_names)).encode())},
            "fingerprint": fingerprint(scene)}


def _check_provenance(out: Path, meta: dict, prov: dict) -> None:
    """VrsError unless the map in ``out`` was built from the dataset ``prov`` describes (maps
    written before provenance was recorded pass)."""
    old = meta.get("provenance") or {}
    if old.get("fingerprint") and old["fingerprint"] != prov["fingerprint"]:
        raise VrsError(f"{out} was built from {old.get('root')} (fingerprint "
                       f"{old['fingerprint'][:12]}), not {prov['root']} (fingerprint "
                       f"{prov['fingerprint'][:12]}); use another --out")


def _existing(out: Path, cfg: MapConfig, source: MapSource, prov: dict
              ) -> tuple[Map | None, dict]:
    """The map already in ``out`` (if any) after checking it may be extended."""
    if not (out / map_io.META).is_file():
        if out.exists() and any(p.name != "sfm" for p in out.iterdir()):
            raise VrsError("folder exists and is not a vrs-jax map; choose an empty --out", out)
        return None, {}
    meta = map_io.read_meta(out)
    _check_provenance(out, meta, prov)
    old = load_partial(out)
    if old.source.format != source.format or old.source.query_names != source.query_names:
        raise VrsError(f"this map folder was built from another dataset or split "
                       f"({old.source.format} at {old.source.root}); use another --out", out)
    if dataclasses.replace(old.config, nerf=dataclasses.replace(
            old.config.nerf, max_steps=cfg.nerf.max_steps)) != cfg:
        raise VrsError(f"this map folder was built with config {old.config.name!r} and other "
                       "settings; use another --out", out / map_io.META)
    if cfg.nerf.max_steps < old.config.nerf.max_steps:
        raise VrsError(f"the map is trained for {old.config.nerf.max_steps} steps; --steps can "
                       "only extend it", out / map_io.META)
    return old, meta.get("stats", {})


def _wait_for_egm(out: Path, cfg: MapConfig, source: MapSource, prov: dict,
                  log: Callable[[str], None], poll_s: float = 2.0) -> tuple[Map, dict]:
    """A multi-process build's other processes: (map, stats) once process 0 has saved the
    EGM into ``out`` (a map folder appears whole: :func:`vrs_jax.maps.map.save_map`). If
    process 0 dies, JAX's distributed runtime ends the waiting processes."""
    if not (out / map_io.META).is_file():
        log("waiting for process 0 to build the EGM")
        while not (out / map_io.META).is_file():
            time.sleep(poll_s)
    m, stats = _existing(out, cfg, source, prov)
    assert m is not None
    return m, stats


def load_partial(folder: Path) -> Map:
    """A map folder as it stands (the NeRF may be missing), with its descriptors."""
    return map_io.load_map(folder, descriptors=True, require_ilm=False)


def seed_from(src: str | Path, out: str | Path, scene: Scene, cfg: MapConfig,
              source_options: dict[str, Any] | None = None,
              log: Callable[[str], None] | None = None) -> bool:
    """Start the map folder ``out`` with the EGM of the map in ``src`` (its NeRF is not
    taken), so that :func:`build_map` trains a NeRF of other settings without building the
    EGM again. ``src`` must be a map of the same dataset and split with the same EGM
    settings. Nothing is done (False) when ``out`` already holds a map: a re-run resumes it.
    ``log`` gets one line naming the NeRF settings in which ``cfg`` differs from ``src``'s
    (the new NeRF trains with ``cfg``'s: a ``--set`` of the source map is not carried over).

    Raises VrsError naming ``src`` when it is not such a map."""
    src, out = Path(src), Path(out)
    if (out / map_io.META).is_file():
        return False
    if not (src / map_io.META).is_file():
        raise VrsError("--egm-from: not a vrs-jax map folder (no map.json)", src)
    if src.resolve() == out.resolve():
        raise VrsError("--egm-from names the output folder itself", src)
    source = scene_source(scene, source_options)
    prov = provenance(scene, source)
    meta = map_io.read_meta(src)
    _check_provenance(src, meta, prov)
    old = load_partial(src)
    if (old.source.format, old.source.options, old.source.query_names) != (
            source.format, source.options, source.query_names):
        raise VrsError(f"--egm-from: the map was built from another dataset, split or reader "
                       f"options ({old.source.format} at {old.source.root}, options "
                       f"{dict(old.source.options)})", src)
    if old.config.egm != cfg.egm:
        raise VrsError(f"--egm-from: the map's EGM settings (config {old.config.name!r}) "
                       f"differ from config {cfg.name!r}'s", src / map_io.META)
    changed = configio.changed_fields(old.config.nerf, cfg.nerf)
    if changed and log is not None:
        log(f"note: --egm-from {src}: this NeRF trains with " + ", ".join(
            f"{k}={b!r} (that map's: {a!r})" for k, a, b in changed))
    stats = {k: v for k, v in meta.get("stats", {}).items() if k == "egm"}
    stats["egm_from"] = str(src.resolve())
    map_io.save_map(Map(egm=old.egm, ilm=None, config=cfg, source=source), out, stats,
                    provenance=prov)
    return True


def keypoint_depths(egm) -> np.ndarray:
    """[N, K_max] z-depth of each map keypoint's 3D point in its reference camera, 0 where
    the keypoint links none (the NeRF's depth-loss targets)."""
    z = jax.vmap(rays_mod.keypoint_depths, in_axes=(None, 0, 0, 0))(
        egm.points3d, egm.point_idx, egm.R, egm.t)
    return np.where(np.asarray(egm.point_idx) >= 0, np.asarray(z), 0.0)


def build_map(scene: Scene, out_dir: str | Path, cfg: MapConfig, progress: bool = True,
              minutes: float | None = None, source_options: dict[str, Any] | None = None,
              log: Callable[[str], None] | None = None, train_nerf: bool = True,
              primary: bool = True) -> Path:
    """EGM (with real-patch descriptors), then the ILM; resumable.

    Args:
      scene: the dataset; its reference images (``~is_query``) are mapped, its queries are
        recorded as the map's held-out split.
      out_dir: the map folder (created; see :mod:`vrs_jax.maps.map`).
      cfg: the MapConfig (stored by value in the map).
      minutes: optional wall-clock cap on this run's NeRF training; a re-run continues.
      source_options: the reader options that produced ``scene`` (recorded in the map).
      log: called with each progress line (default: the ``vrs_jax`` logger at INFO level;
        ``runrecord.setup_logging`` shows it).
      train_nerf: False stops after the EGM (a map without NeRF; a later call continues).
      primary: False for processes 1..N-1 of a multi-process build (``jax.distributed``
        started; the same ``out_dir`` on a shared file system): they wait for process 0's
        EGM, train their shard of the clusters with it and write nothing but their part of
        the checkpoints; process 0 (``primary``) builds the EGM and writes the map.
    Returns:
      the folder.
    """
    log = log or log_.info
    out = Path(out_dir)
    source = scene_source(scene, source_options)
    prov = provenance(scene, source)
    m, stats = (_existing(out, cfg, source, prov) if primary
                else _wait_for_egm(out, cfg, source, prov, log))
    if (m is not None and m.ilm is not None and m.config == cfg and train_nerf
            and "map_bytes" in stats):
        log("[1/3] EGM: already built, skipping")
        log("[2/3] ILM: already trained, skipping")
        log(f"[3/3] {describe(out)}")
        return out  # a finished map: nothing to write (works in a read-only folder too)
    if primary:
        fileio.check_writable(out)
    if m is None:
        log(f"[1/3] EGM: features, pairs, triangulation ({len(scene.references())} references)")
        egm, egm_stats = egm_build.build_egm(scene, cfg.egm, progress=progress)
        log(egm_build.format_stats(egm_stats))
        stats = {"egm": egm_stats}
        m = Map(egm=egm, ilm=None, config=cfg, source=source)
        map_io.save_map(m, out, stats, provenance=prov)
    else:
        log("[1/3] EGM: already built, skipping")
    if not train_nerf:
        return out
    trained = m.ilm is not None and m.ilm.config == cfg.nerf
    if not trained:
        ncfg = cfg.nerf
        log(f"[2/3] ILM: {ncfg.n_clusters} Mip-NeRF cluster(s), config {ncfg.name}, "
            f"{ncfg.max_steps} steps" + (f" (this run: at most {minutes:g} min)" if minutes
                                         else ""))
        refs = scene.references()
        prep = nerf_train.prepare(refs, ncfg, points3d=np.asarray(m.egm.points3d),
                                  patch_keypoints=(m.egm.keypoints, m.egm.kp_mask,
                                                   cfg.features.patches, keypoint_depths(m.egm)))
        res = nerf_train.train(prep, out / "nerf", minutes=minutes, progress=progress)
        if not primary:
            return out  # the map is process 0's to write
        done = int(res.state.step)
        stats["ilm"] = {"steps": done, "steps_per_s": res.steps_per_s, "train_s": res.seconds,
                        "history": res.history[-5:]}
        if done < ncfg.max_steps:
            # map.json keeps describing the last complete state; the checkpoint is ahead
            log(f"NeRF stopped at step {done} of {ncfg.max_steps} (time cap); re-run the same "
                "command to continue")
            return out
        m = m.replace(ilm=res.ilm, config=cfg)
    else:
        log("[2/3] ILM: already trained, skipping")
    if not primary:
        return out
    map_io.save_map(m, out, stats, measure=True, provenance=prov)
    log(f"[3/3] {describe(out)}")
    return out


def describe(folder: str | Path) -> str:
    """One line about a map folder: config, images, sizes of its two variants."""
    meta = map_io.read_meta(folder)
    b = map_io.map_bytes(folder)
    cfg = configio.from_dict(MapConfig, meta["config"], Path(folder) / map_io.META)
    return (f"map {folder}: config {cfg.name}, {len(meta['names'])} reference images; VRS map "
            f"(rendered patches) {b['vrs'] / 1e6:.2f} MB (EGM {b['egm'] / 1e6:.2f} + NeRF "
            f"{b['ilm'] / 1e6:.2f}), real-patch map {b['real'] / 1e6:.2f} MB")
