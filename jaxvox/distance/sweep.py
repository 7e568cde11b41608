"""Fast sweeping of the eikonal equation ``|grad d| = 1`` (Zhao 2005): the "sweep" and
"jfa+sweep" propagations of `jaxvox.distance`.

Sweeping works on *distances* (not triangle ids): Gauss-Seidel sweeps in the 8 diagonal
orders with the Godunov upwind update; seeded voxels are kept fixed. It can
underestimate (by about 0.3 voxel along ridges of the field, where the upwind update
mixes two fronts) and overestimates diagonally from small features.

Sweeping in JAX: a Gauss-Seidel sweep in order (+x, +y, +z) updates voxel
``(i, j, k)`` from its upwind neighbours, all on the hyperplane ``i + j + k = s - 1``,
so the hyperplanes are visited in order by a `jax.lax.fori_loop` over the grid stored
skewed (plane ``s`` as an ``[R, R]`` array over (i, j), ``k = s - i - j``), each plane
updated in place; this is the same update order as the sequential sweep (Detrixhe,
Gibou & Min 2013). The reverse order is a reverse loop over the same layout; flipping
one axis gives the other six orders. The skew is two shears, each a pad and a reshape
(no index arrays), and fixed voxels carry their sign bit (no mask array), so a sweep
needs about 3 R^3 floats beyond the field.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _godunov(a, b, c):
    """Upwind solution of |grad u| = 1 (unit spacing) from the axis minima a, b, c (inf: none)."""
    a, b = jnp.minimum(a, b), jnp.maximum(a, b)
    b, c = jnp.minimum(b, c), jnp.maximum(b, c)
    a, b = jnp.minimum(a, b), jnp.maximum(a, b)
    u1 = a + 1.0
    two = u1 > b  # finite a and b: the two-axis solution applies
    a2, b2 = jnp.where(two, a, 0.0), jnp.where(two, b, 0.0)  # safe where: no inf - inf
    u2 = 0.5 * (a2 + b2 + jnp.sqrt(jnp.maximum(2.0 - (a2 - b2) ** 2, 0.0)))
    three = two & (u2 > c)
    a3, b3, c3 = (jnp.where(three, x, 0.0) for x in (a, b, c))
    s = a3 + b3 + c3
    u3 = (s + jnp.sqrt(jnp.maximum(s * s - 3.0 * (a3 * a3 + b3 * b3 + c3 * c3 - 1.0), 0.0))) / 3.0
    return jnp.where(three, u3, jnp.where(two, u2, u1))


def _shear(a, fill):
    """Shifts row ``i`` of the last two axes right by ``i``: [..., n, m] -> [..., n, m + n - 1].

    ``out[..., i, i + t] = a[..., i, t]``, `fill` elsewhere. Pad, flatten, re-read with a
    row one shorter: copies only, no index arrays.
    """
    *lead, n, m = a.shape
    flat = jnp.pad(a, [(0, 0)] * len(lead) + [(0, 0), (0, n)], constant_values=fill).reshape(*lead, n * (m + n))
    return flat[..., : n * (m + n - 1)].reshape(*lead, n, m + n - 1)


def _unshear(b, m: int, fill):
    """The inverse of `_shear`: [..., n, m + n - 1] -> [..., n, m]."""
    *lead, n, _ = b.shape
    flat = jnp.pad(b.reshape(*lead, n * (m + n - 1)), [(0, 0)] * len(lead) + [(0, n)], constant_values=fill)
    return flat.reshape(*lead, n, m + n)[..., :m]


def _skew(u, fill):
    """[a, b, c] (i, j, k) -> [a + b + c - 2, a, b] (s, i, j) holding ``u[i, j, s - i - j]``, `fill` elsewhere."""
    v = _shear(u, fill)  # [i, j, j + k]
    w = _shear(v.transpose(1, 0, 2), fill)  # [j, i, i + j + k]
    return w.transpose(2, 1, 0)


def _unskew(t, c: int, fill):
    """The inverse of `_skew` of an [a, b, c] array."""
    b = t.shape[2]
    v = _unshear(t.transpose(2, 1, 0), b + c - 1, fill)  # [j, i, j + k]
    return _unshear(v.transpose(1, 0, 2), c, fill)


def _sweep_pair(u):
    """Gauss-Seidel sweeps in orders (+, +, +) then (-, -, -) of u [a, b, c] (inf: unknown).

    Voxels whose sign bit is set are fixed (their value is ``-u``); the others are
    updated to ``min(u, Godunov update)``. Outside the box the skewed layout holds
    ``-inf``: fixed and, read as ``|u|``, no neighbour.
    """
    a, b, c = u.shape
    plane = _skew(u, -jnp.inf)  # [a + b + c - 2, a, b]
    inf_row = jnp.full((1, b), jnp.inf)
    inf_col = jnp.full((a, 1), jnp.inf)

    def update(own, lower, upper):
        """New values of a plane from the planes s - 1 (lower) and s + 1 (upper)."""
        lower, upper = jnp.abs(lower), jnp.abs(upper)
        ax = jnp.minimum(jnp.concatenate([inf_row, lower[:-1]]), jnp.concatenate([upper[1:], inf_row]))
        ay = jnp.minimum(jnp.concatenate([inf_col, lower[:, :-1]], 1), jnp.concatenate([upper[:, 1:], inf_col], 1))
        az = jnp.minimum(lower, upper)
        return jnp.where(jnp.signbit(own), own, jnp.minimum(own, _godunov(ax, ay, az)))

    planes = plane.shape[0]
    # One -inf plane on each side: plane s of the grid is row s + 1 here; updated in place.
    plane = jnp.pad(plane, ((1, 1), (0, 0), (0, 0)), constant_values=-jnp.inf)
    at = lambda p, s: jax.lax.dynamic_index_in_dim(p, s, keepdims=False)

    def step(s, p):
        new = update(at(p, s), at(p, s - 1), at(p, s + 1))
        return jax.lax.dynamic_update_index_in_dim(p, new, s, 0)

    plane = jax.lax.fori_loop(1, planes + 1, step, plane)  # (+, +, +)
    plane = jax.lax.fori_loop(1, planes + 1, lambda n, p: step(planes + 1 - n, p), plane)  # (-, -, -)
    plane = plane[1:-1]
    return _unskew(plane, c, -jnp.inf)


def fast_sweep(u, free, iterations: int):
    """`iterations` rounds of fast sweeping in all 8 diagonal orders; only `free` voxels change."""
    u = jnp.where(free, u, -u)  # the sign bit marks fixed voxels (u >= 0; -0.0 has it too)

    # The four pairs of orders flip no axis, then axis 0, 1 or 2 (a flip undoes itself).
    flips = [lambda a: a] + [lambda a, axis=axis: jnp.flip(a, axis) for axis in range(3)]

    def pair(n, u):
        flip = lambda a: jax.lax.switch(n % 4, flips, a)
        return flip(_sweep_pair(flip(u)))

    # loops, not unrolled: one sweep pair's code, compiled once whatever `iterations` is
    return jnp.abs(jax.lax.fori_loop(0, 4 * iterations, pair, u))
