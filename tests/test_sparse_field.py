"""Sparse narrow-band distance fields against the float64 references of tests/reference.py.

Every band voxel's value is within `TOL` voxel of the float64 point-mesh distance, signed by
the float64 winding number (inside where > 1/2; either sign within `TIE` of 1/2); the band
is complete (every voxel centre within ``band - TOL`` voxels of the surface is present,
none beyond ``band + TOL``).
"""

from __future__ import annotations

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

import jaxvox as jv
from jaxvox import morton
from jaxvox._core.shapes import bucket
from jaxvox.distance import band_sign
from jaxvox.distance.band_sign import (
    CAP_BOUND,
    MOVE,
    Components,
    nested_shells,
    pseudo_normals,
    pseudonormal_sides_exact,
)
from jaxvox.distance.sparse import SLOTS, TILE, UNUSED_VALUE
from jaxvox.distance.topology import boundary_chain, welded_faces
from jaxvox.distance.winding import point_tree
from tests.reference import mesh_distance, winding_number

TOL = 1e-4  # voxels
TIE = 1e-9  # float64 winding numbers this close to 1/2 accept either sign
COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
_compiles: list[float] = []
jax.monitoring.register_event_duration_secs_listener(
    lambda name, secs, **kw: _compiles.append(secs) if name == COMPILE_EVENT else None
)
R = 32


def icosphere(subdivisions=2, radius=0.6, shift=0.5) -> jv.Mesh:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return jv.Mesh(np.asarray(s.vertices, np.float32) + np.float32(shift), np.asarray(s.faces, np.int32))


def box() -> jv.Mesh:
    import trimesh

    b = trimesh.creation.box(extents=(0.7, 0.5, 0.33))
    return jv.Mesh(np.asarray(b.vertices, np.float32) + np.float32(0.5), np.asarray(b.faces, np.int32))


def centres(grid: jv.Grid, ijk) -> np.ndarray:
    return (np.asarray(ijk, np.float64) + 0.5) * float(grid.voxel_size) + np.asarray(grid.origin, np.float64)


def check_field(mesh: jv.Mesh, grid: jv.Grid, field: jv.SparseField, *, signed=True):
    """Values, signs and completeness against the float64 references (see the module docstring)."""
    h = float(grid.voxel_size)
    n = int(field.count)
    ijk = np.asarray(field.voxels.coords[:n])
    values = np.asarray(field.values)
    assert np.all(values[n:] == UNUSED_VALUE)
    p = centres(grid, ijk)
    # The float64 distances of every candidate centre (below), computed once: each band
    # centre lies within band * h of the surface, so within band * h + (longest edge) of a
    # vertex, and is a candidate.
    v = np.asarray(mesh.vertices, np.float64)
    tri = v[np.asarray(mesh.faces)]
    longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1).max(initial=0.0)
    all_ijk = np.indices((grid.resolution,) * 3).reshape(3, -1).T  # C order: flat index ascending
    near, _ = cKDTree(v).query(centres(grid, all_ijk), distance_upper_bound=field.band * h + longest + h)
    flat = np.flatnonzero(np.isfinite(near))
    cand = all_ijk[flat]
    dc = mesh_distance(mesh.vertices, mesh.faces, centres(grid, cand))
    key = np.ravel_multi_index(tuple(ijk.T.astype(np.int64)), (grid.resolution,) * 3)
    rows = np.searchsorted(flat, key)
    found = rows < len(flat)
    found[found] = flat[rows[found]] == key[found]
    d = np.empty(n)
    d[found] = dc[rows[found]]
    if not found.all():  # not expected (see above); computed directly so the checks stay exact
        d[~found] = mesh_distance(mesh.vertices, mesh.faces, p[~found])
    tie = np.zeros(n, bool)
    if signed:
        w = winding_number(mesh.vertices, mesh.faces, p)
        d = np.where(w > 0.5, -d, d)
        # A winding number of 1/2 up to float64 rounding (a centre in the plane of a planar
        # hole, within it) has no side: either sign passes there.
        tie = np.abs(w - 0.5) < TIE
    error = np.where(tie, np.abs(np.abs(values[:n]) - np.abs(d)), np.abs(values[:n] - d))
    assert np.max(error, initial=0.0) / h < TOL
    assert np.all(np.abs(d) <= (field.band + TOL) * h)
    # Completeness: every centre within band - TOL of the surface is present. Centres
    # farther than band * h + (longest edge) from every vertex cannot qualify.
    must = cand[dc <= (field.band - TOL) * h]
    got = set(map(tuple, ijk.tolist()))
    missing = [t for t in map(tuple, must.tolist()) if t not in got]
    assert not missing, missing[:5]
    # Morton order, unique, and the tree finds every voxel at its index.
    assert np.array_equal(np.asarray(jv.voxel_index(field.tree, ijk)), np.arange(n))


