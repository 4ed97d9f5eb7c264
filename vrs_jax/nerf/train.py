"""Training the per-cluster NeRFs: one jitted step vmapped (and sharded) over clusters.

State is a pytree whose leaves all carry a leading cluster axis [C, ...] (parameters,
Adam state, PRNG key data) plus a scalar step. Each cluster draws its own ray batch from
its own image list every step. The cluster axis is sharded over the available devices
(``jax.sharding.Mesh`` with one axis ``"clusters"`` + ``NamedSharding``); the vmapped
clusters never communicate, so the sharded step computes exactly the unsharded one.

Checkpoints: orbax ``CheckpointManager`` under ``<out>/checkpoints``. Orbax writes each
step into a temporary directory and renames it when complete, so a checkpoint is either
whole or absent (atomic); resume restores step, parameters, optimizer state and RNG key,
which makes a resumed run bit-for-bit the continuation of the uninterrupted one (the step
function is deterministic). A NaN/inf guard checks the loss and the updated parameters
on device every step; the host reads that flag with the loss and PSNR every ``log_every``
steps and stops before anything non-finite, or collapsed (:func:`check_health`), is saved.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import functools
import io
import json
import logging
import math
import os
import resource
import shutil
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm.auto import tqdm

from vrs_jax import fileio
from vrs_jax.data.scene import Scene
from vrs_jax.errors import VrsError, sigterm_deferred, sigterm_stops
from vrs_jax.nerf import clusters as clusters_lib
from vrs_jax.nerf import data as data_lib
from vrs_jax.nerf import distributed as dist
from vrs_jax.nerf import patch_pool
from vrs_jax.nerf.config import NerfConfig
from vrs_jax.nerf.ilm import ILM
from vrs_jax.nerf.model import (
    Field,
    depth_loss,
    init_stacked_params,
    inner_radius,
    mse_to_psnr,
    nerf_loss,
    render_levels,
    render_rays,
    window_loss,
)

Array = jax.Array
CLUSTER_AXIS = "clusters"


class TrainingDiverged(VrsError):
    """The loss or the parameters became NaN/inf; the last good checkpoint is kept."""


class TrainState(NamedTuple):
    """step: [] int32; params, opt_state: pytrees [C, ...]; key: [C, 2] uint32 key data."""

    step: Array
    params: Any
    opt_state: Any
    key: Array


@struct.dataclass
class ClusterData:
    """Per-cluster constants of training: image lists (padded) and normalisation.

    members [C, M] int32, counts [C] int32, center [C, 3], scale [C], background [C, 3].
    """

    members: Array
    counts: Array
    center: Array
    scale: Array
    background: Array


# ----------------------------------------------------------------------------- optimiser


def rate_before_warmup(step: Any, cfg: NerfConfig, restart: tuple[int, float] | None = None
                       ) -> Any:
    """The schedule's rate at ``step`` (scalar or array) before the warm-up factor:
    log-linear lr_init -> lr_final over [0, max_steps], or, from ``restart = (s0, lr0)``'s
    step s0 on, log-linear lr0 -> lr_final over [s0, max_steps]."""
    step = jnp.asarray(step, jnp.float32)
    t = jnp.clip(step / cfg.max_steps, 0.0, 1.0)
    lr = jnp.exp(math.log(cfg.lr_init) * (1 - t) + math.log(cfg.lr_final) * t)
    if restart is not None:
        s0, lr0 = restart
        u = jnp.clip((step - s0) / max(cfg.max_steps - s0, 1), 0.0, 1.0)
        later = jnp.exp(math.log(lr0) * (1 - u) + math.log(cfg.lr_final) * u)
        lr = jnp.where(step >= s0, later, lr)
    return lr


def lr_schedule(cfg: NerfConfig, restart: tuple[int, float] | None = None
                ) -> Callable[[Array], Array]:
    """mip-NeRF's schedule: log-linear lr_init -> lr_final over max_steps, times a
    sine warm-up from lr_delay_mult to 1 over lr_delay_steps. ``restart`` (s0, lr0): a run
    continued at step s0 with another max_steps than its checkpoint's goes on from the rate
    lr0 it had reached down to lr_final (:func:`continued_schedule`), instead of jumping to
    the new horizon's rate at s0 (4,000 -> 12,000 steps of cpu-small: 4.6x up, and the
    walk's run diverged)."""

    def schedule(step):
        step = jnp.asarray(step, jnp.float32)
        lr = rate_before_warmup(step, cfg, restart)
        if cfg.lr_delay_steps > 0:
            w = jnp.sin(0.5 * jnp.pi * jnp.clip(step / cfg.lr_delay_steps, 0.0, 1.0))
            lr = lr * (cfg.lr_delay_mult + (1 - cfg.lr_delay_mult) * w)
        return lr

    return schedule


def continued_schedule(cfg: NerfConfig, step: int, old_max_steps: int,
                       old_restart: tuple[int, float] | None) -> tuple[int, float] | None:
    """The restart of a run resumed at ``step`` from a checkpoint trained for
    ``old_max_steps`` (with its own restart, or None): unchanged when the horizon is the
    same, else (step, the rate the checkpoint's schedule had reached there)."""
    if old_max_steps == cfg.max_steps:
        return old_restart
    old = dataclasses.replace(cfg, max_steps=old_max_steps)
    return (int(step), float(rate_before_warmup(step, old, old_restart)))


