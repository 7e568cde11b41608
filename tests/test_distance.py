"""Distance fields and 16-bit storage against float64 and scipy references.

Error bounds per method (voxel units, on the closed spot mesh at 32^3, measured there
as jfa 0.22, jfa-separable 0.38, sweep 1.28 / -0.53, jfa+sweep 0.97 / -0.43):

* "exact": within 2e-4 voxel of the float64 brute force (float32 rounding);
* "jfa", "jfa-separable": distances to real triangles, so never below the exact
  distance; above it by at most 0.5 and 0.75 voxel;
* "sweep", "jfa+sweep" (first-order eikonal): at most 1.75 and 1.5 voxels above, and
  0.75 and 0.6 below (the upwind update undershoots along ridges of the field).

Against scipy's EDT of the conservative surface voxels ``e`` the exact distance ``d``
obeys ``|d - e| <= sqrt(3)/2`` (each is within half a voxel diagonal of the other's
witness), so every method must stay within that plus its own bound. On point sites at
voxel centres the exact field *is* the EDT.
"""

from __future__ import annotations

import math
import os

import hypothesis
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

import jaxvox as jv
from jaxvox.distance.field import box_distance, box_grid
from jaxvox.distance.solid import grid_triangles, padded_mesh, solid_inside
from jaxvox.distance.sweep import fast_sweep
from tests.reference import mesh_distance, ray_parity

BOUNDS = {  # method: (max above exact, max below exact), voxels
    "exact": (2e-4, 2e-4),
    "jfa": (0.5, 2e-4),
    "jfa-separable": (0.75, 2e-4),
    "sweep": (1.75, 0.75),
    "jfa+sweep": (1.5, 0.6),
}
# Sweeping from a few isolated seeds (a lone triangle, geometry outside the grid, which
# enters through the voxels of its triangles' clamped centroids and corners) is first-order
# from point sources: measured up to 2.8 voxels above at 16^3, 3.0 in a clipmap window.
ISOLATED_SWEEP_BOUND = 3.25
OUTSIDE_JFA_BOUND = 2.5  # jump flooding from geometry outside the grid (see its test)
HALF_DIAGONAL = math.sqrt(3) / 2
SLOW = os.environ.get("JAXVOX_SLOW_SCALE", "").strip().lower()


def voxel_centres(grid) -> np.ndarray:
    r = grid.resolution
    ijk = np.indices((r, r, r)).reshape(3, -1).T
    return (ijk + 0.5) * float(grid.voxel_size) + np.asarray(grid.origin, np.float64)


def icosphere(subdivisions=1, radius=1.0, shift=(0.0, 0.0, 0.0)) -> jv.Mesh:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return jv.Mesh(np.asarray(s.vertices, np.float32) + np.float32(shift), np.asarray(s.faces, np.int32))


@pytest.fixture(scope="module")
def spot(meshes_dir):
    """Spot at 32^3 and its exact unsigned distances at the voxel centres [32, 32, 32]
    float32 (world units), from `jaxvox.points.closest_points` (an exact search of its
    own, checked against float64 in tests/test_points.py): the brute-force field
    (``method="exact"``) at 32^3 took most of this module's time with the suite's
    compiler flags, and it is checked against float64 below at 16^3."""
    mesh = jv.load_mesh(meshes_dir / "spot.obj")
    grid = jv.Grid.fit(mesh, resolution=32, padding=0.1)
    closest = jv.points.closest_points(mesh, voxel_centres(grid).astype(np.float32))
    assert (np.asarray(closest.status) == jv.points.PointStatus.OK).all()
    return mesh, grid, np.asarray(closest.distance).reshape((32,) * 3)


