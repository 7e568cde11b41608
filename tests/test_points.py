"""Point queries (`jaxvox.points`) against float64 references: closest points, winding
numbers, signs, statuses, gradients, jit/vmap, compile counts, the sampler and its command.

Most tests share one face capacity (`CAP`) and one point count (`N`), so that they run the
same few compiled programs.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from hypothesis import example, given, settings
from hypothesis import strategies as st

import jaxvox as jv
from jaxvox import points as jp
from jaxvox.points import queries

from . import reference

CAP = 512  # face capacity of the indices built here
N = 512  # points per query


def _mesh(tm) -> jv.Mesh:
    return jv.Mesh(np.asarray(tm.vertices, np.float32), np.asarray(tm.faces, np.int32))


@pytest.fixture(scope="module")
def sphere():
    return _mesh(trimesh.creation.icosphere(subdivisions=2))


@pytest.fixture(scope="module")
def hemisphere():
    """An open mesh: the icosphere's faces above z = -0.3 (a hole at the bottom)."""
    tm = trimesh.creation.icosphere(subdivisions=2)
    keep = tm.triangles_center[:, 2] > -0.3
    return jv.Mesh(np.asarray(tm.vertices, np.float32), np.asarray(tm.faces[keep], np.int32))


def thin_plate() -> jv.Mesh:
    """A thin part: a plate 1 x 0.6 x 0.003, open at one end (its +x side faces removed)."""
    tm = trimesh.creation.box(extents=(1.0, 0.6, 0.003))
    keep = tm.face_normals[:, 0] < 0.5
    return jv.Mesh(np.asarray(tm.vertices, np.float32), np.asarray(tm.faces[keep], np.int32))


@pytest.fixture(scope="module")
def thin():
    return thin_plate()


@pytest.fixture(scope="module")
def overlapping():
    """Self-intersecting: two overlapping spheres in one mesh, plus degenerate triangles
    (a repeated vertex and a sliver) and a duplicated face."""
    a = trimesh.creation.icosphere(subdivisions=1)
    b = a.copy()
    b.apply_translation([0.6, 0.1, 0.0])
    v = np.concatenate([a.vertices, b.vertices])
    f = np.concatenate([a.faces, b.faces + len(a.vertices)])
    sliver = [[0, 1, 1], [2, 3, 2]]
    f = np.concatenate([f, sliver, f[:1]])
    return jv.Mesh(np.asarray(v, np.float32), np.asarray(f, np.int32))


def _points(mesh: jv.Mesh, seed: int = 0) -> np.ndarray:
    """N points: uniform in the padded box, on vertices, edge midpoints, face centroids,
    just off faces, and far away."""
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces)
    rng = np.random.default_rng(seed)
    lo, hi = v.min(0), v.max(0)
    t = v[f]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    parts = [
        v[rng.choice(len(v), 48)],
        (t[:, 0] + t[:, 1])[rng.choice(len(f), 48)] / 2,
        t.mean(1)[rng.choice(len(f), 48)],
        (t.mean(1) + 1e-3 * n)[rng.choice(len(f), 48)],
        (t.mean(1) - 1e-3 * n)[rng.choice(len(f), 48)],
        rng.normal(size=(16, 3)) * 50,
    ]
    rest = N - sum(len(p) for p in parts)
    parts.append(rng.uniform(lo - 0.2 * (hi - lo), hi + 0.2 * (hi - lo), (rest, 3)))
    return np.concatenate(parts).astype(np.float32)


def _diagonal(mesh) -> float:
    v = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces).ravel()]
    return float(np.linalg.norm(v.max(0) - v.min(0)))


@pytest.mark.codegen
@pytest.mark.parametrize("name", ["sphere", "hemisphere", "overlapping", "thin"])
def test_closest_points_match_float64(name, request):
    mesh = request.getfixturevalue(name)
    p = _points(mesh)
    result = jp.closest_points(jp.mesh_index(mesh, capacity=CAP), p)
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    d = reference.mesh_distance(v, f, p)
    diag = _diagonal(mesh)
    np.testing.assert_array_less(np.abs(np.asarray(result.distance) - d), 1e-5 * diag * np.maximum(1, d / diag))
    assert (np.asarray(result.status) == jp.PointStatus.OK).all()
    # the point lies on its triangle, at its barycentric coordinates, at that distance
    t = v[f[np.asarray(result.triangle)]]
    bary = np.asarray(result.barycentric, np.float64)
    np.testing.assert_allclose(bary.sum(1), 1, atol=1e-5)
    assert (bary > -1e-5).all()
    on = np.einsum("nk,nkj->nj", bary, t)
    np.testing.assert_allclose(on, np.asarray(result.point), atol=1e-5 * diag)
    mine = np.linalg.norm(np.asarray(result.point, np.float64) - p, axis=1)
    np.testing.assert_array_less(np.abs(mine - d), 1e-5 * diag * np.maximum(1, d / diag))