def make_optimizer(cfg: NerfConfig, restart: tuple[int, float] | None = None
                   ) -> optax.GradientTransformation:
    adam = optax.adam(lr_schedule(cfg, restart), b1=cfg.adam_b1, b2=cfg.adam_b2,
                      eps=cfg.adam_eps)
    if cfg.grad_max_norm > 0:
        return optax.chain(optax.clip_by_global_norm(cfg.grad_max_norm), adam)
    return adam


def init_state(cfg: NerfConfig, n_clusters: int, seed: int | None = None) -> TrainState:
    """Fresh state for C clusters (independent initialisations and keys)."""
    key = jax.random.key(cfg.seed if seed is None else seed)
    k_init, k_train = jax.random.split(key)
    params = init_stacked_params(k_init, cfg, n_clusters)
    opt_state = jax.vmap(make_optimizer(cfg).init)(params)
    keys = jax.random.key_data(jax.random.split(k_train, n_clusters))
    return TrainState(jnp.zeros((), jnp.int32), params, opt_state, keys)


# ----------------------------------------------------------------------------- step


@functools.lru_cache(maxsize=8)
def make_train_step(cfg: NerfConfig, donate: bool = True,
                    restart: tuple[int, float] | None = None
                    ) -> Callable[[TrainState, ClusterData, data_lib.RayBank],
                                  tuple[TrainState, dict[str, Array]]]:
    """The jitted training step for all clusters at once.

    Returns ``step(state, clusters, bank) -> (state, metrics)`` with metrics of shape [C]:
    loss, psnr (fine level, training batch), finite (loss and new params all finite).
    """
    optimizer = make_optimizer(cfg, restart)

    def one_cluster(params, opt_state, key_data, members, count, center, scale, background,
                    bank):
        key = jax.random.wrap_key_data(key_data)
        key, k_batch, k_render = jax.random.split(key, 3)
        batch = data_lib.sample_rays(bank, members, count, k_batch, cfg.batch_size)
        n_pool = data_lib.pool_rays_per_batch(bank, cfg.batch_size)

        def loss_fn(p):
            field = Field(p, center, scale, background)
            levels = render_levels(field, batch["origins"], batch["directions"],
                                   batch["radii"], batch["near"], batch["far"], k_render, cfg,
                                   randomized=True)
            loss, mse = nerf_loss(levels, batch["rgb"], cfg)
            if cfg.depth_loss_mult > 0:
                loss = loss + cfg.depth_loss_mult * depth_loss(levels, batch["depth"],
                                                               cfg.depth_loss_margin)
            if cfg.window_loss_mult > 0 and n_pool > 0:  # the pool rays lead the batch
                b = {k: v[:n_pool] for k, v in batch.items()}
                loss = loss + cfg.window_loss_mult * window_loss(
                    field, b["origins"], b["directions"], b["radii"], b["rgb"], b["depth"],
                    jax.random.fold_in(k_render, 1), cfg)
            return loss, mse

        (loss, mse), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        finite = jnp.isfinite(loss) & jnp.all(jnp.stack(
            [jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(params)]))
        metrics = {"loss": loss, "psnr": mse_to_psnr(mse), "finite": finite}
        return params, opt_state, jax.random.key_data(key), metrics

    vmapped = jax.vmap(one_cluster, in_axes=(0, 0, 0, 0, 0, 0, 0, 0, None))

    def step(state: TrainState, cl: ClusterData, bank: data_lib.RayBank):
        params, opt_state, keys, metrics = vmapped(
            state.params, state.opt_state, state.key, cl.members, cl.counts, cl.center,
            cl.scale, cl.background, bank)
        return TrainState(state.step + 1, params, opt_state, keys), metrics

    return jax.jit(step, donate_argnums=(0,) if donate else ())


# ----------------------------------------------------------------------------- sharding


def cluster_mesh(n_clusters: int, devices: list | None = None) -> Mesh:
    """A 1-D mesh over as many devices as evenly divide the cluster count.

    Multi-process (``jax.distributed``): over the global devices, the same number from every
    process (:func:`vrs_jax.nerf.distributed.mesh_devices`).
    """
    if dist.is_multiprocess():
        return Mesh(np.array(dist.mesh_devices(n_clusters, devices)), (CLUSTER_AXIS,))
    devices = list(jax.devices() if devices is None else devices)
    d = max(k for k in range(1, len(devices) + 1) if n_clusters % k == 0)
    return Mesh(np.array(devices[:d]), (CLUSTER_AXIS,))


def shard_clusters(tree: Any, mesh: Mesh) -> Any:
    """Place every leaf's leading (cluster) axis across the mesh; scalars are replicated."""

    put_ = dist.put_global if dist.is_multiprocess() else jax.device_put

    def put(x):
        spec = PartitionSpec(CLUSTER_AXIS) if np.ndim(x) > 0 else PartitionSpec()
        return put_(x, NamedSharding(mesh, spec))

    return jax.tree.map(put, tree)


