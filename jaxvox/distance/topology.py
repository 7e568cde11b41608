"""Host-side mesh topology: welded vertex ids, faces at irregular edges, pinched vertices
and crossings, the boundary as a chain of directed edges, connected components of a graph.

Vertices at equal positions are welded (seams of duplicated vertices for texture or normal
coordinates are not holes), and the checks run on the welded faces.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxvox import morton
from jaxvox._core.geometry import corner_bounds


def weld(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(positions [V', 3], faces [F, 3] int64): the distinct positions of vertices [V, 3]
    (in sorted order) and the faces re-indexed into them, so that vertices at equal
    positions share one id."""
    v = np.asarray(vertices)
    order = np.lexsort(v.T[::-1])  # numeric sorts, no row unique
    new_group = np.concatenate([[True], np.any(v[order[1:]] != v[order[:-1]], axis=1)])
    ids = np.empty(len(v), np.int64)
    ids[order] = np.cumsum(new_group) - 1
    return v[order[new_group]], ids[np.asarray(faces, np.int64)]


def welded_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces [F, 3] int64 re-indexed so that vertices [V, 3] at equal positions share one id
    (`weld`)."""
    return weld(vertices, faces)[1]


class EdgeTable(NamedTuple):
    """A mesh's edges, three per face (a -> b, b -> c, c -> a of welded faces [F, 3]),
    ordered by their undirected key ``(lo, hi)``, the faces' order kept among equal
    keys (`edge_table`): entries [3F], and the runs of equal keys [E]."""

    lo: np.ndarray  # [3F] int64 the smaller vertex id
    hi: np.ndarray  # [3F] int64 the larger one
    owner: np.ndarray  # [3F] int64 the face
    side: np.ndarray  # [3F] int64 which of its edges: 0 (a -> b), 1 (b -> c), 2 (c -> a)
    forward: np.ndarray  # [3F] bool the face goes lo -> hi
    start: np.ndarray  # [E] int64 first entry of each distinct edge
    entries: np.ndarray  # [E] int64 its entries


def edge_table(faces: np.ndarray) -> EdgeTable:
    """The `EdgeTable` of welded faces [F, 3] (one sort, shared by the edge checks)."""
    f = np.asarray(faces, np.int64)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    lo, hi = directed.min(1), directed.max(1)
    base = int(f.max()) + 1 if len(f) else 1
    key = lo * base + hi
    order = morton.stable_order_host(key)
    key = key[order]
    start = morton.run_starts(key)
    return EdgeTable(
        lo[order],
        hi[order],
        np.tile(np.arange(len(f)), 3)[order],
        np.repeat(np.arange(3), len(f))[order],
        (directed[:, 0] == lo)[order],
        start,
        np.diff(np.append(start, len(key))),
    )


def _forward_counts(edges: EdgeTable) -> np.ndarray:
    """[E] int64 entries of each edge that go lo -> hi."""
    if not len(edges.start):
        return np.zeros(0, np.int64)
    return np.add.reduceat(edges.forward.astype(np.int64), edges.start)


def irregular_edge_faces(faces: np.ndarray, edges: EdgeTable | None = None) -> np.ndarray:
    """[F] bool: faces with an edge shared by more than two faces, or by two faces with the
    same direction (inconsistent orientation); `faces` welded ([F, 3] int), `edges` their
    `edge_table` (computed when not given)."""
    edges = edge_table(faces) if edges is None else edges
    run = np.repeat(np.arange(len(edges.start)), edges.entries)
    forward = _forward_counts(edges)[run]
    count = edges.entries[run]
    same_way = np.where(edges.forward, forward, count - forward)  # entries of the same direction
    same_way = np.where(edges.lo == edges.hi, count, same_way)  # (a, a): one direction
    out = np.zeros(len(faces), bool)
    out[edges.owner[(same_way > 1) | (count > 2)]] = True
    return out


def crossing_faces(tris: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Which triangles cross another one: [F] bool (host, float64 triangles [F, 3, 3]).

    Triangles sharing a (welded) vertex never count; two others cross when an edge of one
    passes through the other (coplanar overlaps are not found). Broad phase: the
    triangles' boxes hashed into cubic cells; narrow phase: six segment-triangle tests.
    """
    f_count = len(tris)
    crossing = np.zeros(f_count, bool)
    if f_count < 2:
        return crossing
    lo, hi = corner_bounds(tris)
    size = max(float(np.percentile((hi - lo).max(1), 90)), 1e-12)
    while True:
        first, last = np.floor(lo / size).astype(np.int64), np.floor(hi / size).astype(np.int64)
        per_axis = last - first + 1
        counts = per_axis.prod(1)
        if counts.sum() <= 8 * f_count + (1 << 20):
            break
        size *= 2
    owner = np.repeat(np.arange(f_count), counts)  # (int64 indices: numpy gathers with int32 ones slower)
    rank = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
    # Each item's cell as a key (x major, z fastest), one axis at a time from z, and
    # at_first: bit k set where the item's cell is its triangle's first cell along axis k.
    base = first.min(0)
    span = last.max(0) - base + 1
    key = np.zeros(len(owner), np.int64)
    at_first = np.zeros(len(owner), np.uint8)
    scale = 1
    for k in (2, 1, 0):
        if k:
            rank, offset = np.divmod(rank, per_axis[owner, k])
        else:  # (rank is below the x extent)
            offset = rank
        key += (first[owner, k] - base[k] + offset) * scale
        scale *= int(span[k])
        at_first |= (offset == 0).astype(np.uint8) << k
    order = morton.stable_order_host(key)
    key, owner, at_first = key[order], owner[order], at_first[order]
    end = np.searchsorted(key, key, side="right")  # one past each entry's run
    later = end - 1 - np.arange(len(key))  # entries after it in its run
    a = np.repeat(np.arange(len(key)), later)
    b = a + 1 + (np.arange(len(a)) - np.repeat(np.cumsum(later) - later, later))
    # Two triangles share every cell of the intersection of their cell ranges: the pair is
    # kept in the first of them only (on each axis the larger of their first cells, so
    # the cell is one of theirs), so it is unique.
    keep = (at_first[a] | at_first[b]) == 7
    i, j = owner[a.compress(keep)], owner[b.compress(keep)]  # (compress: faster than a boolean index)
    for k in range(3):  # the boxes overlap, axis by axis
        low, high = np.ascontiguousarray(lo[:, k]), np.ascontiguousarray(hi[:, k])
        keep = (low[i] <= high[j]) & (low[j] <= high[i])
        i, j = i.compress(keep), j.compress(keep)
    corner = [np.ascontiguousarray(faces[:, k]) for k in range(3)]
    of_j = [c[j] for c in corner]
    shared = np.zeros(len(i), bool)
    for c in corner:
        of_i = c[i]
        for other in of_j:
            shared |= of_i == other
    i, j = i.compress(~shared), j.compress(~shared)
    for s in range(0, len(i), 1 << 18):
        ti, tj = tris[i[s : s + (1 << 18)]], tris[j[s : s + (1 << 18)]]
        hit = np.zeros(len(ti), bool)
        for edge in range(3):
            hit |= _segment_crosses(ti[:, edge], ti[:, (edge + 1) % 3], tj)
            hit |= _segment_crosses(tj[:, edge], tj[:, (edge + 1) % 3], ti)
        crossing[i[s : s + (1 << 18)][hit]] = True
        crossing[j[s : s + (1 << 18)][hit]] = True
    return crossing


