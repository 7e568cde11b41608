"""Dense distance fields of triangle meshes, solid voxelization and its sign.

The pipeline follows Boissé's thread (``../shared/seeds/003_*.txt``), in grid units
(voxel edge 1; results are scaled to world units at the end):

1. **Closest-triangle voxelization.** Every voxel the surface touches (conservative
   voxelization) gets the id of the triangle nearest its centre among the triangles
   that touch it, ties to the lower id (`jaxvox.voxelize` with ``triangle_ids=True``,
   a lexicographic sort on (voxel, distance, id)). Each triangle also seeds the voxels
   holding its centroid and its three corners clamped into the grid, merged with a
   scatter-min on (distance bits, id), so that geometry outside the grid still reaches
   it (only through those voxels: a triangle outside the grid whose nearest region in
   the grid is cut off from them is found late, see the test suite's bounds).
2. **Narrow band.** ``band`` separable 3x3x3 passes of jump flooding on triangle ids
   (one axis at a time, neighbours at -1, +1): every voxel within ``band`` voxels
   (Chebyshev) of a seeded voxel holds the exact point-triangle distance to the best
   triangle found among its neighbours.
3. **Propagation** to the whole grid, one of:

   * ``"jfa"``: jump flooding on triangle ids with steps R/2, R/4, ..., 1, each
     pass comparing the 26 neighbours at that step (Jacobi within a pass);
   * ``"jfa-separable"``: the same steps, each as three one-axis passes
     (2 neighbours each: 6 candidates per step instead of 26);
   * ``"sweep"``: Zhao's fast sweeping of the eikonal equation ``|grad d| = 1`` on
     *distances* (not ids): Gauss-Seidel sweeps in the 8 diagonal orders, the
     Godunov upwind update, ``sweeps`` iterations; seeded voxels are kept fixed;
   * ``"jfa+sweep"``: the thread's pipeline, the narrow band (default one separable
     3x3x3 pass) followed by sweeps;
   * ``"exact"``: the brute-force minimum over all triangles at every voxel, chunked
     (O(R^3 F): a reference for small grids);
   * ``"band"``: none; the narrow band alone (default 4 passes), +inf beyond it. Its
     value at a voxel depends only on the seeds within ``band`` voxels (Chebyshev),
     which is what truncated fields such as the clipmap's need. Values are distances
     to real triangles (never below exact); voxels within about ``band - 1`` voxels of
     the surface have jump flooding's accuracy, farther ones in the band may have
     been reached only from a farther part of the surface.

   Methods on ids give distances to real triangles, so they never underestimate;
   sweeping can (by about 0.3 voxel along ridges of the field, where the upwind
   update mixes two fronts) and overestimates diagonally from small features.
4. **Sign** from a solid voxelization of the voxel centres: ``"parity"`` (Schwarz &
   Seidel: every triangle flips the inside bit of the voxels of a +x column beyond
   the column's crossing, then a prefix XOR along x; exact and O(surface), right for
   watertight meshes only, which it checks) or ``"winding"`` (the generalized
   winding number, inside where it exceeds 1/2, by `jaxvox.winding_numbers`' tree of
   dipoles: right for open meshes with holes, like the bunny, and for closed ones).

Sweeping in JAX: a Gauss-Seidel sweep in order (+x, +y, +z) updates voxel
``(i, j, k)`` from its upwind neighbours, all on the hyperplane ``i + j + k = s - 1``,
so the hyperplanes are visited in order by a `jax.lax.fori_loop` over the grid stored
skewed (plane ``s`` as an ``[R, R]`` array over (i, j), ``k = s - i - j``), each plane
updated in place; this is the same update order as the sequential sweep (Detrixhe,
Gibou & Min 2013). The reverse order is a reverse loop over the same layout; flipping
one axis gives the other six orders. The skew is two shears, each a pad and a reshape
(no index arrays), and fixed voxels carry their sign bit (no mask array), so a sweep
needs about 3 R^3 floats beyond the field.

Memory: a dense field costs 4 R^3 bytes; the build needs more for temporaries, see
`distance_field_bytes`. `distance_field` refuses sizes above ``max_bytes``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._checks import (
    check_choice,
    check_int,
    check_number,
    check_type,
    check_vector,
    is_concrete,
    refuse,
)
from jaxvox._pytree import pytree_dataclass
from jaxvox._shapes import bucket, expand_counts
from jaxvox.grid import Grid, check_resolution
from jaxvox.mesh import Mesh, pad_mesh, validate_mesh
from jaxvox.trace import HIT, MISS, STEP_CAP
from jaxvox.voxelize import CONSERVATIVE, UNUSED, _point_triangle_dist2, voxelize
from jaxvox.winding import _box_winding_numbers, solid_angle

METHODS = ("exact", "jfa", "jfa-separable", "sweep", "jfa+sweep", "band")
SIGN_METHODS = ("auto", "parity", "winding")
NO_TRIANGLE = -1  # triangle id of a voxel no seed has reached yet
FORMATS = ("float16", "fixed16")

# Peak working memory per voxel of each method (bytes), measured as the process's peak
# resident memory at 64^3-256^3 with room to spare (jump flooding works on blocks of
# voxels: ~30 measured; sweeping holds a skewed [3R-2, R, R] copy and the shears'
# temporaries: 41 measured at 256^3); add SIGN_BYTES_PER_VOXEL for a signed field.
BYTES_PER_VOXEL = {"exact": 16, "jfa": 48, "jfa-separable": 48, "sweep": 64, "jfa+sweep": 64, "band": 48}
SIGN_BYTES_PER_VOXEL = 16
_PAIRS_PER_CHUNK = 1 << 21  # (voxel, triangle) pairs per chunk of the brute-force loops
_VOXELS_PER_BLOCK = 1 << 20  # voxels per block of a jump-flooding step (bounds its temporaries)


# ------------------------------------------------------------------------ helpers


def _centres(shape: tuple[int, int, int]) -> jax.Array:
    """Voxel centres in grid units of a box of `shape` voxels: [n, 3] float32, C order."""
    ijk = jnp.stack(jnp.unravel_index(jnp.arange(math.prod(shape)), shape), -1)
    return ijk.astype(jnp.float32) + 0.5


def _distance_to(points, tris, ids):
    """Distance from points [n, 3] to triangles ``tris[ids]`` ([n] int32; inf where -1)."""
    return jnp.where(ids >= 0, _pair_distance(points, tris[jnp.maximum(ids, 0)]), jnp.inf)


def _per_point(points, tris, fn):
    """``fn(points [c, 1, 3], tris [1, F, 3, 3]) -> [c]`` over all points, in chunks of points."""
    n = points.shape[0]
    chunk = max(1, min(n, _PAIRS_PER_CHUNK // max(tris.shape[0], 1)))
    pad = -n % chunk
    pts = jnp.concatenate([points, jnp.zeros((pad, 3), points.dtype)]).reshape(-1, chunk, 3)
    out = jax.lax.map(lambda p: fn(p[:, None], tris[None]), pts)
    return out.reshape(-1)[:n]


def _mesh_distance(points, tris):
    """Exact distance [n] from points [n, 3] to the nearest of all triangles (inf if none)."""
    return _per_point(points, tris, lambda p, t: _pair_distance(p, t).min(1, initial=jnp.inf))


def _pair_distance(p, t):
    """Point-triangle distances for broadcast points [..., 3] and triangles [..., 3, 3]."""
    return jnp.sqrt(_point_triangle_dist2(p, t[..., 0, :], t[..., 1, :], t[..., 2, :]))


def _winding_numbers(points, tris):
    """Generalized winding number [n] at points [n, 3] by brute force over all triangles, chunked."""
    return _per_point(points, tris, lambda p, t: solid_angle(p, t).sum(1))


# ------------------------------------------------------------------------- seeds


def _flat(ijk, shape: tuple[int, int, int]):
    """C-order flat index of voxels [..., 3] int32 in a box of `shape` voxels."""
    return (ijk[..., 0] * shape[1] + ijk[..., 1]) * shape[2] + ijk[..., 2]


def _seed(tris, coords, triangle, shape: tuple[int, int, int], clamped: bool = True):
    """Closest-triangle seeds: ([n] int32 ids, [n] float32 distances, inf where none), n
    the voxels of a box of `shape`.

    Candidates are the voxelizer's (voxel, closest triangle) pairs (voxels with a
    negative first coordinate are unused) and, if `clamped`, per triangle the voxels of
    its centroid and corners clamped into the box; each voxel keeps the nearest
    candidate, ties to the lower id (a scatter-min on distance bits, then on ids).
    """
    n = math.prod(shape)
    ijk, tri, valid = coords, triangle, coords[:, 0] >= 0
    if clamped:
        points = jnp.concatenate([tris.mean(1), tris[:, 0], tris[:, 1], tris[:, 2]])  # [4F, 3]
        ijk = jnp.concatenate([ijk, jnp.clip(jnp.floor(points), 0, jnp.asarray(shape) - 1).astype(jnp.int32)])
        tri = jnp.concatenate([tri, jnp.tile(jnp.arange(tris.shape[0], dtype=jnp.int32), 4)])
        valid = jnp.concatenate([valid, jnp.tile(jnp.all(jnp.isfinite(tris), (1, 2)), 4)])
    flat = jnp.where(valid, _flat(ijk, shape), n)  # n: dropped
    dist = _distance_to(ijk.astype(jnp.float32) + 0.5, tris, jnp.where(valid, tri, NO_TRIANGLE))
    bits = jax.lax.bitcast_convert_type(dist, jnp.int32)  # non-negative floats order as ints
    best = jnp.full(n, jnp.iinfo(jnp.int32).max, jnp.int32).at[flat].min(bits, mode="drop")
    winner = valid & (bits == best.at[flat].get(mode="fill", fill_value=0))
    ids = jnp.full(n, jnp.iinfo(jnp.int32).max, jnp.int32).at[jnp.where(winner, flat, n)].min(
        tri, mode="drop")
    ids = jnp.where(ids == jnp.iinfo(jnp.int32).max, NO_TRIANGLE, ids)
    return ids, jax.lax.bitcast_convert_type(jnp.where(ids >= 0, best, 0x7F800000), jnp.float32)


# ---------------------------------------------------------------- jump flooding


def _offsets(steps, separable: bool) -> np.ndarray:
    """Neighbour offsets of each pass: [P, M, 3] int32 (M = 2 separable, 26 full)."""
    unit = np.array([o for o in np.ndindex(3, 3, 3) if o != (1, 1, 1)]) - 1
    passes = []
    for step in steps:
        if separable:
            passes += [np.eye(3, dtype=np.int64)[[axis, axis]] * [[-step], [step]] for axis in range(3)]
        else:
            passes.append(unit * step)
    return np.array(passes, np.int32).reshape(-1, 2 if separable else 26, 3)


def _jfa(ids, dist, tris, offsets: np.ndarray, shape: tuple[int, int, int]):
    """Jump-flooding passes on triangle ids [n] (n voxels of a box of `shape`): each voxel
    keeps the nearest of its own and its neighbours' triangles (ties to the lower id);
    neighbours are read from the ids at the start of the pass, outside the box there are
    none (no wrap-around).

    Each neighbour offset is applied to blocks of `_VOXELS_PER_BLOCK` voxels in turn
    (`jax.lax.map`), so the temporaries of the point-triangle distances stay bounded
    (the last block is padded; its extra voxels are dropped).
    """
    if offsets.shape[0] == 0:
        return ids, dist
    size = math.prod(shape)
    block = min(size, _VOXELS_PER_BLOCK)
    pad = -size % block
    ids = jnp.concatenate([ids, jnp.full(pad, NO_TRIANGLE, ids.dtype)])
    dist = jnp.concatenate([dist, jnp.full(pad, jnp.inf, dist.dtype)])
    n = size + pad

    def one_pass(state, pass_offsets):
        prev = state[0]

        def candidate(state, offset):
            def one_block(args):
                start, ids, dist = args
                ijk = jnp.stack(jnp.unravel_index(start + jnp.arange(block, dtype=jnp.int32), shape), -1)
                q = ijk + offset
                ok = jnp.all((q >= 0) & (q < jnp.asarray(shape)), axis=1)
                cand = jnp.where(ok, prev[_flat(q, shape)], NO_TRIANGLE)
                d = _distance_to(ijk.astype(jnp.float32) + 0.5, tris, cand)
                better = (d < dist) | ((d == dist) & (cand >= 0) & ((cand < ids) | (ids < 0)))
                return jnp.where(better, cand, ids), jnp.where(better, d, dist)

            starts = jnp.arange(0, n, block, dtype=jnp.int32)
            ids, dist = jax.lax.map(one_block, (starts, state[0].reshape(-1, block), state[1].reshape(-1, block)))
            return (ids.reshape(-1), dist.reshape(-1)), None

        return jax.lax.scan(candidate, state, pass_offsets)[0], None

    ids, dist = jax.lax.scan(one_pass, (ids, dist), jnp.asarray(offsets))[0]
    return ids[:size], dist[:size]


def _jfa_steps(shape: tuple[int, int, int]):
    """Steps P/2, ..., 1 for the power of two P >= the box's longest side."""
    p = 1 << (max(shape) - 1).bit_length()
    return [p >> s for s in range(1, p.bit_length())]


