"""Independent float64 numpy reference voxelizer, used only by the tests.

Nothing here imports ``jaxvox``: the point is to check it against a second, simple
implementation written straight from the definitions.

Everything is done in *grid units*: a vertex ``v`` (float32, world units) maps to
``p = (float64(v) - float64(origin)) / float64(voxel_size)``, and voxel ``(i, j, k)``,
``0 <= i, j, k < R``, is the closed box ``[i, i+1] x [j, j+1] x [k, k+1]``. Geometry outside
the grid is clipped: only voxels inside ``[0, R)^3`` exist.

Modes
-----
``"conservative"``
    A voxel is set iff its closed box meets the closed triangle. Decided with the 13-axis
    separating-axis test (3 box axes, the triangle normal, the 9 products ``edge x box axis``);
    touching counts. Axes that are exactly zero are skipped, which makes the same test exact
    for zero-area triangles: a segment gets the box axes and ``edge x box axis``; a single
    point gets the box axes only (so a point on a voxel corner sets up to 8 voxels).

``"6-separating"`` (Schwarz & Seidel 2010)
    With ``n`` the triangle normal and ``d = argmax |n|`` (ties go to the lowest axis), a voxel
    with centre ``c`` is set iff

    (a) the plane of the triangle meets the closed segment ``c - e_d/2 .. c + e_d/2``
        (plane values of opposite sign or zero at its two ends: a plane lying exactly on a
        voxel face sets the voxels on both sides);
    (b) in each of the three axis-aligned projections (drop x, drop y, drop z) the projected
        triangle meets the voxel's inscribed diamond ``|a - ca| + |b - cb| <= 1/2`` (closed,
        exact 2D convex overlap by the separating-axis test with the projected edge normals
        and the diamond normals ``(1, 1)``, ``(1, -1)``; zero edge normals are skipped, so
        projections that collapse to a segment or a point are handled exactly);
    (c) the voxel's closed box meets the triangle's axis-aligned bounding box.

    Zero-area triangles (float64 cross product exactly zero) set no voxel in this mode: they
    bound no area. (If their float32 input vertices are pairwise distinct, float32 arithmetic
    may see a sliver instead, so the voxels their segment touches are reported as near-ties;
    see :func:`reference_voxelize`.)

Every decision is taken with *unnormalised* axes, so for vertices on a coarse dyadic lattice
(e.g. multiples of 1/8 voxel, small coordinates, origin 0, voxel size 1) all arithmetic is
exact in float64 and "touching" is decided exactly.

Margins and tolerance
---------------------
Besides the set, the reference returns for each candidate voxel a signed *margin* in voxel
units, ``>= 0`` iff the voxel is set: roughly how far the geometry must move to flip the
decision.

* conservative: ``-max`` over the (valid) SAT axes of the separation gap measured along the
  unit axis;
* 6-separating: the minimum of (a) the distance of the nearer segment end to the plane,
  measured perpendicular to the plane, (b) ``-max`` gap over the 2D SAT axes of the three
  projections, (c) the box/bounding-box overlap. Where the dominant axis is nearly tied and
  the other choice would decide the voxel differently, the margin is also limited by
  ``(|n_d| - |n_d'|) / |n| * L`` (``L`` the longest edge), the size of the vertex motion that
  would swap the dominant axis.

A triangle's tolerance (see :func:`triangle_tolerance`) is

    ``tol = TOL_BASE * (1 + L) * cond``,  ``TOL_BASE = 1e-4`` voxel,

with ``L`` the longest edge in voxels and ``cond = L / h_min = L^2 / (2 * area)`` (at least 1),
the shape factor: it is about 1 to 3 for well-shaped triangles and grows for slivers, whose
normal (hence plane, dominant axis, and the normal SAT axis) is ill-conditioned. For
zero-area triangles in conservative mode the normal axis is not used and ``cond = 1``.
A mismatch with the implementation is *excused* only when ``|margin| <= tol`` for the
deciding triangle(s); the union over triangles is handled by taking, per voxel, the maximum
over triangles of ``margin / tol`` (``relative``): an implementation may differ from the
reference on a voxel only where ``|relative| <= 1``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "MODES",
    "TOL_BASE",
    "Reference",
    "morton_encode",
    "morton_order",
    "reference_voxelize",
    "to_grid_units",
    "triangle_tolerance",
    "winding_number",
    "closest_point_on_triangles",
    "mesh_distance",
    "ray_parity",
    "first_hit",
]

MODES = ("conservative", "6-separating")
TOL_BASE = 1e-4  # voxel units, per unit of (1 + triangle size in voxels) and shape factor
_TINY = 1e-300  # stands in for "-0" so that a margin's sign always equals the decision
_CHUNK = 1 << 16  # candidate (triangle, voxel) pairs evaluated per vectorised batch


# --------------------------------------------------------------------------------------------
# Morton order (x is the lowest bit of each triple)
# --------------------------------------------------------------------------------------------


def morton_encode(ijk) -> np.ndarray:
    """uint64 Morton codes of non-negative ``[N, 3]`` integer coordinates (< 2**21 each)."""
    ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
    if ijk.size and (ijk.min() < 0 or ijk.max() >= 1 << 21):
        raise ValueError("Morton coordinates must lie in [0, 2**21)")
    u = ijk.astype(np.uint64)
    code = np.zeros(len(u), dtype=np.uint64)
    one = np.uint64(1)
    for b in range(21):
        for axis in range(3):
            bit = (u[:, axis] >> np.uint64(b)) & one
            code |= bit << np.uint64(3 * b + axis)
    return code


def morton_order(ijk) -> np.ndarray:
    """``ijk`` (``[N, 3]``) as int32, sorted by Morton code."""
    ijk = np.asarray(ijk).reshape(-1, 3)
    order = np.argsort(morton_encode(ijk), kind="stable")
    return np.ascontiguousarray(ijk[order].astype(np.int32))


# --------------------------------------------------------------------------------------------
# Result
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Reference:
    """Reference voxelization plus per-voxel margins.

    ``keys``/``margin``/``relative`` cover every candidate voxel examined (the set voxels and
    their near misses), keyed by the linear index ``(i * R + j) * R + k``, sorted ascending.
    """

    voxels: np.ndarray  # [N, 3] int32, set voxels, unique, Morton order
    keys: np.ndarray  # [M] int64, linear keys of all candidate voxels, ascending
    margin: np.ndarray  # [M] float64, max over triangles of the signed margin (voxels)
    relative: np.ndarray  # [M] float64, max over triangles of margin / tol(triangle)
    resolution: int

    def linear(self, ijk) -> np.ndarray:
        ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
        r = self.resolution
        return (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2]

    def lookup(self, ijk) -> tuple[np.ndarray, np.ndarray]:
        """(margin, relative) of voxels ``ijk``; ``-inf`` for voxels never examined."""
        q = self.linear(ijk)
        pos = np.searchsorted(self.keys, q)
        pos_c = np.minimum(pos, max(len(self.keys) - 1, 0))
        hit = (pos < len(self.keys)) & (self.keys[pos_c] == q) if len(self.keys) else np.zeros(len(q), bool)
        margin = np.full(len(q), -np.inf)
        relative = np.full(len(q), -np.inf)
        margin[hit] = self.margin[pos_c[hit]]
        relative[hit] = self.relative[pos_c[hit]]
        return margin, relative


# --------------------------------------------------------------------------------------------
# Per-triangle quantities
# --------------------------------------------------------------------------------------------


def to_grid_units(vertices, origin, voxel_size) -> np.ndarray:
    """``(float64(v) - float64(origin)) / float64(voxel_size)``."""
    v = np.asarray(vertices, dtype=np.float32).astype(np.float64)
    o = np.asarray(origin, dtype=np.float32).astype(np.float64).reshape(1, 3)
    h = np.float64(np.asarray(voxel_size, dtype=np.float32))
    return (v - o) / h


def _edges(P):
    return np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 1], P[:, 0] - P[:, 2]], axis=1)  # [T,3,3]


def _normal(P):
    return np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])  # [T,3]


def triangle_tolerance(P, mode: str) -> np.ndarray:
    """Per-triangle tolerance in voxels for grid-unit triangles ``P`` (``[T, 3, 3]``)."""
    P = np.asarray(P, dtype=np.float64)
    E = _edges(P)
    L = np.sqrt((E**2).sum(-1)).max(-1)
    twice_area = np.sqrt((_normal(P) ** 2).sum(-1))
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.where(twice_area > 0, L * L / np.where(twice_area > 0, twice_area, 1.0), 1.0)
    cond = np.maximum(cond, 1.0)
    return TOL_BASE * (1.0 + L) * cond


def _sat_gaps(c, t, axes, valid, tmin, tmax, rad):
    """Separation gaps along unnormalised axes, normalised afterwards. Shapes [m, A]."""
    A = axes[t]  # [m, A, 3]
    ca = np.einsum("mk,mak->ma", c, A)
    r = rad[t]
    gap = np.maximum(tmin[t] - (ca + r), (ca - r) - tmax[t])  # exact sign on dyadic inputs
    norm = np.sqrt((A**2).sum(-1))
    with np.errstate(divide="ignore", invalid="ignore"):
        gap = np.where(valid[t], gap / np.where(norm > 0, norm, 1.0), -np.inf)
    return gap


def _conservative_setup(P):
    T = len(P)
    E = _edges(P)
    n = _normal(P)
    eye = np.eye(3)
    cross = np.cross(E[:, :, None, :], eye[None, None, :, :]).reshape(T, 9, 3)
    axes = np.concatenate([np.broadcast_to(eye, (T, 3, 3)), n[:, None, :], cross], axis=1)  # [T,13,3]
    valid = np.any(axes != 0, axis=-1)
    proj = np.einsum("tvk,tak->tva", P, axes)
    rad = 0.5 * np.abs(axes).sum(-1)  # box support: half the L1 norm of the axis
    return dict(axes=axes, valid=valid, tmin=proj.min(1), tmax=proj.max(1), rad=rad)


def _separating_setup(P):
    T = len(P)
    E = _edges(P)
    n = _normal(P)
    axes = []
    for drop in range(3):
        b, c = [k for k in range(3) if k != drop]
        ax = np.zeros((T, 5, 3))
        ax[:, :3, b] = -E[:, :, c]  # projected edge normals
        ax[:, :3, c] = E[:, :, b]
        ax[:, 3, b], ax[:, 3, c] = 1.0, 1.0  # diamond normals
        ax[:, 4, b], ax[:, 4, c] = 1.0, -1.0
        axes.append(ax)
    axes = np.concatenate(axes, axis=1)  # [T,15,3], zero in the dropped component
    valid = np.any(axes != 0, axis=-1)
    proj = np.einsum("tvk,tak->tva", P, axes)
    rad = 0.5 * np.abs(axes).max(-1)  # diamond support: half the max norm of the 2D axis
    an = np.abs(n)
    # dominant axis, ties to the lowest index; and the runner-up (for the near-tie margin)
    d = np.argmax(an, axis=1)
    an_masked = an.copy()
    an_masked[np.arange(T), d] = -1.0
    d2 = np.argmax(an_masked, axis=1)
    nnorm = np.sqrt((n**2).sum(-1))
    E_len = np.sqrt((E**2).sum(-1)).max(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        tie = np.where(nnorm > 0, (an[np.arange(T), d] - an[np.arange(T), d2]) / np.where(nnorm > 0, nnorm, 1.0), 0.0)
    return dict(
        axes=axes,
        valid=valid,
        tmin=proj.min(1),
        tmax=proj.max(1),
        rad=rad,
        n=n,
        nnorm=nnorm,
        d=d,
        d2=d2,
        tie=tie * E_len,
        bmin=P.min(1),
        bmax=P.max(1),
        v0=P[:, 0],
    )


def _plane_margin(c, t, S, d):
    """Margin of condition (a) for the centre segment along axis ``d[m]``."""
    n = S["n"][t]
    m = len(t)
    half = np.zeros((m, 3))
    half[np.arange(m), d] = 0.5
    v0 = S["v0"][t]
    f_lo = ((c - half - v0) * n).sum(-1)
    f_hi = ((c + half - v0) * n).sum(-1)
    s = np.sign(n[np.arange(m), d])
    return np.minimum(-s * f_lo, s * f_hi) / S["nnorm"][t]


def _eval_chunk(mode, S, t, cell, R):
    c = cell + 0.5
    if mode == "conservative":
        gap = _sat_gaps(c, t, S["axes"], S["valid"], S["tmin"], S["tmax"], S["rad"])
        return -gap.max(1)
    gap = _sat_gaps(c, t, S["axes"], S["valid"], S["tmin"], S["tmax"], S["rad"])
    m_b = -gap.max(1)
    m_c = np.minimum(cell + 1.0 - S["bmin"][t], S["bmax"][t] - cell).min(1)
    m_bc = np.minimum(m_b, m_c)
    margin = np.minimum(_plane_margin(c, t, S, S["d"][t]), m_bc)
    alt = np.minimum(_plane_margin(c, t, S, S["d2"][t]), m_bc)
    is_set = margin >= 0
    flip = is_set != (alt >= 0)
    tie = S["tie"][t]
    margin = np.where(flip, np.where(is_set, np.minimum(margin, tie), np.maximum(margin, -tie)), margin)
    # keep the sign equal to the decision (an exact tie gives tie == 0)
    return np.where(is_set, margin, np.minimum(margin, -_TINY))


# --------------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------------


def _evaluate(P, tol, mode, R):
    """Unreduced (key, margin, relative) for every candidate (triangle, voxel) pair."""
    # Candidate cells: closed bounding-box cells, widened by the tolerance (at most one cell)
    # so that near misses get a margin too; clipped to the grid.
    widen = np.minimum(tol, 1.0)[:, None]
    with np.errstate(invalid="ignore"):
        lo = np.ceil(P.min(1) - widen) - 1
        hi = np.floor(P.max(1) + widen)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, R - 1)
    inside = np.all(lo <= hi, axis=1) & np.all(np.isfinite(P), axis=(1, 2))
    P, tol, lo, hi = P[inside], tol[inside], lo[inside].astype(np.int64), hi[inside].astype(np.int64)

    setup = _conservative_setup if mode == "conservative" else _separating_setup
    S = setup(P) if len(P) else None
    ext = hi - lo + 1
    counts = ext.prod(1)
    starts = np.concatenate([[0], np.cumsum(counts)])
    total = int(starts[-1])

    keys, margins, rels = [np.zeros(0, np.int64)], [np.zeros(0)], [np.zeros(0)]
    for s0 in range(0, total, _CHUNK):
        q = np.arange(s0, min(s0 + _CHUNK, total), dtype=np.int64)
        t = np.searchsorted(starts, q, side="right") - 1
        local = q - starts[t]
        e = ext[t]
        k = local % e[:, 2]
        j = (local // e[:, 2]) % e[:, 1]
        i = local // (e[:, 2] * e[:, 1])
        cell = lo[t] + np.stack([i, j, k], axis=1)
        margin = _eval_chunk(mode, S, t, cell.astype(np.float64), R)
        keys.append((cell[:, 0] * R + cell[:, 1]) * R + cell[:, 2])
        margins.append(margin)
        rels.append(margin / tol[t])
    return np.concatenate(keys), np.concatenate(margins), np.concatenate(rels)


def reference_voxelize(vertices, faces, origin, voxel_size, resolution: int, mode: str = "conservative") -> Reference:
    """Voxelize a triangle mesh with the float64 reference (see the module docstring).

    In 6-separating mode, a zero-area triangle sets nothing. If its three float32 input
    vertices are pairwise distinct (collinear only after the conversion to grid units, which
    float32 arithmetic may not reproduce) the voxels its segment touches in conservative
    mode are reported as near-ties (margin ``-0``) so that an implementation that sees a
    sliver there is excused; a triangle with a repeated input vertex has zero area in any
    arithmetic and gets no such excuse.
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    R = int(resolution)
    p = to_grid_units(vertices, origin, voxel_size)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    P = p[faces]  # [T,3,3]
    tol = triangle_tolerance(P, mode)
    assert P.shape == (len(faces), 3, 3) and P.dtype == np.float64
    assert np.all(tol[np.isfinite(P).all(axis=(1, 2))] > 0), "every finite triangle needs a positive tolerance"
    parts = []
    if mode == "6-separating":
        flat = ~np.any(_normal(P) != 0, axis=-1)  # zero-area triangles set nothing
        v32 = np.asarray(vertices, dtype=np.float32)[faces]
        distinct = ~(
            np.all(v32[:, 0] == v32[:, 1], -1) | np.all(v32[:, 1] == v32[:, 2], -1) | np.all(v32[:, 2] == v32[:, 0], -1)
        )
        ambiguous = flat & distinct
        if ambiguous.any():
            Pa = P[ambiguous]
            key, margin, rel = _evaluate(Pa, triangle_tolerance(Pa, "conservative"), "conservative", R)
            parts.append((key, np.minimum(margin, -_TINY), np.minimum(rel, -_TINY)))
        P, tol = P[~flat], tol[~flat]
    parts.append(_evaluate(P, tol, mode, R))

    key = np.concatenate([k for k, _, _ in parts])
    margin = np.concatenate([m for _, m, _ in parts])
    rel = np.concatenate([r for _, _, r in parts])
    if len(key):
        order = np.argsort(key, kind="stable")
        key, margin, rel = key[order], margin[order], rel[order]
        idx = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
        key = key[idx]
        margin = np.maximum.reduceat(margin, idx)
        rel = np.maximum.reduceat(rel, idx)

    assert not np.isnan(margin).any(), "every examined voxel must get a decided margin"
    assert len(key) == 0 or (key[0] >= 0 and key[-1] < R**3), "candidates must lie inside the grid"
    set_keys = key[margin >= 0]
    ijk = np.stack([set_keys // (R * R), (set_keys // R) % R, set_keys % R], axis=1)
    return Reference(voxels=morton_order(ijk), keys=key, margin=margin, relative=rel, resolution=R)


def winding_number(vertices, faces, points) -> np.ndarray:
    """Generalized winding number of a triangle mesh at each point (float64).

    Sum of the signed solid angles of the triangles seen from the point, over 4 pi
    (Van Oosterom & Strackee). About +-1 inside a closed, consistently oriented
    surface, 0 outside; independent of vertex welding.

    Args:
      vertices: float [V, 3].
      faces: int [F, 3].
      points: float [P, 3].

    Returns:
      float64 [P].
    """
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]  # [F, 3, 3]
    points = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.empty(len(points))
    block = max(1, (1 << 17) // max(len(tri), 1))  # points per block: [block, F] temporaries of 1 MiB, in the cache
    corner = [[tri[None, :, k, axis] for axis in range(3)] for k in range(3)]  # [1, F] per axis
    dot = lambda x, y: x[0] * y[0] + x[1] * y[1] + x[2] * y[2]
    zero_area = (np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) == 0).all(-1)  # [F]
    for start in range(0, len(points), block):
        p = points[start : start + block]
        a, b, c = ([corner[k][axis] - p[:, axis, None] for axis in range(3)] for k in range(3))  # [B, F] each
        la, lb, lc = (np.sqrt(dot(x, x)) for x in (a, b, c))
        cross = (b[1] * c[2] - b[2] * c[1], b[2] * c[0] - b[0] * c[2], b[0] * c[1] - b[1] * c[0])
        den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb
        angle = np.arctan2(dot(a, cross), den)
        # A triangle of zero area has no solid angle, also from a point on it (where the
        # formula reads atan2(0, den <= 0)): the library's convention.
        angle[:, zero_area] = 0.0
        out[start : start + block] = angle.sum(-1) / (2 * np.pi)
    return out


# --------------------------------------------------------------------------------------------
# Distances and inside tests (float64)
# --------------------------------------------------------------------------------------------


def closest_point_on_triangles(p, a, b, c) -> np.ndarray:
    """Closest points on triangles (a, b, c) to points p, all float64 ``[N, 3]`` (broadcast).

    The nearest of four candidates: the closest point of each edge (as a segment) and the
    projection onto the plane when it falls inside the triangle (same side of all three
    edges, by the normal). A degenerate triangle has a zero normal, so only its edges count:
    the right answer for a segment or a point.
    """
    p, a, b, c = np.broadcast_arrays(*(np.asarray(x, np.float64) for x in (p, a, b, c)))
    dot = lambda x, y: np.einsum("...k,...k->...", x, y)

    def on_segment(x0, x1):
        e = x1 - x0
        ee = dot(e, e)
        s = np.clip(dot(p - x0, e) / np.where(ee > 0, ee, 1.0), 0.0, 1.0)
        return x0 + s[..., None] * e

    n = np.cross(b - a, c - a)
    nn = dot(n, n)
    proj = p - (dot(p - a, n) / np.where(nn > 0, nn, 1.0))[..., None] * n
    inside = nn > 0
    for x0, x1 in ((a, b), (b, c), (c, a)):
        inside &= dot(np.cross(x1 - x0, proj - x0), n) >= 0
    candidates = [on_segment(a, b), on_segment(b, c), on_segment(c, a)]
    best = candidates[0]
    for q in candidates[1:]:
        best = np.where((dot(q - p, q - p) < dot(best - p, best - p))[..., None], q, best)
    return np.where(inside[..., None], proj, best)


def mesh_distance(vertices, faces, points, chunk: int = 1 << 14) -> np.ndarray:
    """Unsigned distance (float64 ``[P]``) from points ``[P, 3]`` to a triangle mesh, brute force.

    ``+inf`` for a mesh without faces. Only (point, triangle) pairs that can hold the
    minimum are evaluated exactly: the distance to the nearest vertex bounds the result
    from above, and a triangle whose bounding box lies farther than that cannot be closest
    (`chunk` points at a time).
    """
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64).reshape(-1, 3)]
    points = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.full(len(points), np.inf)
    if len(tri) == 0:
        return out
    lo, hi = tri.min(1), tri.max(1)  # [F, 3]
    corners = cKDTree(np.asarray(vertices, np.float64)[np.unique(np.asarray(faces, np.int64))])
    # The triangles whose box can lie within the nearest corner's distance: the box
    # centres within that distance plus the largest box half-diagonal (a k-d tree), then
    # the exact box test.
    centres = cKDTree((lo + hi) / 2)
    reach = np.sqrt(((hi - lo) ** 2).sum(-1)).max() / 2
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk]
        vertex2 = corners.query(p)[0] ** 2  # the nearest triangle corner (float64)
        near = centres.query_ball_point(p, np.sqrt(vertex2) * (1 + 1e-9) + reach * (1 + 1e-9) + 1e-300)
        i = np.repeat(np.arange(len(p)), [len(x) for x in near])
        f = np.concatenate([np.asarray(x, np.int64) for x in near]) if len(p) else np.zeros(0, np.int64)
        box2 = sum(np.maximum(np.maximum(lo[f, k] - p[i, k], p[i, k] - hi[f, k]), 0) ** 2 for k in range(3))
        keep = box2 <= vertex2[i] * (1 + 1e-9)
        i, f = i[keep], f[keep]
        q = closest_point_on_triangles(p[i], tri[f, 0], tri[f, 1], tri[f, 2])
        d2 = np.full(len(p), np.inf)
        np.minimum.at(d2, i, ((q - p[i]) ** 2).sum(-1))
        out[s : s + chunk] = np.sqrt(d2)
    return out


