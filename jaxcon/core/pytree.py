"""Minimal pytree dataclasses: array fields are leaves, `static_field()`s are hashed metadata.

Unflattening bypasses ``__init__`` so that JAX can rebuild objects from tracers or placeholder leaves
without running user-facing validation; ``replace`` goes through ``__init__`` and validates.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np


def static_field(**kwargs) -> Any:
    """A dataclass field stored as pytree metadata (must be hashable)."""
    metadata = dict(kwargs.pop("metadata", {}) or {})
    metadata["static"] = True
    return dataclasses.field(metadata=metadata, **kwargs)


def pytree_dataclass(cls):
    """Frozen dataclass registered as a pytree; fields marked with `static_field` are metadata."""
    cls = dataclasses.dataclass(frozen=True, eq=False)(cls)
    fields = dataclasses.fields(cls)
    data_names = tuple(f.name for f in fields if not f.metadata.get("static"))
    meta_names = tuple(f.name for f in fields if f.metadata.get("static"))

    def flatten_with_keys(obj):
        children = [(jax.tree_util.GetAttrKey(k), getattr(obj, k)) for k in data_names]
        return children, tuple(getattr(obj, k) for k in meta_names)

    def flatten(obj):
        return [getattr(obj, k) for k in data_names], tuple(getattr(obj, k) for k in meta_names)

    def unflatten(aux, children):
        obj = object.__new__(cls)
        for k, v in zip(data_names, children):
            object.__setattr__(obj, k, v)
        for k, v in zip(meta_names, aux):
            object.__setattr__(obj, k, v)
        return obj

    jax.tree_util.register_pytree_with_keys(cls, flatten_with_keys, unflatten, flatten)

    def replace(self, **changes):
        """Return a copy with the given fields replaced (validated like the constructor)."""
        return dataclasses.replace(self, **changes)

    cls.replace = replace
    cls._data_fields = data_names
    cls._meta_fields = meta_names
    return cls


def concrete(x) -> np.ndarray | None:
    """`x` as a NumPy array if its value is known now, or None if it is a tracer (or contains one)."""
    if isinstance(x, jax.core.Tracer):
        return None
    try:
        return np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError, TypeError):
        return None


class StaticArray:
    """A read-only NumPy array that hashes and compares by content (usable as jit metadata)."""

    __slots__ = ("array", "_hash")

    def __init__(self, array):
        a = np.array(array, copy=True)
        a.setflags(write=False)
        self.array = a
        self._hash = hash((a.shape, a.dtype.str, a.tobytes()))

    def __hash__(self):
        return self._hash

    def __eq__(self, other):
        return (
            isinstance(other, StaticArray)
            and self._hash == other._hash
            and self.array.shape == other.array.shape
            and self.array.dtype == other.array.dtype
            and np.array_equal(self.array, other.array)
        )

    def __repr__(self):
        return f"StaticArray(shape={self.array.shape}, dtype={self.array.dtype})"
