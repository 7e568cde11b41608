"""Signed distance functions (SDFs): primitives, transforms and CSG as jittable pytrees.

A *scene* is a tree of frozen dataclass nodes (`SDF` subclasses) built with the lower
case constructor functions below. Float parameters (radii, centres, blend factors) are
float32 array leaves and the node kinds and children are the tree structure, so a scene
can be passed to `jax.jit` (retraced only when the structure changes), evaluated under
`jax.vmap`, and differentiated with respect to its parameters by `jax.grad`. Calling a
scene on points ``f32[..., 3]`` returns signed distances ``f32[...]`` in world units:
negative inside, positive outside, zero on the surface (Hart 1996; Quilez, "Distance
functions").

Exact or bound. A node's value is either the *exact* Euclidean signed distance or only a
*bound*: a function with the same zero set whose magnitude never exceeds the true
distance as long as its Lipschitz constant is at most 1 (sphere tracing with it is
safe, only slower). Each class documents which; `is_exact` computes it for a tree and
`lipschitz_bound` bounds its Lipschitz constant (sphere tracing a scene whose bound is
above 1 can step through surfaces).

Parameter checks (shapes, NaN, signs) raise `JaxvoxError` when a constructor is called;
the value checks are skipped for traced values, so scenes can be built inside `jit` and
`grad`.
"""

from __future__ import annotations

import abc
import dataclasses
import numbers

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._checks import check_choice, check_number, check_type, refuse
from jaxvox._checks import is_concrete as _is_concrete
from jaxvox._pytree import pytree_dataclass
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh

MAX_MESH_RESOLUTION = 512  # `to_mesh` refuses larger grids (a 512^3 float32 field is 512 MiB)
NORMAL_METHODS = ("grad", "central")  # `normal` methods
_ROTATION_TOLERANCE = 1e-4  # max |R^T R - I| and |det R - 1| accepted by `rotate`


def _safe_norm(v: jax.Array) -> jax.Array:
    """|v| over the last axis with a finite gradient at v = 0 ("safe where" before sqrt)."""
    sq = jnp.sum(v * v, axis=-1)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def _axial(p, center):
    """Distance from the y axis through `center` and the height along it: ([...], [...])."""
    q = p - center
    return _safe_norm(q[..., 0::2]), q[..., 1]


_MAX_PARAM = 1e18  # largest scene parameter magnitude: its square stays finite in float32


def _param(value, name: str, shape: tuple, *, minimum: float | None = None, strict: bool = False) -> jax.Array:
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
    if _is_concrete(x):
        a = np.asarray(x)
        if not np.isfinite(a).all():
            raise refuse(name, "must be finite", a)
        if (np.abs(a) > _MAX_PARAM).any():
            raise refuse(name, f"must be at most {_MAX_PARAM:.0e} in magnitude (squared distances must fit in "
                         "float32)", a)
        if minimum is not None and ((a <= minimum).any() if strict else (a < minimum).any()):
            relation = ">" if strict else ">="
            raise refuse(name, f"must be {relation} {minimum}", a)
    return x


def _check_scene(scene, name: str) -> "SDF":
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


def _node(cls):
    return pytree_dataclass(dataclasses.dataclass(frozen=True)(cls))


# ----------------------------------------------------------------------------- primitives


@_node
class Sphere(SDF):
    """Sphere ``|p - center| - radius``. Exact."""

    radius: jax.Array  # [] float32
    center: jax.Array  # [3] float32
    exact = True

    def _distance(self, p):
        return _safe_norm(p - self.center) - self.radius


@_node
class Box(SDF):
    """Axis-aligned box of half extents ``b``: ``|max(q, 0)| + min(max_i q_i, 0)``, ``q = |p - c| - b``. Exact."""

    half_extents: jax.Array  # [3] float32
    center: jax.Array  # [3] float32
    exact = True

    def _distance(self, p):
        q = jnp.abs(p - self.center) - self.half_extents
        return _safe_norm(jnp.maximum(q, 0.0)) + jnp.minimum(jnp.max(q, axis=-1), 0.0)


@_node
class RoundedBox(SDF):
    """Box of outer half extents ``b`` with edges rounded by ``radius`` (the box of half
    extents ``b - radius`` offset by ``radius``). Exact (offsetting a convex exact SDF is exact)."""

    half_extents: jax.Array  # [3] float32
    radius: jax.Array  # [] float32
    center: jax.Array  # [3] float32
    exact = True

    def _distance(self, p):
        q = jnp.abs(p - self.center) - self.half_extents + self.radius
        inner = _safe_norm(jnp.maximum(q, 0.0)) + jnp.minimum(jnp.max(q, axis=-1), 0.0)
        return inner - self.radius


