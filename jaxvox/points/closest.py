"""Closest points on a mesh: the search (`closest_slots`) and the point on the triangle.

The search keeps, level by level, the nodes that may hold a block's closest triangle:
every point of a block is within ``U`` of the surface, ``U`` the smallest distance from
the block's farthest corner to a node's surface point (``rep``), so a node whose box is
farther than ``U`` from the block's box holds no block point's closest triangle. Each
point also keeps its own bound, its smallest distance to the ``rep`` of the nodes its
block visits (and, from the level above the leaves, to a few leaves' triangles): a node
farther than that from every point of the block is dropped too. Where points are few
and a block of Morton-consecutive points spans much of the mesh's box, the block's
``U`` keeps most of the nodes near the block, and the points' own bounds only those
near one of its points. The leaves kept are evaluated exactly per point
(`jaxvox._core.geometry.rows_dist2`, 8 triangles a leaf). Ties between triangles at the
same float32 distance go to the smallest face id.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxvox._core.geometry import rows_dist2
from jaxvox.points import search
from jaxvox.points.index import FAN_OUT, MeshIndex

_NO_FACE = jnp.iinfo(jnp.int32).max
# The points' own bounds are tightened at a level when its pairs hold at most this many
# (pair, point) entries: a level of many pairs is one of many points, whose blocks are
# small, and there the block's bound prunes as well at less cost.
POINT_BOUNDS_MAX = 1 << 22


class Found(NamedTuple):
    """The search's result per sorted point."""

    dist2: jax.Array  # [nb, BLOCK] float32 squared distance (float32 kernel)
    slot: jax.Array  # [nb, BLOCK] int32 tree slot of the closest triangle
    lost: jax.Array  # [nb] bool: a capacity was too small for the block (answer unreliable)
    needs: jax.Array  # [len(caps)] int32 what each capacity needed


def closest_slots(index: MeshIndex, blocks: search.Blocks, caps: tuple[int, ...]) -> Found:
    """The closest triangle of every sorted point (module docstring), traced.

    `caps`: static capacities, the pairs at each depth below the root (leaves first) and
    then the leaf rows (`row_depths`). ``Found.needs`` says what each needed.
    """
    nb = blocks.p.shape[1]
    # The bounds, as the walk tightens them: the blocks' [nb] and each point's [nb, BLOCK].
    bound = [jnp.full(nb, jnp.inf, jnp.float32), jnp.full(blocks.p.shape[1:], jnp.inf, jnp.float32)]
    seeds: list[search.Rows] = []

    def select(pairs, depth):
        keep, bound[0], bound[1], seed = _select(index, blocks, pairs, bound[0], bound[1], depth)
        seeds.extend([] if seed is None else [seed])
        return keep

    pairs, keep, lost, needs = search.descend(select, nb, index.levels, caps[:-1])
    rows, dropped = search.make_rows(pairs, keep, caps[-1], nb)
    if seeds:  # the seed's leaves are evaluated again with the rest: one kernel
        rows = search.join_rows([seeds[0], rows], nb)
    d2, face = search.eval_rows(rows, blocks, lambda p, leaves: _leaf_minima(index, p, leaves), (jnp.inf, _NO_FACE))
    owner = rows.block
    best = jax.ops.segment_min(d2, owner, nb)
    tie = jnp.where(d2 == best[jnp.minimum(owner, nb - 1)], face, _NO_FACE)
    face = jax.ops.segment_min(tie, owner, nb)
    slot_of = jnp.zeros(index.capacity, jnp.int32).at[index.order].set(jnp.arange(index.capacity, dtype=jnp.int32))
    slot = slot_of[jnp.clip(face, 0, index.capacity - 1)]
    return Found(best, slot, lost | dropped, jnp.concatenate([needs, rows.needed[None]]))


def row_depths(index: MeshIndex) -> tuple[int, ...]:
    """The depths of the pairs that each row capacity of `closest_slots` is made from,
    after its pair capacities (one per depth below the root): the leaf rows."""
    return (0,)


