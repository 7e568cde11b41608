"""Public API, jit/vmap, capacities and overflow, bad input, Morton codes, streaming."""

from __future__ import annotations

import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxvox as jv
from tests.reference import morton_encode as ref_morton


def _tetra(scale=1.0, shift=(0.0, 0.0, 0.0)):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32) * scale + np.float32(shift)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
    return jv.Mesh(v, f)


def test_public_api_has_docstrings():
    for name in jv.__all__:
        obj = getattr(jv, name)
        if inspect.isfunction(obj) or inspect.isclass(obj):
            assert inspect.getdoc(obj), f"jaxvox.{name} has no docstring"
            if inspect.isclass(obj):
                for meth_name, meth in vars(obj).items():
                    if inspect.isfunction(meth) and not meth_name.startswith("_"):
                        assert inspect.getdoc(meth), f"jaxvox.{name}.{meth_name} has no docstring"


@pytest.mark.parametrize("bits", [1, 10, 16, 20])
def test_morton_roundtrip_and_order(bits):
    rng = np.random.default_rng(bits)
    ijk = rng.integers(0, 1 << bits, size=(5000, 3)).astype(np.int32)
    ijk[0] = (1 << bits) - 1
    hi, lo = jv.morton.encode(jnp.asarray(ijk))
    np.testing.assert_array_equal(np.asarray(jv.morton.decode(hi, lo)), ijk)
    code = (np.asarray(hi).astype(np.uint64) << np.uint64(30)) | np.asarray(lo).astype(np.uint64)
    np.testing.assert_array_equal(code, ref_morton(ijk))


def test_grid_fit_and_bad_resolution():
    mesh = _tetra()
    grid = jv.Grid.fit(mesh, resolution=64)
    ijk = jv.voxelize(mesh, grid).to_numpy()
    assert ijk.min() >= 0 and ijk.max() < 64
    for bad in (0, 1, 3, 100, 2**21, 64.5):
        with pytest.raises(jv.JaxvoxError, match="power of two"):
            jv.Grid.fit(mesh, resolution=bad)


def test_eager_jit_vmap_agree():
    meshes = [_tetra(), _tetra(0.5, (0.2, 0.1, 0.3)), _tetra(0.8, (0.1, 0.05, 0.0))]
    grid = jv.Grid(origin=(-0.1, -0.1, -0.1), voxel_size=1.2 / 32, resolution=32)
    expected = [jv.voxelize(m, grid).to_numpy() for m in meshes]
    caps = jv.voxel_capacities(meshes[0], grid)
    caps = jv.Capacities(*(c * 2 for c in caps[:4]), caps.row_chunk)

    fixed = jax.jit(lambda m: jv.voxelize_fixed(m, grid, caps))
    for m, e in zip(meshes, expected):
        np.testing.assert_array_equal(fixed(m).to_numpy(), e)

    batch = jax.tree.map(lambda *xs: jnp.stack(xs), *meshes)
    out = jax.jit(jax.vmap(lambda m: jv.voxelize_fixed(m, grid, caps)))(batch)
    for b, e in enumerate(expected):
        assert int(out.overflow[b]) == 0
        np.testing.assert_array_equal(np.asarray(out.coords[b, : int(out.count[b])]), e)


def test_vmap_over_padded_meshes_of_different_sizes():
    small = _tetra(0.5, (0.2, 0.2, 0.2))
    mesh_b = jv.Mesh(
        np.concatenate([np.asarray(_tetra().vertices), [[0.9, 0.9, 0.9]]]).astype(np.float32),
        np.concatenate([np.asarray(_tetra().faces), [[1, 2, 4]]]),
    )
    grid = jv.Grid(origin=(-0.1, -0.1, -0.1), voxel_size=1.2 / 16, resolution=16)
    expected = [jv.voxelize(m, grid, mode="6-separating").to_numpy() for m in (small, mesh_b)]
    padded = [jv.pad_mesh(m, 5, 5) for m in (small, mesh_b)]
    batch = jax.tree.map(lambda *xs: jnp.stack(xs), *padded)
    caps = jv.voxel_capacities(mesh_b, grid, mode="6-separating")
    out = jax.jit(jax.vmap(lambda m: jv.voxelize_fixed(m, grid, caps, mode="6-separating")))(batch)
    for b, e in enumerate(expected):
        np.testing.assert_array_equal(np.asarray(out.coords[b, : int(out.count[b])]), e)


