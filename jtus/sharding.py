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

import os
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


def host_cores():
    """The cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def use_host_devices(n, batch=None):
    """Split XLA:CPU into ``n`` devices (``jax_num_cpu_devices``; None: one per core this
    process may run on, ``host_cores``), fewer where ``batch`` would not divide among
    them: the largest count up to ``n`` that divides it. Data-parallel training then
    runs a device per core (``batch_parallel``). Only this process's JAX configuration
    changes, not the environment; on a GPU the training devices are the GPUs and this
    changes nothing. It must come before JAX's first computation: returns the count
    set, or None where it left the devices as they are (one device asked for, or JAX
    already started: said when ``n`` was given)."""
    asked, n = n is not None, host_cores() if n is None else n
    if n < 1:
        raise ValueError(f"host devices: expected a positive count, got {n}")
    if batch is not None:
        n = max(d for d in range(1, n + 1) if batch % d == 0)
    if n < 2:
        return None
    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError as e:  # the backends are up: their device count is fixed
        if asked:
            print(f"warning: {e}; keeping {len(jax.devices('cpu'))} CPU device(s)",
                  file=sys.stderr)
        return None
    return n


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


def _specs(tree, axis, size):
    """The ``PartitionSpec`` of each array of ``tree`` under ``_place``'s rule: split
    along ``axis`` where it has that axis and ``size`` divides it, else replicated."""
    def spec(x):
        split = axis is not None and x.ndim > axis and x.shape[axis] % size == 0
        return P(*([None] * axis), "data") if split else P()
    return jax.tree_util.tree_map(spec, tree)


def batch_parallel(fn, mesh, batch_axes, out_batch_axes):
    """``fn`` run by each device of ``mesh`` on its part of the batch (``jax.shard_map``):
    argument i is split along ``batch_axes[i]`` (None: replicated), output j comes back
    split along ``out_batch_axes[j]``; outputs with None there are averaged over the
    devices (``lax.pmean``: a loss and its gradients, which for a mean over the batch
    equal the whole batch's). Unlike jit's automatic partitioning of the whole step,
    nothing inside ``fn`` (a recurrent scan) talks to the other devices: XLA:CPU runs a
    convolution on one thread, and a device per core is what runs a step's
    convolutions on every core (docs/performance.md, "Training on several cores")."""
    size = mesh.devices.size

    def run(*args):
        outs = jax.eval_shape(fn, *args)
        in_specs = tuple(_specs(a, ax, size) for a, ax in zip(args, batch_axes))
        out_specs = tuple(_specs(o, ax, size) for o, ax in zip(outs, out_batch_axes))

        def local(*a):
            res = fn(*a)
            mean = mean_over_devices([r for r, ax in zip(res, out_batch_axes) if ax is None])
            return tuple(next(mean) if ax is None else r for r, ax in zip(res, out_batch_axes))

        return jax.shard_map(local, mesh=mesh, in_specs=in_specs, out_specs=out_specs,
                             check_vma=False)(*args)

    return run


def mean_over_devices(trees, axis="data"):
    """``lax.pmean`` of every array of ``trees`` over ``axis``, as one exchange per dtype:
    the floating arrays of each dtype raveled into one vector, averaged, and cut back.
    Between processes (gloo) each collective costs a round trip: DLCTUS's 18 gradient
    arrays averaged one by one took 72 ms, as one vector 4 ms (two processes on one
    machine, docs/performance.md). Each element is averaged as ``pmean`` averages it
    (the same sum over the devices). Returns an iterator over the averaged trees."""
    leaves, treedef = jax.tree_util.tree_flatten(list(trees))
    out = list(leaves)
    groups = {}
    for i, x in enumerate(leaves):
        if jnp.issubdtype(x.dtype, jnp.floating):
            groups.setdefault(x.dtype, []).append(i)
        else:
            out[i] = jax.lax.pmean(x, axis)
    for idx in groups.values():
        flat = jax.lax.pmean(jnp.concatenate([leaves[i].ravel() for i in idx]), axis)
        start = 0
        for i in idx:
            n = leaves[i].size
            out[i] = flat[start:start + n].reshape(leaves[i].shape)
            start += n
    return iter(jax.tree_util.tree_unflatten(treedef, out))


def to_host(tree):
    """Numpy copies of (replicated) arrays: what one process saves or evaluates."""
    def get(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(x.addressable_data(0))
        return np.asarray(x)
    return jax.tree_util.tree_map(get, tree)
