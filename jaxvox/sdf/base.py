"""The `SDF` base class of scene nodes and the checks shared by the node constructors."""

from __future__ import annotations

import abc
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.checks import is_concrete, refuse
from jaxvox._core.pytree import pytree_dataclass

_MAX_PARAM = 1e18  # largest scene parameter magnitude: its square stays finite in float32


def param(value, name: str, shape: tuple, *, minimum: float | None = None, strict: bool = False) -> jax.Array:
    """`value` as a float32 array of `shape` (a scalar broadcasts); checks NaN and sign when concrete."""
    try:
        x = jnp.asarray(value, jnp.float32)
    except (TypeError, ValueError):
        raise refuse(name, f"must be numbers of shape {shape}" if shape else "must be a number", value) from None
    if x.shape != shape:
        if x.ndim == 0 and shape:
            x = jnp.broadcast_to(x, shape)
        else:
            raise refuse(name, f"must have shape {shape}", x.shape)
    if is_concrete(x):
        a = np.asarray(x)
        if not np.isfinite(a).all():
            raise refuse(name, "must be finite", a)
        if (np.abs(a) > _MAX_PARAM).any():
            raise refuse(
                name, f"must be at most {_MAX_PARAM:.0e} in magnitude (squared distances must fit in float32)", a
            )
        if minimum is not None and ((a <= minimum).any() if strict else (a < minimum).any()):
            relation = ">" if strict else ">="
            raise refuse(name, f"must be {relation} {minimum}", a)
    return x


def check_scene(scene, name: str) -> SDF:
    """`scene` itself; raises `JaxvoxError` (naming `name`) when it is not an `SDF` node."""
    if not isinstance(scene, SDF):
        raise refuse(name, "must be an SDF scene node (jaxvox.sdf)", type(scene))
    return scene


class SDF(abc.ABC):
    """Base class of scene nodes: ``scene(points f32[..., 3]) -> f32[...]`` signed distances.

    Subclasses are pytree dataclasses; build them with the constructor functions
    (`sphere`, `union`, ...), which validate and convert their parameters.
    """

    exact = False  # class-level: True when the node is exact given exact children

    def __call__(self, points) -> jax.Array:
        """Signed distance at `points` [..., 3] (float32, world units) -> [...] float32."""
        p = jnp.asarray(points, jnp.float32)
        if p.shape[-1:] != (3,):
            raise refuse(f"{type(self).__name__} points", "must have shape [..., 3]", p.shape)
        return self._distance(p)

    @abc.abstractmethod
    def _distance(self, p: jax.Array) -> jax.Array:
        """Signed distance at float32 points [..., 3] -> [...] (no checks)."""


def node(cls):
    """Makes an `SDF` subclass a frozen pytree dataclass (fields with ``static=True`` metadata are static)."""
    return pytree_dataclass(dataclasses.dataclass(frozen=True)(cls))
