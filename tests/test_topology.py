"""Host-side mesh topology checks: welding, irregular edges, the boundary chain, pinched
vertices, crossing faces, connected components."""

from __future__ import annotations

import numpy as np

from jaxvox.distance.topology import (
    boundary_chain,
    connected_components,
    crossing_faces,
    irregular_edge_faces,
    pinched_vertex_faces,
    regular_edge_pairs,
    welded_faces,
)


def test_welding_and_edges():
    # Two triangles sharing an edge through duplicated vertices (a seam), plus a third
    # face on the same edge (non-manifold) and a flipped copy of the first.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1]], float)
    f = np.array([[0, 1, 2], [4, 3, 5]])
    w = welded_faces(v, f)
    assert w[0, 1] == w[1, 1] and w[0, 2] == w[1, 0]
    assert not irregular_edge_faces(w).any()
    chain = boundary_chain(w)  # the quad's rim, each edge once, in face direction
    assert len(chain) == 4 and set(map(tuple, chain.tolist())) == {
        (w[0, 0], w[0, 1]),
        (w[0, 2], w[0, 0]),
        (w[1, 1], w[1, 2]),
        (w[1, 2], w[1, 0]),
    }
    assert np.sort(regular_edge_pairs(w), 1).tolist() == [[0, 1]]
    third = np.concatenate([w, [[w[0, 1], w[0, 2], 5]]])  # a third face on edge (1, 2)
    assert irregular_edge_faces(third).tolist() == [True, True, True]
    same_way = np.concatenate([w[:1], [[w[0, 1], w[0, 2], 5]]])  # two faces, same direction
    assert irregular_edge_faces(same_way).all()
    assert len(boundary_chain(same_way)) == 6  # the shared edge is left over twice
    closed = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # a tetrahedron
    assert not len(boundary_chain(closed))


def test_pinched_vertices():
    """Two tetrahedra touching at vertex 0: its faces form two fans."""
    tet = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    both = np.concatenate([tet, np.where(tet == 0, 0, tet + 3)])
    assert not pinched_vertex_faces(tet).any()
    assert pinched_vertex_faces(both).tolist() == [True, True, True, False] * 2


def test_crossing_faces():
    flat = [[0, 0, 0], [2, 0, 0], [0, 2, 0]]
    through = [[0.5, 0.5, -1], [0.5, 0.5, 1], [1.0, 0.2, 1]]  # pierces `flat`
    above = [[0.5, 0.5, 0.1], [0.5, 0.5, 1], [1.0, 0.2, 1]]  # does not reach it
    adjacent = [[2, 0, 0], [0, 2, 0], [2, 2, 1]]  # shares an edge: never counts
    tris = np.array([flat, through, above, adjacent], float)
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [1, 2, 9]])
    assert crossing_faces(tris, faces).tolist() == [True, True, False, False]
    assert not crossing_faces(tris[:1], faces[:1]).any()


def test_connected_components():
    label = connected_components(7, np.array([5, 1, 3, 2]), np.array([1, 0, 2, 4]))
    assert label.tolist() == [0, 0, 2, 2, 2, 0, 6]
    assert connected_components(3, np.zeros(0, int), np.zeros(0, int)).tolist() == [0, 1, 2]
