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
into a row capacity; per-row depth intervals emitted into ``depth`` slots; the valid
candidates are compacted, sorted by Morton code and made unique. No dense ``R^3`` array
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
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox import morton
from jaxvox._errors import JaxvoxError
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh, validate_mesh

CONSERVATIVE = "conservative"
SIX_SEPARATING = "6-separating"
MODES = (CONSERVATIVE, SIX_SEPARATING)

# Overflow bits of `Voxels.overflow`: which fixed capacity was too small.
OVERFLOW_COLUMNS = 1
OVERFLOW_ROWS = 2
OVERFLOW_DEPTH = 4
OVERFLOW_CANDIDATES = 8
OVERFLOW_VOXELS = 16

UNUSED = -1  # value of coordinate and triangle slots past `count`
REGION_SIZE = 1 << morton.WORD_BITS  # largest region sorted with one 32-bit key

_TOL = 2.0**-19  # relative half-plane widening, see the module docstring
_BIG = float(1 << 30)  # clamp for interval bounds before integer conversion


def _check_mode(mode: str) -> str:
    if mode not in MODES:
        raise JaxvoxError(f"unknown voxelization mode {mode!r}; expected one of {MODES}")
    return mode


class Capacities(NamedTuple):
    """Static sizes of the work buffers of `voxelize_fixed` (changing one recompiles).

    Attributes:
      columns: (triangle, column) work items.
      rows: (triangle, column, row) work items.
      depth: voxel slots per row item (4 covers every well-shaped triangle
        conservatively, 3 in 6-separating mode).
      candidates: voxels emitted before duplicates are removed.
      voxels: unique voxels in the result.
    """

    columns: int
    rows: int
    depth: int
    candidates: int
    voxels: int


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["coords", "count", "overflow", "triangle", "grid"],
                   meta_fields=["mode"])
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
    mode: str

    @property
    def capacity(self) -> int:
        """Number of slots in the buffer."""
        return self.coords.shape[-2]

    def to_numpy(self) -> np.ndarray:
        """The valid voxels as a host int32 [count, 3] array in Morton order.

        Raises:
          JaxvoxError: when the overflow flag is set (the set would be truncated).
        """
        if int(self.overflow):
            raise JaxvoxError(f"voxel buffer overflowed (flags {int(self.overflow)}); "
                              "use jaxvox.voxelize, which sizes capacities itself")
        return np.asarray(self.coords[: int(self.count)])

    def triangle_ids(self) -> np.ndarray:
        """Host int32 [count] triangle id per voxel (requires ``triangle_ids=True``)."""
        if self.triangle is None:
            raise JaxvoxError("these voxels carry no triangle ids; voxelize with triangle_ids=True")
        return np.asarray(self.triangle[: int(self.count)])


# ----------------------------------------------------------------------------- setup