@pytest.mark.codegen
@pytest.mark.parametrize("make", [icosphere, box], ids=["icosphere", "box"])
def test_primitives(make):
    mesh = make()
    grid = jv.Grid.fit(mesh, R, padding=0.15)
    field = jv.sparse_distance_field(mesh, grid, band=3)
    assert int(field.count) > 0
    check_field(mesh, grid, field)


# Every test mesh (tests/data) and its R (the bunny's 70 K faces: the float64 references take 39 s at 16^3)
TEST_MESHES = {
    "beetle": 16,
    "cow": 16,
    "fandisk": 16,
    "spot": 16,
    "stanford-bunny": 8,
    "suzanne": 16,
    "teapot": 16,
    "woody": 32,
}


@pytest.mark.parametrize("name, resolution", TEST_MESHES.items())
def test_every_test_mesh(meshes_dir, name, resolution):
    """Every test mesh (tests/data) against the float64 reference: values, signs (winding numbers),
    completeness. Watertight ones are signed by pseudo-normals (spot), the others by
    winding numbers of components (woody, the bunny: open edges; teapot, cow: crossing
    triangles). (16^3 or less: the float64 references loop over points.)"""
    mesh = jv.load_mesh(meshes_dir / f"{name}.obj")
    grid = jv.Grid.fit(mesh, resolution, padding=0.1)
    field = jv.sparse_distance_field(mesh, grid, band=2)
    check_field(mesh, grid, field)


def test_components_signed_by_the_fast_tree(meshes_dir, monkeypatch):
    """The components' winding numbers come from a brute-force sum when they are few (the
    test meshes' grids here) and from the fast tree otherwise (`band_sign.TREE_PAIRS`):
    with the tree forced, the field is the brute-force one (which `test_every_test_mesh`
    checks against the float64 references, on the same grid)."""
    mesh = jv.load_mesh(meshes_dir / "teapot.obj")  # crossing triangles: signed by components
    grid = jv.Grid.fit(mesh, TEST_MESHES["teapot"], padding=0.1)
    summed = jv.sparse_distance_field(mesh, grid, band=2)
    trees = []
    monkeypatch.setattr(band_sign, "TREE_PAIRS", 0)
    monkeypatch.setattr(band_sign, "point_tree", lambda tris: trees.append(len(tris)) or point_tree(tris))
    field = jv.sparse_distance_field(mesh, grid, band=2)
    assert trees == [mesh.num_faces]  # built once, for the components
    np.testing.assert_array_equal(np.asarray(field.values), np.asarray(summed.values))


def test_open_meshes_signed_by_winding_numbers():
    """A single quad (its winding number stays below 1/2: all positive) and a sphere with
    its top cut off (inside where the winding number exceeds 1/2)."""
    v = np.array([[0.2, 0.2, 0.5], [0.8, 0.2, 0.5], [0.8, 0.8, 0.5], [0.2, 0.8, 0.5]], np.float32)
    quad = jv.Mesh(v, np.array([[0, 1, 2], [0, 2, 3]], np.int32))
    grid = jv.Grid(np.zeros(3), 1 / 16, 16)
    signed = jv.sparse_distance_field(quad, grid, band=2)
    check_field(quad, grid, signed)
    assert (np.asarray(signed.values[: int(signed.count)]) > 0).all()
    unsigned = jv.sparse_distance_field(quad, grid, band=2, signed=False)
    check_field(quad, grid, unsigned, signed=False)
    assert np.array_equal(np.abs(np.asarray(signed.values)), np.asarray(unsigned.values))
    sphere = icosphere(2, 0.4)
    tri = np.asarray(sphere.triangles())
    cut = jv.Mesh(sphere.vertices, np.asarray(sphere.faces)[tri[:, :, 2].mean(1) < 0.8])
    assert jv.open_edges(cut) > 0
    field = jv.sparse_distance_field(cut, grid, band=2)
    check_field(cut, grid, field)
    assert (np.asarray(field.values[: int(field.count)]) < 0).any()
    _check_memory(field)