# --------------------------------------------------------------------- sweeping


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


def _sweep(u, free, iterations: int):
    """`iterations` rounds of fast sweeping in all 8 diagonal orders; only `free` voxels change."""
    u = jnp.where(free, u, -u)  # the sign bit marks fixed voxels (u >= 0; -0.0 has it too)
    for _ in range(iterations):
        for axes in ((), (0,), (1,), (2,)):
            flip = lambda a: jnp.flip(a, axes) if axes else a
            u = flip(_sweep_pair(flip(u)))
    return jnp.abs(u)


# -------------------------------------------------------------------------- sign


def open_edges(mesh: Mesh) -> int:
    """Number of edges not shared by an even number of faces (0 for a watertight mesh).

    Vertices at equal positions are welded first, so seams of duplicated vertices
    (texture or normal seams) do not count as holes; zero-length edges are ignored.

    Args:
      mesh: `Mesh` with F faces.

    Returns:
      int, host-side.

    Raises:
      JaxvoxError: not a `Mesh`.
    """
    check_type("open_edges mesh", mesh, Mesh)
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    if len(f) == 0:
        return 0
    order = np.lexsort(v.T[::-1])  # weld: equal positions get one id (numeric sorts, no row unique)
    new_group = np.concatenate([[True], np.any(v[order[1:]] != v[order[:-1]], axis=1)])
    weld = np.empty(len(v), np.int64)
    weld[order] = np.cumsum(new_group) - 1
    f = weld[f]
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    e = e[e[:, 0] != e[:, 1]]
    _, counts = np.unique(e[:, 0] * len(v) + e[:, 1], return_counts=True)
    return int(np.sum(counts % 2))


