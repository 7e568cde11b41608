"""`mesh_to_dag`: the region-by-region DAG equals ``build_dag(voxelize(...))`` table for
table (the test meshes, both modes, many small regions, empty regions and meshes, one
region), the host-side row unique orders as the build's, bad input is refused, and
``jaxvox build`` writes the same file through it."""

from __future__ import annotations

import numpy as np
import pytest

import jaxvox as jv
from jaxvox._core.shapes import voxel_bucket
from jaxvox.octree.host import unique_rows as _unique_rows
from jaxvox.render.materials import normal_table

MESHES = ["stanford-bunny", "spot", "teapot", "suzanne", "fandisk", "cow", "woody", "beetle"]
FIELDS = ("mask", "child", "prefix", "level_count", "voxel_count", "overflow", "level_capacity")


def _assert_same_tree(got: jv.Octree, want: jv.Octree) -> None:
    """Every table of the two trees, padded (as returned) and compact, and the static fields."""
    assert (got.dag, got.mode, got.grid.resolution) == (want.dag, want.mode, want.grid.resolution)
    np.testing.assert_array_equal(np.asarray(got.grid.origin), np.asarray(want.grid.origin))
    np.testing.assert_array_equal(np.asarray(got.grid.voxel_size), np.asarray(want.grid.voxel_size))
    for a, b in ((got, want), (jv.compact(got), jv.compact(want))):
        for field in FIELDS:
            x, y = np.asarray(getattr(a, field)), np.asarray(getattr(b, field))
            assert x.dtype == y.dtype and x.shape == y.shape, field
            np.testing.assert_array_equal(x, y, err_msg=field)


def _check(mesh: jv.Mesh, resolution: int, region: int, mode: str = jv.CONSERVATIVE, grid=None) -> jv.Octree:
    grid = jv.Grid.fit(mesh, resolution) if grid is None else grid
    want = jv.build_dag(jv.voxelize(mesh, grid, mode=mode))
    got = jv.mesh_to_dag(mesh, grid, mode=mode, region=region, progress=False)
    _assert_same_tree(got, want)
    return got


def _tetra(scale=1.0, shift=(0.0, 0.0, 0.0)):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32) * scale + np.float32(shift)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
    return jv.Mesh(v, f)


@pytest.mark.parametrize("name", MESHES)
def test_data_meshes_in_many_regions(meshes_dir, name):
    mesh = jv.load_mesh(meshes_dir / f"{name}.obj")
    tree = _check(mesh, 32, 8)  # up to 64 regions, 3 levels each, 2 above
    assert int(tree.voxel_count) > 0


def test_six_separating_and_deeper_regions(meshes_dir):
    bunny = jv.load_mesh(meshes_dir / "stanford-bunny.obj")
    _check(bunny, 64, 16, jv.SIX_SEPARATING)  # 4 levels per region, 2 above
    _check(jv.load_mesh(meshes_dir / "fandisk.obj"), 32, 8, jv.SIX_SEPARATING)
    _check(jv.load_mesh(meshes_dir / "teapot.obj"), 64, 32)  # 5 levels per region, 1 above


def test_one_region_tiny_regions_and_clipping(meshes_dir):
    mesh = jv.load_mesh(meshes_dir / "spot.obj")
    _check(mesh, 32, 1024)  # the region is clipped to the grid: one region, no level above it
    _check(mesh, 32, 32)
    _check(mesh, 8, 2)  # regions of one mask node each
    # a mesh larger than the grid: clipped, and the regions it only passes near are empty
    grid = jv.Grid(origin=(0.2, 0.2, 0.2), voxel_size=0.6 / 16, resolution=16)
    tree = _check(_tetra(), 16, 4, grid=grid)
    assert int(tree.voxel_count) > 0


def test_mesh_inside_one_region():
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0 / 64, resolution=64)
    small = _tetra(0.05, (0.3, 0.3, 0.3))  # voxels 19-22: inside region (16, 16, 16) of edge 8
    tree = _check(small, 64, 8, grid=grid)
    assert int(tree.voxel_count) > 0
    corner = _tetra(0.05, (0.49, 0.49, 0.49))  # voxels 31-35: across the grid's centre, eight regions
    _check(corner, 64, 8, grid=grid)


def test_empty_meshes_give_build_dags_empty_tree():
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=0.1, resolution=16)
    empty = jv.Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    for mode in (jv.CONSERVATIVE, jv.SIX_SEPARATING):
        tree = _check(empty, 16, 4, mode, grid=grid)
        assert int(tree.voxel_count) == 0 and tree.level_sizes == (0,) * 4
    outside = _tetra(1.0, (5.0, 5.0, 5.0))
    _check(outside, 16, 4, grid=grid)