def _check_memory(field):
    """`SparseField.memory` accounts for every byte of the pytree, part by part."""
    memory = field.memory()
    capacity = field.voxels.capacity
    assert memory["coords"] == 12 * capacity and memory["values"] == 4 * capacity
    assert memory["triangles"] == 4 * capacity  # the closest triangle per slot
    assert memory["topology"] == field.tree.nbytes > 0
    leaves = jax.tree_util.tree_leaves(field)
    assert memory["total"] == sum(x.nbytes for x in leaves)
    assert 0 <= memory["other"] < 1024  # counts, flags, the grid
    assert memory["per_voxel"] == memory["total"] / int(field.count) >= 20  # coords + value + triangle


def test_large_triangles_are_tiled():
    """Two triangles whose dilated boxes span many tiles (`TILE` voxels): every tile takes
    the minimum of both."""
    v = np.array([[0.02, 0.03, 0.1], [0.97, 0.05, 0.4], [0.95, 0.96, 0.9], [0.04, 0.94, 0.6]], np.float32)
    quad = jv.Mesh(v, np.array([[0, 1, 2], [0, 2, 3]], np.int32))
    grid = jv.Grid(np.zeros(3), 1 / 64, 64)
    assert 64 > 8 * TILE
    field = jv.sparse_distance_field(quad, grid, band=1, signed=False)
    check_field(quad, grid, field, signed=False)


def test_crowded_tiles_and_closest_triangles():
    """Many more triangles over one tile than a work unit holds (`SLOTS`): the units'
    minima are merged, and each voxel's triangle is at its distance."""
    rng = np.random.default_rng(3)
    count = 20 * SLOTS
    v = (0.45 + 0.1 * rng.random((count * 3, 3))).astype(np.float32)
    soup = jv.Mesh(v, np.arange(count * 3, dtype=np.int32).reshape(-1, 3))
    grid = jv.Grid(np.zeros(3), 1 / 16, 16)
    field = jv.sparse_distance_field(soup, grid, band=2)
    check_field(soup, grid, field)
    n = int(field.count)
    tri = np.asarray(field.voxels.triangle[:n])
    p = centres(grid, np.asarray(field.voxels.coords[:n]))
    own = np.array([mesh_distance(v, np.asarray(soup.faces)[t : t + 1], q[None])[0] for t, q in zip(tri, p)])
    np.testing.assert_allclose(own, np.abs(np.asarray(field.values[:n])), atol=1e-4 / 16)