def replicate(tree: Any, mesh: Mesh) -> Any:
    put_ = dist.put_global if dist.is_multiprocess() else jax.device_put
    return jax.tree.map(lambda x: put_(x, NamedSharding(mesh, PartitionSpec())), tree)


def shard_state(state: TrainState, mesh: Mesh) -> TrainState:
    return TrainState(replicate(state.step, mesh), shard_clusters(state.params, mesh),
                      shard_clusters(state.opt_state, mesh), shard_clusters(state.key, mesh))


# ----------------------------------------------------------------------------- preparation


@dataclasses.dataclass
class Prepared:
    """Everything training needs, built once from a Scene."""

    cfg: NerfConfig
    refs: Scene  # posed reference images used for training
    held_out: Scene  # posed query images used for evaluation (may be empty)
    near: np.ndarray  # [N_refs]
    far: np.ndarray
    held_near: np.ndarray  # [N_held]
    held_far: np.ndarray
    clustering: clusters_lib.Clustering
    cluster_data: ClusterData
    bank: data_lib.RayBank
    background: np.ndarray  # [3]
    held_images: list[np.ndarray]
    held_cluster: np.ndarray  # [N_held]
    eval_batch: dict[str, np.ndarray] | None  # rays grouped per cluster [C, M] + mask

    def ilm(self, params: Any) -> ILM:
        cd = self.cluster_data
        fields = Field(params=params, center=cd.center, scale=cd.scale,
                       background=cd.background)
        return ILM(fields=fields, cluster_centers=jnp.asarray(self.clustering.centers,
                                                              jnp.float32),
                   image_cluster=jnp.asarray(self.clustering.primary),
                   membership=jnp.asarray(self.clustering.membership),
                   near=jnp.asarray(self.near), far=jnp.asarray(self.far),
                   image_names=tuple(self.refs.names), config=self.cfg)

    def fingerprint(self) -> dict[str, Any]:
        return {"images": list(self.refs.names), "clusters": int(len(self.clustering.centers))}


def prepare(scene: Scene, cfg: NerfConfig, near: float | None = None, far: float | None = None,
            points3d: np.ndarray | None = None, patch_keypoints: tuple | None = None
            ) -> Prepared:
    """Split, near/far, clusters, normalisation, images -> device ray bank, eval rays.

    ``patch_keypoints``: optional ``(keypoints [N, K_max, 4], mask [N, K_max], PatchConfig)``
    or that plus ``depths [N, K_max]`` (each keypoint's 3D point z-depth, <= 0 none: the
    depth loss's targets)
    of the map, N = the scene's posed reference images in order; with
    ``cfg.patch_ray_fraction > 0`` their patch samples join the training rays
    (nerf/patch_pool.py).
    """
    data_lib.check_scene_for_training(scene)
    posed = np.asarray(scene.has_pose)
    refs = scene.subset(~np.asarray(scene.is_query) & posed)
    held = scene.subset(np.asarray(scene.is_query) & posed)
    n_near, n_far = data_lib.scene_near_far(scene, near, far, points3d,
                                            cfg.near_far_percentiles, cfg.near_far_margin)
    ref_idx = np.flatnonzero(~np.asarray(scene.is_query) & posed)
    held_idx = np.flatnonzero(np.asarray(scene.is_query) & posed)
    r_near, r_far = n_near[ref_idx], n_far[ref_idx]
    if cfg.n_clusters > len(refs):
        raise VrsError(f"{cfg.n_clusters} clusters requested but only {len(refs)} reference "
                       "images", scene.root)
    clustering = clusters_lib.cluster_cameras(refs.centers, cfg.n_clusters,
                                              cfg.cluster_overlap, seed=cfg.seed,
                                              method=cfg.cluster_method)
    clusters_lib.check_nonempty(clustering.membership)
    members, counts = data_lib.pad_members(clustering.membership)
    background = np.asarray(scene.background if scene.background is not None else (0, 0, 0),
                            np.float32)
    centers, scales = [], []
    typical = data_lib.typical_depths(
        r_near, r_far, None if points3d is None or not len(points3d)
        else data_lib.point_depths(refs, points3d))
    if not cfg.contraction:
        ratio = data_lib.unbounded_ratio(refs.centers, typical, r_far)
        if ratio > data_lib.UNBOUNDED_RATIO:
            warnings.warn(f"the scene looks unbounded (its far bounds are {ratio:.0f}x the "
                          "radius of the region its cameras see up close): --set "
                          "contraction=true keeps the far field without spending the grid "
                          "on it", stacklevel=2)
    for c in range(cfg.n_clusters):
        sel = clustering.membership[c]
        if cfg.contraction:
            ctr, radius = data_lib.inner_ball(refs.centers[sel], typical[sel])
            s = inner_radius(cfg.norm_radius) / radius
        else:
            pts = data_lib.frustum_points(refs.K[sel], refs.R[sel], refs.t[sel],
                                          refs.sizes[sel], r_near[sel], r_far[sel])
            ctr, s = data_lib.normalization(pts, cfg.norm_radius)
        centers.append(ctr)
        scales.append(s)
    cd = ClusterData(members=jnp.asarray(members), counts=jnp.asarray(counts),
                     center=jnp.asarray(np.stack(centers), jnp.float32),
                     scale=jnp.asarray(np.asarray(scales), jnp.float32),
                     background=jnp.asarray(np.tile(background, (cfg.n_clusters, 1))))
    ref_images = data_lib.load_images(refs, background)
    pool = None
    if patch_keypoints is not None and cfg.patch_ray_fraction > 0:
        kps, kmask, pcfg = patch_keypoints[:3]
        kdepth = patch_keypoints[3] if len(patch_keypoints) > 3 else None
        if len(kps) != len(refs):
            raise VrsError(f"patch keypoints given for {len(kps)} images, the scene has "
                           f"{len(refs)} posed reference images", scene.root)
        pool = patch_pool.patch_pool(refs, np.asarray(kps), np.asarray(kmask), pcfg, r_near,
                                     r_far, cfg.patch_pool_max_rays, cfg.seed, background,
                                     None if kdepth is None else np.asarray(kdepth))
    bank = data_lib.build_bank(refs, r_near, r_far, ref_images, pool, cfg.patch_ray_fraction)
    del ref_images
    held_images = data_lib.load_images(held, background) if len(held) else []
    held_cluster = (clusters_lib.assign_to_clusters(held.centers, clustering.centers)
                    if len(held) else np.zeros(0, np.int32))
    h_near, h_far = n_near[held_idx], n_far[held_idx]
    eval_batch = None
    if len(held):
        ev = data_lib.eval_rays(held, h_near, h_far, held_images, cfg.eval_rays, seed=cfg.seed)
        eval_batch = group_by_cluster(ev, held_cluster[ev["image"]], cfg.n_clusters)
    return Prepared(cfg, refs, held, r_near, r_far, h_near, h_far, clustering, cd, bank,
                    background, held_images, held_cluster, eval_batch)


