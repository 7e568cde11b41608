"""Certified inside/outside sides from a grid of cells: occupancy at many points without a
winding-number sum per point.

**Why it holds.** Cap every boundary loop of the mesh with a fan of triangles from the
loop's centroid, each cap triangle ``(b, a, o)`` cancelling the boundary edge ``a -> b``:
mesh and caps then form a closed chain, so their winding number ``W`` is an integer,
constant on every connected piece of space that no triangle touches, and the mesh's own
winding number is ``w = W - W_caps`` everywhere off the surfaces. The mesh's box (with
two free cells around it) is cut into ``R^3`` cubic cells; mesh and caps are voxelized
conservatively (every cell whose closed box a triangle touches), that set is grown by one
cell (a float32 point can be placed one cell off near a cell face), and the 6-connected
components of the remaining *free* cells are labelled: ``W`` is one integer per component,
computed at one cell centre of each (exact winding sums). At a point in a free cell the
caps' winding number is bounded by area over squared distance,
``|W_caps(x)| <= sum_g A_g / (4 pi d_g(x)^2)`` over groups ``g`` of caps inside balls
(``d_g`` the distance to the ball), so where that bound is below ``|W - 1/2| - MARGIN``
the side is ``W``'s (inside iff ``W >= 1``) and ``|w - 1/2| > MARGIN``.

**Next to the surface** (`_walked_sides`, for the points the cells left open): each
uncertain cell keeps the shortest walk along an axis (at most `RUN` cells) to a certain
cell, and the triangles whose boxes meet it. ``W`` at the point is the certain cell's
plus the signed crossings of the axis-parallel segment from the point to that cell (a
triangle crossed along its normal adds 1): a 2D point-in-triangle test in the plane
across the axis, each crossing counted in the one cell that holds it. A crossing within
`TOLERANCE` of a triangle edge, of a cell face or of the point itself, a nearly edge-on
triangle, or a crowded cell (more triangles than a pass takes, `PASSES`) leaves the point uncertain.
There the caps' winding number is summed exactly (up to `CAP_EXACT` cap triangles), so
``w = W - W_caps`` decides wherever it is `EXACT_MARGIN` plus a bound on the float32
rounding of that sum away from 1/2 (`jaxvox._core.geometry.solid_angle_rounding`: large
only for points next to a cap). What is still open (on
the surface, a walk that failed, a mesh with thousands of holes) is left to the
winding-number path (`jaxvox.points.queries`).

Cost: voxelizing mesh and caps at ``R^3``, labelling ``R^3`` cells and listing the
triangles of the uncertain cells on the host, once per (index, R) and cached beside the
index; then per point a cell lookup and the cap bound, and for the points in cells next
to the surface 64 crossing tests (a second pass with more for a few) and the caps' solid angles; one
compiled program each per (R, point count bucket). Memory: an int8 and an int32 per cell,
plus the uncertain cells' walks and triangle lists.
"""

from __future__ import annotations

import dataclasses
import functools
import weakref

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox import morton
from jaxvox._core.geometry import solid_angle_rounding
from jaxvox._core.pytree import pytree_dataclass
from jaxvox._core.shapes import bucket, pad_rows
from jaxvox.distance.topology import boundary_chain, connected_components, weld
from jaxvox.distance.winding import host_winding_numbers
from jaxvox.grid import Grid
from jaxvox.mesh import Mesh
from jaxvox.points.index import MeshIndex
from jaxvox.points.winding import exact_winding

