"""Data-parallel placement for training: a 1-D ``data`` mesh over the local devices
and the placement of a batch split along it (parameters replicated). On one device
(this CPU) nothing is sharded; the two-device test runs on two virtual CPU devices
(``tests/test_sharding.py``)."""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp
import numpy as np


def data_mesh(batch):
    """A 1-D ``data`` mesh over the local devices when there are several and they
    divide the batch; None otherwise (one device: nothing to shard)."""
    devices = jax.local_devices()
    if len(devices) < 2:
        return None
    if batch % len(devices):
        print(f"warning: batch {batch} is not a multiple of the {len(devices)} devices; "
              f"training on one", file=sys.stderr)
        return None
    return jax.sharding.Mesh(np.array(devices), ("data",))


def shard(tree, mesh, axis):
    """Place every array of ``tree`` with its ``axis`` split over ``mesh``'s data axis
    (arrays without that axis, or not divisible, are replicated)."""
    from jax.sharding import NamedSharding, PartitionSpec as P

    n = mesh.devices.size

    def put(x):
        x = jnp.asarray(x)
        if x.ndim > axis and x.shape[axis] % n == 0:
            return jax.device_put(x, NamedSharding(mesh, P(*([None] * axis), "data")))
        return jax.device_put(x, NamedSharding(mesh, P()))

    return jax.tree_util.tree_map(put, tree)