def group_by_cluster(rays: dict[str, np.ndarray], cluster: np.ndarray, n_clusters: int
                     ) -> dict[str, np.ndarray]:
    """Rays [M, ...] -> [C, Mmax, ...] padded per cluster, plus mask [C, Mmax]."""
    idx = [np.flatnonzero(cluster == c) for c in range(n_clusters)]
    mmax = max(1, max(len(i) for i in idx))
    out: dict[str, np.ndarray] = {}
    for k, v in rays.items():
        arr = np.zeros((n_clusters, mmax) + v.shape[1:], v.dtype)
        for c, i in enumerate(idx):
            arr[c, : len(i)] = v[i]
            if len(i) and len(i) < mmax:
                arr[c, len(i):] = v[i[0]]  # valid padding rays (masked out of the metric)
            elif not len(i) and k in ("directions", "near", "far"):
                arr[c] = {"directions": (0.0, 0.0, 1.0), "near": 1.0, "far": 2.0}[k]
        out[k] = arr
    mask = np.zeros((n_clusters, mmax), np.float32)
    for c, i in enumerate(idx):
        mask[c, : len(i)] = 1
    out["mask"] = mask
    return out


@functools.lru_cache(maxsize=8)
def make_eval_fn(cfg: NerfConfig) -> Callable[[Any, ClusterData, dict[str, Array]], Array]:
    """Jitted held-out PSNR over grouped eval rays: (params [C], clusters, batch) -> PSNR []."""

    def one(params, center, scale, background, b):
        field = Field(params, center, scale, background)

        def chunk(rays):
            return render_rays(field, rays["origins"], rays["directions"], rays["radii"],
                               rays["near"], rays["far"], None, cfg)["rgb"]

        n = b["origins"].shape[0]
        size = min(cfg.render_chunk, n)
        pad = (-n) % size
        rays = {k: jnp.concatenate([b[k], jnp.repeat(b[k][:1], pad, axis=0)])
                for k in ("origins", "directions", "radii", "near", "far")}
        rays = jax.tree.map(lambda x: x.reshape((-1, size) + x.shape[1:]), rays)
        rgb = jax.lax.map(chunk, rays).reshape(-1, 3)[:n]
        se = jnp.mean((rgb - b["rgb"]) ** 2, axis=-1)
        # where, not a product: padding rays of a cluster without held-out views are zeros
        # (zero directions) and render as NaN.
        return jnp.sum(jnp.where(b["mask"] > 0, se, 0.0)), jnp.sum(b["mask"])

    def fn(params, cl: ClusterData, batch):
        se, cnt = jax.vmap(one)(params, cl.center, cl.scale, cl.background, batch)
        return mse_to_psnr(jnp.sum(se) / jnp.maximum(jnp.sum(cnt), 1.0))

    return jax.jit(fn)


# ----------------------------------------------------------------------------- checkpoints


def checkpoint_manager(ckpt_dir: str | Path, cfg: NerfConfig) -> ocp.CheckpointManager:
    """Synchronous orbax manager (atomic per step: tmp dir + rename on completion).

    Raises VrsError naming the folder when it cannot be created (read-only, not a folder).
    """
    d = Path(ckpt_dir).absolute()
    if d.exists() and not d.is_dir():
        raise VrsError("checkpoint path exists and is not a folder", d)
    fileio.check_writable(d)  # permission / read-only: one line before orbax starts
    opts = ocp.CheckpointManagerOptions(max_to_keep=cfg.keep_checkpoints, create=True,
                                        enable_async_checkpointing=False)
    try:
        return ocp.CheckpointManager(d, options=opts, item_names=("state", "meta"))
    except Exception as e:  # noqa: BLE001 - orbax wraps OSErrors in several types
        raise VrsError(f"cannot open the checkpoint folder: {fileio.reason(e)}", d) from None


