"""The pointer-per-present-child layout (`compact_dag`): traced, rendered and indexed exactly as
the 8-slot tables it comes from, with the bytes the layout promises."""

from __future__ import annotations

import hypothesis.strategies as st
import jax
import numpy as np
import pytest
from hypothesis import example, given, settings

import jaxvox as jv
from jaxvox.trace import HIT

from .test_trace import assert_matches, assert_same, rays, spot_scene

LAYOUTS = [True, False]  # with and without prefix sums


@pytest.fixture(scope="module")
def scene(meshes_dir):
    return spot_scene(meshes_dir)


@pytest.fixture(scope="module")
def trees(scene):
    return {"svo": jv.build_octree(scene[0]), "dag": jv.build_dag(scene[0])}


def assert_traces_alike(tree, compact, o, d, **kwargs):
    """Same t, voxel, normal and status; the same index with prefix sums, -1 without."""
    a, b = jv.trace(tree, o, d, **kwargs), jv.trace(compact, o, d, **kwargs)
    for name in ("t", "voxel", "normal", "status"):
        np.testing.assert_array_equal(np.asarray(getattr(b, name)), np.asarray(getattr(a, name)), err_msg=name)
    expected = np.asarray(a.index) if compact.prefix else np.full_like(np.asarray(a.index), -1)
    np.testing.assert_array_equal(np.asarray(b.index), expected)


def all_cells(resolution):
    """Every voxel index of the grid and a one-voxel shell outside it: [(R + 2)^3, 3] int32."""
    r = np.arange(-1, resolution + 1)
    return np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3).astype(np.int32)


def expected_nbytes(tree, prefix):
    """4 bytes per node above level D - 1 (its mask word) and per present child, plus one
    prefix word per child but the first: counted from the 8-slot tables."""
    sizes = jv.octree.stored_sizes(tree.level_sizes)
    if len(sizes) == 1:
        return 4
    masks = np.concatenate([np.asarray(tree.mask)[o : o + n] for o, n in zip(tree.level_offsets[:-1], sizes[:-1])])
    children = int(np.unpackbits(masks[:, None], axis=1).sum())
    inner = len(masks)
    return 4 * (inner + children + (children - int((masks > 0).sum()) if prefix else 0))


@pytest.mark.parametrize("prefix", LAYOUTS)
@pytest.mark.parametrize("kind", ["svo", "dag"])
def test_traces_as_the_tables_over_hard_rays(scene, trees, kind, prefix):
    """Adversarial rays (axis-aligned, zero components, inside voxels, on corners, in voxel
    planes), both traversals, lanes and plain vmap; and the brute-force first hits."""
    vox, ijk, o, d = scene
    tree = trees[kind]
    compact = jv.compact_dag(tree, prefix=prefix)
    assert compact.dag == tree.dag and compact.level_sizes == tree.level_sizes
    assert compact.nbytes == expected_nbytes(tree, prefix)
    for method in jv.TRACE_METHODS:  # persistent lanes, and a plain vmap on the DAG
        for lanes in (64, None) if kind == "dag" else (64,):
            assert_traces_alike(tree, compact, o, d, method=method, lanes=lanes)
    assert_matches(jv.trace(compact, o, d), ijk, o, d)


def test_voxel_index_and_occupancy(scene, trees):
    vox, ijk, o, d = scene
    cells = all_cells(32)
    for tree in trees.values():
        expected = np.asarray(jv.voxel_index(tree, cells))
        np.testing.assert_array_equal(np.asarray(jv.voxel_index(jv.compact_dag(tree), cells)), expected)
        for prefix in LAYOUTS:
            occupied = np.asarray(jv.octree.occupied(jv.compact_dag(tree, prefix=prefix), cells))
            np.testing.assert_array_equal(occupied, expected >= 0)
    with pytest.raises(jv.JaxvoxError, match="prefix sums"):
        jv.voxel_index(jv.compact_dag(trees["dag"], prefix=False), cells)


@pytest.mark.parametrize("name", ["cow", "fandisk", "woody"])
def test_data_meshes(meshes_dir, name):
    """Shared meshes at 64^3 (Grid.fit): rays through the box, both layouts, every cell indexed."""
    mesh = jv.load_mesh(meshes_dir / f"{name}.obj")
    vox = jv.voxelize(mesh, jv.Grid.fit(mesh, 64))
    dag = jv.build_dag(vox)
    ijk = vox.to_numpy()
    o, d = rays(np.random.default_rng(len(name)), 512, 64, ijk)
    to_world = lambda p: np.asarray(vox.grid.origin) + p * float(vox.grid.voxel_size)
    o, d = to_world(o).astype(np.float32), (d * float(vox.grid.voxel_size)).astype(np.float32)
    for prefix in LAYOUTS:
        assert_traces_alike(dag, jv.compact_dag(dag, prefix=prefix), o, d)
    cells = all_cells(64)
    np.testing.assert_array_equal(
        np.asarray(jv.voxel_index(jv.compact_dag(dag), cells)), np.asarray(jv.voxel_index(dag, cells))
    )


