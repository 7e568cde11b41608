"""Cascaded clipmaps of clamped signed distance fields around a moving camera.

`build_clipmap` and `update_clipmap` (host-side; a move recomputes only the newly
exposed slabs of each cascade, stored toroidally), `time_sliced_cascades` (which cascade
to update per frame), `union_clipmaps` (with a dynamic object's clipmap) and
`trace_clipmap` (sphere tracing through the cascades, jittable). See `Clipmap` for
the layout and for how the exposed voxels are computed.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.checks import check_choice, check_int, check_number, check_type, check_vector, is_concrete, refuse
from jaxvox._core.geometry import rows_dist2, triangle_rows
from jaxvox._core.hit import RUNNING
from jaxvox._core.pytree import pytree_dataclass
from jaxvox._core.shapes import bucket, expand_counts, pad_rows
from jaxvox.distance.band_sign import EXACT_BELOW
from jaxvox.distance.field import METHODS, box_distance, box_grid
from jaxvox.distance.solid import grid_triangles, open_edges, padded_mesh, parity_boxes, solid_inside
from jaxvox.distance.winding import box_winding_numbers, brute_force_winding_numbers
from jaxvox.grid import Grid, check_resolution
from jaxvox.mesh import Mesh, host_triangles, validate_mesh
from jaxvox.trace import HIT, MISS, STEP_CAP, Hit

_CORNERS = tuple(np.ndindex(2, 2, 2))  # corner offsets of a trilinear cell
ROW = 8  # voxels per work slot of the "exact" kernel: a row along its box's longest (contiguous) side
ROW_WINDOW = 1 << 13  # work slots (ROW * ROW_WINDOW pairs) per step of the "exact" kernel
ITEM_CHUNK = 1 << 14  # (triangle, box) items per call of the "exact" kernel (a fixed shape)
PAIR_CHUNK = 1 << 30  # at most this many pairs per call of the "exact" kernel (int32 counters)
_ROWS = jax.lax.ScatterDimensionNumbers(  # a row of ROW consecutive cells per index
    update_window_dims=(1,), inserted_window_dims=(), scatter_dims_to_operand_dims=(0,)
)


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
    With ``method="exact"`` (the default) the exposed boxes of all updated cascades are
    computed together, from the band: a voxel's distance is the minimum of the float32
    point-triangle distances over the triangles whose bounding box, dilated by the
    truncation, holds its centre (every triangle within the clamp; farther voxels sit at
    the clamp), each pair evaluated in grid units relative to a lattice voxel fixed by
    the triangle, and the sign is the box's solid voxelization (parity for watertight
    meshes; else winding numbers, those within `EXACT_BELOW` of 1/2 summed by brute
    force). A voxel's value is then a function of its position only: any sequence of
    moves gives bit for bit the cascade of a build from scratch. With a `distance_field`
    method (e.g. "jfa+sweep", the seed's pipeline) each slab is a *scissor volume*: the
    pipeline runs on the slab grown by ``truncation + 1`` voxels on every side, from the
    faces near it (every face within the clamp of a slab voxel is in the grown box), with
    its axes ordered by length (slabs across x, y and z share one compiled pipeline), and
    the sign is the same solid voxelization of the slab. A build from scratch is the
    same computation on the whole window. With ``"band"`` the pipeline is the narrow
    band alone, ``truncation + 1`` passes from the surface voxels of the grown box only:
    a voxel's value then depends on the seeds within that many voxels, all inside the
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
      sign: static str, the inside test of the mesh it was built from: "parity"
        (watertight) or "winding" (open edges), decided once by `build_clipmap`.
    """

    fields: jax.Array  # [N, R, R, R] float32
    corner: jax.Array  # [N, 3] int32
    origin: jax.Array  # [3] float32
    voxel_size: jax.Array  # [] float32
    truncation: float = dataclasses.field(metadata=dict(static=True))
    method: str = dataclasses.field(metadata=dict(static=True))
    sign: str = dataclasses.field(metadata=dict(static=True))

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


def _side(n: int, r: int, pad: int) -> int:
    """A box side of `n` voxels plus `pad` rounded up so that moves share compiled code:
    a side longer than R/2 to R (plus the pad), a shorter one to the power of two above
    it (`bucket`)."""
    return r + pad if 2 * n > r else bucket(n + pad, 4)