@pytest.mark.parametrize(
    "field, flag",
    [
        ("columns", jv.OVERFLOW_COLUMNS),
        ("rows", jv.OVERFLOW_ROWS),
        ("candidates", jv.OVERFLOW_CANDIDATES),
        ("voxels", jv.OVERFLOW_VOXELS),
    ],
)
def test_overflow_flag_and_host_retry(field, flag):
    mesh = _tetra()
    grid = jv.Grid.fit(mesh, resolution=64)
    full = jv.voxelize(mesh, grid).to_numpy()
    caps = jv.voxel_capacities(mesh, grid)
    tiny = caps._replace(**{field: caps.row_chunk if field == "rows" else 8})
    vox = jax.jit(lambda m: jv.voxelize_fixed(m, grid, tiny))(mesh)
    assert int(vox.overflow) & flag
    with pytest.raises(jv.JaxvoxError, match="overflow"):
        vox.to_numpy()
    assert int(vox.count) <= tiny.voxels
    # The host-side API sizes capacities itself and returns the full set.
    assert len(jv.voxelize(mesh, grid).to_numpy()) == len(full)
    # (jitted: op by op it compiles ~340 tiny programs; the four cases share this one)
    fitted = jax.jit(jv.voxelize_fixed, static_argnums=2)(mesh, grid, caps)
    np.testing.assert_array_equal(fitted.to_numpy(), full)


def test_bad_input_errors(tmp_path):
    v = np.asarray(_tetra().vertices).copy()
    f = np.asarray(_tetra().faces)
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=0.1, resolution=16)
    v_nan = v.copy()
    v_nan[2, 1] = np.nan
    with pytest.raises(jv.JaxvoxError, match="NaN or inf"):
        jv.voxelize(jv.Mesh(v_nan, f), grid)
    v_inf = v.copy()
    v_inf[0, 0] = np.inf
    with pytest.raises(jv.JaxvoxError, match="NaN or inf"):
        jv.voxelize(jv.Mesh(v_inf, f), grid)
    with pytest.raises(jv.JaxvoxError, match="index out of range"):
        jv.voxelize(jv.Mesh(v, np.array([[0, 1, 7]])), grid)
    with pytest.raises(jv.JaxvoxError, match="index out of range"):
        jv.voxelize(jv.Mesh(v, np.array([[0, -1, 2]])), grid)
    with pytest.raises(jv.JaxvoxError, match="voxelize mode: expected one of"):
        jv.voxelize(_tetra(), grid, mode="26-separating")
    with pytest.raises(jv.JaxvoxError, match="not found"):
        jv.load_mesh(tmp_path / "missing.obj")
    corrupt = tmp_path / "corrupt.ply"
    corrupt.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99999\n\x00\x01garbage")
    with pytest.raises(jv.JaxvoxError, match="corrupt.ply"):
        jv.load_mesh(corrupt)
    empty_obj = tmp_path / "empty.obj"
    empty_obj.write_text("# nothing here\n")
    with pytest.raises(jv.JaxvoxError, match="no triangles"):
        jv.load_mesh(empty_obj)


def test_empty_mesh_gives_zero_voxels():
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=0.1, resolution=16)
    empty = jv.Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    for mode in (jv.CONSERVATIVE, jv.SIX_SEPARATING):
        vox = jv.voxelize(empty, grid, mode=mode)
        assert int(vox.count) == 0 and vox.to_numpy().shape == (0, 3)
    outside = _tetra(1.0, (5.0, 5.0, 5.0))
    assert jv.voxelize(outside, grid).to_numpy().shape == (0, 3)


def test_streaming_regions_match_single_pass(meshes_dir):
    mesh = jv.load_mesh(meshes_dir / "spot.obj")
    grid = jv.Grid.fit(mesh, resolution=128)
    for mode in ("conservative", "6-separating"):
        whole = jv.voxelize(mesh, grid, mode=mode)
        streamed = jv.voxelize(mesh, grid, mode=mode, region_size=32)
        np.testing.assert_array_equal(streamed.to_numpy(), whole.to_numpy())