def _parity_columns(tris, shape: tuple[int, int, int]):
    """Per triangle: first (j, k) column and the number of columns (j, k) its yz box covers."""
    yz = jnp.asarray(shape[1:])
    lo = jnp.clip(jnp.ceil(tris.min(1)[:, 1:] - 0.5), 0, yz)
    hi = jnp.clip(jnp.floor(tris.max(1)[:, 1:] - 0.5), -1, yz - 1)
    n = jnp.maximum(hi - lo + 1, 0).astype(jnp.int32)
    live = jnp.all(jnp.isfinite(tris), (1, 2)) & (tris.min(1)[:, 0] < shape[0])
    return lo.astype(jnp.int32), jnp.where(live, n[:, 0] * n[:, 1], 0), n[:, 1]


@functools.partial(jax.jit, static_argnames=("shape",))
def _parity_count(tris, *, shape):
    return jnp.sum(_parity_columns(tris, shape)[1])


@functools.partial(jax.jit, static_argnames=("shape", "capacity"))
def _parity(tris, *, shape: tuple[int, int, int], capacity: int):
    """Schwarz & Seidel's solid voxelization of a box of `shape` voxels (triangles in its
    units): [nx, ny, nz] bool, voxel centres inside.

    For every (triangle, column (j, k) whose centre the triangle's yz projection covers)
    the voxels of the column beyond the crossing flip; a prefix XOR along x gives the
    parity of crossings before each centre. Coverage uses edge functions evaluated
    with each edge's endpoints in a canonical order, and the top-left rule on the
    edges, so that a column through a shared edge or vertex is counted exactly once.
    """
    lo, n_cols, nk = _parity_columns(tris, shape)
    tri, rank, valid, _ = expand_counts(n_cols, capacity)
    j = lo[tri, 0] + rank // jnp.maximum(nk[tri], 1)
    k = lo[tri, 1] + rank % jnp.maximum(nk[tri], 1)
    t = tris[tri]  # [C, 3, 3]
    yz = t[:, :, 1:]
    c = jnp.stack([j, k], -1).astype(jnp.float32) + 0.5
    p, q = yz, jnp.roll(yz, -1, axis=1)  # edge p -> q
    swap = (p[..., 0] > q[..., 0]) | ((p[..., 0] == q[..., 0]) & (p[..., 1] > q[..., 1]))
    lo_e = jnp.where(swap[..., None], q, p)
    d = jnp.where(swap[..., None], p - q, q - p)
    e = d[..., 0] * (c[:, None, 1] - lo_e[..., 1]) - d[..., 1] * (c[:, None, 0] - lo_e[..., 0])
    normal = jnp.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    orient = jnp.sign(normal[:, 0])  # +1: counter-clockwise in (y, z)
    sign = jnp.where(swap, -1.0, 1.0) * orient[:, None]
    e = e * sign
    gy, gz = -d[..., 1] * sign, d[..., 0] * sign  # gradient of e: the inward edge normal
    top_left = (gy > 0) | ((gy == 0) & (gz > 0))
    covered = jnp.all((e > 0) | ((e == 0) & top_left), axis=1) & valid & (orient != 0)
    nx = jnp.where(orient != 0, normal[:, 0], 1.0)
    x = t[:, 0, 0] - (normal[:, 1] * (c[:, 0] - t[:, 0, 1]) + normal[:, 2] * (c[:, 1] - t[:, 0, 2])) / nx
    i = jnp.clip(jnp.ceil(x - 0.5), 0, shape[0]).astype(jnp.int32)  # first voxel whose centre is beyond
    n = math.prod(shape)
    flat = jnp.where(covered & (i < shape[0]), _flat(jnp.stack([i, j, k], -1), shape), n)
    flips = jnp.zeros(n, jnp.int32).at[flat].add(1, mode="drop").reshape(shape)
    return (jnp.cumsum(flips, axis=0) & 1).astype(bool)


@jax.jit
def _grid_triangles(mesh: Mesh, grid: Grid):
    return grid.to_grid_units(mesh.triangles())


def _padded(mesh: Mesh) -> Mesh:
    """`mesh` padded to a power-of-two number of faces with ``(0, 0, 0)`` faces (points at
    vertex 0, on the surface: they change no distance, cross no ray and subtend no solid
    angle), so that meshes of similar size share compiled code."""
    return pad_mesh(mesh, mesh.num_vertices, bucket(mesh.num_faces, 256))


