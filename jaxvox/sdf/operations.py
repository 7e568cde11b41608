"""SDF operations: rigid transforms and scaling, and constructive solid geometry (CSG)."""

from __future__ import annotations

import dataclasses
import numbers

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.checks import is_concrete, refuse
from jaxvox._core.geometry import safe_norm
from jaxvox.sdf.base import SDF, check_scene, node, param

_ROTATION_TOLERANCE = 1e-4  # max |R^T R - I| and |det R - 1| accepted by `rotate`


# ----------------------------------------------------------------------------- transforms


@node
class Translate(SDF):
    """``child(p - offset)``. Exact when the child is."""

    child: SDF
    offset: jax.Array  # [3] float32
    exact = True

    def _distance(self, p):
        return self.child._distance(p - self.offset)


@node
class Rotate(SDF):
    """``child(R^T p)``: the child rotated by R about the origin. Exact when the child is."""

    child: SDF
    matrix: jax.Array  # [3, 3] float32 rotation R (local to world)
    exact = True

    def _distance(self, p):
        return self.child._distance(p @ self.matrix)  # row vectors: p @ R == (R^T p)^T


@node
class Scale(SDF):
    """The child scaled by `factor` about the origin.

    Uniform (`factor` []): ``child(p / s) * s``, exact when the child is. Non-uniform
    (`factor` [3]) and ``correct``: ``child(p / s) * min(s)``, a bound (never larger in
    magnitude than the true distance, same sign). ``correct=False``: ``child(p / s)``
    uncorrected; its Lipschitz constant is up to ``1 / min(s)``, so for ``min(s) < 1`` it
    is not a bound and sphere tracing can overstep (used in stability experiments).
    `correct` is static (changing it recompiles).
    """

    child: SDF
    factor: jax.Array  # [] or [3] float32, > 0
    correct: bool = dataclasses.field(metadata={"static": True})

    def _distance(self, p):
        d = self.child._distance(p / self.factor)
        return d * jnp.min(self.factor) if self.correct else d


def translate(scene: SDF, offset) -> Translate:
    """`scene` moved by `offset` [3]. Exact when `scene` is."""
    return Translate(check_scene(scene, "translate scene"), param(offset, "translate offset", (3,)))


def rotation(axis, angle) -> jax.Array:
    """Rotation matrix f32[3, 3] turning by `angle` (radians, right-handed) about `axis` [3] (Rodrigues)."""
    axis = param(axis, "rotation axis", (3,))
    if is_concrete(axis) and not np.asarray(axis).any():
        raise refuse("rotation axis", "must be nonzero", axis)
    x, y, z = axis / safe_norm(axis)
    angle = param(angle, "rotation angle", ())
    k = jnp.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return jnp.eye(3, dtype=jnp.float32) + jnp.sin(angle) * k + (1.0 - jnp.cos(angle)) * (k @ k)


def rotate(scene: SDF, matrix) -> Rotate:
    """`scene` rotated about the origin by the 3x3 rotation `matrix` (e.g. from `rotation`). Exact when `scene` is.

    Raises:
      JaxvoxError: when a concrete `matrix` is not a rotation (orthonormal, det +1).
    """
    m = param(matrix, "rotate matrix", (3, 3))
    if is_concrete(m):
        a = np.asarray(m, np.float64)
        if np.abs(a.T @ a - np.eye(3)).max() > _ROTATION_TOLERANCE or abs(np.linalg.det(a) - 1) > _ROTATION_TOLERANCE:
            raise refuse("rotate matrix", "must be a rotation (orthonormal with det +1)", a)
    return Rotate(check_scene(scene, "rotate scene"), m)


def scale(scene: SDF, factor, *, correct: bool = True) -> Scale:
    """`scene` scaled about the origin by `factor` > 0: a scalar (uniform) or [3] (per axis).

    Uniform scaling is exact (``f(p / s) * s``). Per-axis scaling gives
    ``f(p / s) * min(s)``, a bound, or with ``correct=False`` the uncorrected
    ``f(p / s)``, which is not a bound when ``min(s) < 1`` (see `Scale`).
    """
    uniform = isinstance(factor, numbers.Real) or getattr(factor, "ndim", None) == 0
    f = param(factor, "scale factor", () if uniform else (3,), minimum=0.0, strict=True)
    return Scale(check_scene(scene, "scale scene"), f, bool(correct))


# ----------------------------------------------------------------------------- CSG


@node
class Union(SDF):
    """``min_i f_i``. Exact outside (when the children are), only a bound inside."""

    children: tuple  # of SDF

    def _distance(self, p):
        return jnp.min(jnp.stack([c._distance(p) for c in self.children]), axis=0)


