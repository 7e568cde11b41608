"""Octree and DAG: builds against independent numpy references, round trips, voxel index,
attributes, jit/vmap and overflow, file format."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxvox as jv
from jaxvox.mesh import validate_mesh
from tests.reference import morton_encode

MESHES = ["stanford-bunny", "spot", "teapot", "suzanne", "fandisk", "cow", "woody", "beetle"]
FULL = os.environ.get("JAXVOX_SLOW_SCALE") == "full"
BASE_RESOLUTION = 256 if FULL else 64  # voxelized once per mesh; coarser levels derived
SMALL = 16  # resolution of hypothesis-generated voxel sets


# ------------------------------------------------------------------ numpy references


def reference_svo_sizes(ijk: np.ndarray, depth: int) -> list[int]:
    """Nodes per level, root first: distinct Morton prefixes of the voxels."""
    codes = morton_encode(ijk)
    return [len(np.unique(codes >> np.uint64(3 * (depth - level)))) for level in range(depth)]


def reference_dag_sizes(ijk: np.ndarray, depth: int) -> list[int]:
    """Nodes per level, root first: distinct child rows, deduplicated bottom-up."""
    if len(ijk) == 0:
        return [0] * depth
    cells = np.unique(morton_encode(ijk))
    ids = None
    sizes = []
    for level in range(depth - 1, -1, -1):
        parents, inverse = np.unique(cells >> np.uint64(3), return_inverse=True)
        slot = (cells & np.uint64(7)).astype(np.int64)
        rows = np.full((len(parents), 8), -1, np.int64)
        rows[inverse, slot] = 1 if ids is None else ids  # bottom level: the row is the mask
        unique_rows, ids = np.unique(rows, axis=0, return_inverse=True)
        sizes.append(len(unique_rows))
        cells = parents
    return sizes[::-1]


def reference_expand(tree: jv.Octree) -> np.ndarray:
    """Voxels of a tree by a recursive walk over the host arrays (any order), sorted."""
    mask, child = np.asarray(tree.mask), np.asarray(tree.child)
    out = []

    def walk(node, level, ijk):
        for s in range(8):
            if not (mask[node] >> s) & 1:
                continue
            sub = 2 * ijk + np.array([s & 1, (s >> 1) & 1, (s >> 2) & 1])
            if level == tree.depth - 1:
                out.append(sub)
            else:
                walk(int(child[node, s]), level + 1, sub)

    if int(tree.voxel_count):
        walk(0, 0, np.zeros(3, np.int64))
    ijk = np.array(out, np.int64).reshape(-1, 3)
    return ijk[np.argsort(morton_encode(ijk), kind="stable")].astype(np.int32)


def _check_tree(tree: jv.Octree, ijk: np.ndarray) -> None:
    """Every property of a built tree against the references."""
    depth = tree.depth
    expected = (reference_dag_sizes if tree.dag else reference_svo_sizes)(ijk, depth)
    assert list(tree.level_sizes) == expected
    assert int(tree.voxel_count) == len(ijk) and int(tree.overflow) == 0
    np.testing.assert_array_equal(jv.expand(tree).to_numpy(), ijk)
    np.testing.assert_array_equal(reference_expand(tree), ijk)
    np.testing.assert_array_equal(np.asarray(jv.voxel_index(tree, ijk)), np.arange(len(ijk)))
    stored = [max(expected[0], 1)] + expected[1:]  # an empty tree keeps its root row
    assert jv.compact(tree).nbytes == tree.compact_nbytes == sum(stored) + 64 * sum(stored[:-1])
    # Host-built trees are padded to the shape ladder: power-of-two tables, at most twice
    # the rows or the resolution's floor of R^2 rows (`row_bucket`).
    n, m = tree.mask.shape[0], tree.child.shape[0]
    r = tree.grid.resolution
    inner, floor = sum(stored[:-1]), min(r**2, 1 << 18) if r <= 1024 else 256
    assert m & (m - 1) == 0 and m <= max(2 * inner - 1, floor) if inner else m == 0
    assert n & (n - 1) == 0 and n <= max(2 * (m + stored[-1]) - 1, floor)


def _sorted_voxels(ijk: np.ndarray) -> np.ndarray:
    ijk = np.unique(np.asarray(ijk, np.int32).reshape(-1, 3), axis=0)
    return ijk[np.argsort(morton_encode(ijk), kind="stable")]


# ------------------------------------------------------------------ real meshes


@pytest.fixture(scope="module")
def mesh_voxels(meshes_dir):
    cache = {}

    def get(name, resolution=BASE_RESOLUTION, mode=jv.CONSERVATIVE):
        key = (name, resolution, mode)
        if key not in cache:
            mesh = jv.load_mesh(meshes_dir / f"{name}.obj")
            cache[key] = mesh, jv.voxelize(mesh, jv.Grid.fit(mesh, resolution), mode=mode, triangle_ids=True)
        return cache[key]

    return get


def _coarsened(vox: jv.Voxels, shift: int) -> jv.Voxels:
    """The voxel set at resolution R / 2^shift: a coarse voxel is set when any of its
    children is (for a conservative voxelization, the conservative voxelization of the
    coarser grid with the same origin)."""
    grid = vox.grid
    coarse = jv.Grid(origin=grid.origin, voxel_size=grid.voxel_size * 2**shift, resolution=grid.resolution >> shift)
    return jv.Voxels.from_coords(vox.to_numpy() >> shift, coarse)


@pytest.mark.parametrize("name", MESHES if FULL else MESHES[:2] + ["fandisk", "cow"])
def test_meshes_round_trip_and_level_sizes(mesh_voxels, name):
    _, vox = mesh_voxels(name)
    for shift in (0, 2, 4) if FULL else (0, 2):
        sub = _coarsened(vox, shift)
        ijk = sub.to_numpy()
        assert len(ijk) > 0
        svo, dag = jv.build_octree(sub), jv.build_dag(sub)
        _check_tree(svo, ijk)
        _check_tree(dag, ijk)
        assert svo.level_sizes[0] == dag.level_sizes[0] == 1
        assert all(d <= s for d, s in zip(dag.level_sizes, svo.level_sizes))
        assert dag.level_sizes[-1] <= 255  # distinct non-zero masks


def test_six_separating_round_trip(mesh_voxels):
    _, vox = mesh_voxels("spot", mode=jv.SIX_SEPARATING)
    dag = jv.build_dag(vox)
    assert dag.mode == jv.SIX_SEPARATING
    _check_tree(dag, vox.to_numpy())


def test_attributes_survive_the_dag(mesh_voxels):
    mesh, vox = mesh_voxels("stanford-bunny")
    dag = jv.build_dag(vox)
    attrs = jv.voxel_attributes(mesh, vox)
    ijk = vox.to_numpy()
    idx = np.asarray(jv.voxel_index(dag, ijk))
    np.testing.assert_array_equal(np.asarray(attrs["triangle"])[idx], vox.triangle_ids())
    # normals are the unit normals of those triangles
    tri = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)[vox.triangle_ids()]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    np.testing.assert_allclose(np.asarray(attrs["normal"])[idx], n, atol=1e-5)
    assert "color" not in attrs  # OBJ without colours


def test_colour_attribute_interpolates_vertex_colours():
    mesh = jv.default_scene()
    vox = jv.voxelize(mesh, jv.Grid.fit(mesh, 32), triangle_ids=True)
    color = np.asarray(jv.voxel_attributes(mesh, vox)["color"])[: int(vox.count)]
    assert color.shape == (int(vox.count), 3)
    # a convex combination of the triangle's three vertex colours
    corners = np.asarray(mesh.colors)[np.asarray(mesh.faces)[vox.triangle_ids()]]
    assert (color >= corners.min(1) - 1e-5).all() and (color <= corners.max(1) + 1e-5).all()
    # a one-colour triangle gives exactly its colour
    flat = np.ptp(corners, axis=1).max(1) == 0
    assert flat.any()
    np.testing.assert_allclose(color[flat], corners[flat, 0], atol=1e-6)


def test_load_mesh_reads_vertex_colours(tmp_path):
    box = trimesh.creation.box()
    box.visual.vertex_colors = np.tile([255, 0, 0, 255], (len(box.vertices), 1)).astype(np.uint8)
    path = tmp_path / "box.ply"
    box.export(path)
    mesh = jv.load_mesh(path)
    np.testing.assert_allclose(np.asarray(mesh.colors), np.tile([1.0, 0, 0, 1.0], (len(box.vertices), 1)))
    with pytest.raises(jv.JaxvoxError, match="colors"):
        validate_mesh(jv.Mesh(mesh.vertices, mesh.faces, colors=np.zeros((3, 3))))


def _bilinear_reference(texture, uv):
    """float64 bilinear lookup with repeat wrap; v = 0 is the bottom row."""
    h, w = texture.shape[:2]
    x, y = uv[:, 0] * w - 0.5, (1.0 - uv[:, 1]) * h - 0.5
    out = np.zeros((len(uv), texture.shape[2]))
    for n in range(len(uv)):
        x0, y0 = int(np.floor(x[n])), int(np.floor(y[n]))
        for dy in (0, 1):
            for dx in (0, 1):
                weight = (1 - abs(x[n] - x0 - dx)) * (1 - abs(y[n] - y0 - dy))
                out[n] += weight * texture[(y0 + dy) % h, (x0 + dx) % w]
    return out


def test_sample_texture_is_bilinear_with_repeat():
    rng = np.random.default_rng(0)
    texture = rng.random((5, 7, 4)).astype(np.float32)
    uv = rng.uniform(-1.5, 2.5, size=(200, 2)).astype(np.float32)
    got = np.asarray(jax.jit(jv.sample_texture)(texture, uv))
    np.testing.assert_allclose(got, _bilinear_reference(texture.astype(np.float64), uv.astype(np.float64)), atol=1e-5)
    centres = np.array([[(0 + 0.5) / 7, 1 - (0 + 0.5) / 5], [(6 + 0.5) / 7, 1 - (4 + 0.5) / 5]], np.float32)
    np.testing.assert_allclose(np.asarray(jv.sample_texture(texture, centres)), texture[[0, 4], [0, 6]], atol=1e-6)


def test_load_mesh_reads_a_texture_and_voxels_sample_it(textured_quad):
    path, texels = textured_quad
    mesh = jv.load_mesh(path)
    assert mesh.texture.shape == (4, 4, 4) and mesh.uvs.shape == (mesh.num_vertices, 2)
    np.testing.assert_allclose(np.asarray(mesh.texture)[..., :3], texels, atol=1e-6)
    np.testing.assert_allclose(np.asarray(mesh.uvs), np.asarray(mesh.vertices)[:, :2])
    vox = jv.voxelize(mesh, jv.Grid.fit(mesh, resolution=16), triangle_ids=True)
    n = int(vox.count)
    colour = np.asarray(jv.voxel_attributes(mesh, vox)["color"])[:n, :3]
    # The plane point nearest a voxel centre is its (x, y) clipped to the quad, and uv = (x, y).
    xy = np.clip(
        np.asarray(vox.grid.origin)[:2] + (np.asarray(vox.coords)[:n, :2] + 0.5) * float(vox.grid.voxel_size), 0.0, 1.0
    )
    np.testing.assert_allclose(colour, _bilinear_reference(texels, xy), atol=1e-5)
    padded = jv.pad_mesh(mesh, mesh.num_vertices + 3, mesh.num_faces + 2)
    assert padded.texture.shape == mesh.texture.shape and padded.uvs.shape == (mesh.num_vertices + 3, 2)
    with pytest.raises(jv.JaxvoxError, match="both uvs"):
        validate_mesh(jv.Mesh(mesh.vertices, mesh.faces, uvs=mesh.uvs))
    with pytest.raises(jv.JaxvoxError, match="uvs: must have shape"):
        validate_mesh(jv.Mesh(mesh.vertices, mesh.faces, uvs=np.zeros((2, 2)), texture=mesh.texture))


# ------------------------------------------------------------------ hypothesis voxel sets


def _hand_made_sets():
    r = SMALL
    corners = [[x, y, z] for x in (0, r - 1) for y in (0, r - 1) for z in (0, r - 1)]
    block = [[x, y, z] for x in (2, 3) for y in (4, 5) for z in (6, 7)]
    cube = np.argwhere(np.ones((4, 4, 4), bool)) + 4
    return {
        "empty": np.zeros((0, 3)),
        "one": [[5, 9, 1]],
        "corners": corners,
        "block": block,
        "cube": cube,
        "full": np.argwhere(np.ones((r, r, r), bool)),
    }


@pytest.mark.parametrize("name", list(_hand_made_sets()))
@pytest.mark.parametrize("build", [jv.build_octree, jv.build_dag])
def test_hand_made_sets(name, build):
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=SMALL)
    ijk = _sorted_voxels(_hand_made_sets()[name])
    tree = build(jv.Voxels.from_coords(ijk, grid))
    _check_tree(tree, ijk)
    if name == "full":  # one node per level in the DAG: every subtree is the same
        assert tree.level_sizes == ((1, 1, 1, 1) if tree.dag else (1, 8, 64, 512))
    if name == "empty":
        assert tree.level_sizes == (0,) * 4
        assert (np.asarray(jv.voxel_index(tree, [[0, 0, 0], [3, 3, 3]])) == jv.MISSING).all()


voxel_sets = st.lists(st.tuples(*[st.integers(0, SMALL - 1)] * 3), min_size=0, max_size=300)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(voxel_sets, st.booleans())
def test_random_sets(points, dag):
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=SMALL)
    ijk = _sorted_voxels(np.array(points, np.int32).reshape(-1, 3))
    tree = (jv.build_dag if dag else jv.build_octree)(jv.Voxels.from_coords(ijk, grid))
    _check_tree(tree, ijk)
    # every cell of the grid: index where present, -1 elsewhere
    every = np.argwhere(np.ones((SMALL,) * 3, bool)).astype(np.int32)
    position = {tuple(p): i for i, p in enumerate(ijk.tolist())}
    expected = np.array([position.get(tuple(p), -1) for p in every.tolist()])
    np.testing.assert_array_equal(np.asarray(jv.voxel_index(tree, every)), expected)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(*[st.integers(0, 2**17 - 1)] * 3), min_size=1, max_size=50))
def test_deep_trees(points):
    """Resolution 2^17: Morton codes need both words; 17 levels."""
    resolution = 2**17
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=resolution)
    ijk = _sorted_voxels(np.array(points, np.int32))
    for build in (jv.build_octree, jv.build_dag):
        _check_tree(build(jv.Voxels.from_coords(ijk, grid)), ijk)


def test_dag_is_canonical():
    rng = np.random.default_rng(0)
    ijk = rng.integers(0, SMALL, size=(400, 3))
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=SMALL)
    a = jv.build_dag(jv.Voxels.from_coords(ijk, grid))
    b = jv.build_dag(jv.Voxels.from_coords(np.concatenate([ijk[::-1], ijk[:50]]), grid))
    for field in ("mask", "child", "prefix"):
        np.testing.assert_array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field)))
    # the DAG of a set with no repeated subtree equals its octree
    one = jv.Voxels.from_coords([[1, 2, 3]], grid)
    svo, dag = jv.build_octree(one), jv.build_dag(one)
    np.testing.assert_array_equal(np.asarray(svo.child), np.asarray(dag.child))


# ------------------------------------------------------------------ jit, vmap, overflow, errors


def _sizes_as_capacities(ijk, depth):
    return tuple(1 if level == 0 else s for level, s in enumerate(reference_svo_sizes(ijk, depth)))


@pytest.mark.parametrize("dag", [False, True])
def test_jit_vmap_and_eager_agree(dag):
    rng = np.random.default_rng(1)
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=SMALL)
    sets = [jv.Voxels.from_coords(rng.integers(0, SMALL, size=(n, 3)), grid) for n in (30, 60)]
    build = jv.build_dag if dag else jv.build_octree
    caps = (1, 8, 64, 512)
    eager = [jv.compact(build(v, capacities=caps)) for v in sets]
    host = [jv.compact(build(v)) for v in sets]
    jitted = jax.jit(lambda v: build(v, capacities=caps))
    batched = jax.jit(jax.vmap(lambda v: build(v, capacities=caps)))(jax.tree.map(lambda *x: jnp.stack(x), *sets))
    for i, v in enumerate(sets):
        one = jax.tree.map(lambda x: x[i], batched)
        for tree in (eager[i], jv.compact(jitted(v)), jv.compact(one)):
            for field in ("mask", "child", "prefix", "level_count"):
                np.testing.assert_array_equal(np.asarray(getattr(tree, field)), np.asarray(getattr(host[i], field)))
    # voxel_index and expand under jit and vmap
    ijk = sets[0].to_numpy()
    np.testing.assert_array_equal(np.asarray(jax.jit(jv.voxel_index)(host[0], ijk)), np.arange(len(ijk)))
    expanded = jax.jit(lambda t: jv.expand(t, capacity=64))(host[0])
    np.testing.assert_array_equal(expanded.to_numpy(), ijk)
    per_query = jax.vmap(jv.voxel_index, in_axes=(None, 0))(host[0], ijk)
    np.testing.assert_array_equal(np.asarray(per_query), np.arange(len(ijk)))


@pytest.mark.parametrize("dag", [False, True])
def test_overflow_is_flagged(dag, tmp_path):
    rng = np.random.default_rng(2)
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=SMALL)
    vox = jv.Voxels.from_coords(rng.integers(0, SMALL, size=(200, 3)), grid)
    ijk = vox.to_numpy()
    exact = _sizes_as_capacities(ijk, 4)
    build = jv.build_dag if dag else jv.build_octree
    assert int(build(vox, capacities=exact).overflow) == 0
    small = exact[:-1] + (exact[-1] - 1,)
    tree = build(vox, capacities=small)
    assert int(tree.overflow) & jv.OVERFLOW_NODES
    with pytest.raises(jv.JaxvoxError, match="truncated"):
        jv.expand(tree)
    with pytest.raises(jv.JaxvoxError, match="truncated"):
        jv.save(tmp_path / "truncated.jvx", tree)
    assert not list(tmp_path.iterdir())
    full = build(vox)
    out = jv.expand(full, capacity=len(ijk) - 1)
    assert int(out.overflow) == jv.Overflow.EXPANDED  # its own bit, not the build's NODES
    with pytest.raises(jv.JaxvoxError, match="overflow"):
        out.to_numpy()


def test_bad_input_is_refused():
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=SMALL)
    coords = np.full((64, 3), -1, np.int32)
    coords[:3] = [[0, 0, 1], [0, 0, 0], [1, 0, 0]]  # not in Morton order
    unsorted = jv.Voxels(jnp.asarray(coords), jnp.int32(3), jnp.int32(0), None, grid, jv.CONSERVATIVE)
    with pytest.raises(jv.JaxvoxError, match="Morton order"):
        jv.build_octree(unsorted)
    coords[:3] = [[0, 0, 0], [1, 0, 0], [0, 0, 16]]
    outside = jv.Voxels(jnp.asarray(coords), jnp.int32(3), jnp.int32(0), None, grid, jv.CONSERVATIVE)
    with pytest.raises(jv.JaxvoxError, match="outside"):
        jv.build_dag(outside)
    overflowed = jv.Voxels(
        jnp.asarray(coords), jnp.int32(2), jnp.int32(jv.OVERFLOW_VOXELS), None, grid, jv.CONSERVATIVE
    )
    with pytest.raises(jv.JaxvoxError, match="overflowed"):
        jv.build_dag(overflowed)
    with pytest.raises(jv.JaxvoxError, match="capacities"):
        jv.build_octree(jv.Voxels.from_coords([[1, 1, 1]], grid), capacities=(1, 8))
    with pytest.raises(jv.JaxvoxError, match="outside"):
        jv.Voxels.from_coords([[1, 1, 16]], grid)
    with pytest.raises(jv.JaxvoxError, match="integers"):
        jv.Voxels.from_coords([[1.5, 1, 1]], grid)
    assert int(jv.Voxels.from_coords([], grid).count) == 0
    with pytest.raises(jv.JaxvoxError, match="shape"):
        jv.Voxels.from_coords(np.zeros((0, 5), np.int32), grid)
    tree = jv.build_dag(jv.Voxels.from_coords([[1, 1, 1]], grid))
    for bad in ([[1.0, 1.0, 1.0]], [[1, 1]]):
        with pytest.raises(jv.JaxvoxError, match="integer indices"):
            jv.voxel_index(tree, np.array(bad))


def test_repeated_voxels_in_the_jittable_build():
    """The jittable build documents unique input, but repeats must not corrupt masks."""
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=SMALL)
    coords = np.full((64, 3), -1, np.int32)
    coords[:3] = [[0, 0, 0], [1, 0, 0], [1, 0, 0]]
    vox = jv.Voxels(jnp.asarray(coords), jnp.int32(3), jnp.int32(0), None, grid, jv.CONSERVATIVE)
    for build in (jv.build_octree, jv.build_dag):
        tree = build(vox, capacities=(1, 8, 64, 512))
        np.testing.assert_array_equal(jv.expand(tree).to_numpy(), [[0, 0, 0], [1, 0, 0]])


@pytest.mark.parametrize("id_bits", [1, 8, 9, 16, 17, 32])
def test_packed_sort_keys_order_rows_lexicographically(id_bits):
    octree = __import__("sys").modules["jaxvox.octree.build"]
    rng = np.random.default_rng(id_bits)
    top = min((1 << id_bits) - 2, 2**31)
    rows = rng.integers(0, top + 1, size=(300, 8), dtype=np.int64).astype(np.uint32)
    rows[rng.random((300, 8)) < 0.5] = jv.EMPTY
    rows[:, 0] = np.where((rows == jv.EMPTY).all(1), 0, rows[:, 0])  # a row has a child
    rows[100:150] = rows[:50]  # repeats
    rows[280:] = jv.EMPTY  # padding, past n
    ids, rep, count = octree._unique_rows(jnp.asarray(rows), jnp.int32(280), id_bits)
    unique, inverse = np.unique(rows[:280], axis=0, return_inverse=True)  # EMPTY sorts last in uint32 too
    assert int(count) == len(unique)
    np.testing.assert_array_equal(np.asarray(ids)[:280], inverse.reshape(-1))
    np.testing.assert_array_equal(rows[np.asarray(rep)[: len(unique)]], unique)


@pytest.mark.parametrize("name", ["stanford-bunny", "teapot"])
def test_host_build_matches_the_jittable_build_on_meshes(mesh_voxels, name):
    """The host build (numpy) and the jittable build (XLA, with capacities that fit) give
    the same tables, for the octree and the DAG. Both meshes build with the larger of
    their counted capacities per level, so they share the compiled builds."""
    _, vox = mesh_voxels(name)
    caps = tuple(max(c) for c in zip(*(jv.octree_capacities(mesh_voxels(n)[1]) for n in ("stanford-bunny", "teapot"))))
    for build in (jv.build_octree, jv.build_dag):
        host, jitted = jv.compact(build(vox)), jv.compact(build(vox, capacities=caps))
        for field in ("mask", "child", "prefix", "level_count", "voxel_count"):
            np.testing.assert_array_equal(np.asarray(getattr(jitted, field)), np.asarray(getattr(host, field)))


def test_jittable_build_with_wide_ids_matches_host():
    """Capacities above 2^16 make the DAG sort on eight unpacked keys."""
    rng = np.random.default_rng(5)
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=64)
    vox = jv.Voxels.from_coords(rng.integers(0, 64, size=(3000, 3)), grid)
    caps = (1, 8, 64, 512, 1 << 17, 1 << 17)
    jitted = jv.compact(jv.build_dag(vox, capacities=caps))
    host = jv.compact(jv.build_dag(vox))
    for field in ("mask", "child", "prefix", "level_count"):
        np.testing.assert_array_equal(np.asarray(getattr(jitted, field)), np.asarray(getattr(host, field)))


# ------------------------------------------------------------------ files


@pytest.fixture(scope="module")
def saved(tmp_path_factory, mesh_voxels):
    mesh, vox = mesh_voxels("spot")
    dag = jv.build_dag(vox)
    path = tmp_path_factory.mktemp("files") / "spot.jvx"
    attrs = jv.voxel_attributes(mesh, vox)
    jv.save(path, dag, attributes=attrs)
    return path, dag, attrs, vox


def test_save_load_is_bit_exact(saved, tmp_path):
    path, dag, attrs, vox = saved
    loaded = jv.load(path)
    assert loaded.dag and loaded.mode == dag.mode and loaded.level_sizes == dag.level_sizes
    assert loaded.level_capacities == dag.level_capacities
    for field in ("mask", "child", "prefix", "level_count", "voxel_count"):
        a, b = np.asarray(getattr(loaded, field)), np.asarray(getattr(dag, field))
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
    for field in ("origin", "voxel_size"):
        assert np.asarray(getattr(loaded.grid, field)).tobytes() == np.asarray(getattr(dag.grid, field)).tobytes()
    assert loaded.grid.resolution == dag.grid.resolution
    back = jv.load_attributes(path)
    n = int(vox.count)
    assert set(back) == set(attrs)
    for name in attrs:
        assert back[name].tobytes() == np.asarray(attrs[name])[:n].tobytes()
    # a second save writes the same bytes
    again = tmp_path / "again.jvx"
    jv.save(again, loaded, attributes=back)
    assert again.read_bytes() == path.read_bytes()
    # an octree and an empty tree round-trip too
    svo = jv.build_octree(vox)
    jv.save(again, svo)
    assert not jv.load(again).dag and jv.load_attributes(again) == {}
    np.testing.assert_array_equal(jv.expand(jv.load(again)).to_numpy(), vox.to_numpy())
    empty = jv.build_dag(jv.Voxels.from_coords(np.zeros((0, 3), np.int32), vox.grid))
    jv.save(again, empty)
    assert jv.load(again).level_sizes == empty.level_sizes and int(jv.load(again).voxel_count) == 0


def test_tiny_trees_and_attribute_types(tmp_path):
    path = tmp_path / "tiny.jvx"
    for resolution, ijk in ((2, [[1, 1, 1]]), (2, []), (16, [])):
        grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=resolution)
        tree = jv.build_dag(jv.Voxels.from_coords(ijk, grid))
        n = len(ijk)
        jv.save(path, tree, attributes={"normal": np.zeros((n, 3), np.float32), "id": np.arange(n)})
        back = jv.load(path)
        np.testing.assert_array_equal(jv.expand(back).to_numpy().reshape(-1, 3), np.array(ijk).reshape(-1, 3))
        assert jv.load_attributes(path)["normal"].shape == (n, 3)
    big_endian = np.arange(1, dtype=">f8")
    jv.save(path, tree, attributes={"x": big_endian})
    assert jv.load_attributes(path)["x"].dtype == np.dtype("<f8")
    for bad in (np.array([object()]), np.zeros(1, [("a", "<f4")]), np.array(["s"])):
        with pytest.raises(jv.JaxvoxError, match="dtype"):
            jv.save(tmp_path / "bad.jvx", tree, attributes={"x": bad})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.jvx"]  # no temporary file left


def _rewrite(data: bytes, edit_header=None, edit_arrays=None) -> bytes:
    """A file with an edited header or array bytes and a recomputed, valid checksum."""
    import json
    import struct
    import zlib

    magic, version, head_len = struct.unpack_from("<8sII", data)
    header = json.loads(data[16 : 16 + head_len])
    body = bytearray(data[16 + head_len : -4])
    if edit_header:
        edit_header(header)
    if edit_arrays:
        edit_arrays(header, body)
    head = json.dumps(header).encode()
    head += b" " * (-(len(head) + 16) % 8)
    out = struct.pack("<8sII", magic, version, len(head)) + head + bytes(body)
    return out + struct.pack("<I", zlib.crc32(out))


def test_invalid_trees_with_valid_checksums_are_refused(saved, tmp_path):
    path, *_ = saved
    data = path.read_bytes()
    entry = lambda h, name: next(e for e in h["arrays"] if e["name"] == name)

    def poke(name, index, value):
        def edit(header, body):
            e = entry(header, name)
            view = np.frombuffer(body, np.dtype(e["dtype"]), int(np.prod(e["shape"])), e["offset"])
            view = view.copy()
            view.reshape(-1)[index] = value
            body[e["offset"] : e["offset"] + view.nbytes] = view.tobytes()

        return edit

    edits = {
        "negative shape": dict(edit_header=lambda h: entry(h, "mask").update(shape=[-1])),
        "negative offset": dict(edit_header=lambda h: entry(h, "child").update(offset=-8)),
        "object dtype": dict(edit_header=lambda h: entry(h, "mask").update(dtype="|O")),
        "float shape": dict(edit_header=lambda h: entry(h, "mask").update(shape=[1.5])),
        "wrong resolution": dict(edit_header=lambda h: h["grid"].update(resolution=32)),
        "odd resolution": dict(edit_header=lambda h: h["grid"].update(resolution=48)),
        "voxel count": dict(edit_header=lambda h: h.update(voxel_count=h["voxel_count"] + 1)),
        "huge voxel count": dict(edit_header=lambda h: h.update(voxel_count=2**40)),
        "unknown kind": dict(edit_header=lambda h: h.update(kind="tree")),
        "missing sizes": dict(edit_header=lambda h: h.pop("level_sizes")),
        "pointer out of range": dict(edit_arrays=poke("child", 0, 10**6)),
        "pointer vs mask": dict(edit_arrays=poke("child", 0, jv.EMPTY)),  # the root's first child
        "prefix": dict(edit_arrays=poke("prefix", 8 * 5 + 3, 12345)),
        "mask": dict(edit_arrays=poke("mask", -1, 0)),
    }
    bad = tmp_path / "bad.jvx"
    assert jv.load(path).level_sizes  # the original loads
    for what, edit in edits.items():
        bad.write_bytes(_rewrite(data, **edit))
        with pytest.raises(jv.JaxvoxError, match="inconsistent|corrupt|truncated") as info:
            jv.load(bad)
        assert info.value, what


def test_corrupt_and_truncated_files_are_detected(saved, tmp_path):
    path, *_ = saved
    data = path.read_bytes()
    bad = tmp_path / "bad.jvx"
    rng = np.random.default_rng(3)
    positions = [0, 9, 20, 40, len(data) // 2, len(data) - 5, len(data) - 1] + list(rng.integers(0, len(data), 20))
    for pos in positions:
        flipped = bytearray(data)
        flipped[pos] ^= 0x5A
        bad.write_bytes(bytes(flipped))
        with pytest.raises(jv.JaxvoxError, match="corrupt|truncated|magic|version|inconsistent"):
            jv.load(bad)
    for length in [0, 5, 16, 100, len(data) // 2, len(data) - 4, len(data) - 1]:
        bad.write_bytes(data[:length])
        with pytest.raises(jv.JaxvoxError, match="truncated|magic"):
            jv.load(bad)
    bad.write_bytes(data + b"\0")
    with pytest.raises(jv.JaxvoxError, match="trailing"):
        jv.load(bad)
    with pytest.raises(jv.JaxvoxError, match="load path: file not found"):
        jv.load(tmp_path / "missing.jvx")


def test_cli_build_and_run(tmp_path, capsys, meshes_dir):
    from jaxvox.cli import main

    out = tmp_path / "woody.jvx"
    assert main(["build", str(meshes_dir / "woody.obj"), "--resolution", "32", "--out", str(out)]) == 0
    tree = jv.load(out)
    assert tree.dag and tree.grid.resolution == 32
    mesh = jv.load_mesh(meshes_dir / "woody.obj")
    expected = jv.voxelize(mesh, jv.Grid.fit(mesh, 32)).to_numpy()
    np.testing.assert_array_equal(jv.expand(tree).to_numpy(), expected)
    assert set(jv.load_attributes(out)) == {"triangle", "normal"}
    assert main(["run", "--resolution", "32", "--out", str(tmp_path / "run")]) == 0
    printed = capsys.readouterr().out
    assert "DAG" in printed and "octree/DAG nodes" in printed
    scene = jv.load(tmp_path / "run" / "scene.jvx")
    assert set(jv.load_attributes(tmp_path / "run" / "scene.jvx")) == {"triangle", "normal", "color"}
    assert int(scene.voxel_count) > 0 and (tmp_path / "run" / "voxels.png").stat().st_size > 0
    import imageio.v3 as iio

    render = iio.imread(tmp_path / "run" / "render.png")  # depth | gap | normals, 640x480 each
    assert render.shape == (480, 2 * 640 + 8, 3) and "Mrays/s" in printed
    assert (render[:, :640] < 255).any(axis=-1).mean() > 0.05  # the scene covers part of the image