def test_sample_at_centres_and_gradient():
    mesh = icosphere(3, 0.6)
    grid = jv.Grid.fit(mesh, R, padding=0.15)
    field = jv.sparse_distance_field(mesh, grid, band=3)
    n = int(field.count)
    p = centres(grid, field.voxels.coords[:n]).astype(np.float32)
    values, _ = jv.sample(field, p)
    h = float(grid.voxel_size)
    assert np.max(np.abs(np.asarray(values) - np.asarray(field.values[:n]))) / h < 1e-4
    # Under jit and vmap, the same.
    jitted, _ = jax.jit(jv.sample)(field, p[:64])
    mapped, _ = jax.vmap(jv.sample, in_axes=(None, 0))(field, p[:64])
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(values[:64]), atol=1e-6)
    np.testing.assert_allclose(np.asarray(mapped), np.asarray(values[:64]), atol=1e-6)
    # Gradient vs central differences at points well inside the band (off voxel planes).
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(20, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = (0.5 + dirs * (0.6 + rng.uniform(-1, 1, (20, 1)) * h)).astype(np.float32)
    _, inside = jv.sample(field, pts)
    assert np.asarray(inside).all()
    f = lambda x: jv.sample(field, x)[0]
    grad = np.asarray(jax.vmap(jax.grad(f))(jnp.asarray(pts)))
    eps = 1e-3 * h
    fd = np.stack(
        [
            (np.asarray(f(pts + eps * e)) - np.asarray(f(pts - eps * e))) / (2 * eps)
            for e in np.eye(3, dtype=np.float32)
        ],
        -1,
    )
    np.testing.assert_allclose(grad, fd, atol=2e-2)
    # The gradient of a distance field is about a unit normal, outward.
    assert np.all(np.abs(np.linalg.norm(grad, axis=1) - 1) < 0.1)
    assert np.all(np.sum(grad * dirs, 1) > 0.9)


def test_sample_outside_band_is_clamped():
    mesh = icosphere()
    grid = jv.Grid.fit(mesh, R, padding=0.15)
    field = jv.sparse_distance_field(mesh, grid, band=2)
    far = 2 * float(grid.voxel_size)
    h = float(grid.voxel_size)
    # The sphere's centre and a far point have no neighbour in the band: +band * h. A point
    # 2.6 voxels inside the surface has some neighbours (negative) and some missing: those
    # take -band * h.
    points = np.array([[0.5, 0.5, 0.5], [5.0, 5.0, 5.0], [0.5, 0.5, 1.1], [0.5, 0.5, 1.1 - 2.6 * h]], np.float32)
    values, inside = jv.sample(field, points)
    np.testing.assert_allclose(np.asarray(values)[:2], [far, far], rtol=1e-6)
    assert np.asarray(inside).tolist() == [False, False, True, False]
    assert -far <= float(values[3]) < -h


def test_edge_cases():
    grid = jv.Grid(np.zeros(3), 1 / 16, 16)
    empty = jv.sparse_distance_field(jv.Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32)), grid)
    assert int(empty.count) == 0
    values, inside = jv.sample(empty, np.array([0.5, 0.5, 0.5], np.float32))
    assert float(values) == pytest.approx(3 / 16) and not bool(inside)
    mesh = icosphere(1, 0.3)
    zero = jv.sparse_distance_field(mesh, grid, band=0)
    assert int(zero.count) <= 8
    with pytest.raises(jv.JaxvoxError, match="sparse_distance_field band: must be at least 0, got -1"):
        jv.sparse_distance_field(mesh, grid, band=-1)
    with pytest.raises(jv.JaxvoxError, match="band: must be an integer"):
        jv.sparse_distance_field(mesh, grid, band=1.5)
    with pytest.raises(jv.JaxvoxError, match="signed: must be True or False"):
        jv.sparse_distance_field(mesh, grid, signed="yes")
    with pytest.raises(jv.JaxvoxError, match="grid: expected a jaxvox.Grid"):
        jv.sparse_distance_field(mesh, None)
    with pytest.raises(jv.JaxvoxError, match="sample points: must have shape"):
        jv.sample(zero, np.zeros((4, 2)))
    with pytest.raises(jv.JaxvoxError, match="sample field"):
        jv.sample(grid, np.zeros((4, 3)))


@pytest.mark.parametrize("tiny", [1e-44, 1e-40, 1e-38, 1e-30])
def test_an_edge_too_short_for_float32_loses_no_voxel(tiny):
    """A triangle with an edge of `tiny` world units at the grid's origin (voxel edge 1/2:
    1e-44 is float32's subnormal range): every band voxel, with its float64 distance and
    sign. The edge's inverse squared length was inf in the tile kernel's rows, the
    distance of a cell square to the edge NaN, and the field lost those voxels (it kept
    none of the 20 at 1e-44 and 1e-40, 12 at 1e-38)."""
    mesh = jv.Mesh(np.array([[0, 0, 0], [tiny, 0, 0], [0.5, 1, 0.25]], np.float32), np.array([[0, 1, 2]], np.int32))
    grid = jv.Grid(np.zeros(3), 0.5, 4)
    check_field(mesh, grid, jv.sparse_distance_field(mesh, grid, band=2))


def _turned(vertices: np.ndarray, faces: list) -> jv.Mesh:
    """A mesh of vertices [V, 3] turned off the axes (0.2 rad about x, then 0.3 about z)
    and moved by 0.1."""
    c, s, c2, s2 = np.cos(0.3), np.sin(0.3), np.cos(0.2), np.sin(0.2)
    turn = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, c2, -s2], [0, s2, c2]])
    return jv.Mesh((vertices @ turn.T + 0.1).astype(np.float32), np.array(faces, np.int32))


def wedge(theta: float) -> jv.Mesh:
    """A closed triangular prism whose cross-section is a wedge of angle `theta` (a knife
    edge 0.6 deep, 0.8 long), turned off the axes."""
    h = 0.6 * np.tan(theta / 2)
    section = [(0.0, 0.0), (0.6, -h), (0.6, h)]
    v = np.array([(x, y, z) for z in (0.0, 0.8) for x, y in section])
    return _turned(v, [[0, 2, 1], [3, 4, 5], [0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [2, 0, 3], [2, 3, 5]])


def slab(thickness: float) -> jv.Mesh:
    """A closed box 0.8 x 0.8 x `thickness` (12 triangles), turned off the axes."""
    corners = np.array([(x, y, z) for x in (0.0, 0.8) for y in (0.0, 0.8) for z in (0.0, thickness)])
    faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1]]
    faces += [[2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return _turned(corners, faces)


def flat_tetrahedron() -> jv.Mesh:
    """A tetrahedron with an edge of 1e-10: its two faces off that edge fold onto each other."""
    v = np.array([[0, 0, 0], [1e-10, 0, 0], [0.5, 1, 0.25], [0.3, 0.4, 1.1]], np.float32)
    return jv.Mesh(v, np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]], np.int32))


