"""Host-side mesh topology: welded vertex ids, faces at irregular edges, crossing faces.

Vertices at equal positions are welded (seams of duplicated vertices for texture or normal
coordinates are not holes), and the checks run on the welded faces.
"""

from __future__ import annotations

import numpy as np


def welded_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces [F, 3] int64 re-indexed so that vertices [V, 3] at equal positions share one id."""
    v = np.asarray(vertices)
    order = np.lexsort(v.T[::-1])  # numeric sorts, no row unique
    new_group = np.concatenate([[True], np.any(v[order[1:]] != v[order[:-1]], axis=1)])
    weld = np.empty(len(v), np.int64)
    weld[order] = np.cumsum(new_group) - 1
    return weld[np.asarray(faces, np.int64)]


def irregular_edge_faces(faces: np.ndarray) -> np.ndarray:
    """[F] bool: faces with an edge shared by more than two faces, or by two faces with the
    same direction (inconsistent orientation); `faces` welded ([F, 3] int)."""
    f = np.asarray(faces, np.int64)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    owner = np.tile(np.arange(len(f)), 3)
    base = int(f.max()) + 1 if len(f) else 1
    _, same_way, repeats = np.unique(directed[:, 0] * base + directed[:, 1], return_inverse=True, return_counts=True)
    undirected = np.sort(directed, 1)
    _, any_way, shares = np.unique(undirected[:, 0] * base + undirected[:, 1], return_inverse=True, return_counts=True)
    bad = (repeats[same_way] > 1) | (shares[any_way] > 2)
    out = np.zeros(len(f), bool)
    out[owner[bad]] = True
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
    lo, hi = tris.min(1), tris.max(1)
    size = max(float(np.percentile((hi - lo).max(1), 90)), 1e-12)
    while True:
        first, last = np.floor(lo / size).astype(np.int64), np.floor(hi / size).astype(np.int64)
        per_axis = last - first + 1
        counts = per_axis.prod(1)
        if counts.sum() <= 8 * f_count + (1 << 20):
            break
        size *= 2
    owner = np.repeat(np.arange(f_count), counts)
    rank = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
    n = per_axis[owner]
    cell = first[owner] + np.stack([rank // (n[:, 1] * n[:, 2]), (rank // n[:, 2]) % n[:, 1], rank % n[:, 2]], -1)
    cell -= cell.min(0)
    span = cell.max(0) + 1
    key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")
    key, owner = key[order], owner[order]
    end = np.searchsorted(key, key, side="right")  # one past each entry's run
    later = end - 1 - np.arange(len(key))  # entries after it in its run
    a = np.repeat(np.arange(len(key)), later)
    b = a + 1 + (np.arange(len(a)) - np.repeat(np.cumsum(later) - later, later))
    pairs = np.unique(np.sort(np.stack([owner[a], owner[b]], 1), 1), axis=0)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    i, j = pairs[:, 0], pairs[:, 1]
    keep = (lo[i] <= hi[j]).all(1) & (lo[j] <= hi[i]).all(1)
    keep &= ~(faces[i][:, :, None] == faces[j][:, None, :]).any((1, 2))
    i, j = i[keep], j[keep]
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


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """[E, 2] int64 vertex pairs of the edges used by exactly one face (welded faces [F, 3])."""
    f = np.asarray(faces, np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), 1)
    e = e[e[:, 0] != e[:, 1]]
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    return uniq[counts == 1]


def distance_to_segments(points: np.ndarray, a: np.ndarray, b: np.ndarray, *, chunk: int = 1 << 22) -> np.ndarray:
    """Distance [P] from points [P, 3] to the nearest of the segments a -> b ([E, 3] each;
    inf when E = 0), float64 brute force in chunks of `chunk` (point, segment) pairs."""
    out = np.full(len(points), np.inf)
    if not len(a):
        return out
    d = b - a
    dd = np.maximum(np.einsum("ij,ij->i", d, d), 1e-300)
    step = max(1, chunk // len(a))
    for s in range(0, len(points), step):
        p = points[s : s + step, None]
        t = np.clip(np.einsum("pej,ej->pe", p - a, d) / dd, 0.0, 1.0)
        out[s : s + step] = np.linalg.norm(p - (a + t[..., None] * d), axis=-1).min(1)
    return out