def test_regions_decoded_after_the_loop_where_no_address_space_is_lent(meshes_dir, monkeypatch):
    """Where the system refuses `reserved_empty`'s map (strict overcommit), `voxelize`
    decodes the regions after the last one: the same voxels, capacity and padding."""
    from jaxvox.voxelize import host

    mesh = jv.load_mesh(meshes_dir / "spot.obj")
    grid = jv.Grid.fit(mesh, resolution=128)
    threaded = jv.voxelize(mesh, grid, region_size=32)
    monkeypatch.setattr(host, "reserved_empty", lambda shape, dtype: None)
    after = jv.voxelize(mesh, grid, region_size=32)
    assert int(after.count) == int(threaded.count) > 0
    np.testing.assert_array_equal(np.asarray(after.coords), np.asarray(threaded.coords))


def test_regions_of_several_emit_calls_match_regions_of_one(meshes_dir):
    """The bunny at 256^3 has about 640K candidates in its one region, more than one emit
    call writes (`_SLOTS`): the voxels and their triangle ids are those of 64^3 regions."""
    from jaxvox.voxelize import host

    mesh = jv.load_mesh(meshes_dir / "stanford-bunny.obj")
    grid = jv.Grid.fit(mesh, resolution=256)
    # The counting pass alone (`voxel_capacities` would also voxelize without ids).
    lo, hi = host._region_bounds(np.zeros(3, np.int32), grid.resolution)
    chunks = host._chunks(host._grid_triangles(mesh, grid), np.arange(mesh.num_faces))
    assert host._count_chunks(chunks, lo, hi, False).sum(0)[2] > host._SLOTS
    for mode in ("conservative", "6-separating"):
        whole = jv.voxelize(mesh, grid, mode=mode, triangle_ids=True)
        small = jv.voxelize(mesh, grid, mode=mode, triangle_ids=True, region_size=64)
        np.testing.assert_array_equal(whole.to_numpy(), small.to_numpy())
        np.testing.assert_array_equal(whole.triangle_ids(), small.triangle_ids())


@settings(max_examples=30, deadline=None)
@given(st.lists(st.lists(st.integers(0, 40), max_size=30), min_size=1, max_size=5), st.booleans())
def test_parts_sorted_as_they_come_merge_to_the_sorted_unique_keys(parts, on_a_thread):
    """A region's runs sorted one by one (`_sorted_keys`, on a worker thread or not) and
    merged give the distinct written keys in order and the candidates written, as one
    sort of all of them; `EMPTY` (unwritten slots) counts for nothing."""
    from concurrent.futures import ThreadPoolExecutor

    from jaxvox import morton
    from jaxvox.voxelize import host

    empty = int(morton.EMPTY)
    runs = [(np.array([empty if k == 40 else k for k in part], np.uint32),) for part in parts]
    everything = np.concatenate([run[0] for run in runs])
    written = everything[everything != empty]
    with ThreadPoolExecutor(1) as worker:
        given_parts = [worker.submit(host._sorted_keys, run) if on_a_thread else host._sorted_keys(run) for run in runs]
        keys, triangle, count = host._sort_region(given_parts, with_ids=False)
    np.testing.assert_array_equal(keys, np.unique(written))
    assert keys.dtype == np.uint32 and triangle is None and count == len(written)


def test_runs_that_overflow_an_emit_call_keep_every_triangle(monkeypatch):
    """Large triangles (about 3K candidates each): the first run (all 800) overflows its
    call, the triangles that did not fit start the next run, and later runs hold fewer
    triangles than the run before them, sized to fit (their padding counts nothing).
    The voxels are the union of those of groups of 100 triangles, each group one call."""
    from jaxvox.voxelize import host

    rng = np.random.default_rng(7)
    centres = rng.uniform(40, 216, (800, 1, 3))
    corners = (centres + rng.normal(0, 35, (800, 3, 3))).reshape(-1, 3).astype(np.float32)
    faces = np.arange(len(corners), dtype=np.int32).reshape(-1, 3)
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0, resolution=256)
    mesh = jv.Mesh(corners, faces)
    emit, written, runs = host._emit_chunk, [], []

    def recorded(*args, **kwargs):
        out = emit(*args, **kwargs)
        written.append(int(np.asarray(out[1]).sum()))  # candidates of the run's triangles
        runs.append(int(np.isfinite(np.asarray(args[0])).all((1, 2)).sum()))  # its triangles
        return out

    monkeypatch.setattr(host, "_emit_chunk", recorded)
    for mode in ("conservative", "6-separating"):
        written.clear(), runs.clear()
        got = jv.voxelize(mesh, grid, mode=mode, progress=False).to_numpy()
        assert len(written) >= 3 and written[0] > host._SLOTS and runs[0] == 800  # the first run overflowed
        assert runs[1] < runs[0]  # a shorter run, with triangles after it (a third call)
        calls = len(written)
        groups = [jv.Mesh(corners, faces[k : k + 100]) for k in range(0, 800, 100)]
        linear = lambda ijk: (ijk[:, 0].astype(np.int64) << 16) | (ijk[:, 1] << 8) | ijk[:, 2]
        union = np.unique(np.concatenate([linear(jv.voxelize(g, grid, mode=mode).to_numpy()) for g in groups]))
        np.testing.assert_array_equal(np.sort(linear(got)), union)  # got: unique voxels
        assert len(written) - calls == len(groups) and max(written[calls:]) < host._SLOTS  # a group, a call