def _box_grid(origin, voxel_size, shape: tuple[int, int, int]) -> Grid:
    """The cubic grid whose first `shape` voxels form a box: same origin and voxels,
    resolution the power of two >= the box's longest side."""
    return Grid(origin, voxel_size, max(2, 1 << (max(shape) - 1).bit_length()))


def _sign_method(what: str, mesh: Mesh, method: str) -> str:
    """`method` of `SIGN_METHODS` for `mesh`: "auto" becomes "parity" for a watertight mesh,
    else "winding"; "parity" on a mesh with open edges is refused (`what` names the method)."""
    if method == "winding" or mesh.num_faces == 0:
        return method
    holes = open_edges(mesh)
    if method == "auto":
        return "winding" if holes else "parity"
    if holes:
        raise refuse(what, f"'parity' needs a watertight mesh, but {holes} edges are not shared by an even "
                     "number of faces (holes or non-manifold edges); use 'winding' for open meshes", method)
    return method


def _solid(mesh: Mesh, tris, grid: Grid, shape: tuple[int, int, int], method: str, beta: float):
    """Inside bits [nx, ny, nz] of the voxel centres of the box made of the first `shape`
    voxels of `grid` (`tris`: `mesh`'s padded triangles in grid units, for parity; the
    winding number reads `mesh`; `method`: "parity" or "winding", see `_sign_method`)."""
    if mesh.num_faces == 0:
        return jnp.zeros(shape, bool)
    if method == "parity":
        return _parity(tris, shape=shape, capacity=bucket(int(_parity_count(tris, shape=shape))))
    return _box_winding_numbers(mesh, np.asarray(grid.origin, np.float64), float(grid.voxel_size), shape,
                                beta=beta) > 0.5


def solid_voxelize(mesh: Mesh, grid: Grid, *, method: str = "auto", beta: float = 2.0) -> jax.Array:
    """Voxels whose centre lies inside the mesh: [R, R, R] bool (True inside).

    Args:
      mesh: `Mesh`, outward-facing (counter-clockwise seen from outside) for "winding".
      grid: `Grid` of R^3 voxels; geometry outside it still counts (rays and winding
        numbers see the whole mesh).
      method: "parity" (Schwarz & Seidel: parity of the crossings of the +x ray,
        O(R^3 + surface); exact for watertight meshes, raises for open ones),
        "winding" (generalized winding number > 1/2 at each centre, by
        `jaxvox.winding_numbers`' tree: right for open meshes with holes such as the
        Stanford bunny, and for closed ones), or "auto" (parity when
        `open_edges(mesh) == 0`, else winding).
      beta: the far-field ratio of `jaxvox.winding_numbers` ("winding" only), > 1.

    Raises:
      JaxvoxError: bad method, beta, grid or mesh, "parity" on a mesh that is not
        watertight, or a grid too large (the result costs R^3 bytes plus temporaries).
    """
    check_type("solid_voxelize grid", grid, Grid)
    validate_mesh(mesh)
    check_choice("solid_voxelize method", method, SIGN_METHODS)
    beta = check_number("solid_voxelize beta", beta, above=1.0, finite=False)
    _check_bytes("solid_voxelize", grid.resolution, SIGN_BYTES_PER_VOXEL, None)
    method = _sign_method("solid_voxelize method", mesh, method)
    r = grid.resolution
    return _solid(mesh, _grid_triangles(_padded(mesh), grid), grid, (r, r, r), method, beta)


# ------------------------------------------------------------------- the field


def distance_field_bytes(resolution: int, *, method: str = "jfa+sweep", signed: bool = True) -> int:
    """Estimated peak working memory of `distance_field` at R^3 voxels, in bytes.

    ``R^3 * (BYTES_PER_VOXEL[method] + (SIGN_BYTES_PER_VOXEL if signed else 0))``; the
    result itself is 4 R^3 bytes (512^3: 0.5 GiB; a signed "jfa+sweep" build is estimated
    at 14 GiB there).

    Raises:
      JaxvoxError: an unknown method, or a resolution that is not a power of two.
    """
    per_voxel = BYTES_PER_VOXEL[check_choice("distance_field_bytes method", method, METHODS)]
    return check_resolution(resolution) ** 3 * (per_voxel + (SIGN_BYTES_PER_VOXEL if signed else 0))


def _default_max_bytes() -> int:
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2


def _check_bytes(caller: str, resolution: int, per_voxel: int, max_bytes: int | None) -> None:
    """Refuses a grid of `resolution`^3 voxels whose working memory (`per_voxel` bytes
    each) exceeds `max_bytes` (default half the physical memory)."""
    need = resolution**3 * per_voxel
    limit = _default_max_bytes() if max_bytes is None else max_bytes
    if need > limit:
        raise refuse(f"{caller} grid resolution", f"needs about {need / 2**30:.2f} GiB ({per_voxel} bytes per "
                     f"voxel), above max_bytes = {limit / 2**30:.2f} GiB (default: half the physical memory); use "
                     "a lower resolution or raise max_bytes", resolution)


@functools.partial(jax.jit, static_argnames=("shape", "method", "band", "sweeps", "clamped"))
def _unsigned(tris, coords, triangle, *, shape: tuple[int, int, int], method: str, band: int, sweeps: int,
              clamped: bool = True):
    """Unsigned field of a box of `shape` voxels (triangles and seed voxels in its units):
    [nx, ny, nz] float32 in voxels (inf where no seed reached; `clamped`: see `_seed`)."""
    if method == "exact":
        return _mesh_distance(_centres(shape), tris).reshape(shape)
    ids, dist = _seed(tris, coords, triangle, shape, clamped)
    ids, dist = _jfa(ids, dist, tris, _offsets([1] * band, True), shape)
    if method in ("jfa", "jfa-separable"):
        ids, dist = _jfa(ids, dist, tris, _offsets(_jfa_steps(shape), method == "jfa-separable"), shape)
    dist = dist.reshape(shape)
    if method in ("sweep", "jfa+sweep"):
        dist = _sweep(dist, jnp.isinf(dist), sweeps)
    return dist