@node
class Intersection(SDF):
    """``max_i f_i``. A bound (exact inside near one face, underestimates near edges outside)."""

    children: tuple  # of SDF

    def _distance(self, p):
        return jnp.max(jnp.stack([c._distance(p) for c in self.children]), axis=0)


@node
class Difference(SDF):
    """``max(f_a, -f_b)``: a with b carved out. A bound."""

    a: SDF
    b: SDF

    def _distance(self, p):
        return jnp.maximum(self.a._distance(p), -self.b._distance(p))


@node
class Complement(SDF):
    """``-f``: inside and outside swapped. Exact when the child is."""

    child: SDF
    exact = True

    def _distance(self, p):
        return -self.child._distance(p)


@node
class Mix(SDF):
    """``k f_a + (1 - k) f_b``. A bound for k in [0, 1]; outside it the Lipschitz constant
    ``|k| + |1 - k|`` exceeds 1 and sphere tracing can overstep."""

    a: SDF
    b: SDF
    k: jax.Array  # [] float32

    def _distance(self, p):
        return self.k * self.a._distance(p) + (1.0 - self.k) * self.b._distance(p)


def _smin(a: jax.Array, b: jax.Array, k: jax.Array) -> jax.Array:
    """Quilez's polynomial smooth minimum; blends within |a - b| < k, equals min(a, b) for k = 0."""
    k_ok = k > 0
    h = jnp.where(k_ok, jnp.maximum(k - jnp.abs(a - b), 0.0) / jnp.where(k_ok, k, 1.0), 0.0)
    return jnp.minimum(a, b) - h * h * k * 0.25


@node
class SmoothUnion(SDF):
    """Polynomial smooth minimum of ``f_a, f_b`` with blend width `k` (world units).
    At most ``min(f_a, f_b)``; a bound (its gradient is a convex combination of the children's)."""

    a: SDF
    b: SDF
    k: jax.Array  # [] float32, >= 0

    def _distance(self, p):
        return _smin(self.a._distance(p), self.b._distance(p), self.k)


@node
class SmoothIntersection(SDF):
    """Polynomial smooth maximum ``-smin(-f_a, -f_b, k)``. A bound."""

    a: SDF
    b: SDF
    k: jax.Array  # [] float32, >= 0

    def _distance(self, p):
        return -_smin(-self.a._distance(p), -self.b._distance(p), self.k)


def _scenes(scenes, name):
    if not scenes:
        raise refuse(f"{name} scenes", "needs at least one scene", scenes)
    return tuple(check_scene(s, f"{name} scenes[{i}]") for i, s in enumerate(scenes))


def union(*scenes: SDF) -> Union:
    """Union ``min(f_1, ..., f_n)``. Exact outside, a bound inside."""
    return Union(_scenes(scenes, "union"))


def intersection(*scenes: SDF) -> Intersection:
    """Intersection ``max(f_1, ..., f_n)``. A bound."""
    return Intersection(_scenes(scenes, "intersection"))


def difference(a: SDF, b: SDF) -> Difference:
    """`a` minus `b`: ``max(f_a, -f_b)``. A bound."""
    return Difference(check_scene(a, "difference a"), check_scene(b, "difference b"))


def complement(scene: SDF) -> Complement:
    """Everything outside `scene`: ``-f``. Exact when `scene` is."""
    return Complement(check_scene(scene, "complement scene"))


def mix(a: SDF, b: SDF, k) -> Mix:
    """Linear blend ``k f_a + (1 - k) f_b``; a bound for k in [0, 1], not Lipschitz-1 outside (see `Mix`)."""
    return Mix(check_scene(a, "mix a"), check_scene(b, "mix b"), param(k, "mix k", ()))


def smooth_union(a: SDF, b: SDF, k) -> SmoothUnion:
    """Smooth union with blend width `k` >= 0 in world units (k = 0 is `union`). A bound."""
    return SmoothUnion(
        check_scene(a, "smooth_union a"), check_scene(b, "smooth_union b"), param(k, "smooth_union k", (), minimum=0.0)
    )


def smooth_intersection(a: SDF, b: SDF, k) -> SmoothIntersection:
    """Smooth intersection with blend width `k` >= 0 in world units (k = 0 is `intersection`). A bound."""
    return SmoothIntersection(
        check_scene(a, "smooth_intersection a"),
        check_scene(b, "smooth_intersection b"),
        param(k, "smooth_intersection k", (), minimum=0.0),
    )