@pytest.mark.codegen
def test_exact_matches_float64_on_hard_cases():
    """Brute force against the float64 reference: a closed sphere, an open fan with a
    degenerate (zero-area) triangle and a point, and a mesh half outside the grid."""
    sphere = icosphere(1, 0.6, (0.5, 0.5, 0.5))
    v = np.array([[0.2, 0.2, 0.5], [0.8, 0.3, 0.5], [0.4, 0.9, 0.6], [0.6, 0.6, 0.6], [0.3, 0.3, 0.3]], np.float32)
    fan = jv.Mesh(v, np.array([[0, 1, 2], [1, 3, 3], [4, 4, 4]], np.int32))  # triangle, segment, point
    outside = icosphere(0, 0.5, (1.6, 0.5, -0.4))  # mostly outside the unit box
    grid = jv.Grid(origin=(0.0, 0.0, 0.0), voxel_size=1 / 16, resolution=16)
    points = voxel_centres(grid)
    for mesh in (sphere, fan, outside):
        ref = mesh_distance(mesh.vertices, mesh.faces, points).reshape((16,) * 3)
        got = np.asarray(jv.distance_field(mesh, grid, method="exact", signed=False))
        np.testing.assert_allclose(got * 16, ref * 16, atol=BOUNDS["exact"][0])
        for method in ("jfa", "jfa+sweep"):  # geometry outside the grid still seeds the field
            got = np.asarray(jv.distance_field(mesh, grid, method=method, signed=False))
            err = (got - ref) * 16
            above = ISOLATED_SWEEP_BOUND if method == "jfa+sweep" else BOUNDS[method][0]
            assert err.max() <= above and err.min() >= -BOUNDS[method][1], (method, err.min(), err.max())


def _check_rows_dist2(rows, tris, p):
    """`rows_dist2` of `triangle_rows` rows at points p [n, 3] (grid units) is the float64
    distance to triangles tris [n, 3, 3], within 1e-4."""
    from jaxvox._core.geometry import rows_dist2
    from tests.reference import closest_point_on_triangles

    zero = (jnp.float32(0),) * 3
    d2 = jax.jit(rows_dist2)(tuple(jnp.asarray(p[:, k], jnp.float32) for k in range(3)), tuple(rows), zero)
    ref = np.linalg.norm(p - closest_point_on_triangles(p, tris[:, 0], tris[:, 1], tris[:, 2]), axis=1)
    np.testing.assert_allclose(np.sqrt(np.asarray(d2)), ref, atol=1e-4)


