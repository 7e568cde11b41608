"""Solid voxelization (parity and winding numbers) and open edges against float64 references."""

from __future__ import annotations

import numpy as np
import pytest

import jaxvox as jv
from tests.reference import closest_point_on_triangles, mesh_distance, morton_encode, ray_parity, winding_number
from tests.test_distance import icosphere, voxel_centres


def test_sign_parity_on_watertight_meshes(meshes_dir):
    for name in ("spot", "cow"):
        mesh = jv.load_mesh(meshes_dir / f"{name}.obj")
        assert jv.open_edges(mesh) == 0
        grid = jv.Grid.fit(mesh, resolution=32, padding=0.05)
        solid = np.asarray(jv.solid_voxelize(mesh, grid, method="parity"))
        points = voxel_centres(grid)
        idx = np.random.default_rng(1).choice(len(points), 250, replace=False)
        ref = ray_parity(mesh.vertices, mesh.faces, points[idx])
        assert 0 < solid.sum() < solid.size
        np.testing.assert_array_equal(solid.reshape(-1)[idx], ref)
        field = np.asarray(jv.distance_field(mesh, grid, method="jfa+sweep"))  # sign="auto": parity
        np.testing.assert_array_equal(field < 0, solid)


def test_sign_winding_on_open_mesh_and_parity_refuses(meshes_dir):
    mesh = jv.load_mesh(meshes_dir / "suzanne.obj")
    assert jv.open_edges(mesh) > 0
    grid = jv.Grid.fit(mesh, resolution=16, padding=0.05)
    with pytest.raises(jv.JaxvoxError, match="watertight"):
        jv.solid_voxelize(mesh, grid, method="parity")
    with pytest.raises(jv.JaxvoxError, match="watertight"):
        jv.distance_field(mesh, grid, sign="parity")
    idx = np.random.default_rng(4).choice(16**3, 400, replace=False)
    w = winding_number(mesh.vertices, mesh.faces, voxel_centres(grid)[idx])
    solid = np.asarray(jv.solid_voxelize(mesh, grid)).reshape(-1)[idx]  # auto: winding
    firm = np.abs(w - 0.5) > 1e-3
    assert firm.sum() > 390 and solid.any()
    np.testing.assert_array_equal(solid[firm], (w > 0.5)[firm])


def test_winding_and_parity_agree_on_closed_sphere():
    mesh = icosphere(2, 0.7, (0.0, 0.0, 0.0))
    grid = jv.Grid(origin=(-1.0, -1.0, -1.0), voxel_size=2 / 16, resolution=16)
    parity = np.asarray(jv.solid_voxelize(mesh, grid, method="parity"))
    winding = np.asarray(jv.solid_voxelize(mesh, grid, method="winding"))
    np.testing.assert_array_equal(parity, winding)
    r = np.linalg.norm(voxel_centres(grid), axis=1).reshape((16,) * 3)
    assert parity[r < 0.6].all() and not parity[r > 0.71].any()


def _exposed(solid: np.ndarray, band: np.ndarray) -> np.ndarray:
    """Reference boundary: solid voxels in `band` with a face neighbour in `band` that is
    not solid, or on the grid's faces (dense [R, R, R] bools)."""
    out = np.zeros_like(solid)
    edge = np.pad(np.zeros_like(solid), 1, constant_values=True)
    s, b = np.pad(solid, 1), np.pad(band, 1)
    for axis in range(3):
        for shift in (-1, 1):
            n = lambda a: np.roll(a, shift, axis=axis)[1:-1, 1:-1, 1:-1]
            out |= (n(b) & ~n(s)) | n(edge)
    return solid & band & out


def _dense(vox) -> np.ndarray:
    r = vox.grid.resolution
    out = np.zeros((r, r, r), bool)
    ijk = np.asarray(vox.coords[: int(vox.count)])
    out[tuple(ijk.T)] = True
    return out


def _boundary_reference(mesh, grid):
    """The float64 boundary: solid voxels (winding numbers) within one voxel of the mesh
    (distances) exposed by such a neighbour or the grid's faces; also the voxels whose
    answer is unsure (next to a centre within 1e-4 voxel of distance 1 or of winding
    number 1/2), and the distances in voxels, all [R, R, R]."""
    r, h = grid.resolution, float(grid.voxel_size)
    points = voxel_centres(grid)
    dist = mesh_distance(mesh.vertices, mesh.faces, points).reshape((r, r, r)) / h
    near = np.flatnonzero(dist.reshape(-1) <= 1.5)
    winding = np.zeros(r**3)
    winding[near] = winding_number(mesh.vertices, mesh.faces, points[near])
    winding = winding.reshape(dist.shape)
    band = dist <= 1.0
    unsure = np.pad((np.abs(dist - 1.0) < 1e-4) | ((np.abs(winding - 0.5) < 1e-4) & band), 1)
    unsure = sum(np.roll(unsure, s, axis=a) for a in range(3) for s in (-1, 0, 1))[1:-1, 1:-1, 1:-1] > 0
    return _exposed(winding > 0.5, band), unsure, dist