@_node
class Torus(SDF):
    """Torus in the xz-plane around the y axis through `center`:
    ``|(|p.xz| - major_radius, p.y)| - minor_radius``. Exact."""

    major_radius: jax.Array  # [] float32
    minor_radius: jax.Array  # [] float32
    center: jax.Array  # [3] float32
    exact = True

    def _distance(self, p):
        radial, height = _axial(p, self.center)
        return _safe_norm(jnp.stack([radial - self.major_radius, height], axis=-1)) - self.minor_radius


@_node
class Capsule(SDF):
    """Segment ``[a, b]`` thickened by `radius` (a sphere when a = b). Exact."""

    a: jax.Array  # [3] float32
    b: jax.Array  # [3] float32
    radius: jax.Array  # [] float32
    exact = True

    def _distance(self, p):
        pa, ba = p - self.a, self.b - self.a
        den = jnp.sum(ba * ba)
        den_ok = den > 0
        h = jnp.where(den_ok, jnp.sum(pa * ba, axis=-1) / jnp.where(den_ok, den, 1.0), 0.0)
        return _safe_norm(pa - ba * jnp.clip(h, 0.0, 1.0)[..., None]) - self.radius


@_node
class Cylinder(SDF):
    """Capped cylinder around the y axis through `center`, ``|y - c_y| <= half_height``. Exact."""

    radius: jax.Array  # [] float32
    half_height: jax.Array  # [] float32
    center: jax.Array  # [3] float32
    exact = True

    def _distance(self, p):
        d = jnp.abs(jnp.stack(_axial(p, self.center), axis=-1)) - jnp.stack([self.radius, self.half_height])
        return jnp.minimum(jnp.max(d, axis=-1), 0.0) + _safe_norm(jnp.maximum(d, 0.0))


@_node
class Plane(SDF):
    """Half space ``n . p + offset <= 0`` (unit normal n points outside). Exact."""

    normal: jax.Array  # [3] float32, unit length
    offset: jax.Array  # [] float32
    exact = True

    def _distance(self, p):
        return jnp.sum(p * self.normal, axis=-1) + self.offset


def sphere(radius, center=(0.0, 0.0, 0.0)) -> Sphere:
    """Sphere of `radius` >= 0 (world units) around `center` [3]. Exact."""
    return Sphere(_param(radius, "sphere radius", (), minimum=0.0), _param(center, "sphere center", (3,)))


def box(half_extents, center=(0.0, 0.0, 0.0)) -> Box:
    """Axis-aligned box with `half_extents` [3] (or a scalar: a cube) >= 0 around `center`. Exact."""
    return Box(_param(half_extents, "box half_extents", (3,), minimum=0.0), _param(center, "box center", (3,)))


def rounded_box(half_extents, radius, center=(0.0, 0.0, 0.0)) -> RoundedBox:
    """Box with outer `half_extents` [3] and edges rounded by ``0 <= radius <= min(half_extents)``. Exact."""
    b = _param(half_extents, "rounded_box half_extents", (3,), minimum=0.0)
    r = _param(radius, "rounded_box radius", (), minimum=0.0)
    if _is_concrete(b) and _is_concrete(r) and float(r) > float(jnp.min(b)):
        raise refuse("rounded_box radius", f"must be <= the smallest half extent {float(jnp.min(b))}", float(r))
    return RoundedBox(b, r, _param(center, "rounded_box center", (3,)))


def torus(major_radius, minor_radius, center=(0.0, 0.0, 0.0)) -> Torus:
    """Torus in the xz-plane (axis y): ring radius `major_radius`, tube radius `minor_radius`. Exact."""
    return Torus(_param(major_radius, "torus major_radius", (), minimum=0.0),
                 _param(minor_radius, "torus minor_radius", (), minimum=0.0), _param(center, "torus center", (3,)))


def capsule(a, b, radius) -> Capsule:
    """Capsule: points within `radius` of the segment from `a` [3] to `b` [3]. Exact."""
    return Capsule(_param(a, "capsule a", (3,)), _param(b, "capsule b", (3,)),
                   _param(radius, "capsule radius", (), minimum=0.0))