def test_triangle_rows_of_slivers():
    """`triangle_rows` of slivers (nonzero area, third vertex within 1e-9..1e-6 grid units
    of the first edge's line): finite, no RuntimeWarning, and `rows_dist2` equals the
    float64 closest-point distance. The dual basis once divided by |ab|^2 |ac|^2 -
    (ab . ac)^2, which cancels to 0 for such triangles."""
    import warnings

    from jaxvox._core.geometry import triangle_rows

    rng = np.random.default_rng(1)
    a, ab = rng.uniform(0, 16, (2000, 3)), rng.uniform(-8, 8, (2000, 3))
    off = rng.uniform(-1, 1, (2000, 3)) * 10.0 ** rng.uniform(-9, -6, (2000, 1))
    tris = np.stack([a, a + ab, a + ab * rng.uniform(0.05, 0.95, (2000, 1)) + off], 1)
    assert (np.linalg.norm(np.cross(tris[:, 1] - a, tris[:, 2] - a), axis=1) > 0).all()
    p = rng.uniform(-2, 18, (2000, 3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rows = triangle_rows(tris)
    assert np.isfinite(rows).all()
    _check_rows_dist2(rows, tris, p)


def test_triangle_rows_of_edges_too_short_for_float32():
    """Triangles with an edge of 1e-30..1e-20 grid units near the origin (nonzero in
    float64; its inverse squared length, and for the thinnest the dual basis, beyond
    float32) and points square to that edge, at its ends included: finite rows, and
    `rows_dist2` equals the float64 distance. The inverse was inf, and such a point's
    projection onto the edge 0 * inf = NaN: a sparse field lost those voxels."""
    from jaxvox._core.geometry import triangle_rows

    rng = np.random.default_rng(3)
    n = 600
    axis = rng.integers(0, 3, n)
    tiny = np.zeros((n, 3))
    tiny[np.arange(n), axis] = 10.0 ** rng.uniform(-30, -20, n) * rng.choice([-1.0, 1.0], n)
    a = np.zeros((n, 3))
    c = rng.integers(-4, 5, (n, 3)).astype(np.float64)
    tris = np.stack([a, a + tiny, c], 1)
    tris = np.where(rng.random((n, 1, 1)) < 0.5, tris, tris[:, [1, 2, 0]])  # the short edge as ab or bc
    square = rng.uniform(-3, 3, (n, 3))
    square[np.arange(n), axis] = 0.0  # x . edge = 0 from either end
    p = np.where(rng.random((n, 1)) < 0.2, 0.0, square)
    rows = triangle_rows(tris)
    assert np.isfinite(rows).all()
    _check_rows_dist2(rows, tris, p)


def test_triangle_rows_of_needles():
    """Needles along the grid's axes (integer corners, a short edge bc across the needle,
    1e-13..1e-9 of its length) and points on the needle's line beyond either end. Found by
    hypothesis (`test_points.py`): with ab . ac = |ab|^2 and |ac|^2 = |ab|^2 in float64,
    the dual basis by dot products lost its component along the needle, and such a point
    read as inside at distance 0. `rows_dist2` equals the float64 distance."""
    from jaxvox._core.geometry import triangle_rows

    rng = np.random.default_rng(2)
    n = 2000
    axis = rng.integers(0, 3, n)
    across = (axis + rng.integers(1, 3, n)) % 3
    length = rng.integers(1, 9, n) * rng.choice([-1.0, 1.0], n)
    a = rng.integers(0, 16, (n, 3)).astype(np.float64)
    ab = np.zeros((n, 3))
    ab[np.arange(n), axis] = length
    off = np.zeros((n, 3))
    off[np.arange(n), across] = np.abs(length) * 10.0 ** rng.uniform(-13, -9, n)
    tris = np.stack([a, a + ab, a + ab + off], 1)
    assert (np.linalg.norm(np.cross(tris[:, 1] - a, tris[:, 2] - a), axis=1) > 0).all()
    beyond = np.where(rng.random((n, 1)) < 0.5, -rng.uniform(0.05, 1, (n, 1)), 1 + rng.uniform(0.05, 1, (n, 1)))
    p = a + ab * beyond
    _check_rows_dist2(triangle_rows(tris), tris, p)


@hypothesis.settings(deadline=None, max_examples=25)
@hypothesis.given(st.lists(st.tuples(*[st.floats(-1e6, 1e6)] * 9), max_size=20), st.integers(0, 2))
def test_corner_helpers_are_numpys_reductions(corners, repeat):
    """`corner_bounds`, `centroids` and `farthest_corners` (the sparse field's host
    geometry) give numpy's reductions over the corner axis bit for bit, equal corners
    (segments, points) included."""
    from jaxvox._core.geometry import centroids, corner_bounds, farthest_corners

    tris = np.array(corners, np.float64).reshape(-1, 3, 3)
    if repeat:  # a corner repeated: a segment, or with equal corners a point
        tris[:, 2] = tris[:, repeat - 1]
    lo, hi = corner_bounds(tris)
    c = centroids(tris)
    np.testing.assert_array_equal(lo, tris.min(1))
    np.testing.assert_array_equal(hi, tris.max(1))
    np.testing.assert_array_equal(c, tris.mean(1))
    radius = np.linalg.norm(tris - c[:, None], axis=-1).max(1)
    np.testing.assert_array_equal(farthest_corners(tris, c), radius)


@pytest.mark.parametrize("method", list(BOUNDS))
def test_point_sites_are_the_edt(method):
    """Zero-area triangles at voxel centres: the exact field is scipy's EDT of those voxels."""
    r = 16
    rng = np.random.default_rng(3)
    sites = rng.integers(0, r, size=(12, 3))
    v = (sites + 0.5).astype(np.float32)
    mesh = jv.Mesh(v, np.repeat(np.arange(len(v), dtype=np.int32)[:, None], 3, axis=1))
    grid = jv.Grid(origin=(0.0, 0.0, 0.0), voxel_size=1.0, resolution=r)
    occupied = np.ones((r, r, r), bool)
    occupied[tuple(sites.T)] = False
    edt = ndimage.distance_transform_edt(occupied)
    got = np.asarray(jv.distance_field(mesh, grid, method=method, signed=False))
    above, below = BOUNDS[method]
    assert (got - edt).max() <= above and (got - edt).min() >= -below
    if method == "exact":
        np.testing.assert_allclose(got, edt, atol=1e-5)


@pytest.mark.parametrize("method", [m for m in BOUNDS if m != "exact"])
def test_methods_on_spot_within_bounds(spot, method):
    mesh, grid, exact = spot
    h = float(grid.voxel_size)
    got = np.asarray(jv.distance_field(mesh, grid, method=method, signed=False))
    err = (got - exact) / h
    above, below = BOUNDS[method]
    assert err.max() <= above and err.min() >= -below, (err.min(), err.max())
    # scipy's EDT of the conservative surface voxels, in voxels
    surface = np.ones((32,) * 3, bool)
    surface[tuple(jv.voxelize(mesh, grid).to_numpy().T)] = False
    edt = ndimage.distance_transform_edt(surface)
    assert np.abs(exact / h - edt).max() <= HALF_DIAGONAL + 1e-4
    assert np.abs(got / h - edt).max() <= HALF_DIAGONAL + above


def test_exact_against_float64_on_spot_sample(spot):
    """The brute-force field (spot at 16^3) and the module's reference (32^3, closest
    points) against the float64 distance at 300 voxel centres each."""
    mesh, grid, exact = spot
    small = jv.Grid.fit(mesh, resolution=16, padding=0.1)
    brute = np.asarray(jv.distance_field(mesh, small, method="exact", signed=False))
    for field, g in ((brute, small), (exact, grid)):
        idx = np.random.default_rng(0).choice(field.size, 300, replace=False)
        ref = mesh_distance(mesh.vertices, mesh.faces, voxel_centres(g)[idx])
        h = float(g.voxel_size)
        np.testing.assert_allclose(field.reshape(-1)[idx] / h, ref / h, atol=BOUNDS["exact"][0])


def test_more_band_and_sweeps_options(spot):
    """The band and the number of sweeps are honoured: a wide band is exact near the
    surface, and one sweep already fills the grid."""
    mesh, grid, exact = spot
    h = float(grid.voxel_size)
    wide = np.asarray(jv.distance_field(mesh, grid, method="sweep", band=3, sweeps=1, signed=False))
    assert np.isfinite(wide).all()
    near = exact / h < 1.0
    assert np.abs(wide - exact)[near].max() / h <= BOUNDS["jfa-separable"][0]
    # "band": the narrow band alone, +-inf beyond it
    band = np.asarray(jv.distance_field(mesh, grid, method="band", band=3))
    finite = np.isfinite(band)
    assert finite[exact / h < 2.0].all() and not finite[exact / h > 3 * math.sqrt(3) + HALF_DIAGONAL].any()
    err = (np.abs(band) - exact) / h  # distances to real triangles: never below exact, and
    assert err[finite].min() >= -BOUNDS["jfa-separable"][1]  # within the bound well inside the band
    assert err[exact / h < 2.0].max() <= BOUNDS["jfa-separable"][0]
    signed = np.asarray(jv.distance_field(mesh, grid, method="jfa"))
    np.testing.assert_array_equal(np.sign(band), np.sign(signed))


def test_bad_input_and_memory_limit():
    mesh = icosphere(0)
    grid = jv.Grid(origin=(-1.0, -1.0, -1.0), voxel_size=0.25, resolution=8)
    bad = jv.Mesh(np.asarray(mesh.vertices).copy(), mesh.faces)
    bad = jv.Mesh(np.where(np.arange(len(bad.vertices))[:, None] == 2, np.nan, bad.vertices), bad.faces)
    with pytest.raises(jv.JaxvoxError, match="NaN"):
        jv.distance_field(bad, grid)
    with pytest.raises(jv.JaxvoxError, match="method"):
        jv.distance_field(mesh, grid, method="fmm")
    with pytest.raises(jv.JaxvoxError, match="band"):
        jv.distance_field(mesh, grid, band=-1)
    with pytest.raises(jv.JaxvoxError, match="sweeps"):
        jv.distance_field(mesh, grid, sweeps=0)
    with pytest.raises(jv.JaxvoxError, match="sign"):
        jv.distance_field(mesh, grid, sign="normals")
    with pytest.raises(jv.JaxvoxError, match="GiB"):
        jv.distance_field(mesh, grid, max_bytes=1000)
    with pytest.raises(jv.JaxvoxError, match="power of two"):
        jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=12)
    big = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=1 << 14)
    with pytest.raises(jv.JaxvoxError, match="max_bytes"):
        jv.distance_field(mesh, big)  # 2^42 voxels: refused before anything is allocated
    assert jv.distance_field_bytes(512, method="jfa+sweep") > 4 * 512**3
    empty = jv.Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    field = np.asarray(jv.distance_field(empty, grid))
    assert field.shape == (8, 8, 8) and np.isposinf(field).all()