def distance_field(mesh: Mesh, grid: Grid, *, method: str = "jfa+sweep", signed: bool = True,
                   band: int | None = None, sweeps: int = 3, sign: str = "auto",
                   max_bytes: int | None = None) -> jax.Array:
    """Distance from every voxel centre to the mesh surface, in world units.

    Host-side (it sizes the voxelization and checks memory); the propagation and sign
    steps are compiled once per (resolution, method, band, sweeps). See the module
    docstring for how each method works and what error it makes.

    Args:
      mesh: `Mesh` with F faces (validated: NaN/inf vertices or bad indices raise).
      grid: `Grid` of R^3 voxels. Geometry outside the grid is taken into account.
      method: "jfa+sweep" (narrow band by jump flooding, then fast sweeping), "jfa",
        "jfa-separable", "sweep", "exact" (brute force, O(R^3 F): small grids) or
        "band" (the narrow band only: +inf beyond it, -inf inside when signed).
      signed: negative inside the mesh (see `solid_voxelize` for the sign).
      band: separable 3x3x3 jump-flooding passes around the surface voxels before the
        propagation (exact distances within that many voxels of the surface voxels);
        default 1 for "jfa+sweep", 4 for "band", 0 otherwise; ignored by "exact".
      sweeps: fast-sweeping iterations (each visits the 8 diagonal orders), for
        "sweep" and "jfa+sweep".
      sign: "auto", "parity" or "winding" (see `solid_voxelize`).
      max_bytes: refuse builds whose estimated working memory
        (`distance_field_bytes`) exceeds this; default half the physical memory.

    Returns:
      [R, R, R] float32 indexed (i, j, k); +inf everywhere for a mesh without faces.

    Raises:
      JaxvoxError: bad method, band, sweeps, sign or mesh; "parity" sign on a mesh that
        is not watertight; a grid that would not fit in `max_bytes`.
    """
    check_type("distance_field grid", grid, Grid)
    validate_mesh(mesh)
    check_choice("distance_field method", method, METHODS)
    check_choice("distance_field sign", sign, SIGN_METHODS)
    band = {"jfa+sweep": 1, "band": 4}.get(method, 0) if band is None else band
    if method == "exact":
        band = 0
    band = check_int("distance_field band", band, minimum=0)
    sweeps = check_int("distance_field sweeps", sweeps, minimum=1)
    if max_bytes is not None:
        max_bytes = check_int("distance_field max_bytes", max_bytes, minimum=0)
    r = grid.resolution
    _check_bytes("distance_field", r, BYTES_PER_VOXEL[method] + (SIGN_BYTES_PER_VOXEL if signed else 0), max_bytes)
    if mesh.num_faces == 0:
        return jnp.full((r, r, r), jnp.inf, jnp.float32)
    if signed:
        sign = _sign_method("distance_field sign", mesh, sign)
    dist = _box_distance(mesh, grid, (r, r, r), method=method, band=band, sweeps=sweeps)
    if signed:
        dist = jnp.where(_solid(mesh, _grid_triangles(_padded(mesh), grid), grid, (r, r, r), sign, 2.0), -dist, dist)
    return dist * grid.voxel_size


def _box_distance(mesh: Mesh, grid: Grid, shape: tuple[int, int, int], *, method: str, band: int,
                  sweeps: int, clamped: bool = True) -> jax.Array:
    """Unsigned distance in voxels [nx, ny, nz] float32 at the centres of the box made of
    the first `shape` voxels of `grid`, by `method` (`mesh` has faces; `clamped`: seed
    the box with the clamped centroids and corners of triangles, see `_seed`)."""
    padded = _padded(mesh)
    tris = _grid_triangles(padded, grid)
    if method == "exact":
        coords, triangle = jnp.zeros((0, 3), jnp.int32), jnp.zeros(0, jnp.int32)
    else:
        vox = voxelize(padded, grid, mode=CONSERVATIVE, triangle_ids=True, progress=False)
        n = int(vox.count)
        cap = bucket(n, 4096)  # few shapes: similar meshes share the compiled field
        inside = jnp.all(vox.coords[:n] < jnp.asarray(shape), axis=1, keepdims=True)  # the box only
        coords = jnp.full((cap, 3), UNUSED, jnp.int32).at[:n].set(jnp.where(inside, vox.coords[:n], UNUSED))
        triangle = jnp.full(cap, UNUSED, jnp.int32).at[:n].set(vox.triangle[:n])
    return _unsigned(tris, coords, triangle, shape=shape, method=method, band=band, sweeps=sweeps, clamped=clamped)


# ----------------------------------------------------------------- 16-bit output


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class QuantizedField:
    """A distance field stored in 16 bits per voxel, in units of the voxel size.

    `format` is static (changing it recompiles).

    Attributes:
      values: [R, R, R] float16 (distance / h) or int16 (round(distance / h * steps)).
      voxel_size: [] float32 h, world units.
      steps_per_voxel: [] float32 fixed-point steps per voxel (1 for float16).
      format: "float16" or "fixed16".
    """

    values: jax.Array  # [R, R, R] float16 or int16
    voxel_size: jax.Array  # [] float32
    steps_per_voxel: jax.Array  # [] float32
    format: str = dataclasses.field(metadata=dict(static=True))

    def decode(self) -> jax.Array:
        """The field in world units: [R, R, R] float32."""
        return self.values.astype(jnp.float32) / self.steps_per_voxel * self.voxel_size


def quantize_field(field: jax.Array, grid: Grid, *, format: str = "fixed16",
                   steps_per_voxel: int = 256) -> QuantizedField:
    """Stores a field [R, R, R] float32 (world units) in 16 bits per voxel; jittable.

    * "float16": distance in voxels as float16; error at most 2^-11 of the value
      (0.25 voxel at 512-1024 voxels away), inf kept.
    * "fixed16": int16 steps of 1/`steps_per_voxel` voxel; error at most half a
      step below ``32767 / steps_per_voxel`` voxels (128 voxels at 256 steps), and
      values beyond saturate there (still a safe step for sphere tracing).

    The error a field actually costs: ``abs(q.decode() - field) / grid.voxel_size``.

    Raises:
      JaxvoxError: not a `Grid`, an unknown format, a field not of the grid's shape, or
        (when concrete) `steps_per_voxel` not a finite number > 0.
    """
    check_type("quantize_field grid", grid, Grid)
    check_choice("quantize_field format", format, FORMATS)
    if np.shape(field) != (grid.resolution,) * 3:
        raise refuse("quantize_field field", f"must have the grid's shape {(grid.resolution,) * 3}", np.shape(field))
    if is_concrete(steps_per_voxel):
        check_number("quantize_field steps_per_voxel", steps_per_voxel, above=0.0)
    voxels = field / grid.voxel_size
    if format == "float16":
        return QuantizedField(voxels.astype(jnp.float16), grid.voxel_size, jnp.float32(1.0), format)
    steps = jnp.float32(steps_per_voxel)
    codes = jnp.clip(jnp.round(jnp.clip(voxels, -1e9, 1e9) * steps), -32767, 32767).astype(jnp.int16)
    return QuantizedField(codes, grid.voxel_size, steps, format)


