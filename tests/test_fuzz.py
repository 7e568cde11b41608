"""The public API, fuzzed: every call on generated bad or edge input either returns a valid
result or raises `JaxvoxError`; any other exception, a crash, a NaN where the result
promises none, or an invalid status fails the test.

Inputs: NaN, inf and huge or tiny numbers anywhere; empty, single-element and wrongly
shaped arrays; wrong dtypes and types; resolutions at and beyond the limits; corrupt,
truncated, empty and directory "files". Each test counts its cases in `CASES` (printed
at the end with ``pytest -s``). The examples are derandomized so that CI is repeatable;
``JAXVOX_FUZZ_EXAMPLES=N`` runs N random examples per test instead.
"""

from __future__ import annotations

import collections
import os

import hypothesis.extra.numpy as hnp
import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxvox as jv
from jaxvox import sdf

CASES: collections.Counter = collections.Counter()
_EXAMPLES = int(os.environ.get("JAXVOX_FUZZ_EXAMPLES", "0"))


def fuzz(examples: int):
    """Hypothesis settings for a fuzz test: `examples` derandomized cases (or $JAXVOX_FUZZ_EXAMPLES random ones)."""
    return settings(
        max_examples=_EXAMPLES or examples,
        derandomize=not _EXAMPLES,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.function_scoped_fixture],
    )


def attempt(name: str, call, check=lambda result: None):
    """Runs `call`; a `JaxvoxError` is a valid answer, otherwise `check(result)` must pass."""
    CASES[name] += 1
    try:
        result = jax.block_until_ready(call())
    except jv.JaxvoxError as exc:
        CASES[f"{name} refused"] += 1
        assert str(exc) and ", got " in str(exc) or "overflow" in str(exc), str(exc)
        return None
    check(result)
    return result


@pytest.fixture(scope="module", autouse=True)
def _report():
    yield
    print("\nfuzzed cases:", sum(v for k, v in CASES.items() if not k.endswith("refused")))
    for name in sorted(k for k in CASES if not k.endswith("refused")):
        print(f"  {name}: {CASES[name]} cases, {CASES[name + ' refused']} refused")


SPECIAL = [0.0, -0.0, 1.0, -1.0, 0.5, 1e-30, -1e-30, 1e-45, 1e30, -1e30, 3.4e38, np.nan, np.inf, -np.inf]
reals = st.one_of(st.sampled_from(SPECIAL), st.floats(-4, 4, width=32))
junk = st.sampled_from([None, "abc", "", [], [[1, 2]], {}, (1, 2), True, b"xyz", object()])


def arrays(shapes, dtypes=(np.float32, np.float64, np.int32), elements=reals):
    """Arrays of the given shapes and dtypes filled with special values (cast by dtype)."""

    def build(shape, dtype):
        if np.issubdtype(dtype, np.integer):
            return hnp.arrays(dtype, shape, elements=st.integers(-3, 9) | st.sampled_from([-(2**31), 2**31 - 1]))
        return hnp.arrays(dtype, shape, elements=elements.map(lambda x: float(np.asarray(x, dtype))))

    return st.tuples(st.sampled_from(shapes), st.sampled_from(dtypes)).flatmap(lambda sd: build(*sd))


finite3 = hnp.arrays(np.float32, 3, elements=st.floats(-4, 4, width=32))
vectors3 = st.one_of(finite3, arrays([(3,)]), arrays([(), (2,), (4,), (1, 3), (0,)]), junk)
resolutions = st.one_of(
    st.sampled_from([2, 16, 2**20, 2**21, 1, 0, -16, 3, 24]),
    st.integers(-8, 64),
    st.sampled_from([16.0, 16.5, np.int64(16), np.float32(16), "16"]),
    junk,
)


def _tetra():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32) * 0.6 + 0.2
    return jv.Mesh(v, np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32))


GRID = jv.Grid(np.zeros(3), 1.0 / 16, 16)


@pytest.fixture(scope="module")
def tree():
    return jv.build_dag(jv.voxelize(_tetra(), GRID))


def _valid_voxels(vox: jv.Voxels) -> None:
    ijk = vox.to_numpy()
    assert int(vox.overflow) == 0 and len(ijk) == int(vox.count)
    assert ((ijk >= 0) & (ijk < vox.grid.resolution)).all()
    codes = [tuple(c) for c in ijk]
    assert len(set(codes)) == len(codes)


# ------------------------------------------------------------------------- grid, mesh


