"""Point queries against a mesh: closest points, winding numbers, occupancy, signed distance.

Every function takes a `Mesh` (indexed on the host for that call) or a `MeshIndex`
(built once with `mesh_index`, reused for any number of batches) and points
``[*batch, 3]``. Each search is one compiled program with static capacities (pairs and
rows of the tree walk, `jaxvox.points.search`), planned per (face capacity, point count):
on concrete inputs a search that ran out is run again with the capacities it reported
needing (one more compile, then remembered for that shape), so nothing is dropped; inside
`jax.jit`, `jax.vmap` or `jax.grad` the plan is used as it stands and a block that did
not fit is reported as `PointStatus.LOST` per point (call once on concrete points of
that shape first to grow the plan).

Signs (``sign=``):

* ``"winding"`` (default): inside where the generalized winding number exceeds 1/2;
  right on open, self-intersecting and non-manifold meshes. On concrete inputs the fast
  sum (``beta = 2``) is checked: points within `REFINE` of 1/2 are summed again over
  every triangle (float64 near 1/2), so a side is wrong only where the fast sum erred by
  more than `REFINE` (its largest error on the test meshes is about a fifth of that).
  Inside jit the fast value decides.
  A mesh whose index is `MeshIndex.closed` (watertight, no crossings, ...) is signed by
  pseudo-normals instead, which is exact there and costs no winding numbers.
* ``"pseudonormal"``: the side of the angle-weighted pseudo-normal of the closest feature
  (Baerentzen & Aanaes 2005): exact on closed, consistently oriented manifolds without
  self-intersections, and no extra cost.

Statuses per point (`PointStatus`): ``UNCERTAIN`` where the winding number lies within
``margin`` of 1/2 (the mesh itself leaves the side open there: holes, overlaps),
``INVALID`` for non-finite points (their results are NaN), ``LOST`` as above.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float32, Int32

from jaxvox._core.checks import check_choice, check_number, check_type, is_concrete, refuse
from jaxvox._core.devices import on_all_devices, on_each_device
from jaxvox._core.errors import JaxvoxError
from jaxvox._core.pytree import pytree_dataclass
from jaxvox._core.shapes import bucket, pad_rows
from jaxvox.mesh import Mesh
from jaxvox.points import closest, search, sides, winding
from jaxvox.points.index import MeshIndex, mesh_index

Sign = Literal["winding", "pseudonormal"]
SIGNS = ("winding", "pseudonormal")
DEFAULT_PAIRS = {"closest": 256, "winding": 512}  # first plan: pairs per block at least
DEFAULT_ROWS = {"closest": 8, "winding": 16}  # first plan: rows per block at least
# First plan: a block of points meets about c sqrt(s) nodes of a level of s nodes, c
# growing as the blocks get fewer (and so wider): c = C (PLAN_BLOCKS / blocks) ** E.
# (C, E) of the pairs (at the leaves, above them) and of the rows (the far rows at each
# depth, then the near leaf rows; "closest": its one row capacity), fitted so that the
# first plan holds what the searches needed, with room to spare, on meshes of 1,000 to
# 280,000 faces at 1,000 and 10,000 points, uniform in the box or near the surface. The
# closest search's pairs above the leaves take the tighter `CLOSE_PAIRS` where that keeps
# them within its points' own bounds (`closest.POINT_BOUNDS_MAX`; docs/design-history.md).
PLAN_BLOCKS = 313  # the blocks of 10,000 points
FIRST_PAIRS = {"closest": ((4.2, 0.45), (10.0, 0.3)), "winding": ((20.0, 0.25), (20.0, 0.25))}
CLOSE_PAIRS = (9.0, 0.4)  # the closest search's pairs above the leaves where that keeps the points' own bounds
FIRST_ROWS = {"closest": ((0.12, 0.45),), "winding": ((0.8, 0.125), (0.3, 0.6))}
REFINE = 0.1  # fast winding numbers this close to 1/2 are summed again (host API)
WINDING_BLOCK = 32  # points per block of the winding-number search
SPLIT_MIN = 1 << 14  # points per device at least, for a query to be split over devices
GRID_MIN = 1 << 16  # points per call at least for sides from cells (`jaxvox.points.sides`)
EXACT_BUDGET = 1 << 27  # (points x faces) that the cells leave open, summed exactly at most


class PointStatus(enum.IntEnum):
    """Per-point status of a query (int32 arrays hold these values)."""

    OK = 0
    UNCERTAIN = 1  # winding number within `margin` of 1/2: the side is not certain
    INVALID = 2  # a non-finite point: results are NaN
    LOST = 3  # inside jit: a search capacity was too small for the point's block


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class ClosestPoints:
    """Closest points on a mesh (`closest_points`). Leading axes are the points' batch axes.

    Attributes:
      distance: [*b] float32 unsigned distance, world units.
      point: [*b, 3] float32 closest point on the mesh.
      triangle: [*b] int32 face id of the closest triangle (ties: the smallest id).
      barycentric: [*b, 3] float32 barycentric coordinates of ``point`` on that face.
      status: [*b] int32 `PointStatus` (OK, INVALID or LOST).
    """

    distance: Float32[Array, "*b"]
    point: Float32[Array, "*b 3"]
    triangle: Int32[Array, "*b"]
    barycentric: Float32[Array, "*b 3"]
    status: Int32[Array, "*b"]


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class PointQuery:
    """Everything `query_points` knows about each point ([*b] leading axes).

    Attributes:
      closest: `ClosestPoints`.
      signed_distance: [*b] float32, negative inside.
      inside: [*b] bool.
      winding: [*b] float32 generalized winding number (NaN with ``sign="pseudonormal"``).
      status: [*b] int32 `PointStatus`.
    """

    closest: ClosestPoints
    signed_distance: Float32[Array, "*b"]
    inside: Bool[Array, "*b"]
    winding: Float32[Array, "*b"]
    status: Int32[Array, "*b"]


def _as_index(what: str, mesh) -> MeshIndex:
    if isinstance(mesh, MeshIndex):
        return mesh
    check_type(what, mesh, (Mesh, MeshIndex))
    return mesh_index(mesh)


def _points(what: str, points) -> tuple[tuple[int, ...], jax.Array]:
    """The batch shape ``*b`` of points [*b, 3] and the points as float32 [n, 3] (refused
    when they are not numbers or the last axis is not 3)."""
    if is_concrete(points):
        a = np.asarray(points)
        if a.dtype.kind not in "biuf":
            raise refuse(what, "must be numbers", a.dtype)
        if a.ndim < 1 or a.shape[-1] != 3:
            raise refuse(what, "must have shape [..., 3]", a.shape)
        return a.shape[:-1], jax.device_put(np.ascontiguousarray(a.reshape(-1, 3), np.float32))  # no program
    p = jnp.asarray(points, jnp.float32)
    if p.ndim < 1 or p.shape[-1] != 3:
        raise refuse(what, "must have shape [..., 3]", p.shape)
    return p.shape[:-1], p.reshape(-1, 3)


def _host(*trees) -> bool:
    """Whether every leaf is concrete (the host API can read counts and retry)."""
    return all(is_concrete(x) for x in jax.tree_util.tree_leaves(trees))


_ROW_DEPTHS = {"closest": closest.row_depths, "winding": winding.row_depths}  # a plan's rows, after its pairs
_PLANS: dict[tuple, tuple[int, ...]] = {}  # (what, face capacity, blocks) -> capacities that sufficed


def _plan(what: str, index: MeshIndex, nb: int) -> tuple[int, ...]:
    """The capacities of a search: the largest any earlier call of this shape needed, or the
    first plan (pairs and rows per block by depth from `FIRST_PAIRS` and `FIRST_ROWS`, at
    least `DEFAULT_PAIRS` and `DEFAULT_ROWS`; pairs at most the level's nodes)."""
    key = (what, index.capacity, nb)  # (beta changes the program, not its capacities)
    if key not in _PLANS:
        sizes = [size for _, size in index.levels]
        per_block = lambda fit, size: fit[0] * np.sqrt(size) * (PLAN_BLOCKS / nb) ** fit[1]
        pair_count = lambda fit, size: min(size, max(DEFAULT_PAIRS[what], per_block(fit, size)))
        capacity = lambda per: bucket(int(np.ceil(nb * per)))
        pairs = [capacity(pair_count(FIRST_PAIRS[what][d > 0], s)) for d, s in enumerate(sizes[:-1])]
        if what == "closest":  # the tighter fit where it keeps the points' own bounds
            bounded = lambda cap: cap * search.BLOCK <= closest.POINT_BOUNDS_MAX
            close = [capacity(pair_count(CLOSE_PAIRS, s)) for s in sizes[1:-1]]
            pairs[1:] = [c if bounded(c) and not bounded(n) else n for n, c in zip(pairs[1:], close)]
        depths = _ROW_DEPTHS[what](index)
        row_fits = [FIRST_ROWS[what][0]] * (len(depths) - 1) + [FIRST_ROWS[what][-1]]
        rows = [capacity(max(DEFAULT_ROWS[what], per_block(fit, sizes[d]))) for fit, d in zip(row_fits, depths)]
        _PLANS[key] = tuple(pairs + rows)
    return _PLANS[key]


def _searched(what: str, body, index: MeshIndex, flat, block: int, **static):
    """Runs the search ``body(index, points, caps=..., **static) -> (result, lost, needs)``
    over flattened points [n, 3] with the plan's capacities; on concrete inputs, again with
    grown capacities while a block was lost (nothing is dropped), remembering what
    sufficed. On concrete inputs with several JAX devices (e.g.
    ``jax.config.update("jax_num_cpu_devices", os.cpu_count())``, as the command line
    does), one program runs the search on an equal share of the points on each device."""
    host = _host(index, flat)
    parts = jax.device_count() if host and flat.shape[0] >= SPLIT_MIN * jax.device_count() else 1
    n = flat.shape[0]
    per = -(-n // parts)
    key = (what, index.capacity, _blocks_of(per, block))
    caps = _plan(what, index, key[2])
    if parts > 1:
        points = np.asarray(flat)
        points = np.concatenate([points, np.repeat(points[-1:], per * parts - n, 0)])
        index = on_all_devices(index)
        run = lambda caps: _split_program(body, index, points, caps=caps, **static)
    else:
        run = lambda caps: _program(body, index, jax.lax.stop_gradient(flat), caps=caps, **static)
    for _ in range(2 * len(caps) + 2):  # each retry fits at least one more level
        result, lost, needs = run(caps)
        if not host or not np.asarray(lost).any():
            return (result, lost) if parts == 1 else jax.tree_util.tree_map(lambda x: x[:n], (result, lost))
        caps = _PLANS[key] = search.grown(caps, np.asarray(needs).max(0), _ROW_DEPTHS[what](index))
    raise JaxvoxError(f"{what} search: capacities {caps} still too small after growing them (a bug)")


@functools.partial(jax.jit, static_argnums=0, static_argnames=("caps", "beta"))
def _program(body, index, points, **static):
    """One search as one program."""
    return body(index, points, **static)


@functools.partial(jax.jit, static_argnums=0, static_argnames=("caps", "beta"))
def _split_program(body, index, points, **static):
    """One search as one program, each device searching its share of the points."""
    return on_each_device(functools.partial(body, **static), index, points)


def _closest_body(index: MeshIndex, points, *, caps):
    """(slot [n], finite [n]), lost [n], needs [1, k] of the closest-triangle search."""
    finite = jnp.all(jnp.isfinite(points), -1)
    blocks = search.make_blocks(index, jnp.where(finite[:, None], points, index.centre))
    found = closest.closest_slots(index, blocks, caps)
    lost = search.per_point(blocks, jnp.repeat(found.lost[:, None], search.BLOCK, 1))
    return (search.per_point(blocks, found.slot), finite), lost, found.needs[None]


def _winding_body(index: MeshIndex, points, *, beta: float, caps):
    """(w [n], bound [n]), lost [n], needs [1, k] of the fast winding-number sum."""
    finite = jnp.all(jnp.isfinite(points), -1)
    blocks = search.make_blocks(index, jnp.where(finite[:, None], points, index.centre), WINDING_BLOCK)
    w, err, lost, needs = winding.winding_sums(index, blocks, beta, caps)
    lost = search.per_point(blocks, jnp.repeat(lost[:, None], WINDING_BLOCK, 1))
    return (search.per_point(blocks, w), search.per_point(blocks, err)), lost, needs[None]


def _blocks_of(n: int, size: int) -> int:
    return -(-n // size)


def _closest(index: MeshIndex, flat):
    """(slot [n], finite [n], lost [n]) of the closest triangles of flattened points [n, 3]."""
    (slot, finite), lost = _searched("closest", _closest_body, index, flat, search.BLOCK)
    return slot, finite, lost


@functools.partial(jax.jit, static_argnames=("sign", "margin"))
def _answer(index: MeshIndex, flat, slot, finite, lost, w, by_sides, *, sign: str | None, margin: float) -> PointQuery:
    """Everything about flattened points [n, 3] from their closest triangles' tree slots and
    (with ``sign="winding"``) winding numbers [n], or with `by_sides` ([] bool, a closed
    mesh) the pseudo-normal sides as winding numbers 0 and 1; differentiable in flat and
    the vertices."""
    face = index.order[slot]
    tri = index.vertices[index.faces[face]] - index.centre  # [n, 3, 3]
    q = flat - index.centre
    feature = closest.closest_on_triangles(jax.lax.stop_gradient(q), tri[:, 0], tri[:, 1], tri[:, 2])
    normal = jax.lax.stop_gradient(_pseudo_normal(index, slot, feature.region))
    offset = q - feature.point
    status = jnp.where(finite, jnp.where(lost, PointStatus.LOST, PointStatus.OK), PointStatus.INVALID)
    behind = jnp.sum(normal * jax.lax.stop_gradient(offset), -1) <= 0
    if sign == "winding":
        w = jnp.where(by_sides, jnp.where(behind, 1.0, 0.0), w)
        inside = w > 0.5
        status = jnp.where((status == PointStatus.OK) & (jnp.abs(w - 0.5) < margin), PointStatus.UNCERTAIN, status)
    else:
        inside = behind
        w = jnp.full(flat.shape[0], jnp.nan, jnp.float32)
    s = jnp.where(inside, -1.0, 1.0)
    n = _unit(normal)
    nan = lambda x: jnp.where(finite.reshape((-1,) + (1,) * (x.ndim - 1)), x, jnp.nan)
    closest_ = ClosestPoints(
        distance=nan(_signed_norm(offset, jnp.ones_like(s), n)),
        point=nan(feature.point + index.centre),
        triangle=jnp.where(finite, face, -1),
        barycentric=nan(feature.barycentric),
        status=jnp.where(status == PointStatus.UNCERTAIN, PointStatus.OK, status).astype(jnp.int32),
    )
    sd = nan(_signed_norm(offset, s, n * s[:, None]))
    return PointQuery(closest_, sd, inside & finite, nan(w), status.astype(jnp.int32))


def _unflatten(x, batch):
    return jax.tree_util.tree_map(lambda a: a.reshape(batch + a.shape[1:]), x)


def closest_points(mesh: Mesh | MeshIndex, points: Float32[ArrayLike, "*b 3"]) -> ClosestPoints:
    """The closest point on `mesh` to each of `points`, exact in float32.

    Args:
      mesh: `Mesh` (indexed for this call) or `MeshIndex` (`mesh_index`, reused).
      points: [*b, 3] world positions.

    Returns:
      `ClosestPoints` with leading axes ``*b``. ``distance`` is differentiable with
      respect to the points and the index's vertices.

    Raises:
      JaxvoxError: not a mesh or index, a mesh without faces, points not [..., 3].
    """
    index = _as_index("closest_points mesh", mesh)
    batch, flat = _points("closest_points points", points)
    if flat.shape[0] == 0:
        return _empty_closest(batch)
    slot, finite, lost = _closest(index, flat)
    zeros = jnp.zeros(flat.shape[0], jnp.float32)
    answer = _answer(index, flat, slot, finite, lost, zeros, jnp.asarray(False), sign=None, margin=0.0)
    return _unflatten(answer.closest, batch)


def _empty_closest(batch) -> ClosestPoints:
    z = lambda *s, dtype=jnp.float32: jnp.zeros(batch + s, dtype)
    return ClosestPoints(z(), z(3), z(dtype=jnp.int32), z(3), z(dtype=jnp.int32))


def _fast_winding(index: MeshIndex, flat, beta: float):
    """((w, bound), lost) [n] fast winding numbers of flattened points (non-finite: any)."""
    return _searched("winding", _winding_body, index, flat, WINDING_BLOCK, beta=beta)


def _settled_winding(index: MeshIndex, flat):
    """Winding numbers [n] and lost [n]: fast, then on concrete inputs refined near 1/2."""
    (w, _), lost = _fast_winding(index, flat, 2.0)
    if not _host(index, flat):
        return w, lost
    w = np.array(w, np.float64)
    again = np.flatnonzero(np.abs(w - 0.5) < REFINE)
    if len(again):
        w[again] = winding.exact_winding(index, np.asarray(flat)[again])
    return jnp.asarray(w, jnp.float32), lost


def _grid_winding(index: MeshIndex, flat):
    """Stand-ins for winding numbers [n] float32 (host, finite points [n, 3]) that give each
    point's side: where `jaxvox.points.sides` certifies it, its stand-in (1 or 0, or the
    winding number from a walk; `sides.grid_sides`); elsewhere the exact winding number
    (up to `EXACT_BUDGET` point-face pairs: one compiled program per face capacity, where
    the tree walk would add its own) or the settled one; and lost [n] bool."""
    points = np.asarray(flat, np.float32)
    side, w = sides.grid_sides(index, points)
    lost = np.zeros(len(points), bool)
    again = np.flatnonzero((side < 0) & np.all(np.isfinite(points), -1))
    if len(again) and len(again) * index.capacity <= EXACT_BUDGET:  # a few: summed exactly
        w[again] = winding.exact_winding(index, points[again])
    elif len(again):
        subset = pad_rows(points[again], bucket(len(again)))  # padded: programs per bucket
        w_again, lost_again = _settled_winding(index, jax.device_put(subset))
        w[again] = np.asarray(w_again)[: len(again)]
        lost[again] = np.asarray(lost_again)[: len(again)]
    return jnp.asarray(w), jnp.asarray(lost)


def _sides_winding(index: MeshIndex, flat):
    """Winding numbers, or stand-ins with the same sides (`_grid_winding`) for many
    concrete points, and lost [n]: for answers that need the side only."""
    if _host(index, flat) and flat.shape[0] >= GRID_MIN:
        return _grid_winding(index, flat)
    return _settled_winding(index, flat)


def winding_number(
    mesh: Mesh | MeshIndex,
    points: Float32[ArrayLike, "*b 3"],
    *,
    mode: Literal["fast", "exact"] = "fast",
    beta: float = 2.0,
    return_bound: bool = False,
):
    """Generalized winding number of `mesh` at each of `points` (1 inside a closed,
    outward-oriented mesh, 0 outside, in between across holes).

    Args:
      mesh: `Mesh` or `MeshIndex`.
      points: [*b, 3] world positions.
      mode: ``"fast"`` (tree of dipoles, `jaxvox.points.winding`) or ``"exact"`` (every
        triangle, O(points x faces), host-side; float64 near 1/2).
      beta: far-field acceptance ratio of the fast mode, > 1 (larger: more exact,
        slower). The error bound returned with ``return_bound`` holds for any beta.
      return_bound: also return the fast mode's per-point bound on ``|w - w_exact|``.

    Returns:
      [*b] float32 winding numbers (NaN for non-finite points), and with ``return_bound``
      a [*b] float32 error bound (0 in exact mode).

    Raises:
      JaxvoxError: bad mesh, points, mode or beta; exact mode on traced points.
    """
    index = _as_index("winding_number mesh", mesh)
    batch, flat = _points("winding_number points", points)
    check_choice("winding_number mode", mode, ("fast", "exact"))
    beta = check_number("winding_number beta", beta, above=1.0)
    if flat.shape[0] == 0:
        z = jnp.zeros(batch, jnp.float32)
        return (z, z) if return_bound else z
    finite = jnp.all(jnp.isfinite(flat), -1)
    if mode == "exact":
        if not _host(index, flat):
            raise refuse("winding_number mode", "'exact' runs on the host: not inside jit", mode)
        safe = np.where(np.asarray(finite)[:, None], np.asarray(flat), 0.0)
        w = jnp.asarray(winding.exact_winding(index, safe), jnp.float32)
        bound = jnp.zeros_like(w)
    else:
        (w, bound), _ = _fast_winding(index, flat, beta)
    w = jnp.where(finite, w, jnp.nan).reshape(batch)
    return (w, bound.reshape(batch)) if return_bound else w


def query_points(
    mesh: Mesh | MeshIndex,
    points: Float32[ArrayLike, "*b 3"],
    *,
    sign: Sign = "winding",
    margin: float = 0.01,
) -> PointQuery:
    """Closest points, signed distance, occupancy and winding number at each point.

    Args:
      mesh: `Mesh` or `MeshIndex`.
      points: [*b, 3] world positions.
      sign: ``"winding"`` or ``"pseudonormal"`` (module docstring).
      margin: winding numbers within this of 1/2 are flagged `PointStatus.UNCERTAIN`.

    Returns:
      `PointQuery`. The signed distance is differentiable with respect to the points and
      the index's vertices (`signed_distance`).
    """
    index = _as_index("query_points mesh", mesh)
    batch, flat = _points("query_points points", points)
    check_choice("query_points sign", sign, SIGNS)
    margin = check_number("query_points margin", margin, minimum=0.0)
    return query_flat(index, flat, batch, sign=sign, margin=margin, winding_numbers=True)


def query_flat(index: MeshIndex, flat, batch, *, sign: str, margin: float, winding_numbers: bool) -> PointQuery:
    """`query_points` of flattened points [n, 3] (`index` a `MeshIndex`, `batch` the shape
    to give the answers); without `winding_numbers` (`signed_distance`, the sampler) the
    ``winding`` field only stands in for the winding number: on its side of 1/2, and equal
    to it within `jaxvox.points.sides.MARGIN` of 1/2, so statuses hold for margins up to
    that (`_sides_winding`)."""
    if flat.shape[0] == 0:
        z = jnp.zeros(batch, jnp.float32)
        return PointQuery(_empty_closest(batch), z, z > 0, z, z.astype(jnp.int32))
    slot, finite, lost = _closest(index, flat)
    w = jnp.zeros(flat.shape[0], jnp.float32)
    by_sides = sign == "winding" and _host(index) and bool(index.closed)
    if sign == "winding" and not by_sides:
        w, lost_w = _settled_winding(index, flat) if winding_numbers else _sides_winding(index, flat)
        lost = lost | lost_w
    answer = _answer(index, flat, slot, finite, lost, w, jnp.asarray(by_sides), sign=sign, margin=margin)
    return _unflatten(answer, batch)


def _pseudo_normal(index: MeshIndex, slot, region):
    """[n, 3] pseudo-normal of each point's closest feature (region as `closest.Feature`)."""
    rows = index.normals[:, slot].T.reshape(-1, 7, 3)
    return jnp.take_along_axis(rows, region[:, None, None], 1)[:, 0]


def _unit(v):
    n = jnp.sqrt(jnp.sum(v * v, -1, keepdims=True))
    return v / jnp.where(n > 0, n, 1.0)


@jax.custom_jvp
def _signed_norm(v, s, n):
    """``s |v|`` for offsets v [n, 3] and signs s [n]; its gradient is ``s v / |v|``, and
    ``n`` [n, 3] (the unit pseudo-normal times s) where v = 0 (a point on the surface)."""
    return s * jnp.sqrt(jnp.sum(v * v, -1))


@_signed_norm.defjvp
def _signed_norm_jvp(primals, tangents):
    v, s, n = primals
    dv = tangents[0]
    length2 = jnp.sum(v * v, -1, keepdims=True)
    safe = jnp.where(length2 > 0, length2, 1.0)
    direction = jnp.where(length2 > 0, s[:, None] * v * jax.lax.rsqrt(safe), n)
    return _signed_norm(v, s, n), jnp.sum(direction * dv, -1)


def signed_distance(
    mesh: Mesh | MeshIndex,
    points: Float32[ArrayLike, "*b 3"],
    *,
    sign: Sign = "winding",
) -> Float32[Array, "*b"]:
    """Signed distance from each point to `mesh`, negative inside.

    Differentiable: with respect to the points the gradient is the unit vector from the
    closest point, times the sign (the unit pseudo-normal on the surface itself: never
    NaN); with respect to `MeshIndex.vertices` it moves the closest point with its
    triangle (pass an index, e.g. ``dataclasses.replace(index, vertices=v)``; the search
    uses the index's tree, so rebuild it when the vertices have moved far).

    Args:
      mesh: `Mesh` or `MeshIndex`.
      points: [*b, 3] world positions.
      sign: ``"winding"`` (default) or ``"pseudonormal"`` (module docstring).

    Returns:
      [*b] float32 (NaN for non-finite points). `query_points` also gives statuses.
    """
    index = _as_index("signed_distance mesh", mesh)
    batch, flat = _points("signed_distance points", points)
    check_choice("signed_distance sign", sign, SIGNS)
    return query_flat(index, flat, batch, sign=sign, margin=0.01, winding_numbers=False).signed_distance


def occupancy(
    mesh: Mesh | MeshIndex,
    points: Float32[ArrayLike, "*b 3"],
    *,
    sign: Sign = "winding",
) -> Bool[Array, "*b"]:
    """Whether each point is inside `mesh` (``sign`` as in `signed_distance`).

    With ``sign="winding"`` only the winding number is computed (no closest points).

    Returns:
      [*b] bool (False for non-finite points).
    """
    index = _as_index("occupancy mesh", mesh)
    batch, flat = _points("occupancy points", points)
    check_choice("occupancy sign", sign, SIGNS)
    if sign == "pseudonormal":
        return query_points(index, flat, sign=sign).inside.reshape(batch)
    if flat.shape[0] == 0:
        return jnp.zeros(batch, bool)
    finite = jnp.all(jnp.isfinite(flat), -1)
    w, _ = _sides_winding(index, jnp.where(finite[:, None], flat, index.centre))
    return ((w > 0.5) & finite).reshape(batch)
