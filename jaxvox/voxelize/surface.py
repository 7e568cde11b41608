"""The boundary surface of a voxel set as a closed, manifold triangle mesh (`voxels_to_mesh`).

Every face between an occupied voxel and an empty one (or the outside of the grid) is a
unit square, counter-clockwise seen from the empty side. Where the voxel set touches
itself only along an edge or at a corner, welding every shared corner would give a
non-manifold mesh (an edge used by four triangles, a vertex where two cones meet), which
mesh tools report as not watertight. Instead, occupied voxels that share only an edge
or a corner are kept apart, as with 6-connected voxels:

* at a corner, the exposed faces of its 2x2x2 block of cells link through the six
  half-edges leaving it: two faces at a half-edge link, and four (two occupied cells
  diagonally opposite) link in pairs of the same occupied cell. The links form
  cycles (fans); each fan gets its own vertex. Both tables (`_FAN`, `_DIAGONAL`) are
  computed once for the 256 occupancy patterns of the block;
* an edge with four exposed faces gets one midpoint per occupied cell, and each of
  those faces becomes a fan of triangles around its centre, so that the two copies
  of the edge never join the same pair of vertices.

So every edge is used by exactly two triangles in opposite directions and every vertex
is surrounded by one cycle of triangles: the mesh is a closed 2-manifold (possibly
touching itself in space where the voxels do), and its volume is the voxels' volume.
Faces without such an edge are two triangles over the welded corners. All work is
host-side numpy on sorted linear voxel keys (`np.searchsorted`); no dense ``R^3`` array
is formed.
"""

from __future__ import annotations

import itertools

import numpy as np

from jaxvox._core.checks import check_type
from jaxvox.mesh import Mesh
from jaxvox.voxelize.voxels import Voxels

# The 27 cells around a voxel, offset (dx, dy, dz) at index (dx+1)*9 + (dy+1)*3 + (dz+1).
_OFFSETS = np.array(list(itertools.product((-1, 0, 1), repeat=3)), np.int64)  # [27, 3]
# Voxel corner q (0..7) is at offset (q & 1, q >> 1 & 1, q >> 2 & 1); also the cell l of a
# corner's 2x2x2 block lies on the + side of the corner along the axes of its set bits.
_BITS = np.array([[q & 1, q >> 1 & 1, q >> 2 & 1] for q in range(8)], np.int64)  # [8, 3]


def _offset_index(offset) -> int:
    """Index into `_OFFSETS` of an offset in {-1, 0, 1}^3."""
    return int(np.dot(np.asarray(offset) + 1, (9, 3, 1)))


# _BLOCK[q, l]: the neighbourhood index of cell l of the block around voxel corner q.
_BLOCK = np.array([[_offset_index(_BITS[q] + _BITS[l] - 1) for l in range(8)] for q in range(8)])


def _face_tables():
    """Per face f = 2 * axis + (side > 0) of a voxel, in `_OFFSETS` / `_BITS` terms.

    Returns:
      (neighbour [6] index of the cell across the face, corners [6, 4] the voxel corners
      counter-clockwise seen from outside, edge_axis [6, 4] and edge_side [6, 4]: the axis
      of the edge from corner i to corner i + 1 and 1 where it leaves corner i towards +).
    """
    neighbour, corners = [], []
    for axis, side in itertools.product(range(3), (-1, 1)):
        u, w = (axis + 1) % 3, (axis + 2) % 3  # u x w = axis: this ring turns counter-clockwise about +axis
        ring = [(0, 0), (1, 0), (1, 1), (0, 1)][::side]
        offsets = np.zeros((4, 3), np.int64)
        offsets[:, axis] = side > 0
        offsets[:, u], offsets[:, w] = np.array(ring).T
        neighbour.append(_offset_index(np.eye(3, dtype=np.int64)[axis] * side))
        corners.append(offsets @ (1, 2, 4))
    corners = np.array(corners)
    step = _BITS[np.roll(corners, -1, axis=1)] - _BITS[corners]  # [6, 4, 3], one nonzero entry
    return np.array(neighbour), corners, np.abs(step).argmax(-1), (step.sum(-1) > 0).astype(np.int64)


_FACE_NEIGHBOUR, _FACE_CORNERS, _EDGE_AXIS, _EDGE_SIDE = _face_tables()


def _find(root: dict, item):
    """The representative of `item` in a union-find forest given by parent links."""
    while root[item] != item:
        item = root[item]
    return item


def _corner_tables():
    """Fans and diagonal edges around a lattice corner, for each occupancy of its block.

    The corner's 2x2x2 block has cells l = 0..7 (bit a set: on the + side along axis
    a); pattern p has bit l set when cell l is occupied. Exposed face (l, a) separates
    occupied cell l from empty cell ``l ^ (1 << a)``; its edges at the corner are the
    half-edges (b, bit b of l) for the two axes b != a.

    Returns:
      (fan [256, 8, 3] int8: the fan of exposed face (l, a), -1 where not exposed;
      diagonal [256, 3, 2] bool: half-edge (axis, side) has four exposed faces).
    """
    fan = np.full((256, 8, 3), -1, np.int8)
    diagonal = np.zeros((256, 3, 2), bool)
    for p in range(256):
        occupied = [bool(p >> l & 1) for l in range(8)]
        faces = [(l, a) for l in range(8) for a in range(3) if occupied[l] and not occupied[l ^ 1 << a]]
        root = {face: face for face in faces}
        for b, t in itertools.product(range(3), range(2)):
            here = [(l, a) for l, a in faces if a != b and (l >> b & 1) == t]
            diagonal[p, b, t] = len(here) == 4
            for f, g in itertools.combinations(here, 2):
                if len(here) == 2 or f[0] == g[0]:
                    root[_find(root, f)] = _find(root, g)
        labels = {}
        for l, a in faces:
            fan[p, l, a] = labels.setdefault(_find(root, (l, a)), len(labels))
    return fan, diagonal