@pytest.mark.parametrize("bound", [1, 2, 200, 255, 256, 1000, 70_000, 2**31, 2**32 - 1])
def test_host_unique_orders_rows_lexicographically(bound):
    rng = np.random.default_rng(bound)
    rows = rng.integers(0, bound, size=(300, 8), dtype=np.uint64).astype(np.uint32)
    rows[rng.random(rows.shape) < 0.4] = jv.EMPTY
    rows[150:] = rows[:150][rng.permutation(150)]  # every row twice
    rep, inverse = _unique_rows(rows, bound)
    unique, expected = np.unique(rows, axis=0, return_inverse=True)
    np.testing.assert_array_equal(rows[rep], unique)
    np.testing.assert_array_equal(inverse, expected.reshape(-1))


def test_bad_input_is_refused():
    mesh = _tetra()
    grid = jv.Grid.fit(mesh, 16)
    cases = [
        (dict(mesh=np.zeros((3, 3))), "mesh_to_dag mesh: expected a jaxvox.Mesh, got ndarray"),
        (dict(grid=16), "mesh_to_dag grid: expected a jaxvox.Grid, got int"),
        (dict(mode="solid"), "mesh_to_dag mode: expected one of 'conservative', '6-separating', got 'solid'"),
        (dict(region=3), "mesh_to_dag region: must be a power of two between 2 and 1024, got 3"),
        (dict(region=1), "mesh_to_dag region: must be at least 2, got 1"),
        (dict(region=2048), "mesh_to_dag region: must be at most 1024, got 2048"),
        (dict(region=8.0), "mesh_to_dag region: must be an integer, got 8.0"),
        (dict(region=True), "mesh_to_dag region: must be an integer, got True"),
    ]
    for change, message in cases:
        args = dict(mesh=mesh, grid=grid) | change
        with pytest.raises(jv.JaxvoxError) as info:
            jv.mesh_to_dag(args.pop("mesh"), args.pop("grid"), **args)
        assert str(info.value) == message
    bad = jv.Mesh(np.array([[np.nan, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]], np.int32))
    with pytest.raises(jv.JaxvoxError, match="NaN"):
        jv.mesh_to_dag(bad, grid)


