"""Cascaded clipmaps: incremental updates against scratch builds and the exact clamped
field, the scissor volumes of a move, the compile budget of a flight, and sphere tracing
through the cascades."""

from __future__ import annotations

import hypothesis
import hypothesis.strategies as st
import jax
import numpy as np
import pytest

import jaxvox as jv
from jaxvox.distance.clipmap import _exposed_boxes
from tests.reference import first_hit, mesh_distance, winding_number
from tests.test_compiles import count_compiles
from tests.test_distance import BOUNDS, ISOLATED_SWEEP_BOUND, icosphere


def _open_sphere() -> jv.Mesh:
    """An icosphere with a cap cut off (open edges: signed by winding numbers)."""
    sphere = icosphere(2, 0.5, (0.1, 0.0, 0.0))
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    return jv.Mesh(v, f[v[f].mean(1)[:, 2] < 0.3])


def _exact_clamped(mesh: jv.Mesh, clip: jv.Clipmap):
    """The float64 clamped signed distance [N, R, R, R] in voxels of each cascade, in the
    clipmap's toroidal slots, and the winding numbers there (brute force)."""
    n, r = clip.num_cascades, clip.resolution
    ref, wind = np.zeros((n, r, r, r)), np.zeros((n, r, r, r))
    for c in range(n):
        h = float(clip.voxel_size) * 2.0**c
        g = np.asarray(clip.corner[c]) + np.argwhere(np.ones((r, r, r), bool))
        centres = np.asarray(clip.origin, np.float64) + (g + 0.5) * h
        slots = tuple(np.mod(g, r).T)
        w = winding_number(mesh.vertices, mesh.faces, centres)
        d = np.minimum(mesh_distance(mesh.vertices, mesh.faces, centres) / h, clip.truncation)
        ref[c][slots], wind[c][slots] = np.where(w > 0.5, -d, d), w
    return ref, wind


@pytest.mark.parametrize("method", ["exact", "band"])
def test_clipmap_incremental_equals_scratch_after_moves(method):
    """After time-sliced moves (small, large, random), the incremental clipmap equals a
    build from scratch: bit for bit for "exact" (a function of position: each pair is
    evaluated relative to its triangle's lattice voxel), and to float32 rounding for
    "band" (a function of the seeds near each voxel; see `Clipmap`)."""
    mesh = icosphere(1, 0.5, (0.1, 0.0, 0.0))
    kw = dict(resolution=16, num_cascades=3, voxel_size=0.05, method=method)
    rng = np.random.default_rng(5)
    moves = [(-0.9, 0.2, 0.1), (-0.85, 0.2, 0.1), (2.0, 1.0, -1.0)] + list(rng.uniform(-1, 1, (3, 3)))
    clip = jv.build_clipmap(mesh, (-1.0, 0.2, 0.1), **kw)
    for frame, camera in enumerate(moves):  # time-sliced: at most one cascade per frame
        clip = jv.update_clipmap(clip, mesh, camera, cascades=jv.time_sliced_cascades(frame, 3))
        assert len(jv.time_sliced_cascades(frame, 3)) == 1
    clip = jv.update_clipmap(clip, mesh, moves[-1])  # catch up every cascade
    scratch = jv.build_clipmap(mesh, moves[-1], **kw)
    np.testing.assert_array_equal(np.asarray(clip.corner), np.asarray(scratch.corner))
    if method == "exact":
        np.testing.assert_array_equal(np.asarray(clip.fields), np.asarray(scratch.fields))
    else:
        np.testing.assert_allclose(np.asarray(clip.fields), np.asarray(scratch.fields), atol=1e-5)
    # stored values are the signed distance at each voxel centre, clamped (exact, or within
    # the separable jump flooding's bound, never below)
    above = BOUNDS["exact"][0] if method == "exact" else BOUNDS["jfa-separable"][0]
    c, r = 1, 16
    h = 0.05 * 2**c
    g = np.asarray(scratch.corner[c]) + np.argwhere(np.ones((r, r, r), bool))
    centres = (g + 0.5) * h
    slots = np.mod(g, r)
    ref = np.minimum(mesh_distance(mesh.vertices, mesh.faces, centres), 8 * h) / h
    inside = winding_number(mesh.vertices, mesh.faces, centres[::97]) > 0.5
    got = np.asarray(scratch.fields[c])[tuple(slots.T)] / h
    err = np.abs(got) - ref
    assert err.max() <= above + 1e-4 and err.min() >= -2e-4, (err.min(), err.max())
    np.testing.assert_array_equal(got[::97] < 0, inside)
    # union with a dynamic object: pointwise min
    if method == "band":
        return
    ball = jv.build_clipmap(icosphere(0, 0.2, (-0.6, 0.0, 0.0)), moves[-1], **kw)
    union = jv.union_clipmaps(scratch, ball)
    np.testing.assert_array_equal(np.asarray(union.fields), np.minimum(scratch.fields, ball.fields))