@pytest.mark.parametrize("fmt", jv.distance.FORMATS)
def test_quantized_field_error(spot, fmt):
    mesh, grid, exact = spot
    q = jax.jit(lambda f: jv.quantize_field(f, grid, format=fmt))(jnp.asarray(exact))
    assert q.values.dtype == (jnp.float16 if fmt == "float16" else jnp.int16)
    err = np.abs(np.asarray(q.decode()) - exact) / float(grid.voxel_size)
    voxels = np.abs(exact) / float(grid.voxel_size)
    bound = voxels * 2.0**-11 if fmt == "float16" else np.full_like(voxels, 0.5 / 256 + 1e-6)
    assert (err <= bound + 1e-6).all()


def _triangles_jfa_error(corners) -> np.ndarray:
    """JFA minus the float64 distance at the voxel centres of an 8^3 unit grid, in voxels."""
    v = np.array(corners, np.float32).reshape(-1, 3)
    mesh = jv.Mesh(v, np.arange(len(v), dtype=np.int32).reshape(-1, 3))
    grid = jv.Grid(origin=(0.0, 0.0, 0.0), voxel_size=1 / 8, resolution=8)
    ref = mesh_distance(v, np.asarray(mesh.faces), voxel_centres(grid)).reshape((8,) * 3) * 8
    return np.asarray(jv.distance_field(mesh, grid, method="jfa", signed=False)) * 8 - ref