UNKNOWN = -128  # int8 cell value: a surface cell, one next to it, or a component without a certain W
MARGIN = 0.05  # sides from a cell or a bound have |w - 1/2| above this
EXACT_MARGIN = 1e-3  # sides from a walk with the caps summed exactly: |w - 1/2| above this
CAP_GROUPS = 16  # balls bounding the caps (loops grouped along a Morton curve when more)
PAD_CELLS = 2  # free cells around the mesh's box on each side
RESOLUTION = 128  # cells per axis
# the walks: (longest walk in cells, most triangles per cell on it, points per call), a
# short pass for every point the cells left open, then a long one for those still open
PASSES = ((4, 16, 1 << 16), (16, 64, 1 << 10))
RUN = PASSES[-1][0]  # walks are kept up to this length
CAP_EXACT = 4096  # the most cap triangles summed exactly per point
MAX_PAIRS = 1 << 25  # (cell, triangle) pairs listed at most
# the smallest table sizes (then the ladder): meshes up to about these sizes share programs
FLOORS = {"walks": 1 << 18, "lists": 1 << 20, "corners": 1 << 17, "caps": 256}
TOLERANCE = 1e-3  # crossings this close (in cells, or relative) to an edge, a cell face or the point are uncertain


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class SideGrid:
    """The cells of `side_grid` (device arrays, `resolution` R static). Positions are
    relative to ``origin``, in float32.

    Attributes:
      winding: [R^3] int8 ``W`` per cell (x-major: ``(i R + j) R + k``), `UNKNOWN` for the
        uncertain cells.
      slot: [R^3] int32 each uncertain cell's row S in the tables below, -1 for the others.
      walk: [S, 4] int32 per uncertain cell, the shortest axis-parallel walk to a certain
        cell: axis (0..2), step (1 or -1), length L (1..`RUN`; 0: none) and that cell's W.
      first: [S + 1] int32 where each uncertain cell's triangles start in ``triangles``.
      triangles: [P] int32 rows of ``corners`` whose bounding box meets the cell.
      corners: [T, 9] float32 corners a, b, c (xyz each) of the mesh's and the caps' triangles.
      caps: [C, 9] float32 corners of the cap triangles (padding: zeros, no solid angle);
        [0, 9] when there are more than `CAP_EXACT`.
      balls: [G, 5] float32 balls bounding groups of cap triangles: centre xyz, radius,
        total area / (4 pi) (padding rows: area 0).
      origin: [3] float32 world position of the grid's minimum corner.
      cell: [] float32 edge of a cell.
      resolution: R.
    """

    winding: jax.Array
    slot: jax.Array
    walk: jax.Array
    first: jax.Array
    triangles: jax.Array
    corners: jax.Array
    caps: jax.Array
    balls: jax.Array
    origin: jax.Array
    cell: jax.Array
    resolution: int = dataclasses.field(metadata={"static": True})