def test_ties_go_to_the_smallest_face_id():
    # two copies of one triangle (ids 0 and 2) and a farther one: every point ties
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    v = np.concatenate([tri, tri + [0, 0, 5], tri])
    mesh = jv.Mesh(v, np.array([[6, 7, 8], [3, 4, 5], [0, 1, 2]], np.int32))
    p = np.random.default_rng(1).uniform(-1, 2, (N, 3)).astype(np.float32)
    p[:, 2] = np.minimum(p[:, 2], 2.0)
    result = jp.closest_points(jp.mesh_index(mesh, capacity=64), p)  # the hypothesis test's programs
    assert set(np.asarray(result.triangle).tolist()) == {0}


def test_the_points_own_bounds_keep_every_closest_triangle(meshes_dir, monkeypatch):
    """The search with each point's own bound (what few points get) and with the blocks'
    bounds alone (`closest.POINT_BOUNDS_MAX` 0: what many points get) finds the same
    triangles at the same distances on the bunny (open, 69 K faces), and for a thousand
    points spread over its box the points' bounds keep fewer pairs at every level."""
    from jaxvox.points import closest, search

    mesh = jv.load_mesh(meshes_dir / "stanford-bunny.obj")
    index = jp.mesh_index(mesh)
    v = np.asarray(mesh.vertices)
    p = np.random.default_rng(3).uniform(v.min(0), v.max(0), (1024, 3)).astype(np.float32)
    caps = (1 << 17, 1 << 16, 1 << 13, 1 << 10, 1 << 8, 1 << 13)  # room for what either search needs
    search_all = lambda q: closest.closest_slots(index, search.make_blocks(index, q), caps)
    found = []
    for limit in (closest.POINT_BOUNDS_MAX, 0):
        monkeypatch.setattr(closest, "POINT_BOUNDS_MAX", limit)
        found.append(jax.jit(lambda q: search_all(q))(p))  # (a new function each time: traced anew)
    own, block_only = found
    assert not np.asarray(own.lost).any() and not np.asarray(block_only.lost).any()
    np.testing.assert_array_equal(np.asarray(own.slot), np.asarray(block_only.slot))
    np.testing.assert_array_equal(np.asarray(own.dist2), np.asarray(block_only.dist2))
    assert (np.asarray(own.needs) <= np.asarray(block_only.needs)).all(), (own.needs, block_only.needs)
    assert int(own.needs[0]) < int(block_only.needs[0]) // 2, (own.needs, block_only.needs)


def test_winding_numbers_fast_within_bound_and_exact(hemisphere, overlapping):
    for mesh in (hemisphere, overlapping):
        index = jp.mesh_index(mesh, capacity=CAP)
        p = _points(mesh, seed=2)
        ref = reference.winding_number(mesh.vertices, mesh.faces, p)
        w, bound = jp.winding_number(index, p, return_bound=True)
        w, bound = np.asarray(w, np.float64), np.asarray(bound)
        off_surface = np.asarray(jp.closest_points(index, p).distance) > 1e-4
        assert (np.abs(w - ref)[off_surface] <= bound[off_surface]).all()
        exact = np.asarray(jp.winding_number(index, p, mode="exact"), np.float64)
        np.testing.assert_allclose(exact[off_surface], ref[off_surface], atol=1e-5)