def _from_orbax(tb) -> bool:
    while tb is not None:
        f = tb.tb_frame.f_code.co_filename
        if "orbax" in f or "tensorstore" in f:
            return True
        tb = tb.tb_next
    return False


class _DropOrbaxNoise(logging.Filter):
    """Drops log records about orbax's work (its worker threads and asyncio tasks log each
    failed write with a full traceback, while the caller gets the exception anyway)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if "orbax" in record.pathname:
            return False
        exc = record.exc_info[2] if record.exc_info else None
        if record.exc_info and str(record.exc_info[1]) == "Event loop is closed":
            return False  # orbax's cancelled writes completing into their closed loops
        return not (_from_orbax(exc) or "orbax" in str(record.msg) or
                    any("orbax" in str(a) for a in (record.args or ()) if isinstance(a, str)))


_DROP_ORBAX = _DropOrbaxNoise()
_FAILED = {"save": False}


def _quiet_orbax_logs() -> None:
    """Drop orbax's own log records of a failed write (its threads log the failure with full
    tracebacks; the caller gets one VrsError line). Other records still show."""
    for name in ("absl", "asyncio", "concurrent.futures"):
        logging.getLogger(name).addFilter(_DROP_ORBAX)
    for h in [logging.lastResort, *logging.getLogger().handlers]:
        if h is not None:
            h.addFilter(_DROP_ORBAX)


@contextlib.contextmanager
def _captured_noise() -> Iterator[None]:
    """Keep what orbax and tensorstore print while reading a damaged checkpoint (absl/orbax
    log records, tracebacks of their callbacks into closed event loops) off the terminal:
    the caller reports the failure as one line. Captured text goes to the DEBUG log."""
    buf = io.StringIO()
    handler = logging.StreamHandler(buf)
    loggers = [logging.getLogger(n) for n in ("absl", "orbax", "asyncio")]
    saved = [(lg.handlers, lg.propagate) for lg in loggers]
    for lg in loggers:
        lg.handlers, lg.propagate = [handler], False
    try:
        with contextlib.redirect_stderr(buf):
            yield
    finally:
        for lg, (handlers, propagate) in zip(loggers, saved, strict=True):
            lg.handlers, lg.propagate = handlers, propagate
        if buf.getvalue():
            logging.getLogger("vrs_jax").debug("orbax while restoring:\n%s", buf.getvalue())


def _preflight(directory: Path, tree: Any, step: int) -> None:
    """Refuse a save that cannot fit before orbax starts it (orbax's failure midway is noisy):
    free space on the device and the process's file size limit against the state's bytes."""
    need = sum(int(x.nbytes) if isinstance(x, jax.Array) else int(np.asarray(x).nbytes)
               for x in jax.tree.leaves(tree))  # jax.Array: the global size (multi-process)
    try:
        free = shutil.disk_usage(directory).free
    except OSError:
        free = None
    if free is not None and free < need + (1 << 20):
        raise VrsError(f"cannot save the checkpoint of step {step}: no space left on the device "
                       f"(needs about {need / 1e6:.1f} MB, {free / 1e6:.1f} MB free)", directory)
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if soft != resource.RLIM_INFINITY and soft < need:
        raise VrsError(f"cannot save the checkpoint of step {step}: file too large for this "
                       f"file system or limit (disk full?) (needs about {need / 1e6:.1f} MB, "
                       f"file size limit {soft} bytes)", directory)


def _remove_partial(directory: Path, wait: bool = False) -> None:
    """Delete orbax's temporary step folders left by a failed save (``wait``: first let
    orbax's worker threads end, they may still be writing; once more at exit)."""
    if wait:
        for t in threading.enumerate():
            if t is not threading.current_thread() and "orbax" in type(t).__module__:
                try:
                    t.join(timeout=10)
                except Exception:  # noqa: BLE001, S110 - orbax's join re-raises the failure
                    pass

    def remove():
        for _ in range(5):  # tensorstore may still add files while the folder goes
            left = list(directory.glob("*.orbax-checkpoint-tmp*"))
            if not left:
                return
            for p in left:
                shutil.rmtree(p, ignore_errors=True)
            time.sleep(0.05)

    remove()
    if wait:
        atexit.register(remove)


def save_checkpoint(mngr: ocp.CheckpointManager, state: TrainState, meta: dict[str, Any]
                    ) -> None:
    """Save ``state`` as step ``state.step``, synchronously.

    Raises VrsError (one line naming the checkpoint folder: disk full, permission denied...)
    when the save fails; orbax's partial temporary folder is removed, earlier checkpoints
    stay intact.
    """
    step = int(state.step)
    tree = {"step": state.step, "params": state.params, "opt_state": state.opt_state,
            "key": state.key}
    directory = Path(str(mngr.directory))
    _preflight(directory, tree, step)
    _quiet_orbax_logs()
    try:
        with sigterm_deferred():  # a stop waits for the whole checkpoint
            mngr.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(tree),
                                                    meta=ocp.args.JsonSave(meta)), force=True)
            mngr.wait_until_finished()
    except Exception as e:  # noqa: BLE001 - orbax/tensorstore wrap the OSError
        _FAILED["save"] = True
        _remove_partial(directory)
        raise VrsError(f"cannot save the checkpoint of step {step}: {fileio.reason(e)}",
                       directory) from None


