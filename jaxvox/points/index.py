"""`MeshIndex`: the acceleration structure of one mesh for point queries, built once.

Triangles are ordered along a Morton curve of their centroids and grouped eight by eight,
level by level, into an implicit 8-ary tree (node ``j`` of a level has the children
``8 j .. 8 j + 7`` of the level below; level 0 is the triangles). Each node keeps what
the two searches need:

* for closest points, its bounding box and one surface point (``rep``, a corner of its
  first triangle): every point's distance to the mesh is at most its distance to ``rep``,
  at least its distance to the box;
* for winding numbers, its dipole: the area-weighted centre ``c``, a radius ``r`` about
  ``c`` that bounds its triangles, the area vector ``A`` (sum of area times unit normal)
  and the unsigned area ``S`` (for the error bound of the far field).

Triangles are stored as the float32 rows of `jaxvox._core.geometry.triangle_rows` (computed
in float64 on the host), their corners and their angle-weighted pseudo-normals. Everything
is relative to ``centre`` (the middle of the mesh's box), so a mesh far from the origin
keeps float32 precision. The face count is padded to the shape ladder (`bucket`, at least
64): meshes whose face counts share a bucket share every compiled query program. Padding
triangles are marked invalid and never found.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float32, Int32

from jaxvox import morton
from jaxvox._core.checks import check_int, refuse
from jaxvox._core.geometry import triangle_rows
from jaxvox._core.pytree import pytree_dataclass
from jaxvox._core.shapes import bucket
from jaxvox.distance.band_sign import pseudo_normals, pseudonormal_sides_exact
from jaxvox.mesh import Mesh, validate_mesh

FAN_OUT = 8  # children per node, triangles per leaf
FAR = 1e30  # corner a of padding triangles in `MeshIndex.leaf_rows`
MIN_FACES = 64  # the smallest face capacity (two levels of nodes)


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class MeshIndex:
    """The point-query structure of a mesh (`mesh_index`): a pytree, so it can be passed
    into `jax.jit` functions, reused for any number of point batches, and stacked
    (`stack_indices`) for `jax.vmap` over meshes.

    F is the face capacity (the ladder bucket of the face count, at least `MIN_FACES`), N
    the node count of all levels above the triangles, V the vertex count. ``levels`` is
    static (it depends on F only): a mesh whose face capacity differs recompiles.

    Attributes:
      vertices: [V, 3] float32 the mesh's vertices, world units (for vertex gradients),
        padded with zeros to the ladder bucket of the vertex count.
      faces: [F, 3] int32 the mesh's faces in their own order, padded with ``(0, 0, 0)``.
      order: [F] int32 the face id at each tree slot (padding slots: ids >= face count).
      valid: [F] bool whether a tree slot holds a real face.
      centre: [3] float32 world position that all rows below are relative to.
      leaf_rows: [F / 8, 28, 8] float32 `triangle_rows` of each leaf's triangles (leaf
        major, so that a leaf's data is one contiguous gather); padding triangles have
        corner a at `FAR` (their distance overflows to inf).
      leaf_corners: [F / 8, 9, 8] float32 corners a, b, c (xyz each) of each leaf's triangles
        (padding triangles are points: zero solid angle).
      leaf_faces: [F / 8, 8] int32 face id of each leaf's triangles (padding: ids >= face count).
      corners: [9, F] float32 corners a, b, c (xyz each) in tree order.
      normals: [21, F] float32 pseudo-normals in tree order: face, edges ab, bc, ca,
        vertices a, b, c (xyz each; unit face normal, unnormalized sums otherwise).
      nodes: [N, 24] float32 per node (one contiguous row, one gather per visit): its box
        (lo xyz, hi xyz; empty nodes have lo > hi), a surface point ``rep`` (xyz; inf for
        empty nodes), an oriented box bounding its triangles (centre xyz, three unit axes
        xyz each, half extents along them; -1 for empty nodes).
      dipole: [N, 8] float32 per node: centre xyz, radius, area vector xyz, unsigned area.
      num_faces: [] int32 the face count.
      closed: [] bool whether pseudo-normal sides are winding-number sides everywhere
        (`jaxvox.distance.band_sign.pseudonormal_sides_exact`: watertight, no crossings, ...); the
        host API then signs by pseudo-normals, exactly, without summing winding numbers.
      levels: ((offset, size), ...) static: the node levels in ``box`` from the leaves
        (level 1) up to the root.
    """

    vertices: Float32[Array, "V 3"]
    faces: Int32[Array, "F 3"]
    order: Int32[Array, " F"]
    valid: Bool[Array, " F"]
    centre: Float32[Array, 3]
    leaf_rows: Float32[Array, "L 28 8"]
    leaf_corners: Float32[Array, "L 9 8"]
    leaf_faces: Int32[Array, "L 8"]
    corners: Float32[Array, "9 F"]
    normals: Float32[Array, "21 F"]
    nodes: Float32[Array, "N 24"]
    dipole: Float32[Array, "N 8"]
    num_faces: Int32[Array, ""]
    closed: Bool[Array, ""]
    levels: tuple[tuple[int, int], ...] = dataclasses.field(metadata={"static": True})

    @property
    def capacity(self) -> int:
        """The face capacity F (static)."""
        return self.faces.shape[-2]


def _group(x: np.ndarray, fill) -> np.ndarray:
    """[n, ...] -> [ceil(n / FAN_OUT), FAN_OUT, ...], padded with `fill`."""
    pad = -len(x) % FAN_OUT
    x = np.concatenate([x, np.full((pad,) + x.shape[1:], fill, x.dtype)])
    return x.reshape(-1, FAN_OUT, *x.shape[1:])


def _node_levels(tris: np.ndarray, valid: np.ndarray):
    """Node tables of each level above the triangles (float64, host): lists of box [n, 6],
    rep [n, 3], dipole [n, 8] from the leaves to the root."""
    area = 0.5 * np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]) * valid[:, None]
    weight = np.linalg.norm(area, axis=1)
    centroid = tris.mean(1)
    inf = np.inf
    box = np.where(valid[:, None], np.concatenate([tris.min(1), tris.max(1)], 1), [inf] * 3 + [-inf] * 3)
    rep = np.where(valid[:, None], tris[:, 0], inf)
    # level 0 "nodes" are the triangles: centre, radius 0 about the corners handled below
    centre, radius, vector, unsigned = centroid, np.zeros(len(tris)), area, weight
    corners: np.ndarray | None = np.where(valid[:, None, None], tris, np.nan)  # what the leaves' radii cover
    out = []
    first = True
    while first or len(box) > 1:
        first = False
        g_box, g_rep, g_valid = _group(box, np.nan), _group(rep, inf), _group(np.isfinite(rep[:, 0]), False)
        g_box = np.where(np.isnan(g_box), [inf] * 3 + [-inf] * 3, g_box)
        g_centre, g_vector, g_unsigned = _group(centre, 0.0), _group(vector, 0.0), _group(unsigned, 0.0)
        total = g_unsigned.sum(1)
        count = np.maximum(g_valid.sum(1), 1)
        plain = np.where(g_valid[..., None], g_centre, 0.0).sum(1) / count[:, None]
        weighted = (g_unsigned[..., None] * g_centre).sum(1) / np.where(total > 0, total, 1.0)[:, None]
        new_centre = np.where((total > 0)[:, None], weighted, plain)
        if corners is not None:  # the leaves: the radius covers the triangles' corners
            g_corners = _group(corners, np.nan).reshape(len(g_box), -1, 3)
            reach = np.linalg.norm(g_corners - new_centre[:, None], axis=-1)
            new_radius = np.nanmax(np.where(np.isnan(reach), -np.inf, reach), 1)
        else:
            g_radius = _group(radius, 0.0)
            reach = np.linalg.norm(g_centre - new_centre[:, None], axis=-1) + g_radius
            new_radius = np.where(g_valid, reach, -np.inf).max(1)
        new_radius = np.maximum(new_radius, 0.0)
        box = np.concatenate([g_box[:, :, :3].min(1), g_box[:, :, 3:].max(1)], 1)
        rep = g_rep[:, 0]
        centre, radius, vector, unsigned = new_centre, new_radius, g_vector.sum(1), total
        corners = None
        out.append((box, rep, np.concatenate([centre, radius[:, None], vector, unsigned[:, None]], 1)))
    return out


def _oriented_boxes(tris: np.ndarray, valid: np.ndarray, levels: int) -> list[np.ndarray]:
    """[n, 15] oriented boxes (centre, axes, half extents) of each level above the
    triangles: axes from the principal directions of the node's corners (moments summed up
    the tree), extents covering its corners (leaves) or its children's boxes' corners."""
    pts = _group(np.where(valid[:, None, None], tris, np.nan), np.nan).reshape(-1, 3 * FAN_OUT, 3)
    ok = ~np.isnan(pts[..., 0])
    x = np.where(ok[..., None], pts, 0.0)
    count, total, outer = ok.sum(1), x.sum(1), np.einsum("nki,nkj->nij", x, x)
    out: list[np.ndarray] = []
    for depth in range(levels):
        if depth:
            count, total, outer = (_group(a, 0).sum(1) for a in (count, total, outer))
            prev = out[-1]
            corners = prev[:, None, :3] + np.einsum(
                "ks,nsj->nkj", _SIGNS, prev[:, 3:12].reshape(-1, 3, 3) * prev[:, 12:, None]
            )
            corners = np.where((prev[:, 12:13] >= 0)[:, :, None], corners, np.nan)
            pts = _group(corners, np.nan).reshape(len(count), -1, 3)
        mean = total / np.maximum(count, 1)[:, None]
        cov = outer / np.maximum(count, 1)[:, None, None] - np.einsum("ni,nj->nij", mean, mean)
        axes = np.linalg.eigh(cov)[1].transpose(0, 2, 1)  # [n, 3 axes, 3]
        proj = np.einsum("nkj,naj->nka", pts - mean[:, None], axes)
        lo, hi = (
            np.nanmin(np.where(np.isnan(proj), np.inf, proj), 1),
            np.nanmax(np.where(np.isnan(proj), -np.inf, proj), 1),
        )
        empty = count == 0
        lo, hi = np.where(empty[:, None], 0.0, lo), np.where(empty[:, None], 0.0, hi)
        centre = mean + np.einsum("na,naj->nj", (lo + hi) / 2, axes)
        half = np.where(empty[:, None], -1.0, (hi - lo) / 2)
        out.append(np.concatenate([centre, axes.reshape(-1, 9), half], 1))
    return out


_SIGNS = np.array([[(i >> k & 1) * 2 - 1 for k in range(3)] for i in range(8)], np.float64)  # box corner signs


def mesh_index(mesh: Mesh, *, capacity: int | None = None) -> MeshIndex:
    """Builds the point-query structure of `mesh` (host-side, once per mesh; float64).

    Args:
      mesh: `Mesh` with at least one face (validated). Its orientation sets the sign of
        winding numbers (outward normals: 1 inside).
      capacity: face capacity F, at least the face count (default: its ladder bucket,
        at least `MIN_FACES`). Give meshes one capacity to stack their indices for `jax.vmap`.

    Returns:
      `MeshIndex`. Cost: O(F log F) on the host, plus a crossing test of the faces when
      the mesh is watertight.

    Raises:
      JaxvoxError: a malformed mesh, a mesh without faces, or a capacity below the face count.
    """
    validate_mesh(mesh)
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    if len(f) == 0:
        raise refuse("mesh_index mesh", "has no faces (point queries need a surface)", f.shape)
    cap = bucket(len(f), MIN_FACES) if capacity is None else check_int("mesh_index capacity", capacity, minimum=1)
    if cap < len(f):
        raise refuse("mesh_index capacity", f"must be at least the face count {len(f)}", cap)
    cap = bucket(cap, MIN_FACES)
    lo, hi = v[f.ravel()].min(0), v[f.ravel()].max(0)
    centre = (lo + hi) / 2
    tris = v[f] - centre
    order = morton.curve_order_host(tris.mean(1))
    slots = np.concatenate([order, np.arange(len(f), cap)])
    valid = slots < len(f)
    padded_tris = np.concatenate([tris, np.repeat(tris[:1, :1], cap - len(f), 0).repeat(3, 1)])[slots]
    normals = np.concatenate([pseudo_normals(v, f), np.zeros((cap - len(f), 7, 3), np.float32)])[slots]
    levels = _node_levels(padded_tris, valid)
    sizes = [len(level[0]) for level in levels]
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).tolist()
    rows = triangle_rows(padded_tris)
    rows[:3, ~valid] = FAR
    # no conversion program; (ascontiguousarray makes scalars [1])
    put = lambda x, dtype=np.float32: jax.device_put(np.ascontiguousarray(x, dtype).reshape(np.shape(x)))
    leaf_major = lambda x, dtype=np.float32: put(x.reshape(len(x), -1, FAN_OUT).transpose(1, 0, 2), dtype)
    table = lambda i: np.concatenate([level[i] for level in levels])
    frames = _oriented_boxes(padded_tris, valid, len(levels))
    faces = np.zeros((cap, 3), np.int32)
    faces[: len(f)] = f
    vertices = np.zeros((bucket(len(v)), 3))
    vertices[: len(v)] = v  # padded to the ladder too: a program per vertex count would recompile
    return MeshIndex(
        vertices=put(vertices),
        faces=put(faces, np.int32),
        order=put(slots, np.int32),
        valid=put(valid, bool),
        centre=put(centre),
        leaf_rows=leaf_major(rows),
        leaf_corners=leaf_major(padded_tris.reshape(cap, 9).T),
        leaf_faces=put(slots.reshape(-1, FAN_OUT), np.int32),
        corners=put(padded_tris.reshape(cap, 9).T),
        normals=put(normals.reshape(cap, 21).T),
        nodes=put(np.concatenate([table(0), table(1), np.concatenate(frames)], 1)),
        dipole=put(table(2)),
        num_faces=put(len(f), np.int32),
        closed=put(pseudonormal_sides_exact(v, f), bool),
        levels=tuple(zip(offsets, sizes)),
    )


def stack_indices(indices: list[MeshIndex]) -> MeshIndex:
    """Indices of several meshes stacked along a leading axis, for `jax.vmap` over meshes.

    All must have the same face capacity (build them with one ``capacity``); vertex
    arrays are padded to the longest with copies of the origin (unreferenced).

    Raises:
      JaxvoxError: an empty list or indices of different face capacities.
    """
    if not indices:
        raise refuse("stack_indices indices", "must hold at least one MeshIndex", indices)
    if len({i.levels for i in indices}) > 1:
        raise refuse(
            "stack_indices indices",
            "have different face capacities (build them with one mesh_index capacity)",
            [i.capacity for i in indices],
        )
    nv = max(i.vertices.shape[0] for i in indices)
    pad = lambda i: dataclasses.replace(i, vertices=jnp.pad(i.vertices, ((0, nv - i.vertices.shape[0]), (0, 0))))
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[pad(i) for i in indices])