def cylinder(radius, half_height, center=(0.0, 0.0, 0.0)) -> Cylinder:
    """Capped cylinder, axis y, of `radius` and height ``2 * half_height`` around `center`. Exact."""
    return Cylinder(_param(radius, "cylinder radius", (), minimum=0.0),
                    _param(half_height, "cylinder half_height", (), minimum=0.0),
                    _param(center, "cylinder center", (3,)))


def plane(normal, offset=0.0) -> Plane:
    """Half space ``{p : n . p + offset <= 0}``, ``n = normal / |normal|``.

    The distance is ``n . p + offset``: positive on the side `normal` points to, so the
    plane passes through ``-offset * n``. Exact.
    """
    n = _param(normal, "plane normal", (3,))
    if _is_concrete(n) and not np.asarray(n).any():
        raise refuse("plane normal", "must be nonzero", n)
    return Plane(n / _safe_norm(n), _param(offset, "plane offset", ()))


# ----------------------------------------------------------------------------- transforms


@_node
class Translate(SDF):
    """``child(p - offset)``. Exact when the child is."""

    child: SDF
    offset: jax.Array  # [3] float32
    exact = True

    def _distance(self, p):
        return self.child._distance(p - self.offset)


@_node
class Rotate(SDF):
    """``child(R^T p)``: the child rotated by R about the origin. Exact when the child is."""

    child: SDF
    matrix: jax.Array  # [3, 3] float32 rotation R (local to world)
    exact = True

    def _distance(self, p):
        return self.child._distance(p @ self.matrix)  # row vectors: p @ R == (R^T p)^T


@_node
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
    correct: bool = dataclasses.field(metadata=dict(static=True))

    def _distance(self, p):
        d = self.child._distance(p / self.factor)
        return d * jnp.min(self.factor) if self.correct else d


def translate(scene: SDF, offset) -> Translate:
    """`scene` moved by `offset` [3]. Exact when `scene` is."""
    return Translate(_check_scene(scene, "translate scene"), _param(offset, "translate offset", (3,)))


def rotation(axis, angle) -> jax.Array:
    """Rotation matrix f32[3, 3] turning by `angle` (radians, right-handed) about `axis` [3] (Rodrigues)."""
    axis = _param(axis, "rotation axis", (3,))
    if _is_concrete(axis) and not np.asarray(axis).any():
        raise refuse("rotation axis", "must be nonzero", axis)
    x, y, z = axis / _safe_norm(axis)
    angle = _param(angle, "rotation angle", ())
    k = jnp.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return jnp.eye(3, dtype=jnp.float32) + jnp.sin(angle) * k + (1.0 - jnp.cos(angle)) * (k @ k)


def rotate(scene: SDF, matrix) -> Rotate:
    """`scene` rotated about the origin by the 3x3 rotation `matrix` (e.g. from `rotation`). Exact when `scene` is.

    Raises:
      JaxvoxError: when a concrete `matrix` is not a rotation (orthonormal, det +1).
    """
    m = _param(matrix, "rotate matrix", (3, 3))
    if _is_concrete(m):
        a = np.asarray(m, np.float64)
        if np.abs(a.T @ a - np.eye(3)).max() > _ROTATION_TOLERANCE or abs(np.linalg.det(a) - 1) > _ROTATION_TOLERANCE:
            raise refuse("rotate matrix", "must be a rotation (orthonormal with det +1)", a)
    return Rotate(_check_scene(scene, "rotate scene"), m)


def scale(scene: SDF, factor, *, correct: bool = True) -> Scale:
    """`scene` scaled about the origin by `factor` > 0: a scalar (uniform) or [3] (per axis).

    Uniform scaling is exact (``f(p / s) * s``). Per-axis scaling gives
    ``f(p / s) * min(s)``, a bound, or with ``correct=False`` the uncorrected
    ``f(p / s)``, which is not a bound when ``min(s) < 1`` (see `Scale`).
    """
    uniform = isinstance(factor, numbers.Real) or getattr(factor, "ndim", None) == 0
    f = _param(factor, "scale factor", () if uniform else (3,), minimum=0.0, strict=True)
    return Scale(_check_scene(scene, "scale scene"), f, bool(correct))


# ----------------------------------------------------------------------------- CSG


@_node
class Union(SDF):
    """``min_i f_i``. Exact outside (when the children are), only a bound inside."""

    children: tuple  # of SDF

    def _distance(self, p):
        return jnp.min(jnp.stack([c._distance(p) for c in self.children]), axis=0)