def restore_checkpoint(mngr: ocp.CheckpointManager, template: TrainState,
                       step: int | None = None) -> tuple[TrainState, dict[str, Any]]:
    """Restore the latest (or given) step into the structure/shardings of ``template``.

    Raises VrsError for a corrupt or incompatible checkpoint.
    """
    step = mngr.latest_step() if step is None else step
    where = Path(str(mngr.directory)) / str(step)
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct,
                            {"step": template.step, "params": template.params,
                             "opt_state": template.opt_state, "key": template.key})
    try:
        out = mngr.restore(step, args=ocp.args.Composite(
            state=ocp.args.StandardRestore(abstract), meta=ocp.args.JsonRestore()))
    except Exception as e:  # orbax/tensorstore raise many types for damaged files
        msg = str(e).splitlines()[0][:160] if str(e) else ""
        raise VrsError(f"corrupt or incompatible checkpoint ({type(e).__name__}: {msg})",
                       where) from None
    tree, meta = out["state"], out["meta"]
    leaves = jax.tree.leaves(tree)
    if not all(np.all(np.isfinite(np.asarray(x))) for x in leaves
               if jnp.issubdtype(x.dtype, jnp.floating)):
        raise VrsError("checkpoint holds non-finite values", where)
    if int(tree["step"]) != int(step):
        raise VrsError(f"checkpoint records step {int(tree['step'])}, not {step}", where)
    return TrainState(tree["step"], tree["params"], tree["opt_state"], tree["key"]), meta


def restore_latest(mngr: ocp.CheckpointManager, template: TrainState,
                   warn: Callable[[str], None] | None = None
                   ) -> tuple[TrainState, dict[str, Any], list[int]]:
    """Restore the newest checkpoint that reads back intact.

    Tries the steps newest first; each one that fails (corrupt, truncated, non-finite) is
    reported through ``warn`` naming its folder, and the next older one is tried.

    Returns:
      (state, meta, bad steps skipped, newest first).
    Raises:
      VrsError naming the checkpoint folder when none restores.
    """
    warn = warn or (lambda s: warnings.warn(s, stacklevel=3))
    steps = sorted(mngr.all_steps(), reverse=True)
    bad: list[int] = []
    lines: list[str] = []
    with _captured_noise():  # orbax's noise about the damaged ones stays off the terminal
        for s in steps:
            try:
                state, meta = restore_checkpoint(mngr, template, s)
                break
            except VrsError as e:
                bad.append(s)
                lines.append(f"warning: {e}; trying an earlier checkpoint")
        else:
            state = None
        if bad:
            time.sleep(0.5)  # tensorstore's late callbacks into orbax's closed loops
    for line in lines:
        warn(line)
    if state is None:
        raise VrsError(f"none of the {len(steps)} checkpoint(s) restores (corrupt or "
                       "incompatible checkpoint data); move the folder away to train from "
                       "scratch", Path(str(mngr.directory)))
    if bad:
        warn(f"warning: resumed from step {s}, the newest intact checkpoint (skipped "
             f"damaged step(s) {', '.join(map(str, bad))})")
    return state, meta, bad


def set_aside(mngr: ocp.CheckpointManager, steps: list[int]) -> ocp.CheckpointManager:
    """Move damaged step folders out of the manager's folder (to ``<folder>-damaged/``, kept
    for inspection) so that training can save those steps again; returns a reloaded manager.
    """
    directory = Path(str(mngr.directory))
    aside = directory.with_name(directory.name + "-damaged")
    try:
        for s in steps:
            aside.mkdir(exist_ok=True)
            dest = aside / f"{s}-{time.strftime('%Y%m%d-%H%M%S')}"
            os.replace(directory / str(s), dest)  # fileio-exempt: moves a folder
    except OSError as e:
        raise VrsError(f"cannot move a damaged checkpoint aside: {fileio.reason(e)}",
                       directory) from None
    mngr.reload()
    return mngr


# ----------------------------------------------------------------------------- loop


# A cluster whose training-batch PSNR level falls this far below its best level of the run
# (from the first step on) has collapsed (an lr far too high: 3.9 dB against 19.4 on the
# synthetic room); healthy runs stay within about 1 dB of their best.
COLLAPSE_DB = 6.0
# The level is the median of the last 3 host reads, each one batch's PSNR: a small batch's
# PSNR swings by several dB (64-ray batches of the phone walk's 4-cluster map: 22.3 -> 16.1
# dB on one read), so the best single read of a long run is no baseline (such runs were
# stopped as diverged at steps 3,500-10,900 and went on fine); a collapse persists.
COLLAPSE_READS = 3