def _select(index: MeshIndex, blocks: search.Blocks, pairs: search.Pairs, bound, u, depth: int):
    """The pairs of a level that may hold a block point's closest triangle ([capacity]
    bool), the tightened bounds (squared: the blocks' [nb] and each point's ``u`` [nb,
    BLOCK]) and at depth 1 the `_seed` rows. Above the leaves, where the level's pairs
    are few enough (`POINT_BOUNDS_MAX`), every pair's ``rep`` tightens the bounds of its
    block's points (points spread over a large block, as few
    points in a large box are, each keep only the nodes near them); a pair is kept only
    if it may be closer than its block's bound to the block's box and closer than a
    point's bound to one of the block's points."""
    nb = blocks.p.shape[1]
    node = index.nodes[index.levels[depth][0] + pairs.node]  # [capacity, 24]
    used = pairs.block < nb
    b = jnp.minimum(pairs.block, nb - 1)
    box = blocks.bounds[b]  # [capacity, 6]
    p = tuple(blocks.p[k][b] for k in range(3))  # [capacity, BLOCK]
    ub = jnp.where(used, search.far_corner2(box, node[:, 6:9]), jnp.inf)
    bound = jnp.minimum(bound, jax.ops.segment_min(ub, pairs.block, nb, indices_are_sorted=True))
    seed = None
    if depth >= 1 and pairs.block.shape[0] * search.BLOCK <= POINT_BOUNDS_MAX:
        to_rep = sum((p[k] - node[:, 6 + k, None]) ** 2 for k in range(3))  # [capacity, BLOCK]
        to_rep = jnp.where(used[:, None], to_rep, jnp.inf)
        u = jnp.minimum(u, jax.ops.segment_min(to_rep, pairs.block, nb, indices_are_sorted=True))
    if depth == 1:  # exact distances to the leaves of each block's most promising nodes
        seed, found = _seed(index, blocks, pairs, ub)
        u = jnp.minimum(u, found)
    bound = jnp.minimum(bound, u.max(1))
    oriented = jnp.maximum(search.frame_gap(box, node[:, 9:]), 0.0)
    lb = jnp.maximum(search.box_gap2(box, node), oriented * oriented * (1.0 - 1e-5))
    keep = used & (lb <= bound[b] * search.SLACK)
    if depth <= 1:
        keep &= jnp.any(search.point_gap2(p, node) <= u[b] * search.SLACK, axis=1)
    return keep, bound, u, seed


