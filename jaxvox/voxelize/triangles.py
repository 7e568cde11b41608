"""Per-triangle setup (half-planes, column / row / depth intervals) and the expansion of
triangles into columns, rows and candidate voxels (see `jaxvox.voxelize` for the method)."""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxvox import morton
from jaxvox._core.geometry import point_triangle_dist2
from jaxvox._core.shapes import expand_counts

_TOL = 2.0**-19  # relative half-plane widening, see the docstring of `jaxvox.voxelize`
_BIG = float(1 << 30)  # clamp for interval bounds before integer conversion
_FLAT = 2.0**-60  # a half-plane's coefficient this small beside its others is taken as zero (`_linear_bounds`)


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


def _half_planes(qa, qb, six_sep, tol):
    """Edge (and diamond) half-planes of one 2D projection of a triangle.

    The edge normals point inwards by the projected triangle's orientation, taken from
    the same float32 edges: the pair of consecutive edges whose 2D cross product is
    largest in magnitude among those whose sign is certain (beyond their products'
    rounding). The 3D normal's
    component can round to zero or to the other sign where the projection is a sliver
    (a corner's tiny offset lost beside a large one), which would turn the short edge's
    half-plane outwards.

    Args:
      qa, qb: [3] float32 projected corner coordinates (local grid units).
      six_sep: static bool, diamond constants instead of box-corner constants.
      tol: widening distance in voxels.

    Returns:
      [3, H] float32 rows (alpha, beta, gamma): a voxel with 2D corner (a, b) passes
      when ``alpha * a + beta * b + gamma >= 0`` for all H half-planes (H = 3 edges,
      plus 4 diamond axes in 6-separating mode).
    """
    ea = jnp.roll(qa, -1) - qa
    eb = jnp.roll(qb, -1) - qb
    first, second = ea * jnp.roll(eb, -1), eb * jnp.roll(ea, -1)
    cross = first - second  # [3] 2D cross of consecutive edges
    # A cross below its products' rounding has no certain sign: XLA may contract one
    # product into the difference (a fused multiply-add) and leave the other's rounding,
    # which outweighed a sliver's true cross (a corner 1e-10 off a long edge, found by
    # hypothesis). Such crosses are passed over while another has a certain sign.
    certain = jnp.abs(cross) > 2.0**-22 * (jnp.abs(first) + jnp.abs(second))
    score = jnp.where(certain.any(), jnp.where(certain, jnp.abs(cross), -1.0), jnp.abs(cross))
    sigma = jnp.where(cross[jnp.argmax(score)] >= 0, 1.0, -1.0)
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
        rows.append(
            jnp.stack(
                [
                    jnp.array([-1.0, 1.0, -1.0, 1.0], jnp.float32),
                    jnp.array([-1.0, 1.0, 1.0, -1.0], jnp.float32),
                    jnp.stack([s.max() - 0.5, 1.5 - s.min(), t.max() + 0.5, 0.5 - t.min()]) + tol,
                ]
            )
        )
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

    A half-plane whose `free` is zero, or below `_FLAT` times ``|other| + |gamma|``, bounds
    s alone. Dividing by such a `free` could overflow to an infinite bound whose slope
    times s = 0 is NaN, which drops the whole column (a corner at x = 1.2e-38 did).
    Its t term, at most ``|free| * _BIG`` for every t a bound is clamped to, goes into
    the constant instead: a wider half-plane, so the voxels stay conservative.

    Returns:
      ([4, H] bounds on t linear in s: lower_p, lower_q, upper_p, upper_q, all finite),
      and ([2, H] constraints ``coef * s + rest >= 0`` on s alone from the flat
      half-planes; the others become the neutral ``0 * s + 1``).
    """
    flat = jnp.abs(free) <= _FLAT * (jnp.abs(other) + jnp.abs(gamma))
    safe = jnp.where(flat, 1.0, free)
    p, q = -gamma / safe, -other / safe
    lower, upper = (free > 0) & ~flat, (free < 0) & ~flat
    bounds = jnp.stack(
        [jnp.where(lower, p, -_BIG), jnp.where(lower, q, 0.0), jnp.where(upper, p, _BIG), jnp.where(upper, q, 0.0)]
    )
    rest = gamma + jnp.abs(free) * _BIG
    return bounds, jnp.stack([jnp.where(flat, other, 0.0), jnp.where(flat, rest, 1.0)])


def _setup_triangle(p, region_lo, region_hi, six_sep):
    """Per-triangle constants of one triangle (vmapped by `setup_triangles`).

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
    qp, npl = q[:, perm], normal[perm]
    lo_i = (box_lo - base)[perm]
    hi_i = (box_hi - base)[perm]
    dom = _half_planes(qp[:, 0], qp[:, 1], six_sep, tol)  # (u, v): alpha u + beta v
    vw = _half_planes(qp[:, 1], qp[:, 2], six_sep, tol)  # (v, w): alpha v + beta w
    wu = _half_planes(qp[:, 2], qp[:, 0], six_sep, tol)  # (w, u): alpha w + beta u
    v_of_u, u_only_a = _linear_bounds(dom[1], dom[0], dom[2])
    w_of_v, v_only = _linear_bounds(vw[1], vw[0], vw[2])
    w_of_u, u_only_b = _linear_bounds(wu[0], wu[1], wu[2])
    u_lo, u_hi = _interval(
        jnp.concatenate([u_only_a[0], u_only_b[0]]), jnp.concatenate([u_only_a[1], u_only_b[1]]), lo_i[0], hi_i[0]
    )
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
    col_data = jnp.concatenate(
        [v_of_u.reshape(-1), w_of_u.reshape(-1), jnp.stack([v_lo, v_hi, lo_i[2], hi_i[2], z_lo, z_hi, kx])]
    )
    row_data = jnp.concatenate([w_of_v.reshape(-1), ky[None]])
    place = jnp.concatenate([base.astype(jnp.int32), perm.astype(jnp.int32)])
    return n_cols, u_lo.astype(jnp.int32), col_data, row_data, place


