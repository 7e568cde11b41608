"""Signs of band voxels (`jaxvox.distance.sparse`): inside where the generalized winding number
of the mesh exceeds 1/2, negative inside.

Two methods, both exact (the float64 brute-force winding number is the reference):

* **Pseudo-normals.** For a watertight mesh whose triangles neither cross one another
  (`jaxvox.distance.topology.crossing_faces`) nor have an irregular edge, a pinched
  vertex, zero area, a sliver (`SLIVER`, the sides of a thin slab) or a fold (two faces
  at an edge within `FOLD` of facing each other), and none of whose shells winds around
  another (`nested_shells`: between two nested spheres of the same orientation the
  winding number is 1, but the closest surface is the inner sphere, seen from outside).
  Where two sheets of the surface come closer than the float32 kernel's rounding, as at
  a fold or across a thin slab, it cannot tell which is closer, and the two face opposite
  ways. The sign is the side of the angle-weighted
  pseudo-normal (Baerentzen & Aanaes 2005) of the closest feature of the voxel's closest
  triangle (the face normal when the closest point is interior to the face, the sum of
  the two face normals for an edge, the angle-weighted normal sum for a vertex; vertices
  welded by position).

* **Components** (every other mesh: holes like the bunny's base, crossings like the
  teapot's handle, irregular edges). The mesh's boundary, as a chain of directed edges, is
  closed by *caps*: for each connected piece of it, a fan of triangles from the mean of its
  vertices. The winding number ``W`` of mesh plus caps is then an integer, constant on each
  connected part of space minus mesh and caps, and the mesh's own winding number is
  ``w = W - w_caps``. Band voxels are joined into components by moves that cross neither
  mesh nor caps:

  - two 6-neighbours a, b whose unsigned distances (grid units) satisfy
    ``d(a) + d(b) > 1`` and likewise for the caps (a crossing at x would give
    ``d(a) + d(b) <= |a - x| + |x - b| = 1``);
  - voxels with the same closest triangle on the same side of its pseudo-normal (each
    reaches the triangle's side through its empty ball, then runs along it), and the same
    sides of two triangles sharing a regular edge, for *free* triangles: none within one
    ring of faces crosses another, has an irregular edge, a pinched vertex or zero area,
    and every point within ``band`` of the triangle lies more than a move (1 voxel) from
    every cap.

  One winding number per component (at its voxel farthest from mesh and caps: the fast
  tree's `jaxvox.distance.winding.point_winding_numbers`, or a brute-force sum when the
  components are few, below `TREE_PAIRS` point-triangle pairs) plus the exact cap term,
  rounded, gives its ``W``.
  Each voxel then takes ``w = W - w_caps``: the cap term is summed exactly (brute force
  over the cap triangles) unless a bound keeps it below `CAP_BOUND`, in which case
  ``w = W``. The bound, per triangle: a cap of area A_k inside the ball of radius r_k
  about c_k adds at most ``A_k / (4 pi (|p - c_k| - r_k)^2)``; where that is not small,
  the exact term at the closest triangle's centroid plus the reach times a bound on its
  gradient. Voxels whose triangle fails it, and those within a move of a cap by their
  triangle's bound, are tried again by aligned blocks of 4^3, then 2^3 voxels
  (`Components.blocked_cap_terms`): the exact term and cap distance at the block's
  centre, with the block's radius times a Biot-Savart bound on the gradient (the caps'
  boundary is the mesh's boundary chain) where the block's ball misses the caps. On the
  bunny at 1024^3, 60 K voxels take exact terms this way, where 1.1 M did with a bound
  per triangle. A component whose voxels all lie within 1/2 voxel of mesh or caps
  (voxels on the surface are alone) is evaluated voxel by voxel: its W from the fast
  tree plus the exact cap term, rounded, less the cap term. Winding numbers within
  `CLOSE` of 1/2 are summed again by brute force (in float64 within
  `jaxvox.distance.winding.F32_CLOSE`). The bunny at 256^3 (897 K band voxels) takes 2
  components and about 900 voxels on their own this way, where one winding number per
  (triangle, side) and per voxel near a hole took 264 K.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox import morton
from jaxvox._core.geometry import (
    centroids,
    farthest_corners,
    rows_dist2,
    solid_angle_parts,
    squared_lengths,
    triangle_rows,
)
from jaxvox._core.shapes import bucket, chunk_rows, pad_rows
from jaxvox.distance.topology import (
    EdgeTable,
    boundary_chain,
    connected_components,
    crossing_faces,
    edge_table,
    irregular_edge_faces,
    pinched_vertex_faces,
    regular_edge_pairs,
    welded_faces,
)
from jaxvox.distance.winding import (
    PointTree,
    brute_force_winding_numbers,
    exact_winding_numbers,
    host_winding_numbers,
    point_tree,
    point_winding_numbers,
    relative_corners,
    triangle_blocks,
)
from jaxvox.mesh import Mesh

POINT_CHUNK = 1 << 16  # band voxels per call of the sign kernels (fewer dispatches than 2^14)
FEWER_POINTS = 64  # a job below POINT_CHUNK runs in chunks this many times smaller (a region's cap terms: a few dozen)
EXACT_BELOW = 0.1  # fast winding numbers this close to 1/2 are summed again by brute force
TREE_PAIRS = 1 << 23  # (point, triangle) pairs below which a job's winding numbers are summed by brute force
BRUTE_CHUNK = 256  # points per call of that brute force (one program per mesh size, as the tree's)
CLOSE = 1e-3  # exact winding numbers (W minus the cap term) this close to 1/2 likewise
CAP_BLOCK = 32  # cap triangles per step of the caps' kernel (a mesh's holes often have a few dozen)
CAP_BOUND = 0.45  # the cap term is summed exactly unless its bound stays below this (< 1/2)
MOVE = 1.0 + 1e-3  # d(a) + d(b) beyond this certifies that a 6-neighbour move crosses nothing
ON_SURFACE = 1e-3  # voxels this close (grid units) to the caps are evaluated alone; to the mesh, sides in float64
ON_MESH = 1e-6  # voxels this close (grid units, float64) to the mesh have no certain side: evaluated alone
REFINE_EDGE = 128.0  # voxels whose closest triangle is longer (grid units) get float64 distances
F32_ERROR = 5e-7  # measured error of the float32 distance kernel per grid unit of the closest triangle's longest edge
SIDE_REFINE = 8 * F32_ERROR  # sides in float64 where the distance is below this times that edge
FOLD = 1e-3  # faces at an edge with 1 + n1 . n2 below this (within about 2.6 degrees) are suspect
SLIVER = 1e-4  # faces whose altitude is below this times their longest edge are suspect
BLOCK_BITS = (2, 1)  # cap terms and distances are bounded by aligned blocks of 4^3 voxels, then 2^3
_FAR = np.float32(1e9)  # corner of the padding cap triangles (zero area, far away)


def closest_feature(p, a, b, c, xp=jnp):
    """Closest point region of triangles (a, b, c) to points p (Ericson), each a tuple of
    its (x, y, z) float32 arrays (broadcast; no [..., 3] axis, which XLA's CPU code handles
    slowly); with ``xp=numpy``, host arrays (float64 in `exact_closest`).

    Returns:
      [...] int32: 0 face interior, 1 edge ab, 2 edge bc, 3 edge ca, 4 vertex a,
      5 vertex b, 6 vertex c; and the closest point, a tuple of (x, y, z) arrays.
    """
    sub = lambda x, y: tuple(xi - yi for xi, yi in zip(x, y))
    dot = lambda x, y: x[0] * y[0] + x[1] * y[1] + x[2] * y[2]
    along = lambda o, t, e: tuple(oi + t * ei for oi, ei in zip(o, e))
    ab, ac, ap = sub(b, a), sub(c, a), sub(p, a)
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = sub(p, b)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = sub(p, c)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    safe = lambda x: xp.where(x != 0, x, 1.0)
    den = safe(va + vb + vc)
    face = tuple(ai + (vb / den) * bi + (vc / den) * ci for ai, bi, ci in zip(a, ab, ac))
    cases = [  # (condition, region, point), first match wins (Ericson's order)
        ((d1 <= 0) & (d2 <= 0), 4, a),
        ((d3 >= 0) & (d4 <= d3), 5, b),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1, along(a, d1 / safe(d1 - d3), ab)),
        ((d6 >= 0) & (d5 <= d6), 6, c),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), 3, along(a, d2 / safe(d2 - d6), ac)),
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), 2, along(b, (d4 - d3) / safe(d4 - d3 + d5 - d6), sub(c, b))),
    ]
    region = xp.zeros(xp.shape(d1), xp.int32)
    point = face
    for cond, r, q in reversed(cases):
        region = xp.where(cond, r, region)
        point = tuple(xp.where(cond, qi, pi) for qi, pi in zip(q, point))
    return region, point


def exact_closest(tris: np.ndarray, ijk: np.ndarray, tri: np.ndarray):
    """Float64 closest points of voxel centres ijk [n, 3] (grid units, centres at
    ijk + 1/2) on their triangles tri [n] of tris [F, 3, 3] float64 (host): (region [n]
    int32 as in `closest_feature`, offset [n, 3] float64 centre minus closest point).

    The float32 kernels lose up to about `F32_ERROR` voxel per voxel of a triangle's
    longest edge (their coordinates are that large); this is the reference they are
    refined with where that matters (`REFINE_EDGE`, `SIDE_REFINE`)."""
    p = ijk.astype(np.float64) + 0.5
    t = tris[tri]
    a, b, c = (tuple(t[:, i].T) for i in range(3))
    region, q = closest_feature(tuple(p.T), a, b, c, xp=np)
    return region, p - np.stack(q, -1)


@jax.jit
def _behind(ijk, tri, corners, normals):
    """Whether each voxel is behind (inside) the pseudo-normal of its closest feature, [P]
    bool.

    ijk [P, 3] int32 voxels (centres at ijk + 1/2, grid units), tri [P] int32 their
    closest triangles, corners [9, F] float32 rows a_xyz, b_xyz, c_xyz of the triangles
    (grid units), normals [3, 7 F] float32 xyz rows of the feature normals (7 per face:
    face, edges ab bc ca, vertices a b c).
    """
    t = jnp.maximum(tri, 0)
    p = tuple(ijk[:, k].astype(jnp.float32) + 0.5 for k in range(3))
    a, b, c = (tuple(corners[3 * i + k][t] for k in range(3)) for i in range(3))
    region, q = closest_feature(p, a, b, c)
    n = tuple(normals[k][7 * t + region] for k in range(3))
    return sum((pk - qk) * nk for pk, qk, nk in zip(p, q, n)) < 0


@functools.partial(jax.jit, static_argnames="distance")
def _cap_terms(points, blocks, rows, radius, *, distance: bool):
    """Winding number [P] float32 at points [P, 3] of the cap triangles `blocks`
    (`jaxvox.distance.winding.TriangleBlocks` of the corners' xyz rows, `split_rows`; each
    a fan triangle (centre, b, a) over a boundary edge a -> b), and with `distance` also
    the squared distance [P] float32 to the nearest of them (`rows`: the same blocks of
    their `triangle_rows`), both relative to the points, and the bound [P] float32 on the
    term's gradient in the ball of radius `radius` ([] float32) about each point (inf
    where a boundary edge comes that close; see `Components.blocked_cap_terms`). One
    program gives distances with and without the bound: the bound costs little beside
    the distances, and a program of its own cost a compile on a mesh's first call."""
    p = [points[None, :, k] for k in range(3)]  # points along the minor axis (as `winding._brute_force`)
    zero = [jnp.float32(0)] * 3

    def step(i, carry):
        w, d2, bound = carry
        corners, tri_rows = blocks.rows[i], rows.rows[i]
        w = w + jnp.sum(solid_angle_parts(*relative_corners(corners[:, :, None], p)), 0)  # [block, P] summed
        if distance:
            near2, edge2 = rows_dist2(zero, list(tri_rows[:, :, None]), p, edge_bc=True)
            d2 = jnp.minimum(d2, jnp.min(near2, 0))
            # The bound: over the boundary edges a -> b (each fan triangle's edge bc), the sum
            # of len / (4 pi gap^2), gap = distance to the edge - radius.
            inverse = tri_rows[26, :, None]  # 1 / |bc|^2, 0 for a point edge
            length = jnp.where(inverse > 0, jax.lax.rsqrt(jnp.where(inverse > 0, inverse, 1.0)), 0.0)
            gap = jnp.sqrt(edge2) - radius
            term = length / (4 * jnp.pi * jnp.where(gap > 0, gap * gap, 1.0))
            bound = bound + jnp.sum(jnp.where(gap > 0, term, jnp.inf), 0)
        return w, d2, bound

    n = points.shape[0]
    start = (jnp.zeros(n, jnp.float32), jnp.full(n, jnp.inf, jnp.float32), jnp.zeros(n, jnp.float32))
    w, d2, bound = jax.lax.fori_loop(0, blocks.used, step, start)
    return (w, d2, bound) if distance else w