def _seed(index: MeshIndex, blocks: search.Blocks, pairs: search.Pairs, ub):
    """Rows [nb, ROW] of the leaves of each block's ROW / FAN_OUT pairs of smallest ``ub``
    [capacity] (level-1 nodes) and the exact squared distances [nb, BLOCK] of the block's
    points to them: a tight bound for the rest of the search."""
    nb = blocks.p.shape[1]
    b = jnp.minimum(pairs.block, nb - 1)
    slots = jnp.arange(ub.shape[0])
    picks = []
    for _ in range(search.ROW // FAN_OUT):
        best = jax.ops.segment_min(ub, pairs.block, nb, indices_are_sorted=True)
        first = jnp.where((ub == best[b]) & (pairs.block < nb) & (ub < jnp.inf), slots, ub.shape[0])
        picks.append(jax.ops.segment_min(first, pairs.block, nb, indices_are_sorted=True))
        ub = jnp.where(slots == picks[-1][b], jnp.inf, ub)  # the next pick is another pair
    pick = jnp.stack(picks, 1)  # [nb, ROW / FAN_OUT]
    node = pairs.node[jnp.clip(pick, 0, ub.shape[0] - 1)]
    leaves = node[:, :, None] * FAN_OUT + jnp.arange(FAN_OUT)  # [nb, ROW / FAN_OUT, FAN_OUT]
    ok = (leaves < index.levels[0][1]) & (pick < ub.shape[0])[:, :, None]
    table = jnp.where(ok, leaves, -1).reshape(nb, search.ROW)
    rows = search.Rows(table, jnp.arange(nb, dtype=jnp.int32), jnp.int32(nb), jnp.int32(nb))
    minima = lambda p, leaves: _leaf_minima(index, p, leaves)
    return rows, search.eval_rows(rows, blocks, minima, (jnp.inf, _NO_FACE))[0]


def _leaf_minima(index: MeshIndex, p, leaves):
    """Per point of each row: the smallest squared distance to the triangles of its leaves
    and the smallest face id at that distance ([c, BLOCK] each)."""
    safe = jnp.maximum(leaves, 0)
    rows = index.leaf_rows[safe]  # [c, ROW, 28, 8]: one contiguous gather per leaf
    faces = jnp.where(leaves[..., None] >= 0, index.leaf_faces[safe], _NO_FACE)  # [c, ROW, 8]
    zero = jnp.zeros((), jnp.float32)
    q = tuple(x[:, None, None, :] for x in p)  # [c, 1, 1, BLOCK]
    d2 = rows_dist2(q, tuple(rows[:, :, i, :, None] for i in range(28)), (zero, zero, zero))  # [c, ROW, 8, BLOCK]
    d2 = jnp.where(faces[..., None] < _NO_FACE, d2, jnp.inf)
    best = d2.min((1, 2))
    face = jnp.where(d2 == best[:, None, None, :], faces[..., None], _NO_FACE).min((1, 2))
    return best, face


class Feature(NamedTuple):
    """The closest point of a triangle to a point, in float32."""

    point: jax.Array  # [n, 3] the closest point (relative to the index's centre)
    barycentric: jax.Array  # [n, 3] its barycentric coordinates on the triangle (a, b, c)
    region: jax.Array  # [n] int32 0 face, 1-3 edges ab, bc, ca, 4-6 vertices a, b, c


def closest_on_triangles(p, a, b, c) -> Feature:
    """Closest points on triangles (a, b, c) [n, 3] to points p [n, 3]: the projection
    onto the plane where it falls inside, else the nearest point of the three edges (a
    degenerate or needle triangle's closest point is on its edges).

    The projection is computed in the frame of the triangle's longest edge e (from corner
    r0, the third corner r2 = r0 + f): with n = e x f and w = n x e (in the plane,
    perpendicular to e by construction), the coefficients of ``p - r0 = beta e + gamma f``
    are ``gamma = (p - r0) . w / |n|^2`` and ``beta = ((p - r0) . e - gamma f . e) / |e|^2``.
    On a sliver (Ericson's Gram-matrix form divides by |n|^2 after subtracting products
    of |e|^2 |f|^2 size) this keeps the point, and the corners weighted by the
    barycentric coordinates, within float32 rounding of the exact projection.
    """
    dot = lambda x, y: jnp.sum(x * y, -1)
    k = jnp.argmax(jnp.stack([dot(b - a, b - a), dot(c - b, c - b), dot(a - c, a - c)], -1), -1)
    pick = lambda k, x, y, z: jnp.where(k == 0, x, jnp.where(k == 1, y, z))  # x, y or z by k
    k3 = k[..., None]
    r0, r1, r2 = pick(k3, a, b, c), pick(k3, b, c, a), pick(k3, c, a, b)  # r0 r1: the longest edge
    e, f, q = r1 - r0, r2 - r0, p - r0
    n = jnp.cross(e, f)
    nn, ee = dot(n, n), dot(e, e)
    proper = nn > 1e-10 * ee * dot(f, f)  # a triangle of clear area
    gamma = dot(q, jnp.cross(n, e)) / jnp.where(proper, nn, 1.0)
    beta = (dot(q, e) - gamma * dot(f, e)) / jnp.where(ee > 0, ee, 1.0)
    inside = proper & (beta >= 0) & (gamma >= 0) & (beta + gamma <= 1)
    t0, t1, t2 = 1.0 - beta - gamma, beta, gamma  # barycentric on r0, r1, r2
    face_bary = jnp.stack([pick(k, t0, t2, t1), pick(k, t1, t0, t2), pick(k, t2, t1, t0)], -1)  # on a, b, c

    def segment(x0, x1, i, j):
        e = x1 - x0
        ee = dot(e, e)
        s = jnp.clip(dot(p - x0, e) / jnp.where(ee > 0, ee, 1.0), 0.0, 1.0)
        bary = jnp.zeros(p.shape).at[..., i].set(1.0 - s).at[..., j].add(s)
        q = x0 + s[..., None] * e
        return dot(p - q, p - q), bary, s

    edges = [segment(a, b, 0, 1), segment(b, c, 1, 2), segment(c, a, 2, 0)]
    best = jnp.argmin(jnp.stack([e[0] for e in edges], -1), -1)
    bary_e = jnp.where((best == 0)[..., None], edges[0][1], jnp.where((best == 1)[..., None], edges[1][1], edges[2][1]))
    s_e = jnp.where(best == 0, edges[0][2], jnp.where(best == 1, edges[1][2], edges[2][2]))
    corner = jnp.where(s_e <= 0.0, 4 + best, jnp.where(s_e >= 1.0, 4 + (best + 1) % 3, 1 + best))
    bary = jnp.where(inside[..., None], face_bary, bary_e)
    region = jnp.where(inside, 0, corner).astype(jnp.int32)
    on_face = r0 + beta[..., None] * e + gamma[..., None] * f
    on_edge = bary_e[..., :1] * a + bary_e[..., 1:2] * b + bary_e[..., 2:] * c
    point = jnp.where(inside[..., None], on_face, on_edge)
    return Feature(point, bary, region)
