"""Exact conservative and 6-separating triangle voxelization (Schwarz & Seidel 2010).

Each triangle picks its dominant axis ``w`` (the largest component of its plane
normal) and the two others ``u`` (columns) and ``v`` (rows). Every voxel test is a
linear inequality in the voxel's integer corner, so for a fixed column the valid rows
form an interval, and for a fixed (column, row) the valid depths form an interval:

* columns: the triangle's bounding box along ``u``;
* rows: the dominant projection's three edge functions (and, in 6-separating mode, the
  diamond's two axes), intersected with the bounding box along ``v``;
* depths: the plane (critical corners in conservative mode; the centre segment along
  ``w`` in 6-separating mode), the two side projections' edge functions, and the
  bounding box along ``w``.

The modes differ only in the edge constants (box corner vs. inscribed diamond). Work is
expanded in JAX with fixed-size padding: per-triangle column counts, a prefix sum and an
expansion into a column capacity; per-column row counts, a prefix sum and an expansion
into a row capacity; per-row depth intervals, a prefix sum and an expansion into a candidate
capacity; the candidates are sorted by Morton code and made unique. No dense ``R^3`` array
is formed. Large triangles cost one work item per (column, row), not per bounding-box
voxel.

All tests run in float32 on coordinates local to the triangle (grid units relative to an
integer cell near its minimum corner). Every half-plane is widened by a tolerance of
``2^-19 * (1 + L)`` voxels (L: the triangle's extent in voxels) and the plane test by the
largest distance of the triangle's corners from the float32 plane, so rounding can only
add voxels that lie within that tolerance of the exact decision boundary, never drop one.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox import morton
from jaxvox._checks import check_choice, check_int, check_type, refuse
from jaxvox._errors import JaxvoxError
from jaxvox._geometry import point_triangle_dist2
from jaxvox._pytree import pytree_dataclass
from jaxvox._shapes import bucket, expand_counts
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh, validate_mesh
from jaxvox.overflow import Overflow, check_overflow, raise_if_overflow

CONSERVATIVE = "conservative"
SIX_SEPARATING = "6-separating"
MODES = (CONSERVATIVE, SIX_SEPARATING)
Mode = Literal["conservative", "6-separating"]

# Overflow bits of `Voxels.overflow` (names kept for `jaxvox.overflow.Overflow`'s members).
OVERFLOW_COLUMNS = Overflow.COLUMNS
OVERFLOW_ROWS = Overflow.ROWS
OVERFLOW_CANDIDATES = Overflow.CANDIDATES
OVERFLOW_VOXELS = Overflow.VOXELS

UNUSED = -1  # value of coordinate and triangle slots past `count`
REGION_SIZE = 1 << morton.WORD_BITS  # largest region sorted with one 32-bit key

ROW_CHUNK = 4  # rows per gather on the host path (`Capacities.row_chunk` of `voxel_capacities`)
_TOL = 2.0**-19  # relative half-plane widening, see the module docstring
_BIG = float(1 << 30)  # clamp for interval bounds before integer conversion


class Capacities(NamedTuple):
    """Static sizes of the work buffers of `voxelize_fixed` (changing one recompiles).

    Attributes:
      columns: (triangle, column) work items.
      rows: (triangle, column, row) work items, a multiple of `row_chunk`.
      candidates: voxels emitted before duplicates are removed.
      voxels: unique voxels in the result.
      row_chunk: rows handled together per column (a power of two; about the mean
        number of rows per column is fastest; `voxel_capacities` gives `ROW_CHUNK`).
    """

    columns: int
    rows: int
    candidates: int
    voxels: int
    row_chunk: int = ROW_CHUNK


def check_capacities(what: str, capacities) -> Capacities:
    """`capacities` as `Capacities` of Python ints: sizes >= 1, a power-of-two `row_chunk`
    and `rows` a multiple of it; raises `JaxvoxError` naming `what` otherwise."""
    try:
        caps = Capacities(*capacities)
    except TypeError:
        raise refuse(what, "expected a jaxvox.Capacities (4 or 5 integers)", capacities) from None
    caps = Capacities(*(check_int(f"{what} {name}", c, minimum=1) for name, c in zip(Capacities._fields, caps)))
    if caps.row_chunk & (caps.row_chunk - 1):
        raise refuse(f"{what} row_chunk", "must be a power of two", caps.row_chunk)
    if caps.rows % caps.row_chunk:
        raise refuse(f"{what} rows", f"must be a multiple of row_chunk = {caps.row_chunk}", caps.rows)
    return caps


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Voxels:
    """A set of voxels in a fixed-capacity buffer, in Morton order.

    Slots ``[0, count)`` hold unique voxels sorted by Morton code; later slots hold
    `UNUSED` (-1). `mode` is static (changing it recompiles).

    Attributes:
      coords: [capacity, 3] int32 voxel indices (i, j, k).
      count: [] int32 number of valid voxels.
      overflow: [] int32 bitmask of ``OVERFLOW_*`` flags; nonzero means the buffer
        holds a truncated set. The host-side `voxelize` never returns one.
      triangle: [capacity] int32 id of the triangle closest to each voxel's centre
        among those that set it (ties to the lower id), or None if not requested.
      grid: the `Grid` the indices refer to.
      mode: "conservative" or "6-separating".
    """

    coords: jax.Array  # [capacity, 3] int32
    count: jax.Array  # [] int32
    overflow: jax.Array  # [] int32
    triangle: jax.Array | None  # [capacity] int32
    grid: Grid
    mode: str = dataclasses.field(metadata=dict(static=True))

    @property
    def capacity(self) -> int:
        """Number of slots in the buffer."""
        return self.coords.shape[-2]

    @classmethod
    def from_coords(cls, ijk, grid: Grid, *, mode: str = CONSERVATIVE) -> "Voxels":
        """Voxels from arbitrary voxel indices (host-side): checked, deduplicated, Morton-sorted.

        Args:
          ijk: int [N, 3] voxel indices, each in ``[0, grid.resolution)``, any order,
            repeats allowed.
          grid: the `Grid` they refer to.
          mode: the mode to record (the set is taken as given).

        Raises:
          JaxvoxError: not a `Grid`, a bad mode, wrong shape, non-integer values or
            indices outside the grid.
        """
        check_type("Voxels.from_coords grid", grid, Grid)
        check_choice("Voxels.from_coords mode", mode, MODES)
        try:
            a = np.asarray(ijk)
        except ValueError:  # ragged nested sequences
            raise refuse("Voxels.from_coords ijk", "must have shape [N, 3]", ijk) from None
        if a.size == 0 and a.ndim == 1:  # e.g. []
            a = a.reshape(0, 3)
        if a.size == 0 and a.ndim == 2 and a.shape[1] == 3:
            a = a.astype(np.int32)
        if a.ndim != 2 or a.shape[1] != 3:
            raise refuse("Voxels.from_coords ijk", "must have shape [N, 3]", a.shape)
        if not np.issubdtype(a.dtype, np.integer):
            raise refuse("Voxels.from_coords ijk", "must be integers", a.dtype)
        outside = ((a < 0) | (a >= grid.resolution)).any(1)
        if outside.any():
            raise refuse("Voxels.from_coords ijk", f"holds voxel indices outside [0, {grid.resolution})",
                         a[outside][0])
        a = a.astype(np.int32)
        hi, lo = (np.asarray(w).astype(np.int64) for w in morton.encode(a))
        codes, first = np.unique((hi << 30) | lo, return_index=True)
        n = len(codes)
        coords = np.full((bucket(n), 3), UNUSED, np.int32)
        coords[:n] = a[first]
        return cls(jnp.asarray(coords), jnp.int32(n), jnp.int32(0), None, grid, mode)

    def to_numpy(self) -> np.ndarray:
        """The valid voxels as a host int32 [count, 3] array in Morton order.

        Raises:
          JaxvoxError: when the overflow flag is set (the set would be truncated).
        """
        check_overflow("Voxels", self.overflow, "use jaxvox.voxelize, which sizes capacities itself")
        return np.asarray(self.coords[: int(self.count)])

    def triangle_ids(self) -> np.ndarray:
        """Host int32 [count] triangle id per voxel (requires ``triangle_ids=True``).

        Raises:
          JaxvoxError: when the voxels carry no triangle ids.
        """
        if self.triangle is None:
            raise refuse("Voxels.triangle_ids self.triangle", "must hold triangle ids (voxelize with "
                         "triangle_ids=True)", self.triangle)
        return np.asarray(self.triangle[: int(self.count)])


# ----------------------------------------------------------------------------- setup


class _Triangles(NamedTuple):
    """Per-triangle constants (F triangles, H half-planes per projection).

    Every half-plane is stored as a bound on one coordinate that is linear in another:
    ``t >= lower_p + lower_q * s`` or ``t <= upper_p + upper_q * s`` (unused entries are
    -/+2^30 with slope 0), so columns and rows evaluate bounds with one multiply-add.
    """

    n_cols: jax.Array  # [F] int32 columns of each triangle (0 when inactive)
    col_lo: jax.Array  # [F] int32 first column (local u)
    col_data: jax.Array  # [F, 8H+7] float32 v bounds(u) and w bounds(u) (4H each), v range, w range, plane(u)
    row_data: jax.Array  # [F, 4H+1] float32 w bounds(v), plane slope ky
    base: jax.Array  # [F, 6] int32 base cell (x, y, z) and the axes u, v, w (w dominant)


def _half_planes(qa, qb, sigma, six_sep, tol):
    """Edge (and diamond) half-planes of one 2D projection of a triangle.

    Args:
      qa, qb: [3] float32 projected corner coordinates (local grid units).
      sigma: orientation, +1 or -1, so that edge normals point inwards.
      six_sep: static bool, diamond constants instead of box-corner constants.
      tol: widening distance in voxels.

    Returns:
      [3, H] float32 rows (alpha, beta, gamma): a voxel with 2D corner (a, b) passes
      when ``alpha * a + beta * b + gamma >= 0`` for all H half-planes (H = 3 edges,
      plus 4 diamond axes in 6-separating mode).
    """
    ea = jnp.roll(qa, -1) - qa
    eb = jnp.roll(qb, -1) - qb
    na, nb = -eb * sigma, ea * sigma
    l1 = jnp.abs(na) + jnp.abs(nb)
    if six_sep:
        push = 0.5 * (na + nb) + 0.5 * jnp.maximum(jnp.abs(na), jnp.abs(nb))
    else:
        push = jnp.maximum(na, 0.0) + jnp.maximum(nb, 0.0)
    gamma = -(na * qa + nb * qb) + push + tol * l1
    rows = [jnp.stack([na, nb, gamma])]
    if six_sep:
        # The diamond's axes: a + b <= max(s) - 1/2, a + b >= min(s) - 3/2 (s = qa + qb),
        # a - b <= max(t) + 1/2, a - b >= min(t) - 1/2 (t = qa - qb), for the corner (a, b).
        s, t = qa + qb, qa - qb
        rows.append(jnp.stack([
            jnp.array([-1.0, 1.0, -1.0, 1.0], jnp.float32),
            jnp.array([-1.0, 1.0, 1.0, -1.0], jnp.float32),
            jnp.stack([s.max() - 0.5, 1.5 - s.min(), t.max() + 0.5, 0.5 - t.min()]) + tol,
        ]))
    return jnp.concatenate(rows, axis=1)


def _plane_normal(q):
    """The plane used for depth ranges and its corners' largest depth deviation.

    The float32 cross product is used unless the triangle is degenerate or so thin that
    its corners stray further from that plane than from a plane through its longest
    edge (chosen so that its normal's largest component is the one along the edge's
    smallest axis); the deviation `delta` widens the depth range so it always contains
    the triangle.

    Returns:
      (normal [3] float32, delta [] float32 in voxels along the normal's largest axis).
    """
    n = jnp.cross(q[1] - q[0], q[2] - q[0])
    edges = jnp.roll(q, -1, axis=0) - q
    longest = edges[jnp.argmax(jnp.sum(edges * edges, axis=1))]
    m = jnp.argmin(jnp.abs(longest))
    n_fake = jnp.eye(3, dtype=jnp.float32)[m] * jnp.dot(longest, longest) - longest * longest[m]
    n_fake = jnp.where(jnp.any(n_fake != 0), n_fake, jnp.array([0.0, 0.0, 1.0], jnp.float32))

    def deviation(normal):
        big = jnp.max(jnp.abs(normal))
        safe = jnp.where(big > 0, big, 1.0)
        dev = jnp.max(jnp.abs((q - q[0]) @ normal)) / safe
        return jnp.where(big > 0, dev, jnp.inf)

    dev_n, dev_fake = deviation(n), deviation(n_fake)
    use_n = dev_n <= dev_fake
    return jnp.where(use_n, n, n_fake), jnp.where(use_n, dev_n, dev_fake)



def _interval(coef, rest, lo, hi):
    """Integers t with ``coef * t + rest >= 0`` for every half-plane, within [lo, hi].

    Args:
      coef, rest: [..., H] float32.
      lo, hi: [...] float32 integer-valued bounds.

    Returns:
      (lo [...], hi [...]) float32 integer-valued; empty when hi < lo.
    """
    bound = jnp.clip(-rest / jnp.where(coef == 0, 1.0, coef), -_BIG, _BIG)
    lower = jnp.where(coef > 0, jnp.ceil(bound), -_BIG)
    upper = jnp.where(coef < 0, jnp.floor(bound), _BIG)
    upper = jnp.where((coef == 0) & (rest < 0), -_BIG, upper)
    return jnp.maximum(lo, lower.max(-1)), jnp.minimum(hi, upper.min(-1))


def _linear_bounds(free, other, gamma):
    """Splits half-planes ``free * t + other * s + gamma >= 0`` by the sign of `free`.

    Returns:
      ([4, H] bounds on t linear in s: lower_p, lower_q, upper_p, upper_q), and
      ([2, H] constraints ``coef * s + rest >= 0`` on s alone from half-planes with
      ``free == 0``; the others become the neutral ``0 * s + 1``).
    """
    flat = free == 0
    safe = jnp.where(flat, 1.0, free)
    p, q = -gamma / safe, -other / safe
    lower, upper = free > 0, free < 0
    bounds = jnp.stack([jnp.where(lower, p, -_BIG), jnp.where(lower, q, 0.0),
                        jnp.where(upper, p, _BIG), jnp.where(upper, q, 0.0)])
    return bounds, jnp.stack([jnp.where(flat, other, 0.0), jnp.where(flat, gamma, 1.0)])


def _setup_triangle(p, region_lo, region_hi, six_sep):
    """Per-triangle constants of one triangle (vmapped by `_setup`).

    Args:
      p: [3, 3] float32 corners in grid units.
      region_lo, region_hi: [3] int32 inclusive voxel range that may be emitted.
      six_sep: static bool.
    """
    finite = jnp.all(jnp.isfinite(p))
    p = jnp.where(finite, p, 0.0)
    lo_f, hi_f = p.min(0), p.max(0)
    reg_lo = region_lo.astype(jnp.float32)
    reg_hi = region_hi.astype(jnp.float32)
    # Closed voxel range touched by the bounding box, clipped to the region.
    box_lo = jnp.clip(jnp.ceil(lo_f - 1.0), reg_lo, reg_hi + 1.0)
    box_hi = jnp.clip(jnp.floor(hi_f), reg_lo - 1.0, reg_hi)
    base = jnp.clip(jnp.floor(lo_f), reg_lo - 1.0, reg_hi + 1.0)
    q = p - base
    tol = _TOL * (1.0 + jnp.max(hi_f - lo_f))

    n_true = jnp.cross(q[1] - q[0], q[2] - q[0])
    normal, delta = _plane_normal(q)
    d = jnp.argmax(jnp.abs(normal))
    perm = (d + jnp.arange(1, 4)) % 3  # (u, v, w) = (d+1, d+2, d): a rotation of (x, y, z)
    qp, npl, nt = q[:, perm], normal[perm], n_true[perm]
    lo_i = (box_lo - base)[perm]
    hi_i = (box_hi - base)[perm]
    sign = lambda x: jnp.where(x >= 0, 1.0, -1.0)
    dom = _half_planes(qp[:, 0], qp[:, 1], sign(nt[2]), six_sep, tol)  # (u, v): alpha u + beta v
    vw = _half_planes(qp[:, 1], qp[:, 2], sign(nt[0]), six_sep, tol)  # (v, w): alpha v + beta w
    wu = _half_planes(qp[:, 2], qp[:, 0], sign(nt[1]), six_sep, tol)  # (w, u): alpha w + beta u
    v_of_u, u_only_a = _linear_bounds(dom[1], dom[0], dom[2])
    w_of_v, v_only = _linear_bounds(vw[1], vw[0], vw[2])
    w_of_u, u_only_b = _linear_bounds(wu[0], wu[1], wu[2])
    u_lo, u_hi = _interval(jnp.concatenate([u_only_a[0], u_only_b[0]]),
                           jnp.concatenate([u_only_a[1], u_only_b[1]]), lo_i[0], hi_i[0])
    v_lo, v_hi = _interval(v_only[0], v_only[1], lo_i[1], hi_i[1])

    # Depth range from the plane w = w0 + kx (u - u0) + ky (v - v0), widened by `delta`.
    kx, ky = -npl[0] / npl[2], -npl[1] / npl[2]
    slack = delta + tol
    if six_sep:  # the plane crosses the centre segment along w of voxel (u, v, .)
        z = qp[0, 2] + kx * (0.5 - qp[0, 0]) + ky * (0.5 - qp[0, 1])
        z_lo, z_hi = z - slack, z + slack
    else:  # the plane's extremes over the voxel's (u, v) square: critical corners
        z = qp[0, 2] - kx * qp[0, 0] - ky * qp[0, 1]
        z_lo = z + jnp.minimum(kx, 0.0) + jnp.minimum(ky, 0.0) - slack
        z_hi = z + jnp.maximum(kx, 0.0) + jnp.maximum(ky, 0.0) + slack

    active = finite & (u_hi >= u_lo) & (v_hi >= v_lo) & (hi_i[2] >= lo_i[2])
    if six_sep:  # zero-area triangles bound no area and set nothing in 6-separating mode
        # A repeated corner is tested directly: XLA may fuse the cross product's
        # multiply-adds, so cross(a, a) need not round to exactly zero.
        repeated = jnp.any(jnp.all(p == jnp.roll(p, 1, axis=0), axis=1))
        active &= jnp.any(n_true != 0) & ~repeated
    n_cols = jnp.where(active, u_hi - u_lo + 1.0, 0.0).astype(jnp.int32)
    col_data = jnp.concatenate([v_of_u.reshape(-1), w_of_u.reshape(-1),
                                jnp.stack([v_lo, v_hi, lo_i[2], hi_i[2], z_lo, z_hi, kx])])
    row_data = jnp.concatenate([w_of_v.reshape(-1), ky[None]])
    place = jnp.concatenate([base.astype(jnp.int32), perm.astype(jnp.int32)])
    return n_cols, u_lo.astype(jnp.int32), col_data, row_data, place


def _setup(tris, region_lo, region_hi, six_sep) -> _Triangles:
    """Per-triangle constants for F triangles [F, 3, 3] (grid units) inside a region."""
    fn = jax.vmap(_setup_triangle, in_axes=(0, None, None, None))
    return _Triangles(*fn(tris, region_lo, region_hi, six_sep))


# ------------------------------------------------------------------------ expansion


class _Columns(NamedTuple):
    """Column work items (C slots): one (triangle, column u) each."""

    tri: jax.Array  # [C] int32 triangle
    row_lo: jax.Array  # [C] float32 first row (local v)
    n_rows: jax.Array  # [C] int32 rows in the column (0 for invalid slots)
    depth: jax.Array  # [C, 4H+5] float32 w range, plane range at v = 0, w bounds(v), ky
    origin: jax.Array  # [C, 5] int32 global (i, j, k) of local (u, 0, 0), v axis, w axis
    total: jax.Array  # [] int32 number of columns needed


def _eval_bounds(bounds, s, lo, hi):
    """Intersects [lo, hi] with ``lower_p + lower_q s <= t <= upper_p + upper_q s``.

    Args:
      bounds: [..., 4H] float32 (lower_p, lower_q, upper_p, upper_q), H each.
      s: [...] float32; lo, hi: [...] float32 integer-valued.

    Returns:
      (lo, hi) [...] float32 integer-valued.
    """
    h = bounds.shape[-1] // 4
    s = s[..., None]
    lower = jnp.ceil(bounds[..., :h] + bounds[..., h:2 * h] * s).max(-1)
    upper = jnp.floor(bounds[..., 2 * h:3 * h] + bounds[..., 3 * h:] * s).min(-1)
    return jnp.maximum(lo, lower), jnp.minimum(hi, upper)


def _columns(tris: _Triangles, col_cap: int, start=0) -> _Columns:
    """Expands triangles into columns (the window of `col_cap` columns from `start` on);
    per column, its rows and depth coefficients."""
    tri, rank, valid, total = expand_counts(tris.n_cols, col_cap, start)
    cu = (tris.col_lo[tri] + rank).astype(jnp.float32)
    c = tris.col_data[tri]
    h4 = (c.shape[1] - 7) // 2
    v_lo, v_hi, w_lo, w_hi, z_lo, z_hi, kx = (c[:, 2 * h4 + i] for i in range(7))
    row_lo, row_hi = _eval_bounds(c[:, :h4], cu, v_lo, v_hi)
    w_lo, w_hi = _eval_bounds(c[:, h4:2 * h4], cu, w_lo, w_hi)
    n_rows = jnp.where(valid, jnp.maximum(row_hi - row_lo + 1.0, 0.0), 0.0).astype(jnp.int32)
    depth = jnp.concatenate([jnp.stack([w_lo, w_hi, z_lo + kx * cu, z_hi + kx * cu], 1),
                             tris.row_data[tri]], axis=1)
    place = tris.base[tri]
    u_step = cu.astype(jnp.int32)[:, None] * (jnp.arange(3, dtype=jnp.int32) == place[:, 3:4])
    origin = jnp.concatenate([place[:, :3] + u_step, place[:, 4:]], axis=1)
    return _Columns(tri, row_lo, n_rows, depth, origin, total)


class _Rows(NamedTuple):
    """Row work items (Rw slots): one (triangle, column, row) each."""

    place: jax.Array  # [Rw, 5] int32 global (i, j, k) of the row's first voxel, w axis, triangle
    n_depth: jax.Array  # [Rw] int32 voxels in the row (0 for invalid slots)
    total: jax.Array  # [] int32 number of row slots needed


def _rows(columns: _Columns, row_cap: int, chunk: int, start=0) -> _Rows:
    """Expands columns into rows; per row, the interval of depths that are set.

    Rows are handled `chunk` at a time (one gather of the column's coefficients per
    chunk), so `row_cap` counts slots of whole chunks; the window starts at chunk slot
    `start`.
    """
    n_chunks = (columns.n_rows + chunk - 1) // chunk
    col, rank, valid, total = expand_counts(n_chunks, row_cap // chunk, start)
    offset = rank[:, None] * chunk + jnp.arange(chunk, dtype=jnp.int32)  # [Rc, K]
    ok = valid[:, None] & (offset < columns.n_rows[col][:, None])
    v = columns.row_lo[col][:, None] + offset.astype(jnp.float32)
    c = columns.depth[col][:, None, :]
    ky = c[..., -1]
    lo = jnp.maximum(c[..., 0], jnp.ceil(c[..., 2] + ky * v - 1.0))
    hi = jnp.minimum(c[..., 1], jnp.floor(c[..., 3] + ky * v))
    lo, hi = _eval_bounds(c[..., 4:-1], v, lo, hi)
    n_depth = jnp.where(ok, jnp.maximum(hi - lo + 1.0, 0.0), 0.0).astype(jnp.int32)
    o = columns.origin[col][:, None, :]
    axis = jnp.arange(3, dtype=jnp.int32)
    lo_i = jnp.where(ok, lo, 0.0).astype(jnp.int32)
    start = (o[..., :3] + v.astype(jnp.int32)[..., None] * (axis == o[..., 3:4])
             + lo_i[..., None] * (axis == o[..., 4:5]))
    tri = jnp.broadcast_to(columns.tri[col][:, None, None], ok.shape + (1,))
    w_axis = jnp.broadcast_to(o[..., 4:5], tri.shape)
    place = jnp.concatenate([start, w_axis, tri], axis=-1)
    return _Rows(place.reshape(-1, 5), n_depth.reshape(-1), total * chunk)


def _candidates(tris_grid, rows: _Rows, cand_cap: int, words: int, with_ids: bool, start=0, ids=None):
    """Expands rows into candidate voxels (the window of `cand_cap` from `start` on) and
    their sort operands.

    Args:
      ids: [F] int32 triangle id to record for each row of `tris_grid` (default: the row).

    Returns:
      (keys: tuple of `words` uint32 [cand_cap] Morton words (invalid = EMPTY),
      payload: (squared-distance bits, triangle id) uint32 [cand_cap] or (),
      total [] int32 candidates needed).
    """
    row, rank, valid, total = expand_counts(rows.n_depth, cand_cap, start)
    p = rows.place[row]
    ijk = p[:, :3] + rank[:, None] * (jnp.arange(3, dtype=jnp.int32) == p[:, 3:4])
    if words == 1:
        keys = (jnp.where(valid, morton.encode_word(ijk & morton.WORD_MASK), morton.EMPTY),)
    else:
        keys = tuple(jnp.where(valid, k, morton.EMPTY) for k in morton.encode(ijk))
    payload = ()
    if with_ids:
        tri = p[:, 4]
        corners = tris_grid[tri]
        dist2 = point_triangle_dist2(ijk.astype(jnp.float32) + 0.5, corners[:, 0], corners[:, 1], corners[:, 2])
        payload = (jax.lax.bitcast_convert_type(dist2, jnp.uint32),
                   (tri if ids is None else ids[tri]).astype(jnp.uint32))
    return keys, payload, total


def _compact(keep, arrays, capacity, fill):
    """Moves entries where `keep` to the front of `capacity`-sized buffers (order kept).

    Returns:
      (tuple of [capacity] arrays padded with `fill`, number of kept entries [] int32).
    """
    pos = jnp.where(keep, jnp.cumsum(keep) - 1, capacity)  # dropped entries go past the end
    out = tuple(jnp.full(capacity, fill, a.dtype).at[pos].set(a, mode="drop") for a in arrays)
    return out, jnp.sum(keep, dtype=jnp.int32)


def _sort_unique(keys, payload, words: int, region_lo, vox_cap: int):
    """Sorts candidates (EMPTY padding sorts last), keeps the first of each key, decodes.

    With a payload the sort's later keys are (distance, triangle), so the kept entry is
    the closest triangle, ties to the lower id.

    Returns:
      (coords [vox_cap, 3] int32, triangle [vox_cap] int32 or None, count [] int32).
    """
    operands = keys + payload
    if len(operands) == 1:
        ordered = (jnp.sort(operands[0]),)
    else:
        ordered = jax.lax.sort(operands, num_keys=len(operands))
    k = ordered[:words]
    changed = functools.reduce(jnp.logical_or, [a[1:] != a[:-1] for a in k])
    keep = (k[-1] != morton.EMPTY) & jnp.concatenate([jnp.ones(1, bool), changed])
    extra = (ordered[-1].astype(jnp.int32),) if payload else ()
    out, count = _compact(keep, k + extra, vox_cap, 0)
    if words == 1:  # the region is aligned and at most 1024 wide: its high word is shared
        coords = morton.decode_word(out[0]) | ((region_lo >> morton.WORD_BITS) << morton.WORD_BITS)
    else:
        coords = morton.decode(out[0], out[1])
    used = jnp.arange(vox_cap) < count
    coords = jnp.where(used[:, None], coords, UNUSED)
    triangle = jnp.where(used, out[-1], UNUSED) if payload else None
    return coords, triangle, jnp.minimum(count, vox_cap), count


# ------------------------------------------------------------------- jittable core


def _words(region_size: int) -> int:
    return 1 if region_size <= REGION_SIZE else 2


def _pipeline(tris_grid, region_lo, region_size: int, six_sep: bool, caps: Capacities, with_ids: bool):
    """All stages for one aligned cubic region; returns (coords, triangle, count, overflow)."""
    region_hi = region_lo + region_size - 1
    words = _words(region_size)
    tris = _setup(tris_grid, region_lo, region_hi, six_sep)
    columns = _columns(tris, caps.columns)
    rows = _rows(columns, caps.rows, caps.row_chunk)
    keys, payload, n_cand = _candidates(tris_grid, rows, caps.candidates, words, with_ids)
    coords, triangle, count, n_vox = _sort_unique(keys, payload, words, region_lo, caps.voxels)
    overflow = functools.reduce(jnp.bitwise_or, [
        jnp.where(columns.total > caps.columns, OVERFLOW_COLUMNS, 0),
        jnp.where(rows.total > caps.rows, OVERFLOW_ROWS, 0),
        jnp.where(n_cand > caps.candidates, OVERFLOW_CANDIDATES, 0),
        jnp.where(n_vox > caps.voxels, OVERFLOW_VOXELS, 0)]).astype(jnp.int32)
    return coords, triangle, count, overflow


def voxelize_fixed(mesh: Mesh, grid: Grid, capacities: Capacities, *, mode: Mode = CONSERVATIVE,
                   triangle_ids: bool = False, checked: bool = False) -> Voxels:
    """Jittable voxelization with static capacities; usable inside a user's `jax.jit`.

    Never resizes: what does not fit is dropped and flagged in ``Voxels.overflow``
    (`jaxvox.Overflow` bits COLUMNS, ROWS, CANDIDATES, VOXELS). Get capacities that fit
    from `voxel_capacities`, or use the host-side `voxelize`, which sizes them and never
    returns a truncated result (see `jaxvox.overflow` for the protocol).
    Input validation (NaN vertices, face indices) is the caller's job here: non-finite
    triangles are skipped and out-of-range indices are clamped by JAX's gather.

    Args:
      mesh: `Mesh` with F faces.
      grid: `Grid`; the whole grid is one region (Morton keys take two words above 1024^3).
      capacities: `Capacities` (static).
      mode: "conservative" or "6-separating" (static).
      triangle_ids: also return the closest triangle id per voxel (static).
      checked: raise (as an error of the running computation) instead of returning a
        flagged result when a capacity is too small (static).

    Returns:
      `Voxels` with capacity ``capacities.voxels``.

    Raises:
      JaxvoxError: not a `Mesh` or `Grid`, a bad mode, or capacities that are not
        integers >= 1 with a power-of-two ``row_chunk`` dividing ``rows``.
    """
    check_type("voxelize_fixed mesh", mesh, Mesh)
    check_type("voxelize_fixed grid", grid, Grid)
    capacities = check_capacities("voxelize_fixed capacities", capacities)
    six_sep = check_choice("voxelize_fixed mode", mode, MODES) == SIX_SEPARATING
    tris = grid.to_grid_units(mesh.triangles())
    coords, triangle, count, overflow = _pipeline(
        tris, jnp.zeros(3, jnp.int32), grid.resolution, six_sep, capacities, triangle_ids)
    if checked:
        raise_if_overflow("voxelize_fixed result", overflow)
    return Voxels(coords, count, overflow, triangle, grid, mode)


# ------------------------------------------------------------------ host-side API

# The host path walks fixed work windows, so that every mesh at every resolution runs the
# same few compiled programs whatever its counts: triangles in chunks of `_CHUNK`,
# expanded into windows of columns, row slots and candidates, written into fixed pages.
# Only the sort of a region's candidates (a whole number of pages, on the shape ladder)
# changes shape.
_CHUNK = 4096
_WINDOW_COLUMNS = 1 << 15
_WINDOW_ROWS = 1 << 16
_WINDOW_CANDIDATES = 1 << 17
_PAGE = 1 << 18  # slots per page of a region's sort buffer (the emit program writes two)


def _walk(tris_grid, region_lo, region_hi, six_sep, visit, carry):
    """Calls ``carry = visit(rows, carry)`` on every row window of a chunk of triangles.

    Returns:
      (columns [] int32, row slots [] int32, final carry).
    """
    tris = _setup(tris_grid, region_lo, region_hi, six_sep)

    def columns_step(state):
        start, slots, carry = state
        columns = _columns(tris, _WINDOW_COLUMNS, start)
        n_slots = jnp.sum((columns.n_rows + ROW_CHUNK - 1) // ROW_CHUNK)

        def rows_step(state):
            row_start, carry = state
            rows = _rows(columns, _WINDOW_ROWS, ROW_CHUNK, row_start)
            return row_start + _WINDOW_ROWS // ROW_CHUNK, visit(rows, carry)

        _, carry = jax.lax.while_loop(lambda s: s[0] < n_slots, rows_step, (jnp.int32(0), carry))
        return start + _WINDOW_COLUMNS, slots + n_slots * ROW_CHUNK, carry

    n_cols = jnp.sum(tris.n_cols)
    _, n_slots, carry = jax.lax.while_loop(lambda s: s[0] < n_cols, columns_step,
                                           (jnp.int32(0), jnp.int32(0), carry))
    return n_cols, n_slots, carry


@functools.partial(jax.jit, static_argnames=("six_sep",))
def _count_chunk(tris_grid, region_lo, region_hi, *, six_sep):
    """[3] int32 (columns, row slots, candidates) of a chunk [_CHUNK, 3, 3] in a region."""
    visit = lambda rows, n: n + jnp.sum(rows.n_depth)
    n_cols, n_slots, n_cand = _walk(tris_grid, region_lo, region_hi, six_sep, visit, jnp.int32(0))
    return jnp.stack([n_cols, n_slots, n_cand])


@functools.partial(jax.jit, static_argnames=("six_sep", "with_ids"), donate_argnames=("pages",))
def _emit_chunk(tris_grid, ids, region_lo, region_hi, pages, offset, *, six_sep, with_ids):
    """Writes the candidates of a chunk that fall in two consecutive pages of the region's
    sort buffer (a chunk holds fewer candidates than a page, so one call usually writes
    all of them).

    Args:
      tris_grid: [_CHUNK, 3, 3] float32 triangles in grid units (NaN rows are skipped).
      ids: [_CHUNK] int32 triangle ids to record.
      pages: two pages, each (keys,) or (keys, distance bits, triangle ids) of uint32
        [_PAGE] (donated).
      offset: [] int32 slot of the chunk's first candidate relative to the first page's
        first slot (negative when the chunk started in an earlier page); candidates
        outside the two pages are skipped.

    Returns:
      The two pages.
    """
    def visit(rows, carry):
        pages, offset = carry
        n = jnp.sum(rows.n_depth)

        def step(state):
            start, pages = state
            keys, payload, _ = _candidates(tris_grid, rows, _WINDOW_CANDIDATES, 1, with_ids, start, ids)
            slot = start + jnp.arange(_WINDOW_CANDIDATES, dtype=jnp.int32)
            pos = jnp.where((slot < n) & (offset + slot >= 0), offset + slot, 2 * _PAGE)
            return start + _WINDOW_CANDIDATES, tuple(
                tuple(b.at[pos - first].set(v, mode="drop") for b, v in zip(page, keys + payload))
                for first, page in zip((0, _PAGE), pages))  # slots outside a page are dropped

        # Only the windows that overlap the pages: from the one holding their first slot.
        first = jnp.maximum(-offset, 0) // _WINDOW_CANDIDATES * _WINDOW_CANDIDATES
        _, pages = jax.lax.while_loop(lambda s: (s[0] < n) & (offset + s[0] < 2 * _PAGE), step, (first, pages))
        return pages, offset + n

    return _walk(tris_grid, region_lo, region_hi, six_sep, visit, (pages, offset))[2][0]


@jax.jit
def _sort_region(pages, region_lo):
    """Sorts and deduplicates a region's candidates, given as pages of sort operands.

    Returns:
      (coords [K, 3] int32, triangle [K] int32 or None, count [] int32), K the pages' total.
    """
    buffers = tuple(jnp.concatenate(parts) for parts in zip(*pages))
    coords, triangle, count, _ = _sort_unique(buffers[:1], buffers[1:], 1, region_lo, buffers[0].shape[0])
    return coords, triangle, count


def _grid_triangles(mesh: Mesh, grid: Grid) -> np.ndarray:
    """Host float32 [F, 3, 3] triangle corners in grid units (the same float32 operations
    as `Grid.to_grid_units`; numpy, so a new mesh size compiles nothing)."""
    v = np.asarray(mesh.vertices, np.float32)[np.asarray(mesh.faces)]
    return (v - np.asarray(grid.origin, np.float32)) / np.asarray(grid.voxel_size, np.float32)


def _chunks(tris: np.ndarray, idx: np.ndarray):
    """Device arrays (triangles [_CHUNK, 3, 3] NaN-padded, ids [_CHUNK] int32) per chunk of `idx`."""
    out = []
    for start in range(0, len(idx), _CHUNK):
        part = idx[start:start + _CHUNK]
        t = np.full((_CHUNK, 3, 3), np.nan, np.float32)
        t[:len(part)] = tris[part]
        ids = np.zeros(_CHUNK, np.int32)
        ids[:len(part)] = part
        out.append((jax.device_put(t), jax.device_put(ids)))
    return out


def _region_bounds(region_lo, region_size: int):
    lo = np.asarray(region_lo, np.int32)
    return jax.device_put(lo), jax.device_put(lo + np.int32(region_size - 1))


def _count_chunks(chunks, lo, hi, six_sep: bool) -> np.ndarray:
    """Host int64 [chunks, 3] (columns, row slots, candidates) of a region's chunks."""
    counts = [_count_chunk(t, lo, hi, six_sep=six_sep) for t, _ in chunks]
    return np.asarray(jax.device_get(counts), np.int64).reshape(-1, 3)


def _voxelize_region(tris: np.ndarray, idx: np.ndarray, region_lo, region_size: int, six_sep: bool,
                     with_ids: bool):
    """Host-side passes for one region: a counting pass places every chunk's candidates
    in the sort buffer, the chunks write them page by page and one sort makes them
    unique.

    Returns:
      (coords [n, 3] int32, triangle [n] int32 ids or None) host arrays.
    """
    lo, hi = _region_bounds(region_lo, region_size)
    chunks = _chunks(tris, idx)
    ends = np.cumsum(_count_chunks(chunks, lo, hi, six_sep)[:, 2])
    starts = ends - np.diff(ends, prepend=0)
    total = int(ends[-1])
    n_pages = bucket(total, _PAGE) // _PAGE
    pages = []
    for _ in range(n_pages + 1):  # and a spare page past the end, written as the last pair's second
        page = [np.full(_PAGE, morton.EMPTY, np.uint32)] + [np.zeros(_PAGE, np.uint32) for _ in range(2 * with_ids)]
        pages.append(tuple(jax.device_put(b, may_alias=False) for b in page))
    for (t, ids), start, end in zip(chunks, starts, ends):
        page = int(start) // _PAGE
        while page * _PAGE < end:  # two pages per call: once, unless a chunk spans more
            pages[page], pages[page + 1] = _emit_chunk(t, ids, lo, hi, (pages[page], pages[page + 1]),
                                                       np.int32(start - page * _PAGE), six_sep=six_sep,
                                                       with_ids=with_ids)
            page += 2
    pages = pages[:n_pages]
    coords, triangle, count = _sort_region(pages, lo)
    count = int(count)
    # The pages were sized by the exact count of the same walk, so nothing is dropped
    # (a count past the buffer would show as a missing sentinel, never silently).
    if count > total:
        raise JaxvoxError(f"internal error: {count} voxels from {total} candidates")
    return np.asarray(coords)[:count], (np.asarray(triangle)[:count] if with_ids else None)


def _regions(tris_np: np.ndarray, resolution: int, region_size: int):
    """Aligned regions touched by any triangle's bounding box, in Morton order.

    Returns a list of (region_lo int32[3], triangle indices) pairs.
    """
    n = resolution // region_size
    if n == 1:
        return [(np.zeros(3, np.int32), np.arange(len(tris_np)))]
    lo = np.clip(np.floor((tris_np.min(1) - 1.0) / region_size), 0, n - 1).astype(np.int64)
    hi = np.clip(np.floor(tris_np.max(1) / region_size), 0, n - 1).astype(np.int64)
    inside = (tris_np.max(1) >= 0).all(1) & (tris_np.min(1) <= resolution).all(1)
    cells = set()
    for a, b in {(tuple(l), tuple(h)) for l, h in zip(lo[inside], hi[inside])}:
        a = np.array(a)
        cells.update(tuple(a + c) for c in np.ndindex(*(np.array(b) - a + 1)))
    cells = np.array(sorted(cells), np.int64).reshape(-1, 3)
    order = np.argsort(morton.encode_word_host(cells), kind="stable")
    out = []
    for c in cells[order]:
        hit = inside & (lo <= c).all(1) & (hi >= c).all(1)
        out.append(((c * region_size).astype(np.int32), np.flatnonzero(hit)))
    return out


def _pad_rows(parts: list[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
    """Moves int32 host arrays into one buffer of `shape` padded with `UNUSED`.

    Empties `parts` as it goes, and the buffer's pages are only touched as they are
    filled, so the parts and the whole buffer are never held at once.
    """
    out = np.empty(shape, np.int32)
    start = 0
    parts.reverse()
    while parts:
        part = parts.pop()
        out[start:start + len(part)] = part
        start += len(part)
    out[start:] = UNUSED
    return out


def voxelize(mesh: Mesh, grid: Grid, *, mode: Mode = CONSERVATIVE, triangle_ids: bool = False,
             region_size: int = REGION_SIZE, progress: bool | None = None) -> Voxels:
    """Voxelizes a triangle mesh exactly; capacities are sized by counting passes.

    Triangles go through fixed-size chunks and fixed work windows, so every mesh runs
    the same compiled programs; a counting pass over the same windows sizes each
    region's candidate buffer (on the shape ladder), so nothing is ever dropped and no
    retry is needed. The count is checked against what was written, and a mismatch
    raises instead of returning a truncated set.

    Grids above `region_size`^3 are streamed: the grid is cut into aligned cubic
    regions, visited in Morton order, each voxelized from the triangles whose bounding
    boxes touch it, so working memory follows the surface inside one region and the
    concatenated result is already in Morton order.

    Args:
      mesh: the `Mesh` (validated: NaN/inf vertices or bad face indices raise).
      grid: the `Grid`; geometry outside it is clipped.
      mode: "conservative" (every voxel whose closed box touches the closed triangle)
        or "6-separating" (Schwarz & Seidel's thin, 6-separating subset).
      triangle_ids: also record, per voxel, the id of the triangle closest to its
        centre among those that set it (ties to the lower id).
      region_size: edge of the streaming regions, a power of two <= 1024.
      progress: show a progress bar over regions (default: when on a terminal).

    Returns:
      `Voxels` with ``overflow == 0`` and capacity rounded up to a few buckets.

    Raises:
      JaxvoxError: not a `Grid`, a bad mode, region size or mesh.
    """
    check_type("voxelize grid", grid, Grid)
    six_sep = check_choice("voxelize mode", mode, MODES) == SIX_SEPARATING
    validate_mesh(mesh)
    region_size = check_int("voxelize region_size", region_size, minimum=1, maximum=REGION_SIZE)
    if region_size & (region_size - 1):
        raise refuse("voxelize region_size", f"must be a power of two <= {REGION_SIZE}", region_size)
    region_size = min(region_size, grid.resolution)
    tris = _grid_triangles(mesh, grid)
    regions = _regions(tris, grid.resolution, region_size) if mesh.num_faces else []
    from tqdm.auto import tqdm

    parts, tri_parts = [], []
    disable = len(regions) < 2 if progress is None else not progress
    for region_lo, idx in tqdm(regions, desc="regions", disable=disable, leave=False):
        coords, triangle = _voxelize_region(tris, idx, region_lo, region_size, six_sep, triangle_ids)
        parts.append(coords)  # on the host as we go: device memory holds one region
        if triangle_ids:
            tri_parts.append(triangle)
    total = sum(len(p) for p in parts)
    cap = bucket(total)
    coords = _pad_rows(parts, (cap, 3))
    triangle = _pad_rows(tri_parts, (cap,)) if triangle_ids else None
    to_device = functools.partial(jax.device_put, may_alias=True)  # one copy, not jnp.asarray's two
    return Voxels(to_device(coords), jnp.int32(total), jnp.int32(0),
                  None if triangle is None else to_device(triangle), grid, mode)


def voxel_capacities(mesh: Mesh, grid: Grid, *, mode: Mode = CONSERVATIVE) -> Capacities:
    """Capacities with which `voxelize_fixed` does not overflow for this mesh and grid.

    Found by the host-side counting pass over the whole grid as one region (and the
    voxel count of `voxelize`), each rounded up on the shape ladder so that similar
    inputs share a compiled function.

    Raises:
      JaxvoxError: not a `Grid`, a bad mode or mesh.
    """
    check_type("voxel_capacities grid", grid, Grid)
    six_sep = check_choice("voxel_capacities mode", mode, MODES) == SIX_SEPARATING
    validate_mesh(mesh)
    if mesh.num_faces == 0:
        return Capacities(*(bucket(0),) * 4, ROW_CHUNK)
    lo, hi = _region_bounds(np.zeros(3, np.int32), grid.resolution)
    chunks = _chunks(_grid_triangles(mesh, grid), np.arange(mesh.num_faces))
    columns, rows, candidates = (bucket(n) for n in _count_chunks(chunks, lo, hi, six_sep).sum(0))
    voxels = bucket(int(voxelize(mesh, grid, mode=mode).count))
    return Capacities(columns, rows, candidates, voxels, ROW_CHUNK)