def _scissor_values(mesh: Mesh, padded: Mesh, bounds, lo, hi, h: float, clip: Clipmap):
    """Clamped signed distances [hi - lo] of the lattice box [lo, hi) of voxels of edge h.

    The scissor volume: `clip.method`'s pipeline runs on the box grown by the truncation
    plus one voxel on every side, from the faces near that grown box only (a farther face
    is beyond the clamp from every voxel of the box); the sign is the solid voxelization
    of the box itself from the whole mesh. Box sides go through `_side`, and the
    pipeline sees the box's axes sorted by length.
    """
    origin = np.asarray(clip.origin, np.float64)
    size: tuple[int, int, int] = tuple(int(n) for n in hi - lo)  # type: ignore[assignment]
    margin = math.ceil(clip.truncation) + 1
    r = clip.resolution
    shape: tuple[int, int, int] = tuple(_side(n, r, 2 * margin) for n in size)  # type: ignore[assignment]
    corner = origin + (lo - margin) * h
    limit = np.float32(clip.truncation * h)
    near = _near_faces(mesh, bounds, corner - h, corner + (np.asarray(shape) + 1) * h)
    if near is None:
        d = np.full(size, limit)
    else:
        band = margin if clip.method == "band" else int(clip.method == "jfa+sweep")
        # The box's axes in order of length, so that slabs across x, y and z share one
        # program: the distance does not depend on the order of the axes.
        order = np.argsort(shape, kind="stable")
        sorted_shape: tuple[int, int, int] = tuple(int(shape[a]) for a in order)  # type: ignore[assignment]
        field = box_distance(
            Mesh(np.asarray(near.vertices)[:, order], near.faces),
            box_grid(corner[order], h, sorted_shape),
            sorted_shape,
            method=clip.method,
            band=band,
            sweeps=3,
            clamped=clip.method != "band",
        )
        box = np.asarray(field).transpose(np.argsort(order))
        cut = box[margin : margin + size[0], margin : margin + size[1], margin : margin + size[2]]
        d = np.minimum(cut * np.float32(h), limit)
    sign_shape: tuple[int, int, int] = tuple(_side(n, r, 0) for n in size)  # type: ignore[assignment]
    grid = box_grid(origin + lo * h, h, sign_shape)
    inside = np.asarray(solid_inside(mesh, grid_triangles(padded, grid), grid, sign_shape, clip.sign, 2.0))
    return np.where(inside[: size[0], : size[1], : size[2]], -d, d)


def _refresh(fields: np.ndarray, mesh: Mesh, padded: Mesh, cascade: int, old, new, clip: Clipmap):
    """Writes the voxels of cascade `cascade` in window `new` that window `old` lacks with
    a pipeline method into the host copy `fields` [N, R, R, R] (`padded`: `padded_mesh(mesh)`;
    the sign is ``clip.sign``'s solid voxelization). Box values are cut and written on the host: no
    small program per box shape."""
    r = fields.shape[-1]
    h = float(clip.voxel_size) * 2.0**cascade
    tris = host_triangles(mesh)
    bounds = np.stack([tris.min(1), tris.max(1)])  # [2, F, 3]: once per cascade, not per box
    for lo, hi in _exposed_boxes(old, new, r):
        slots = np.ix_(*(np.mod(np.arange(a, b), r) for a, b in zip(lo, hi)))
        fields[cascade][slots] = _scissor_values(mesh, padded, bounds, lo, hi, h, clip)