@hypothesis.settings(deadline=None, max_examples=6)
@hypothesis.given(st.lists(st.tuples(*[st.floats(0.0, 1.0, width=32)] * 9), min_size=1, max_size=4))
@hypothesis.example([(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)])  # two equal corners: a segment
@hypothesis.example([(0.5, 0.5, 0.5) * 3])  # a point
def test_random_triangles_jfa_bounds(corners):
    """Random triangles in the grid (possibly degenerate): JFA never below the float64
    distance and within its bound above (measured: at most 0.03 voxel in 400 cases)."""
    err = _triangles_jfa_error(corners)
    assert err.min() >= -BOUNDS["jfa"][1] and err.max() <= BOUNDS["jfa"][0]


def test_triangles_outside_the_grid_jfa_bounds():
    """Triangles partly or wholly outside the grid reach it only through the voxels of
    their clamped corners and centroid, so a triangle whose nearest-region in the grid
    is cut off from those seeds is found late: never below the exact distance, and at
    most OUTSIDE_JFA_BOUND above (measured: 1.9 voxels worst in 300 random cases).
    A fixed sample, so the test is deterministic; it includes the case CI found."""
    rng = np.random.default_rng(7)
    cases = [[(0, 0, 0) * 3, (0, 0, 0) * 3, (0, 0, 0, 0, 0, 0, 0, 1, 1), (0, 0, 1, 1, 0, 1.25, 0, 0, 1)]]
    cases += [rng.choice([-0.25, 0.0, 0.5, 1.0, 1.25], size=(rng.integers(1, 5), 9)) for _ in range(12)]
    cases += [rng.uniform(-0.25, 1.25, size=(rng.integers(1, 5), 9)) for _ in range(12)]
    for corners in cases:
        err = _triangles_jfa_error(corners)
        assert err.min() >= -BOUNDS["jfa"][1] and err.max() <= OUTSIDE_JFA_BOUND, (corners, err.max())