def cap_triangles(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cap triangles [C, 3, 3] float64 closing every boundary loop of the mesh (welded), and
    their loop ids [C] int64 (0..L-1): for each boundary edge a -> b of the chain
    (`jaxvox.distance.topology.boundary_chain`), the triangle (b, a, o) with o the centroid of
    the loop's vertices."""
    weld_v, welded = weld(np.asarray(vertices, np.float64), faces)
    edges = boundary_chain(welded)
    if len(edges) == 0:
        return np.zeros((0, 3, 3)), np.zeros(0, np.int64)
    used, local = np.unique(edges, return_inverse=True)
    local = local.reshape(edges.shape)
    label = connected_components(len(used), local[:, 0], local[:, 1])
    _, loop_of_vertex = np.unique(label, return_inverse=True)
    loops = int(loop_of_vertex.max()) + 1
    counts = np.bincount(loop_of_vertex, minlength=loops)[:, None]
    centroid = np.stack([np.bincount(loop_of_vertex, weld_v[used][:, k], loops) for k in range(3)], 1) / counts
    loop = loop_of_vertex[local[:, 0]]
    tris = np.stack([weld_v[edges[:, 1]], weld_v[edges[:, 0]], centroid[loop]], 1)
    return tris, loop


def _cap_balls(tris: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """[CAP_GROUPS, 5] float32 balls (centre, radius, area / 4 pi) bounding the caps, each
    a group of whole loops; unused rows have area 0."""
    loops = int(loop.max()) + 1 if len(loop) else 0
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    centre = tris[:, 2]  # each loop's centroid o: every cap triangle lies in the ball about it
    reach = np.linalg.norm(tris - centre[:, None], axis=-1).max(1)
    loop_centre = np.zeros((loops, 3))
    loop_centre[loop] = centre
    loop_radius = np.zeros(loops)
    np.maximum.at(loop_radius, loop, reach)
    loop_area = np.bincount(loop, area, loops)
    group = np.arange(loops)
    if loops > CAP_GROUPS:
        group[morton.curve_order_host(loop_centre)] = np.arange(loops) * CAP_GROUPS // loops
    groups = int(group.max()) + 1 if loops else 0
    out = np.zeros((CAP_GROUPS, 5))
    for g in range(groups):
        members = group == g
        c = loop_centre[members].mean(0)
        out[g, :3] = c
        out[g, 3] = (np.linalg.norm(loop_centre[members] - c, axis=1) + loop_radius[members]).max()
        out[g, 4] = loop_area[members].sum() / (4 * np.pi)
    return out.astype(np.float32)


def _dilated(coords: np.ndarray, resolution: int) -> np.ndarray:
    """[R, R, R] bool: the cells of `coords` [n, 3] and their 26 neighbours."""
    marked = np.zeros((resolution + 2,) * 3, bool)
    i, j, k = (coords[:, a] + 1 for a in range(3))
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            for dk in (-1, 0, 1):
                marked[i + di, j + dj, k + dk] = True
    return marked[1:-1, 1:-1, 1:-1]


def _first_cells(labels: np.ndarray, count: int) -> np.ndarray:
    """[count] flat index of one cell of each label 1..count."""
    flat = labels.ravel()
    first = np.searchsorted(np.maximum.accumulate(flat), np.arange(1, count + 1))
    if np.array_equal(flat[np.minimum(first, len(flat) - 1)], np.arange(1, count + 1)):
        return first  # labels numbered in scan order (scikit-image's), found by a running max
    _, first = np.unique(flat, return_index=True)
    return first[1:]


def side_grid(index: MeshIndex, resolution: int = RESOLUTION) -> SideGrid:
    """The cells of the index's mesh at `resolution` (a power of two >= 16); host, cached
    per (index, resolution) while the index lives."""
    cache = _CACHE.get(id(index))
    if cache is None or cache[0]() is not index:
        cache = _CACHE[id(index)] = (weakref.ref(index), {})
        weakref.finalize(index, _CACHE.pop, id(index), None)
    if resolution not in cache[1]:
        cache[1][resolution] = _build(index, resolution)
    return cache[1][resolution]


_CACHE: dict[int, tuple[weakref.ref, dict[int, SideGrid]]] = {}


def _component_windings(index: MeshIndex, caps: np.ndarray, grid: Grid, free: np.ndarray) -> np.ndarray:
    """[R^3] int8 ``W`` of each free cell's component (`UNKNOWN` elsewhere, and for a
    component whose sum at its first cell's centre is not within 0.25 of an integer)."""
    from skimage.measure import label as label_components

    labels, components = label_components(free, connectivity=1, return_num=True)
    if not components:
        return np.full(free.size, UNKNOWN, np.int8)
    first = _first_cells(labels, components)
    ijk = np.stack(np.unravel_index(first, labels.shape), 1)
    centres = np.asarray(grid.origin, np.float64) + (ijk + 0.5) * float(grid.voxel_size)
    total = exact_winding(index, centres)
    if len(caps):
        total += host_winding_numbers(caps, centres)
    w = np.round(total)
    certain = (np.abs(total - w) < 0.25) & (np.abs(w) < 100)
    per_label = np.concatenate([[UNKNOWN], np.where(certain, w, UNKNOWN)]).astype(np.int8)
    return np.where(free.ravel(), per_label[labels.ravel()], UNKNOWN).astype(np.int8)


def _walks(winding: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Slots [R^3] int32 of the uncertain cells and their walks [S, 4] (`SideGrid`)."""
    certain = winding != UNKNOWN
    cells = np.flatnonzero(~certain)
    slot = np.full(winding.size, -1, np.int32)
    slot[cells] = np.arange(len(cells))
    ijk = np.stack(np.unravel_index(cells, (resolution,) * 3), 1)
    walk = np.zeros((len(cells), 4), np.int32)
    for axis in range(3):
        for step in (1, -1):
            run = np.zeros(len(cells), np.int32)
            target = np.zeros(len(cells), np.int32)
            for length in range(RUN, 0, -1):  # the shortest wins
                q = ijk.copy()
                q[:, axis] += length * step
                ok = (q[:, axis] >= 0) & (q[:, axis] < resolution)
                flat = np.ravel_multi_index(q.T, (resolution,) * 3, mode="clip")
                found = ok & certain[flat]
                run = np.where(found, length, run)
                target = np.where(found, winding[flat], target)
            better = (run > 0) & ((walk[:, 2] == 0) | (run < walk[:, 2]))
            walk[better] = np.stack([np.full(len(cells), axis), np.full(len(cells), step), run, target], 1)[better]
    return slot, walk


def _cell_triangles(tris: np.ndarray, slot: np.ndarray, cell: float, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """(first [S + 1], triangles [P]) int32: the triangles [T, 3, 3] (relative to the grid's
    origin) whose bounding box meets each uncertain cell; empty lists past `MAX_PAIRS`."""
    lo = np.clip(np.floor(tris.min(1) / cell), 0, resolution - 1).astype(np.int64)
    hi = np.clip(np.floor(tris.max(1) / cell), 0, resolution - 1).astype(np.int64)
    ext = hi - lo + 1
    sizes = ext.prod(1)
    slots = int(slot.max()) + 1
    if sizes.sum() > MAX_PAIRS:
        return np.zeros(slots + 1, np.int32), np.zeros(1, np.int32)
    tri = np.repeat(np.arange(len(tris)), sizes)
    local = np.arange(sizes.sum()) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    e = ext[tri]
    k, j, i = local % e[:, 2], local // e[:, 2] % e[:, 1], local // (e[:, 2] * e[:, 1])
    s = slot[((lo[tri, 0] + i) * resolution + lo[tri, 1] + j) * resolution + lo[tri, 2] + k]
    keep = s >= 0
    order = morton.stable_order_host(s[keep])
    first = np.concatenate([[0], np.cumsum(np.bincount(s[keep], minlength=slots))])
    return first.astype(np.int32), np.concatenate([tri[keep][order], [0]]).astype(np.int32)


def _build(index: MeshIndex, resolution: int) -> SideGrid:
    from jaxvox.voxelize import voxelize

    count = int(index.num_faces)
    faces = np.asarray(index.faces)[:count]
    vertices = np.asarray(index.vertices, np.float64)
    caps, loop = cap_triangles(vertices, faces)
    used = vertices[np.unique(faces)]
    lo, hi = used.min(0), used.max(0)
    cell = max(float((hi - lo).max()), 1e-30) / (resolution - 2 * PAD_CELLS) * (1 + 1e-6)
    grid = Grid(origin=np.float32(lo - PAD_CELLS * cell), voxel_size=np.float32(cell), resolution=resolution)
    origin, cell = np.asarray(grid.origin, np.float64), float(grid.voxel_size)
    cap_v = caps.reshape(-1, 3)
    surface = Mesh(
        np.concatenate([vertices, cap_v]).astype(np.float32),
        np.concatenate([faces, len(vertices) + np.arange(len(cap_v)).reshape(-1, 3)]).astype(np.int32),
    )
    vox = voxelize(surface, grid, progress=False)
    free = ~_dilated(np.asarray(vox.coords)[: int(vox.count)], resolution)
    winding = _component_windings(index, caps, grid, free)
    slot, walk = _walks(winding, resolution)
    tris = np.concatenate([vertices[faces], caps]) - origin
    first, triangles = _cell_triangles(tris, slot, cell, resolution)
    cap_rows = (caps - origin).reshape(-1, 9).astype(np.float32)
    exact_caps = pad_rows(cap_rows, bucket(len(caps), FLOORS["caps"])) if len(caps) <= CAP_EXACT else cap_rows[:0]
    put = jax.device_put
    # tables padded to the ladder (one program for meshes of any size); the last walk row
    # (zeros: no walk) is for points without a slot
    rows = bucket(len(walk) + 1, FLOORS["walks"])
    return SideGrid(
        winding=put(winding),
        slot=put(slot),
        walk=put(pad_rows(walk, rows)),
        first=put(pad_rows(first, rows + 1, first[-1])),
        triangles=put(pad_rows(triangles, bucket(len(triangles), FLOORS["lists"]))),
        corners=put(pad_rows(tris.reshape(-1, 9).astype(np.float32), bucket(len(tris), FLOORS["corners"]))),
        caps=put(exact_caps),
        balls=put(_cap_balls(caps - origin, loop)),
        origin=put(np.asarray(grid.origin, np.float32)),
        cell=put(np.asarray(grid.voxel_size, np.float32)),
        resolution=resolution,
    )


def _cell_of(cell, r: int, rel):
    """(ijk [n, 3] int32 clipped, flat [n] int32, in_grid [n] bool) of positions rel [n, 3]
    in R = `r` cells of edge `cell` per axis."""
    ijk = jnp.floor(rel / cell)
    in_grid = jnp.all((ijk >= 0) & (ijk < r), -1)
    ijk = jnp.clip(ijk, 0, r - 1).astype(jnp.int32)
    return ijk, (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2], in_grid


def _cap_bound(b, rel):
    """[n] float32 upper bound on |W_caps| at positions rel [n, 3] (inf inside a ball) from
    the balls b [G, 5] (`SideGrid.balls`)."""
    d = jnp.sqrt(jnp.sum((rel[:, None, :] - b[None, :, :3]) ** 2, -1)) - b[None, :, 3]
    term = jnp.where(d > 0, b[None, :, 4] / jnp.where(d > 0, d * d, 1.0), jnp.inf)
    return jnp.sum(jnp.where(b[None, :, 4] > 0, term, 0.0), -1)


@functools.partial(jax.jit, static_argnames="resolution")
def _cell_sides(winding, balls, origin, cell, points, *, resolution: int):
    """[n] int8 sides of points [n, 3] (world) from their cells (`SideGrid` fields; not the
    whole grid, whose other tables' sizes would key the program): 1 inside, 0 outside, -1
    not certain (non-finite points too)."""
    rel = points - origin
    _, flat, in_grid = _cell_of(cell, resolution, rel)
    w = jnp.where(in_grid, winding[flat], 0).astype(jnp.int32)
    finite = jnp.all(jnp.isfinite(points), -1)
    certain = finite & (w != UNKNOWN) & (_cap_bound(balls, rel) < jnp.abs(w - 0.5) - MARGIN)
    return jnp.where(certain, (w >= 1).astype(jnp.int8), jnp.int8(-1))


def _crossing(p, t, axis, tol):
    """Signed crossings of the line through points p [m, 3] along `axis` [m] with triangles
    t [m, 9], all relative to the grid: (hit [m] bool, position along the axis [m], sign
    [m] +-1 of the normal's axis component, ambiguous [m] bool)."""
    perm = jnp.stack([(axis + 1) % 3, (axis + 2) % 3, axis], 1)  # (u, v, axis): right-handed
    q = jnp.take_along_axis(p, perm, 1)
    c = [jnp.take_along_axis(t[:, 3 * i : 3 * i + 3], perm, 1) - q for i in range(3)]
    orient = lambda x, y: x[:, 0] * y[:, 1] - x[:, 1] * y[:, 0]
    norm = lambda x: jnp.sqrt(x[:, 0] * x[:, 0] + x[:, 1] * x[:, 1])
    e = [orient(c[1], c[2]), orient(c[2], c[0]), orient(c[0], c[1])]
    scale = [norm(c[1]) * norm(c[2]), norm(c[2]) * norm(c[0]), norm(c[0]) * norm(c[1])]
    pos = [ek > tol * sk for ek, sk in zip(e, scale)]
    neg = [ek < -tol * sk for ek, sk in zip(e, scale)]
    outside = (pos[0] | pos[1] | pos[2]) & (neg[0] | neg[1] | neg[2])
    inside = (pos[0] & pos[1] & pos[2]) | (neg[0] & neg[1] & neg[2])
    area = e[0] + e[1] + e[2]
    thin = jnp.abs(area) < 1e-3 * jnp.maximum(jnp.maximum(scale[0], scale[1]), scale[2])
    safe = jnp.where(area != 0, area, 1.0)
    along = (e[0] * c[0][:, 2] + e[1] * c[1][:, 2] + e[2] * c[2][:, 2]) / safe
    ambiguous = ~outside & (~inside | thin)
    return inside & ~thin, q[:, 2] + along, jnp.where(area > 0, 1, -1), ambiguous


@functools.partial(jax.jit, static_argnames=("run", "per_cell"))
def _walked_sides(g: SideGrid, rel, *, run: int, per_cell: int):
    """[m] int8 sides (1, 0, -1 not certain) and [m] float32 values (`grid_sides`) of
    finite positions rel [m, 3] (relative to the grid's origin): ``W`` of their cell, or of
    the end of their cell's walk (at most `run` cells, `per_cell` triangles a cell) plus
    the signed crossings on the way; then ``w = W - W_caps`` with the caps summed exactly."""
    ijk, flat, in_grid = _cell_of(g.cell, g.resolution, rel)
    w_cell = jnp.where(in_grid, g.winding[flat], 0).astype(jnp.int32)
    s = jnp.where(in_grid, g.slot[flat], -1)
    walk = g.walk[jnp.where(s >= 0, s, g.walk.shape[0] - 1)]
    axis, step, length = walk[:, 0], walk[:, 1], walk[:, 2]
    offsets = jnp.arange(run)[None, :] * step[:, None]  # [m, run]
    along_cell = jnp.take_along_axis(ijk, axis[:, None], 1) + offsets  # cell index along the axis
    onehot = jax.nn.one_hot(axis, 3, dtype=jnp.int32)
    cells = ijk[:, None, :] + offsets[:, :, None] * onehot[:, None, :]
    r = g.resolution
    cells = jnp.clip(cells, 0, r - 1)
    slots = g.slot[(cells[..., 0] * r + cells[..., 1]) * r + cells[..., 2]]
    on_walk = (jnp.arange(run)[None, :] < length[:, None]) & (slots >= 0)
    start = g.first[jnp.maximum(slots, 0)]
    count = jnp.where(on_walk, g.first[jnp.maximum(slots, 0) + 1] - start, 0)
    x_along = jnp.take_along_axis(rel, axis[:, None], 1)[:, 0]
    tol_cell = TOLERANCE * g.cell

    def body(i, state):
        total, ambiguous = state
        k, j = i // per_cell, i % per_cell
        use = j < count[:, k]
        t = g.corners[g.triangles[jnp.where(use, start[:, k] + j, 0)]]
        hit, at, sign, unsure = _crossing(rel, t, axis, TOLERANCE)
        f = at / g.cell - along_cell[:, k]  # within the walk's k-th cell: 0 <= f < 1
        ahead = (at - x_along) * step
        mine = (f >= 0) & (f < 1) & (ahead > 0)
        edge = (jnp.abs(f) < TOLERANCE) | (jnp.abs(f - 1) < TOLERANCE) | (jnp.abs(ahead) < tol_cell)
        total = total + jnp.where(use & hit & mine, sign * step, 0)
        return total, ambiguous | (use & (unsure | (hit & edge)))

    total, ambiguous = jax.lax.fori_loop(
        0, run * per_cell, body, (jnp.zeros(rel.shape[0], jnp.int32), jnp.zeros(rel.shape[0], bool))
    )
    overflow = jnp.any(count > per_cell, 1) | (length > run)
    walked = (s >= 0) & (length > 0) & (walk[:, 3] != UNKNOWN) & ~ambiguous & ~overflow
    w = jnp.where(s >= 0, walk[:, 3] + total, w_cell)
    known = jnp.where(s >= 0, walked, w_cell != UNKNOWN)
    caps = g.caps
    exact = caps.shape[0] > 0
    value = w.astype(jnp.float32)
    if exact:  # w itself, to the float32 rounding of the caps' sum (bounded per term)

        def add(i, acc):
            angle, rounding = solid_angle_rounding(rel, caps[i].reshape(3, 3)[None])
            return acc[0] - angle, acc[1] + rounding

        value, rounding = jax.lax.fori_loop(0, caps.shape[0], add, (value, jnp.zeros_like(value)))
        certain = known & (jnp.abs(value - 0.5) > EXACT_MARGIN + rounding)
    else:  # W alone: the caps' bound must leave it on its side
        certain = known & (_cap_bound(g.balls, rel) < jnp.abs(value - 0.5) - MARGIN)
    return jnp.where(certain, (value > 0.5).astype(jnp.int8), jnp.int8(-1)), value


def grid_sides(index: MeshIndex, points: np.ndarray, resolution: int = RESOLUTION) -> tuple[np.ndarray, np.ndarray]:
    """Sides [n] int8 of points [n, 3] (host float32, world): 1 inside, 0 outside, -1 not
    certain (for the winding-number path); and stand-ins [n] float32 for their winding
    numbers, on the same side of 1/2: 1 or 0 for a side from a cell (``|w - 1/2| >
    MARGIN``), ``w`` itself for one from a walk with the caps summed exactly (NaN where
    not certain). Programs per point-count bucket and walk pass."""
    g = side_grid(index, resolution)
    n = len(points)
    padded = pad_rows(np.asarray(points, np.float32), bucket(n))
    sides = np.array(_cell_sides(g.winding, g.balls, g.origin, g.cell, padded, resolution=resolution))[:n]
    w = np.where(sides >= 0, sides, np.nan).astype(np.float32)
    again = np.flatnonzero((sides < 0) & np.all(np.isfinite(points), -1))
    rel = np.asarray(points[again], np.float64) - np.asarray(g.origin, np.float64)
    for run, per_cell, size in PASSES:  # fixed chunks: one program per pass
        for start in range(0, len(again), size):
            part = rel[start : start + size]
            side, value = _walked_sides(g, pad_rows(part.astype(np.float32), size), run=run, per_cell=per_cell)
            rows = again[start : start + size]
            sides[rows] = np.asarray(side)[: len(part)]
            w[rows] = np.where(sides[rows] >= 0, np.asarray(value)[: len(part)], np.nan)
        still = sides[again] < 0
        again, rel = again[still], rel[still]
    return sides, w