class _Tables(NamedTuple):
    """Per-triangle constants, packed so that one gather fetches a triangle's row."""

    n_cols: jax.Array  # [F] int32 columns of each triangle (0 when inactive)
    col_lo: jax.Array  # [F] int32 first column (local u)
    rows: jax.Array  # [F, 3H+2] float32 dominant half-planes (alpha, beta, gamma) + v range
    depth: jax.Array  # [F, 6H+8] float32 side half-planes, plane and w range
    place: jax.Array  # [F, 4] int32 base cell (u, v, w, global) and dominant axis


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
        s, t = qa + qb, qa - qb
        one = jnp.ones(4, jnp.float32)
        rows.append(jnp.stack([
            one * jnp.array([-1.0, 1.0, -1.0, 1.0]),
            one * jnp.array([-1.0, 1.0, 1.0, -1.0]),
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


def _setup_triangle(p, region_lo, region_hi, six_sep):
    """Per-triangle constants (one triangle; vmapped by `_setup`).

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
    extent = jnp.max(hi_f - lo_f)
    tol = _TOL * (1.0 + extent)

    n_true = jnp.cross(q[1] - q[0], q[2] - q[0])
    normal, delta = _plane_normal(q)
    d = jnp.argmax(jnp.abs(normal))
    perm = (d + jnp.arange(1, 4)) % 3  # (u, v, w) = (d+1, d+2, d): a rotation of (x, y, z)
    qp, np_, nt = q[:, perm], normal[perm], n_true[perm]
    lo_i = (box_lo - base)[perm]
    hi_i = (box_hi - base)[perm]
    sign = lambda x: jnp.where(x >= 0, 1.0, -1.0)
    planes = [
        _half_planes(qp[:, 0], qp[:, 1], sign(nt[2]), six_sep, tol),  # dominant (u, v)
        _half_planes(qp[:, 1], qp[:, 2], sign(nt[0]), six_sep, tol),  # side (v, w)
        _half_planes(qp[:, 2], qp[:, 0], sign(nt[1]), six_sep, tol),  # side (w, u)
    ]
    kx, ky = -np_[0] / np_[2], -np_[1] / np_[2]
    plane = jnp.stack([qp[0, 0], qp[0, 1], qp[0, 2], kx, ky, delta + tol])

    active = finite & jnp.all(hi_i >= lo_i)
    if six_sep:  # zero-area triangles bound no area and set nothing in 6-separating mode
        active &= jnp.any(n_true != 0)
    n_cols = jnp.where(active, hi_i[0] - lo_i[0] + 1.0, 0.0).astype(jnp.int32)
    rows = jnp.concatenate([planes[0].reshape(-1), lo_i[1:2], hi_i[1:2]])
    depth = jnp.concatenate([planes[1].reshape(-1), planes[2].reshape(-1), plane, lo_i[2:], hi_i[2:]])
    place = jnp.concatenate([base[perm], d[None].astype(jnp.float32)]).astype(jnp.int32)
    return n_cols, lo_i[0].astype(jnp.int32), rows, depth, place


def _setup(tris, region_lo, region_hi, six_sep) -> _Tables:
    fn = jax.vmap(_setup_triangle, in_axes=(0, None, None, None))
    return _Tables(*fn(tris, region_lo, region_hi, six_sep))


# ------------------------------------------------------------------------ expansion


def _expand(counts, capacity):
    """Expands per-item counts into `capacity` work slots.

    Args:
      counts: [n] int32 non-negative counts.
      capacity: static int, number of slots.

    Returns:
      (owner [capacity] int32 item of each slot, rank [capacity] int32 position within
      its item, valid [capacity] bool, total [] int32 = sum(counts)). Slots past
      `total` are invalid (owner clamped to a real item).
    """
    ends = jnp.cumsum(counts)
    starts = ends - counts
    total = ends[-1] if counts.shape[0] else jnp.int32(0)
    # The owner of slot s is the last item whose start is <= s: mark starts, then cummax.
    marks = jnp.zeros(capacity, jnp.int32).at[starts].max(
        jnp.where(counts > 0, jnp.arange(counts.shape[0], dtype=jnp.int32), 0), mode="drop")
    owner = jax.lax.cummax(marks)
    slot = jnp.arange(capacity, dtype=jnp.int32)
    rank = slot - starts[owner] if counts.shape[0] else slot
    return owner, rank, slot < total, total


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


def _columns(tables: _Tables, col_cap: int):
    """Column work items and their row intervals.

    Returns:
      (tri [C] int32, cu [C] float32 local column, row_lo [C] float32, n_rows [C] int32,
      total columns [] int32).
    """
    tri, rank, valid, total = _expand(tables.n_cols, col_cap)
    cu = (tables.col_lo[tri] + rank).astype(jnp.float32)
    r = tables.rows[tri]
    h = (r.shape[1] - 2) // 3
    alpha, beta, gamma = r[:, :h], r[:, h:2 * h], r[:, 2 * h:3 * h]
    row_lo, row_hi = _interval(beta, alpha * cu[:, None] + gamma, r[:, -2], r[:, -1])
    n_rows = jnp.where(valid, jnp.maximum(row_hi - row_lo + 1.0, 0.0), 0.0).astype(jnp.int32)
    return tri, cu, row_lo, n_rows, total


def _rows(tables: _Tables, columns, row_cap: int, six_sep: bool):
    """Row work items and their depth intervals.

    Returns:
      (tri [Rw] int32, cuvk [Rw, 3] float32 local (column, row, first depth),
      n_depth [Rw] int32, total rows [] int32).
    """
    col_tri, col_u, col_row_lo, n_rows, _ = columns
    col, rank, valid, total = _expand(n_rows, row_cap)
    tri = col_tri[col]
    cu = col_u[col]
    cv = col_row_lo[col] + rank.astype(jnp.float32)
    t = tables.depth[tri]
    h = (t.shape[1] - 8) // 6
    side_vw, side_wu = t[:, :3 * h], t[:, 3 * h:6 * h]
    u0, v0, w0, kx, ky, slack = (t[:, 6 * h + i] for i in range(6))
    w_lo, w_hi = t[:, -2], t[:, -1]
    if six_sep:  # the plane crosses the centre segment along w
        zc = w0 + kx * (cu + 0.5 - u0) + ky * (cv + 0.5 - v0)
        z_lo, z_hi = zc - slack, zc + slack
    else:  # the plane crosses the box: critical corners
        z = w0 + kx * (cu - u0) + ky * (cv - v0)
        z_lo = z + jnp.minimum(kx, 0.0) + jnp.minimum(ky, 0.0) - slack
        z_hi = z + jnp.maximum(kx, 0.0) + jnp.maximum(ky, 0.0) + slack
    lo = jnp.maximum(w_lo, jnp.ceil(z_lo - 1.0))
    hi = jnp.minimum(w_hi, jnp.floor(z_hi))
    # side (v, w): alpha * v + beta * w + gamma >= 0; side (w, u): alpha * w + beta * u + gamma >= 0.
    lo, hi = _interval(side_vw[:, h:2 * h], side_vw[:, :h] * cv[:, None] + side_vw[:, 2 * h:], lo, hi)
    lo, hi = _interval(side_wu[:, :h], side_wu[:, h:2 * h] * cu[:, None] + side_wu[:, 2 * h:], lo, hi)
    n_depth = jnp.where(valid, jnp.maximum(hi - lo + 1.0, 0.0), 0.0).astype(jnp.int32)
    return tri, jnp.stack([cu, cv, lo], axis=-1), n_depth, total


def _point_triangle_dist2(p, a, b, c):
    """Squared distance from points p [n, 3] to triangles (a, b, c) [n, 3] (Ericson's regions)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = jnp.sum(ab * ap, -1), jnp.sum(ac * ap, -1)
    bp, cp = p - b, p - c
    d3, d4 = jnp.sum(ab * bp, -1), jnp.sum(ac * bp, -1)
    d5, d6 = jnp.sum(ab * cp, -1), jnp.sum(ac * cp, -1)

    def seg(x0, x1):
        e = x1 - x0
        ee = jnp.sum(e * e, -1)
        s = jnp.clip(jnp.sum((p - x0) * e, -1) / jnp.where(ee > 0, ee, 1.0), 0.0, 1.0)
        r = p - (x0 + s[:, None] * e)
        return jnp.sum(r * r, -1)

    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    inside = (va >= 0) & (vb >= 0) & (vc >= 0)
    den = va + vb + vc
    safe = jnp.where(den > 0, den, 1.0)
    proj = a + (vb / safe)[:, None] * ab + (vc / safe)[:, None] * ac
    r = p - proj
    face = jnp.sum(r * r, -1)
    edges = jnp.minimum(jnp.minimum(seg(a, b), seg(b, c)), seg(c, a))
    return jnp.where(inside & (den > 0), jnp.minimum(face, edges), edges)


def _emit(tables: _Tables, rows, depth: int, region_words: int, tris, with_ids: bool):
    """Candidate voxels of every row item, `depth` slots each.

    Returns:
      (keys: tuple of uint32 [Rw * depth] sort keys (Morton words; invalid = EMPTY),
      payload: tuple of extra sort operands (distance bits, triangle id) or (),
      max_depth [] int32 largest depth interval seen).
    """
    tri, cuvk, n_depth = rows
    slot = jnp.arange(depth, dtype=jnp.float32)
    local = jnp.broadcast_to(cuvk[:, None, :], (cuvk.shape[0], depth, 3))
    local = local.at[:, :, 2].add(slot)
    valid = slot[None, :] < n_depth[:, None].astype(jnp.float32)
    place = tables.place[tri]
    ijk_perm = local.astype(jnp.int32) + place[:, None, :3]
    # Permuted axis p is original axis (d + 1 + p) % 3; invert the rotation.
    inv = (jnp.arange(3)[None, :] - place[:, 3:4] - 1) % 3
    ijk = jnp.take_along_axis(ijk_perm, inv[:, None, :], axis=2).reshape(-1, 3)
    valid = valid.reshape(-1)
    if region_words == 1:
        keys = (jnp.where(valid, morton.encode_word(ijk & morton.WORD_MASK), morton.EMPTY),)
    else:
        hi, lo = morton.encode(ijk)
        keys = (jnp.where(valid, hi, morton.EMPTY), jnp.where(valid, lo, morton.EMPTY))
    payload = ()
    if with_ids:
        tri_rep = jnp.repeat(tri, depth)
        corners = tris[tri_rep]
        dist2 = _point_triangle_dist2(ijk.astype(jnp.float32) + 0.5, corners[:, 0], corners[:, 1], corners[:, 2])
        payload = (jax.lax.bitcast_convert_type(dist2, jnp.uint32), tri_rep.astype(jnp.uint32))
    return keys, payload, valid, n_depth.max(initial=0)


def _compact(valid, arrays, capacity, fill):
    """Moves entries where `valid` to the front of `capacity`-sized buffers (order kept).

    Returns:
      (tuple of [capacity] arrays padded with `fill`, number of valid entries [] int32).
    """
    pos = jnp.cumsum(valid) - 1
    pos = jnp.where(valid, pos, capacity)  # invalid entries go to a dump slot, dropped
    out = tuple(jnp.full(capacity, fill, a.dtype).at[pos].set(a, mode="drop") for a in arrays)
    return out, jnp.sum(valid, dtype=jnp.int32)


def _sort_unique(keys, payload, region_words: int, base_hi, vox_cap: int):
    """Sorts candidates (padding sorts last), keeps the first of each key, decodes.

    Returns:
      (coords [vox_cap, 3] int32, triangle [vox_cap] int32 or None, count [] int32).
    """
    operands = keys + payload
    ordered = jax.lax.sort(operands, num_keys=len(operands)) if len(operands) > 1 else (jnp.sort(keys[0]),)
    k = ordered[:len(keys)]
    real = k[-1] != morton.EMPTY
    first = jnp.ones_like(real).at[1:].set(functools.reduce(
        jnp.logical_or, [a[1:] != a[:-1] for a in k]))
    keep = real & first
    extra = (ordered[-1].astype(jnp.int32),) if payload else ()
    out, count = _compact(keep, k + extra, vox_cap, 0)
    if region_words == 1:
        coords = morton.decode_word(out[0]) | (base_hi << morton.WORD_BITS)
    else:
        coords = morton.decode(out[0], out[1])
    used = jnp.arange(vox_cap) < count
    coords = jnp.where(used[:, None], coords, UNUSED)
    triangle = jnp.where(used, out[-1], UNUSED) if payload else None
    return coords, triangle, count


# ------------------------------------------------------------------- jittable core


def _region_pipeline(tris, region_lo, region_size, six_sep, caps: Capacities, with_ids: bool):
    """Voxelizes triangles (grid units) inside one aligned cubic region.

    Returns:
      (coords, triangle, count, overflow, sizes) where `sizes` holds the exact number
      of columns, rows, candidates and the largest depth interval (exact only for
      stages whose predecessors did not overflow).
    """
    region_hi = region_lo + region_size - 1
    words = 1 if region_size <= REGION_SIZE else 2
    tables = _setup(tris, region_lo, region_hi, six_sep)
    columns = _columns(tables, caps.columns)
    tri, cuvk, n_depth, n_rows = _rows(tables, columns, caps.rows, six_sep)
    keys, payload, valid, max_depth = _emit(tables, (tri, cuvk, n_depth), caps.depth, words, tris, with_ids)
    compacted, n_cand = _compact(valid, keys + payload, caps.candidates, morton.EMPTY)
    keys, payload = compacted[:len(keys)], compacted[len(keys):]
    base_hi = region_lo >> morton.WORD_BITS
    coords, triangle, count = _sort_unique(keys, payload, words, base_hi, caps.voxels)
    n_cols = columns[-1]
    overflow = (jnp.where(n_cols > caps.columns, OVERFLOW_COLUMNS, 0)
                | jnp.where(n_rows > caps.rows, OVERFLOW_ROWS, 0)
                | jnp.where(max_depth > caps.depth, OVERFLOW_DEPTH, 0)
                | jnp.where(n_cand > caps.candidates, OVERFLOW_CANDIDATES, 0)
                | jnp.where(count > caps.voxels, OVERFLOW_VOXELS, 0)).astype(jnp.int32)
    return coords, triangle, jnp.minimum(count, caps.voxels), overflow, (n_cols, n_rows, n_cand, max_depth)


def voxelize_fixed(mesh: Mesh, grid: Grid, capacities: Capacities, *,
                   mode: str = CONSERVATIVE, triangle_ids: bool = False) -> Voxels:
    """Jittable voxelization with static capacities; usable inside a user's `jax.jit`.

    Never resizes: what does not fit is dropped and flagged in ``Voxels.overflow``
    (``OVERFLOW_*`` bits). Get capacities that fit from `voxel_capacities`, or use the
    host-side `voxelize`, which sizes them and never returns a truncated result.
    Input validation (NaN vertices, face indices) is the caller's job here: non-finite
    triangles are skipped, out-of-range indices are clamped by JAX's gather.

    Args:
      mesh: `Mesh` with F faces.
      grid: `Grid`; the whole grid is one region (Morton keys take two words above 1024^3).
      capacities: `Capacities` (static).
      mode: "conservative" or "6-separating" (static).
      triangle_ids: also return the closest triangle id per voxel (static).

    Returns:
      `Voxels` with capacity ``capacities.voxels``.
    """
    six_sep = _check_mode(mode) == SIX_SEPARATING
    tris = grid.to_grid_units(mesh.triangles())
    coords, triangle, count, overflow, _ = _region_pipeline(
        tris, jnp.zeros(3, jnp.int32), grid.resolution, six_sep, Capacities(*capacities), triangle_ids)
    return Voxels(coords, count, overflow, triangle, grid, mode)


# ------------------------------------------------------------------ host-side API


def _bucket(n: int, minimum: int = 256) -> int:
    """Rounds up to 4, 5, 6 or 7 times a power of two (at most 25% slack, few shapes)."""
    n = max(int(n), minimum)
    shift = max(n.bit_length() - 3, 0)
    return -(-n >> shift) << shift


@functools.partial(jax.jit, static_argnames=("region_size", "six_sep", "caps", "stage", "with_ids"))
def _staged(tris, region_lo, *, region_size, six_sep, caps, stage, with_ids=False):
    """One host-side pass: "columns"/"rows" count work, "voxels" runs everything."""
    region_hi = region_lo + region_size - 1
    tables = _setup(tris, region_lo, region_hi, six_sep)
    if stage == "columns":
        return jnp.sum(tables.n_cols)
    columns = _columns(tables, caps.columns)
    if stage == "rows":
        return jnp.sum(columns[3])
    return _region_pipeline(tris, region_lo, region_size, six_sep, caps, with_ids)


def _voxelize_region(tris, region_lo, region_size, six_sep, with_ids, depth):
    """Counts work, sizes capacities, voxelizes one region; retries on overflow."""
    kw = dict(region_size=region_size, six_sep=six_sep)
    n_cols = int(_staged(tris, region_lo, caps=None, stage="columns", **kw))
    caps = Capacities(_bucket(n_cols), 0, depth, 0, 0)
    n_rows = int(_staged(tris, region_lo, caps=caps, stage="rows", **kw))
    caps = caps._replace(rows=_bucket(n_rows))
    caps = caps._replace(candidates=_bucket(caps.rows * 2), voxels=_bucket(caps.rows * 2))
    for _ in range(4):
        coords, triangle, count, overflow, sizes = _staged(
            tris, region_lo, caps=caps, stage="voxels", with_ids=with_ids, **kw)
        if not int(overflow):
            return coords, triangle, int(count), caps
        _, _, n_cand, max_depth = (int(s) for s in sizes)
        caps = caps._replace(depth=max(caps.depth, max_depth),
                             candidates=_bucket(max(caps.candidates, n_cand)),
                             voxels=_bucket(max(caps.voxels, n_cand)))
    raise JaxvoxError(f"voxelization kept overflowing (flags {int(overflow)}) with capacities {caps}")


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
    order = np.argsort(np.asarray(jax.device_get(morton.encode_word(jnp.asarray(cells, jnp.int32)))), kind="stable")
    out = []
    for c in cells[order]:
        hit = inside & (lo <= c).all(1) & (hi >= c).all(1)
        out.append(((c * region_size).astype(np.int32), np.flatnonzero(hit)))
    return out


@jax.jit
def _grid_triangles(mesh: Mesh, grid: Grid):
    return grid.to_grid_units(mesh.triangles())


def voxelize(mesh: Mesh, grid: Grid, *, mode: str = CONSERVATIVE, triangle_ids: bool = False,
             region_size: int = REGION_SIZE, progress: bool | None = None) -> Voxels:
    """Voxelizes a triangle mesh exactly; capacities are sized by counting passes.

    Grids above `region_size`^3 are streamed: the grid is cut into aligned cubic
    regions, visited in Morton order, each voxelized from the triangles whose bounding
    boxes touch it, so memory follows the surface inside one region at a time and the
    concatenated result is already in Morton order.

    Args:
      mesh: the `Mesh` (validated: NaN/inf vertices or bad face indices raise).
      grid: the `Grid`; geometry outside it is clipped.
      mode: "conservative" (every voxel whose closed box touches the closed triangle)
        or "6-separating" (Schwarz & Seidel's thin, 6-separating subset).
      triangle_ids: also record, per voxel, the id of the closest triangle to its
        centre among those that set it (ties to the lower id).
      region_size: edge of the streaming regions, a power of two <= 1024.
      progress: show a progress bar over regions (default: when on a terminal).

    Returns:
      `Voxels` with ``overflow == 0``, capacity rounded up to a few buckets.

    Raises:
      JaxvoxError: bad mode, resolution, region size or mesh.
    """
    six_sep = _check_mode(mode) == SIX_SEPARATING
    validate_mesh(mesh)
    if region_size & (region_size - 1) or not 1 <= region_size <= REGION_SIZE:
        raise JaxvoxError(f"region_size must be a power of two <= {REGION_SIZE}, got {region_size}")
    region_size = min(region_size, grid.resolution)
    depth = 3 if six_sep else 4
    tris = _grid_triangles(mesh, grid)
    parts, tri_parts = [], []
    regions = _regions(np.asarray(tris), grid.resolution, region_size) if mesh.num_faces else []
    from tqdm.auto import tqdm
    disable = (len(regions) < 2) if progress is None else not progress
    for region_lo, idx in tqdm(regions, desc="regions", disable=disable, leave=False):
        if not len(idx):
            continue
        padded = np.concatenate([idx, np.full(_bucket(len(idx), 64) - len(idx), idx[0])])
        coords, triangle, count, caps = _voxelize_region(
            tris[jnp.asarray(padded)], jnp.asarray(region_lo), region_size, six_sep, triangle_ids, depth)
        depth = caps.depth
        parts.append(coords[:count])
        if triangle_ids:
            tri_parts.append(jnp.asarray(padded)[triangle[:count]])
    total = sum(int(p.shape[0]) for p in parts)
    cap = _bucket(total, 1)
    coords = jnp.full((cap, 3), UNUSED, jnp.int32)
    triangle = jnp.full((cap,), UNUSED, jnp.int32) if triangle_ids else None
    if parts:
        coords = coords.at[:total].set(jnp.concatenate(parts))
        if triangle_ids:
            triangle = triangle.at[:total].set(jnp.concatenate(tri_parts))
    return Voxels(coords, jnp.int32(total), jnp.int32(0), triangle, grid, mode)


def voxel_capacities(mesh: Mesh, grid: Grid, *, mode: str = CONSERVATIVE) -> Capacities:
    """Capacities that fit `voxelize_fixed` for this mesh and grid (host-side counting).

    Rounded up to a few buckets so that similar inputs share a compiled function.
    """
    six_sep = _check_mode(mode) == SIX_SEPARATING
    validate_mesh(mesh)
    tris = _grid_triangles(mesh, grid)
    size = grid.resolution
    if mesh.num_faces == 0:
        return Capacities(256, 256, 3 if six_sep else 4, 256, 256)
    _, _, count, caps = _voxelize_region(tris, jnp.zeros(3, jnp.int32), size, six_sep, False, 3 if six_sep else 4)
    return caps._replace(voxels=_bucket(count))