def longest_edges(tris: np.ndarray) -> np.ndarray:
    """[F] float64 longest edge of each triangle of tris [F, 3, 3]."""
    return np.sqrt(squared_lengths(tris - np.roll(tris, 1, axis=1)).max(1, initial=0.0))


def pseudo_normals(
    vertices: np.ndarray, faces: np.ndarray, welded: np.ndarray | None = None, edges: EdgeTable | None = None
) -> np.ndarray:
    """Angle-weighted pseudo-normals per face corner feature (host, float64 in, float32 out).

    Args:
      vertices: [V, 3] float; faces: [F, 3] int (consistently oriented, watertight).
      welded: `welded_faces(vertices, faces)`, and edges its `edge_table` (each computed
        when not given).

    Returns:
      [F, 7, 3] float32: the unit face normal, the edge normals of ab, bc, ca (sum of the
      adjacent faces' unit normals) and the vertex normals of a, b, c (sum of the incident
      faces' unit normals weighted by their corner angles). Vertices are welded by position.
    """
    v = np.asarray(vertices, np.float64)
    f = welded_faces(v, faces) if welded is None else welded
    tri = v[np.asarray(faces, np.int64)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    e1 = np.roll(tri, -1, axis=1) - tri  # [F, 3, 3] from each corner to the next
    e2 = np.roll(e1, 1, axis=1)  # minus the vector to the one after (the previous corner's e1)
    length = np.sqrt(squared_lengths(e1))
    cos = -np.einsum("fcj,fcj->fc", e1, e2) / np.maximum(length * np.roll(length, 1, axis=1), 1e-300)
    angle = np.arccos(np.clip(cos, -1, 1))  # [F, 3] corner angles
    vertex_n = _sums(f.T.reshape(-1), (angle.T[..., None] * n).reshape(-1, 3), int(f.max()) + 1 if f.size else 0)
    table = edge_table(f) if edges is None else edges  # each face corner's edge (ab, bc, ca): its run
    inverse = np.empty(3 * len(f), np.int64)
    inverse[3 * table.owner + table.side] = np.repeat(np.arange(len(table.start)), table.entries)
    edge_n = _sums(inverse, np.repeat(n, 3, axis=0), len(table.start))
    out = np.empty((len(f), 7, 3), np.float32)
    out[:, 0] = n
    out[:, 1:4] = edge_n[inverse].reshape(-1, 3, 3)
    out[:, 4:] = vertex_n[f]
    return out


def _sums(index: np.ndarray, rows: np.ndarray, size: int) -> np.ndarray:
    """[size, 3] float64 sums of rows [n, 3] by index [n] int, added in order (as
    ``np.add.at``, so the same float64 sums)."""
    return np.stack([np.bincount(index, rows[:, j], minlength=size) for j in range(3)], axis=1)


def _start_chunks(fn, rows, *rest) -> list:
    """Dispatches ``fn(*row chunks [POINT_CHUNK, ...], *rest)`` over all rows of `rows` (an
    array, or a tuple of arrays with the same first axis; smaller chunks for a small job,
    `chunk_rows`) without waiting: [(result, rows in the chunk)], for `_join_chunks`."""
    rows = rows if isinstance(rows, tuple) else (rows,)
    width = chunk_rows(len(rows[0]), POINT_CHUNK, FEWER_POINTS)
    started = []
    for s in range(0, len(rows[0]), width):
        parts = [r[s : s + width] for r in rows]
        started.append((fn(*(jax.device_put(pad_rows(x, width)) for x in parts), *rest), len(parts[0])))
    return started


def _join_chunks(started: list):
    """The results of `_start_chunks` (one array or a tuple each) as host arrays,
    concatenated over the chunks."""
    out = [tuple(np.asarray(r)[:m] for r in (res if isinstance(res, tuple) else (res,))) for res, m in started]
    if not out:
        return np.zeros(0, np.float32)
    joined = tuple(np.concatenate(x) for x in zip(*out))
    return joined if len(joined) > 1 else joined[0]


def _chunked(fn, rows, *rest):
    """``fn`` over all rows of `rows` in chunks (`_start_chunks`), joined on the host."""
    return _join_chunks(_start_chunks(fn, rows, *rest))


class Sides:
    """Which side of its closest feature's pseudo-normal each band voxel lies on: the
    float32 kernel (`_behind`), started while the voxels are still being found
    (`start`), then float64 where the float32 closest point may be on the wrong side
    (`finish`)."""

    def __init__(self, mesh: Mesh, tris: np.ndarray, edge: np.ndarray, welded: np.ndarray, edges: EdgeTable):
        """mesh: the `Mesh`; tris: [F, 3, 3] float64 its triangles in grid units; edge:
        [F] their `longest_edges`; welded: its `welded_faces`, edges their `edge_table`."""
        f = np.asarray(mesh.faces)
        rows = bucket(len(f))
        self.tris = tris
        self.feature_normals = pseudo_normals(np.asarray(mesh.vertices), f, welded, edges)  # [F, 7, 3] float32
        self.normals = jax.device_put(pad_rows(self.feature_normals, rows).reshape(-1, 3).T)
        self.corners = jax.device_put(pad_rows(tris.astype(np.float32), rows).reshape(rows, 9).T)
        # float64 sides where the float32 closest point may be on the wrong side, and for
        # every voxel within ON_SURFACE (its side decides whether it joins a component)
        self.limit = np.where(edge > REFINE_EDGE, np.inf, np.maximum(SIDE_REFINE * edge, ON_SURFACE)).astype(np.float32)

    def start(self, ijk: np.ndarray, tri: np.ndarray) -> list:
        """Starts the float32 sides of voxels ijk [m, 3] int with closest triangles tri
        [m] int (global ids); returns the pending chunks."""
        return _start_chunks(_behind, (ijk.astype(np.int32), tri.astype(np.int32)), self.corners, self.normals)

    def finish(self, started: list, ijk: np.ndarray, tri: np.ndarray, dist: np.ndarray):
        """The sides of voxels ijk [n, 3] (tri [n], unsigned distances dist [n] in grid
        units) whose kernels `start` began, in order, in `started` (a list of its
        results): (behind [n] bool: behind the closest feature's pseudo-normal, on [n]
        bool: within `ON_MESH` of the surface in float64, so that no side is certain)."""
        behind = _join_chunks([chunk for part in started for chunk in part])
        on = np.zeros(len(behind), bool)
        if np.isfinite(self.limit).all():  # a pass over dist alone first: its few voxels are then looked at
            refine = np.flatnonzero(dist < self.limit.max(initial=0))
            refine = refine[dist[refine] < self.limit[tri[refine]]]
        else:
            refine = np.flatnonzero(dist < self.limit[tri])
        if len(refine):
            region, offset = exact_closest(self.tris, ijk[refine], tri[refine])
            n = self.feature_normals[tri[refine], region].astype(np.float64)
            behind[refine] = np.einsum("ij,ij->i", offset, n) < 0
            on[refine] = np.einsum("ij,ij->i", offset, offset) < ON_MESH * ON_MESH
        return behind, on


def prepare_signs(
    tris: np.ndarray, welded: np.ndarray, edges: EdgeTable, edge: np.ndarray, band: int
) -> Callable[..., np.ndarray]:
    """The inside test of a mesh's band voxels (module docstring for the methods): what
    depends on the mesh alone (crossings, caps, free triangles, the winding tree)
    is computed here, once, so that the voxels can come in parts (regions).

    Args:
      tris: [F, 3, 3] float64 the mesh's triangles in grid units; welded: [F, 3] its
        `welded_faces`, edges their `edge_table`; edge: [F] the triangles'
        `longest_edges`; band: the half width.

    Returns:
      ``inside(ijk, keys, dist, tri, behind, on)``: whether each is inside ([n] bool) at
      band voxels ijk [n, 3] int (Morton order; any subset of the band, e.g. one
      region's), keys [n] uint64 their Morton codes, dist [n] float32 unsigned distance
      (grid units, at most `band`), tri [n] int closest triangle, behind and on [n] bool
      their sides (`Sides.finish`).
    """
    suspect, chain = _suspect_faces(tris, welded, edges, edge), boundary_chain(welded, edges)
    if not len(chain) and not suspect.any() and not nested_shells(tris, welded):
        return lambda ijk, keys, dist, tri, behind, on: behind
    return Components(tris, welded, suspect, chain, band, edges).inside


def _suspect_faces(tris: np.ndarray, welded: np.ndarray, edges: EdgeTable, edge: np.ndarray) -> np.ndarray:
    """[F] bool faces that may make pseudo-normal sides wrong: zero area, slivers (an
    altitude below `SLIVER` of the longest edge: the sides of a slab thinner than the
    float32 kernel's rounding, whose two large faces it cannot tell apart), crossings,
    irregular edges, pinched vertices, folds (triangles [F, 3, 3], welded faces and their
    edges, and the triangles' `longest_edges` [F])."""
    cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area2 = squared_lengths(cross)
    return (
        (area2 == 0)
        | (np.sqrt(area2) < SLIVER * edge * edge)  # |cross| / edge^2 is the altitude over the edge
        | crossing_faces(tris, welded)
        | irregular_edge_faces(welded, edges)
        | pinched_vertex_faces(welded, edges)
        | _folded_faces(cross / np.sqrt(np.where(area2 > 0, area2, 1.0))[:, None], regular_edge_pairs(welded, edges))
    )


def _folded_faces(normals: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """[F] bool the two faces of each regular edge (pairs [P, 2], `regular_edge_pairs`)
    whose sheets fold onto each other: unit normals [F, 3] (0 for zero area) with
    ``1 + n1 . n2 < FOLD``. Near such an edge the other sheet's triangle lies within the
    tile kernel's float32 rounding of the closest one and faces the other way, so the
    kernel may give a voxel the wrong one of the two (docs/design-history.md, "Two
    sheets closer than float32")."""
    fold = 1 + np.einsum("ij,ij->i", normals[pairs[:, 0]], normals[pairs[:, 1]]) < FOLD
    out = np.zeros(len(normals), bool)
    out[pairs[fold].reshape(-1)] = True
    return out


def pseudonormal_sides_exact(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether the pseudo-normal side of every point's closest feature is the side of the
    winding number (module docstring: watertight, no crossings, irregular edges, pinched
    vertices, zero-area faces, slivers, folds or nested shells). Host, float64; the boundary is checked
    first, so an open mesh costs no crossing test."""
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces)
    welded = welded_faces(vertices, faces)
    edges = edge_table(welded)
    if len(boundary_chain(welded, edges)):
        return False
    tris = vertices[faces]
    return not _suspect_faces(tris, welded, edges, longest_edges(tris)).any() and not nested_shells(tris, welded)


NESTED_WORK = 1 << 26  # (point, triangle) pairs `nested_shells` sums at most


def nested_shells(tris: np.ndarray, welded: np.ndarray) -> bool:
    """Whether a shell (faces joined by shared welded vertices) of a mesh winds around a
    vertex of another: float64 winding number of the shell at one vertex of each other
    shell inside its box, ``|w| > 1/2``. tris [F, 3, 3] float64, welded [F, 3] int
    (`welded_faces`). Meant for closed meshes whose shells do not cross (each one's winding
    number is then an integer off its surface); True, conservatively, when the pairs to
    sum exceed `NESTED_WORK`."""
    if not len(welded):
        return False
    shell = connected_components(int(welded.max()) + 1, welded[:, [0, 1]].ravel(), welded[:, [1, 2]].ravel())
    _, first, face_shell = np.unique(shell[welded[:, 0]], return_index=True, return_inverse=True)
    if len(first) == 1:
        return False
    lo = np.full((len(first), 3), np.inf)
    hi = np.full((len(first), 3), -np.inf)
    np.minimum.at(lo, face_shell, tris.min(1))
    np.maximum.at(hi, face_shell, tris.max(1))
    point = tris[first, 0]  # [S, 3] a vertex of each shell
    inside = np.all((point[None] >= lo[:, None]) & (point[None] <= hi[:, None]), -1)  # [around, point]
    np.fill_diagonal(inside, False)
    around, points = np.nonzero(inside)  # ordered by `around`
    sizes = np.bincount(face_shell)
    if int(sizes[around].sum()) > NESTED_WORK:
        return True
    faces = tris[np.argsort(face_shell, kind="stable")]  # shell by shell: each a slice, no mask over F
    first_face = np.cumsum(sizes) - sizes
    shells, first_pair = np.unique(around, return_index=True)
    for a, pairs in zip(shells, np.split(points, first_pair[1:])):
        if np.any(np.abs(host_winding_numbers(faces[first_face[a] : first_face[a] + sizes[a]], point[pairs])) > 0.5):
            return True
    return False


def _caps(tris: np.ndarray, welded: np.ndarray, chain: np.ndarray):
    """Fans closing the boundary chain: (triangles [C, 3, 3] float64, centre [K, 3], radius
    [K], area [K] of each connected piece of the chain)."""
    if not len(chain):
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0)
    position = np.zeros((int(welded.max()) + 1, 3))
    position[welded.reshape(-1)] = tris.reshape(-1, 3)
    piece = connected_components(len(position), chain[:, 0], chain[:, 1])[chain[:, 0]]
    _, piece = np.unique(piece, return_inverse=True)
    count = np.bincount(piece)
    centre = np.stack([np.bincount(piece, position[chain[:, 0], k]) for k in range(3)], 1) / count[:, None]
    a, b = position[chain[:, 0]], position[chain[:, 1]]
    fans = np.stack([centre[piece], b, a], 1)  # cancels a -> b
    radius = np.zeros(len(count))
    np.maximum.at(radius, piece, np.linalg.norm(a - centre[piece], axis=1))
    area = np.bincount(piece, 0.5 * np.linalg.norm(np.cross(b - centre[piece], a - centre[piece]), axis=1))
    return fans, centre, radius, area


def _cap_gaps(points: np.ndarray, reach: np.ndarray, centre: np.ndarray, radius: np.ndarray, area: np.ndarray):
    """For points [P, 3] standing for anything within `reach` [P] of them: (a lower bound
    [P] on the distance to every cap, an upper bound [P] on |w_caps| and one on the
    length of its gradient), in chunks of caps.

    A cap of area A at distance at least g adds at most ``A / (4 pi g^2)`` to |w_caps|
    (each element subtends at most its area over the squared distance) and
    ``2 A / (4 pi g^3)`` to its gradient (the gradient of the solid angle kernel
    ``n . (x - p) / |x - p|^3`` is at most ``2 / |x - p|^3`` long)."""
    gap = np.full(len(points), np.inf)
    bound = np.zeros(len(points))
    slope = np.zeros(len(points))
    for s in range(0, len(centre), 64):
        g = np.linalg.norm(points[:, None] - centre[None, s : s + 64], axis=-1) - radius[s : s + 64] - reach[:, None]
        gap = np.minimum(gap, g.min(1, initial=np.inf))
        safe = np.where(g > 0, g, 1.0)
        term = np.where(g > 0, area[s : s + 64] / (4 * np.pi * safe * safe), np.inf)
        bound += term.sum(1)
        slope += (2 * term / safe).sum(1)
    return gap, bound, slope


class Components:
    """Signs by components of mesh plus caps (module docstring): the mesh's caps, bounds
    and free triangles at construction, the voxels' components per call of `inside`."""

    def __init__(self, tris, welded, suspect, chain, band, edges: EdgeTable | None = None):
        """tris [F, 3, 3] float64 (grid units), welded [F, 3] faces, suspect [F] bool,
        chain the boundary chain, band the half width; edges the faces' `EdgeTable`
        (computed when not given)."""
        self.tris = tris
        caps, cap_centre, cap_radius, cap_area = _caps(tris, welded, chain)
        centroid = centroids(tris)
        tri_radius = farthest_corners(tris, centroid)
        reach = tri_radius + band  # a triangle's band voxels lie within this of its centroid
        tri_gap, tri_bound, tri_slope = _cap_gaps(centroid, reach, cap_centre, cap_radius, cap_area)
        self.has_caps = len(caps) > 0
        self.caps = caps  # [C, 3, 3] float64 fan triangles (centre, b, a) over the boundary edges a -> b
        self.blocks = triangle_blocks(caps, float(_FAR), block=CAP_BLOCK)  # padding far away: never the nearest
        self.rows = triangle_blocks(caps, float(_FAR), triangle_rows, CAP_BLOCK)  # the same blocks, for distances
        # Where the balls about the caps do not settle it: the exact cap term and distance
        # at the centroid, with the term's largest change within the reach.
        doubt = np.flatnonzero((tri_bound >= CAP_BOUND) | (tri_gap <= MOVE))
        if len(doubt):
            w, d2 = self.cap_terms(centroid[doubt], distance=True)
            gap = np.sqrt(d2) - reach[doubt]
            safe = np.where(gap > 0, gap, 1.0)
            slope = np.minimum(tri_slope[doubt], np.where(gap > 0, 2 * cap_area.sum() / (4 * np.pi * safe**3), np.inf))
            tri_gap[doubt] = np.maximum(tri_gap[doubt], gap)
            tri_bound[doubt] = np.minimum(tri_bound[doubt], np.abs(w) + reach[doubt] * slope)
        ring = np.zeros(int(welded.max()) + 1, bool)
        ring[welded[suspect].reshape(-1)] = True
        self.free = ~ring[welded].any(1) & (tri_gap > MOVE)
        gap32 = tri_gap.astype(np.float32)
        self.tri_gap32 = np.where(gap32 > tri_gap, np.nextafter(gap32, np.float32(-np.inf)), gap32)
        self.capped = tri_bound >= CAP_BOUND  # per triangle: the cap term is summed exactly
        pairs = regular_edge_pairs(welded, edges)
        pairs = pairs[self.free[pairs].all(1)]
        # The (triangle, side) nodes joined through the free triangles' regular edges, once
        # for every region: a region's components are these, joined by its voxels' moves.
        u, v = 2 * pairs, 2 * pairs + 1
        self.side_label = connected_components(
            2 * len(tris), np.concatenate([u[:, 0], v[:, 0]]), np.concatenate([u[:, 1], v[:, 1]])
        )
        self.tree: PointTree | None = None  # the fast winding tree, built for the first job too large for brute force
        self.mesh_blocks = triangle_blocks(tris, 0.0)

    def _mesh_winding_numbers(self, points: np.ndarray) -> np.ndarray:
        """The mesh's winding numbers [P] float32 at points [P, 3] (grid units): summed by
        brute force when the (point, triangle) pairs are below `TREE_PAIRS` (a small grid's
        few components: cheaper than building the tree), else by the fast tree (its error
        reaches a few 1e-2), built at the first such job and kept for the next regions'."""
        if len(points) * len(self.tris) < TREE_PAIRS:
            return brute_force_winding_numbers(self.tris, points, chunk=BRUTE_CHUNK, blocks=self.mesh_blocks)
        if self.tree is None:
            self.tree = point_tree(self.tris)
        return point_winding_numbers(self.tris, points, tree=self.tree, blocks=self.mesh_blocks)

    def cap_terms(self, points: np.ndarray, *, distance: bool, radius: float | None = None):
        """The caps' winding number [P] at points [P, 3] (grid units), and with `distance`
        also the squared distance [P] to the nearest cap; with a `radius` also the bound of
        `_cap_terms` on the term's gradient within it."""
        out = _chunked(
            functools.partial(_cap_terms, distance=distance),
            points.astype(np.float32),
            self.blocks,
            self.rows,
            np.float32(radius or 0.0),
        )
        return out[:2] if distance and radius is None else out

    def blocked_cap_terms(self, ijk: np.ndarray, keys: np.ndarray, gap: np.ndarray):
        """The caps' winding numbers and distances at voxels ijk [n, 3] (Morton order,
        codes keys [n] uint64) whose distance to the caps is at least gap [n] (grid
        units), exact only where the sign needs it.

        Voxels are taken in aligned blocks of 4^3, then 2^3 (`BLOCK_BITS`). At a block's
        centre q: the exact term and distance to the caps, and a bound on the term's
        gradient in the ball of radius r about q that holds the block's voxel centres.
        Off the caps, the gradient of the solid angle of a surface is a Biot-Savart
        integral over its boundary, at most ``sum_e len_e / g_e^2`` for boundary edges e
        at least g_e away; the caps' boundary is the mesh's boundary chain. So where the
        ball misses the caps, every voxel of the block lies at least ``|q - caps| - r``
        from them, and ``|w_caps| <= |w(q)| + r sum_e len_e / (4 pi g_e^2)``: where that
        is below `CAP_BOUND`, the block is settled.

        Returns:
          (w [n] float32: the exact term, or 0 where ``|w_caps| < CAP_BOUND`` holds for
          the voxel's whole block; gap [n] float32: a lower bound on the distance to the
          caps, the exact distance where neither the given gap nor a block puts it beyond
          `MOVE`).
        """
        w, gap = np.zeros(len(ijk), np.float32), gap.astype(np.float32)  # a copy
        rest = np.arange(len(ijk))
        for bits in BLOCK_BITS:
            if not len(rest):
                break
            radius = np.sqrt(3.0) * ((1 << bits) - 1) / 2  # from a block's centre to its farthest voxel centre
            block = keys[rest] >> np.uint64(3 * bits)
            starts = morton.run_starts(block)
            q = (ijk[rest[starts]] >> bits << bits) + (1 << bits) / 2  # float64 block centres
            term, d2, slope = self.cap_terms(q, distance=True, radius=radius)
            reach = np.sqrt(d2) - np.float32(radius)
            counts = np.diff(np.append(starts, len(rest)))
            gap[rest] = np.maximum(gap[rest], np.repeat(reach, counts))
            settled = (reach > ON_SURFACE) & (np.abs(term) + np.float32(radius) * slope < CAP_BOUND)
            rest = rest[~(np.repeat(settled, counts) & (gap[rest] > MOVE))]  # nearer: exact distances
        far = gap[rest] > MOVE
        if far.any():
            w[rest[far]] = self.cap_terms(ijk[rest[far]] + 0.5, distance=False)
        if not far.all():
            close = rest[~far]
            w[close], d2 = self.cap_terms(ijk[close] + 0.5, distance=True)
            gap[close] = np.sqrt(d2)
        return w, gap

    def winding_numbers(self, points: np.ndarray) -> np.ndarray:
        """The mesh's winding numbers [P] float64 at points [P, 3] (grid units):
        `_mesh_winding_numbers` (brute force or the fast tree), then
        `exact_winding_numbers` where it lands within `EXACT_BELOW` of 1/2 (the tree's
        error reaches a few 1e-2)."""
        w = self._mesh_winding_numbers(points).astype(np.float64)
        close = np.flatnonzero(np.abs(w - 0.5) < EXACT_BELOW)
        if len(close):
            w[close] = exact_winding_numbers(self.tris, points[close], blocks=self.mesh_blocks)
        return w

    def inside(self, ijk, keys, dist, tri, behind, on):
        """Whether each voxel is inside, [n] bool, at voxels ijk [n, 3] (Morton order,
        codes keys [n] uint64) of unsigned distance dist [n] and closest triangle tri [n]
        int32, behind [n] bool those behind their closest feature's pseudo-normal, on [n]
        bool those on the surface (no certain side).

        Most voxels are *tied*: of a free triangle, so their node is their (triangle,
        side) and their winding number the integer ``W`` of its component (less the cap
        term where the triangle is `capped`). The per-voxel work is a few gathers from
        per-node tables; the *loose* voxels (not free, or on the surface) are nodes of
        their own and take the detailed steps."""
        centre = lambda rows: ijk[rows] + 0.5  # float64 grid units
        n, faces, tris = len(ijk), len(self.tris), self.tris

        # Cap terms: exact where the bound is not small, and with the distance for loose
        # voxels within a move of a cap (lower bounds elsewhere).
        loose = np.flatnonzero(~self.free[tri] | on)
        gap = self.tri_gap32[tri[loose]]  # [loose]
        near = np.flatnonzero(gap <= MOVE)  # rows of loose
        capped = self.capped[tri]
        capped[loose[near]] = False
        bounded = np.flatnonzero(capped)
        del capped
        near_w, gap[near] = self.blocked_cap_terms(ijk[loose[near]], keys[loose[near]], gap[near])
        bounded_w = self.blocked_cap_terms(ijk[bounded], keys[bounded], np.full(len(bounded), np.inf))[0]
        alone = on[loose] | (gap < ON_SURFACE)  # [loose]

        # Nodes: the (triangle, side) groups of these voxels, numbered in the order of
        # 2 triangle + side, then the loose voxels; the groups that the mesh's regular
        # edges join (`side_label`) start joined, so no node of the whole mesh is visited.
        index = np.int32 if 2 * faces + len(loose) < (1 << 31) else np.int64
        side = 2 * tri.astype(index) + behind
        present = np.zeros(2 * faces, bool)
        present[np.delete(side, loose)] = True  # the groups of the tied voxels
        groups = np.flatnonzero(present)
        grouped = len(groups)
        number = np.zeros(2 * faces, index)
        number[groups] = np.arange(grouped, dtype=index)
        node = number[side]
        node[loose] = grouped + np.arange(len(loose), dtype=index)
        star = np.zeros(2 * faces, index)  # per label, one of its groups (any): joined to the others
        star[self.side_label[groups]] = np.arange(grouped, dtype=index)
        u = [np.arange(grouped, dtype=index)]
        v = [star[self.side_label[groups]]]
        movers = np.flatnonzero(~alone)  # rows of loose
        mover = loose[movers]
        for axis in range(3):
            for step in (-1, 1):
                other = ijk[mover].copy()
                other[:, axis] += step
                within = (other[:, axis] >= 0) & (other[:, axis] < (1 << 20))
                key = morton.encode_host(np.clip(other, 0, None))
                at = np.minimum(np.searchsorted(keys, key), n - 1)
                row = np.minimum(np.searchsorted(loose, at), len(loose) - 1)
                tied = loose[row] != at  # a tied voxel: no cap within a move, not alone
                at_gap = np.where(tied, np.float32(np.inf), gap[row])
                found = within & (keys[at] == key) & (tied | ~alone[row])
                ok = found & (dist[mover] + dist[at] > MOVE) & (gap[movers] + at_gap > MOVE)
                u.append(node[mover[ok]])
                v.append(node[at[ok]])
        nodes = grouped + len(loose)
        label = connected_components(nodes, np.concatenate(u), np.concatenate(v))

        # One winding number per component, at its voxel farthest from mesh and caps:
        # the best score per node (a loose node has one voxel), then per component.
        node_best = np.full(nodes, -1.0, np.float32)
        dist = dist.astype(np.float32, copy=False)  # compared with node_best below
        np.maximum.at(node_best, node, dist)
        node_best[grouped:] = np.where(alone, np.float32(-1), np.minimum(dist[loose], gap))
        best = np.full(len(label), -1.0, np.float32)
        np.maximum.at(best, label, node_best)
        winner = (node_best == best[label]) & (node_best >= 0.5)
        hit = np.flatnonzero(winner[node])
        hit = hit[(dist[hit] == node_best[node[hit]]) | (node[hit] >= grouped)]  # a loose node has one voxel
        rep = np.full(len(label), -1)
        rep[label[node[hit]]] = hit
        has_rep = rep >= 0
        roots = np.flatnonzero(has_rep)
        reps = rep[roots]
        lone = np.flatnonzero(~has_rep[label][node])  # components without a representative
        # W of mesh plus caps (an integer, within the fast tree's error if it was used) at the
        # representatives and the lone voxels; a lone voxel's own w is W less its cap term.
        points = np.concatenate([centre(reps), centre(lone)])
        values = self._mesh_winding_numbers(points)
        caps = self.cap_terms(points, distance=False) if self.has_caps else np.zeros(len(points), np.float32)
        total = np.rint(values + caps)
        wrong = np.flatnonzero(np.abs(values + caps - total) > 0.25)
        if len(wrong):  # the fast value missed by more than its error, or the point is on a cap
            values[wrong] = brute_force_winding_numbers(tris, points[wrong], blocks=self.mesh_blocks)
            whole = values[wrong] + caps[wrong]
            total[wrong] = np.where(np.abs(whole - np.rint(whole)) > 0.25, np.nan, np.rint(whole))
        own = total - caps
        own[wrong] = values[wrong]  # summed exactly
        component_w = np.full(len(label), np.nan, np.float32)
        component_w[roots] = total[: len(reps)]
        node_w = component_w[label]
        # per node: 0 outside, 1 inside, 2 no representative (lone), 3 rounding failed
        state = np.where(np.isnan(node_w), np.where(has_rep[label], 3, 2), node_w > 0.5).astype(np.int8)[node]
        result = state == 1
        exact = np.concatenate([loose[near], bounded])  # elsewhere w is an integer (or NaN)
        w = node_w[node[exact]] - np.concatenate([near_w, bounded_w])
        result[exact] = w > 0.5
        result[lone] = own[len(reps) :] > 0.5
        close = np.concatenate([exact[np.abs(w - 0.5) < CLOSE], lone[np.abs(own[len(reps) :] - 0.5) < CLOSE]])
        if len(close):
            result[close] = exact_winding_numbers(tris, centre(close), blocks=self.mesh_blocks) > 0.5
        single = np.flatnonzero(state == 3)  # components whose rounding failed
        if len(single):
            result[single] = self.winding_numbers(centre(single)) > 0.5
        return result
