"""Data parallelism over all devices: a 1-D device mesh, its shardings and multi-host start-up.

Every data-parallel computation here splits one batch axis over a 1-D mesh and replicates the
rest (parameters, optimizer state, training images): inside `jit`, a sharding constraint on
the batch is enough for GSPMD to run each device on its slice and insert the all-reduces
(gradients, loss sums). The global batch is the same whatever the device count, and randomness
drawn inside `jit` does not depend on the sharding (`jax_threefry_partitionable`, on by
default), so results agree across device counts up to the order of floating-point sums.

Several hosts: call `initialize_distributed` in every process before anything else touches
JAX; `jax.devices()` then lists the devices of all processes and the same code runs unchanged
(each process runs the same program on its own devices).
"""

from __future__ import annotations

from typing import Any, Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from signerf_jax.errors import InputError

BATCH_AXIS = "batch"


def device_mesh(devices: Sequence[jax.Device] | None = None, axis_name: str = BATCH_AXIS
                ) -> Mesh:
  """A 1-D mesh over `devices` (default: all devices of all processes) with one axis."""
  devices = list(jax.devices() if devices is None else devices)
  return Mesh(np.asarray(devices), (axis_name,))


def replicated(mesh: Mesh) -> NamedSharding:
  """The whole array on every device of `mesh`."""
  return NamedSharding(mesh, PartitionSpec())


def batch_sharded(mesh: Mesh) -> NamedSharding:
  """The leading (batch) axis split evenly over the mesh's one axis; other axes whole."""
  return NamedSharding(mesh, PartitionSpec(mesh.axis_names[0]))


def replicate(tree: Any, mesh: Mesh) -> Any:
  """Places every leaf of `tree` (host or device arrays, the same in every process) on all
  devices of `mesh`."""
  return jax.device_put(tree, replicated(mesh))


def check_divisible(batch_size: int, mesh: Mesh, field: str) -> None:
  """Raises InputError (naming `field`) unless `batch_size` splits evenly over the mesh."""
  if batch_size % mesh.size:
    raise InputError(f"{batch_size} does not split evenly over {mesh.size} devices; use a "
                     f"multiple of {mesh.size}", field=field)


def initialize_distributed(coordinator_address: str, num_processes: int, process_id: int
                           ) -> None:
  """Joins a multi-process (multi-host) JAX run: `jax.distributed.initialize` with its
  arguments checked.

  Args:
    coordinator_address: "host:port" of process 0, reachable from every process.
    num_processes: how many processes take part (one per host, usually).
    process_id: this process's index in [0, num_processes).
  """
  host, _, port = coordinator_address.rpartition(":")
  if not host or not port.isdigit():
    raise InputError(f"expected HOST:PORT, got {coordinator_address!r}",
                     field="coordinator_address")
  if num_processes < 1:
    raise InputError(f"must be at least 1, got {num_processes}", field="num_processes")
  if not 0 <= process_id < num_processes:
    raise InputError(f"must be in [0, {num_processes}), got {process_id}", field="process_id")
  jax.distributed.initialize(coordinator_address, num_processes=num_processes,
                             process_id=process_id)


def barrier(name: str) -> None:
  """Waits until every process of the run has reached the barrier `name` (one process: returns
  at once)."""
  if jax.process_count() > 1:
    from jax.experimental import multihost_utils  # pylint: disable=g-import-not-at-top
    multihost_utils.sync_global_devices(name)
