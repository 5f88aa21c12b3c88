"""Data-parallel placement for training: a 1-D ``data`` mesh over the devices and the
placement of a batch split along it (parameters replicated).

One process: the mesh spans its local devices (nothing is sharded on this one-device
CPU; ``tests/test_sharding.py`` runs two virtual CPU devices). Several processes
(``initialize``, ``python -m jtus.train --distributed``): the mesh spans every process's
devices, each process passes its own part of the batch (``shard`` assembles the global
array from the process-local pieces) and the same replicated state; XLA's collectives
(gloo between CPU processes, NCCL between GPUs) sum the gradients.
"""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P


def initialize(coordinator=None, num_processes=None, process_id=None):
    """Join a multi-process run (``jax.distributed.initialize``) before any other JAX
    call. Without arguments JAX reads them from the cluster (SLURM, Open MPI, ...);
    CPU processes exchange gradients over gloo."""
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator, num_processes, process_id)


def is_main():
    """Whether this process writes the run's files (process 0)."""
    return jax.process_index() == 0


def data_mesh(batch):
    """A 1-D ``data`` mesh over the devices when there are several and they divide
    the batch; None otherwise (one device: nothing to shard). With several processes
    the mesh is required: a batch they do not divide is an error."""
    devices = jax.devices()
    if jax.process_count() > 1:
        if batch % len(devices):
            raise ValueError(f"batch: {batch} is not a multiple of the {len(devices)} devices "
                             f"of the {jax.process_count()} processes")
        return jax.sharding.Mesh(np.array(devices), ("data",))
    if len(devices) < 2:
        return None
    if batch % len(devices):
        print(f"warning: batch {batch} is not a multiple of the {len(devices)} devices; "
              f"training on one", file=sys.stderr)
        return None
    return jax.sharding.Mesh(np.array(devices), ("data",))


def shard(tree, mesh, axis):
    """Place every array of ``tree`` with its ``axis`` split over ``mesh``'s data axis
    (arrays without that axis, or not divisible, are replicated). With several
    processes, ``tree`` is this process's part: split arrays hold its slice of the
    batch, replicated ones the same value on every process."""
    return _place(tree, mesh, axis)


def replicate(tree, mesh):
    """Place every array of ``tree`` whole on every device of ``mesh`` (parameters,
    optimizer state)."""
    return _place(tree, mesh, None)


def _place(tree, mesh, axis):
    multi = jax.process_count() > 1
    n = len(mesh.local_devices) if multi else mesh.devices.size

    def put(x):
        x = np.asarray(x) if multi else jnp.asarray(x)
        split = axis is not None and x.ndim > axis and x.shape[axis] % n == 0
        s = NamedSharding(mesh, P(*([None] * axis), "data") if split else P())
        if multi:
            return jax.make_array_from_process_local_data(s, x)
        return jax.device_put(x, s)

    return jax.tree_util.tree_map(put, tree)


def to_host(tree):
    """Numpy copies of (replicated) arrays: what one process saves or evaluates."""
    def get(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(x.addressable_data(0))
        return np.asarray(x)
    return jax.tree_util.tree_map(get, tree)
