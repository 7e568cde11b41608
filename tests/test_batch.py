"""Batched pipelines: stacking, one compiled program for a batch, overflow flags and re-runs.

Every batched result is compared with the one-by-one host path (`voxelize`, `build_dag` /
`build_octree`, `trace`; trees compared after `compact`). The grids have power-of-two voxel sizes: then
``x / h`` is exact however XLA evaluates it (inside a vmapped program it may multiply by
``1 / h`` instead), so geometry lying exactly on a voxel plane (woody is flat, in one)
and rays through voxel edges give bit-identical results on both paths.
"""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest

import jaxvox as jv
from tests.test_compiles import count_compiles

RESOLUTION = 16
NAMES = ("suzanne", "woody", "beetle", "spot")
TREE_FIELDS = ("mask", "child", "prefix", "level_count", "level_capacity", "voxel_count")
HIT_FIELDS = ("t", "voxel", "normal", "index", "status")


def pow2_grid(mesh: jv.Mesh, resolution: int) -> jv.Grid:
    """A grid around the mesh, centred on its bounding box, whose voxel size is a power of two."""
    v = np.asarray(mesh.vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    h = 2.0 ** math.ceil(math.log2((hi - lo).max() * 1.02 / resolution))
    return jv.Grid(((lo + hi) / 2 - resolution * h / 2).astype(np.float32), h, resolution)


def camera_rays(mesh: jv.Mesh, width: int = 24, height: int = 16):
    return tuple(np.asarray(a) for a in jv.pinhole_rays(*jv.look_at_view(mesh), width=width, height=height))


def host_reference(mesh, grid, origins, directions, *, mode="conservative", dag=True):
    """(voxels [n, 3], compact tree, hit) of the one-by-one host path. The hits are traced on
    the tree as built, padded to the shape ladder, so that the items share one compiled trace
    (test_batch_in_one_jit_matches_host_path checks that the compact tree traces the same)."""
    vox = jv.voxelize(mesh, grid, mode=mode)
    tree = (jv.build_dag if dag else jv.build_octree)(vox)
    return vox.to_numpy(), jv.compact(tree), jv.trace(tree, origins, directions)


def assert_item_equal(voxels, tree, hit, ref):
    ref_voxels, ref_tree, ref_hit = ref
    np.testing.assert_array_equal(voxels, ref_voxels)
    assert tree.dag == ref_tree.dag
    for field in TREE_FIELDS:
        np.testing.assert_array_equal(
            np.asarray(getattr(tree, field)), np.asarray(getattr(ref_tree, field)), err_msg=field
        )
    for field in HIT_FIELDS:
        np.testing.assert_array_equal(
            np.asarray(getattr(hit, field)), np.asarray(getattr(ref_hit, field)), err_msg=field
        )


def item(tree, b):
    """Item `b` of a batched pytree."""
    return jax.tree.map(lambda x: x[b], tree)


class CompileCounter:
    """Counts the programs the process builds while active: the "backend compile" events
    of `jax.monitoring`, one per program missing from the in-memory cache (also when the
    persistent compilation cache that tests/conftest.py turns on serves it)."""

    def __init__(self):
        self.count = 0
        jax.monitoring.register_event_duration_secs_listener(self._listen)

    def _listen(self, event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            self.count += 1


@pytest.fixture(scope="module")
def batch(meshes_dir):
    """Four test meshes (geometry only), their grids, rays, capacities and host results."""
    meshes = [jv.load_mesh(meshes_dir / f"{name}.obj") for name in NAMES]
    meshes = [jv.Mesh(m.vertices, m.faces) for m in meshes]
    grids = [pow2_grid(m, RESOLUTION) for m in meshes]
    rays = [camera_rays(m) for m in meshes]
    origins, directions = (np.stack(parts) for parts in zip(*rays))
    refs = [host_reference(m, g, *r) for m, g, r in zip(meshes, grids, rays)]
    return dict(
        meshes=meshes,
        grids=grids,
        origins=origins,
        directions=directions,
        refs=refs,
        capacities=jv.batch_capacities(meshes, grids),
    )


def test_stack_meshes_pads_to_the_ladder(batch):
    meshes = batch["meshes"]
    stacked = jv.stack_meshes(meshes)
    v_max, f_max = max(m.num_vertices for m in meshes), max(m.num_faces for m in meshes)
    v_pad, f_pad = 1 << v_max.bit_length(), 1 << (f_max - 1).bit_length()  # one spare vertex
    assert stacked.vertices.shape == (4, v_pad, 3) and stacked.vertices.dtype == np.float32
    assert stacked.faces.shape == (4, f_pad, 3) and stacked.faces.dtype == np.int32
    for b, mesh in enumerate(meshes):
        faces, vertices = np.asarray(stacked.faces[b]), np.asarray(stacked.vertices[b])
        np.testing.assert_array_equal(faces[: mesh.num_faces], np.asarray(mesh.faces))
        np.testing.assert_array_equal(vertices[: mesh.num_vertices], np.asarray(mesh.vertices))
        # padding: NaN vertices, faces at the first of them (the voxelizer skips them)
        assert np.isnan(vertices[mesh.num_vertices :]).all()
        assert (faces[mesh.num_faces :] == mesh.num_vertices).all()
    grids = jv.stack_grids(batch["grids"])
    assert grids.origin.shape == (4, 3) and grids.voxel_size.shape == (4,)
    assert grids.resolution == RESOLUTION


def test_batch_in_one_jit_matches_host_path(batch):
    caps, tree_caps = batch["capacities"]
    assert tree_caps[0] == 1 and len(tree_caps) == int(math.log2(RESOLUTION))
    meshes, grids = jv.stack_meshes(batch["meshes"]), jv.stack_grids(batch["grids"])
    run = jax.jit(lambda m, g, o, d: jv.voxelize_build_trace(m, g, o, d, capacities=caps, tree_capacities=tree_caps))
    counter = CompileCounter()
    vox, tree, hit = jax.block_until_ready(run(meshes, grids, batch["origins"], batch["directions"]))
    # The whole batch is one compiled program (an eager helper dropped from the caches by
    # an earlier module's teardown may recompile beside it).
    assert 1 <= counter.count <= 2
    np.testing.assert_array_equal(np.asarray(vox.overflow), 0)
    np.testing.assert_array_equal(np.asarray(tree.overflow), 0)
    for b, ref in enumerate(batch["refs"]):
        assert_item_equal(item(vox, b).to_numpy(), jv.compact(item(tree, b)), item(hit, b), ref)
    # The host hits do not depend on the padding: the compact tree traces the same.
    _, compact_tree, ref_hit = batch["refs"][0]
    compact_hit = jv.trace(compact_tree, batch["origins"][0], batch["directions"][0])
    for field in HIT_FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(compact_hit, field)), np.asarray(getattr(ref_hit, field)))

    # Other meshes of the same padded sizes (the batch reversed) run the same program.
    order = [3, 2, 1, 0]
    again = jv.stack_meshes([batch["meshes"][b] for b in order])
    assert again.faces.shape == meshes.faces.shape
    before = counter.count
    vox, tree, hit = run(
        again, jv.stack_grids([batch["grids"][b] for b in order]), batch["origins"][order], batch["directions"][order]
    )
    assert counter.count == before
    for b, source in enumerate(order):
        assert_item_equal(item(vox, b).to_numpy(), jv.compact(item(tree, b)), item(hit, b), batch["refs"][source])


