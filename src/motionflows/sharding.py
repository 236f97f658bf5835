"""Data-parallel scale-out on JAX's own runtime: one ``data`` mesh axis.

Parameters and optimiser state are replicated (``PartitionSpec()``), the batch is split
along its first axis (``PartitionSpec("data")``) over every device of every process. The
jitted train step is unchanged: XLA inserts the gradient all-reduce because the loss is a
mean over the sharded batch. Over several hosts, call :func:`initialize_distributed` first
(it wraps ``jax.distributed.initialize``); each process then loads the same global batch
(``dataset.batch`` is deterministic in (seed, index)) and contributes its own slice.
"""

from __future__ import annotations

import os
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

DATA_AXIS = "data"


def initialize_distributed(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
) -> bool:
    """Join a multi-host run via ``jax.distributed.initialize``; returns whether it did.

    Arguments default to the environment variables ``MOTIONFLOWS_COORDINATOR``
    (host:port of process 0), ``MOTIONFLOWS_NUM_PROCESSES`` and ``MOTIONFLOWS_PROCESS_ID``.
    With none given (and no cluster environment JAX detects by itself, such as SLURM or
    Cloud TPU), nothing happens and the run stays single-host.
    """
    env = os.environ
    coordinator_address = coordinator_address or env.get("MOTIONFLOWS_COORDINATOR")
    if num_processes is None and env.get("MOTIONFLOWS_NUM_PROCESSES"):
        num_processes = int(env["MOTIONFLOWS_NUM_PROCESSES"])
    if process_id is None and env.get("MOTIONFLOWS_PROCESS_ID"):
        process_id = int(env["MOTIONFLOWS_PROCESS_ID"])
    if coordinator_address is None and not any(
        k in env for k in ("SLURM_JOB_ID", "TPU_WORKER_HOSTNAMES", "OMPI_COMM_WORLD_SIZE")
    ):
        return False
    jax.distributed.initialize(
        coordinator_address=coordinator_address,
        num_processes=num_processes,
        process_id=process_id,
    )
    return True


def data_mesh(devices: Any = None) -> Mesh:
    """A 1-D mesh with axis ``"data"`` over ``devices`` (default: all devices of all hosts)."""
    devices = jax.devices() if devices is None else list(devices)
    return Mesh(np.asarray(devices), (DATA_AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


def batch_sharding(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec(DATA_AXIS))


def replicate(tree: Any, mesh: Mesh) -> Any:
    """Place every leaf of ``tree`` on all devices of ``mesh`` (a full copy each)."""
    return jax.device_put(tree, replicated(mesh))


def check_batch_size(batch_size: int, mesh: Mesh) -> None:
    n = mesh.devices.size
    if batch_size % n:
        raise ValueError(
            f"train.batch_size={batch_size} is not divisible by the {n} devices of the data "
            f"mesh; use a multiple of {n}, e.g. --set train.batch_size="
            f"{n * max(1, batch_size // n)}"
        )


def shard_batch(batch: dict[str, Any], mesh: Mesh) -> dict[str, jax.Array]:
    """Split a global batch (identical on every process) along axis 0 over the mesh.

    Each process keeps only its own rows (``process_index``-th of ``process_count`` equal
    slices) and :func:`jax.make_array_from_process_local_data` assembles the global array.
    """
    sharding = batch_sharding(mesh)
    pid, count = jax.process_index(), jax.process_count()
    out = {}
    for name, value in batch.items():
        value = np.asarray(value)
        check_batch_size(value.shape[0], mesh)
        per = value.shape[0] // count
        local = value[pid * per : (pid + 1) * per]
        out[name] = jax.make_array_from_process_local_data(sharding, local, value.shape)
    return out