def test_a_triangle_larger_than_two_emit_calls():
    """A single triangle with more candidates than two calls write (`_SLOTS` each) is
    written part by part and sets each of its counted candidates once, as it does (up
    to near-ties) in regions small enough for one call."""
    from jaxvox.voxelize import host
    from jaxvox.voxelize.host import _SLOTS

    corners = np.array([[0.01, 0.02, 0.05], [0.98, 0.03, 0.95], [0.02, 0.97, 0.5]], np.float32)
    tri = jv.Mesh(corners, np.array([[0, 1, 2]], np.int32))
    grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0 / 1024, resolution=1024)
    lo, hi = host._region_bounds(np.zeros(3, np.int32), 1024)
    counted = host._count_chunks(host._chunks(host._grid_triangles(tri, grid), np.arange(1)), lo, hi, False)
    assert counted[0, 2] > 2 * _SLOTS  # 1.16 M candidates: three parts
    whole = jv.voxelize(tri, grid).to_numpy()
    assert len(whole) == counted[0, 2]  # one triangle never repeats a voxel: every candidate, once
    # In 512^3 regions the candidates of each fit one call. The region's coordinates scale
    # the half-plane tolerance, so 28 of the 1.16 M voxels (near-ties) are not set there.
    linear = lambda ijk: (ijk[:, 0].astype(np.int64) << 20) | (ijk[:, 1] << 10) | ijk[:, 2]
    parts = linear(jv.voxelize(tri, grid, region_size=512).to_numpy())
    assert np.isin(parts, linear(whole)).all() and len(whole) - len(parts) < 1e-4 * len(whole)


@pytest.mark.parametrize("wide", [False, True])
def test_bounds_round_alike_in_every_program(wide):
    """`_mul_add` gives the same float32 bits compiled (where XLA may contract a
    multiply-add) as numpy's separately rounded operations, for integer coordinates
    below `NARROW` (or 2^16, `wide`) and slopes of any size (infinite, zero, denormal):
    a tie cannot round one way where a row is counted and the other where it is placed."""
    from jaxvox.voxelize.triangles import NARROW, _mul_add

    rng = np.random.default_rng(3)
    n, bound = 1 << 16, (1 << 16) if wide else NARROW
    p = rng.uniform(-2 * bound, 2 * bound, n).astype(np.float32)
    q = (rng.uniform(-1, 1, n) * 10.0 ** rng.integers(-3, 3, n)).astype(np.float32)
    q[:8] = [np.inf, -np.inf, 0.0, -0.0, 2.0**30, 1e-40, -3e38, 1.0]  # sentinels, a denormal, huge
    s = rng.integers(-bound + 1, bound, n).astype(np.float32)
    got = np.asarray(jax.jit(_mul_add, static_argnums=3)(p, q, s, wide))
    top = lambda x: (x.view(np.uint32) & np.uint32(0xFFFF0000 if wide else 0xFFFFF000)).view(np.float32)
    with np.errstate(all="ignore"):
        q1 = top(q)
        rest = np.where(np.isfinite(q), q - q1, np.float32(0))
        q2 = top(rest) if wide else rest
        want = ((p + q1 * s) + q2 * s) + (rest - q2) * s if wide else (p + q1 * s) + rest * s
        exact = p.astype(np.float64) + q.astype(np.float64) * s
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
    finite = np.abs(exact) < 1e38  # and the value is p + q s, up to the additions' rounding
    np.testing.assert_allclose(got[finite], exact[finite], rtol=1e-6, atol=1e-3)
    assert np.isposinf(got[0]) == (s[0] > 0) and np.isneginf(got[1]) == (s[1] > 0)


