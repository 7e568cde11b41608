"""Triangle meshes of sparse narrow-band distance fields (`field_to_mesh`).

Marching cubes (`skimage.measure.marching_cubes`, Lewiner's topologically consistent
variant) on the voxel centres of a `SparseField`, one aligned block of ``BLOCK^3`` cells at
a time, welded into one mesh. A *cell* is the cube between 8 neighbouring voxel centres,
named by its lowest corner; a *sample* is a voxel centre ``(i, j, k)``.

* **One value per sample.** A band voxel's sample is its stored distance. A sample missing
  from the band takes ``s * band * h``, the clamp of `jaxvox.sample`, where ``s`` is -1 if
  the sum of the present values among its 26 neighbours (the corners of the 8 cells that
  share it) is negative and +1 otherwise; `sample` decides ``s`` per interpolation cell
  instead, which could give one sample two values in two cells and crack the surface.
  Samples outside the grid count as outside (``+band * h``).
* **Which cells.** Only cells with at least one corner in the band are marched (the others
  may have corners without a present neighbour, whose sign is unknown: deep inside a solid
  the clamp would be wrong). A block is a ``(BLOCK + 1)^3`` array of its cells' corner
  samples (one sample of overlap on the high side, shared with the next block), filled by
  `np.searchsorted` in the sorted linear keys of the band voxels (plus a layer of
  neighbours for ``s``); no array of size R^3 is formed.
* **Welding.** Each vertex marching cubes puts on a cell edge is keyed by (the edge's lower
  sample, its axis) and placed by linear interpolation of the two samples' values in
  float64, so the two blocks sharing a face compute the same key and the same position
  from the same two values; vertices with equal keys merge. (Lewiner's extra vertex inside
  a cell is keyed by the cell.) Samples within ``NUDGE * band`` voxel units of the level
  are moved that far away from it first, so no vertex sits on a sample (where its edge
  could not be told from the float32 position marching cubes returns) and no face is
  degenerate; this moves the surface by at most about ``NUDGE * band`` voxels.

**Closed output.** Marching cubes over one consistent sample field is crack-free inside
the marched cells, so the surface can only be open on a face between a marched cell and an
unmarched one (all 4 corners missing from the band) whose corners change sign. For the
exact signed distance of a closed surface inside the grid box with ``band >= 2`` (what
`jaxvox.sparse_distance_field` gives for a watertight mesh) that cannot happen: two
neighbouring samples of opposite sign have the surface between them, less than a voxel
away, so neither is missing; a missing sample is more than ``band >= 2 > sqrt(3)`` voxels
from the surface, so all its present neighbours (within ``sqrt(3)`` voxels) share its sign
and ``s`` is its true sign; a sample on the grid's outer layer inside the solid is within
half a voxel of the box, so it is present. So the mesh is closed and consistently oriented
for every ``|level| < band * h``. At level 0 every cell the surface crosses has all 8 corners
within ``sqrt(3) < band`` voxels of it, so present: the vertices are the zeros of the exact
trilinear interpolation of `sample` on the cell edges. Away from zero the clamp enters cells
once ``|level| > (band - sqrt(3)) h``, flattening the offset surface there.

A surface cut by the grid is capped between the outermost samples and the layer just
outside; where a solid's interior further than ``band`` voxels from its surface reaches the
grid boundary the cap has holes (that interior is unknown). Fields that are not signed
distances (unsigned fields, winding-number signs of open meshes, pseudo-normal signs that
are wrong where a mesh intersects itself) still give a surface, with no guarantee of
closure: the surface can end on a face whose missing corners were given opposite signs.

Cost: host numpy and scikit-image, a Python loop over the blocks near the band, about
``(BLOCK + 3)^3`` binary searches per block.
"""

from __future__ import annotations

import itertools

import numpy as np

from jaxvox._core.checks import check_number, check_type, refuse
from jaxvox.distance.sparse import SparseField
from jaxvox.mesh import Mesh

BLOCK = 32  # cells per block edge (>= 2; <= 64 keeps vertex offsets resolvable in float32)
NUDGE = 2.0**-12  # samples closer than NUDGE * band voxel units to the level move that far from it
_CENTRE = 3  # vertex kind of Lewiner's vertex inside a cell (kinds 0, 1, 2: edge along x, y, z)
_LOWER_CORNERS = np.array(list(itertools.product((-1, 0), repeat=3)), np.int64)  # [8, 3]


def _box_sum(a: np.ndarray) -> np.ndarray:
    """Sums over 3x3x3 neighbourhoods: [n, n, n] -> [n - 2, n - 2, n - 2] (the same order of
    additions at every sample, so every block gets bit-identical sums)."""
    for axis in range(3):
        a = np.moveaxis(a, axis, 0)
        a = np.moveaxis(a[:-2] + a[1:-1] + a[2:], 0, axis)
    return a