@functools.partial(jax.jit, donate_argnums=0)
def _pair_minima(d2, rows, first, ext, axis, shift, base, stride):
    """Scatter-min of squared point-triangle distances over (triangle, voxel) pairs.

    Item t pairs triangle ``rows[t]`` with the voxels ``first[t] + [0, ext[t])`` of its
    *anchor* frame (grid units with the triangle's anchor voxel at 0, so a pair's float32
    arithmetic is the same whatever box it is computed for); in its box, voxel p of that
    frame is ``p + shift[t]``, stored at ``base[t] + (p + shift[t]) . stride[t]``. Work
    slots are rows of `ROW` voxels along the box's contiguous axis ``axis[t]`` (stride
    1): a slot's indexing and gathers serve `ROW` pairs, and its minima go to d2 as one
    window of `ROW` consecutive cells (XLA:CPU spends several times longer on a scatter
    of single cells). Cells of a row past its item get +inf (no change).

    Args:
      d2: [V] float32 squared distances (grid units) of the boxes' voxels, flat, +inf
        where no pair has arrived, at least `ROW` cells past the last voxel (donated).
      rows: [T, 28] float32 the triangles' `triangle_rows` (transposed), in the items'
        anchor frames; first, ext, shift: [T, 3] int32 (padding items: ext 0);
      axis: [T, 1] int32; base: [T, 1] int32; stride: [T, 3] int32.

    Returns:
      The updated d2 [V].
    """
    unit = (axis == jnp.arange(3)).astype(jnp.int32)  # [T, 3]: the row axis
    slots = ext + unit * ((ext + ROW - 1) // ROW - ext)  # rows per axis: ceil(ext / ROW) along it
    counts = jnp.prod(slots, axis=1)
    total = jnp.sum(counts)

    def step(state):
        start, d2 = state
        along = jnp.arange(ROW, dtype=jnp.int32)  # here, not closed over: a constant XLA can fold
        owner, rank, valid, _ = expand_counts(counts, ROW_WINDOW, start)
        e, u = jnp.maximum(slots[owner], 1), unit[owner]
        row = jnp.stack([rank // (e[:, 1] * e[:, 2]), (rank // e[:, 2]) % e[:, 1], rank % e[:, 2]], -1)
        row = first[owner] + row + (ROW - 1) * row * u  # the row's first voxel
        p = row[:, None, :] + along[None, :, None] * u[:, None, :]  # [S, ROW, 3]
        length = jnp.sum((first[owner] + ext[owner] - row) * u, 1)[:, None]  # voxels left in the item
        t = rows[owner]
        q = [p[..., k].astype(jnp.float32) + 0.5 for k in range(3)]
        d = rows_dist2(q, [t[:, k, None] for k in range(28)], (0.0, 0.0, 0.0))
        d = jnp.where(valid[:, None] & (along < length), d, jnp.inf)
        v, s = row + shift[owner], stride[owner]  # no reductions over length-3 axes
        cell = jnp.where(valid, base[owner, 0] + v[:, 0] * s[:, 0] + v[:, 1] * s[:, 1] + v[:, 2] * s[:, 2], 0)
        return start + ROW_WINDOW, jax.lax.scatter_min(d2, cell[:, None], d, _ROWS, mode=jax.lax.GatherScatterMode.CLIP)

    return jax.lax.while_loop(lambda state: state[0] < total, step, (jnp.int32(0), d2))[1]


@jax.jit
def _write(fields, d2, scale, limit, negative, slots):
    """`fields` with voxels ``slots`` [V, 4] int32 (cascade, slot; rows with cascade N are
    padding) set to ``min(sqrt(d2) * scale, limit)``, negated where `negative` (all [V])."""
    value = jnp.minimum(jnp.sqrt(d2) * scale, limit)
    value = jnp.where(negative, -value, value)
    return fields.at[slots[:, 0], slots[:, 1], slots[:, 2], slots[:, 3]].set(value, mode="drop")


def _dispatch_inside(mesh: Mesh, padded, boxes: list, r: int, sign: str) -> list:
    """The inside bits of the voxel centres of each box (corner [3] world minimum corner,
    h voxel edge, size [3] voxels) of `boxes` (`padded`: [P, 3, 3] float64 world
    triangles of `padded_mesh(mesh)`): the solid voxelization ("parity"),
    or the fast winding numbers with those within `EXACT_BELOW` of 1/2 summed again by
    brute force ("winding"), so that the sign is the exact inside test's.

    Parity: every box's crossing count is dispatched before any is read, and the
    voxelizations are dispatched, not waited for; "winding" is computed here. Returns the
    bits of each box, [size] or larger from the corner on (device or numpy bool)."""
    side = lambda n: _side(int(n), r, 0)
    shapes = [(side(x), side(y), side(z)) for _, _, (x, y, z) in boxes]
    local = [(padded - corner) / h for corner, h, _ in boxes]  # grid units of each box (padding subtends nothing)
    if sign == "parity":
        return parity_boxes([(jnp.asarray(t, jnp.float32), shape) for t, shape in zip(local, shapes)])
    out = []
    for (corner, h, size), shape, tris in zip(boxes, shapes, local):
        w = np.array(box_winding_numbers(mesh, corner, h, shape))[: size[0], : size[1], : size[2]]
        close = np.argwhere(np.abs(w - 0.5) < EXACT_BELOW)
        if len(close):
            w[tuple(close.T)] = brute_force_winding_numbers(tris, close + 0.5)
        out.append(w > 0.5)
    return out


def _box_items(world, low, high, origin, h: float, lo, hi, reach: float, layout):
    """The work of the lattice box [lo, hi) of voxels of edge h for `_pair_minima`: one
    item per triangle of `world` ([F, 3, 3] float64; `low`, `high`: their bounding boxes
    [F, 3]) that may lie within `reach` of a voxel centre, with the box's voxels in the
    triangle's bounding box dilated by `reach` (on each axis, by what the box's distance
    on the two others leaves of it). `layout`: (base, axis, stride) of the box in the flat
    voxel order (`_layout`). Returns the kernel's arrays (rows, first, ext, axis, shift,
    base, stride), or None."""
    t_lo, t_hi = (low - origin) / h - 0.5, (high - origin) / h - 0.5  # voxel i's centre at i
    anchor = np.ceil(t_lo - reach)  # first voxel of each dilated box, whatever the box
    gap = np.maximum(np.maximum(lo - t_hi, t_lo - (hi - 1)), 0.0)  # from the box's centres, per axis
    rest = reach**2 - (np.sum(gap**2, 1, keepdims=True) - gap**2)  # left for each axis by the two others
    side = np.where(rest >= 0, np.sqrt(np.maximum(rest, 0.0)), -np.inf)
    first = np.maximum(np.ceil(t_lo - side), lo)
    last = np.minimum(np.floor(t_hi + side), hi - 1)
    ids = np.flatnonzero((last >= first).all(1))
    if not len(ids):
        return None
    a = anchor[ids].astype(np.int64)
    rows = triangle_rows((world[ids] - origin) / h - a[:, None]).T
    base, axis, stride = (np.broadcast_to(x, (len(ids), np.size(x))) for x in layout)
    offsets = (first[ids] - a, last[ids] - first[ids] + 1, axis, a - lo, base, stride)
    return (rows, *(x.astype(np.int32) for x in offsets))


def _layout(lo, hi, base: int):
    """The flat order of the box [lo, hi)'s voxels from `base` on: its longest side (the
    last axis on ties) varies fastest, the two others in axis order. Returns (base, axis,
    stride [3] (cells per step along each axis), order [3] (the axes, slowest first))."""
    size = hi - lo
    axis = 2 if size[2] == size.max() else int(np.argmax(size))
    order = [a for a in range(3) if a != axis] + [axis]
    stride = np.zeros(3, np.int64)
    stride[order] = [size[order[1]] * size[axis], size[axis], 1]
    return base, axis, stride, order


def _exact_update(fields, mesh: Mesh, jobs, clip: Clipmap):
    """Writes the lattice boxes ``jobs`` [(cascade, lo, hi)] with the exact clamped signed
    distance, all with one call of `_pair_minima` (per `ITEM_CHUNK` items) and of `_write`.

    A voxel's distance is the minimum over the (triangle, voxel) pairs whose centre lies in
    the triangle's bounding box dilated by ``reach = max(truncation, 1)`` (every triangle
    within the clamp; `_box_items`); other voxels are at the clamp. A box without items is
    farther than one voxel from the surface everywhere, so no segment between neighbouring
    centres crosses it: the whole box has the sign of one voxel (`_dispatch_inside` of a
    single voxel). Total voxels are rounded up to the ladder (at least ``4 R^2``, two
    slabs), so a flight runs a few compiled programs. The device work (signs, then pair
    minima) is dispatched before the host lays out where the values go.
    """
    if not jobs:
        return fields
    origin = np.asarray(clip.origin, np.float64)
    r = clip.resolution
    world, low, high, padded = _host_tables(mesh)
    h = [float(clip.voxel_size) * 2.0**c for c, _, _ in jobs]
    counts = [int(np.prod(hi - lo)) for _, lo, hi in jobs]
    bases = np.cumsum([0] + counts)
    reach = max(clip.truncation, 1.0)
    layouts = [_layout(lo, hi, b) for (_, lo, hi), b in zip(jobs, bases)]
    items = [
        _box_items(world, low, high, origin, hb, lo, hi, reach, layout[:3])
        for (_, lo, hi), hb, layout in zip(jobs, h, layouts)
    ]
    boxes = [  # a box without items has the sign of one voxel
        (origin + lo * hb, hb, (1, 1, 1) if box is None else hi - lo) for (_, lo, hi), hb, box in zip(jobs, h, items)
    ]
    insides = _dispatch_inside(mesh, padded, boxes, r, clip.sign) if mesh.num_faces else []
    rows = bucket(bases[-1] + ROW, 4 * r * r)  # a row starting at the last voxel fits
    d2 = jnp.asarray(np.full(rows, np.inf, np.float32))
    found = [x for x in items if x is not None]
    if found:
        columns = [np.concatenate(x) for x in zip(*found)]  # rows, first, ext, axis, shift, base, stride
        pairs = np.cumsum(columns[2].prod(1))
        start = 0
        while start < len(pairs):  # chunks of at most ITEM_CHUNK items and PAIR_CHUNK pairs
            done = pairs[start - 1] if start else 0
            stop = min(start + ITEM_CHUNK, max(int(np.searchsorted(pairs, done + PAIR_CHUNK, "right")), start + 1))
            # padding items have ext 0: no pairs
            d2 = _pair_minima(d2, *(jnp.asarray(pad_rows(x[start:stop], ITEM_CHUNK)) for x in columns))
            start = stop
    slots = np.full((rows, 4), clip.num_cascades, np.int32)  # padding rows: cascade N, dropped
    for (c, lo, hi), (b, _, _, order) in zip(jobs, layouts):
        g = np.stack(np.meshgrid(*(np.arange(lo[a], hi[a]) for a in order), indexing="ij"), -1).reshape(-1, 3)
        slots[b : b + len(g), 0] = c
        slots[b : b + len(g), 1 + np.asarray(order)] = np.mod(g, r)
    scale = pad_rows(np.repeat(np.asarray(h, np.float32), counts), rows, 1)  # padding: 1, no inf * 0
    limit = pad_rows(np.repeat(np.asarray(h) * clip.truncation, counts).astype(np.float32), rows)
    negative = np.zeros(rows, bool)
    for (_, lo, hi), (b, _, _, order), (_, _, size), inside in zip(jobs, layouts, boxes, insides):
        inside = np.asarray(inside)[: size[0], : size[1], : size[2]]
        inside = np.broadcast_to(inside, tuple(hi - lo)).transpose(order)  # in the box's flat order
        negative[b : b + inside.size] = inside.reshape(-1)
    return _write(fields, d2, *(jnp.asarray(x) for x in (scale, limit, negative, slots)))


_LAST_TABLES: list = []  # [(mesh, tables)]: `_host_tables` of the last mesh asked for


def _host_tables(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The host arrays of `mesh` that every frame's exact update reads: its triangles [F, 3,
    3] float64 (world units), their bounding boxes' minima and maxima [F, 3], and the
    triangles of `padded_mesh(mesh)` [P, 3, 3] float64 (none for an empty mesh). A flight
    passes the same `Mesh` every frame and a `Mesh`'s arrays are immutable, so the last
    mesh's tables are kept, and the mesh with them."""
    if _LAST_TABLES and _LAST_TABLES[0][0] is mesh:
        return _LAST_TABLES[0][1]
    world = host_triangles(mesh)
    padded = host_triangles(padded_mesh(mesh)) if mesh.num_faces else world
    tables = (world, world.min(1), world.max(1), padded)
    _LAST_TABLES[:] = [(mesh, tables)]
    return tables


def build_clipmap(
    mesh: Mesh,
    camera,
    *,
    resolution: int,
    num_cascades: int,
    voxel_size: float,
    origin=(0.0, 0.0, 0.0),
    truncation: float = 8.0,
    method: str = "exact",
) -> Clipmap:
    """A clipmap around `camera` built from scratch (every voxel of every cascade).

    Host-side. With ``method="exact"`` (the default) exposed voxels get the exact clamped
    signed distance from the band (see `Clipmap`): about ``(2 truncation + 1)^2`` times
    the box's thickness (triangle, voxel) pairs per triangle near a box, none for the
    others, plus one solid voxelization per box. With a `distance_field` method each
    exposed slab costs a distance field of the slab grown by ``truncation + 1`` voxels
    per side, from the faces near it (see `Clipmap`); a build is one such field of
    ``(R + 2 truncation + 2)^3`` per cascade. Measured on spot (experiments/
    clipmap_updates.py, 32^3 and 64^3 cascades): "exact" within 5e-6 voxel of Open3D's
    (float32) exact clamped value and 20 to 100 times faster per move than the others;
    "band" and "jfa" within 0.42 voxel, "jfa+sweep" within 0.78 (the tests allow 1e-3,
    0.75, 0.5 and 3.25).

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
    empty = Clipmap(
        jnp.zeros((num_cascades, r, r, r), jnp.float32),
        jnp.asarray(far),
        jnp.asarray(origin, jnp.float32),
        jnp.float32(voxel_size),
        float(truncation),
        check_choice("build_clipmap method", method, METHODS),
        "winding" if open_edges(mesh) else "parity",  # once, not every frame
    )
    return update_clipmap(empty, mesh, camera)


def update_clipmap(clip: Clipmap, mesh: Mesh, camera, *, cascades=None) -> Clipmap:
    """Re-centres cascades on `camera`, recomputing only the newly exposed voxels.

    Host-side. Toroidal storage: voxels seen by both the old and the new window stay
    in their slots untouched; no data is copied.

    Args:
      clip: the current `Clipmap`.
      mesh: the (static) scene `Mesh`, the one `build_clipmap` was given (its inside test,
        ``clip.sign``, was decided there).
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
    if clip.method == "exact" or not mesh.num_faces:  # every exposed box of every cascade at once
        jobs = [(c, lo, hi) for c in cascades for lo, hi in _exposed_boxes(corner[c], new[c], clip.resolution)]
        fields = _exact_update(fields, mesh, jobs, clip)
    else:
        padded = padded_mesh(mesh)
        host = np.array(fields)
        for c in cascades:
            _refresh(host, mesh, padded, c, corner[c], new[c], clip)
        fields = jax.device_put(host)
    corner[list(cascades)] = new[list(cascades)]
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
        raise refuse("union_clipmaps b", f"must have a's windows (corners {np.asarray(a.corner).tolist()})", b.corner)
    return dataclasses.replace(a, fields=jnp.minimum(a.fields, b.fields))


def _cell(clip: Clipmap, c, p):
    """The trilinear cell of world point p [3] in cascade c: the values at its 8 corners
    (in `_CORNERS` order), the fractions [3] of p in it, whether p is inside the
    cascade's volume, and the cascade's voxel edge h."""
    r = clip.resolution
    h = clip.voxel_size * 2.0 ** c.astype(jnp.float32)
    q = (p - clip.origin) / h - 0.5 - clip.corner[c]  # window-relative, centres at integers
    inside = jnp.all((q >= 0) & (q <= r - 1))
    base = jnp.clip(jnp.floor(q), 0, r - 2).astype(jnp.int32)
    f = jnp.clip(q - base, 0.0, 1.0)
    values = []
    for corner in _CORNERS:
        slot = jnp.mod(clip.corner[c] + base + jnp.asarray(corner, jnp.int32), r)
        values.append(clip.fields[c, slot[0], slot[1], slot[2]])
    return values, f, inside, h


def _sample(clip: Clipmap, c, p):
    """Trilinear value of cascade c at world point p [3]; and whether p is inside its volume."""
    values, f, inside, h = _cell(clip, c, p)
    value = 0.0
    for corner, v in zip(_CORNERS, values):
        w = jnp.prod(jnp.where(np.asarray(corner) == 1, f, 1.0 - f))
        value = value + w * v
    return value, inside, h


def _normal(clip: Clipmap, c, p):
    """Unit gradient [3] of cascade c's trilinear field at world point p [3] (the
    outward normal near a surface; zero where the field is flat, e.g. clamped)."""
    values, f, _, _ = _cell(clip, c, p)
    g: list = [0.0, 0.0, 0.0]
    for corner, v in zip(_CORNERS, values):
        w = [f[a] if corner[a] else 1.0 - f[a] for a in range(3)]
        for a in range(3):  # d/df_a of the corner's weight times its value
            g[a] = g[a] + (1.0 if corner[a] else -1.0) * w[(a + 1) % 3] * w[(a + 2) % 3] * v
    gradient = jnp.stack(g)
    length = jnp.sqrt(jnp.sum(gradient * gradient))
    return jnp.where(length > 0, gradient / jnp.where(length > 0, length, 1.0), 0.0)  # safe where


def trace_clipmap(
    clip: Clipmap,
    origins: jax.Array,
    directions: jax.Array,
    *,
    max_steps: int = 512,
    t_max: float = np.inf,
    hit_voxels: float = 0.05,
) -> Hit:
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
      `jaxvox.Hit` [n], as `jaxvox.sphere_trace` returns: ``t`` the distance of the hit
      along the unit direction (world units; inf unless `HIT`), ``normal`` the unit
      gradient of the hit cascade's trilinear field at the hit (zero unless `HIT`, or
      where that field is flat), ``index`` the cascade where the ray hit (its voxels
      have edge ``voxel_size * 2^index``; -1 unless `HIT`), ``voxel`` -1, ``status``
      `HIT`, `MISS` or `STEP_CAP`.

    Raises:
      JaxvoxError: not a `Clipmap`, rays that are not both [n, 3], `max_steps` not an
        integer >= 1, or (when concrete) a NaN `t_max` or a `hit_voxels` that is not a
        finite number >= 0.
    """
    check_type("trace_clipmap clip", clip, Clipmap)
    if np.ndim(origins) != 2 or np.shape(origins)[1] != 3 or np.shape(directions) != np.shape(origins):
        raise refuse(
            "trace_clipmap origins, directions",
            "must both have shape [n, 3]",
            (np.shape(origins), np.shape(directions)),
        )
    max_steps = check_int("trace_clipmap max_steps", max_steps, minimum=1)
    if is_concrete(t_max):
        check_number("trace_clipmap t_max", t_max, finite=False)
    if is_concrete(hit_voxels):
        check_number("trace_clipmap hit_voxels", hit_voxels, minimum=0.0)
    last = clip.num_cascades - 1

    def one(o, d):
        d = d / jnp.linalg.norm(d)

        def cond(state):
            return (state[3] == RUNNING) & (state[2] < max_steps)

        def body(state):
            t, c, steps, status = state
            p = o + t * d
            value, inside, h = _sample(clip, c, p)
            _, inside_next, _ = _sample(clip, c, p + jnp.maximum(value, 0.0) * d)
            hit = inside & (value < hit_voxels * h)
            coarser = (~inside | ~inside_next) & ~hit & (c < last)
            escaped = ~inside & ~hit & (c == last)
            t_new = jnp.where(hit | coarser | escaped, t, t + value)
            status = jnp.where(hit, HIT, jnp.where(escaped | (t_new > t_max), MISS, RUNNING))
            return t_new, c + coarser.astype(jnp.int32), steps + 1, status

        start = (jnp.float32(0.0), jnp.int32(0), jnp.int32(0), jnp.int32(RUNNING))
        t, c, _, status = jax.lax.while_loop(cond, body, start)
        status = jnp.where(status == RUNNING, STEP_CAP, status)
        hit = status == HIT
        normal = jnp.where(hit, _normal(clip, c, o + t * d), 0.0)
        return jnp.where(hit, t, jnp.inf), normal, jnp.where(hit, c, -1), status

    t, normal, cascade, status = jax.vmap(one)(jnp.asarray(origins, jnp.float32), jnp.asarray(directions, jnp.float32))
    return Hit(t=t, voxel=jnp.full(t.shape + (3,), -1, jnp.int32), normal=normal, index=cascade, status=status)