@pytest.mark.parametrize(
    "make, grid_of, band, pseudo",
    [
        (lambda: wedge(1e-1), lambda mesh: jv.Grid.fit(mesh, resolution=64), 3, True),
        (lambda: wedge(1e-6), lambda mesh: jv.Grid.fit(mesh, resolution=64), 3, False),
        (lambda: slab(1e-6), lambda mesh: jv.Grid.fit(mesh, resolution=64), 3, False),
        (flat_tetrahedron, lambda mesh: jv.Grid(np.zeros(3), 0.5, 4), 2, False),
    ],
    ids=["wedge-1e-1", "wedge-1e-6", "slab-1e-6", "flat-tetrahedron"],
)
def test_thin_sheets_are_signed_by_winding_numbers(make, grid_of, band, pseudo):
    """Closed meshes where two sheets of the surface come closer than the float32 kernel's
    rounding, so that it cannot tell which is closer and the two face opposite ways: a
    wedge of 1e-6 rad (a fold), a slab 1e-6 thick (its sides are slivers), a tetrahedron
    with an edge of 1e-10 (a fold). They are signed by winding numbers; pseudo-normals put
    59 of 20,646, 4 of 18,046 and 2 of 34 band voxels on the wrong side. A wedge of 0.1
    rad keeps pseudo-normals. Every voxel, value and sign against float64."""
    mesh = make()
    assert pseudonormal_sides_exact(mesh.vertices, mesh.faces) == pseudo
    grid = grid_of(mesh)
    check_field(mesh, grid, jv.sparse_distance_field(mesh, grid, band=band))