@pytest.mark.parametrize("mesh", [icosphere(2, 0.5, (0.1, 0.0, 0.0)), _open_sphere()], ids=["watertight", "open"])
def test_exact_clipmap_matches_float64_after_moves(mesh):
    """The default "exact" method after moves (the lattice indices of the windows go
    negative) equals the float64 clamped signed distance within 1e-3 voxel at every voxel
    of every cascade, with no sign error: parity for the watertight mesh, winding numbers
    for the open one (excused only where the float64 winding number is within 1e-4 of
    1/2: a tie of the inside test itself)."""
    kw = dict(resolution=16, num_cascades=3, voxel_size=0.05, truncation=3.0)
    clip = jv.build_clipmap(mesh, (-0.9, 0.2, 0.1), **kw)
    assert clip.method == "exact"
    for frame, camera in enumerate([(-0.8, 0.25, 0.1), (-0.3, 0.0, 0.2), (0.35, -0.3, -0.1), (0.4, -0.25, -0.1)]):
        clip = jv.update_clipmap(clip, mesh, camera, cascades=None if frame % 2 else jv.time_sliced_cascades(frame, 3))
    clip = jv.update_clipmap(clip, mesh, (0.4, -0.25, -0.1))
    assert (np.asarray(clip.corner) < 0).any()
    ref, wind = _exact_clamped(mesh, clip)
    got = np.asarray(clip.fields) / (0.05 * 2.0 ** np.arange(3))[:, None, None, None]
    assert (np.abs(ref) < 3.0).sum() > 1000 and (ref < 0).any()  # a real band, and an inside
    tie = np.abs(wind - 0.5) < 1e-4
    err = np.abs(got - ref)[~tie]
    assert err.max() <= 1e-3, err.max()
    firm = (np.abs(ref) > 1e-3) & ~tie
    np.testing.assert_array_equal(got[firm] < 0, ref[firm] < 0)
    # a mesh without faces: everything at the clamp, outside
    empty = jv.build_clipmap(jv.Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)), (0.0, 0.0, 0.0), **kw)
    limit = 3.0 * 0.05 * 2.0 ** np.arange(3)[:, None, None, None]
    np.testing.assert_allclose(np.asarray(empty.fields), np.broadcast_to(limit, got.shape), rtol=1e-6)


def test_exact_clipmap_flight_compiles_nothing_new():
    """Moves run programs already compiled: a flight repeated elsewhere on the lattice
    (camera and mesh shifted by a whole number of the coarsest voxels, so that every box
    and every count falls in the same buckets) compiles nothing."""
    mesh = icosphere(2, 0.5, (0.1, 0.0, 0.0))
    kw = dict(resolution=16, num_cascades=2, voxel_size=0.05)
    path = [np.array([-0.61, 0.13, 0.07]) + np.array([1.0, 0.5, 0.25]) * 0.08 * f for f in range(6)]

    def fly(shift):
        moved = jv.Mesh(np.asarray(mesh.vertices) + shift, mesh.faces)
        clip = jv.build_clipmap(moved, path[0] + shift, **kw)
        for camera in path[1:]:
            clip = jv.update_clipmap(clip, moved, camera + shift)
        return jax.block_until_ready(clip.fields)

    first = fly(np.zeros(3))
    with count_compiles() as n:
        again = fly(np.array([-1.6, 0.8, -2.4]))  # 16, 8 and 24 coarse voxels of 0.1
    assert n[0] == 0, f"{n[0]} programs compiled for a flight in the warmed-up buckets"
    np.testing.assert_allclose(np.sort(np.asarray(again).ravel()), np.sort(np.asarray(first).ravel()), atol=1e-5)


@hypothesis.settings(max_examples=60, deadline=None)
@hypothesis.given(st.sampled_from([4, 8]), st.lists(st.integers(-9, 9), min_size=6, max_size=6))
def test_exposed_boxes_cover_the_new_window_once(r, moves):
    """The scissor volumes of a move: disjoint boxes inside the new window whose union is
    exactly the voxels the old window lacks (nothing computed twice, nothing missed)."""
    old, new = np.array(moves[:3]), np.array(moves[3:])
    count = {}
    for lo, hi in _exposed_boxes(old, new, r):
        assert np.all(lo >= new) and np.all(hi <= new + r) and np.all(hi > lo)
        for g in np.ndindex(*(hi - lo)):
            key = tuple(lo + g)
            count[key] = count.get(key, 0) + 1
    want = {
        g
        for g in (tuple(new + np.array(i)) for i in np.ndindex(r, r, r))
        if np.any((np.array(g) < old) | (np.array(g) >= old + r))
    }
    assert set(count) == want and all(c == 1 for c in count.values())