@_node
class Intersection(SDF):
    """``max_i f_i``. A bound (exact inside near one face, underestimates near edges outside)."""

    children: tuple  # of SDF

    def _distance(self, p):
        return jnp.max(jnp.stack([c._distance(p) for c in self.children]), axis=0)


@_node
class Difference(SDF):
    """``max(f_a, -f_b)``: a with b carved out. A bound."""

    a: SDF
    b: SDF

    def _distance(self, p):
        return jnp.maximum(self.a._distance(p), -self.b._distance(p))


@_node
class Complement(SDF):
    """``-f``: inside and outside swapped. Exact when the child is."""

    child: SDF
    exact = True

    def _distance(self, p):
        return -self.child._distance(p)


@_node
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


@_node
class SmoothUnion(SDF):
    """Polynomial smooth minimum of ``f_a, f_b`` with blend width `k` (world units).
    At most ``min(f_a, f_b)``; a bound (its gradient is a convex combination of the children's)."""

    a: SDF
    b: SDF
    k: jax.Array  # [] float32, >= 0

    def _distance(self, p):
        return _smin(self.a._distance(p), self.b._distance(p), self.k)


@_node
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
    return tuple(_check_scene(s, f"{name} scenes[{i}]") for i, s in enumerate(scenes))


def union(*scenes: SDF) -> Union:
    """Union ``min(f_1, ..., f_n)``. Exact outside, a bound inside."""
    return Union(_scenes(scenes, "union"))


def intersection(*scenes: SDF) -> Intersection:
    """Intersection ``max(f_1, ..., f_n)``. A bound."""
    return Intersection(_scenes(scenes, "intersection"))


def difference(a: SDF, b: SDF) -> Difference:
    """`a` minus `b`: ``max(f_a, -f_b)``. A bound."""
    return Difference(_check_scene(a, "difference a"), _check_scene(b, "difference b"))


def complement(scene: SDF) -> Complement:
    """Everything outside `scene`: ``-f``. Exact when `scene` is."""
    return Complement(_check_scene(scene, "complement scene"))


def mix(a: SDF, b: SDF, k) -> Mix:
    """Linear blend ``k f_a + (1 - k) f_b``; a bound for k in [0, 1], not Lipschitz-1 outside (see `Mix`)."""
    return Mix(_check_scene(a, "mix a"), _check_scene(b, "mix b"), _param(k, "mix k", ()))


def smooth_union(a: SDF, b: SDF, k) -> SmoothUnion:
    """Smooth union with blend width `k` >= 0 in world units (k = 0 is `union`). A bound."""
    return SmoothUnion(_check_scene(a, "smooth_union a"), _check_scene(b, "smooth_union b"),
                       _param(k, "smooth_union k", (), minimum=0.0))


def smooth_intersection(a: SDF, b: SDF, k) -> SmoothIntersection:
    """Smooth intersection with blend width `k` >= 0 in world units (k = 0 is `intersection`). A bound."""
    return SmoothIntersection(_check_scene(a, "smooth_intersection a"), _check_scene(b, "smooth_intersection b"),
                              _param(k, "smooth_intersection k", (), minimum=0.0))


# ----------------------------------------------------------------------------- tree queries


def is_exact(scene: SDF) -> bool:
    """True when `scene` is the exact signed distance: exact primitives under translations,
    rotations, uniform (corrected) scales and complements; False for any CSG node."""
    _check_scene(scene, "is_exact scene")
    if isinstance(scene, Scale):
        return scene.correct and scene.factor.ndim == 0 and is_exact(scene.child)
    if isinstance(scene, (Translate, Rotate, Complement)):
        return is_exact(scene.child)
    return type(scene).exact


def lipschitz_bound(scene: SDF) -> float:
    """Host-side upper bound on the Lipschitz constant of `scene` (1.0 for most scenes).

    Primitives 1; transforms, union, intersection, difference and the smooth operations
    keep the largest of their children's; `mix` gives ``|k| L_a + |1 - k| L_b``; an
    uncorrected scale ``L / min(s)`` (uniform or not). Needs concrete `k` and scale factors.
    """
    _check_scene(scene, "lipschitz_bound scene")
    if isinstance(scene, Mix):
        k = float(scene.k)
        return abs(k) * lipschitz_bound(scene.a) + abs(1.0 - k) * lipschitz_bound(scene.b)
    if isinstance(scene, Scale):
        inner = lipschitz_bound(scene.child)
        return inner if scene.correct else inner / float(jnp.min(scene.factor))
    children = [c for c in jax.tree.leaves(scene, is_leaf=lambda x: x is not scene and isinstance(x, SDF))
                if isinstance(c, SDF)]
    return max((lipschitz_bound(c) for c in children), default=1.0)


