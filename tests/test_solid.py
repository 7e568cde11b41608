"""Solid voxelization (parity and winding numbers) and open edges against float64 references."""

from __future__ import annotations

import numpy as np
import pytest

import jaxvox as jv
from tests.reference import ray_parity, winding_number
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