@dataclasses.dataclass
class Health:
    """The PSNR collapse check's memory: per cluster, the last reads and the best level."""

    recent: list[np.ndarray] = dataclasses.field(default_factory=list)  # <= COLLAPSE_READS x [C]
    best: np.ndarray | None = None  # [C] best level so far

    def update(self, psnr: np.ndarray) -> np.ndarray:
        """Add one read [C]; returns the level [C] (median of the recent reads)."""
        self.recent = [*self.recent, np.asarray(psnr, np.float64)][-COLLAPSE_READS:]
        level = np.median(np.stack(self.recent), axis=0)
        self.best = level if self.best is None else np.fmax(self.best, level)
        return level


def check_health(m: dict[str, np.ndarray], health: Health, step: int,
                 last_good: int | None, out_dir: str | Path | None) -> bool:
    """Raise TrainingDiverged when the host-read metrics ``m`` ([C] loss, psnr, finite) show
    non-finite values or a PSNR collapse (the level, :class:`Health`, :data:`COLLAPSE_DB`
    below its best so far). Returns whether this read alone is that low (suspect: the caller
    saves no checkpoint until the level says whether it was noise)."""
    psnr = np.asarray(m["psnr"], np.float64)
    finite = np.asarray(m["finite"]) & np.isfinite(psnr)
    level = health.update(np.where(finite, psnr, -np.inf))
    collapsed = finite & (level < health.best - COLLAPSE_DB)
    if np.all(finite) and not np.any(collapsed):
        return bool(np.any(psnr < health.best - COLLAPSE_DB))
    where = (f"last good checkpoint: step {last_good} in {Path(out_dir) / 'checkpoints'}"
             if last_good is not None else "no checkpoint was saved yet")
    c = int(np.flatnonzero(~finite | collapsed)[0])
    what = (f"loss {float(m['loss'][c])}, parameters finite: no" if not finite[c] else
            f"training PSNR collapsed to {psnr[c]:.1f} dB from {health.best[c]:.1f}")
    raise TrainingDiverged(f"training diverged by step {step} (cluster {c}: {what}); stopped; "
                           f"{where}; try a lower lr_init")


@dataclasses.dataclass
class TrainResult:
    state: TrainState
    ilm: ILM
    history: list[dict[str, float]]
    steps_per_s: float
    seconds: float
    compile_s: float