@pytest.mark.codegen
@pytest.mark.parametrize("name", ["sphere", "hemisphere", "overlapping", "thin"])
def test_signs_follow_the_exact_winding_number(name, request):
    mesh = request.getfixturevalue(name)
    index = jp.mesh_index(mesh, capacity=CAP)
    p = _points(mesh, seed=3)
    q = jp.query_points(index, p)
    ref = reference.winding_number(mesh.vertices, mesh.faces, p)
    d = reference.mesh_distance(mesh.vertices, mesh.faces, p)
    clear = (np.abs(ref - 0.5) >= 0.05) & (d > 1e-4)
    inside = np.asarray(q.inside)
    assert (inside[clear] == (ref[clear] > 0.5)).all()
    sd = np.asarray(q.signed_distance)
    assert ((sd < 0) == inside)[d > 1e-6].all()
    uncertain = np.asarray(q.status) == jp.PointStatus.UNCERTAIN
    assert (uncertain == (np.abs(np.asarray(q.winding) - 0.5) < 0.01)).all()
    assert (np.asarray(jp.occupancy(index, p)) == inside)[d > 1e-4].all()  # on the surface: either side


def test_pseudonormal_sign_is_exact_on_a_closed_mesh(sphere, hemisphere, overlapping):
    index = jp.mesh_index(sphere, capacity=CAP)
    assert bool(index.closed)
    assert not bool(jp.mesh_index(hemisphere).closed) and not bool(jp.mesh_index(overlapping).closed)
    p = _points(sphere, seed=4)
    d = reference.mesh_distance(sphere.vertices, sphere.faces, p)
    ref = reference.winding_number(sphere.vertices, sphere.faces, p) > 0.5
    q = jp.query_points(index, p, sign="pseudonormal")
    assert (np.asarray(q.inside) == ref)[d > 1e-6].all()
    assert np.isnan(np.asarray(q.winding)).all()


def test_nan_points_empty_inputs_and_bad_input(sphere):
    index = jp.mesh_index(sphere, capacity=CAP)
    p = _points(sphere)
    p[3] = np.nan
    p[7, 1] = np.inf
    q = jp.query_points(index, p)
    status = np.asarray(q.status)
    assert status[3] == status[7] == jp.PointStatus.INVALID
    assert np.isnan(np.asarray(q.signed_distance)[[3, 7]]).all()
    assert np.isfinite(np.delete(np.asarray(q.signed_distance), [3, 7])).all()
    assert np.asarray(q.closest.triangle)[3] == -1
    empty = jp.signed_distance(index, np.zeros((0, 3)))
    assert empty.shape == (0,)
    assert jp.closest_points(index, np.zeros((2, 0, 3))).point.shape == (2, 0, 3)
    with pytest.raises(jv.JaxvoxError, match="points"):
        jp.signed_distance(index, np.zeros((4, 2)))
    with pytest.raises(jv.JaxvoxError, match="no faces"):
        jp.mesh_index(jv.Mesh(np.zeros((3, 3)), np.zeros((0, 3), np.int32)))
    with pytest.raises(jv.JaxvoxError, match="sign"):
        jp.signed_distance(index, p, sign="parity")
    with pytest.raises(jv.JaxvoxError, match="capacity"):
        jp.mesh_index(sphere, capacity=10)


