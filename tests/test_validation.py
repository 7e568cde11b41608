"""Validation at the door: the bad inputs users reported each get one clear `JaxvoxError`
of the form ``"<what>: <why>, got <value>"`` (the fuzzed version is `test_fuzz.py`)."""

from __future__ import annotations

import numpy as np
import pytest

import jaxvox as jv
from jaxvox import sdf

V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
GRID = jv.Grid(np.zeros(3), 0.1, 16)

BAD = {
    "voxel size 0": (lambda: jv.Grid(np.zeros(3), 0.0, 16), "Grid voxel_size: must be one finite number > 0, got 0.0"),
    "voxel size -1": (lambda: jv.Grid(np.zeros(3), -1.0, 16), "Grid voxel_size"),
    "voxel size nan": (lambda: jv.Grid(np.zeros(3), np.nan, 16), "got nan"),
    "voxel size inf": (lambda: jv.Grid(np.zeros(3), np.inf, 16), "got inf"),
    "voxel size below float32": (lambda: jv.Grid(np.zeros(3), 1e-50, 16), "Grid voxel_size"),
    "origin with a NaN": (lambda: jv.Grid([0.0, np.nan, 0.0], 1.0, 16), "Grid origin: must be three finite numbers"),
    "origin with two values": (
        lambda: jv.Grid([0.0, 0.0], 1.0, 16),
        "Grid origin: must be three finite numbers, got [0.0, 0.0]",
    ),
    "resolution 3": (lambda: jv.Grid(np.zeros(3), 1.0, 3), "resolution: must be a power of two"),
    "resolution 2^21": (lambda: jv.Grid(np.zeros(3), 1.0, 2**21), "resolution"),
    "resolution 16.5": (lambda: jv.Grid(np.zeros(3), 1.0, 16.5), "got 16.5"),
    "fit padding -1": (lambda: jv.Grid.fit(jv.Mesh(V, F), 16, padding=-1.0), "Grid.fit padding"),
    "face 2.5": (lambda: jv.Mesh(V, F + 0.5), "Mesh faces: must hold integer vertex indices, got 0.5"),
    "face index 7": (lambda: jv.voxelize(jv.Mesh(V, np.array([[0, 1, 7]])), GRID), "index out of range"),
    "string vertices": (lambda: jv.Mesh([["a", "b", "c"]], F), "Mesh vertices: must be an array of numbers"),
    "colour 1.5": (
        lambda: jv.voxelize(jv.Mesh(V, F, colors=np.full((4, 3), 1.5)), GRID),
        "Mesh colors: must lie in [0, 1]",
    ),
    "not a grid": (lambda: jv.voxelize(jv.Mesh(V, F), 16), "voxelize grid: expected a jaxvox.Grid, got int"),
    "not a mesh": (lambda: jv.voxelize(V, GRID), "mesh: expected a jaxvox.Mesh, got ndarray"),
    "unknown mode": (lambda: jv.voxelize(jv.Mesh(V, F), GRID, mode="26"), "voxelize mode: expected one of"),
    "trace t_max text": (
        lambda: jv.trace(jv.build_dag(jv.voxelize(jv.Mesh(V, F), GRID)), V[:1], V[1:2], t_max="far"),
        "trace t_max: must be numbers",
    ),
    "rays of 2 numbers": (
        lambda: jv.trace(jv.build_dag(jv.voxelize(jv.Mesh(V, F), GRID)), V[:1, :2], V[1:2]),
        "trace origins: must have shape [..., 3]",
    ),
    "expand capacity -1": (
        lambda: jv.expand(jv.build_dag(jv.voxelize(jv.Mesh(V, F), GRID)), capacity=-1),
        "expand capacity: must be at least 1",
    ),
    "camera eye = target": (
        lambda: jv.pinhole_rays(np.zeros(3), np.zeros(3), width=4, height=4),
        "must differ from the eye",
    ),
    "camera up parallel": (lambda: jv.pinhole_rays([0.0, -3.0, 0.0], np.zeros(3), width=4, height=4), "parallel"),
    "camera fov 180": (
        lambda: jv.pinhole_rays([0.0, 0.0, -3.0], np.zeros(3), width=4, height=4, fov=180.0),
        "pinhole_rays fov: must be < 180",
    ),
    "image width 0": (
        lambda: jv.pinhole_rays([0.0, 0.0, -3.0], np.zeros(3), width=0, height=4),
        "width: must be at least 1",
    ),
    "field of the wrong shape": (lambda: jv.quantize_field(np.zeros((8, 8, 8)), GRID), "quantize_field field"),
    "albedo above 1": (lambda: jv.voxel_albedo({}, default=(2.0, 0.0, 0.0)), "voxel_albedo default"),
    "negative frame": (lambda: jv.time_sliced_cascades(-1, 3), "time_sliced_cascades frame"),
    "clipmap voxel size 0": (
        lambda: jv.build_clipmap(jv.Mesh(V, F), np.zeros(3), resolution=8, num_cascades=2, voxel_size=0.0),
        "Grid voxel_size",
    ),
    "sphere radius NaN": (lambda: sdf.sphere(np.nan), "got nan"),
    "float PNG": (lambda: jv.write_png("/tmp/never.png", np.full((2, 2, 3), 0.5)), "write_png rgb"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_is_refused_with_a_clear_message(case):
    call, message = BAD[case]
    with pytest.raises(jv.JaxvoxError) as info:
        call()
    text = str(info.value)
    assert message in text and ", got " in text, text


def test_output_paths_are_checked_before_writing(tmp_path):
    tree = jv.build_dag(jv.voxelize(jv.Mesh(V, F), GRID))
    for write in (
        lambda p: jv.save(p, tree),
        lambda p: jv.save_voxels(p, jv.expand(tree)),
        lambda p: jv.write_png(p, np.zeros((2, 2), np.uint8)),
    ):
        with pytest.raises(jv.JaxvoxError, match="does not exist"):
            write(tmp_path / "missing" / "file.npz")
        with pytest.raises(jv.JaxvoxError, match="is a directory|extension: expected one of"):
            write(tmp_path)
    with pytest.raises(jv.JaxvoxError, match="enable_compilation_cache path: cannot create the folder"):
        (tmp_path / "file").write_text("")
        jv.enable_compilation_cache(path=tmp_path / "file")


def test_traced_values_pass_and_report_by_status():
    """Inside jit the checks cannot see values: a NaN ray is an INVALID item, not an error."""
    import jax

    tree = jv.build_dag(jv.voxelize(jv.Mesh(V, F), GRID))
    origins = np.array([[0.05, 0.05, -1.0], [np.nan, 0.0, 0.0]], np.float32)
    directions = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], np.float32)
    hit = jax.jit(lambda o, d: jv.trace(tree, o, d))(origins, directions)
    assert list(np.asarray(hit.status)) == [jv.HIT, jv.INVALID]
    grid = jax.jit(lambda h: jv.Grid(np.zeros(3), h, 16).voxel_size)(0.0)  # traced: no check
    assert float(grid) == 0.0