def normal(scene: SDF, points, *, method: str = "grad", h: float = 1e-3) -> jax.Array:
    """Unit surface normals (normalized SDF gradients) at `points` [..., 3] -> [..., 3] float32.

    ``method="grad"`` differentiates the scene with `jax.grad`; ``"central"`` uses central
    differences with step `h` (world units). Zero where the gradient vanishes.

    Raises:
      JaxvoxError: a bad method or scene, points not [..., 3], or (when concrete) a step
        `h` that is not a finite number > 0.
    """
    check_choice("normal method", method, NORMAL_METHODS)
    _check_scene(scene, "normal scene")
    p = jnp.asarray(points, jnp.float32)
    if p.shape[-1:] != (3,):
        raise refuse("normal points", "must have shape [..., 3]", p.shape)
    if _is_concrete(h):
        check_number("normal h", h, above=0.0)
    if method == "grad":
        flat = p.reshape(-1, 3)
        g = jax.vmap(jax.grad(scene._distance))(flat).reshape(p.shape)
    else:
        offsets = jnp.eye(3, dtype=jnp.float32) * h  # [3 axes, 3]
        plus = scene._distance(p[..., None, :] + offsets)
        minus = scene._distance(p[..., None, :] - offsets)
        g = (plus - minus) / (2.0 * h)
    n = _safe_norm(g)
    return g / jnp.where(n > 0, n, 1.0)[..., None]


# ----------------------------------------------------------------------------- meshing


@jax.jit
def _sample(scene: SDF, grid: Grid) -> jax.Array:
    """The scene at every voxel centre, one x-slab per `lax.map` step: [R, R, R] float32."""
    r = grid.resolution
    c = (jnp.arange(r, dtype=jnp.float32) + 0.5) * grid.voxel_size
    y, z = jnp.meshgrid(c, c, indexing="ij")

    def slab(x):
        p = jnp.stack([jnp.full_like(y, x), y, z], axis=-1) + grid.origin
        return scene._distance(p)

    return jax.lax.map(slab, c)


def to_mesh(scene: SDF, grid: Grid, *, level: float = 0.0) -> Mesh:
    """Triangle mesh of the ``scene == level`` surface by marching cubes on `grid`'s voxel centres.

    The field is sampled at ``origin + (ijk + 0.5) * voxel_size`` one slab at a time (no
    intermediate larger than the R^3 float32 field) and passed to
    `skimage.measure.marching_cubes`. Faces are counter-clockwise seen from outside
    (where ``scene > level``); vertices are in world coordinates. The surface is open
    where it leaves the grid.

    Returns:
      A `Mesh`; it has 0 vertices and 0 faces when the field does not cross `level`.

    Raises:
      JaxvoxError: not a scene or `Grid`, a resolution above `MAX_MESH_RESOLUTION`, a
        level that is not a finite number, or a NaN in the field.
    """
    from skimage.measure import marching_cubes

    _check_scene(scene, "to_mesh scene")
    check_type("to_mesh grid", grid, Grid)
    level = check_number("to_mesh level", level)
    if grid.resolution > MAX_MESH_RESOLUTION:
        raise refuse("to_mesh grid", f"resolution must be at most {MAX_MESH_RESOLUTION} "
                     f"(the field alone would take {grid.resolution ** 3 * 4 / 2 ** 30:.1f} GiB)", grid.resolution)
    field = np.array(_sample(scene, grid))  # writable: marching_cubes needs it
    if np.isnan(field).any():
        raise refuse("to_mesh scene", f"must not be NaN at a voxel centre (NaN at {int(np.isnan(field).sum())} "
                     f"of {field.size})", scene)
    if not field.min() < level < field.max():
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    verts, faces, _, _ = marching_cubes(field, level, gradient_direction="descent")
    h, origin = float(grid.voxel_size), np.asarray(grid.origin, np.float64)
    return Mesh((origin + (verts + 0.5) * h).astype(np.float32), faces.astype(np.int32))
