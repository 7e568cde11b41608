"""Geometry kernels shared by several modules (private module, public names).

Point-triangle squared distance (the voxelizer's closest-triangle ids, the distance
fields), the signed solid angle of a triangle (winding numbers, the brute-force sign
of the distance fields) and a NaN-safe vector norm (SDF scenes, sphere tracing). The
first two work on x, y, z components as separate arrays, so XLA fuses each into one
elementwise loop.
"""

from __future__ import annotations

import jax.numpy as jnp


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
    dot = lambda x, y: x[0] * y[0] + x[1] * y[1] + x[2] * y[2]
    la, lb, lc = (jnp.sqrt(dot(x, x)) for x in (a, b, c))
    det = a[0] * (b[1] * c[2] - b[2] * c[1]) + a[1] * (b[2] * c[0] - b[0] * c[2]) + a[2] * (b[0] * c[1] - b[1] * c[0])
    den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb
    return jnp.arctan2(det, den) / (2 * jnp.pi)


def safe_norm(v):
    """|v| over the last axis, [..., n] -> [...], with a finite gradient at v = 0 ("safe where" before sqrt).

    Used by the SDF scenes and sphere tracing.
    """
    sq = jnp.sum(v * v, axis=-1)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)
