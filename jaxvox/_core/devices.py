"""Work split over the JAX devices: `on_each_device` runs a function on each device's
slice of the leading axis, `everywhere` is the replicated sharding, `on_all_devices`
places read-only tables on every device (aliased, not copied, on the CPU)."""

from __future__ import annotations

import jax
import numpy as np


def on_each_device(fn, shared, *arrays):
    """``fn(shared, *arrays)`` with each JAX device running it on its own equal slice of
    the arrays' leading axis (a multiple of the device count) and all of `shared` (a
    pytree); the outputs' slices are joined along their leading axis."""
    split = jax.sharding.PartitionSpec("rays")
    specs = (jax.sharding.PartitionSpec(),) + (split,) * len(arrays)
    return jax.shard_map(fn, mesh=_mesh(), in_specs=specs, out_specs=split, check_vma=False)(shared, *arrays)


def everywhere() -> jax.sharding.NamedSharding:
    """The sharding that replicates an array on every JAX device: what `on_each_device`'s
    callers give the values they carry from call to call, so that every call sees the
    same shardings and compiles once."""
    return jax.sharding.NamedSharding(_mesh(), jax.sharding.PartitionSpec())


def on_all_devices(values):
    """`values` (a pytree of arrays that are only read) placed with `everywhere()`. On CPU
    the devices share the host's memory, so an array on one CPU device, or a page-aligned
    host array (the attribute memmaps of `mesh_to_dag`), is aliased by every device
    instead of copied; other host arrays and other platforms are copied."""

    def shared(x):
        if isinstance(x, jax.Array) and len(x.devices()) == 1 and next(iter(x.devices())).platform == "cpu":
            return np.asarray(x)  # a read-only view of the device's buffer
        return x

    return jax.device_put(jax.tree.map(shared, values), everywhere(), may_alias=True)


def _mesh():
    return jax.sharding.Mesh(np.array(jax.devices()), ("rays",))
