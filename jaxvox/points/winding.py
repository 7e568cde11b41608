"""Generalized winding numbers at points: fast, with a per-point error bound, or exact.

The winding number ``w(p) = sum_t solid_angle_t(p) / (4 pi)`` is 1 inside a closed,
outward-oriented mesh and 0 outside; across a hole it varies smoothly, and ``w > 1/2`` is
the inside test that stays right on open and self-intersecting meshes (Jacobson et al.
2013). The fast sum (Barill et al. 2018) walks the `MeshIndex` tree by blocks of points
(`jaxvox.points.search`): a node is *far* from a block when the distance between the
block's box and the node's centre ``c`` exceeds ``beta r`` (``r`` the node's radius,
so every point of the block sees the node from farther than ``beta r``); a far node adds its dipole term
``A . (c - p) / (4 pi |c - p|^3)`` for each point of the block, a near node opens, and a
near leaf adds its triangles' exact solid angles.

**Error bound.** For a triangle set of unsigned area ``S`` within ``r`` of ``c``, the
dipole term differs from the exact sum by at most ``2 r S / (4 pi (R - r)^3)`` at a point
at distance ``R > r`` from ``c`` (the integrand ``(y - p) / |y - p|^3`` moves by at most
``|y - c|`` times its largest gradient, ``2 / |x|^3``, along the segment from ``c`` to
``y``). The fast sum returns the sum of these bounds over the far nodes it used, plus
`FLOAT_MARGIN` for float32 rounding: ``|w - w_fast| <= bound`` (tested). A point's side
is certain where ``|w_fast - 1/2| > bound``; elsewhere the host API sums exactly.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.geometry import solid_angle_parts
from jaxvox._core.shapes import chunk_rows
from jaxvox.points import search
from jaxvox.points.index import MeshIndex

FLOAT_MARGIN = 1e-4  # float32 rounding allowance added to every error bound
EXACT_MIN = 256  # points per exact sum (padded): one program per face capacity


def winding_sums(index: MeshIndex, blocks: search.Blocks, beta: float, caps: tuple[int, ...]):
    """Fast winding numbers and their error bounds [nb, BLOCK] of the sorted points, [nb]
    bool blocks that lost pairs or rows to a capacity (their values are incomplete), and
    [len(caps)] int32 what each capacity needed; traced.

    `caps`: static capacities (the pairs below the root, then `row_depths`): the pairs at each depth below
    the root (leaves first), the far rows at each depth (leaves first), the near leaf rows.
    """
    nb = blocks.p.shape[1]
    top = len(index.levels)
    w = jnp.zeros(blocks.p.shape[1:], jnp.float32)
    err = jnp.full(blocks.p.shape[1:], FLOAT_MARGIN, jnp.float32)
    far_rows: list[search.Rows] = []
    far_lost: list[jax.Array] = []
    far_needed: list[jax.Array] = [jnp.int32(0)] * top

    def select(pairs, depth):
        far, near = _split(index, blocks, pairs, depth, beta)
        rows, lost = search.make_rows(pairs, far, caps[top - 1 + depth], nb)
        offset = index.levels[depth][0]
        far_rows.append(rows._replace(node=jnp.where(rows.node >= 0, rows.node + offset, -1)))
        far_lost.append(lost)
        far_needed[depth] = rows.needed
        return near

    pairs, near, lost, needs = search.descend(select, nb, index.levels, caps[: top - 1])
    far = search.join_rows(far_rows, nb)
    dw, de = search.eval_rows(far, blocks, lambda p, nodes: _dipoles(index, p, nodes), (0.0, 0.0))
    rows, dropped = search.make_rows(pairs, near, caps[-1], nb)
    (dn,) = search.eval_rows(rows, blocks, lambda p, leaves: (leaf_solid_angles(index, p, leaves),), (0.0,))
    w = _add(_add(w, far, dw, nb), rows, dn, nb)
    needed = jnp.concatenate([needs, jnp.stack(far_needed), rows.needed[None]])
    return w, _add(err, far, de, nb), lost | dropped | jnp.any(jnp.stack(far_lost), 0), needed


def row_depths(index: MeshIndex) -> tuple[int, ...]:
    """The depths of the pairs that each row capacity of `winding_sums` is made from,
    after its pair capacities (one per depth below the root): the far rows at each depth
    (leaves first), then the near leaf rows."""
    return (*range(len(index.levels)), 0)


def _split(index: MeshIndex, blocks: search.Blocks, pairs: search.Pairs, depth: int, beta: float):
    """(far, near) [capacity] bool: the pairs whose node is far from the block, and those
    to open (nodes without area are neither)."""
    nb = blocks.p.shape[1]
    node = index.dipole[index.levels[depth][0] + pairs.node]  # [capacity, 8]
    box = blocks.bounds[jnp.minimum(pairs.block, nb - 1)]
    gap2 = sum(jnp.maximum(0.0, jnp.maximum(box[:, k] - node[:, k], node[:, k] - box[:, 3 + k])) ** 2 for k in range(3))
    used = (pairs.block < nb) & (node[:, 7] > 0)
    far = used & (gap2 > (beta * node[:, 3]) ** 2)
    return far, used & ~far


def _add(acc, rows: search.Rows, values, nb: int):
    """acc [nb, BLOCK] plus the per-row values [capacity, BLOCK] summed per block."""
    return acc + jax.ops.segment_sum(values, rows.block, nb)


def _dipoles(index: MeshIndex, p, nodes):
    """Dipole terms and their error bounds summed over the nodes [c, ROW] (global ids, -1:
    none) of a row at the points p (3 arrays [c, BLOCK]): two [c, BLOCK] arrays."""
    d = index.dipole[jnp.maximum(nodes, 0)]  # [c, ROW, 8]
    col = lambda i: d[:, :, i, None]  # [c, ROW, 1] against p [c, 1, BLOCK]
    x = [col(k) - p[k][:, None, :] for k in range(3)]
    r2 = x[0] * x[0] + x[1] * x[1] + x[2] * x[2]
    dist = jnp.sqrt(r2)
    dipole = (col(4) * x[0] + col(5) * x[1] + col(6) * x[2]) / (4 * jnp.pi * r2 * dist)
    gap = jnp.maximum(dist - col(3), 1e-30)
    bound = 2 * col(3) * col(7) / (4 * jnp.pi * gap * gap * gap)
    ok = (nodes >= 0)[:, :, None]
    return jnp.where(ok, dipole, 0.0).sum(1), jnp.where(ok, bound, 0.0).sum(1)


def leaf_solid_angles(index: MeshIndex, p, leaves):
    """Sum of the solid angles / (4 pi) of the triangles of leaves [c, ROW] (-1: none) at
    the points p (3 arrays [c, BLOCK]): [c, BLOCK]."""
    corners = index.leaf_corners[jnp.maximum(leaves, 0)]  # [c, ROW, 9, 8]
    q = [x[:, None, None, :] for x in p]  # [c, 1, 1, BLOCK]
    rel = [tuple(corners[:, :, 3 * i + k, :, None] - q[k] for k in range(3)) for i in range(3)]
    omega = solid_angle_parts(*rel)  # [c, ROW, 8, BLOCK]
    return jnp.where((leaves >= 0)[:, :, None, None], omega, 0.0).sum((1, 2))


def tree_triangles(index: MeshIndex) -> np.ndarray:
    """The index's triangles [F, 3, 3] float64 (world units, host; F the face capacity,
    padding triangles are points: no solid angle), for exact sums whose programs depend
    on the capacity only."""
    corners = np.asarray(index.corners, np.float64).T.reshape(-1, 3, 3)
    return corners + np.asarray(index.centre, np.float64)


def exact_winding(index: MeshIndex, points) -> np.ndarray:
    """Exact winding numbers [n] float64 (host) of points [n, 3] over every triangle of the
    index (`jaxvox.distance.winding.exact_winding_numbers`: float64 near 1/2), in chunks
    of `EXACT_MIN` points (the last one padded there), or of a sixteenth of that where
    fewer points than one chunk are asked (`chunk_rows`: often a handful, those the fast
    sum left near 1/2): sets of any size share two compiled programs per face capacity."""
    from jaxvox.distance.winding import exact_winding_numbers

    p = np.asarray(points, np.float64).reshape(-1, 3)
    return exact_winding_numbers(tree_triangles(index), p, chunk=chunk_rows(len(p), EXACT_MIN))