def test_tiny_capacities_flag_items_and_only_those_are_rerun(batch):
    meshes, grids = batch["meshes"], batch["grids"]
    depth = int(math.log2(RESOLUTION))
    caps, tree_caps = batch["capacities"]
    needs = [jv.voxel_capacities(m, g) for m, g in zip(meshes, grids)]
    # octree nodes per level (what tree capacities bound, for a DAG too): distinct ijk >> (D - l)
    sizes = [
        np.array([len(np.unique(ref[0] >> (depth - level), axis=0)) for level in range(depth)]) for ref in batch["refs"]
    ]
    # Capacities that fit the item with the fewest voxels, and its tree's last level.
    small = int(np.argmin([len(ref[0]) for ref in batch["refs"]]))
    tiny = jv.Capacities(caps.columns, caps.rows, caps.candidates, needs[small].voxels, caps.row_chunk)
    tiny_tree = tree_caps[:-1] + (1 << (int(sizes[small][-1]) - 1).bit_length(),)
    expected_bits = [jv.OVERFLOW_VOXELS * (len(ref[0]) > tiny.voxels) for ref in batch["refs"]]
    overflowing = tuple(b for b, bits in enumerate(expected_bits) if bits)
    assert 0 < len(overflowing) < len(meshes)

    vox, tree, _ = jv.voxelize_build_trace(
        jv.stack_meshes(meshes),
        jv.stack_grids(grids),
        batch["origins"],
        batch["directions"],
        capacities=tiny,
        tree_capacities=tiny_tree,
    )
    np.testing.assert_array_equal(np.asarray(vox.overflow), expected_bits)
    for b, bits in enumerate(expected_bits):
        flags = int(tree.overflow[b])
        assert flags & ~jv.OVERFLOW_NODES == bits
        if not bits:  # the tree of untruncated voxels overflows exactly when a level does not fit
            assert bool(flags & jv.OVERFLOW_NODES) == bool((sizes[b] > np.asarray(tiny_tree)).any())

    result = jv.run_batch(
        meshes, grids, batch["origins"], batch["directions"], capacities=tiny, tree_capacities=tiny_tree
    )
    rerun = tuple(b for b in range(len(meshes)) if int(tree.overflow[b]))
    assert result.retried == (rerun,)  # the re-run takes the counted capacities: once is enough
    assert result.capacities.voxels > tiny.voxels
    for b, ref in enumerate(batch["refs"]):
        assert_item_equal(result.voxels[b], result.trees[b], item(result.hits, b), ref)
    assert len(result.trees[0].level_capacities) == depth

    with pytest.raises(jv.JaxvoxError, match="still overflow"):
        jv.run_batch(
            meshes,
            grids,
            batch["origins"],
            batch["directions"],
            capacities=tiny,
            tree_capacities=tiny_tree,
            max_tries=1,
        )