@pytest.mark.slow
@pytest.mark.parametrize("method", ["jfa", "sweep", "jfa+sweep"])
def test_bunny_unsigned_bounds(meshes_dir, method):
    """The bunny (open, 69k triangles) against the float64 reference on a sample of voxels;
    64^3 with JAXVOX_SLOW_SCALE=full, 16^3 otherwise."""
    r = 64 if SLOW == "full" else 16
    mesh = jv.load_mesh(meshes_dir / "stanford-bunny.obj")
    grid = jv.Grid.fit(mesh, resolution=r, padding=0.1)
    got = np.asarray(jv.distance_field(mesh, grid, method=method, signed=False)).reshape(-1)
    idx = np.random.default_rng(2).choice(got.size, 60, replace=False)
    ref = mesh_distance(mesh.vertices, mesh.faces, voxel_centres(grid)[idx])
    err = (got[idx] - ref) / float(grid.voxel_size)
    above, below = BOUNDS[method]
    assert err.max() <= above and err.min() >= -below


@pytest.mark.parametrize("method", [m for m in BOUNDS if m != "sweep"] + ["band"])
def test_box_pipeline_on_a_non_cubic_box(method):
    """The pipeline on a box of 5 x 12 x 7 voxels (what a scissor volume runs on), with
    the mesh partly outside it: within the method's bounds of the float64 distance, and
    the parity and winding signs of the box equal the references at its centres."""
    mesh = icosphere(1, 0.5, (0.35, 0.3, 0.2))
    shape = (5, 12, 7)
    h = 0.1
    grid = box_grid((0.0, 0.0, 0.0), h, shape)
    points = (np.indices(shape).reshape(3, -1).T + 0.5) * h
    ref = mesh_distance(mesh.vertices, mesh.faces, points).reshape(shape) / h
    band = {"jfa+sweep": 1, "band": 12}.get(method, 0)  # 12 passes cover the box
    got = np.asarray(box_distance(mesh, grid, shape, method=method, band=band, sweeps=3))
    assert got.shape == shape
    above = ISOLATED_SWEEP_BOUND if "sweep" in method else OUTSIDE_JFA_BOUND if method != "exact" else 2e-4
    err = got - ref
    assert err.max() <= above and err.min() >= -BOUNDS.get(method, (0, 2e-4))[1], (err.min(), err.max())
    inside = ray_parity(mesh.vertices, mesh.faces, points).reshape(shape)
    tris = grid_triangles(padded_mesh(mesh), grid)
    for sign in ("parity", "winding"):
        solid = np.asarray(solid_inside(mesh, tris, grid, shape, sign, 2.0))
        np.testing.assert_array_equal(solid, inside)


def test_sweep_on_non_cubic_boxes_matches_a_cube():
    """Sweeping a box equals sweeping the same seeds inside a larger cube whose extra
    voxels are fixed at inf (no neighbour): the skewed layout handles any shape."""
    rng = np.random.default_rng(2)
    shape = (3, 6, 5)
    u = np.where(rng.random(shape) < 0.1, 3 * rng.random(shape), np.inf).astype(np.float32)
    got = np.asarray(fast_sweep(jnp.asarray(u), jnp.isinf(jnp.asarray(u)), 1))
    assert np.isfinite(got).all()
    cube = np.full((8, 8, 8), np.inf, np.float32)
    cube[:3, :6, :5] = u
    box = np.zeros((8, 8, 8), bool)
    box[:3, :6, :5] = True
    ref = np.asarray(fast_sweep(jnp.asarray(cube), jnp.asarray(np.isinf(cube) & box), 1))
    np.testing.assert_allclose(got, ref[:3, :6, :5], rtol=1e-6)  # compiled per shape: rounding may differ