@fuzz(150)
@given(
    origin=st.one_of(finite3, vectors3),
    voxel_size=st.one_of(st.floats(1e-6, 1e6), reals, arrays([(), (1,), (2,)]), junk),
    resolution=resolutions,
)
def test_grid(origin, voxel_size, resolution):
    def check(g):
        o, h = np.asarray(g.origin), float(g.voxel_size)
        assert o.shape == (3,) and np.isfinite(o).all() and np.isfinite(h) and h > 0
        assert g.resolution >= 2 and g.resolution & (g.resolution - 1) == 0

    attempt("Grid", lambda: jv.Grid(origin, voxel_size, resolution), check)


# Geometry: mostly inside the grid, on voxel planes (multiples of 1/16) or anywhere, so that
# degenerate, sliver and plane-aligned triangles come up; or with the special values.
coordinates = st.one_of(st.integers(-2, 18).map(lambda k: k / 16), st.floats(-0.25, 1.25, width=32))
axial_or_any = st.sampled_from([0.0, 1.0, -1.0, 1e-30]) | st.floats(-1, 1, width=32)  # axis-aligned, grazing
vertex_arrays = st.one_of(
    arrays([(3, 3), (4, 3), (6, 3)], dtypes=(np.float32,), elements=coordinates),
    arrays([(0, 3), (1, 3), (3, 3), (4, 3), (6, 3)]),
    arrays([(3,), (4, 2), (2, 3, 3)]),
    junk,
)
face_arrays = st.one_of(
    arrays([(0, 3), (1, 3), (2, 3), (4, 3)], dtypes=(np.int32, np.int64)),
    hnp.arrays(np.int32, st.sampled_from([(1, 3), (4, 3)]), elements=st.integers(0, 2)),
    arrays([(1, 3), (2, 3)], dtypes=(np.float32,), elements=st.sampled_from([0.0, 1.0, 2.5, np.nan])),
    arrays([(3,), (2, 4)], dtypes=(np.int32,)),
    junk,
)


@fuzz(120)
@given(
    vertices=vertex_arrays,
    faces=face_arrays,
    mode=st.sampled_from(["conservative", "6-separating", "26"]),
    scale=st.sampled_from([1.0, 1e-30, 1e30, -1.0]),
)
def test_mesh_voxelize_and_fit(vertices, faces, mode, scale):
    def make():
        return jv.Mesh(
            np.asarray(vertices, np.float64) * scale if isinstance(vertices, np.ndarray) else vertices, faces
        )

    mesh = attempt("Mesh", make)
    if mesh is None:
        return
    attempt("voxelize", lambda: jv.voxelize(mesh, GRID, mode=mode), _valid_voxels)

    def check_grid(g):
        assert np.isfinite(np.asarray(g.origin)).all() and float(g.voxel_size) > 0

    attempt("Grid.fit", lambda: jv.Grid.fit(mesh, 16), check_grid)


@fuzz(60)
@given(
    colors=st.one_of(
        st.none(),
        hnp.arrays(np.float32, st.sampled_from([(4, 3), (4, 4)]), elements=st.floats(0, 1)),
        arrays([(4, 3), (4, 4), (4, 2), (3, 3)]),
        junk,
    ),
    uvs=st.one_of(st.none(), hnp.arrays(np.float32, (4, 2), elements=st.floats(-2, 2)), arrays([(4, 2), (4, 3)])),
    texture=st.one_of(
        st.none(),
        hnp.arrays(np.float32, (2, 2, 3), elements=st.floats(0, 1)),
        arrays([(2, 2, 3), (2, 2, 5), (0, 2, 3)]),
    ),
)
def test_mesh_attributes(colors, uvs, texture):
    base = _tetra()
    mesh = attempt(
        "Mesh with attributes", lambda: jv.Mesh(base.vertices, base.faces, colors=colors, uvs=uvs, texture=texture)
    )
    if mesh is not None:
        vox = attempt("voxelize with attributes", lambda: jv.voxelize(mesh, GRID, triangle_ids=True), _valid_voxels)
        if vox is not None:

            def check(attributes):
                for value in attributes.values():
                    value = np.asarray(value)
                    assert not (value.dtype.kind == "f" and np.isnan(value[: int(vox.count)]).any())

            attempt("voxel_attributes", lambda: jv.voxel_attributes(mesh, vox), check)


# -------------------------------------------------------------------- trees and rays


