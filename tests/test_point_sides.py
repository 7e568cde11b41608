"""Sides from cells (`jaxvox.points.sides`): every side the grid certifies is the side of
the float64 winding number, on real, open, self-intersecting and damaged meshes, for
points uniform in the box, near the surface, on vertices and edges, and on cell faces;
and the host API's many-point path gives the answers of the per-point path.

The meshes are indexed with one face capacity and queried with one point count, so that
they share the compiled programs.
"""

from __future__ import annotations

import os

import jax
import numpy as np
import pytest
import trimesh

import jaxvox as jv
from jaxvox import points as jp
from jaxvox.points import queries, sides

from . import reference
from .test_points import thin_plate

CAP = 16384  # face capacity
# Points per mesh (an eighth per kind): the float64 winding numbers of every point are
# most of the certified-sides test's time, so it runs at 2048 unless JAXVOX_SLOW_SCALE=full.
N = 4096 if os.environ.get("JAXVOX_SLOW_SCALE") == "full" else 2048


def _damaged(tm: trimesh.Trimesh, rng) -> jv.Mesh:
    """Holes punched (a tenth of the faces gone), some faces flipped, some duplicated."""
    f = np.asarray(tm.faces)
    f = f[rng.random(len(f)) > 0.1]
    flip = rng.random(len(f)) < 0.02
    f = np.where(flip[:, None], f[:, ::-1], f)
    f = np.concatenate([f, f[rng.choice(len(f), 20)]])
    return jv.Mesh(np.asarray(tm.vertices, np.float32), np.asarray(f, np.int32))


def _meshes(meshes_dir):
    rng = np.random.default_rng(0)
    load = lambda name: trimesh.load(meshes_dir / f"{name}.obj", process=False, force="mesh")
    overlap = trimesh.util.concatenate([trimesh.creation.icosphere(3), trimesh.creation.icosphere(3)])
    overlap.vertices[len(overlap.vertices) // 2 :] += [0.7, 0.2, 0.1]
    yield "suzanne (open, pieces)", jv.load_mesh(meshes_dir / "suzanne.obj")
    yield "spot (closed)", jv.load_mesh(meshes_dir / "spot.obj")
    yield "fandisk damaged", _damaged(load("fandisk"), rng)
    yield "overlapping spheres", jv.Mesh(np.asarray(overlap.vertices, np.float32), np.asarray(overlap.faces, np.int32))
    yield "thin plate (open, thinner than a cell)", thin_plate()


def _points(mesh: jv.Mesh, grid: sides.SideGrid, rng) -> np.ndarray:
    """Uniform in 1.2x the box, near the surface (two scales), on vertices and edge
    midpoints, and on cell faces of the grid."""
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces)
    lo, hi = v.min(0), v.max(0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 * 1.2
    k = N // 8
    tri = v[f[rng.integers(0, len(f), 3 * k)]]
    on = np.einsum("nk,nkd->nd", rng.dirichlet([1, 1, 1], 3 * k), tri)
    scale = np.linalg.norm(hi - lo)
    near = on + rng.normal(size=on.shape) * np.repeat([1e-3, 1e-2, 3e-2], k)[:, None] * scale
    cell, origin = float(grid.cell), np.asarray(grid.origin, np.float64)
    planes = rng.uniform(lo, hi, (k, 3))
    planes[:, 0] = origin[0] + np.round((planes[:, 0] - origin[0]) / cell) * cell  # on x cell faces
    edges = (v[f[:, 0]] + v[f[:, 1]]) / 2
    parts = [rng.uniform(centre - half, centre + half, (N - 6 * k, 3)), near, v[:k], edges[:k], planes]
    return np.concatenate(parts).astype(np.float32)[:N]


@pytest.mark.slow
def test_certified_sides_are_the_winding_numbers_sides(meshes_dir):
    rng = np.random.default_rng(1)
    for name, mesh in _meshes(meshes_dir):
        index = jp.mesh_index(mesh, capacity=CAP)
        grid = sides.side_grid(index)
        p = _points(mesh, grid, rng)
        side, stand_in = sides.grid_sides(index, p)
        w = reference.winding_number(np.asarray(mesh.vertices), np.asarray(mesh.faces), p)
        certain = side >= 0
        uniform = certain[: N - 6 * (N // 8)]  # on and next to the surface, fewer can be
        if "damaged" not in name:  # (a thousand holes: their caps' bound certifies few cells)
            assert uniform.mean() > 0.9 and certain.mean() > 0.6, (name, uniform.mean(), certain.mean())
        wrong = (side[certain] == 1) != (w[certain] > 0.5)
        assert not wrong.any(), (name, np.flatnonzero(certain)[wrong][:5], w[certain][wrong][:5])
        assert ((stand_in[certain] > 0.5) == (side[certain] == 1)).all() and np.isnan(stand_in[~certain]).all()
        walked = certain & (stand_in != np.round(stand_in))  # a walk's w: the winding number
        np.testing.assert_allclose(stand_in[walked], w[walked], atol=1e-4, err_msg=name)
        assert (np.abs(w[certain] - 0.5) > sides.EXACT_MARGIN - 1e-4).all(), name


def test_caps_close_every_boundary_loop():
    """Mesh plus caps is a closed chain (no boundary edge left); a closed mesh gets none."""
    from jaxvox.distance.topology import boundary_chain, welded_faces

    tm = trimesh.creation.icosphere(2)
    keep = np.abs(tm.triangles_center[:, 2]) < 0.7  # holes at the top and the bottom
    v, f = np.asarray(tm.vertices), np.asarray(tm.faces[keep])
    caps, loop = sides.cap_triangles(v, f)
    assert loop.max() + 1 == 2
    all_v = np.concatenate([v, caps.reshape(-1, 3)])
    all_f = np.concatenate([f, len(v) + np.arange(3 * len(caps)).reshape(-1, 3)])
    assert len(boundary_chain(welded_faces(all_v, all_f))) == 0
    assert len(sides.cap_triangles(v, np.asarray(tm.faces))[0]) == 0


def test_many_points_take_the_cells_and_agree_with_the_per_point_path(meshes_dir, monkeypatch):
    """occupancy and signed_distance with at least GRID_MIN points (the cells) against
    query_points (winding numbers for every point), NaN points included. GRID_MIN is
    lowered to 8192 here: the same paths at an eighth of the points."""
    monkeypatch.setattr(queries, "GRID_MIN", 8192)
    mesh = jv.load_mesh(meshes_dir / "suzanne.obj")
    index = jp.mesh_index(mesh, capacity=CAP)
    rng = np.random.default_rng(2)
    v = np.asarray(mesh.vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    p = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), (queries.GRID_MIN, 3)).astype(np.float32)
    p[:3] = np.nan
    full = jp.query_points(index, p)
    inside = np.asarray(jp.occupancy(index, p))
    sd = np.asarray(jp.signed_distance(index, p))
    certain = np.asarray(full.status) == jp.PointStatus.OK
    np.testing.assert_array_equal(inside[certain], np.asarray(full.inside)[certain])
    np.testing.assert_array_equal(sd, np.asarray(full.signed_distance))
    assert not inside[:3].any() and np.isnan(sd[:3]).all()
    # the sampler (near-surface points mostly) takes the cells too: the same answers and statuses
    samples = jv.sample_sdf(mesh, queries.GRID_MIN, jax.random.key(0), index=index)
    again = jp.query_points(index, np.asarray(samples.points))
    np.testing.assert_array_equal(np.asarray(samples.status), np.asarray(again.status))
    np.testing.assert_array_equal(np.asarray(samples.sdf), np.asarray(again.signed_distance))
