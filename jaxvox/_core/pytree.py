"""Registers frozen dataclasses as pytrees without calling their ``__init__``."""

from __future__ import annotations

import dataclasses

import jax


def pytree_dataclass(cls):
    """Registers a frozen dataclass as a pytree.

    Fields whose metadata has ``static=True`` are static (part of the tree structure;
    changing one recompiles); the others are leaves. Unflattening bypasses
    ``__init__``, so constructors may validate and convert their inputs while
    transformations such as `jax.vmap` rebuild instances with batched leaves.
    """
    fields = dataclasses.fields(cls)
    data = [f.name for f in fields if not f.metadata.get("static", False)]
    meta = [f.name for f in fields if f.metadata.get("static", False)]

    def flatten(obj):
        children = [(jax.tree_util.GetAttrKey(n), getattr(obj, n)) for n in data]
        return children, tuple(getattr(obj, n) for n in meta)

    def unflatten(aux, children):
        obj = object.__new__(cls)
        for name, value in zip(data, children):
            object.__setattr__(obj, name, value)
        for name, value in zip(meta, aux):
            object.__setattr__(obj, name, value)
        return obj

    jax.tree_util.register_pytree_with_keys(cls, flatten, unflatten)
    return cls