def test_batch_axes_jit_and_vmap(sphere, hemisphere):
    a, b = jp.mesh_index(sphere, capacity=CAP), jp.mesh_index(hemisphere, capacity=CAP)
    p = _points(sphere, seed=5)
    eager = np.asarray(jp.signed_distance(a, p, sign="pseudonormal"))
    batched = jp.signed_distance(a, p.reshape(2, N // 2, 3), sign="pseudonormal")
    np.testing.assert_array_equal(np.asarray(batched).reshape(-1), eager)
    jitted = jax.jit(lambda i, x: jp.signed_distance(i, x, sign="pseudonormal"))(a, jnp.asarray(p))
    np.testing.assert_allclose(np.asarray(jitted), eager, atol=1e-6)
    both = jp.stack_indices([a, b])
    mapped = jax.vmap(lambda i: jp.closest_points(i, jnp.asarray(p)).distance)(both)
    np.testing.assert_allclose(np.asarray(mapped[1]), np.asarray(jp.closest_points(b, p).distance), atol=1e-6)
    np.testing.assert_allclose(np.asarray(mapped[0]), np.abs(eager), atol=1e-6)


def test_gradients_against_finite_differences(hemisphere):
    index = jp.mesh_index(hemisphere, capacity=CAP)
    rng = np.random.default_rng(6)
    p = rng.uniform(-1.2, 1.2, (N, 3)).astype(np.float32)
    f = lambda x: jp.signed_distance(index, x, sign="pseudonormal")
    g = np.asarray(jax.grad(lambda x: f(x).sum())(jnp.asarray(p)))
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-4)
    eps = 1e-3
    for k in range(3):
        step = np.zeros(3, np.float32)
        step[k] = eps
        fd = (np.asarray(f(p + step)) - np.asarray(f(p - step))) / (2 * eps)
        smooth = np.abs(fd - g[:, k]) < 0.05  # away from the medial axis and sign changes
        assert smooth.mean() > 0.95
    # on the surface, at vertices and on edges: finite, unit gradients
    v, fc = np.asarray(hemisphere.vertices), np.asarray(hemisphere.faces)
    surface = np.concatenate([v[fc[:100, 0]], (v[fc[:100, 0]] + v[fc[:100, 1]]) / 2, v[fc[:100]].mean(1)])
    surface = np.concatenate([surface, surface[: N - len(surface)]])
    gs = np.asarray(jax.grad(lambda x: f(x).sum())(jnp.asarray(surface)))
    assert np.isfinite(gs).all()
    np.testing.assert_allclose(np.linalg.norm(gs, axis=1), 1.0, atol=1e-4)


def test_gradient_with_respect_to_vertices(sphere):
    index = jp.mesh_index(sphere, capacity=CAP)
    p = (_points(sphere, seed=7)[256:] * 1.3).astype(np.float32)
    p = np.concatenate([p, p])[:N]
    loss = lambda verts: jp.signed_distance(dataclasses.replace(index, vertices=verts), p, sign="pseudonormal").sum()
    v0 = index.vertices
    g = np.asarray(jax.grad(loss)(v0))
    rng = np.random.default_rng(8)
    for _ in range(3):
        direction = np.zeros(v0.shape, np.float32)
        direction[: sphere.num_vertices] = rng.normal(size=(sphere.num_vertices, 3))
        eps = 1e-3
        fd = (float(loss(v0 + eps * direction)) - float(loss(v0 - eps * direction))) / (2 * eps)
        assert abs(fd - float((g * direction).sum())) < 0.02 * max(1.0, abs(fd))


def test_lost_blocks_are_retried_on_the_host_and_reported_inside_jit(sphere):
    index = jp.mesh_index(sphere, capacity=CAP)
    p = _points(sphere, seed=9)
    good = np.asarray(jp.closest_points(index, p).distance)
    nb = -(-N // jp.search.BLOCK)
    key = ("closest", index.capacity, nb)
    saved = queries._PLANS[key]
    try:
        queries._PLANS[key] = tuple(16 for _ in saved)  # far too small
        inside_jit = jax.jit(lambda i, x: jp.closest_points(i, x).status)(index, jnp.asarray(p))
        assert (np.asarray(inside_jit) == jp.PointStatus.LOST).any()
        again = jp.closest_points(index, p)  # concrete: grows the plan and runs again
        np.testing.assert_array_equal(np.asarray(again.distance), good)
        assert all(c > 16 for c in queries._PLANS[key])
    finally:
        queries._PLANS[key] = saved


def test_the_first_plan_holds_a_thousand_points_on_the_bunny(meshes_dir, monkeypatch):
    """The first plan (`queries.FIRST_PAIRS`, `queries.FIRST_ROWS`) holds what both
    searches need for a thousand points on the bunny (69 K faces), spread over its box or
    near its surface: one run and one program each, no retry (the defaults alone had
    every search here run twice)."""
    mesh = jv.load_mesh(meshes_dir / "stanford-bunny.obj")
    index = jp.mesh_index(mesh)
    v = np.asarray(mesh.vertices)
    rng = np.random.default_rng(11)
    spread = rng.uniform(v.min(0), v.max(0), (1000, 3))
    near = v[rng.integers(0, len(v), 1000)] + rng.normal(0, 0.01 * np.ptp(v, 0).max(), (1000, 3))
    program, runs = queries._program, []

    def counted(body, index, points, **static):
        out = program(body, index, points, **static)
        runs.append((body.__name__, bool(np.asarray(out[1]).any())))
        return out

    monkeypatch.setattr(queries, "_program", counted)
    monkeypatch.setattr(queries, "_PLANS", {})
    for p in (spread, near):
        queries._PLANS.clear()
        runs.clear()
        jp.closest_points(index, p.astype(np.float32))
        jp.winding_number(index, p.astype(np.float32))
        assert runs == [("_closest_body", False), ("_winding_body", False)], runs


def test_grown_scales_what_lies_below_an_overflowed_level():
    """A pair level that overflowed by r passed on only 1/r of its pairs, so the needs
    below it (deeper pairs, rows of its depth and deeper) grow by r as well; the levels
    above it, and what had room, keep their capacities. Never smaller than before."""
    caps = (8192, 8192, 8192, 1024, 256)  # pairs at depths 0..3 (leaves first), then the leaf rows
    needs = (22936, 32520, 4352, 768, 470)  # depths 1 and 0 overflowed, by 3.97 and 2.8
    grown = jp.search.grown(caps, needs, (0,))
    over1, over0 = 32520 / 8192, 22936 / 8192
    assert grown[1] == 65536  # no overflow above it: its own need and a quarter, on the ladder
    assert grown[0] >= 22936 * over1 * 1.25 > 22936 * 1.25 * 2  # scaled by the overflow above it
    assert grown[4] >= 470 * over1 * over0 * 1.25  # the leaf rows: by both
    assert grown[2:4] == caps[2:4]
    assert grown == jp.search.grown(grown, (0, 0, 0, 0, 0), (0,))  # nothing needed: unchanged
    # the winding search's layout: far rows per depth (0..4), then the leaf rows
    caps = (512,) * 4 + (256,) * 6
    needs = (100, 2048, 100, 100) + (100,) * 6
    grown = jp.search.grown(caps, needs, (0, 1, 2, 3, 4, 0))
    assert grown[0] >= 100 * 4 and grown[1] >= 2048 and grown[2:4] == (512, 512)  # depth 1 overflowed 4x
    assert grown[4] >= 400 and grown[5] >= 400 and grown[6:9] == (256, 256, 256) and grown[9] >= 400


def test_a_second_mesh_of_the_same_bucket_compiles_nothing(sphere, hemisphere):
    # the first mesh open too (the hemisphere mirrored), so that it needs winding numbers
    mirrored = jv.Mesh(np.asarray(hemisphere.vertices) * [1, 1, -1], np.asarray(hemisphere.faces)[:, ::-1])
    a, b = jp.mesh_index(mirrored, capacity=CAP), jp.mesh_index(hemisphere, capacity=CAP)
    jax.block_until_ready(jp.query_points(a, _points(mirrored)))
    compiles = []
    listener = lambda name, *_, **__: (
        compiles.append(name) if name == "/jax/core/compile/backend_compile_duration" else None
    )
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        jax.block_until_ready(jp.query_points(b, _points(hemisphere)))
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert len(compiles) <= 2  # small host-side conversions at most; no search program


@settings(max_examples=15, deadline=None)
@given(
    st.lists(st.floats(-1, 1, width=32), min_size=27, max_size=27),
    st.integers(0, 2**31 - 1),
)
# a needle that the points' leaves read as inside at distance 0 (`triangle_rows`)
@example(coords=[0.5, *[0.0] * 7, 1e-12, *[0.0] * 15, 1.0, 0.0, 0.0], seed=0)
def test_random_triangles_hypothesis(coords, seed):
    v = np.asarray(coords, np.float32).reshape(9, 3)
    f = np.arange(9, dtype=np.int32).reshape(3, 3)
    mesh = jv.Mesh(v, f)
    rng = np.random.default_rng(seed)
    p = np.concatenate([rng.uniform(-1.5, 1.5, (N - 9, 3)), v]).astype(np.float32)
    result = jp.closest_points(jp.mesh_index(mesh, capacity=64), p)
    d = reference.mesh_distance(v, f, p)
    np.testing.assert_allclose(np.asarray(result.distance), d, atol=2e-6 * max(1.0, float(np.abs(v).max())))


def test_sample_sdf_is_deterministic_and_consistent(hemisphere):
    s = jp_sample(hemisphere, 0)
    again = jp_sample(hemisphere, 0)
    other = jp_sample(hemisphere, 1)
    np.testing.assert_array_equal(np.asarray(s.points), np.asarray(again.points))
    assert not np.array_equal(np.asarray(s.points), np.asarray(other.points))
    assert np.bincount(np.asarray(s.kind)).tolist() == [205, 205, 102]
    q = jp.query_points(jp.mesh_index(hemisphere, capacity=CAP), np.asarray(s.points))
    np.testing.assert_array_equal(np.asarray(q.signed_distance), np.asarray(s.sdf))
    np.testing.assert_array_equal(np.asarray(q.inside), np.asarray(s.occupancy))
    with pytest.raises(jv.JaxvoxError, match="fractions"):
        jv.sample_sdf(hemisphere, 10, jax.random.PRNGKey(0), fractions=(0.5, 0.6, 0.1))


def jp_sample(mesh, seed):
    return jv.sample_sdf(mesh, N, jax.random.PRNGKey(seed), index=jp.mesh_index(mesh, capacity=CAP))


def test_jaxvox_sample_command_skips_bad_meshes_and_resumes(tmp_path, sphere):
    from jaxvox.cli import main

    src = tmp_path / "meshes"
    src.mkdir()
    jv.save_mesh(str(src / "sphere.obj"), sphere)
    moved = jv.Mesh(np.asarray(sphere.vertices) * 2 + 1, sphere.faces)  # same face bucket: same programs
    jv.save_mesh(str(src / "half.obj"), moved)
    (src / "broken.obj").write_text("this is not a mesh\n")
    (src / "nan.obj").write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    out = tmp_path / "out"
    assert main(["sample", str(src), "--out", str(out), "--samples", str(N)]) == 1  # two skipped
    files = sorted(os.listdir(out))
    assert files == ["half.npz", "sphere.npz"]
    data = np.load(out / "sphere.npz")
    assert set(data.files) == {"points", "sdf", "occupancy", "status", "kind", "seed"}
    assert data["points"].shape == (N, 3) and data["sdf"].dtype == np.float32
    first = (out / "sphere.npz").stat().st_mtime_ns
    (out / "half.npz").unlink()  # as if interrupted before this mesh
    assert main(["sample", str(src), "--out", str(out), "--samples", str(N)]) == 1
    assert (out / "sphere.npz").stat().st_mtime_ns == first  # not redone
    again = np.load(out / "half.npz")
    assert again["points"].shape == (N, 3)
    assert not any(name.endswith(".partial.npz") for name in os.listdir(out))


def _half_sphere_query(path) -> None:
    """Queries 2 * SPLIT_MIN + 5 points around an open icosphere; saves signed distances,
    closest triangles and winding numbers to `path` (.npz)."""
    tm = trimesh.creation.icosphere(subdivisions=2)
    keep = tm.triangles_center[:, 2] > -0.3
    mesh = jv.Mesh(np.asarray(tm.vertices, np.float32), np.asarray(tm.faces[keep], np.int32))
    index = jp.mesh_index(mesh, capacity=512)
    p = np.random.default_rng(0).uniform(-1.3, 1.3, (2 * jp.queries.SPLIT_MIN + 5, 3)).astype(np.float32)
    q = jp.query_points(index, p)
    np.savez(path, sd=np.asarray(q.signed_distance), tri=np.asarray(q.closest.triangle), w=np.asarray(q.winding))


def test_split_over_two_devices_matches_one(tmp_path, monkeypatch):
    """A concrete query with two JAX devices (one program, half the points on each) gives
    the one-device answer (this process's): the same closest triangles and signed
    distances; the fast winding numbers (blocks differ, so their far fields do) within
    their error. SPLIT_MIN is lowered to 1024 in both processes: the same split at a
    sixteenth of the points."""
    import subprocess
    import sys

    code = (
        "import sys, jax; jax.config.update('jax_num_cpu_devices', 2)\n"
        "import jaxvox; jaxvox.enable_compilation_cache()\n"  # the suite's $JAXVOX_CACHE_DIR: warm runs compile nothing
        "from jaxvox.points import queries; queries.SPLIT_MIN = 1024\n"
        "from tests.test_points import _half_sphere_query; _half_sphere_query(sys.argv[1])"
    )
    root = pathlib.Path(__file__).resolve().parents[1]
    subprocess.run([sys.executable, "-c", code, str(tmp_path / "2.npz")], check=True, cwd=root)
    assert jax.device_count() == 1
    monkeypatch.setattr(jp.queries, "SPLIT_MIN", 1024)
    _half_sphere_query(tmp_path / "1.npz")
    one, two = np.load(tmp_path / "1.npz"), np.load(tmp_path / "2.npz")
    for key in ("sd", "tri"):
        np.testing.assert_array_equal(one[key], two[key])
    np.testing.assert_allclose(one["w"], two["w"], atol=0.02)