def test_pseudo_normals_of_a_box():
    mesh = box()
    normals = pseudo_normals(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    # A box corner's angle-weighted normal points along the diagonal.
    corner = normals[:, 4:].reshape(-1, 3)
    unit = corner / np.linalg.norm(corner, axis=1, keepdims=True)
    assert np.allclose(np.abs(unit), 1 / np.sqrt(3), atol=1e-6)


def test_new_mesh_compiles_nothing():
    """A second mesh in the same face bucket runs the compiled programs, its field's
    sampling too: a smaller sphere, with half the band voxels, whose field's buffers
    take the band's floor (`band_bucket`) rather than their own power of two."""
    grid = jv.Grid(np.zeros(3), 1 / 16, 16)
    points = np.random.default_rng(0).uniform(0, 1, (100, 3)).astype(np.float32)
    first = jv.sparse_distance_field(icosphere(1, 0.3), grid, band=2)
    jax.block_until_ready(jv.sample(first, points))
    before = len(_compiles)
    second = jv.sparse_distance_field(icosphere(1, 0.2, 0.49), grid, band=2)
    jax.block_until_ready(jv.sample(second, points))
    assert len(_compiles) == before
    assert bucket(int(second.count)) < bucket(int(first.count))  # (their own buckets differ)


@pytest.mark.parametrize("name", ["teapot", "cow"])
def test_crossing_triangles_are_signed_by_winding_numbers(meshes_dir, name):
    """The teapot (open, its handle and spout cross its body) and the cow (watertight, but
    triangles cross: pseudo-normals gave 55 wrong signs at 64^3) against the float64
    winding number at every band voxel (32^3)."""
    mesh = jv.load_mesh(meshes_dir / f"{name}.obj")
    grid = jv.Grid.fit(mesh, 32)
    field = jv.sparse_distance_field(mesh, grid, band=3)
    n = int(field.count)
    w = winding_number(mesh.vertices, mesh.faces, centres(grid, np.asarray(field.voxels.coords[:n])))
    assert np.array_equal(np.asarray(field.values[:n]) < 0, w > 0.5)


def damaged_mesh(seed: int, resolution: int) -> jv.Mesh:
    """One or two (crossing) spheres, maybe a tetrahedron pinched onto one at a vertex,
    vertices maybe snapped to voxel planes and centres, maybe cut (on a voxel plane half
    the time), some faces maybe flipped or removed at random."""
    import trimesh

    rng = np.random.default_rng(seed)
    verts, faces = [], []

    def add(v, f):
        faces.append(np.asarray(f) + sum(len(x) for x in verts))
        verts.append(np.asarray(v, np.float64))

    for _ in range(rng.integers(1, 3)):
        s = trimesh.creation.icosphere(subdivisions=int(rng.integers(1, 3)), radius=rng.uniform(0.12, 0.3))
        add(s.vertices + rng.uniform(0.35, 0.65, 3), s.faces)
    if rng.random() < 0.3:
        apex = verts[0][0]
        add(np.concatenate([[apex], apex + rng.normal(0, 0.1, (3, 3))]), [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    v, f = np.concatenate(verts), np.concatenate(faces)
    if rng.random() < 0.4:
        v = np.round(v * 2 * resolution) / (2 * resolution)
    if rng.random() < 0.7:
        axis, cut = rng.integers(3), rng.uniform(0.4, 0.6)
        if rng.random() < 0.5:
            cut = np.round(cut * resolution) / resolution
        f = f[v[f].mean(1)[:, axis] < cut]
    if rng.random() < 0.3:
        flip = rng.random(len(f)) < 0.05
        f[flip] = f[flip][:, ::-1]
    if rng.random() < 0.2:
        f = f[rng.random(len(f)) > 0.1]
    return jv.Mesh(v.astype(np.float32), f.astype(np.int32))


@settings(max_examples=5, deadline=None)
@given(st.integers(0, 2**32 - 1))
@example(seed=16711705)  # a sphere inside another: pseudo-normals had 91 wrong signs between them
def test_signs_of_damaged_meshes(seed):
    """Holes (cut on voxel planes or not), crossing or nested spheres, pinched vertices,
    flipped faces: values and signs against the float64 winding number (`check_field`)."""
    mesh = damaged_mesh(seed, 16)
    grid = jv.Grid(np.zeros(3), 1 / 16, 16)
    region = (None, 4)[seed % 2]  # half the examples in regions of 4^3, each signed alone
    check_field(mesh, grid, jv.sparse_distance_field(mesh, grid, band=2, region=region))


def test_nested_shells_are_signed_by_winding_numbers():
    """Closed shells that do not cross: apart, pseudo-normals sign them; a sphere inside
    another of the same orientation (winding number 2 inside both, 1 between them) or
    inverted (a hollow ball: 0 in the cavity) takes winding numbers (`nested_shells`)."""
    outer, inner, apart = icosphere(2, 0.35), icosphere(2, 0.15), icosphere(1, 0.1, shift=0.1)

    def union(*parts, flip=()):
        faces = [np.asarray(p.faces)[:, ::-1] if i in flip else np.asarray(p.faces) for i, p in enumerate(parts)]
        offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
        v = np.concatenate([np.asarray(p.vertices) for p in parts])
        return jv.Mesh(v, np.concatenate([f + o for f, o in zip(faces, offsets)]).astype(np.int32))

    grid = jv.Grid(np.zeros(3), 1 / 16, 16)
    for mesh, nested in [
        (union(outer, apart), False),
        (union(outer, inner), True),
        (union(outer, inner, flip=(1,)), True),
    ]:
        tris = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)]
        assert nested_shells(tris, welded_faces(mesh.vertices, mesh.faces)) == nested
        check_field(mesh, grid, jv.sparse_distance_field(mesh, grid, band=2))


def test_cap_blocks_settle_only_where_the_bound_holds():
    """A sphere with a hole: voxels whose cap term needs only a bound are settled by
    4^3 and 2^3 blocks (`Components.blocked_cap_terms`). Every voxel of a settled block
    must have |w_caps| < CAP_BOUND by the float64 winding number of the caps; the others
    get the exact term. Both kinds occur. The distances are lower bounds, exact up to
    `MOVE`."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    faces = s.faces[s.vertices[s.faces].mean(1)[:, 2] < 12.0]  # a hole of radius about 15
    tris = s.vertices[faces] + 32.0  # grid units, the centre at (32, 32, 32)
    welded = welded_faces(s.vertices, faces)
    components = Components(tris, welded, np.zeros(len(faces), bool), boundary_chain(welded), band=3)
    ijk = np.indices((64, 64, 64)).reshape(3, -1).T
    ijk = ijk[np.abs(np.linalg.norm(ijk + 0.5 - 32.0, axis=1) - 20.0) < 8.0]  # a shell about the sphere
    keys = morton.encode_host(ijk)
    order = np.argsort(keys)
    ijk, keys = ijk[order].astype(np.int32), keys[order]
    got, gap = components.blocked_cap_terms(ijk, keys, np.zeros(len(ijk)))
    caps = components.caps
    exact = winding_number(caps.reshape(-1, 3), np.arange(3 * len(caps)).reshape(-1, 3), ijk + 0.5)
    distance = mesh_distance(caps.reshape(-1, 3), np.arange(3 * len(caps)).reshape(-1, 3), ijk + 0.5)
    assert np.all(gap <= distance + 1e-4)
    near = gap <= MOVE
    assert near.sum() > 100
    np.testing.assert_allclose(gap[near], distance[near], atol=1e-4)
    settled = got == 0
    assert 0.1 < settled.mean() < 0.99
    assert np.abs(exact[settled]).max() < CAP_BOUND
    # the others: the exact term (float32 kernel), away from the caps' own surface
    off = ~settled & (np.abs(np.abs(exact) - 0.5) > 0.05)
    assert off.sum() > 100
    np.testing.assert_allclose(got[off], exact[off], atol=1e-4)


@pytest.mark.parametrize("name, resolution", [("cow", 32), ("teapot", 64), ("spot", 32)])
def test_regions_change_nothing(meshes_dir, name, resolution, monkeypatch):
    """Built in 8 regions (each region's voxels distanced, signed on its own and merged
    into the DAG alone), the field equals the one built whole, and its tree is
    `build_dag` of its voxels (the canonical DAG). Where the system refuses to reserve
    the field's buffers, the regions are joined instead: the same field, padding
    included. The cow (closed, with crossing triangles) and the teapot (open) are signed
    by winding numbers of components, spot (watertight, no crossings) by pseudo-normal
    sides."""
    mesh = jv.load_mesh(meshes_dir / f"{name}.obj")
    assert pseudonormal_sides_exact(np.asarray(mesh.vertices), np.asarray(mesh.faces)) == (name == "spot")
    grid = jv.Grid.fit(mesh, resolution)
    region = resolution // 2
    whole = jv.sparse_distance_field(mesh, grid, band=3)
    parts = jv.sparse_distance_field(mesh, grid, band=3, region=region)
    n = int(whole.count)
    assert int(parts.count) == n > 0
    assert np.array_equal(np.asarray(parts.voxels.coords), np.asarray(whole.voxels.coords))
    a, b = np.asarray(parts.values[:n]), np.asarray(whole.values[:n])
    assert np.array_equal(a < 0, b < 0)
    assert np.max(np.abs(a - b)) / float(grid.voxel_size) < 1e-6
    dag = jv.build_dag(whole.voxels)
    for name in ("mask", "child", "prefix", "level_count", "voxel_count"):
        assert np.array_equal(np.asarray(getattr(parts.tree, name)), np.asarray(getattr(dag, name))), name
    for field in (whole, parts):
        assert np.array_equal(np.asarray(jv.voxel_index(field.tree, np.asarray(field.voxels.coords[:n]))), np.arange(n))
    with monkeypatch.context() as patch:
        patch.setattr(importlib.import_module("jaxvox.distance.sparse"), "reserved_empty", lambda shape, dtype: None)
        joined = jv.sparse_distance_field(mesh, grid, band=3, region=region)
    for got, want in zip(jax.tree.leaves(joined), jax.tree.leaves(parts)):
        assert np.array_equal(np.asarray(got), np.asarray(want))
    # Handed out region by region: the same voxels and values, each region's tree its own.
    regions = list(jv.sparse_field_regions(mesh, grid, band=3, region=region))
    assert len(regions) >= 6
    counts = [int(r.count) for r in regions]
    join = lambda get: np.concatenate([np.asarray(get(r))[:c] for r, c in zip(regions, counts)])
    assert np.array_equal(join(lambda r: r.voxels.coords), np.asarray(whole.voxels.coords[:n]))
    assert np.array_equal(join(lambda r: r.values), a)
    assert np.array_equal(join(lambda r: r.voxels.triangle), np.asarray(parts.voxels.triangle[:n]))
    last = regions[-1]
    ijk = np.asarray(last.voxels.coords[: counts[-1]])
    assert np.array_equal(np.asarray(jv.voxel_index(last.tree, ijk)), np.arange(counts[-1]))
    assert int(jv.voxel_index(last.tree, np.asarray(whole.voxels.coords[0]))) == -1


def test_compact_field_is_the_field_without_its_coordinates(monkeypatch):
    """``compact=True`` keeps the values and the tree only: the same values, the same
    voxels out of the tree, the same samples and mesh; built whole, in regions, joined
    (no reserved buffers) or handed out region by region; its memory is the values'
    capacity and the DAG's tables, every byte accounted for."""
    sphere = icosphere(2, 0.4)
    tri = np.asarray(sphere.triangles())
    cut = jv.Mesh(sphere.vertices, np.asarray(sphere.faces)[tri[:, :, 2].mean(1) < 0.8])  # open: winding signs
    grid = jv.Grid(np.zeros(3), 1 / 16, 16)
    full = jv.sparse_distance_field(cut, grid, band=2)
    n = int(full.count)
    points = np.random.default_rng(3).uniform(-0.6, 0.6, (500, 3)).astype(np.float32)
    with monkeypatch.context() as patch:
        patch.setattr(importlib.import_module("jaxvox.distance.sparse"), "reserved_empty", lambda shape, dtype: None)
        joined = jv.sparse_distance_field(cut, grid, band=2, region=8, compact=True)
    for field in (jv.sparse_distance_field(cut, grid, band=2, compact=True), joined):
        assert field.voxels is None and int(field.count) == n > 0
        np.testing.assert_array_equal(np.asarray(field.values), np.asarray(full.values))
        np.testing.assert_array_equal(np.asarray(field.voxel_coords()), np.asarray(full.voxels.coords[:n]))
        for got, want in zip(jv.sample(field, points), jv.sample(full, points)):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
        faces = [np.asarray(jv.field_to_mesh(f).faces) for f in (field, full)]
        np.testing.assert_array_equal(*faces)
        memory = field.memory()
        assert memory["coords"] == memory["triangles"] == 0
        assert memory["values"] == 4 * field.values.shape[0] and memory["topology"] == field.tree.nbytes
        assert memory["total"] == sum(x.nbytes for x in jax.tree_util.tree_leaves(field)) < full.memory()["total"]
        assert memory["per_voxel"] == memory["total"] / n
    whole = list(jv.sparse_field_regions(cut, grid, band=2, region=8))
    parts = list(jv.sparse_field_regions(cut, grid, band=2, region=8, compact=True))
    assert len(parts) == len(whole) > 1
    for part, want in zip(parts, whole):
        assert part.voxels is None
        np.testing.assert_array_equal(np.asarray(part.voxel_coords()), np.asarray(want.voxel_coords()))
        np.testing.assert_array_equal(np.asarray(part.values), np.asarray(want.values))
    with pytest.raises(jv.JaxvoxError, match="sparse_distance_field compact: must be True or False"):
        jv.sparse_distance_field(cut, grid, compact="yes")


def test_bad_region():
    mesh = icosphere(1, 0.3)
    grid = jv.Grid(np.zeros(3), 1 / 16, 16)
    with pytest.raises(jv.JaxvoxError, match="sparse_distance_field region: must be a power of two"):
        jv.sparse_distance_field(mesh, grid, region=12)


@pytest.mark.parametrize("closed", [True, False], ids=["closed", "open"])
def test_large_tilted_triangles_far_from_the_origin(closed):
    """A tilted slab of 200-voxel triangles near voxel (3000, 3000, 3000) of a 4096^3 grid,
    closed (pseudo-normal signs) and with two faces removed (winding-number signs). In
    float32 at that size and place, distances were off by up to 2e-4 voxel and voxels
    within 1e-4 voxel of a face took the wrong sign; now values and signs match the
    float64 references."""
    import trimesh

    slab = trimesh.creation.box(extents=(200, 200, 16))
    slab.apply_transform(trimesh.transformations.rotation_matrix(0.37, [1, 0.6, 0.2]))
    h = 1 / 4096
    faces = np.asarray(slab.faces, np.int32)
    mesh = jv.Mesh(((slab.vertices + 3000.3) * h).astype(np.float32), faces if closed else faces[2:])
    grid = jv.Grid(np.zeros(3), h, 4096)
    field = jv.sparse_distance_field(mesh, grid, band=2)
    n = int(field.count)
    p = centres(grid, np.asarray(field.voxels.coords[:n]))
    d = mesh_distance(mesh.vertices, mesh.faces, p)
    inside = winding_number(mesh.vertices, mesh.faces, p) > 0.5
    values = np.asarray(field.values[:n], np.float64)
    assert np.sort(d)[0] / h < 1e-5  # voxels this close to a face are what the test is about
    assert np.array_equal(values < 0, inside)
    assert np.max(np.abs(np.abs(values) - d)) / h < TOL