@fuzz(80)
@given(
    ijk=st.one_of(
        hnp.arrays(np.int32, st.sampled_from([(1, 3), (5, 3), (40, 3)]), elements=st.integers(0, 15)),
        arrays([(0, 3), (1, 3), (5, 3)], dtypes=(np.int32, np.int64)),
        arrays([(2, 3)], dtypes=(np.float32,)),
        arrays([(3,), (2, 2)], dtypes=(np.int32,)),
        junk,
    ),
    resolution=st.sampled_from([2, 16]),
    dag=st.booleans(),
)
def test_build_and_expand(ijk, resolution, dag):
    grid = jv.Grid(np.zeros(3), 1.0, resolution)
    vox = attempt("Voxels.from_coords", lambda: jv.Voxels.from_coords(ijk, grid), _valid_voxels)
    if vox is None:
        return
    built = attempt("build_dag" if dag else "build_octree", lambda: (jv.build_dag if dag else jv.build_octree)(vox))
    back = attempt("expand", lambda: jv.expand(built))
    np.testing.assert_array_equal(back.to_numpy(), vox.to_numpy())


@fuzz(100)
@given(
    origins=st.one_of(
        hnp.arrays(np.float32, st.sampled_from([(3,), (4, 3)]), elements=coordinates),
        arrays([(0, 3), (1, 3), (4, 3)]),
        arrays([(3,), (2, 2)]),
        junk,
    ),
    directions=st.one_of(
        hnp.arrays(np.float32, st.sampled_from([(3,), (4, 3)]), elements=axial_or_any),
        arrays([(1, 3), (4, 3)]),
        arrays([(2,)]),
        junk,
    ),
    t_max=st.one_of(st.sampled_from([np.inf, 0.0, -1.0, np.nan, 1e30]), arrays([(4,), (3,)]), junk),
    method=st.sampled_from(["esvo", "stack", "dda"]),
    max_steps=st.sampled_from([None, 64, 0, -1, 2.5, "x"]),
)
def test_trace(tree, origins, directions, t_max, method, max_steps):
    def check(hit):
        status = np.asarray(hit.status)
        assert np.isin(status, [jv.HIT, jv.MISS, jv.INVALID, jv.STEP_CAP]).all()
        hits = status == jv.HIT
        t, voxel, index = (np.asarray(a) for a in (hit.t, hit.voxel, hit.index))
        assert np.isfinite(t[hits]).all() and (t[hits] >= 0).all()
        assert ((voxel[hits] >= 0) & (voxel[hits] < 16)).all() and (index[hits] >= 0).all()
        assert (index[~hits] == jv.MISSING).all()
        o, d = np.broadcast_arrays(np.asarray(origins, np.float32), np.asarray(directions, np.float32))
        bad = ~np.isfinite(o).all(-1) | ~np.isfinite(d).all(-1) | ~d.any(-1)
        assert not hits[np.broadcast_to(bad, hits.shape)].any()

    attempt(
        "trace", lambda: jv.trace(tree, origins, directions, t_max=t_max, method=method, max_steps=max_steps), check
    )


@fuzz(40)
@given(
    ijk=st.one_of(
        arrays([(0, 3), (1, 3), (6, 3)], dtypes=(np.int32, np.int64)),
        arrays([(2, 3)], dtypes=(np.float32,)),
        arrays([(3, 2)], dtypes=(np.int32,)),
        junk,
    )
)
def test_voxel_index(tree, ijk):
    def check(index):
        index = np.asarray(index)
        assert ((index == jv.MISSING) | ((index >= 0) & (index < int(tree.voxel_count)))).all()

    attempt("voxel_index", lambda: jv.voxel_index(tree, ijk), check)


_VIEW = dict(
    eye=finite3,
    target=finite3,
    up=st.just((0.0, 1.0, 0.0)),
    fov=st.floats(1, 179),
    width=st.integers(1, 3),
    height=st.integers(1, 2),
)
_BAD_VIEW = dict(
    eye=vectors3,
    target=vectors3,
    up=vectors3,
    fov=st.one_of(reals, st.sampled_from([0.0, 179.9, 180.0]), junk),
    width=st.one_of(st.integers(-1, 3), junk),
    height=st.one_of(st.sampled_from([0, 1, 2.0]), junk),
)


@fuzz(100)
@given(view=st.one_of(st.fixed_dictionaries(_VIEW), st.fixed_dictionaries(_BAD_VIEW)))
def test_pinhole_rays(view):
    """Valid views, and views with any of their arguments bad."""

    def check(rays):
        origins, directions = (np.asarray(a) for a in rays)
        assert directions.shape == (view["height"], view["width"], 3) and np.isfinite(directions).all()
        np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, rtol=1e-5)

    attempt(
        "pinhole_rays",
        lambda: jv.pinhole_rays(
            view["eye"], view["target"], width=view["width"], height=view["height"], fov=view["fov"], up=view["up"]
        ),
        check,
    )