def test_shared_grid_octrees_six_separating():
    """Procedural meshes in one shared grid, plain octrees, 6-separating mode."""
    import trimesh

    shapes = [
        trimesh.creation.icosphere(subdivisions=2, radius=0.4),
        trimesh.creation.torus(major_radius=0.3, minor_radius=0.1, major_sections=24, minor_sections=12),
        trimesh.creation.box(extents=(0.5, 0.3, 0.7)),
    ]
    rng = np.random.default_rng(0)
    meshes = []
    for shape in shapes:
        rotation = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
        meshes.append(jv.Mesh((shape.vertices @ rotation.T).astype(np.float32), shape.faces))
    grid = jv.Grid((-0.5, -0.5, -0.5), 1 / 16, 16)
    rays = [camera_rays(m, 12, 8) for m in meshes]
    origins, directions = (np.stack(parts) for parts in zip(*rays))
    result = jv.run_batch(meshes, grid, origins, directions, mode="6-separating", dag=False)
    assert result.retried == ()
    for b, (mesh, r) in enumerate(zip(meshes, rays)):
        ref = host_reference(mesh, grid, *r, mode="6-separating", dag=False)
        assert not result.trees[b].dag
        assert_item_equal(result.voxels[b], result.trees[b], item(result.hits, b), ref)
    # The next batch of a dataset, smaller meshes (fewer voxels, nodes and work items),
    # runs this batch's program: run_batch starts from the largest default capacities it
    # ran with at this resolution, mode and tree kind.
    smaller = [jv.Mesh(np.asarray(m.vertices) * 0.6, m.faces) for m in meshes]
    assert any(
        a < b for a, b in zip(jv.batch_capacities(smaller, grid, mode="6-separating")[0], result.capacities)
    )  # (counted alone, it would take other capacities: another program)
    rays = [camera_rays(m, 12, 8) for m in smaller]
    origins, directions = (np.stack(parts) for parts in zip(*rays))
    with count_compiles() as n:
        again = jv.run_batch(smaller, grid, origins, directions, mode="6-separating", dag=False)
    assert n[0] == 0 and again.capacities == result.capacities
    for b, mesh in enumerate(smaller):
        assert np.array_equal(again.voxels[b], jv.voxelize(mesh, grid, mode="6-separating").to_numpy())


def test_bad_input_raises():
    tetra = jv.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    grids = [jv.Grid((0, 0, 0), 1 / 16, 16), jv.Grid((0, 0, 0), 1 / 32, 32)]
    with pytest.raises(jv.JaxvoxError, match="one resolution"):
        jv.stack_grids(grids)
    with pytest.raises(jv.JaxvoxError, match="one resolution"):
        jv.batch_capacities([tetra, tetra], grids)
    origins = np.zeros((2, 4, 3), np.float32)
    with pytest.raises(jv.JaxvoxError, match="one resolution"):
        jv.run_batch([tetra, tetra], grids, origins, origins + 1)
    coloured = jv.Mesh(tetra.vertices, tetra.faces, colors=np.ones((4, 3), np.float32))
    with pytest.raises(jv.JaxvoxError, match="colors"):
        jv.stack_meshes([tetra, coloured])
    with pytest.raises(jv.JaxvoxError, match="too small"):
        jv.stack_meshes([tetra], num_faces=2)
    stacked = jv.stack_meshes([tetra, tetra])
    with pytest.raises(jv.JaxvoxError, match="leading batch axis"):
        jv.voxelize_build_trace(
            stacked,
            grids[0],
            origins[:1],
            origins[:1] + 1,
            capacities=jv.Capacities(256, 256, 256, 256),
            tree_capacities=(1, 8, 64, 256),
        )
    with pytest.raises(jv.JaxvoxError, match="tree_capacities"):
        jv.voxelize_build_trace(
            stacked,
            grids[0],
            origins,
            origins + 1,
            capacities=jv.Capacities(256, 256, 256, 256),
            tree_capacities=(2, 8, 64, 256),
        )