@pytest.mark.parametrize("method", ["jfa", "jfa+sweep"])
def test_clipmap_pipeline_within_method_bounds(method):
    """Distance-field methods: after moves, the incremental clipmap and a scratch build
    are each within the method's bounds of the exact clipmap (so within the sum of both
    bounds of each other); signs agree away from the surface."""
    mesh = icosphere(1, 0.5, (0.1, 0.0, 0.0))
    kw = dict(resolution=16, num_cascades=2, voxel_size=0.05)
    clip = jv.build_clipmap(mesh, (-1.0, 0.2, 0.1), method=method, **kw)
    assert clip.method == method
    for frame, camera in enumerate([(-0.9, 0.2, 0.1), (0.4, -0.3, 0.2), (0.45, -0.2, 0.1)]):
        clip = jv.update_clipmap(clip, mesh, camera, cascades=jv.time_sliced_cascades(frame, 2))
    clip = jv.update_clipmap(clip, mesh, (0.45, -0.2, 0.1))
    scratch = jv.build_clipmap(mesh, (0.45, -0.2, 0.1), method=method, **kw)
    exact = jv.build_clipmap(mesh, (0.45, -0.2, 0.1), method="exact", **kw)
    np.testing.assert_array_equal(np.asarray(clip.corner), np.asarray(exact.corner))
    above, below = BOUNDS[method]
    above = ISOLATED_SWEEP_BOUND if "sweep" in method else above  # the mesh crosses the windows
    for c in range(2):
        h = 0.05 * 2**c
        ref = np.asarray(exact.fields[c]) / h
        firm = np.abs(ref) > 0.5  # the sign may differ within half a voxel of the surface
        for built in (clip, scratch):
            got = np.asarray(built.fields[c]) / h
            np.testing.assert_array_equal(np.sign(got[firm]), np.sign(ref[firm]))
            err = np.abs(got) - np.abs(ref)
            assert err.max() <= above + 1e-4 and err.min() >= -below - 1e-4, (c, err.min(), err.max())
    # Kept slots hold values from older windows: incremental and scratch differ, within both bounds.
    gap = (
        np.abs(np.asarray(clip.fields) - np.asarray(scratch.fields)) / (0.05 * 2.0 ** np.arange(2))[:, None, None, None]
    )
    assert gap.max() <= above + below + 1e-4


def test_clipmap_tracing_matches_exact_hits():
    mesh = icosphere(2, 0.5, (0.1, 0.0, 0.0))
    camera = np.array([-1.0, 0.2, 0.1])
    clip = jv.build_clipmap(mesh, camera, resolution=16, num_cascades=3, voxel_size=0.05)
    rng = np.random.default_rng(6)
    towards = np.array([0.1, 0.0, 0.0]) + rng.uniform(-0.3, 0.3, (24, 3)) - camera  # well inside the silhouette
    away = rng.normal(size=(8, 3)) * 0.2 + [-1.0, 0.0, 0.0]
    dirs = np.concatenate([towards, away])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = np.repeat(camera[None], len(dirs), 0)
    result = jax.jit(jv.trace_clipmap)(clip, origins, dirs)
    assert isinstance(result, jv.Hit)
    ref = first_hit(mesh.vertices, mesh.faces, origins, dirs)
    status, t, cascade = np.asarray(result.status), np.asarray(result.t), np.asarray(result.index)
    np.testing.assert_array_equal(status == jv.HIT, np.isfinite(ref))
    assert (status[np.isinf(ref)] == jv.MISS).all()
    hit = np.isfinite(ref)
    assert hit.sum() == 24
    h = 0.05 * 2.0 ** cascade[hit]
    assert (np.abs(t[hit] - ref[hit]) <= h).all()
    # Hit's conventions: inf, -1 and zero unless hit; the normal is the sphere's, outward
    assert np.isposinf(t[~hit]).all() and (cascade[~hit] == -1).all() and (cascade[hit] >= 0).all()
    np.testing.assert_array_equal(np.asarray(result.voxel), -1)
    normal = np.asarray(result.normal)
    np.testing.assert_array_equal(normal[~hit], 0.0)
    radial = origins[hit] + t[hit, None] * dirs[hit] - [0.1, 0.0, 0.0]
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    np.testing.assert_allclose(np.linalg.norm(normal[hit], axis=1), 1.0, atol=1e-5)
    assert (np.sum(normal[hit] * radial, axis=1) > 0.9).all()
    capped = jv.trace_clipmap(clip, origins[:4], dirs[:4], max_steps=1).status
    assert (np.asarray(capped) == jv.STEP_CAP).all()
