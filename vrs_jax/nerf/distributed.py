"""JAX's multi-process runtime for training: one process per host (or per GPU), one global mesh.

    python -m experiments.train_nerf ... --coordinator HOST0:PORT --num-processes N --process-id I

Every process runs the same program on the same data (``prepare`` is deterministic); the
cluster axis of the training state is sharded over the *global* device list
(``jax.devices()``: all processes' devices), so each process computes and holds only its own
clusters' parameters. The clusters never communicate during a step; host reads (metrics, the
final parameters) gather the shards with ``multihost_utils.process_allgather`` (on CPU through
JAX's gloo collectives, the default ``jax_cpu_collectives_implementation`` here). Orbax's
checkpointing is multi-host aware: every process calls save and writes its own shards, the
primary process (0) writes the metadata and commits the step folder (a shared file system is
needed, as for any orbax multi-host checkpoint).

Single-process runs never touch this module's collectives: :func:`is_multiprocess` is False
and training takes its original code path.
"""

from __future__ import annotations

import os
from typing import Any

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Sharding

from vrs_jax.errors import VrsError

ENV_COORDINATOR = "JAX_COORDINATOR_ADDRESS"  # read by jax.distributed itself too
ENV_NUM_PROCESSES = "JAX_NUM_PROCESSES"
ENV_PROCESS_ID = "JAX_PROCESS_ID"


def initialize(coordinator: str | None, num_processes: int | None, process_id: int | None,
               local_device_ids: list[int] | None = None, timeout_s: int = 300) -> bool:
    """Start JAX's distributed runtime when more than one process is asked for.

    Args:
      coordinator: "host:port" of process 0 (its coordinator service listens there); None
        reads $JAX_COORDINATOR_ADDRESS.
      num_processes, process_id: None reads $JAX_NUM_PROCESSES / $JAX_PROCESS_ID.
      local_device_ids: this process's accelerators (e.g. [0] for one GPU per process);
        None: all visible devices.
    Returns:
      True when the runtime was started (N > 1), False for a single-process run.
    Raises:
      VrsError for missing or inconsistent settings, or when the coordinator cannot be reached.
    """
    coordinator = coordinator or os.environ.get(ENV_COORDINATOR) or None
    if num_processes is None and os.environ.get(ENV_NUM_PROCESSES):
        num_processes = int(os.environ[ENV_NUM_PROCESSES])
    if process_id is None and os.environ.get(ENV_PROCESS_ID):
        process_id = int(os.environ[ENV_PROCESS_ID])
    if num_processes is None or num_processes <= 1:
        if process_id not in (None, 0):
            raise VrsError(f"process id {process_id} given for a single-process run "
                           "(set --num-processes)")
        return False
    if coordinator is None or process_id is None:
        raise VrsError(f"{num_processes} processes need --coordinator HOST:PORT and "
                       "--process-id I (or $JAX_COORDINATOR_ADDRESS and $JAX_PROCESS_ID)")
    if not 0 <= process_id < num_processes:
        raise VrsError(f"process id {process_id} is not in 0..{num_processes - 1}")
    if ":" not in coordinator:
        raise VrsError(f"coordinator address {coordinator!r} must be HOST:PORT")
    try:
        jax.distributed.initialize(coordinator, num_processes, process_id,
                                   local_device_ids=local_device_ids,
                                   initialization_timeout=timeout_s)
    except Exception as e:  # noqa: BLE001 - grpc/XLA raise several types
        msg = str(e).splitlines()[0][:200] if str(e) else type(e).__name__
        raise VrsError(f"process {process_id} of {num_processes} could not join the "
                       f"coordinator at {coordinator}: {msg}") from None
    return True


def is_multiprocess() -> bool:
    return jax.process_count() > 1


def is_primary() -> bool:
    """Process 0: the one that logs, writes the map and the reports."""
    return jax.process_index() == 0


def mesh_devices(n_clusters: int, devices: list | None = None) -> list:
    """Devices for a 1-D cluster mesh: the most devices d that divide the cluster count,
    taken evenly from every process (d a multiple of the process count, d / P local devices
    of each, in process order) so that every process holds a shard.

    Raises VrsError when the clusters cannot be spread over all processes.
    """
    devices = list(jax.devices() if devices is None else devices)
    n_proc = jax.process_count()
    per_proc: dict[int, list] = {}
    for d in devices:
        per_proc.setdefault(d.process_index, []).append(d)
    local = min(len(v) for v in per_proc.values())
    for k in range(local, 0, -1):
        if n_clusters % (k * n_proc) == 0:
            return [d for p in sorted(per_proc) for d in per_proc[p][:k]]
    raise VrsError(f"{n_clusters} cluster(s) cannot be split over {n_proc} processes: use a "
                   f"multiple of {n_proc} clusters (--clusters)")


def put_global(x: Any, sharding: Sharding) -> jax.Array:
    """A host value, identical on every process, as a global array with ``sharding``: each
    process places only its own shards. x: any array-like."""
    arr = np.asarray(x)
    return jax.make_array_from_callback(arr.shape, sharding, lambda idx: arr[idx])


def gather(tree: Any) -> Any:
    """Pytree of (possibly process-sharded) arrays -> the same tree of full numpy arrays on
    every process (a collective: all processes must call it at the same point)."""
    return multihost_utils.process_allgather(tree, tiled=True)


def agree(flag: bool) -> bool:
    """Process 0's value of ``flag`` on every process (e.g. a wall-clock deadline, which each
    process would otherwise see at a different step)."""
    return bool(multihost_utils.broadcast_one_to_all(np.asarray(flag)))


def barrier(name: str) -> None:
    multihost_utils.sync_global_devices(name)