class _Band:
    """The band voxels as sorted int64 linear keys ``(i * R + j) * R + k`` with their values."""

    def __init__(self, coords: np.ndarray, values: np.ndarray, resolution: int):
        self.resolution = resolution
        keys = (coords[:, 0] * resolution + coords[:, 1]) * resolution + coords[:, 2]
        order = np.argsort(keys)
        self.keys, self.values = keys[order], values[order].astype(np.float64)

    def lookup(self, lo: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(present [n, n, n] bool, values [n, n, n] float64, 0 where absent) at the samples
        ``lo + [0, n)^3`` (grid indices, possibly outside the grid)."""
        r = self.resolution
        axes = [lo[a] + np.arange(n) for a in range(3)]
        inside = [((x >= 0) & (x < r)) for x in axes]
        i, j, k = (np.clip(x, 0, r - 1) for x in axes)
        key = (i[:, None, None] * r + j[None, :, None]) * r + k[None, None, :]
        pos = np.minimum(np.searchsorted(self.keys, key), len(self.keys) - 1)
        present = (
            (self.keys[pos] == key) & inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]
        )
        return present, np.where(present, self.values[pos], 0.0)


def _blocks(coords: np.ndarray, block: int) -> np.ndarray:
    """[n, 3] int64 block indices (sorted) holding a cell with a corner among `coords`: the
    cells ``v + {-1, 0}^3`` of each band voxel ``v``."""
    b = coords // block
    low = (coords - b * block) == 0  # the cell at v - 1 along that axis is in the block before
    lo = b.min(0) - 1
    span = b.max(0) - lo + 1
    key = ((b[:, 0] - lo[0]) * span[1] + (b[:, 1] - lo[1])) * span[2] + (b[:, 2] - lo[2])
    pairs = np.unique(key * 8 + low @ np.array([1, 2, 4]))
    key, code = np.divmod(pairs, 8)
    base = np.stack([key // (span[1] * span[2]), (key // span[2]) % span[1], key % span[2]], 1) + lo
    out = []
    for offset in _LOWER_CORNERS:
        need = int((offset < 0) @ np.array([1, 2, 4]))
        out.append(base[(code & need) == need] + offset)
    return np.unique(np.concatenate(out), axis=0)


def _march(field: SparseField, level: float, block: int, values: np.ndarray | None = None):
    """Marching cubes on every block, before welding (`values`: the field's [count] band
    values on the host, when the caller has them).

    Returns:
      (keys [N] int64 vertex keys, points [N, 3] float64 vertex positions in grid index
      units (sample (i, j, k) at (i, j, k)), faces [F, 3] int64 into the N vertices,
      counter-clockwise seen from where the field exceeds `level`). Vertices on block
      faces appear once per block, with equal keys and equal points.
    """
    from skimage.measure import marching_cubes

    values = np.asarray(field.values)[: int(field.count)] if values is None else values  # (cut on the host)
    n = len(values)
    r = field.grid.resolution
    h = float(field.grid.voxel_size)
    band = field.band
    target = level / h  # the level in voxel units (marching cubes sees voxel units)
    delta = NUDGE * band
    stride = r + 2  # vertex keys: (lower sample + 1) in [0, R + 1]^3, times 4 kinds
    coords = np.asarray(field.voxel_coords(), np.int64)
    lookup = _Band(coords, values, r)
    keys: list[np.ndarray] = []
    points: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    count = 0
    for b in _blocks(coords, block) if n else np.zeros((0, 3), np.int64):
        lo = b * block  # first corner sample of the block's cells
        present, values = lookup.lookup(lo - 1, block + 3)
        sign = np.where(_box_sum(values) < 0, -1.0, 1.0)  # per sample: the clamp's sign
        here = present[1:-1, 1:-1, 1:-1]
        u = np.where(here, values[1:-1, 1:-1, 1:-1] / h, sign * band)
        axes = [lo[a] + np.arange(block + 1) for a in range(3)]
        outside = [(x < 0) | (x >= r) for x in axes]
        u[outside[0][:, None, None] | outside[1][None, :, None] | outside[2][None, None, :]] = band
        u = np.clip(u, -2.0 * band, 2.0 * band)
        close = np.abs(u - target) < delta
        u[close] = np.where(u[close] >= target, target + delta, target - delta)
        u = u.astype(np.float32)
        cells = np.zeros((block,) * 3, bool)  # marched: a corner in the band
        above = u.astype(np.float64) > target
        n_above = np.zeros((block,) * 3, np.int64)
        for c in itertools.product((0, 1), repeat=3):
            sl = tuple(slice(d, d + block) for d in c)
            cells |= here[sl]
            n_above += above[sl]
        if not (cells & (n_above > 0) & (n_above < 8)).any():
            continue
        mask = np.zeros(u.shape, bool)  # scikit-image reads a cell's flag at its highest corner
        mask[1:, 1:, 1:] = cells
        verts, tris, _, _ = marching_cubes(u, target, mask=mask, allow_degenerate=True, gradient_direction="descent")
        frac = verts != np.floor(verts)  # edge vertices: 1 fractional coordinate, centres: 3
        kinds = frac.sum(1)
        if not np.all((kinds == 1) | (kinds == 3)):
            raise RuntimeError("field_to_mesh: a marching cubes vertex lies on a sample (internal error)")
        kind = np.where(kinds == 1, frac.argmax(1), _CENTRE)
        low = np.floor(verts).astype(np.int64)  # the edge's lower sample, or the cell
        p = verts.astype(np.float64)
        edge = kind != _CENTRE
        step = np.eye(3, dtype=np.int64)[kind[edge]]
        a = u[tuple(low[edge].T)].astype(np.float64)
        z = u[tuple((low[edge] + step).T)].astype(np.float64)
        p[edge] = low[edge] + step * ((target - a) / (z - a))[:, None]
        g = low + lo + 1
        keys.append(((g[:, 0] * stride + g[:, 1]) * stride + g[:, 2]) * 4 + kind)
        points.append(p + lo)
        faces.append(tris.astype(np.int64) + count)
        count += len(verts)
    if not keys:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(keys), np.concatenate(points), np.concatenate(faces)


def field_to_mesh(field: SparseField, *, level: float = 0.0) -> Mesh:
    """The ``field == level`` surface of a sparse narrow-band field, by marching cubes.

    Host-side (numpy and scikit-image), block by block, without an R^3 array; see the module
    docstring for the method. Missing samples take the clamp ``s * band * h`` of
    `jaxvox.sample`, with ``s`` decided once per sample from its 26 neighbours; only cells
    with a corner in the band are marched. For the exact signed distance field of a closed
    surface inside the grid with ``band >= 2`` (`jaxvox.sparse_distance_field` of a
    watertight mesh) the result is closed: every edge is used by exactly two faces, in
    opposite directions. At ``level = 0`` its vertices lie where the trilinear
    interpolation of the band values (`jaxvox.sample`) equals 0 on the voxel-centre edges.
    The output does not depend on the block size: vertices are sorted by their edge, faces
    by their vertices.

    Args:
      field: a `SparseField` (not batched), e.g. from `jaxvox.sparse_distance_field`.
      level: iso level in world units, ``|level| < field.band * voxel_size``: positive
        levels give the outward offset surface.

    Returns:
      A `Mesh`: vertices [V, 3] float32 world coordinates, faces [F, 3] int32
      counter-clockwise seen from outside (where the field exceeds `level`), so normals
      point towards increasing distance. 0 vertices and 0 faces when the field is empty
      (``count == 0``) or does not cross `level`.

    Raises:
      JaxvoxError: `field` is not a single `SparseField` or holds non-finite values;
        `level` is not a finite number or ``|level| >= band * voxel_size`` (no surface
        there is represented by the band).
    """
    check_type("field_to_mesh field", field, SparseField)
    level = check_number("field_to_mesh level", level)
    if np.ndim(field.values) != 1 or np.ndim(field.grid.voxel_size) != 0:
        raise refuse("field_to_mesh field", "must be a single field, not a batch", np.shape(field.values))
    h = float(field.grid.voxel_size)
    limit = field.band * h
    if not abs(level) < limit:
        raise refuse(
            "field_to_mesh level",
            f"must satisfy |level| < band * voxel_size = {field.band} * {h:g} = {limit:g} "
            "(beyond the band the field holds no surface)",
            level,
        )
    n = int(field.count)
    values = np.asarray(field.values)[:n]  # (cut on the host: no program per count)
    if not np.isfinite(values).all():
        raise refuse("field_to_mesh field", "values must be finite", values[~np.isfinite(values)][0])
    keys, points, faces = _march(field, level, BLOCK, values)
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    turn = faces.argmin(1)[:, None]  # rotate each face to start at its lowest vertex (same orientation)
    faces = np.take_along_axis(faces, (turn + np.arange(3)) % 3, axis=1)
    faces = faces[np.lexsort(faces.T[::-1])]
    origin = np.asarray(field.grid.origin, np.float64)
    vertices = origin + (points[first] + 0.5) * h
    return Mesh(vertices.astype(np.float32), faces.astype(np.int32))