def _segment_crosses(p0: np.ndarray, p1: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Whether segments p0 -> p1 [n, 3] meet triangles [n, 3, 3] (Moller-Trumbore, float64,
    closed bounds; segments parallel to the triangle's plane never do)."""
    d = p1 - p0
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > 1e-12 * np.linalg.norm(d, axis=1) * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    inv = 1.0 / np.where(ok, det, 1.0)
    s = p0 - tri[:, 0]
    u = inv * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, q)
    t = inv * np.einsum("ij,ij->i", e2, q)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def connected_components(count: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """[count] int64 label per node, the smallest node id of its component, of the graph
    with `count` nodes and edges ``u[i] - v[i]`` (int arrays): hook higher roots onto lower
    ones, then jump pointers to the roots, until no edge joins two roots."""
    label = np.arange(count)
    u, v = np.asarray(u, np.int64), np.asarray(v, np.int64)
    while True:
        lu, lv = label[u], label[v]
        apart = lu != lv
        if not apart.any():
            return label
        u, v, lu, lv = (x.compress(apart) for x in (u, v, lu, lv))  # (faster than a boolean index)
        np.minimum.at(label, np.maximum(lu, lv), np.minimum(lu, lv))
        while True:
            up = label[label]
            if np.array_equal(up, label):
                break
            label = up


def boundary_chain(faces: np.ndarray, edges: EdgeTable | None = None) -> np.ndarray:
    """[E, 2] int64 directed edges (a, b) of the mesh's boundary as a chain: each face
    (a, b, c) contributes a -> b, b -> c, c -> a, opposite directions cancel, and an edge
    left over k times is listed k times (welded faces [F, 3], `edges` their `edge_table`
    (computed when not given); empty when every edge is met equally often in both
    directions). Ordered by the edges' undirected keys."""
    edges = edge_table(faces) if edges is None else edges
    first = edges.start
    net = 2 * _forward_counts(edges) - edges.entries
    net[edges.lo[first] == edges.hi[first]] = 0  # (a, a): no edge
    keep = np.flatnonzero(net)
    a, b = edges.lo[first[keep]], edges.hi[first[keep]]
    forward = net[keep] > 0
    chain = np.stack([np.where(forward, a, b), np.where(forward, b, a)], 1)
    return np.repeat(chain, np.abs(net[keep]), axis=0)


def regular_edge_pairs(faces: np.ndarray, edges: EdgeTable | None = None) -> np.ndarray:
    """[P, 2] int64 pairs of faces sharing an edge that no third face uses (welded faces,
    `edges` their `edge_table`, computed when not given)."""
    edges = edge_table(faces) if edges is None else edges
    pair = edges.start[edges.entries == 2]
    return np.stack([edges.owner[pair], edges.owner[pair + 1]], 1)


def pinched_vertex_faces(faces: np.ndarray, edges: EdgeTable | None = None) -> np.ndarray:
    """[F] bool: faces at a vertex whose faces form more than one fan (two cones or sheets
    touching at a point), where one pseudo-normal cannot tell the sides (welded faces,
    `edges` their `edge_table`, computed when not given)."""
    f = np.asarray(faces, np.int64)
    edges = edge_table(f) if edges is None else edges
    # A corner at v touches the edges (v, next) and (v, previous) of its face: the corners
    # at either end of one edge, over the faces that share it, belong to one fan. Corner
    # 3 i + k of face i is at f[i, k]; its edge k starts there and ends at corner k + 1.
    start = 3 * edges.owner + edges.side
    end = 3 * edges.owner + (edges.side + 1) % 3
    at_lo, at_hi = np.where(edges.forward, start, end), np.where(edges.forward, end, start)
    later = np.ones(len(start), bool)  # entries after the first of their edge
    later[edges.start] = False
    later = np.flatnonzero(later)
    loop = np.flatnonzero(edges.lo == edges.hi)  # (v, v): both ends at v
    u = np.concatenate([at_lo[later - 1], at_hi[later - 1], at_lo[loop]])
    v = np.concatenate([at_lo[later], at_hi[later], at_hi[loop]])
    corners = 3 * len(f)
    fan = connected_components(corners, u, v)
    pairs = np.unique(f.reshape(-1) * corners + fan)  # (vertex, fan), packed
    base = int(f.max()) + 1 if len(f) else 1
    fans_per_vertex = np.bincount(pairs // corners, minlength=base)
    return np.asarray((fans_per_vertex[f] > 1).any(1))