# ------------------------------------------------------------ cascaded clipmap

_RUNNING = -1  # `trace_clipmap` status while marching (statuses are `jaxvox.trace`'s)


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class Clipmap:
    """N cascades of R^3 voxels centred on a moving point, stored toroidally.

    Cascade c has voxels of edge ``h_c = voxel_size * 2^c`` on the lattice
    ``origin + g * h_c`` (g integer); its window is ``corner[c] <= g < corner[c] + R``
    and lattice voxel g lives in slot ``g mod R`` (per axis), so a move rewrites only
    the newly exposed slabs. A voxel holds the signed distance from its centre to the
    whole mesh, clamped to ``truncation * h_c`` (negative inside).

    A move exposes at most three slabs per cascade (disjoint boxes, one per axis that
    moved; the whole window when nothing is shared); only they are computed and written.
    With ``method="exact"`` a voxel's value is a function of its position only (the
    brute-force distance, the generalized winding number for the sign), so any sequence
    of moves gives the same cascade as a build from scratch. With a `distance_field`
    method (e.g. "jfa+sweep", the seed's pipeline) each slab is a *scissor volume*: the
    pipeline runs on the slab grown by ``truncation + 1`` voxels on every side, from the
    faces near it (every face within the clamp of a slab voxel is in the grown box), and
    the sign is the solid voxelization of the slab (parity for watertight meshes, else
    winding numbers) from the whole mesh. A build from scratch is the same computation
    on the whole window. With ``"band"`` (the default) the pipeline is the narrow band
    alone, ``truncation + 1`` passes from the surface voxels of the grown box only: a
    voxel's value then depends on the seeds within that many voxels, all inside the
    grown box whatever the box, so an incremental clipmap equals a scratch build up to
    float32 rounding of the box-relative coordinates. With the other methods (jump
    flooding over the whole box, sweeps) the two differ by where the method's error falls
    (both are within it of the exact field).
    `truncation` and `method` are static.

    Attributes:
      fields: [N, R, R, R] float32 world units, toroidal slots.
      corner: [N, 3] int32 lattice index of each window's minimum voxel.
      origin: [3] float32 world position of lattice point 0.
      voxel_size: [] float32 edge of the finest cascade's voxels.
      truncation: static float, clamp in voxels of the cascade.
      method: static str, how exposed voxels are computed ("exact" or a
        `distance_field` method).
    """

    fields: jax.Array  # [N, R, R, R] float32
    corner: jax.Array  # [N, 3] int32
    origin: jax.Array  # [3] float32
    voxel_size: jax.Array  # [] float32
    truncation: float = dataclasses.field(metadata=dict(static=True))
    method: str = dataclasses.field(default="exact", metadata=dict(static=True))

    @property
    def resolution(self) -> int:
        """Voxels per axis R of every cascade."""
        return self.fields.shape[-1]

    @property
    def num_cascades(self) -> int:
        """Number of cascades N."""
        return self.fields.shape[-4]


