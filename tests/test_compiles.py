"""Compile budget: a new mesh of a familiar size runs programs that are already compiled."""

from __future__ import annotations

import contextlib

import jax
import numpy as np

import jaxvox as jv

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
_compiles = []
jax.monitoring.register_event_duration_secs_listener(
    lambda name, secs, **kw: _compiles.append(secs) if name == COMPILE_EVENT else None
)


@contextlib.contextmanager
def count_compiles():
    """Yields a list that holds, on exit, the number of XLA compilations inside the block."""
    start, out = len(_compiles), []
    yield out
    out.append(len(_compiles) - start)


def _rotated(mesh: jv.Mesh, degrees: float) -> jv.Mesh:
    a = np.radians(degrees)
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]], np.float32)
    return jv.Mesh(np.asarray(mesh.vertices) @ rot.T, np.asarray(mesh.faces))


def _pipeline(mesh: jv.Mesh, resolution: int):
    grid = jv.Grid.fit(mesh, resolution)
    dag = jv.build_dag(jv.voxelize(mesh, grid))
    eye, centre = jv.look_at_view(mesh)
    origins, directions = jv.pinhole_rays(eye, centre, width=48, height=32)
    hit = jv.trace(dag, origins, directions)
    image = jv.render(dag, eye, centre, width=48, height=32, spp=2, bounces=1)
    jax.block_until_ready((hit.t, image.radiance))
    return dag, hit


def test_a_new_mesh_of_a_familiar_size_compiles_nothing(meshes_dir):
    spot = jv.load_mesh(meshes_dir / "spot.obj")
    _pipeline(spot, 64)  # warm-up
    others = [_rotated(spot, 35.0), _rotated(spot, -60.0)]  # other meshes, same buckets
    for mesh in others:
        with count_compiles() as n:
            dag, hit = _pipeline(mesh, 64)
        assert int(dag.voxel_count) > 0 and (np.asarray(hit.status) == jv.HIT).any()
        assert n[0] == 0, f"{n[0]} programs compiled for a mesh in the warmed-up buckets"
    # Another image size with a ray count in the same bucket (1,200 rays against 1,536):
    # the beam start's program, keyed by the image shape, compiles once; without the beam
    # the rays are padded to their bucket and nothing compiles.
    origins, directions = jv.pinhole_rays(*jv.look_at_view(others[0]), width=40, height=30)
    with count_compiles() as n:
        hit = jv.trace(dag, origins, directions)
    assert hit.t.shape == (30, 40) and n[0] == 1
    with count_compiles() as n:
        jv.trace(dag, origins, directions)
    assert n[0] == 0
    jv.trace(dag, *jv.pinhole_rays(*jv.look_at_view(others[0]), width=48, height=32), beam=False)
    with count_compiles() as n:
        hit = jv.trace(dag, origins, directions, beam=False)
    assert hit.t.shape == (30, 40) and n[0] == 0


def test_counting_sees_compiles():
    """The counter itself works: a program of a new shape compiles once, then never."""
    f = jax.jit(lambda x: x * 3 + 1)
    with count_compiles() as first:
        f(np.zeros(7919, np.float32)).block_until_ready()
    with count_compiles() as again:
        f(np.ones(7919, np.float32)).block_until_ready()
    assert first[0] >= 1 and again[0] == 0


def test_sparse_fields_of_meshes_with_new_holes_compile_nothing(meshes_dir):
    """Spot with holes of new shapes (other numbers of cap triangles, the same face
    bucket) runs the sparse field's programs of the first holed spot: the caps' blocks
    are on the shape ladder (`jaxvox.distance.winding.TriangleBlocks`), and each field
    still has an inside."""
    spot = jv.load_mesh(meshes_dir / "spot.obj")
    faces = np.asarray(spot.faces)

    def field(every: int) -> jv.SparseField:
        """Spot without every `every`-th face (a hole each), at 16^3."""
        mesh = jv.Mesh(np.asarray(spot.vertices), np.delete(faces, np.s_[::every], axis=0))
        return jax.block_until_ready(jv.sparse_distance_field(mesh, jv.Grid.fit(mesh, 16), band=2))

    field(50)  # warm-up: 117 holes
    for every in (9, 20):  # 650 and 293 holes
        with count_compiles() as n:
            got = field(every)
        assert (np.asarray(got.values[: int(got.count)]) < 0).any()
        assert n[0] == 0, f"{n[0]} programs compiled for spot without every {every}th face"


def test_distance_fields_of_a_mesh_without_its_texture_compile_nothing(meshes_dir):
    """A mesh's colours, uvs and texture are no part of its distance field's programs:
    spot without them (a mesh of another pytree structure) runs textured spot's."""
    spot = jv.load_mesh(meshes_dir / "spot.obj")
    grid = jv.Grid.fit(spot, 16)
    assert spot.uvs is not None and spot.texture is not None
    want = jax.block_until_ready(jv.distance_field(spot, grid))
    with count_compiles() as n:
        got = jax.block_until_ready(jv.distance_field(jv.Mesh(spot.vertices, spot.faces), grid))
    assert np.array_equal(np.asarray(got), np.asarray(want))
    assert n[0] == 0, f"{n[0]} programs compiled for spot without its texture"


def test_solid_voxels_of_a_turned_mesh_compile_nothing(meshes_dir):
    """The parity voxelization's capacity has a voxel list's floor: the cow turned by 35
    degrees (other column counts) runs the program of the cow."""
    cow = jv.load_mesh(meshes_dir / "cow.obj")
    jax.block_until_ready(jv.solid_voxelize(cow, jv.Grid.fit(cow, 32), method="parity"))
    turned = _rotated(cow, 35.0)
    with count_compiles() as n:
        inside = jax.block_until_ready(jv.solid_voxelize(turned, jv.Grid.fit(turned, 32), method="parity"))
    assert np.asarray(inside).any()
    assert n[0] == 0, f"{n[0]} programs compiled for the turned cow"