_FAN, _DIAGONAL = _corner_tables()
_FANS = int(_FAN.max()) + 1  # most fans at one corner (4: cells touching only at it)


def _linear(ijk: np.ndarray, size: int) -> np.ndarray:
    """Row-major linear keys of int [..., 3] indices in ``[0, size)^3``: int64 [...]."""
    return (ijk[..., 0] * size + ijk[..., 1]) * size + ijk[..., 2]


def _occupied(ijk: np.ndarray, keys: np.ndarray, resolution: int, offsets: np.ndarray) -> np.ndarray:
    """Whether each voxel's neighbours at `offsets` are in the set: bool [N, len(offsets)].

    Args:
      ijk: int64 [N, 3] voxel indices.
      keys: int64 sorted linear keys of the set, followed by one larger sentinel.
      resolution: R; cells outside ``[0, R)^3`` are empty.
      offsets: int64 [K, 3].
    """
    out = np.empty((len(ijk), len(offsets)), bool)
    base = _linear(ijk, resolution)
    for n, offset in enumerate(offsets):
        cell = ijk + offset
        inside = ((cell >= 0) & (cell < resolution)).all(axis=1)
        key = base + _linear(offset, resolution)
        out[:, n] = inside & (keys[np.searchsorted(keys, key)] == key)
    return out


def voxels_to_mesh(voxels: Voxels) -> Mesh:
    """The exposed faces of a voxel set as a closed, manifold triangle mesh in world units.

    Faces between an occupied voxel and an empty one (including the grid's boundary)
    are kept, counter-clockwise seen from outside, and corners are welded; voxels that
    touch only along an edge or at a corner get separate vertices there (see the
    module docstring), so the mesh is watertight and every vertex and edge is
    manifold. A single voxel gives 8 vertices and 12 triangles; an empty set gives an
    empty mesh (no vertices, no faces).

    Args:
      voxels: a `Voxels` set (one, not a batch).

    Returns:
      `Mesh` with float32 vertices ``origin + h * corner`` and int32 faces.

    Raises:
      JaxvoxError: not a `Voxels`, or an overflowed set.
    """
    check_type("voxels_to_mesh voxels", voxels, Voxels)
    grid = voxels.grid
    r = grid.resolution
    ijk = voxels.to_numpy().astype(np.int64)
    keys = np.append(np.sort(_linear(ijk, r)), np.iinfo(np.int64).max)
    exposed = ~_occupied(ijk, keys, r, _OFFSETS[_FACE_NEIGHBOUR])  # [N, 6]
    surface = exposed.any(axis=1)
    ijk, exposed = ijk[surface], exposed[surface]
    block = _occupied(ijk, keys, r, _OFFSETS)[:, _BLOCK]  # [M, 8 corners, 8 cells]
    pattern = (block << np.arange(8)).sum(axis=-1)  # [M, 8]

    voxel, face = np.nonzero(exposed)  # [F] each
    q = _FACE_CORNERS[face]  # [F, 4]
    pat = pattern[voxel[:, None], q]
    fan = _FAN[pat, 7 - q, (face // 2)[:, None]]  # the voxel is cell 7 - q of corner q's block
    corner = ijk[voxel, None, :] + _BITS[q]  # [F, 4, 3] in grid units
    diagonal = _DIAGONAL[pat, _EDGE_AXIS[face], _EDGE_SIDE[face]]  # [F, 4]: edge i to i+1
    q_next = np.roll(q, -1, axis=1)

    corner_keys, corner_id = np.unique(_linear(corner, r + 1) * _FANS + fan, return_inverse=True)
    corner_id = corner_id.reshape(q.shape)
    mid_key = (voxel[:, None] * 8 + np.minimum(q, q_next)) * 8 + np.maximum(q, q_next)
    _, mid_first, mid_inverse = np.unique(mid_key[diagonal], return_index=True, return_inverse=True)
    mid_id = np.full(q.shape, -1, np.int64)
    mid_id[diagonal] = len(corner_keys) + mid_inverse.reshape(-1)
    split = diagonal.any(axis=1)  # faces fanned around their centre
    centre_id = len(corner_keys) + len(mid_first) + np.arange(int(split.sum()))

    c = corner_keys // _FANS
    points = np.concatenate(
        [
            np.stack([c // (r + 1) ** 2, c // (r + 1) % (r + 1), c % (r + 1)], axis=1),
            ((corner + np.roll(corner, -1, axis=1)) / 2)[diagonal][mid_first],
            corner[split].mean(axis=1),
        ]
    )
    cs, ms, has_mid = corner_id[split], mid_id[split], diagonal[split]
    cs_next = np.roll(cs, -1, axis=1)
    centre = np.broadcast_to(centre_id[:, None], cs.shape)
    triangles = np.concatenate(
        [
            corner_id[~split][:, [[0, 1, 2], [0, 2, 3]]].reshape(-1, 3),
            np.stack([centre, cs, np.where(has_mid, ms, cs_next)], axis=-1).reshape(-1, 3),
            np.stack([centre, ms, cs_next], axis=-1)[has_mid],
        ]
    )
    vertices = np.asarray(grid.origin, np.float64) + float(grid.voxel_size) * points
    return Mesh(vertices.astype(np.float32), triangles.astype(np.int32))