def clipmap_corners(camera, origin, voxel_size, resolution: int, num_cascades: int) -> np.ndarray:
    """Window corners [N, 3] int32 centring each cascade on `camera` (snapped to its voxels).

    Raises:
      JaxvoxError: `camera` or `origin` not three finite numbers, `voxel_size` not a
        finite number > 0, a bad resolution, `num_cascades` not an integer >= 1.
    """
    check_vector("clipmap_corners camera", camera, 3)
    check_vector("clipmap_corners origin", origin, 3)
    voxel_size = check_number("clipmap_corners voxel_size", voxel_size, above=0.0)
    resolution = check_resolution(resolution)
    num_cascades = check_int("clipmap_corners num_cascades", num_cascades, minimum=1)
    h = voxel_size * 2.0 ** np.arange(num_cascades)[:, None]
    g = np.floor((np.asarray(camera, np.float64) - np.asarray(origin, np.float64)) / h)
    return (g - resolution // 2).astype(np.int32)


@jax.jit
def _cascade_values(points, tris, limit):
    """Signed distances clamped to +-limit at world points [n, 3] (triangles [F, 3, 3] world)."""
    d = _mesh_distance(points, tris)
    inside = _winding_numbers(points, tris) > 0.5
    d = jnp.minimum(d, limit)
    return jnp.where(inside, -d, d)


def _exposed_boxes(old, new, resolution: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Disjoint lattice boxes ``[lo, hi)`` covering window `new` minus window `old`
    (windows of `resolution`^3 voxels given by their corners [3]): a slab per axis that
    moved, each slab cut off from the earlier ones; one box when nothing is shared."""
    old, new = np.asarray(old, np.int64), np.asarray(new, np.int64)
    lo, hi = new.copy(), new + resolution
    if np.any(np.abs(new - old) >= resolution):
        return [(lo, hi)]
    boxes = []
    for axis in range(3):
        box_lo, box_hi = lo.copy(), hi.copy()
        if new[axis] > old[axis]:  # exposed above the old window
            box_lo[axis] = hi[axis] = old[axis] + resolution
        elif new[axis] < old[axis]:  # exposed below it
            box_hi[axis] = lo[axis] = old[axis]
        else:
            continue
        boxes.append((box_lo, box_hi))
    return boxes


def _near_faces(mesh: Mesh, bounds, lo, hi) -> Mesh | None:
    """The faces of `mesh` whose bounding boxes (`bounds`: [2, F, 3] float64 minima and
    maxima) touch the world box [lo, hi] [3], with only their vertices (so that padding
    faces sit on them); None if there are none."""
    near = np.all((bounds[0] <= hi) & (bounds[1] >= lo), axis=1)
    if not near.any():
        return None
    used, faces = np.unique(np.asarray(mesh.faces)[near], return_inverse=True)
    return Mesh(np.asarray(mesh.vertices)[used], faces.reshape(-1, 3).astype(np.int32))


def _scissor_values(mesh: Mesh, padded: Mesh, bounds, lo, hi, h: float, clip: Clipmap, sign: str):
    """Clamped signed distances [hi - lo] of the lattice box [lo, hi) of voxels of edge h.

    The scissor volume: `clip.method`'s pipeline runs on the box grown by the truncation
    plus one voxel on every side, from the faces near that grown box only (a farther face
    is beyond the clamp from every voxel of the box); the sign is the solid voxelization
    of the box itself from the whole mesh. Box sides are rounded up so that moves share
    compiled code: a side longer than R/2 to R (plus the margins), a shorter one to
    the power of two above it (`bucket`).
    """
    origin = np.asarray(clip.origin, np.float64)
    size = tuple(int(n) for n in hi - lo)
    margin = math.ceil(clip.truncation) + 1
    r = clip.resolution
    side = lambda n, pad: r + pad if 2 * n > r else bucket(n + pad, 4)
    shape = tuple(side(n, 2 * margin) for n in size)
    corner = origin + (lo - margin) * h
    limit = np.float32(clip.truncation * h)
    near = _near_faces(mesh, bounds, corner - h, corner + (np.asarray(shape) + 1) * h)
    if near is None:
        d = jnp.full(size, limit)
    else:
        band = margin if clip.method == "band" else int(clip.method == "jfa+sweep")
        d = _box_distance(near, _box_grid(corner, h, shape), shape, method=clip.method, band=band, sweeps=3,
                          clamped=clip.method != "band")
        d = jnp.minimum(d[margin: margin + size[0], margin: margin + size[1], margin: margin + size[2]] * h, limit)
    sign_shape = tuple(side(n, 0) for n in size)
    grid = _box_grid(origin + lo * h, h, sign_shape)
    inside = _solid(mesh, _grid_triangles(padded, grid), grid, sign_shape, sign, 2.0)
    return jnp.where(inside[: size[0], : size[1], : size[2]], -d, d)


def _refresh(fields, mesh: Mesh, padded: Mesh | None, cascade: int, old, new, clip: Clipmap, sign: str):
    """Writes the voxels of cascade `cascade` in window `new` that window `old` lacks
    (`padded`: `_padded(mesh)`, None without faces; `sign`: the solid voxelization method
    for pipeline methods)."""
    r = fields.shape[-1]
    h = float(clip.voxel_size) * 2.0**cascade
    limit = np.float32(clip.truncation * h)
    boxes = _exposed_boxes(old, new, r)
    if padded is not None and clip.method != "exact":
        tris = np.asarray(mesh.triangles(), np.float64)
        bounds = np.stack([tris.min(1), tris.max(1)])  # [2, F, 3]: once per cascade, not per box
    for lo, hi in boxes:
        slots = np.ix_(*(np.mod(np.arange(a, b), r) for a, b in zip(lo, hi)))
        if padded is None:  # no triangles: everything is far outside
            values = jnp.full(tuple(hi - lo), limit)
        elif clip.method == "exact":
            g = np.stack(np.meshgrid(*(np.arange(a, b) for a, b in zip(lo, hi)), indexing="ij"), -1).reshape(-1, 3)
            n = len(g)
            centres = np.zeros((bucket(n, 256), 3), np.float32)
            centres[:n] = np.asarray(clip.origin, np.float64) + (g + 0.5) * h
            values = _cascade_values(jnp.asarray(centres), padded.triangles(), jnp.float32(limit))[:n].reshape(hi - lo)
        else:
            values = _scissor_values(mesh, padded, bounds, lo, hi, h, clip, sign)
        fields = fields.at[(cascade,) + slots].set(values)
    return fields


def build_clipmap(mesh: Mesh, camera, *, resolution: int, num_cascades: int, voxel_size: float,
                  origin=(0.0, 0.0, 0.0), truncation: float = 8.0, method: str = "band") -> Clipmap:
    """A clipmap around `camera` built from scratch (every voxel of every cascade).

    Host-side. With ``method="exact"`` exposed voxels get brute-force point-triangle
    distances and winding numbers over all triangles (O(voxels * F): a build costs
    N R^3 F pairs, a move only the exposed slabs'). With a `distance_field` method each
    exposed slab costs a distance field of the slab grown by ``truncation + 1`` voxels
    per side, from the faces near it (see `Clipmap`); a build is one such field of
    ``(R + 2 truncation + 2)^3`` per cascade. Measured on spot (experiments/
    clipmap_updates.py, 32^3 and 64^3 cascades): "band" and "jfa" within 0.42 voxel of
    the exact clamped value, "jfa+sweep" within 0.78 (the tests allow 0.75, 0.5 and 3.25).

    Args:
      mesh: `Mesh` (validated).
      camera: [3] world position the cascades centre on.
      resolution: R, voxels per axis of each cascade (a power of two).
      num_cascades: N >= 1; cascade c has voxels of `voxel_size` * 2^c.
      voxel_size: finest voxel edge, world units.
      origin: [3] world position of the lattice shared by all cascades.
      truncation: distances are clamped to this many voxels of their cascade.
      method: "exact" or one of `distance_field`'s methods (static in the result).

    Returns:
      `Clipmap` with fields [N, R, R, R] float32 (4 N R^3 bytes).

    Raises:
      JaxvoxError: a malformed mesh, a bad camera, placement, resolution, cascade count,
        truncation or method.
    """
    validate_mesh(mesh)
    r = Grid(origin, voxel_size, resolution).resolution  # checks the placement and resolution
    num_cascades = check_int("build_clipmap num_cascades", num_cascades, minimum=1)
    check_vector("build_clipmap camera", camera, 3)
    truncation = check_number("build_clipmap truncation", truncation, above=0.0)
    far = np.full((num_cascades, 3), np.iinfo(np.int32).min // 2, np.int32)  # nothing in common
    empty = Clipmap(jnp.zeros((num_cascades, r, r, r), jnp.float32), jnp.asarray(far),
                    jnp.asarray(origin, jnp.float32), jnp.float32(voxel_size), float(truncation),
                    check_choice("build_clipmap method", method, METHODS))
    return update_clipmap(empty, mesh, camera)


def update_clipmap(clip: Clipmap, mesh: Mesh, camera, *, cascades=None) -> Clipmap:
    """Re-centres cascades on `camera`, recomputing only the newly exposed voxels.

    Host-side. Toroidal storage: voxels seen by both the old and the new window stay
    in their slots untouched; no data is copied.

    Args:
      clip: the current `Clipmap`.
      mesh: the (static) scene `Mesh`.
      camera: [3] world position.
      cascades: indices of the cascades to update this frame (default all); with
        `time_sliced_cascades` at most one cascade is updated per frame.

    Returns:
      The updated `Clipmap`; cascades not updated keep their window.

    Raises:
      JaxvoxError: not a `Clipmap`, a malformed mesh, a bad camera, or cascades that are
        not indices of the clipmap's cascades.
    """
    check_type("update_clipmap clip", clip, Clipmap)
    validate_mesh(mesh)
    check_vector("update_clipmap camera", camera, 3)
    if cascades is None:
        cascades = range(clip.num_cascades)
    elif not isinstance(cascades, (list, tuple, range, np.ndarray)):
        raise refuse("update_clipmap cascades", "must be a sequence of cascade indices", cascades)
    for c in cascades:
        check_int("update_clipmap cascades", c, minimum=0, maximum=clip.num_cascades - 1)
    new = clipmap_corners(camera, clip.origin, clip.voxel_size, clip.resolution, clip.num_cascades)
    corner = np.asarray(clip.corner).copy()
    fields = clip.fields
    padded = _padded(mesh) if mesh.num_faces else None
    sign = "winding" if clip.method == "exact" or open_edges(mesh) else "parity"
    for c in cascades:
        fields = _refresh(fields, mesh, padded, c, corner[c], new[c], clip, sign)
        corner[c] = new[c]
    return dataclasses.replace(clip, fields=fields, corner=jnp.asarray(corner))


def time_sliced_cascades(frame: int, num_cascades: int) -> tuple[int, ...]:
    """The cascades to update at `frame`: the finest on even frames, the others in turn
    on odd frames (as in the thread), so at most one cascade is rebuilt per frame.

    Raises:
      JaxvoxError: `frame` not an integer >= 0, `num_cascades` not an integer >= 1.
    """
    frame = check_int("time_sliced_cascades frame", frame, minimum=0)
    num_cascades = check_int("time_sliced_cascades num_cascades", num_cascades, minimum=1)
    if frame % 2 == 0 or num_cascades == 1:
        return (0,)
    return (1 + (frame // 2) % (num_cascades - 1),)


def union_clipmaps(a: Clipmap, b: Clipmap) -> Clipmap:
    """Union of two scenes' clipmaps with the same windows (e.g. static scene and dynamic
    objects rebuilt each frame): the pointwise min of their fields; jittable.

    Raises:
      JaxvoxError: not two `Clipmap` objects, fields of different shapes, or (when
        concrete) different window corners.
    """
    check_type("union_clipmaps a", a, Clipmap)
    check_type("union_clipmaps b", b, Clipmap)
    if a.fields.shape != b.fields.shape:
        raise refuse("union_clipmaps b", f"must have fields of a's shape {a.fields.shape}", b.fields.shape)
    if is_concrete(a.corner) and is_concrete(b.corner) and np.any(np.asarray(a.corner) != np.asarray(b.corner)):
        raise refuse("union_clipmaps b", f"must have a's windows (corners {np.asarray(a.corner).tolist()})",
                     b.corner)
    return dataclasses.replace(a, fields=jnp.minimum(a.fields, b.fields))


def _sample(clip: Clipmap, c, p):
    """Trilinear value of cascade c at world point p [3]; and whether p is inside its volume."""
    r = clip.resolution
    h = clip.voxel_size * 2.0 ** c.astype(jnp.float32)
    q = (p - clip.origin) / h - 0.5 - clip.corner[c]  # window-relative, centres at integers
    inside = jnp.all((q >= 0) & (q <= r - 1))
    base = jnp.clip(jnp.floor(q), 0, r - 2).astype(jnp.int32)
    f = jnp.clip(q - base, 0.0, 1.0)
    value = 0.0
    for corner in np.ndindex(2, 2, 2):
        o = jnp.asarray(corner, jnp.int32)
        slot = jnp.mod(clip.corner[c] + base + o, r)
        w = jnp.prod(jnp.where(o == 1, f, 1.0 - f))
        value = value + w * clip.fields[c, slot[0], slot[1], slot[2]]
    return value, inside, h


def trace_clipmap(clip: Clipmap, origins: jax.Array, directions: jax.Array, *, max_steps: int = 512,
                  t_max: float = np.inf, hit_voxels: float = 0.05):
    """Sphere tracing through the cascades; pure and jittable.

    Each ray starts in the finest cascade and steps by the (trilinear) distance until
    the distance falls below `hit_voxels` voxels of the current cascade (a hit). When
    it stands outside the current cascade's volume, or the step would take it out, it
    moves to the next coarser cascade *without advancing*, so each cascade needs only
    its own geometry; leaving the coarsest cascade is a miss.

    Args:
      clip: `Clipmap`.
      origins, directions: [n, 3] float32 world rays (directions need not be unit).
      max_steps: static step cap per ray (hitting it gives `STEP_CAP`).
      t_max: rays are misses beyond this distance (world units).
      hit_voxels: hit threshold in voxels of the current cascade.

    Returns:
      (t [n] float32 ray parameter of the hit (world units along the unit direction),
      status [n] int32 HIT / MISS / STEP_CAP,
      cascade [n] int32 cascade where the ray stopped).

    Raises:
      JaxvoxError: not a `Clipmap`, rays that are not both [n, 3], `max_steps` not an
        integer >= 1, or (when concrete) a NaN `t_max` or a `hit_voxels` that is not a
        finite number >= 0.
    """
    check_type("trace_clipmap clip", clip, Clipmap)
    if np.ndim(origins) != 2 or np.shape(origins)[1] != 3 or np.shape(directions) != np.shape(origins):
        raise refuse("trace_clipmap origins, directions", "must both have shape [n, 3]",
                     (np.shape(origins), np.shape(directions)))
    max_steps = check_int("trace_clipmap max_steps", max_steps, minimum=1)
    if is_concrete(t_max):
        check_number("trace_clipmap t_max", t_max, finite=False)
    if is_concrete(hit_voxels):
        check_number("trace_clipmap hit_voxels", hit_voxels, minimum=0.0)
    last = clip.num_cascades - 1

    def one(o, d):
        d = d / jnp.linalg.norm(d)

        def cond(state):
            return (state[3] == _RUNNING) & (state[2] < max_steps)

        def body(state):
            t, c, steps, status = state
            p = o + t * d
            value, inside, h = _sample(clip, c, p)
            _, inside_next, _ = _sample(clip, c, p + jnp.maximum(value, 0.0) * d)
            hit = inside & (value < hit_voxels * h)
            coarser = (~inside | ~inside_next) & ~hit & (c < last)
            escaped = ~inside & ~hit & (c == last)
            t_new = jnp.where(hit | coarser | escaped, t, t + value)
            status = jnp.where(hit, HIT, jnp.where(escaped | (t_new > t_max), MISS, _RUNNING))
            return t_new, c + coarser.astype(jnp.int32), steps + 1, status

        t, c, _, status = jax.lax.while_loop(cond, body, (jnp.float32(0.0), jnp.int32(0), jnp.int32(0), jnp.int32(_RUNNING)))
        return t, jnp.where(status == _RUNNING, STEP_CAP, status), c

    return jax.vmap(one)(jnp.asarray(origins, jnp.float32), jnp.asarray(directions, jnp.float32))
