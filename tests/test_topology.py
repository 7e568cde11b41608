"""Host-side mesh topology checks: welding, irregular and boundary edges, crossing faces."""

from __future__ import annotations

import numpy as np

from jaxvox.topology import boundary_edges, crossing_faces, distance_to_segments, irregular_edge_faces, welded_faces


def test_welding_and_edges():
    # Two triangles sharing an edge through duplicated vertices (a seam), plus a third
    # face on the same edge (non-manifold) and a flipped copy of the first.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1]], float)
    f = np.array([[0, 1, 2], [4, 3, 5]])
    w = welded_faces(v, f)
    assert w[0, 1] == w[1, 1] and w[0, 2] == w[1, 0]
    assert not irregular_edge_faces(w).any()
    assert len(boundary_edges(w)) == 4
    third = np.concatenate([w, [[w[0, 1], w[0, 2], 5]]])  # a third face on edge (1, 2)
    assert irregular_edge_faces(third).tolist() == [True, True, True]
    same_way = np.concatenate([w[:1], [[w[0, 1], w[0, 2], 5]]])  # two faces, same direction
    assert irregular_edge_faces(same_way).all()


def test_crossing_faces():
    flat = [[0, 0, 0], [2, 0, 0], [0, 2, 0]]
    through = [[0.5, 0.5, -1], [0.5, 0.5, 1], [1.0, 0.2, 1]]  # pierces `flat`
    above = [[0.5, 0.5, 0.1], [0.5, 0.5, 1], [1.0, 0.2, 1]]  # does not reach it
    adjacent = [[2, 0, 0], [0, 2, 0], [2, 2, 1]]  # shares an edge: never counts
    tris = np.array([flat, through, above, adjacent], float)
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [1, 2, 9]])
    assert crossing_faces(tris, faces).tolist() == [True, True, False, False]
    assert not crossing_faces(tris[:1], faces[:1]).any()


def test_distance_to_segments():
    p = np.array([[0.5, 1.0, 0.0], [3.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    a, b = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]])
    np.testing.assert_allclose(distance_to_segments(p, a, b), [1.0, 2.0, 1.0])
    assert np.isinf(distance_to_segments(p, a[:0], b[:0])).all()
