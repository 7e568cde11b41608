"""Fast generalized winding numbers against the float64 brute force (tests/reference.py)."""

from __future__ import annotations

import hypothesis
import hypothesis.strategies as st
import numpy as np
import pytest

import jaxvox as jv
from tests.reference import closest_point_on_triangles, winding_number

# Far-field error of the tree at beta = 2, in winding-number units: measured at most
# 5e-3 on spot and 3e-3 on the bunny at 32^3, 4e-3 on random triangle soups.
TOLERANCE = 1e-2


def _centres(grid: jv.Grid) -> np.ndarray:
    r = grid.resolution
    ijk = np.stack(np.unravel_index(np.arange(r**3), (r,) * 3), -1)
    return np.asarray(grid.origin, np.float64) + (ijk + 0.5) * float(grid.voxel_size)


@pytest.mark.parametrize("name, block", [("spot", 4), ("stanford-bunny", 2), ("suzanne", 1)])
def test_data_meshes_against_brute_force(meshes_dir, name, block):
    """Every voxel (spot, suzanne) or a sample (the bunny) at 16^3: within TOLERANCE, and
    the same inside/outside decision wherever the exact value is not that close to 1/2."""
    mesh = jv.load_mesh(meshes_dir / f"{name}.obj")
    grid = jv.Grid.fit(mesh, resolution=16, padding=0.1)
    got = np.asarray(jv.winding_numbers(mesh, grid, block=block)).reshape(-1)
    idx = np.arange(16**3) if mesh.num_faces < 10_000 else np.random.default_rng(0).choice(16**3, 300, replace=False)
    ref = winding_number(mesh.vertices, mesh.faces, _centres(grid)[idx])
    assert np.abs(got[idx] - ref).max() < TOLERANCE
    firm = np.abs(ref - 0.5) > TOLERANCE
    np.testing.assert_array_equal((got[idx] > 0.5)[firm], (ref > 0.5)[firm])
    assert (ref > 0.5).any()


@hypothesis.settings(deadline=None, max_examples=8)
@hypothesis.given(
    st.lists(st.tuples(*[st.floats(-0.5, 1.5, width=32)] * 9), min_size=1, max_size=40), st.sampled_from([1, 2, 8])
)
# A repeated corner: voxel centres on the segment read atan2(+-0, den <= 0) = +-pi, half a
# winding number, until zero-area triangles got no solid angle (found by hypothesis).
@hypothesis.example(corners=[(0.0,) * 9, (0.0,) * 6 + (1.5, 1.5, 0.5)], block=1)
@hypothesis.example(corners=[(0.0,) * 9, (0.0, 1.5, 0.0, 0.0, 0.0, 0.0, 1.5, 0.0, 0.5)], block=1)  # a centre on an edge
def test_random_soups_against_brute_force(corners, block):
    """Random triangles, degenerate ones and ones outside the grid included."""
    v = np.array(corners, np.float32).reshape(-1, 3)
    mesh = jv.Mesh(v, np.arange(len(v), dtype=np.int32).reshape(-1, 3))
    grid = jv.Grid(origin=(0.0, 0.0, 0.0), voxel_size=1 / 8, resolution=8)
    got = np.asarray(jv.winding_numbers(mesh, grid, block=block)).reshape(-1)
    centres = _centres(grid)
    ref = winding_number(v, np.asarray(mesh.faces), centres)
    assert np.isfinite(got).all()
    # A voxel centre on a triangle (its plane inside it, or an edge) has an undefined
    # solid angle, and one within float32 rounding of it an ill-conditioned one: those
    # are left out. A triangle of zero area has none, also from a point on it.
    tris = v.reshape(-1, 3, 3).astype(np.float64)
    proper = np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1) > 0
    near = np.zeros(len(centres), bool)
    for a, b, c in tris[proper]:
        near |= np.linalg.norm(closest_point_on_triangles(centres, a, b, c) - centres, axis=1) < 1e-6
    np.testing.assert_allclose(got[~near], ref[~near], atol=TOLERANCE)


def test_huge_beta_is_the_brute_force_and_orientation_flips_the_sign(meshes_dir):
    mesh = jv.load_mesh(meshes_dir / "woody.obj")
    grid = jv.Grid.fit(mesh, resolution=8, padding=0.1)
    ref = winding_number(mesh.vertices, mesh.faces, _centres(grid))
    exact = np.asarray(jv.winding_numbers(mesh, grid, beta=1e6)).reshape(-1)
    np.testing.assert_allclose(exact, ref, atol=1e-5)
    flipped = jv.Mesh(mesh.vertices, np.asarray(mesh.faces)[:, ::-1])
    np.testing.assert_allclose(
        np.asarray(jv.winding_numbers(flipped, grid)).reshape(-1),
        -np.asarray(jv.winding_numbers(mesh, grid)).reshape(-1),
        atol=1e-6,
    )


def test_empty_mesh_and_bad_arguments():
    grid = jv.Grid(origin=(0.0, 0.0, 0.0), voxel_size=1.0, resolution=4)
    empty = jv.Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    np.testing.assert_array_equal(np.asarray(jv.winding_numbers(empty, grid)), 0.0)
    tri = jv.Mesh(np.eye(3, dtype=np.float32), np.array([[0, 1, 2]], np.int32))
    with pytest.raises(jv.JaxvoxError, match="beta"):
        jv.winding_numbers(tri, grid, beta=1.0)
    with pytest.raises(jv.JaxvoxError, match="block"):
        jv.winding_numbers(tri, grid, block=3)