def setup_triangles(tris, region_lo, region_hi, six_sep) -> _Triangles:
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


NARROW = 1 << 12  # local coordinates below this need `_mul_add`'s two-part split only


def _mul_add(p, q, s, wide: bool):
    """``p + q * s`` for an integer-valued float32 `s`, rounded alike wherever it is
    computed: ``|s| < NARROW`` (`wide` False: every region of the host path), or
    ``|s| < 2^16`` (`wide`: a triangle's local coordinates in a grid up to 65536^3).

    XLA recomputes cheap elementwise values inside each fusion that reads them, and
    the CPU backend may contract a multiply-add into one fused operation in some copies
    only. A bound at a tie would then round one way where a row's voxels are counted
    and the other where they are placed, shifting the row by a voxel. Split into parts
    of at most 12 (or 8) significant bits, `q` gives exact products, so every evaluation
    order rounds the same additions. An infinite `q` keeps its infinite part alone (its
    rest would be inf - inf).
    """
    mask = jnp.uint32(0xFFFF0000 if wide else 0xFFFFF000)  # the leading 8 (or 12) significant bits
    top = lambda x: jax.lax.bitcast_convert_type(jax.lax.bitcast_convert_type(x, jnp.uint32) & mask, jnp.float32)
    q1 = top(q)
    rest = jnp.where(jnp.isfinite(q), q - q1, 0.0)  # exact
    if not wide:
        return (p + q1 * s) + rest * s
    q2 = top(rest)
    return ((p + q1 * s) + q2 * s) + (rest - q2) * s


def _eval_bounds(bounds, s, lo, hi, wide: bool):
    """Intersects [lo, hi] with ``lower_p + lower_q s <= t <= upper_p + upper_q s``.

    Args:
      bounds: [..., 4H] float32 (lower_p, lower_q, upper_p, upper_q), H each.
      s: [...] float32; lo, hi: [...] float32 integer-valued.

    Returns:
      (lo, hi) [...] float32 integer-valued.
    """
    # Unrolled over the H half-planes: an elementwise loop, where a reduction over the
    # short last axis compiles to a slower reduction kernel on the CPU.
    h = bounds.shape[-1] // 4
    lower = [jnp.ceil(_mul_add(bounds[..., i], bounds[..., h + i], s, wide)) for i in range(h)]
    upper = [jnp.floor(_mul_add(bounds[..., 2 * h + i], bounds[..., 3 * h + i], s, wide)) for i in range(h)]
    return functools.reduce(jnp.maximum, lower, lo), functools.reduce(jnp.minimum, upper, hi)


