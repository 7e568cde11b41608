"""Geometry kernels shared by several modules (private module, public names).

Point-triangle squared distance (the voxelizer's closest-triangle ids, the distance
fields; `rows_dist2` from per-triangle rows computed once, for the sparse fields' many
points per triangle), the signed solid angle of a triangle (winding numbers, the brute-force sign
of the distance fields) and a NaN-safe vector norm (SDF scenes, sphere tracing). The
first two work on x, y, z components as separate arrays, so XLA fuses each into one
elementwise loop.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def point_triangle_dist2(p, a, b, c):
    """Squared distance from points p [..., 3] to triangles (a, b, c) [..., 3] (Ericson's regions).

    Leading axes broadcast. Works on the x, y, z components as separate arrays: no
    reductions over a length-3 axis, so XLA fuses it all into one elementwise loop.
    """
    p, a, b, c = (tuple(x[..., i] for i in range(3)) for x in (p, a, b, c))
    sub = lambda x, y: tuple(xi - yi for xi, yi in zip(x, y))
    dot = lambda x, y: x[0] * y[0] + x[1] * y[1] + x[2] * y[2]
    ab, ac, ap = sub(b, a), sub(c, a), sub(p, a)
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp, cp = sub(p, b), sub(p, c)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)

    def seg(x0, x1):
        e, q = sub(x1, x0), sub(p, x0)
        ee = dot(e, e)
        s = jnp.clip(dot(q, e) / jnp.where(ee > 0, ee, 1.0), 0.0, 1.0)
        r = tuple(qi - s * ei for qi, ei in zip(q, e))
        return dot(r, r)

    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    inside = (va >= 0) & (vb >= 0) & (vc >= 0)
    den = va + vb + vc
    safe = jnp.where(den > 0, den, 1.0)
    v, w = vb / safe, vc / safe
    r = tuple(api - v * abi - w * aci for api, abi, aci in zip(ap, ab, ac))
    face = dot(r, r)
    edges = jnp.minimum(jnp.minimum(seg(a, b), seg(b, c)), seg(c, a))
    return jnp.where(inside & (den > 0), jnp.minimum(face, edges), edges)


def solid_angle(p, t):
    """Signed solid angle / (4 pi) of triangles t [..., 3, 3] seen from points p [..., 3].

    Positive from the side the counter-clockwise normal points away from (inside a
    closed, outward-oriented mesh). Van Oosterom & Strackee, on separate components.
    """
    a, b, c = (tuple(t[..., i, k] - p[..., k] for k in range(3)) for i in range(3))
    return solid_angle_parts(a, b, c)


def solid_angle_parts(a, b, c):
    """`solid_angle` from the corners relative to the point, each a tuple of its (x, y, z)
    arrays (broadcast): no [..., 3] axis, which XLA's CPU code handles slowly."""
    det, den, _ = _atan2_arguments(a, b, c)
    return atan2(det, den) / (2 * jnp.pi)


def _atan2_arguments(a, b, c):
    """(det, den) of Van Oosterom & Strackee for corners a, b, c relative to the point
    (tuples of x, y, z arrays), and the magnitude of the terms each sums (for
    `solid_angle_rounding`; XLA drops it where it is unused).

    A triangle of zero area (its edges' cross product exactly zero, e.g. a repeated
    corner) gets (0, 1): no solid angle. Otherwise a point on its segment would read
    atan2(+-0, den <= 0) = +-pi, half a winding number from a triangle that has no inside.
    """
    dot = lambda x, y: x[0] * y[0] + x[1] * y[1] + x[2] * y[2]
    la, lb, lc = (jnp.sqrt(dot(x, x)) for x in (a, b, c))
    # det = a . (b x c) = a . ((b - a) x (c - a)): the edges' cross product (the plane's
    # normal) dotted with a keeps its relative rounding near the point's distance to the
    # plane over |a|, where a . (b x c) rounds at |a| |b| |c| (points near the triangle)
    e = tuple(bi - ai for ai, bi in zip(a, b))
    f = tuple(ci - ai for ai, ci in zip(a, c))
    n = (e[1] * f[2] - e[2] * f[1], e[2] * f[0] - e[0] * f[2], e[0] * f[1] - e[1] * f[0])
    flat = (n[0] == 0) & (n[1] == 0) & (n[2] == 0)
    det = jnp.where(flat, 0.0, dot(a, n))
    ab, bc, ca = dot(a, b), dot(b, c), dot(c, a)
    den = jnp.where(flat, 1.0, la * lb * lc + ab * lc + bc * la + ca * lb)
    terms = la * jnp.sqrt(dot(e, e) * dot(f, f)) + la * lb * lc + jnp.abs(ab) * lc + jnp.abs(bc) * la + jnp.abs(ca) * lb
    return det, den, terms


ROUNDING = 16 * 2.0**-24  # float32 unit roundoffs allowed per term of `solid_angle_rounding`


def solid_angle_rounding(p, t):
    """`solid_angle` (same arguments) and a bound on its float32 rounding ([...] each).

    The arguments of its atan2 are sums of products: each is off by a few unit roundoffs
    of its terms' magnitudes (``|a| |e| |f|`` for det, with e, f the edges from a; the four
    products for den), and the angle moves by at most their error over the length of
    (det, den). Large only close to the triangle, where the arguments cancel.
    """
    det, den, terms = _atan2_arguments(*(tuple(t[..., i, k] - p[..., k] for k in range(3)) for i in range(3)))
    length = jnp.sqrt(det * det + den * den)
    bound = jnp.where(length > 0, ROUNDING * terms / jnp.where(length > 0, length, 1.0), jnp.inf)
    return atan2(det, den) / (2 * jnp.pi), bound / (2 * jnp.pi)


_TAN_PI_8 = np.float32(np.sqrt(2.0) - 1.0)


def atan2(y, x):
    """``jnp.arctan2`` for float32, as accurate (at most 2.7e-7 rad from the float64
    value against 2.5e-7 for ``jnp.arctan2``, 4 M random pairs over 60 decades; the same
    results at signed zeros and infinities) and faster in some of XLA's CPU kernels: 1.75x
    in a kernel of solid angles alone, 1.25x in the brute-force winding numbers, no change
    in the cap-term kernel. Octant reduction to ``|t| <= tan(pi/8)``, then Cephes'
    ``atanf`` polynomial."""
    ax, ay = jnp.abs(x), jnp.abs(y)
    big, small = jnp.maximum(ax, ay), jnp.minimum(ax, ay)
    t = small / jnp.where(big > 0, big, 1.0)  # in [0, 1]
    upper = t > _TAN_PI_8
    t = jnp.where(upper, (t - 1.0) / (t + 1.0), t)
    z = t * t
    r = ((((8.05374449538e-2 * z - 1.38776856032e-1) * z + 1.99777106478e-1) * z - 3.33329491539e-1) * z) * t + t
    r = jnp.where(upper, r + np.float32(np.pi / 4), r)
    r = jnp.where(ay > ax, np.float32(np.pi / 2) - r, r)
    r = jnp.where(x < 0, np.float32(np.pi) - r, r)
    return jnp.where(jnp.signbit(y), -r, r)


def safe_norm(v):
    """|v| over the last axis, [..., n] -> [...], with a finite gradient at v = 0 ("safe where" before sqrt).

    Used by the SDF scenes and sphere tracing.
    """
    sq = jnp.sum(v * v, axis=-1)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def corner_bounds(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) [F, 3]: the per-axis minima and maxima of the corners of triangles
    [F, 3, 3] (host). The values of ``tris.min(1)`` and ``tris.max(1)``, a few times
    faster: numpy reduces an axis of 3 slowly."""
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    return np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)


def centroids(tris: np.ndarray) -> np.ndarray:
    """[F, 3] float64 corner means of triangles [F, 3, 3] float64 (host): the values of
    ``tris.mean(1)`` (the same sums in the same order), a few times faster."""
    return (tris[:, 0] + tris[:, 1] + tris[:, 2]) / 3


def squared_lengths(v: np.ndarray) -> np.ndarray:
    """[...] squared lengths of host vectors v [..., 3]: the sums of ``np.linalg.norm(v,
    axis=-1) ** 2`` before the root, in the same order, without numpy's slow reduction over
    an axis of 3."""
    return v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1] + v[..., 2] * v[..., 2]


def farthest_corners(tris: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """[F] distance from each centre [F, 3] to the farthest corner of its triangle of
    tris [F, 3, 3] (host): the values of ``np.linalg.norm(tris - centre[:, None],
    axis=-1).max(1)``."""
    return np.sqrt(squared_lengths(tris - centre[:, None]).max(1, initial=0.0))


def triangle_rows(tris: np.ndarray) -> np.ndarray:
    """What the tile kernels need of each triangle, computed once in float64 on the host:
    [28, F] float32 rows ``a_hi (3), a_lo (3), ab, ac, bc, u, v, n (3 each), 1/|ab|^2,
    1/|ac|^2, 1/|bc|^2, proper`` for triangles tris [F, 3, 3] float64 (grid units).

    ``a = a_hi + a_lo`` (so that ``(a_hi - o) + a_lo`` keeps float64 precision relative to
    a tile origin o); u, v the dual basis of (ab, ac) in the triangle's plane (``q . u``
    and ``q . v`` are the barycentric coordinates of the projection of ``q = p - a``); n
    the unit normal; proper 1 for a triangle of nonzero area whose u and v fit float32
    (else u, v, n are 0 and only its edges count). Every row is finite. Per-cell work is
    then products and sums only, no division."""
    out = np.empty((28, len(tris)), np.float32)
    a, b, c = (np.ascontiguousarray(tris[:, i].T) for i in range(3))  # [3, F] each: one row per axis
    ab, ac, bc = b - a, c - a, c - b
    dot = lambda x, y: x[0] * y[0] + x[1] * y[1] + x[2] * y[2]
    cross = lambda x, y: np.stack([x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]])
    normal = cross(ab, ac)
    area2 = dot(normal, normal)
    proper = area2 > 0
    # |ab|^2 |ac|^2 - (ab . ac)^2 by Lagrange's identity: the cross product's norm, without
    # the cancellation that makes the difference 0 for a sliver of nonzero area
    den = np.where(proper, area2, 1.0)
    # u, v: the gradients of b's and c's barycentric coordinates, normal x (the edge
    # opposite) over |normal|^2, as accurate as the normal; the dot-product form
    # ``(|ac|^2 ab - (ab . ac) ac) / den`` cancels to nothing in float64 for a needle
    # across which ab . ac and |ac|^2 round to |ab|^2
    u, v = cross(normal, -ac) / den, cross(normal, ab) / den
    # a sliver whose u or v exceeds float32 (thinner than about 1e-38 of its edges) counts
    # by its edges alone, whose distance from any point exceeds its own by less than its
    # width (no inf in the rows)
    largest = np.finfo(np.float32).max
    proper &= (np.abs(u) <= largest).all(0) & (np.abs(v) <= largest).all(0)
    out[0:3] = a
    out[3:6] = a - out[0:3]
    out[6:9], out[9:12], out[12:15] = ab, ac, bc
    out[15:18] = np.where(proper, u, 0.0)
    out[18:21] = np.where(proper, v, 0.0)
    out[21:24] = np.where(proper, normal / np.sqrt(den), 0.0)
    for row, edge in zip((24, 25, 26), (ab, ac, bc)):
        ee = dot(edge, edge)
        # at most float32's largest: an edge shorter than about 5e-20 would give inf, and
        # a point square to it 0 * inf = NaN (the clamp moves the point by under |edge|)
        out[row] = np.minimum(np.divide(1.0, ee, out=np.zeros_like(ee), where=ee > 0), largest)
    out[27] = proper
    return out


def rows_dist2(p, r, o, *, edge_bc: bool = False):
    """Squared distance from points p (3 arrays, grid units relative to o) to triangles
    given by `triangle_rows` rows r (28 arrays, broadcast against p), o: 3 float32 arrays
    the origin the points are relative to; with `edge_bc` also the squared distance to
    each triangle's edge bc (a pair of arrays)."""
    dot = lambda x, y: x[0] * y[0] + x[1] * y[1] + x[2] * y[2]
    q = tuple(p[k] - ((r[k] - o[k]) + r[3 + k]) for k in range(3))  # p - a
    ab, ac, bc, u, v, n = (tuple(r[6 + 3 * i + k] for k in range(3)) for i in range(6))

    def segment(x, e, inverse):  # squared distance from x (relative to its start) to e
        s = jnp.clip(dot(x, e) * inverse, 0.0, 1.0)
        off = tuple(xi - s * ei for xi, ei in zip(x, e))
        return dot(off, off)

    qb = tuple(qi - ei for qi, ei in zip(q, ab))
    to_bc = segment(qb, bc, r[26])
    edges = jnp.minimum(jnp.minimum(segment(q, ab, r[24]), segment(q, ac, r[25])), to_bc)
    s, t, h = dot(q, u), dot(q, v), dot(q, n)
    inside = (s >= 0) & (t >= 0) & (s + t <= 1) & (r[27] > 0)
    d2 = jnp.where(inside, jnp.minimum(h * h, edges), edges)
    return (d2, to_bc) if edge_bc else d2