def train(prep: Prepared, out_dir: str | Path | None, steps: int | None = None,
          minutes: float | None = None, resume: bool = True, progress: bool = True,
          mesh: Mesh | None = None, log: Callable[[str], None] | None = None) -> TrainResult:
    """Train until ``steps`` total steps or ``minutes`` of wall clock (whichever first).

    Args:
      prep: from :func:`prepare`.
      out_dir: checkpoints go to ``out_dir/checkpoints`` (None: no checkpoints).
      steps: total step count to reach (default the config's ``max_steps``; resume counts
        the steps already done).
      minutes: wall-clock cap of this call (compilation included); a later call resumes.
      resume: continue from the latest checkpoint in out_dir when there is one.
      mesh: device mesh for the cluster axis (default: all devices, see cluster_mesh).

    Multi-process (after ``jax.distributed.initialize``, see nerf/distributed.py): every
    process calls ``train`` with the same arguments; each trains its shard of the clusters,
    all write the orbax checkpoints together, only process 0 logs and shows progress; the
    returned state and ILM hold every cluster's parameters on every process.
    Raises:
      TrainingDiverged (a VrsError) when the loss or parameters become non-finite; the last
      good checkpoint stays on disk.
    """
    cfg = prep.cfg
    if steps is None:
        steps = cfg.max_steps
    log = log or (lambda s: tqdm.write(s))
    multi = dist.is_multiprocess()
    if multi and not dist.is_primary():
        log, progress = (lambda _: None), False
    t_start = time.perf_counter()
    n_c = cfg.n_clusters
    mesh = mesh or cluster_mesh(n_c)
    state = init_state(cfg, n_c)
    meta = {"config": cfg.to_dict(), "scene": prep.fingerprint()}
    restart = None  # a resumed run's learning-rate restart (lr_schedule)
    mngr = None
    if out_dir is not None:
        mngr = checkpoint_manager(Path(out_dir) / "checkpoints", cfg)
        if not resume and mngr.latest_step() is not None:
            mngr.close()
            raise VrsError("folder already holds checkpoints: resume, or train into another "
                           "folder", Path(out_dir) / "checkpoints")
        if resume and mngr.latest_step() is not None:
            try:
                state, old, bad = restore_latest(mngr, state, warn=log)
                # a longer run of the same map continues (only the step budget differs)
                same = {**NerfConfig.ADDED_FIELDS, **(old.get("config") or {}),
                        "max_steps": cfg.max_steps}
                if json.dumps(same, sort_keys=True) != json.dumps(meta["config"],
                                                                   sort_keys=True):
                    raise VrsError("checkpoint was trained with a different config; use "
                                   "another output folder", Path(out_dir) / "checkpoints")
                if old.get("scene") != meta["scene"]:
                    raise VrsError("checkpoint belongs to a different scene or clustering",
                                   Path(out_dir) / "checkpoints")
                if bad:
                    mngr = set_aside(mngr, bad)
            except VrsError:
                mngr.close()
                raise
            old_max = int((old.get("config") or {}).get("max_steps", cfg.max_steps))
            old_restart = old.get("lr_restart")
            restart = continued_schedule(cfg, int(state.step), old_max,
                                         tuple(old_restart) if old_restart else None)
            if old_max != cfg.max_steps:
                log(f"resumed from step {int(state.step)} (trained for {old_max} steps): "
                    f"the learning rate goes on from {restart[1]:.3g} to {cfg.lr_final:.3g} "
                    f"at step {cfg.max_steps}")
            else:
                log(f"resumed from step {int(state.step)}")
    meta["lr_restart"] = list(restart) if restart is not None else None
    state = shard_state(state, mesh)
    cl = shard_clusters(prep.cluster_data, mesh)
    bank = replicate(prep.bank, mesh)
    step_fn = make_train_step(cfg, restart=restart)
    eval_fn = make_eval_fn(cfg) if prep.eval_batch is not None else None
    eval_batch = (shard_clusters(jax.tree.map(jnp.asarray, prep.eval_batch), mesh)
                  if eval_fn else None)

    start_step = int(state.step)
    target = steps if steps is not None else 10**12
    deadline = t_start + 60 * minutes if minutes is not None else math.inf
    last_good = mngr.latest_step() if mngr else None
    history: list[dict[str, float]] = []
    bar = tqdm(total=(target - start_step) if steps is not None else None, disable=not progress,
               desc=f"nerf[{cfg.name}]", dynamic_ncols=True, mininterval=1.0)
    compile_s, t_loop, aside_s = 0.0, None, 0.0  # aside: evaluation + checkpoint time
    steps_after_compile = start_step
    held = math.nan
    health = Health()
    stop_on_sigterm = sigterm_stops()  # a kill is a clean stop: checkpoints stay whole
    stop_on_sigterm.__enter__()
    try:
        s = start_step
        while s < target and (multi or time.perf_counter() < deadline):
            state, metrics = step_fn(state, cl, bank)
            s += 1  # counted on the host: no device sync per step
            if t_loop is None:  # the first step includes compilation
                jax.block_until_ready(state.step)
                # the starting point of the PSNR collapse check (one host read per run)
                health.update((dist.gather(metrics) if multi else jax.device_get(metrics))["psnr"])
                t_loop = time.perf_counter()
                compile_s = t_loop - t_start
                steps_after_compile = s
            if multi:  # the processes must stop at the same step: process 0's clock decides
                past = (s % cfg.log_every == 0 and math.isfinite(deadline)
                        and dist.agree(time.perf_counter() >= deadline))
            else:
                past = time.perf_counter() >= deadline
            read = (s % cfg.log_every == 0 or s % cfg.checkpoint_every == 0 or s >= target
                    or past or (eval_fn is not None and s % cfg.eval_every == 0))
            if not read:
                continue
            # steps are dispatched asynchronously: wait for the queued ones here, so that
            # their compute counts as training time and only the read, evaluation and
            # checkpoint below count as aside
            jax.block_until_ready(metrics)
            t_aside = time.perf_counter()
            # the only host read: every log_every steps
            m = dist.gather(metrics) if multi else jax.device_get(metrics)
            suspect = check_health(m, health, s, last_good, out_dir)
            rec = {"step": s, "loss": float(np.mean(m["loss"])),
                   "psnr": float(np.mean(m["psnr"])), "time": time.perf_counter() - t_start}
            if eval_fn is not None and (s % cfg.eval_every == 0):
                held = float(eval_fn(state.params, cl, eval_batch))
                rec["heldout_psnr"] = held
                log(f"step {s}: train psnr {rec['psnr']:.2f} held-out psnr {held:.2f}")
            history.append(rec)
            bar.update(s - bar.n)
            shown = {"loss": f"{rec['loss']:.4f}", "psnr": f"{rec['psnr']:.2f}"}
            if math.isfinite(held):  # held-out views exist and were evaluated
                shown["val"] = f"{held:.2f}"
            bar.set_postfix(shown, refresh=False)
            if mngr is not None and s % cfg.checkpoint_every == 0 and not suspect:
                save_checkpoint(mngr, state, meta)
                last_good = s
            aside_s += time.perf_counter() - t_aside
            if past:
                break
        jax.block_until_ready(state)
        t_end = time.perf_counter()
        done = int(state.step)
        if mngr is not None and done != last_good and done > start_step:
            save_checkpoint(mngr, state, meta)
    finally:
        stop_on_sigterm.__exit__(None, None, None)
        bar.close()
        if mngr is not None:
            try:
                mngr.close()
            except Exception:  # noqa: BLE001
                if not _FAILED["save"]:  # after a failed save, close re-raises it
                    raise
            if _FAILED["save"]:  # orbax's threads may have written on after the failure
                _remove_partial(Path(str(mngr.directory)), wait=True)
    # Training throughput: steps after the first (compiling) one, with evaluation and
    # checkpointing excluded.
    timed_steps = done - steps_after_compile
    loop_s = (t_end - t_loop - aside_s) if t_loop is not None else 0.0
    sps = timed_steps / loop_s if loop_s > 0 else 0.0
    params = dist.gather(state.params) if multi else jax.device_get(state.params)
    return TrainResult(state, prep.ilm(jax.tree.map(jnp.asarray, params)), history, sps,
                       t_end - t_start, compile_s)