@settings(max_examples=2, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([2, 16]))
@example(seed=11, resolution=16)  # the empty set
@example(seed=1, resolution=2)  # the full grid at depth 1
def test_random_sets_and_lattice_rays(seed, resolution):
    """Random voxel sets at small R (depth 1 included: the root is a mask), with rays on
    integer and half-integer coordinates; the full grid and the empty set always among
    them (explicit examples: seed 11 draws the empty set, seed 1 the full grid)."""
    rng = np.random.default_rng(seed)
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=resolution)
    choice = rng.integers(0, 4)
    if choice == 0:
        ijk = np.zeros((0, 3), np.int32)
    elif choice == 1:
        ijk = all_cells(resolution)[np.all((all_cells(resolution) >= 0) & (all_cells(resolution) < resolution), 1)]
    else:
        count = rng.integers(1, max(2, resolution**3 // 4))
        ijk = np.unique(rng.integers(0, resolution, (count, 3)), axis=0).astype(np.int32)
    dag = jv.build_dag(jv.Voxels.from_coords(ijk, grid))
    o = (rng.integers(-2, 2 * resolution + 4, (64, 3)) / 2.0).astype(np.float32)
    d = rng.integers(-2, 3, (64, 3)).astype(np.float32)
    d[(d == 0).all(1), 0] = 1
    for prefix in LAYOUTS:
        compact = jv.compact_dag(dag, prefix=prefix)
        assert compact.nbytes == expected_nbytes(dag, prefix)
        assert_traces_alike(dag, compact, o, d, lanes=16)
        assert_matches(jv.trace(compact, o, d, method="stack", lanes=None), ijk, o, d)
    cells = all_cells(resolution)
    np.testing.assert_array_equal(
        np.asarray(jv.voxel_index(jv.compact_dag(dag), cells)), np.asarray(jv.voxel_index(dag, cells))
    )


def test_jit_and_vmap(scene, trees):
    vox, ijk, o, d = scene
    compact = jv.compact_dag(trees["dag"])
    eager = jv.trace(compact, o[:120], d[:120])
    jitted = jax.jit(lambda t, a, b: jv.trace(t, a, b))(compact, o[:120], d[:120])
    assert_same(jitted, eager)
    mapped = jax.vmap(lambda a, b: jv.trace(compact, a, b))(o[:120].reshape(4, 30, 3), d[:120].reshape(4, 30, 3))
    assert_same(jax.tree.map(lambda x: x.reshape((120,) + x.shape[2:]), mapped), eager)
    hits = np.asarray(eager.status) == HIT
    index = jax.jit(jv.voxel_index)(compact, np.asarray(eager.voxel)[hits])
    np.testing.assert_array_equal(np.asarray(index), np.asarray(eager.index)[hits])


def test_renders_the_same_image(scene, trees):
    vox = scene[0]
    dag = trees["dag"]
    eye, target = np.array([40.0, 30.0, -20.0]), np.full(3, 16.0)
    albedo = np.random.default_rng(0).uniform(0, 1, (int(vox.count), 3)).astype(np.float32)
    settings = dict(width=24, height=16, spp=2, bounces=2, key=3)
    reference = jv.render(dag, eye, target, albedo=albedo, **settings)
    assert_same(jv.render(jv.compact_dag(dag), eye, target, albedo=albedo, **settings), reference)
    # The default grey, as a per-voxel table of the same shape: the reference's program
    # (compiling is most of this test's time), and the same image as one grey row.
    grey = jv.render(dag, eye, target, albedo=np.full_like(albedo, 0.7), **settings)
    assert_same(jv.render(jv.compact_dag(dag, prefix=False), eye, target, **settings), grey)
    with pytest.raises(jv.JaxvoxError, match="prefix sums"):
        jv.render(jv.compact_dag(dag, prefix=False), eye, target, albedo=albedo, **settings)


def test_bad_input():
    with pytest.raises(jv.JaxvoxError, match="compact_dag tree"):
        jv.compact_dag(np.zeros((4, 4, 4), bool))
    with pytest.raises(jv.JaxvoxError, match="Octree or jaxvox.CompactDag"):
        jv.trace("tree", np.zeros((1, 3)), np.ones((1, 3)))


def test_trees_beyond_int32_indices(scene, trees, monkeypatch):
    """A tree of more than 2^31 - 1 voxels (the count is uint32; a 32768^3 bunny holds
    3.5 G) has no int32 Morton index: `voxel_index` and `trace` refuse it, the sparse
    layout without prefix sums traces it, and `mesh_to_dag` refuses only past 2^32 - 1."""
    import dataclasses

    import jax.numpy as jnp

    from jaxvox.octree import stream

    vox, ijk, o, d = scene
    dag = trees["dag"]
    assert dag.voxel_count.dtype == jnp.uint32
    huge = dataclasses.replace(dag, voxel_count=jnp.uint32(2**31))
    for call in (lambda t: jv.voxel_index(t, ijk), lambda t: jv.trace(t, o, d)):
        with pytest.raises(jv.JaxvoxError, match="beyond int32 Morton indices"):
            call(huge)
        with pytest.raises(jv.JaxvoxError, match="beyond int32 Morton indices"):
            call(jv.compact_dag(huge))
    traced = jv.trace(jv.compact_dag(huge, prefix=False), o, d)
    assert_same(jax.tree.map(np.asarray, traced), jv.trace(jv.compact_dag(dag, prefix=False), o, d))
    assert stream.MAX_VOXELS == 2**32 - 1
    monkeypatch.setattr(stream, "MAX_VOXELS", 100)
    mesh = jv.Mesh(np.array([[1, 1, 1], [30, 2, 2], [2, 30, 29]], np.float32), np.array([[0, 1, 2]], np.int32))
    with pytest.raises(jv.JaxvoxError, match="more than 100 voxels"):
        jv.mesh_to_dag(mesh, vox.grid, region=8)
