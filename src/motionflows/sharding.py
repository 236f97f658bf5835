"""Data-parallel scale-out on JAX's own runtime: one ``data`` mesh axis.

Parameters and optimiser state are replicated (``PartitionSpec()``), the batch is split
along its first axis (``PartitionSpec("data")``) over every device of every process. The
jitted train step is unchanged: XLA inserts the gradient all-reduce because the loss is a
mean over the sharded batch. Over several processes, join the run first
(:func:`motionflows.distributed.initialize`); each process then loads the same global batch
(``dataset.batch`` is deterministic in (seed, index)) and contributes its own slice.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

DATA_AXIS = "data"


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


def shard_batch(batch: Any, mesh: Mesh) -> Any:
    """Split a global batch (identical on every process) along axis 0 over the mesh.

    ``batch`` is any pytree of arrays (a dict of them, or one array), each with the batch
    on axis 0; the same pytree of sharded arrays comes back. Each process puts on each of
    its own devices exactly the rows that the ``data`` sharding gives that device
    (:func:`jax.make_array_from_callback`), so the processes feed disjoint slices whose
    union is the global batch, whatever the mesh's device order.
    """
    sharding = batch_sharding(mesh)

    def put(value):
        value = np.asarray(value)
        check_batch_size(value.shape[0], mesh)
        return jax.make_array_from_callback(value.shape, sharding, lambda index: value[index])

    return jax.tree.map(put, batch)


def data_parallel(model: Any, rows: int) -> tuple[Any, Mesh | None]:
    """Where a jitted call on ``model`` and batches of ``rows`` rows computes each row once.

    Returns ``(model, mesh)``: pass each batch through :func:`shard_batch` on ``mesh``
    when it is not None. A model replicated over a mesh of several devices of this
    process (as training and the bench leave it) would otherwise run the whole batch on
    every device, each a full copy of the work on the same cores (4 simulated CPU devices:
    4x the work). So the batch is split over that mesh when ``rows`` divides evenly (each
    device scores or samples its own rows), else the model is copied to the mesh's first
    device. A model on one device, or on devices of several processes, is returned as it
    is with mesh None.
    """
    leaves = jax.tree.leaves(model)
    sharding = getattr(leaves[0], "sharding", None) if leaves else None
    if not isinstance(sharding, NamedSharding) or not sharding.is_fully_replicated:
        return model, None
    mesh = sharding.mesh
    if mesh.devices.size == 1 or mesh.is_multi_process:
        return model, None
    if rows % mesh.devices.size == 0:
        return model, mesh
    return jax.device_put(model, mesh.devices.flat[0]), None