def expand_columns(tris: _Triangles, col_cap: int, start=0, *, wide: bool = False) -> _Columns:
    """Expands triangles into columns (the window of `col_cap` columns from `start` on);
    per column, its rows and depth coefficients. `wide` (static): the region is wider
    than `NARROW` voxels (see `_mul_add`)."""
    tri, rank, valid, total = expand_counts(tris.n_cols, col_cap, start)
    cu = (tris.col_lo[tri] + rank).astype(jnp.float32)
    c = tris.col_data[tri]
    h4 = (c.shape[1] - 7) // 2
    v_lo, v_hi, w_lo, w_hi, z_lo, z_hi, kx = (c[:, 2 * h4 + i] for i in range(7))
    row_lo, row_hi = _eval_bounds(c[:, :h4], cu, v_lo, v_hi, wide)
    w_lo, w_hi = _eval_bounds(c[:, h4 : 2 * h4], cu, w_lo, w_hi, wide)
    n_rows = jnp.where(valid, jnp.maximum(row_hi - row_lo + 1.0, 0.0), 0.0).astype(jnp.int32)
    depth = jnp.stack([w_lo, w_hi, _mul_add(z_lo, kx, cu, wide), _mul_add(z_hi, kx, cu, wide)], 1)
    depth = jnp.concatenate([depth, tris.row_data[tri]], axis=1)
    place = tris.base[tri]
    u_step = cu.astype(jnp.int32)[:, None] * (jnp.arange(3, dtype=jnp.int32) == place[:, 3:4])
    origin = jnp.concatenate([place[:, :3] + u_step, place[:, 4:]], axis=1)
    return _Columns(tri, row_lo, n_rows, depth, origin, total)


class _Rows(NamedTuple):
    """Row work items (Rw slots): one (triangle, column, row) each."""

    place: jax.Array  # [Rw, 5] int32 global (i, j, k) of the row's first voxel, w axis, triangle
    n_depth: jax.Array  # [Rw] int32 voxels in the row (0 for invalid slots)
    total: jax.Array  # [] int32 number of row slots needed


def expand_rows(columns: _Columns, row_cap: int, chunk: int, start=0, *, wide: bool = False) -> _Rows:
    """Expands columns into rows; per row, the interval of depths that are set.

    Rows are handled `chunk` at a time (one gather of the column's coefficients per
    chunk), so `row_cap` counts slots of whole chunks; the window starts at chunk slot
    `start`. `wide` as in `expand_columns`.
    """
    n_chunks = (columns.n_rows + chunk - 1) // chunk
    col, rank, valid, total = expand_counts(n_chunks, row_cap // chunk, start)
    offset = rank[:, None] * chunk + jnp.arange(chunk, dtype=jnp.int32)  # [Rc, K]
    ok = valid[:, None] & (offset < columns.n_rows[col][:, None])
    v = columns.row_lo[col][:, None] + offset.astype(jnp.float32)
    c = columns.depth[col][:, None, :]
    ky = c[..., -1]
    lo = jnp.maximum(c[..., 0], jnp.ceil(_mul_add(c[..., 2], ky, v, wide) - 1.0))
    hi = jnp.minimum(c[..., 1], jnp.floor(_mul_add(c[..., 3], ky, v, wide)))
    lo, hi = _eval_bounds(c[..., 4:-1], v, lo, hi, wide)
    n_depth = jnp.where(ok, jnp.maximum(hi - lo + 1.0, 0.0), 0.0).astype(jnp.int32)
    o = columns.origin[col][:, None, :]
    axis = jnp.arange(3, dtype=jnp.int32)
    lo_i = jnp.where(ok, lo, 0.0).astype(jnp.int32)
    start = (
        o[..., :3] + v.astype(jnp.int32)[..., None] * (axis == o[..., 3:4]) + lo_i[..., None] * (axis == o[..., 4:5])
    )
    tri = jnp.broadcast_to(columns.tri[col][:, None, None], ok.shape + (1,))
    w_axis = jnp.broadcast_to(o[..., 4:5], tri.shape)
    place = jnp.concatenate([start, w_axis, tri], axis=-1)
    return _Rows(place.reshape(-1, 5), n_depth.reshape(-1), total * chunk)


def expand_candidates(tris_grid, rows: _Rows, cand_cap: int, words: int, with_ids: bool, start=0, ids=None):
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
    keys: tuple[jax.Array, ...]
    if words == 1:
        keys = (jnp.where(valid, morton.encode_word(ijk & morton.WORD_MASK), morton.EMPTY),)
    else:
        keys = tuple(jnp.where(valid, k, morton.EMPTY) for k in morton.encode(ijk))
    payload: tuple[jax.Array, ...] = ()
    if with_ids:
        tri = p[:, 4]
        corners = tris_grid[tri]
        dist2 = point_triangle_dist2(ijk.astype(jnp.float32) + 0.5, corners[:, 0], corners[:, 1], corners[:, 2])
        payload = (
            jax.lax.bitcast_convert_type(dist2, jnp.uint32),
            (tri if ids is None else ids[tri]).astype(jnp.uint32),
        )
    return keys, payload, total