def ray_parity(vertices, faces, points, direction=(0.5773, 0.5774, 0.5775)) -> np.ndarray:
    """Inside test by ray parity (float64 ``[P]`` bool): odd number of crossings of the ray
    ``point + t * direction``, ``t > 0``, with the triangles (Moller-Trumbore, no culling).

    Right for watertight meshes; the default direction is generic, so that rays through
    edges or vertices are unlikely.
    """
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64).reshape(-1, 3)]
    d = np.asarray(direction, np.float64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(d, e2)
    det = np.einsum("fk,fk->f", e1, h)
    ok = np.abs(det) > 1e-300
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    out = np.empty(len(points), bool)
    for n, p in enumerate(np.asarray(points, np.float64)):
        s = p - tri[:, 0]
        u = np.einsum("fk,fk->f", s, h) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("fk,fk->f", e2, q) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        out[n] = hit.sum() % 2 == 1
    return out


def first_hit(vertices, faces, origins, directions) -> np.ndarray:
    """Ray parameter of the nearest triangle hit, ``t >= 0`` (float64 ``[P]``, inf on a miss),
    for unit directions (Moller-Trumbore, no culling)."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64).reshape(-1, 3)]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    out = np.full(len(origins), np.inf)
    for n, (o, d) in enumerate(zip(np.asarray(origins, np.float64), np.asarray(directions, np.float64))):
        d = d / np.linalg.norm(d)
        h = np.cross(d, e2)
        det = np.einsum("fk,fk->f", e1, h)
        ok = np.abs(det) > 1e-300
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o - tri[:, 0]
        u = np.einsum("fk,fk->f", s, h) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("fk,fk->f", e2, q) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0)
        if hit.any():
            out[n] = t[hit].min()
    return out
