"""``Localizer``: load a map once, compile once, localize images.

    loc = Localizer("maps/room", "cpu-small")           # or a Map, or a LocalizeConfig
    loc = Localizer("maps/room", cache_mb=50)           # a query stream: cache rendered refs
    loc.warmup(320, 240)                                 # optional: compile before the first image
    r = loc.localize_image("query.png", K, dist)         # LocalizeResult of numpy values
    results, errors = loc.localize_batch(paths, Ks, dists)
    frames = loc.track(paths, K, dist)                   # a stream: track with a motion prior
    loc = Localizer("maps/room", devices=4)              # batches split over 4 devices

A thin wrapper around :func:`~vrs_jax.localize.query.prepare_query`,
:func:`~vrs_jax.localize.run.localize` and :func:`~vrs_jax.localize.query.stack_queries`:
every query is padded to ``cfg.query_keypoints``, so one compilation serves every image (and
one per batch size for ``localize_batch``, which runs ``jax.vmap(localize)`` over the batch,
its query axis sharded over the devices: :func:`~vrs_jax.localize.batch.localize_batch`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax.data.images import read_gray
from vrs_jax.errors import VrsError
from vrs_jax.localize import batch as batch_lib
from vrs_jax.localize import retry as retry_lib
from vrs_jax.localize import track as track_lib
from vrs_jax.localize.cache import DescriptorCache
from vrs_jax.localize.confidence import map_scale
from vrs_jax.localize.config import LocalizeConfig, get_config
from vrs_jax.localize.query import Query, prepare_query, stack_queries
from vrs_jax.localize.render import first_pass_keypoints
from vrs_jax.localize.run import JITTED_STAGES, localize, run_stages
from vrs_jax.localize.stages import LocalizeResult, failure_reason
from vrs_jax.maps import Map, load_map_for

_first_pass_keypoints = jax.jit(first_pass_keypoints, static_argnames=("cfg",))


def _resolve_config(cfg: LocalizeConfig | str | None, source: str | None) -> LocalizeConfig:
    if cfg is None:
        cfg = get_config("cpu-small")
    elif isinstance(cfg, str):
        cfg = get_config(cfg)
    elif not isinstance(cfg, LocalizeConfig):
        raise VrsError(f"cfg must be a LocalizeConfig, a config name or None, got {type(cfg)}")
    if source is not None:
        cfg = dataclasses.replace(cfg, source=source)
    return cfg


class Localizer:
    """A map and a query-time config, ready to localize images.

    Args:
      map_or_dir: a map folder (loaded once, with the real-patch descriptors only when the
        source is "real") or a loaded :class:`~vrs_jax.maps.Map`.
      cfg: a LocalizeConfig, the name of one (``localize.CONFIGS``) or None ("cpu-small").
      source: "render" (VRS-NeRF) or "real" (the real-patch baseline); None keeps the
        config's (the named configs render).
      cache_mb: render mode: keep the rendered descriptors of recently retrieved reference
        images within this many MB (:class:`~vrs_jax.localize.cache.DescriptorCache`); 0: no
        cache, every query renders its references (the fused jitted ``localize``). The
        cached path uses every cached reference and renders the missing ones best first,
        with the config's early exit.
      devices: ``localize_batch`` splits its batch over these devices (a list, the first N of
        ``jax.devices()``, or None: all of them); one device: a plain vmapped batch.
    """

    def __init__(self, map_or_dir: Map | str | Path, cfg: LocalizeConfig | str | None = None,
                 source: str | None = None, cache_mb: float = 0.0,
                 devices: Sequence[Any] | int | None = None):
        self.cfg = _resolve_config(cfg, source)
        if isinstance(cache_mb, bool) or not isinstance(cache_mb, (int, float)) \
                or not math.isfinite(cache_mb) or cache_mb < 0:
            raise VrsError(f"cache_mb must be a finite number >= 0 (0: no cache), got "
                           f"{cache_mb!r}")
        self.cache = (DescriptorCache(cache_mb) if cache_mb > 0 and self.cfg.source == "render"
                      else None)
        if isinstance(map_or_dir, Map):
            self.map = map_or_dir
        else:
            self.map = load_map_for(map_or_dir, self.cfg.source)
        self.scale = map_scale(self.map)  # the scene scale, for the confidence of retries
        self.mesh = batch_lib.query_mesh(devices)
        self._placed_map: Map | list[Map] | None = None
        self.stream_cache_stats: dict[str, float] | None = None  # the last track()'s cache

    # ------------------------------------------------------------------ preparation

    def prepare(self, image: str | Path | np.ndarray, K: np.ndarray,
                dist: np.ndarray | None = None, name: str | None = None) -> Query:
        """One image (file or array) -> Query (host work). VrsError naming the image for an
        unreadable file, or an image, K or dist that
        :func:`~vrs_jax.localize.query.validate` refuses."""
        name = name or (str(image) if isinstance(image, (str, Path)) else "image")
        if isinstance(image, (str, Path)):
            image = read_gray(image)  # VrsError naming the path when missing or unreadable
        return prepare_query(self.map, image, K, dist, self.cfg, name)

    # ------------------------------------------------------------------ localization

    def localize_image(self, image: str | Path | np.ndarray, K: np.ndarray,
                       dist: np.ndarray | None = None) -> LocalizeResult:
        """Localize one image.

        Args:
          image: an image file, or an [H, W] grey / [H, W, 3] RGB array (uint8, or float in
            [0, 1]).
          K: [3, 3] intrinsics of that image size (COLMAP pixel convention).
          dist: [5] OpenCV distortion (k1, k2, p1, p2, k3) or None.
        Returns:
          LocalizeResult with numpy values (world-to-camera R [3, 3], t [3], flags, counts);
          :meth:`failure_reason` says why it has no PnP pose.
        Raises:
          VrsError naming the path for an unreadable image, or the image when its size
          contradicts K.
        """
        return self.localize_query(self.prepare(image, K, dist))

    def failure_reason(self, r: LocalizeResult) -> str | None:
        """Why result ``r`` has no PnP pose (a blank query image: no keypoints; no match; too
        few inliers), or None when it has one."""
        return failure_reason(r, self.cfg.pnp.min_inliers)

    def localize_query(self, q: Query) -> LocalizeResult:
        """Localize a prepared query in full (retrieval, first pass, guided passes; the
        descriptor cache when there is one; ``cfg.retries``: a pose that is not "localized"
        tried again with the next references, :mod:`~vrs_jax.localize.retry`) ->
        LocalizeResult of numpy values."""
        def once(c: LocalizeConfig) -> LocalizeResult:
            return (localize(self.map, q, c) if self.cache is None
                    else self._localize_cached(q, c))

        return retry_lib.localize_with_retries(self.map, q, self.cfg, once, self.scale)[0]

    def track(self, frames: Sequence[Any], K: np.ndarray, dist: np.ndarray | None = None,
              names: Sequence[str] | None = None, progress: bool = False,
              sizes: Sequence[Any] | None = None) -> list[track_lib.TrackResult]:
        """Localize a stream of frames in order, tracking with a motion prior
        (:mod:`~vrs_jax.localize.track`): the first frame, and any frame whose tracking is
        rejected, is localized in full (:meth:`localize_query`); the others run only the
        guided pass from the constant-velocity prediction (one jitted tracking step,
        compiled once). Settings: ``cfg.track``; in render mode without a cache of its own
        the Localizer keeps the stream's rendered references in one of
        ``cfg.track.cache_mb`` for this call (its counts in ``stream_cache_stats``).

        Args:
          frames: image files or arrays ([H, W] grey / [H, W, 3] RGB), in stream order.
          K: [3, 3] intrinsics of every frame, or [N, 3, 3] one per frame.
          dist: None, one [5] OpenCV distortion, or one per frame (entries may be None).
          names: per frame, for results and messages (default: the path or "frame i").
          progress: show a progress bar.
          sizes: per frame the (width, height) a frame file is read at, when K belongs to
            scaled images (a dataset read with ``--downscale``: ``scene.sizes``); None: the
            file's own size.
        Returns:
          per frame a :class:`~vrs_jax.localize.track.TrackResult`: the LocalizeResult
          fields plus ``tracked``, ``confidence``, ``verdict``, ``latency_s``; an unreadable
          or blank frame has ``error`` set (success False, verdict "failed") and the stream
          goes on.
        Raises:
          VrsError for frames that are not a list, or a K / dist count that is not one or
          one per frame.
        """
        own = self._stream_cache()  # the stream's full localizations and views share it
        if own:
            self.cache = DescriptorCache(self.cfg.track.cache_mb)
        try:
            return track_lib.track_frames(self.map, self.cfg, frames, K, dist, self.prepare,
                                          self.localize_query, names=names,
                                          progress=progress, sizes=sizes,
                                          views=self._reference_views)
        finally:
            if own:
                self.stream_cache_stats = self.cache.stats()
                self.cache = None

    def _stream_cache(self) -> bool:
        """Whether :meth:`track` makes a cache of ``cfg.track.cache_mb`` for its stream (render
        mode, a positive budget, no cache of the Localizer's own)."""
        return (self.cache is None and self.cfg.source == "render"
                and self.cfg.track.cache_mb > 0)

    def _localize_cached(self, q: Query, cfg: LocalizeConfig) -> LocalizeResult:
        """Retrieval, then each retrieved reference's descriptors from the cache or rendered
        and described (one jitted call per missing reference), then the remaining stages.

        The cached references cost nothing and are always used; the missing ones are
        rendered best first, and with ``cfg.early_exit_inliers`` the rest are skipped once
        the descriptors at hand give a RANSAC seed with that many inliers (the rule of
        :func:`~vrs_jax.localize.stages.early_exit_render`)."""
        m = self.map
        s = run_stages(m, q, cfg, until="retrieval", jitted=JITTED_STAGES)
        descs, have, n_rendered = self._candidates(q, s, cfg)
        s.update(self._described(s, descs, have, cfg))
        s["n_rendered"] = jnp.int32(n_rendered)
        return run_stages(m, q, cfg, jitted=JITTED_STAGES, state=s, after="describe")["result"]

    def _candidates(self, q: Query, s: dict, cfg: LocalizeConfig
                    ) -> tuple[list, np.ndarray, int]:
        """Descriptors of the candidates ``s["idx"]`` [k]: (per candidate [K_max, D] or None,
        have [k] bool, patches rendered). The cached ones are always used; the missing ones
        are rendered best first (and cached) until, with ``cfg.early_exit_inliers``, the
        descriptors at hand give a RANSAC seed with that many inliers."""
        idx = np.asarray(s["idx"])
        # hits: cached references used; misses: references rendered (an early exit leaves
        # the others neither)
        descs = [self.cache.get(int(i)) if self.cache is not None and int(i) in self.cache
                 else None for i in idx]
        have = np.array([d is not None for d in descs])
        n_rendered = 0
        for c in np.flatnonzero(~have):
            if cfg.early_exit_inliers > 0 and have.any() and self._confident(q, s, descs, have,
                                                                             cfg):
                break
            if self.cache is not None:
                self.cache.get(int(idx[c]))  # a miss
            descs[c], n = self._render_reference(q, cfg, int(idx[c]))
            n_rendered += n
            have[c] = True
        return descs, have, n_rendered

    def _render_reference(self, q: Query, cfg: LocalizeConfig, i: int
                          ) -> tuple[np.ndarray, int]:
        """Reference ``i``'s first-pass descriptors [K_max, D] rendered from its own camera
        (one jitted call; the query gives only shapes), stored in the cache when there is
        one; and the patches rendered."""
        one = {"idx": jnp.asarray([i], jnp.int32)}
        one.update(JITTED_STAGES["render"](self.map, q, cfg, one))
        desc = np.asarray(JITTED_STAGES["describe"](self.map, q, cfg, one)["desc"][0])
        if self.cache is not None:
            self.cache.put(i, desc)
        return desc, int(one["n_rendered"])

    def _reference_views(self, q: Query, R_pred: np.ndarray, t_pred: np.ndarray, size: Any,
                         cfg: LocalizeConfig) -> tuple:
        """A tracking step's references at the predicted pose and their own-view first-pass
        descriptors, from the cache or rendered best first under the config's early exit
        (:meth:`_candidates`; :func:`track.track_step`'s ``views``): (idx [k], desc
        [k, K_max, D], mask [k, K_max] (a reference not rendered: none), patches rendered)."""
        f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
        idx = np.asarray(track_lib.step_references_jit(self.map, q, f32(R_pred), f32(t_pred),
                                                       f32(size), cfg))
        s = {"idx": jnp.asarray(idx)}
        descs, have, n_rendered = self._candidates(q, s, cfg)
        d = self._described(s, descs, have, cfg)
        return idx, d["desc"], d["desc_mask"], n_rendered

    def _described(self, s: dict, descs: list, have: np.ndarray, cfg: LocalizeConfig
                   ) -> dict:
        """The describe stage's state from per-candidate descriptors (None: not rendered,
        masked out)."""
        blank = np.zeros_like(next(d for d in descs if d is not None))
        desc = np.stack([blank if d is None else d for d in descs])
        mask = _first_pass_keypoints(self.map, s["idx"], cfg) & jnp.asarray(have)[:, None]
        return {"desc": jnp.asarray(desc), "desc_mask": mask}

    def _confident(self, q: Query, s: dict, descs: list, have: np.ndarray,
                   cfg: LocalizeConfig) -> bool:
        """Whether the candidates at hand already give a RANSAC seed with
        ``cfg.early_exit_inliers`` distinct inliers."""
        st = {**s, **self._described(s, descs, have, cfg)}
        for name in ("matching", "ransac"):
            st.update(JITTED_STAGES[name](self.map, q, cfg, st))
        n = int(jnp.sum(st["inl0"] & st["ok"]))
        return bool(st["ok_seed"]) and n >= cfg.early_exit_inliers

    def localize_batch(self, images: Sequence[Any], Ks: Sequence[np.ndarray],
                       dists: Sequence[np.ndarray | None] | None = None
                       ) -> tuple[list[LocalizeResult | None], list[str | None]]:
        """Localize several images in one vmapped call.

        Args:
          images: N image files or arrays (as :meth:`localize_image`; sizes may differ).
          Ks: N [3, 3] intrinsics; dists: N [5] distortions (or None entries), or None.
        Returns:
          (results, errors): per image a LocalizeResult of numpy values, or None with the
          reason (the VrsError's message) in ``errors`` at the same index; the other images are
          localized. Compiled once per number of usable images (rounded up to a multiple of
          the device count: the batch is sharded over ``devices``).
        """
        n = len(images)
        if len(Ks) != n or (dists is not None and len(dists) != n):
            raise VrsError(f"localize_batch: {n} images but {len(Ks)} K and "
                           f"{'no' if dists is None else len(dists)} distortions")
        queries: list[Query] = []
        ok: list[int] = []
        errors: list[str | None] = [None] * n
        for i in range(n):
            name = str(images[i]) if isinstance(images[i], (str, Path)) else f"image {i}"
            try:
                queries.append(self.prepare(images[i], Ks[i],
                                            None if dists is None else dists[i], name))
                ok.append(i)
            except VrsError as e:
                errors[i] = str(e)
        results: list[LocalizeResult | None] = [None] * n
        if queries:
            if self._placed_map is None:  # the map on every device of the mesh, once
                self._placed_map = (self.map if self.mesh.size == 1 else
                                    batch_lib.place_map(self.map, self.mesh))
            batch = jax.device_get(batch_lib.localize_batch(
                self._placed_map, stack_queries(queries), self.cfg, self.mesh))
            for j, i in enumerate(ok):
                results[i] = jax.tree.map(lambda x, j=j: x[j], batch)
        return results, errors

    def warmup(self, width: int, height: int, track: bool = False) -> None:
        """Compile query preparation and ``localize`` for images of this size (a blank image:
        no keypoints, so a fallback result, with the shapes of any query), once per attempt
        ``cfg.retries`` allows (each retry's config is its own compilation), and with a
        descriptor cache (or, with ``track``, the stream's: ``cfg.track.cache_mb``) its
        per-reference path too (the cache is left empty); with ``track`` also the tracking
        step of :meth:`track`."""
        for what, v in (("width", width), ("height", height)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise VrsError(f"warmup: {what} must be an integer >= 1, got {v!r}")
        f = float(max(width, height))
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
        q = self.prepare(np.zeros((height, width), np.float32), K, None, "warm-up image")
        mine = self.cache
        if track and self._stream_cache():
            self.cache = DescriptorCache(self.cfg.track.cache_mb)  # the stream's, for now
        for a in range(retry_lib.attempts(self.map, self.cfg)):  # each retry's config too
            c = retry_lib.attempt_config(self.cfg, a)
            jax.block_until_ready(localize(self.map, q, c))
            if self.cache is not None:  # the cached path's stages, per attempt
                jax.block_until_ready(self._localize_cached(q, c).R)
        # warm-up renders are not the stream's: an empty cache (none if it was the stream's)
        self.cache = None if mine is None else DescriptorCache(mine.budget / 1e6)
        if track:
            R0, t0 = self.map.egm.R[0], self.map.egm.t[0]
            views = None
            if self.cfg.source == "render" and self.cfg.track.reference_views:
                held, self.cache = self.cache, None  # warm-up renders are not the stream's
                views = self._reference_views(q, R0, t0, (width, height), self.cfg)[:3]
                self.cache = held
            jax.block_until_ready(track_lib.track_step(
                self.map, q, R0, t0, (width, height), self.cfg, views))
            if self.cfg.track.frame_pass:  # the frame pass and the map points of a pose
                k = min(self.cfg.top_k, self.map.egm.num_images)
                pid = track_lib.frame_points_jit(self.map, q, R0, t0,
                                                 jnp.arange(k, dtype=jnp.int32),
                                                 self.cfg.track.associate_px)
                jax.block_until_ready(track_lib.frame_step(
                    self.map, q, (q.desc, pid, np.zeros(3)), (width, height), self.cfg))
