"""Voxel files (binvox, npz, PLY / OBJ surfaces), `voxels_to_mesh` and `jaxvox voxelize --out`.

Binvox is checked against trimesh's reader and writer and against the layout of the
binvox specification (y fastest, then z, then x), written out by hand; surfaces against a
dense numpy grid (exposed faces counted with `np.diff`) and trimesh's watertightness.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import jaxvox as jv
from jaxvox.cli import main

H = 0.25  # voxel size of the hand-made grids
ORIGIN = (0.5, -1.0, 2.0)


def _grid(resolution: int) -> jv.Grid:
    return jv.Grid(ORIGIN, H, resolution)


def _voxels(ijk, resolution: int = 8, **kw) -> jv.Voxels:
    return jv.Voxels.from_coords(np.asarray(ijk, np.int64).reshape(-1, 3), _grid(resolution), **kw)


def _random_voxels(seed: int, resolution: int) -> jv.Voxels:
    rng = np.random.default_rng(seed)
    occupied = rng.random((resolution,) * 3) < rng.uniform(0.1, 0.9)
    return _voxels(np.argwhere(occupied), resolution)


def _index_set(ijk) -> set:
    return set(map(tuple, np.asarray(ijk).tolist()))


def _exposed_faces(ijk: np.ndarray, resolution: int) -> int:
    """Reference: faces between an occupied and an empty cell of a dense grid with an empty border."""
    dense = np.zeros((resolution + 2,) * 3, np.int8)
    dense[tuple((ijk + 1).T)] = 1
    return sum(int(np.count_nonzero(np.diff(dense, axis=a))) for a in range(3))


def _vertex_links_are_cycles(faces: np.ndarray, num_vertices: int) -> bool:
    """Every vertex is used, and the far edges of its triangles form one directed cycle (a disk)."""
    after: dict[int, dict[int, int]] = {}
    for tri in faces.tolist():
        for k in range(3):
            a, b, c = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
            link = after.setdefault(a, {})
            if b in link:
                return False  # two triangles leave `a` along the same directed edge
            link[b] = c
    for link in after.values():
        start = cur = next(iter(link))
        for steps in range(1, len(link) + 1):
            cur = link.get(cur)
            if cur is None or cur == start:
                break
        if cur != start or steps != len(link):
            return False
    return len(after) == num_vertices


def _check_closed_surface(mesh: jv.Mesh, ijk: np.ndarray, grid: jv.Grid) -> trimesh.Trimesh:
    """The properties a surface of voxels must have, against the dense reference."""
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    t = trimesh.Trimesh(v, f, process=False)
    h = float(grid.voxel_size)
    assert t.is_watertight and t.is_winding_consistent
    assert _vertex_links_are_cycles(f, len(v))
    assert t.area_faces.min() > 0
    np.testing.assert_allclose(t.area, _exposed_faces(ijk, grid.resolution) * h * h, rtol=1e-5)
    np.testing.assert_allclose(t.volume, len(ijk) * h**3, rtol=1e-5)  # positive: faces turn outwards
    corners = (v - np.asarray(grid.origin)) / h
    np.testing.assert_allclose(corners * 2, np.round(corners * 2), atol=1e-3)  # corners, edge and face midpoints
    return t


@pytest.fixture(scope="module")
def spot(meshes_dir):
    """(mesh, conservative voxels at 32^3) of the watertight test `spot` mesh."""
    mesh = jv.load_mesh(meshes_dir / "spot.obj")
    return mesh, jv.voxelize(mesh, jv.Grid.fit(mesh, 32))


# ------------------------------------------------------------------------------ binvox


def test_binvox_layout_follows_the_specification(tmp_path):
    """Voxel (i, j, k) is bit (i * R + k) * R + j of the dense grid, in runs of (value, count)."""
    path = tmp_path / "two.binvox"
    jv.save_binvox(path, _voxels([[1, 0, 0], [0, 1, 0]], 2))  # linear 4 and 1 of 8
    data = path.read_bytes()
    header = b"#binvox 1\ndim 2 2 2\ntranslate 0.5 -1.0 2.0\nscale 0.5\ndata\n"
    assert data == header + bytes([0, 1, 1, 1, 0, 2, 1, 1, 0, 3])
    back = jv.load_binvox(path)
    assert _index_set(back.to_numpy()) == {(1, 0, 0), (0, 1, 0)}


@pytest.mark.parametrize("seed", [0, 1])
def test_binvox_written_by_jaxvox_reads_in_trimesh(tmp_path, seed):
    vox = _random_voxels(seed, 16)
    path = tmp_path / "random.binvox"
    jv.save_binvox(path, vox)
    with open(path, "rb") as fh:
        parsed = trimesh.exchange.binvox.parse_binvox(fh)
    np.testing.assert_array_equal(parsed.shape, [16, 16, 16])
    np.testing.assert_allclose(parsed.translate, ORIGIN)
    assert parsed.scale == 16 * H
    with open(path, "rb") as fh:
        grid = trimesh.exchange.binvox.load_binvox(fh)
    assert _index_set(np.argwhere(grid.encoding.dense)) == _index_set(vox.to_numpy())


def test_binvox_written_by_trimesh_reads_in_jaxvox(tmp_path):
    dense = np.random.default_rng(2).random((16, 16, 16)) < 0.3
    path = tmp_path / "trimesh.binvox"
    path.write_bytes(trimesh.exchange.binvox.export_binvox(trimesh.voxel.VoxelGrid(dense)))
    vox = jv.load_binvox(path)
    assert _index_set(vox.to_numpy()) == _index_set(np.argwhere(dense))
    assert vox.grid.resolution == 16 and vox.mode == jv.CONSERVATIVE
    # trimesh writes scale = pitch * (R - 1) (its voxel centres span the scale); binvox's is R * h.
    assert float(vox.grid.voxel_size) == np.float32(15 / 16)
    for tree in (jv.build_octree(vox), jv.build_dag(vox)):
        assert int(tree.voxel_count) == int(dense.sum())
        np.testing.assert_array_equal(jv.expand(tree).to_numpy(), vox.to_numpy())


def test_binvox_runs_longer_than_255_and_empty_sets(tmp_path):
    block = np.argwhere(np.ones((8, 8, 8), bool))  # one run of 512 ones in a 32^3 grid
    for ijk in (block, block[:0], [[31, 31, 31]]):
        vox = _voxels(ijk, 32)
        path = tmp_path / "runs.binvox"
        jv.save_binvox(path, vox)
        runs = np.frombuffer(path.read_bytes().split(b"data\n", 1)[1], np.uint8)
        assert runs[1::2].min() >= 1 and runs[1::2].sum() == 32**3
        with open(path, "rb") as fh:
            dense = trimesh.exchange.binvox.load_binvox(fh).encoding.dense
        assert _index_set(np.argwhere(dense)) == _index_set(vox.to_numpy())
        np.testing.assert_array_equal(jv.load_binvox(path).to_numpy(), vox.to_numpy())


def test_binvox_sparse_at_high_resolution(tmp_path):
    """A few voxels at 1024^3 round-trip through runs alone (about 8 MiB of zero runs)."""
    ijk = [[0, 0, 0], [1023, 0, 5], [512, 700, 1023]]
    path = tmp_path / "sparse.binvox"
    jv.save_binvox(path, _voxels(ijk, 1024))
    back = jv.load_binvox(path)
    assert back.grid.resolution == 1024 and _index_set(back.to_numpy()) == _index_set(ijk)
    with pytest.raises(jv.JaxvoxError, match="save as .npz"):
        jv.save_binvox(tmp_path / "huge.binvox", _voxels(ijk, 1 << 20))


def test_binvox_odd_dims_are_padded_to_a_power_of_two(tmp_path):
    path = tmp_path / "three.binvox"
    path.write_bytes(b"#binvox 1\ndim 3 3 3\ntranslate 1 2 3\nscale 0.75\ndata\n" + bytes([0, 26, 1, 1]))
    vox = jv.load_binvox(path, mode=jv.SIX_SEPARATING)
    assert vox.grid.resolution == 4 and vox.mode == jv.SIX_SEPARATING
    assert float(vox.grid.voxel_size) == 0.25
    np.testing.assert_array_equal(np.asarray(vox.grid.origin), [1, 2, 3])
    assert _index_set(vox.to_numpy()) == {(2, 2, 2)}


def _binvox(body: bytes = b"", dims: bytes = b"2 2 2") -> bytes:
    return b"#binvox 1\ndim " + dims + b"\ntranslate 0 0 0\nscale 1\ndata\n" + body


@pytest.mark.parametrize(
    "content, message",
    [
        (None, "file not found"),
        (b"", "empty"),
        (b"ply\nformat ascii 1.0\n", "not a binvox file"),
        (b"#binvox 1\ndim 2 2 2\n", "'data' line"),
        (_binvox(bytes([0, 4, 1])), "odd length"),
        (_binvox(bytes([0, 4, 1, 3])), "truncated"),
        (_binvox(), "truncated"),
        (_binvox(bytes([0, 255, 1, 3])), "too much data"),
        (_binvox(bytes([0, 8]), b"2 2 4"), "cubic"),
        (_binvox(bytes([0, 8]), b"2 x 2"), "bad binvox header line"),
        (b"#binvox 1\ntranslate 0 0 0\ndata\n", "no 'dim'"),
        (b"#binvox 1\ndim 2 2 2\ncolour 1\ndata\n", "unknown binvox header"),
    ],
)
def test_bad_binvox_files_are_refused_by_name(tmp_path, content, message):
    path = tmp_path / "bad.binvox"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(jv.JaxvoxError, match=message) as err:
        jv.load_binvox(path)
    assert str(path) in str(err.value)


def test_a_directory_is_refused(tmp_path):
    folder = tmp_path / "folder.binvox"
    folder.mkdir()
    for load in (jv.load_binvox, jv.load_voxels):
        with pytest.raises(jv.JaxvoxError, match="is a directory") as err:
            load(folder)
        assert str(folder) in str(err.value)


# ------------------------------------------------------------------------------ npz and dispatch


def test_every_format_round_trips(tmp_path, spot):
    _, vox = spot
    surface = jv.voxels_to_mesh(vox)
    for ext in (".binvox", ".npz", ".ply", ".obj", ".PLY"):
        path = tmp_path / f"spot{ext}"
        jv.save_voxels(path, vox)
        assert [p.name for p in tmp_path.iterdir()] == [path.name]  # exactly this name
        if ext in (".binvox", ".npz"):
            back = jv.load_voxels(path)
            np.testing.assert_array_equal(back.to_numpy(), vox.to_numpy())
            np.testing.assert_array_equal(np.asarray(back.grid.origin), np.asarray(vox.grid.origin))
            assert float(back.grid.voxel_size) == float(vox.grid.voxel_size)
            assert back.grid.resolution == vox.grid.resolution and back.capacity == vox.capacity
        else:
            back = jv.load_mesh(path)
            np.testing.assert_array_equal(np.asarray(back.faces), np.asarray(surface.faces))
            np.testing.assert_allclose(np.asarray(back.vertices), np.asarray(surface.vertices), atol=1e-7)
        path.unlink()


def test_npz_keeps_the_mode(tmp_path):
    vox = _random_voxels(3, 8)
    vox = jv.Voxels.from_coords(vox.to_numpy(), vox.grid, mode=jv.SIX_SEPARATING)
    path = tmp_path / "v.npz"
    jv.save_voxels(path, vox)
    with np.load(path) as npz:
        assert sorted(npz.files) == ["ijk", "mode", "origin", "resolution", "voxel_size"]
        assert npz["ijk"].dtype == np.int32 and str(npz["mode"]) == jv.SIX_SEPARATING
    back = jv.load_voxels(path)
    assert back.mode == jv.SIX_SEPARATING
    np.testing.assert_array_equal(back.to_numpy(), vox.to_numpy())


@pytest.mark.parametrize(
    "change, message",
    [
        (None, "file not found"),
        (b"", "empty"),
        (b"hello", "zip signature"),
        (b"PK\x03\x04 and then nothing", "not a readable .npz"),
        ({"ijk": None}, "lacks the arrays ijk"),
        ({"ijk": [[0, 0, 8]]}, "outside"),
        ({"mode": "solid"}, "holds mode"),
        ({"resolution": 100}, "power of two"),
    ],
)
def test_bad_npz_files_are_refused_by_name(tmp_path, change, message):
    path = tmp_path / "bad.npz"
    if isinstance(change, bytes):
        path.write_bytes(change)
    elif change is not None:
        arrays = {"ijk": [[0, 0, 0]], "origin": ORIGIN, "voxel_size": H, "resolution": 8, "mode": "conservative"}
        arrays.update(change)
        np.savez(path, **{k: v for k, v in arrays.items() if v is not None})
    with pytest.raises(jv.JaxvoxError, match=message) as err:
        jv.load_voxels(path)
    assert str(path) in str(err.value)


def test_unknown_extensions_are_refused(tmp_path):
    vox = _voxels([[0, 0, 0]])
    with pytest.raises(jv.JaxvoxError, match=r"expected one of '\.binvox', '\.npz', '\.ply', '\.obj', got '\.xyz'"):
        jv.save_voxels(tmp_path / "v.xyz", vox)
    with pytest.raises(jv.JaxvoxError, match=r"expected one of '\.binvox', '\.npz', got '\.ply'"):
        jv.load_voxels(tmp_path / "v.ply")
    with pytest.raises(jv.JaxvoxError, match=r"expected one of '\.ply', '\.obj', got '\.stl'"):
        jv.save_mesh(tmp_path / "m.stl", jv.voxels_to_mesh(vox))
    with pytest.raises(jv.JaxvoxError, match="does not exist"):
        jv.save_voxels(tmp_path / "no" / "v.npz", vox)
    assert list(tmp_path.iterdir()) == []


def test_save_mesh_writes_colours(tmp_path):
    mesh = jv.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], colors=[[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    for ext in (".ply", ".obj"):
        jv.save_mesh(tmp_path / f"tri{ext}", mesh)
        back = jv.load_mesh(tmp_path / f"tri{ext}")
        np.testing.assert_allclose(np.asarray(back.colors)[:, :3], np.asarray(mesh.colors))
    assert (tmp_path / "tri.ply").read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")


# ------------------------------------------------------------------------------ voxels_to_mesh


def test_single_voxel_is_a_cube():
    mesh = jv.voxels_to_mesh(_voxels([[3, 0, 7]]))
    assert mesh.num_vertices == 8 and mesh.num_faces == 12
    corners = np.asarray(ORIGIN) + H * (np.array([3, 0, 7]) + np.argwhere(np.ones((2, 2, 2))))
    assert _index_set(np.round(np.asarray(mesh.vertices) / H * 4)) == _index_set(np.round(corners / H * 4))
    t = _check_closed_surface(mesh, np.array([[3, 0, 7]]), _grid(8))
    np.testing.assert_allclose(t.volume, H**3, rtol=1e-6)
    assert t.euler_number == 2


@pytest.mark.parametrize(
    "other, vertices, triangles, euler",
    [
        ((2, 1, 1), 12, 20, 2),  # sharing a face: it is removed, its corners welded
        ((2, 2, 1), 22, 36, 4),  # sharing an edge: two cubes, the edge split with one midpoint each
        ((2, 2, 2), 16, 24, 4),  # sharing a corner: two cubes, the corner not welded
    ],
)
def test_two_voxels(other, vertices, triangles, euler):
    ijk = np.array([[1, 1, 1], other])
    mesh = jv.voxels_to_mesh(_voxels(ijk))
    assert (mesh.num_vertices, mesh.num_faces) == (vertices, triangles)
    assert _check_closed_surface(mesh, ijk, _grid(8)).euler_number == euler


def test_voxels_touching_along_an_edge_inside_one_surface():
    """Two voxels meeting along an edge between two full layers: at both ends of that edge
    the surface has one vertex, so only the midpoints keep the edge's two copies apart.
    The empty cells beside the edge join through it: a handle (Euler characteristic 0)."""
    ijk = np.array(
        [[3, 3, 3], [4, 4, 3], [3, 3, 4], [4, 4, 4], [3, 4, 4], [4, 3, 4], [3, 3, 2], [4, 4, 2], [3, 4, 2], [4, 3, 2]]
    )
    mesh = jv.voxels_to_mesh(_voxels(ijk))
    assert _check_closed_surface(mesh, ijk, _grid(8)).euler_number == 0
    units = (np.asarray(mesh.vertices) - np.asarray(ORIGIN, np.float32)) / H
    count = lambda point: int((np.abs(units - point) < 1e-4).all(axis=1).sum())
    assert count((4, 4, 3)) == count((4, 4, 4)) == 1 and count((4, 4, 3.5)) == 2


def test_ring_has_genus_one():
    ijk = np.array([[x, y, 0] for x in range(3) for y in range(3) if (x, y) != (1, 1)])
    t = _check_closed_surface(jv.voxels_to_mesh(_voxels(ijk, 4)), ijk, _grid(4))
    assert t.euler_number == 0


def test_empty_voxels_give_an_empty_mesh(tmp_path):
    empty = _voxels(np.zeros((0, 3)))
    mesh = jv.voxels_to_mesh(empty)
    assert mesh.vertices.shape == (0, 3) and mesh.faces.shape == (0, 3)
    for ext in (".binvox", ".npz"):
        jv.save_voxels(tmp_path / f"empty{ext}", empty)
        assert int(jv.load_voxels(tmp_path / f"empty{ext}").count) == 0


@pytest.mark.parametrize("seed", range(6))
def test_random_voxel_sets_give_closed_manifold_surfaces(seed):
    """Random sets (many edge- and corner-only contacts, voxels on the grid's boundary)."""
    resolution = 4 if seed % 2 else 8
    vox = _random_voxels(seed, resolution)
    _check_closed_surface(jv.voxels_to_mesh(vox), vox.to_numpy(), vox.grid)


def test_surface_of_a_closed_mesh_is_watertight_as_ply(tmp_path, spot, meshes_dir):
    _, vox = spot
    bunny = jv.load_mesh(meshes_dir / "stanford-bunny.obj")
    for voxels in (vox, jv.voxelize(bunny, jv.Grid.fit(bunny, 32))):
        jv.save_voxels(tmp_path / "surface.ply", voxels)
        back = jv.load_mesh(tmp_path / "surface.ply")
        t = _check_closed_surface(back, voxels.to_numpy(), voxels.grid)
        assert t.is_volume


# ------------------------------------------------------------------------------ command line


def test_cli_voxelize_writes_each_format(tmp_path, capsys, meshes_dir):
    mesh = str(meshes_dir / "spot.obj")
    for ext in (".binvox", ".npz", ".ply", ".obj"):
        out = tmp_path / f"spot{ext}"
        assert main(["voxelize", mesh, "--resolution", "32", "--out", str(out)]) == 0
        assert capsys.readouterr().out.rstrip().endswith(f"wrote {out}")
        if ext in (".binvox", ".npz"):
            assert int(jv.load_voxels(out).count) > 0
        else:
            assert trimesh.load(out, process=False).is_watertight
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"spot{e}" for e in (".binvox", ".npz", ".ply", ".obj"))


def test_cli_refuses_an_unknown_extension_before_voxelizing(tmp_path, capsys, monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("voxelized before checking --out")

    monkeypatch.setattr(jv, "voxelize", fail)
    assert main(["voxelize", "--resolution", "32", "--out", str(tmp_path / "v.xyz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out extension" in err[0] and ".binvox" in err[0] and "'.xyz'" in err[0]
    assert list(tmp_path.iterdir()) == []