@pytest.mark.parametrize("name", ["spot", "suzanne"])
def test_solid_boundary_against_float64(meshes_dir, name):
    """The boundary of the solid (float64 winding numbers) within one voxel of the mesh
    (float64 distances); for watertight spot that is the whole boundary of the parity
    solid. Each voxel's triangle is its closest one."""
    mesh = jv.load_mesh(meshes_dir / f"{name}.obj")
    grid = jv.Grid.fit(mesh, resolution=32, padding=0.05)
    vox = jv.solid_boundary(mesh, grid, triangle_ids=True)
    got = _dense(vox)
    ref, unsure, dist = _boundary_reference(mesh, grid)
    assert ref.sum() > 500 and unsure.sum() < 20
    np.testing.assert_array_equal(got[~unsure], ref[~unsure])
    assert vox.mode == "solid-boundary" and int(vox.overflow) == 0 and vox.capacity >= int(vox.count)
    codes = morton_encode(np.asarray(vox.coords[: int(vox.count)]))
    assert (np.diff(codes.astype(np.int64)) > 0).all()
    if name == "spot":  # watertight: exactly the boundary of the parity solid, nothing cut by the band
        parity = np.asarray(jv.solid_voxelize(mesh, grid, method="parity"))
        np.testing.assert_array_equal(got, _exposed(parity, np.ones_like(parity)))
    ijk = np.asarray(vox.coords[: int(vox.count)])
    tri = np.asarray(vox.triangle[: int(vox.count)])
    centres = voxel_centres(grid).reshape(got.shape + (3,))[tuple(ijk.T)]
    corners = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)[tri]]
    own = np.linalg.norm(centres - closest_point_on_triangles(centres, *corners.transpose(1, 0, 2)), axis=1)
    np.testing.assert_allclose(own / float(grid.voxel_size), dist[tuple(ijk.T)], atol=1e-4)


def test_solid_boundary_renders_as_the_solid(meshes_dir):
    """Rays from outside the grid (random, and axis-aligned in voxel face planes) hit the
    boundary's DAG where they hit the dense solid: same voxel, entry distance and face."""
    mesh = jv.load_mesh(meshes_dir / "spot.obj")
    grid = jv.Grid.fit(mesh, resolution=32, padding=0.05)
    solid = np.asarray(jv.solid_voxelize(mesh, grid, method="parity"))
    tree = jv.build_dag(jv.solid_boundary(mesh, grid))
    rng = np.random.default_rng(7)
    centre = np.asarray(grid.origin) + 16 * float(grid.voxel_size)
    far = 40 * float(grid.voxel_size)
    around = rng.normal(size=(3000, 3))
    origins = centre + far * around / np.linalg.norm(around, axis=1, keepdims=True)  # outside the grid
    aim = centre + 10 * float(grid.voxel_size) * rng.uniform(-1, 1, size=(3000, 3))
    directions = aim - origins
    plane = np.asarray(grid.origin) + float(grid.voxel_size) * rng.integers(8, 24, size=(600, 3))
    axis = rng.integers(0, 3, 600)
    origins[:600] = plane
    origins[np.arange(600), axis] = centre[axis] - far  # on voxel face planes, along an axis
    directions[:600] = 0.0
    directions[np.arange(600), axis] = 1.0
    origins, directions = origins.astype(np.float32), directions.astype(np.float32)
    dense = jv.trace_dense(solid, grid, origins, directions)
    hit = jv.trace(tree, origins, directions)
    assert (np.asarray(dense.status) == jv.HIT).sum() > 1500
    np.testing.assert_array_equal(np.asarray(hit.status), np.asarray(dense.status))
    np.testing.assert_array_equal(np.asarray(hit.voxel), np.asarray(dense.voxel))
    np.testing.assert_array_equal(np.asarray(hit.normal), np.asarray(dense.normal))
    np.testing.assert_allclose(np.asarray(hit.t), np.asarray(dense.t), rtol=1e-5)


def test_solid_boundary_edge_cases(tmp_path):
    grid = jv.Grid(origin=(-1.0, -1.0, -1.0), voxel_size=2 / 16, resolution=16)
    empty = jv.Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    vox = jv.solid_boundary(empty, grid, triangle_ids=True)
    assert int(vox.count) == 0 and vox.triangle is not None
    with pytest.raises(jv.JaxvoxError, match="solid_boundary grid"):
        jv.solid_boundary(empty, "grid")
    with pytest.raises(jv.JaxvoxError, match="solid_boundary triangle_ids"):
        jv.solid_boundary(empty, grid, triangle_ids=1)
    # A sphere cut by the grid's faces: exposed there within one voxel of the mesh.
    sphere = icosphere(3, 1.1, (0.0, 0.0, 0.0))
    vox = jv.solid_boundary(sphere, grid)
    got = _dense(vox)
    ref, unsure, _ = _boundary_reference(sphere, grid)
    assert ref[0].any() and ref[1:-1, 1:-1, 1:-1].any()
    np.testing.assert_array_equal(got[~unsure], ref[~unsure])
    jv.save_voxels(tmp_path / "b.npz", vox)
    again = jv.load_voxels(tmp_path / "b.npz")
    assert again.mode == "solid-boundary" and int(again.count) == int(vox.count)