@fuzz(40)
@given(bounds=st.one_of(st.tuples(vectors3, vectors3), vertex_arrays), azimuth=reals, distance=st.one_of(reals, junk))
def test_look_at_view(bounds, azimuth, distance):
    def argument():
        return bounds if isinstance(bounds, tuple) else jv.Mesh(bounds, np.zeros((0, 3), np.int32))

    def check(view):
        assert all(np.isfinite(np.asarray(v)).all() for v in view)

    attempt("look_at_view", lambda: jv.look_at_view(argument(), azimuth=azimuth, distance=distance), check)


# ------------------------------------------------------------------------------ SDFs


@fuzz(80)
@given(
    kind=st.sampled_from(["sphere", "box", "torus", "capsule", "cylinder", "plane", "rounded_box"]),
    a=st.one_of(reals, arrays([(3,), (2,)]), junk),
    b=st.one_of(reals, arrays([(3,)]), junk),
)
def test_sdf_primitives_and_sphere_trace(kind, a, b):
    build = {
        "sphere": lambda: sdf.sphere(a),
        "box": lambda: sdf.box(a),
        "torus": lambda: sdf.torus(a, b),
        "capsule": lambda: sdf.capsule(a, b, 0.1),
        "cylinder": lambda: sdf.cylinder(a, b),
        "plane": lambda: sdf.plane(a, offset=b),
        "rounded_box": lambda: sdf.rounded_box(a, b),
    }[kind]
    scene = attempt(f"sdf.{kind}", build)
    if scene is None:
        return
    origins = np.array([[0.0, 0.0, -3.0], [0.3, 0.2, -3.0], [0.0, 0.0, 0.0], [np.nan, 0, 0]], np.float32)
    directions = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], np.float32)

    def check(hit):
        status = np.asarray(hit.status)
        assert np.isin(status, [jv.HIT, jv.MISS, jv.INVALID, jv.STEP_CAP]).all()
        assert status[3] == jv.INVALID
        assert np.isfinite(np.asarray(hit.t)[status == jv.HIT]).all()

    attempt("sphere_trace", lambda: jv.sphere_trace(scene, origins, directions), check)


# ------------------------------------------------------------------------------ files


@pytest.fixture(scope="module")
def valid_files(tmp_path_factory, tree):
    """One valid file per format (the bytes that the corruptions start from)."""
    folder = tmp_path_factory.mktemp("valid")
    jv.save(folder / "tree.jvx", tree, attributes={"id": np.arange(int(tree.voxel_count))})
    jv.write_exr(folder / "image.exr", {"R": np.ones((3, 4)), "Z": np.full((3, 4), np.inf)})
    (folder / "mesh.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (folder / "image.hdr").write_bytes(
        b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 1 +X 2\n" + bytes([128, 128, 128, 129] * 2)
    )
    voxels = jv.voxelize(_tetra(), GRID)
    jv.save_voxels(folder / "voxels.binvox", voxels)
    jv.save_voxels(folder / "voxels.npz", voxels)
    return {p.suffix: p.read_bytes() for p in folder.iterdir()}


READERS = {
    ".jvx": [jv.load, jv.load_attributes],
    ".exr": [jv.read_exr, jv.load_environment],
    ".obj": [jv.load_mesh],
    ".hdr": [jv.read_hdr, jv.load_environment],
    ".binvox": [jv.load_binvox, jv.load_voxels],
    ".npz": [jv.load_voxels],
}


@fuzz(150)
@given(
    suffix=st.sampled_from(sorted(READERS)),
    how=st.sampled_from(["truncate", "flip", "random", "empty"]),
    where=st.floats(0, 1),
    noise=st.binary(min_size=1, max_size=64),
)
def test_corrupt_files(tmp_path, valid_files, suffix, how, where, noise):
    data = valid_files[suffix]
    cut = int(where * len(data))
    corrupt = {
        "truncate": data[:cut],
        "flip": data[:cut] + bytes([data[cut % len(data)] ^ 0x5A]) + data[cut + 1 :],
        "random": noise,
        "empty": b"",
    }[how]
    path = tmp_path / f"corrupt{suffix}"
    path.write_bytes(corrupt)
    for reader in READERS[suffix]:
        attempt(f"{reader.__name__}({suffix})", lambda: reader(path))


def test_missing_files_and_directories(tmp_path):
    for readers in READERS.values():
        for reader in readers:
            for path in (tmp_path, tmp_path / "missing.file"):
                with pytest.raises(jv.JaxvoxError, match=", got "):
                    reader(path)
                CASES[f"{reader.__name__}(directory or missing)"] += 1