def test_high_resolutions_use_two_word_keys():
    tri = jv.Mesh(
        np.array([[0.1, 0.2, 0.3], [0.1001, 0.2, 0.3], [0.1, 0.2002, 0.3001]], np.float32),
        np.array([[0, 1, 2]], np.int32),
    )
    for bits in (16, 20):  # 48- and 60-bit Morton keys, two 32-bit words each
        r = 1 << bits
        grid = jv.Grid(origin=(0, 0, 0), voxel_size=1.0 / r, resolution=r)
        streamed = jv.voxelize(tri, grid).to_numpy()
        caps = jv.voxel_capacities(tri, grid)
        whole = jax.jit(lambda m, g: jv.voxelize_fixed(m, g, caps))(tri, grid).to_numpy()
        np.testing.assert_array_equal(streamed, whole)
        p = np.asarray(grid.to_grid_units(tri.vertices))
        assert (streamed >= np.floor(p.min(0)) - 1).all() and (streamed <= np.floor(p.max(0))).all()
        order = ref_morton(streamed)
        assert (order[1:] > order[:-1]).all()


def test_triangle_ids_are_closest_setting_triangle():
    mesh = _tetra()
    grid = jv.Grid(origin=(-0.05, -0.05, -0.05), voxel_size=1.1 / 8, resolution=8)
    vox = jv.voxelize(mesh, grid, triangle_ids=True)
    ijk, ids = vox.to_numpy(), vox.triangle_ids()
    streamed = jv.voxelize(mesh, grid, triangle_ids=True, region_size=4)  # the tetra crosses every region boundary
    np.testing.assert_array_equal(streamed.triangle_ids(), ids)
    tris = np.asarray(grid.to_grid_units(mesh.triangles()), np.float64)
    per_face = [
        {tuple(x) for x in jv.voxelize(jv.Mesh(mesh.vertices, mesh.faces[f : f + 1]), grid).to_numpy()}
        for f in range(mesh.num_faces)
    ]
    settable = np.array([[tuple(x) in per_face[f] for f in range(mesh.num_faces)] for x in ijk])
    assert settable[np.arange(len(ids)), ids].all()  # each id is a triangle that sets the voxel
    d = np.stack([_dist_point_triangle(ijk + 0.5, tris[f]) for f in range(len(tris))], 1)
    chosen = d[np.arange(len(ids)), ids]
    best = np.where(settable, d, np.inf).min(1)
    np.testing.assert_allclose(chosen, best, atol=1e-5)


def _dist_point_triangle(p, tri):
    """Distance from points [n, 3] to one triangle [3, 3] by dense sampling (test-only, float64)."""
    s, t = np.meshgrid(np.linspace(0, 1, 201), np.linspace(0, 1, 201))
    keep = s + t <= 1
    pts = tri[0] + s[keep, None] * (tri[1] - tri[0]) + t[keep, None] * (tri[2] - tri[0])
    return np.sqrt(((p[:, None, :] - pts[None]) ** 2).sum(-1)).min(1)


def test_cli_errors_are_one_line(capsys):
    from jaxvox.cli import main

    assert main(["voxelize", "does-not-exist.obj", "--out", "x.npz"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not found" in err[0]
    assert main(["voxelize", "--resolution", "100"]) == 2
    assert "power of two" in capsys.readouterr().err


def test_the_command_runs_itself_again_with_huge_pages():
    """`jaxvox.cli.ask_for_huge_pages` starts the same command line again with glibc's
    huge-page tunable added to the ones already set, once (on glibc; elsewhere it does
    nothing)."""
    import os
    import platform
    import subprocess
    import sys

    from jaxvox.cli import HUGE_PAGES

    script = (
        "from jaxvox.cli import ask_for_huge_pages as a; print('start', flush=True); a(); "
        "import os; print(os.environ['GLIBC_TUNABLES'])"
    )
    env = dict(os.environ, GLIBC_TUNABLES="glibc.malloc.check=0")
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True).stdout
    if platform.libc_ver()[0] != "glibc":
        assert out.split() == ["start", "glibc.malloc.check=0"]
    else:
        assert out.split() == ["start", "start", f"glibc.malloc.check=0:{HUGE_PAGES}"]
