"""`field_to_mesh` against the input meshes: closed, outward, on the surface, and the same
for every block size (blocks stitched exactly)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxvox as jv
from jaxvox.distance import meshing as field_mesh
from jaxvox.distance.meshing import _march
from tests.reference import closest_point_on_triangles, mesh_distance

R = 32
BAND = 3
RADIUS = 0.35


def sphere_mesh() -> jv.Mesh:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=3, radius=RADIUS)
    return jv.Mesh(np.asarray(s.vertices, np.float32) + np.float32(0.5), np.asarray(s.faces, np.int32))


@pytest.fixture(scope="module")
def sphere():
    """The sphere, its grid (1% padding: the sphere pokes out past the outermost voxel
    centres, so the mesh is capped against the outside of the grid) and its field."""
    mesh = sphere_mesh()
    grid = jv.Grid.fit(mesh, resolution=R)
    return mesh, grid, jv.sparse_distance_field(mesh, grid, band=BAND)


@pytest.fixture(scope="module")
def padded_sphere():
    """The sphere in a grid with room for its offset surfaces."""
    mesh = sphere_mesh()
    grid = jv.Grid.fit(mesh, resolution=R, padding=0.1)
    return mesh, grid, jv.sparse_distance_field(mesh, grid, band=BAND)


def assert_closed(mesh: jv.Mesh) -> None:
    """Every undirected edge is used by exactly two faces, in opposite directions."""
    import trimesh

    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64)
    assert len(f) > 0
    assert (f[:, 0] != f[:, 1]).all() and (f[:, 1] != f[:, 2]).all() and (f[:, 2] != f[:, 0]).all()
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = directed[:, 0] * len(v) + directed[:, 1]
    assert len(np.unique(key)) == len(key), "a directed edge is used twice"
    assert np.isin(directed[:, 1] * len(v) + directed[:, 0], key).all(), "an edge is used once"
    assert np.unique(f).size == len(v), "unused vertices"
    t = trimesh.Trimesh(v, f, process=False)
    assert t.is_watertight and t.is_winding_consistent


def distance_to_mesh(mesh: jv.Mesh, points, bound: float) -> np.ndarray:
    """Float64 distances from points [P, 3] to `mesh`, exact where below `bound` (otherwise
    at least `bound`, possibly inf): only faces whose centroid lies within `bound` plus the
    largest centroid-corner distance of a point are checked."""
    from scipy.spatial import cKDTree

    tri = np.asarray(mesh.triangles(), np.float64)
    centroid = tri.mean(1)
    radius = bound + np.linalg.norm(tri - centroid[:, None], axis=2).max()
    points = np.asarray(points, np.float64)
    near = cKDTree(centroid).query_ball_point(points, radius)
    owner = np.repeat(np.arange(len(points)), [len(x) for x in near])
    face = np.concatenate([np.asarray(x, np.int64) for x in near])
    q = closest_point_on_triangles(points[owner], tri[face, 0], tri[face, 1], tri[face, 2])
    out = np.full(len(points), np.inf)
    np.minimum.at(out, owner, np.linalg.norm(q - points[owner], axis=1))
    return out


def signed_volume(mesh: jv.Mesh) -> float:
    t = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)]
    return float(np.linalg.det(t).sum() / 6)


def test_sphere_is_closed_outward_and_on_the_surface(sphere):
    mesh, grid, field = sphere
    out = jv.field_to_mesh(field)
    h = float(grid.voxel_size)
    assert out.vertices.dtype == np.float32 and out.faces.dtype == np.int32
    assert_closed(out)
    volume = signed_volume(out)
    assert volume > 0  # counter-clockwise seen from outside
    np.testing.assert_allclose(volume, signed_volume(mesh), rtol=0.02)
    d = distance_to_mesh(mesh, out.vertices, h)
    assert d.max() < 0.5 * h
    np.testing.assert_allclose(d[::20], mesh_distance(mesh.vertices, mesh.faces, out.vertices[::20]), atol=1e-12)
    rng = np.random.default_rng(0)  # the other direction: points on the input surface
    tri = np.asarray(mesh.triangles(), np.float64)
    w = rng.dirichlet(np.ones(3), 2000)
    samples = np.einsum("pk,pkd->pd", w, tri[rng.integers(len(tri), size=2000)])
    samples = np.concatenate([samples, np.asarray(mesh.vertices)])
    assert distance_to_mesh(out, samples, h).max() < h


def test_small_blocks_stitch_to_the_same_mesh(sphere, monkeypatch):
    _, _, field = sphere
    reference = jv.field_to_mesh(field)
    for block in (4, 7):  # 7: blocks that do not divide the grid
        keys, points, _ = _march(field, 0.0, block)
        unique, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
        assert len(unique) < len(keys)  # vertices on block faces, found by both blocks ...
        np.testing.assert_array_equal(points, points[first][inverse])  # ... at the same position
        monkeypatch.setattr(field_mesh, "BLOCK", block)
        out = jv.field_to_mesh(field)
        assert_closed(out)
        np.testing.assert_array_equal(out.vertices, reference.vertices)
        np.testing.assert_array_equal(out.faces, reference.faces)


@pytest.mark.parametrize("shift", [-1.0, 1.0])
def test_level_offsets_the_surface(padded_sphere, shift):
    mesh, grid, field = padded_sphere
    h = float(grid.voxel_size)
    out = jv.field_to_mesh(field, level=shift * h)
    assert_closed(out)
    d = distance_to_mesh(mesh, out.vertices, 2 * h)
    assert np.abs(d - abs(shift) * h).max() < 0.5 * h
    radius = np.linalg.norm(np.asarray(out.vertices, np.float64) - 0.5, axis=1)
    assert (np.sign(shift) * (radius - RADIUS) > 0).all()  # outside the sphere for > 0, inside for < 0
    assert np.sign(signed_volume(out) - signed_volume(jv.field_to_mesh(field))) == np.sign(shift)


def test_box_with_faces_on_voxel_centres():
    """Samples exactly on the level (the box's faces pass through voxel centres) are nudged
    off it: still closed, no degenerate faces, vertices on the box."""
    import trimesh

    h = 1.0 / R
    b = trimesh.creation.box(bounds=[[8.5 * h, 10.5 * h, 12.5 * h], [23.5 * h, 20.5 * h, 19.5 * h]])
    mesh = jv.Mesh(np.asarray(b.vertices, np.float32), np.asarray(b.faces, np.int32))
    grid = jv.Grid(origin=np.zeros(3, np.float32), voxel_size=h, resolution=R)
    field = jv.sparse_distance_field(mesh, grid, band=BAND)
    assert (np.abs(np.asarray(field.values[: int(field.count)])) < 1e-4 * h).sum() > 100
    out = jv.field_to_mesh(field)
    assert_closed(out)
    assert signed_volume(out) > 0
    assert distance_to_mesh(mesh, out.vertices, h).max() < 0.5 * h


def test_empty_and_uncrossed_fields_give_empty_meshes(sphere):
    mesh, grid, _ = sphere
    empty = jv.sparse_distance_field(jv.Mesh(np.zeros((3, 3)), np.zeros((0, 3))), grid, band=BAND)
    assert int(empty.count) == 0
    unsigned = jv.sparse_distance_field(mesh, grid, band=BAND, signed=False)
    for field, level in ((empty, 0.0), (unsigned, -0.5 * float(grid.voxel_size))):
        out = jv.field_to_mesh(field, level=level)
        assert out.vertices.shape == (0, 3) and out.faces.shape == (0, 3)


def test_bad_inputs_are_refused(sphere):
    mesh, grid, field = sphere
    h = float(grid.voxel_size)
    with pytest.raises(jv.JaxvoxError, match="field_to_mesh field: expected a jaxvox.SparseField, got Mesh"):
        jv.field_to_mesh(mesh)
    for level in (BAND * h, -BAND * h, 10.0, float("nan"), float("inf"), "0"):
        with pytest.raises(jv.JaxvoxError, match="field_to_mesh level"):
            jv.field_to_mesh(field, level=level)
    batched = jax.tree.map(lambda x: jnp.stack([x, x]), field)
    with pytest.raises(jv.JaxvoxError, match="field_to_mesh field: must be a single field"):
        jv.field_to_mesh(batched)
    broken = dataclasses.replace(field, values=field.values.at[0].set(jnp.nan))
    with pytest.raises(jv.JaxvoxError, match="field_to_mesh field: values must be finite"):
        jv.field_to_mesh(broken)