def test_cli_build_streams_the_same_file(tmp_path, monkeypatch):
    from jaxvox import cli

    whole = tmp_path / "whole.jvx"
    assert cli.main(["build", "--resolution", "32", "--out", str(whole)]) == 0  # the default scene: colours
    monkeypatch.setattr(cli, "_STREAM_ABOVE", 16)
    monkeypatch.setattr(cli, "_STREAM_REGION", 16)
    streamed = tmp_path / "streamed.jvx"
    assert cli.main(["build", "--resolution", "32", "--out", str(streamed)]) == 0
    assert set(jv.load_attributes(streamed)) == {"triangle", "normal", "color"}
    assert streamed.read_bytes() == whole.read_bytes()
    # File-backed attributes: memory-mapped views, addressed by voxel_index as in memory.
    mapped, read = jv.load_attributes(streamed, mmap=True), jv.load_attributes(streamed)
    tree = jv.load(streamed)
    voxels = jv.expand(tree).to_numpy()[::7]
    index = np.asarray(jv.voxel_index(tree, voxels))
    for key, value in read.items():
        assert not mapped[key].flags.writeable and not mapped[key].flags.owndata
        np.testing.assert_array_equal(mapped[key], value)
        np.testing.assert_array_equal(mapped[key][index], value[index])
    corrupt = bytearray(streamed.read_bytes())
    corrupt[len(corrupt) // 2] ^= 1
    streamed.write_bytes(bytes(corrupt))
    with pytest.raises(jv.JaxvoxError, match="checksum"):
        jv.load_attributes(streamed, mmap=True)


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


_DISTRIBUTED = """
import sys
import jax
import numpy as np
jax.config.update("jax_cpu_collectives_implementation", "gloo")
jax.config.update("jax_num_cpu_devices", 2)  # two local devices: a thread each
jax.distributed.initialize(sys.argv[1], num_processes=int(sys.argv[2]), process_id=int(sys.argv[3]))
assert len(jax.local_devices()) == 2, jax.local_devices()
import jaxvox as jv
mesh = jv.load_mesh(sys.argv[4])
dag = jv.mesh_to_dag(mesh, jv.Grid.fit(mesh, 32), region=8, progress=False, distributed=True)
np.savez(sys.argv[5], **{f: np.asarray(getattr(dag, f)) for f in sys.argv[6].split(",")})
"""


def _run_processes(commands: list[list[str]], **environ: str) -> None:
    """Runs the commands at once (local processes, with `environ` added to this one's
    environment); every one must succeed."""
    import os
    import subprocess

    env = dict(os.environ, JAX_PLATFORMS="cpu", **environ)
    workers = [
        subprocess.Popen(c, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for c in commands
    ]
    for w in workers:
        out, err = w.communicate(timeout=600)
        assert w.returncode == 0, err[-3000:]


def test_two_processes_build_the_same_dag(meshes_dir, tmp_path):
    """`mesh_to_dag(distributed=True)` in two jax.distributed processes on this machine,
    each with two local CPU devices (a thread each): both processes end with the DAG one
    process builds from the whole voxel list (64 regions of 8^3, some empty, split four
    ways)."""
    import sys

    mesh_path = meshes_dir / "spot.obj"
    address = f"127.0.0.1:{_free_port()}"
    outs = [tmp_path / f"p{k}.npz" for k in range(2)]
    _run_processes(
        [
            [sys.executable, "-c", _DISTRIBUTED, address, "2", str(k), str(mesh_path), str(outs[k]), ",".join(FIELDS)]
            for k in range(2)
        ]
    )
    mesh = jv.load_mesh(mesh_path)
    want = jv.build_dag(jv.voxelize(mesh, jv.Grid.fit(mesh, 32)))
    for out in outs:
        got = np.load(out)
        for field in FIELDS:
            np.testing.assert_array_equal(got[field], np.asarray(getattr(want, field)), err_msg=field)


def test_cli_build_with_two_processes_writes_the_same_file(meshes_dir, tmp_path):
    """``jaxvox build --processes 2`` (two local jax.distributed processes) writes the bytes
    of the one-process, in-memory build, attributes included."""
    import sys

    from jaxvox import cli

    mesh_path = str(meshes_dir / "spot.obj")
    whole, split = tmp_path / "whole.jvx", tmp_path / "split.jvx"
    assert cli.main(["build", mesh_path, "--resolution", "32", "--out", str(whole)]) == 0
    command = [sys.executable, "-m", "jaxvox", "build", mesh_path, "--resolution", "32", "--region", "8"]
    # One CPU device per process: JAX writes its persistent compilation cache from
    # process 0 only (and process 1 found none of its entries, JAX_LOG_COMPILES), so
    # process 1 compiles every program once per local device: 24 s with two devices
    # against 10 s with one. Two devices per process, split four ways: the test above.
    _run_processes([command + ["--processes", "2", "--out", str(split)]], JAX_NUM_CPU_DEVICES="1")
    assert split.read_bytes() == whole.read_bytes()
    with pytest.raises(SystemExit):
        cli.main(["build", mesh_path, "--processes", "two"])
    assert cli.main(["build", mesh_path, "--kind", "octree", "--processes", "2", "--out", str(split)]) == 2


def test_attributes_go_to_files_region_by_region(meshes_dir, tmp_path):
    """``mesh_to_dag(..., attributes=folder)``: the same DAG, and attributes written region
    by region as read-only memmaps equal to `voxel_attributes` of the whole voxel list
    (spot has colours); `voxel_index` addresses them; each file holds zero rows up to the
    voxel-list ladder, which the renderer's tables take without a copy (a plain array of
    the same rows is copied); a missing or used folder is refused."""
    mesh = jv.load_mesh(meshes_dir / "spot.obj")
    grid = jv.Grid.fit(mesh, 64)
    vox = jv.voxelize(mesh, grid, triangle_ids=True)
    want = jv.voxel_attributes(mesh, vox)
    dag, attributes = jv.mesh_to_dag(mesh, grid, region=16, progress=False, attributes=tmp_path)
    _assert_same_tree(dag, jv.build_dag(vox))
    assert set(attributes) == set(want) == {"triangle", "normal", "color"}
    index = np.asarray(jv.voxel_index(dag, vox.to_numpy()))
    for key, value in attributes.items():
        assert isinstance(value, np.memmap) and not value.flags.writeable
        np.testing.assert_array_equal(value, np.asarray(want[key])[: int(vox.count)], err_msg=key)
        np.testing.assert_array_equal(value[index], np.asarray(want[key])[: int(vox.count)], err_msg=key)
        capacity = voxel_bucket(int(vox.count), grid.resolution)
        whole = np.fromfile(tmp_path / key, value.dtype).reshape((-1,) + value.shape[1:])
        assert len(whole) == capacity > len(value) and not whole[len(value) :].any(), key
    table = normal_table("normals", attributes["normal"], int(vox.count), grid.resolution)
    assert table.shape == (capacity, 3) and np.shares_memory(table, attributes["normal"])
    copied = normal_table("normals", np.array(attributes["normal"]), int(vox.count), grid.resolution)
    np.testing.assert_array_equal(copied, table)
    assert not np.shares_memory(copied, attributes["normal"])
    with pytest.raises(jv.JaxvoxError, match="already holds"):
        jv.mesh_to_dag(mesh, grid, attributes=tmp_path)
    with pytest.raises(jv.JaxvoxError, match="existing folder"):
        jv.mesh_to_dag(mesh, grid, attributes=tmp_path / "missing")
