"""Path tracing of voxel DAGs: determinism, a white furnace, emission, the sun, EXR and PNG, the CLI.

All renders share one scene (a slab with a sphere above it, 32^3) and one image size
(64x48, one batch), so the suite compiles the renderer twice (with and without a sun).
"""

from __future__ import annotations

import os
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import jaxvox as jv

W, H = 64, 48
SETTINGS = dict(width=W, height=H, spp=2, batch_rays=W * H * 2)


@pytest.fixture(scope="module")
def scene():
    """(tree, eye, target, mesh): a thin slab and a sphere above it, voxelized at 32^3."""
    slab = trimesh.creation.box(extents=[2.0, 0.2, 2.0])
    slab.apply_translation([0.0, -0.6, 0.0])
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.45)
    ball.apply_translation([0.2, 0.0, 0.1])
    both = trimesh.util.concatenate([slab, ball])
    mesh = jv.Mesh(np.asarray(both.vertices, np.float32), np.asarray(both.faces, np.int32))
    tree = jv.build_dag(jv.voxelize(mesh, jv.Grid.fit(mesh, resolution=32)))
    eye, target = jv.look_at_view(mesh, azimuth=30.0, elevation=35.0, distance=1.6)
    return tree, eye, target, mesh


def _interior(mask):
    """Pixels whose 3x3 neighbourhood lies entirely in `mask` (jittered samples stay there)."""
    m = np.pad(mask, 1, constant_values=False)
    out = np.ones_like(mask)
    for di in (0, 1, 2):
        for dj in (0, 1, 2):
            out &= m[di : di + mask.shape[0], dj : dj + mask.shape[1]]
    return out


def test_same_seed_same_image_and_finite(scene):
    tree, eye, target, _ = scene
    env = jv.sky_environment()
    a = jv.render(tree, eye, target, env=env, bounces=3, key=7, **SETTINGS)
    b = jv.render(tree, eye, target, env=env, bounces=3, key=7, **SETTINGS)
    assert a.radiance.shape == (H, W, 3) and a.depth.shape == (H, W) and a.normal.shape == (H, W, 3)
    np.testing.assert_array_equal(np.asarray(a.radiance), np.asarray(b.radiance))
    rgb = np.asarray(a.radiance)
    assert np.isfinite(rgb).all() and (rgb >= 0).all() and rgb.max() > 0
    assert int(a.stopped) == 0
    other = jv.render(tree, eye, target, env=env, bounces=3, key=8, **SETTINGS)
    assert not np.array_equal(np.asarray(other.radiance), rgb)
    # Another batch size draws the same samples: equal up to float32 summation order.
    split = jv.render(tree, eye, target, env=env, bounces=3, key=7, **dict(SETTINGS, batch_rays=W * H // 2 + 5))
    np.testing.assert_allclose(np.asarray(split.radiance), rgb, rtol=1e-5, atol=1e-6)


def test_aovs_match_primary_trace(scene):
    tree, eye, target, _ = scene
    result = jv.render(tree, eye, target, env=jv.uniform_environment(rgb=0.0), bounces=0, key=0, **SETTINGS)
    origins, directions = jv.pinhole_rays(eye, target, width=W, height=H)
    hit = jv.trace(tree, origins, directions)
    hits = np.asarray(hit.status) == jv.HIT
    depth, normal = np.asarray(result.depth), np.asarray(result.normal)
    assert np.mean(np.isfinite(depth) == hits) > 0.99  # pixel-centre rays, up to float32 ties
    both = hits & np.isfinite(depth)
    np.testing.assert_allclose(depth[both], np.asarray(hit.t)[both], rtol=1e-4)
    assert np.mean((normal == np.asarray(hit.normal)).all(-1)[both]) > 0.99
    assert (normal[~np.isfinite(depth)] == 0).all()


def test_white_furnace(scene):
    """Albedo 1 under a uniform environment of radiance 1: every path carries exactly 1 out."""
    tree, eye, target, _ = scene
    result = jv.render(
        tree, eye, target, env=jv.uniform_environment(rgb=1.0), albedo=(1.0, 1.0, 1.0), bounces=48, key=1, **SETTINGS
    )
    rgb = np.asarray(result.radiance)
    hits = np.isfinite(np.asarray(result.depth))
    assert hits.mean() > 0.3  # the scene covers much of the image
    assert rgb.max() <= 1.0 + 1e-6
    assert abs(rgb.mean() - 1.0) < 1e-3
    # Grey albedo: energy is lost at every bounce, nothing gains any.
    grey = jv.render(
        tree, eye, target, env=jv.uniform_environment(rgb=1.0), albedo=(0.5, 0.5, 0.5), bounces=48, key=1, **SETTINGS
    )
    g = np.asarray(grey.radiance)
    assert g.max() <= 1.0 + 1e-6 and (g[_interior(hits)] < 1.0).all()
    np.testing.assert_array_equal(g[_interior(~hits)], 1.0)


def test_black_environment_and_emission(scene):
    tree, eye, target, _ = scene
    black = jv.uniform_environment(rgb=0.0)
    dark = jv.render(tree, eye, target, env=black, bounces=4, key=2, **SETTINGS)
    np.testing.assert_array_equal(np.asarray(dark.radiance), 0.0)
    # Every voxel emits, nothing reflects: surface pixels show exactly the emission.
    glow = jv.render(
        tree, eye, target, env=black, albedo=(0, 0, 0), emission=(1.0, 2.0, 3.0), bounces=4, key=2, **SETTINGS
    )
    rgb = np.asarray(glow.radiance)
    hits = np.isfinite(np.asarray(glow.depth))
    inner = _interior(hits)
    assert inner.sum() > 100
    np.testing.assert_array_equal(rgb[inner], np.broadcast_to(np.float32([1.0, 2.0, 3.0]), (inner.sum(), 3)))
    np.testing.assert_array_equal(rgb[_interior(~hits)], 0.0)
    # A few emissive voxels light their surroundings; the background stays black. The table
    # has a row per voxel slot of the expanded tree (as `box_emission` makes it for the CLI's
    # --emit): test_cli_info_and_errors's render then runs this test's compiled program.
    emission = np.zeros((jv.expand(tree).coords.shape[0], 3), np.float32)
    emission[::7] = 4.0
    lit = jv.render(
        tree, eye, target, env=black, albedo=(0.8, 0.8, 0.8), emission=emission, bounces=4, key=2, **SETTINGS
    )
    rgb = np.asarray(lit.radiance)
    assert np.isfinite(rgb).all() and rgb.max() > 0
    np.testing.assert_array_equal(rgb[_interior(~hits)], 0.0)


def test_sun_on_upward_faces(scene):
    """No sky, sun straight up, no bounces: lit upward faces show albedo / pi * E exactly."""
    tree, eye, target, _ = scene
    env = jv.sky_environment(sun_direction=(0, 1, 0), sun_irradiance=(3.0, 2.0, 1.0), zenith=0, horizon=0, ground=0)
    result = jv.render(tree, eye, target, env=env, albedo=(0.6, 0.6, 0.6), bounces=0, key=3, **SETTINGS)
    rgb = np.asarray(result.radiance)
    up = _interior((np.asarray(result.normal) == [0, 1, 0]).all(-1))
    side = _interior((np.asarray(result.normal)[..., 1] <= 0) & np.isfinite(np.asarray(result.depth)))
    expected = np.float32(0.6) / np.pi * np.float32([3.0, 2.0, 1.0])
    assert up.sum() > 20 and side.sum() > 5
    assert np.mean(np.isclose(rgb[up], expected, rtol=1e-5).all(-1)) > 0.9  # the rest lies in the ball's shadow
    assert np.mean((rgb[side] == 0).all(-1)) > 0.95  # no sun on side and bottom faces (a pixel may straddle)


def test_exr_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(0)
    channels = {name: rng.standard_normal((7, 5)).astype(np.float32) * 1e3 for name in ("R", "G", "B", "Z", "N.X")}
    channels["Z"][0, 0] = np.inf
    channels["R"][1, 1] = np.float32(1e-40)  # subnormal
    channels["G"][2, 2] = -0.0
    path = tmp_path / "a.exr"
    jv.write_exr(path, channels)
    back = jv.read_exr(path)
    assert set(back) == set(channels)
    for name, a in channels.items():
        assert back[name].dtype == np.float32 and back[name].shape == a.shape
        np.testing.assert_array_equal(back[name].view(np.uint32), a.view(np.uint32))
    sky = {c: np.full((2, 4), v, np.float32) for c, v in zip("RGB", (0.5, 1.0, 2.0))}
    jv.write_exr(tmp_path / "sky.exr", sky)
    env = jv.load_environment(tmp_path / "sky.exr", scale=2.0)  # a lat-long environment map
    assert env.image.shape == (2, 4, 3)
    np.testing.assert_array_equal(np.asarray(env.radiance(np.float32([[1, 0, 0]]))), [[1.0, 2.0, 4.0]])


def _rgbe(image):
    """Float RGB [H, W, 3] -> RGBE bytes [H, W, 4] (the reference encoding: mantissas below 256)."""
    peak = image.max(-1)
    exponent = np.where(peak > 0, np.floor(np.log2(np.maximum(peak, 1e-38))) + 1, 0).astype(int)
    mantissa = np.where(peak[..., None] > 0, np.floor(image * 256.0 / np.exp2(exponent)[..., None]), 0)
    return np.concatenate([mantissa, np.where(peak > 0, exponent + 128, 0)[..., None]], -1).astype(np.uint8)


def test_read_hdr_flat_and_run_length_encoded(tmp_path):
    rng = np.random.default_rng(1)
    image = (rng.random((3, 40, 3)) * 4.0).astype(np.float32)
    image[1, 5:30] = [0.5, 1.0, 2.0]  # a run
    rgbe = _rgbe(image)
    expected = rgbe[..., :3] * np.exp2(rgbe[..., 3:].astype(float) - 136)
    header = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 3 +X 40\n"
    (tmp_path / "flat.hdr").write_bytes(header + rgbe.tobytes())
    rle = bytearray(header)
    for row in rgbe:
        rle += bytes([2, 2, 0, 40])
        for c in range(4):
            x, values = 0, row[:, c]
            while x < 40:
                run = 1
                while x + run < 40 and run < 127 and values[x + run] == values[x]:
                    run += 1
                if run >= 3:
                    rle += bytes([128 + run, values[x]])
                    x += run
                else:
                    n = min(2, 40 - x)
                    rle += bytes([n]) + values[x : x + n].tobytes()
                    x += n
    (tmp_path / "rle.hdr").write_bytes(bytes(rle))
    for name in ("flat.hdr", "rle.hdr"):
        got = jv.read_hdr(tmp_path / name)
        assert got.dtype == np.float32 and got.shape == (3, 40, 3)
        np.testing.assert_allclose(got, expected, rtol=1e-6)
        assert (np.abs(got - image) <= image.max(-1, keepdims=True) / 64).all()  # shared exponent, 8-bit mantissas
    assert jv.load_environment(tmp_path / "rle.hdr").image.shape == (3, 40, 3)
    (tmp_path / "short.hdr").write_bytes(bytes(rle[:-30]))
    with pytest.raises(jv.JaxvoxError, match="truncated"):
        jv.read_hdr(tmp_path / "short.hdr")


def test_save_render_writes_exr_and_png(scene, tmp_path):
    import imageio.v3 as iio

    tree, eye, target, _ = scene
    result = jv.render(tree, eye, target, env=jv.sky_environment(), bounces=2, key=4, **SETTINGS)
    exr, png = jv.save_render(tmp_path / "img.exr", result)
    assert png == str(tmp_path / "img.png")
    back = jv.read_exr(exr)
    np.testing.assert_array_equal(np.stack([back[c] for c in "RGB"], -1), np.asarray(result.radiance))
    np.testing.assert_array_equal(back["Z"], np.asarray(result.depth))
    np.testing.assert_array_equal(np.stack([back[f"N.{c}"] for c in "XYZ"], -1), np.asarray(result.normal))
    covered = np.isfinite(np.asarray(result.depth))
    assert covered.any() and not covered.all()  # the scene covers part of the image
    np.testing.assert_array_equal(back["A"], covered.astype(np.float32))
    picture = iio.imread(png)
    assert picture.shape == (H, W, 3) and picture.dtype == np.uint8 and picture.max() > 0
    # A finite far value for tools that expect one; the coverage channel still tells background apart.
    back = jv.read_exr(jv.save_render(tmp_path / "far.exr", result, far=1e4)[0])
    np.testing.assert_array_equal(back["Z"], np.where(covered, np.asarray(result.depth), 1e4).astype(np.float32))
    for bad in (dict(far=0.0), dict(far=np.nan), dict(exposure=np.inf)):
        with pytest.raises(jv.JaxvoxError, match="save_render"):
            jv.save_render(tmp_path / "bad.exr", result, **bad)
    with pytest.raises(jv.JaxvoxError, match="does not exist"):
        jv.save_render(tmp_path / "missing" / "img.exr", result)


def test_bounce_origins_never_start_inside_a_voxel():
    """A ray through a voxel edge comes in diagonally; the voxel across the entry face the
    traversal reports can be occupied. The bounce used to start inside it (the path then
    stopped: 6 of 1.3 M paths in `make run`'s render); it now leaves into the voxel the ray
    crossed. Here: voxel (1, 1, 0) hit through its edge with (1, 0, 0) occupied below it
    and a reported normal of -y."""
    import importlib

    surface = importlib.import_module("jaxvox.render.integrator")._voxel_surface
    grid = jv.Grid(np.zeros(3), 1.0, 4)
    tree = jv.build_octree(jv.Voxels.from_coords([[1, 1, 0], [1, 0, 0]], grid))
    direction = np.array([[1.0, 1.0, 0.2]], np.float32) / np.float32(np.sqrt(2.04))
    t = np.float32(np.sqrt(2.04) / 2)  # from (0.5, 0.5, 0.4) to the edge point (1, 1, 0.5)
    origin = np.array([[0.5, 0.5, 0.4]], np.float32)
    hit = jv.Hit(
        t=jnp.full(1, t),
        voxel=jnp.array([[1, 1, 0]], jnp.int32),
        normal=jnp.array([[0.0, -1.0, 0.0]]),
        index=jnp.zeros(1, jnp.int32),
        status=jnp.full(1, jv.HIT),
    )
    none = jnp.zeros((1, 3), jnp.float32)  # no shading normals
    point = np.asarray(surface(tree, jnp.asarray(origin), jnp.asarray(direction), hit, none).point)[0]
    cell = np.floor(point).astype(int)
    assert int(jv.voxel_index(tree, cell)) == jv.MISSING, (point, cell)
    np.testing.assert_array_equal(cell, [0, 0, 0])  # the voxel the ray came from
    # Away from edges nothing changes: the point is just across the reported face.
    hit = jv.Hit(
        t=jnp.full(1, t),
        voxel=jnp.array([[1, 1, 0]], jnp.int32),
        normal=jnp.array([[-1.0, 0.0, 0.0]]),
        index=jnp.zeros(1, jnp.int32),
        status=jnp.full(1, jv.HIT),
    )
    point = np.asarray(surface(tree, jnp.asarray(origin), jnp.asarray(direction), hit, none).point)[0]
    np.testing.assert_array_equal(np.floor(point).astype(int), [0, 1, 0])


def test_default_render_has_no_stopped_paths():
    """The smallest render of `make run`'s scene that stopped a path before the fix (1 path)."""
    from jaxvox.cli import _upright_default_scene

    mesh = _upright_default_scene()
    tree = jv.build_dag(jv.voxelize(mesh, jv.Grid.fit(mesh, resolution=64)))
    bounds = tuple(np.asarray(b) for b in (mesh.vertices.min(0), mesh.vertices.max(0)))
    eye, target = jv.look_at_view(bounds)
    result = jv.render(tree, eye, target, env=jv.sky_environment(), width=192, height=108, spp=16, bounces=8, key=0)
    assert int(result.stopped) == 0


def test_tonemap():
    x = np.array([[0.0, 0.0, 0.0], [0.18, 0.18, 0.18], [1e6, 1e6, 1e6], [np.nan, -1.0, 0.5]], np.float32)
    out = jv.tonemap(x)
    assert out.dtype == np.uint8
    assert out[0].tolist() == [0, 0, 0] and out[2].tolist() == [255, 255, 255] and out[3, 0] == 0
    assert 0 < out[1, 0] < 255
    assert jv.tonemap(x, curve="clip", exposure=1.0)[1, 0] > jv.tonemap(x, curve="clip")[1, 0]
    with pytest.raises(jv.JaxvoxError, match="tonemap curve"):
        jv.tonemap(x, curve="filmic")


def test_voxel_albedo():
    colours = np.array([[1.0, 0.5, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0]], np.float32)
    albedo = np.asarray(jv.voxel_albedo({"color": colours}))
    np.testing.assert_allclose(albedo, [[1.0, 0.21404114, 0.0], [0, 0, 0]], rtol=1e-5)
    np.testing.assert_allclose(np.asarray(jv.voxel_albedo({}, default=(0.2, 0.3, 0.4))), [[0.2, 0.3, 0.4]])


def test_bad_inputs(scene, tmp_path):
    tree, eye, target, _ = scene
    env = jv.uniform_environment(rgb=1.0)
    for bad, match in (
        (dict(width=0), "width"),
        (dict(spp=0), "spp"),
        (dict(bounces=-1), "bounces"),
        (dict(fov=180.0), "fov"),
        (dict(albedo=np.ones((3, 3))), "albedo"),
        (dict(emission=(1.0, -1.0, 0.0)), "emission"),
        (dict(env="sky"), "Environment"),
    ):
        with pytest.raises(jv.JaxvoxError, match=match):
            jv.render(tree, eye, target, **{"env": env, **bad})
    with pytest.raises(jv.JaxvoxError, match="differ"):
        jv.render(tree, eye, eye, env=env)
    with pytest.raises(jv.JaxvoxError, match="parallel"):
        jv.render(tree, (0, 2, 0), (0, 0, 0), env=env)
    with pytest.raises(jv.JaxvoxError, match="not found"):
        jv.load_environment(tmp_path / "missing.exr")
    (tmp_path / "sky.png").write_bytes(b"\x89PNG")
    with pytest.raises(jv.JaxvoxError, match=".exr, .hdr or .npy"):
        jv.load_environment(tmp_path / "sky.png")
    (tmp_path / "sky.hdr").write_bytes(b"#?RADIANCE\n")
    with pytest.raises(jv.JaxvoxError, match="truncated"):
        jv.load_environment(tmp_path / "sky.hdr")
    with pytest.raises(jv.JaxvoxError, match="negative"):
        jv.uniform_environment(rgb=(1.0, -1.0, 0.0))


def test_cli_info_and_errors(scene, tmp_path, capsys):
    from jaxvox.cli import main

    tree, _, _, _ = scene
    path = tmp_path / "scene.jvx"
    jv.save(path, tree)
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "levels: 5" in out and "bits per voxel" in out and f"voxels: {int(tree.voxel_count):,}" in out
    out_exr = tmp_path / "from_tree.exr"
    assert (
        main(
            [
                "render",
                str(path),
                "--size",
                f"{W}x{H}",
                "--spp",
                "2",
                "--bounces",
                "0",
                "--batch-rays",
                str(W * H * 2),
                "--camera",
                "30,35,1.6",
                "--albedo",
                "0.5,0.6,0.7",
                "--env",
                "black",
                "--emit=-9,-9,-9,9,9,9:1,2,3",
                "--out",
                str(out_exr),
            ]
        )
        == 0
    )
    assert str(tmp_path / "from_tree.png") in capsys.readouterr().out
    channels = jv.read_exr(out_exr)
    rgb, hits = np.stack([channels[c] for c in "RGB"], -1), np.isfinite(channels["Z"])
    assert rgb.shape == (H, W, 3) and _interior(hits).sum() > 20
    np.testing.assert_array_equal(rgb[_interior(hits)], np.broadcast_to([1.0, 2.0, 3.0], rgb[_interior(hits)].shape))
    np.testing.assert_array_equal(rgb[_interior(~hits)], 0.0)
    assert main(["info", str(tmp_path / "missing.jvx")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.jvx" in err[0]
    for argv, match in (
        (["render", "--size", "64by48"], "WIDTHxHEIGHT"),
        (["render", "--camera", "1,2,3,4"], "camera"),
        (["render", "--env", str(tmp_path / "nope.exr")], "not found"),
        (["render", "--resolution", "100"], "power of two"),
        (["render", "--emit", "0,0,0,1,1,1"], "--emit: takes"),
        (["render", "--emit", "0,0,0,1,1:1"], "emit box"),
        (["render", "nope.obj"], "not found"),
    ):
        assert main(argv + ["--out", str(tmp_path / "x.exr")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and match in err[0], (argv, err)
    for argv, match in (
        (["render", "--out", str(tmp_path / "x.png")], "--out extension: expected one of '.exr'"),
        (["render", "--spp", "0", "--out", str(tmp_path / "x.exr")], "spp"),
        (["render", "--fov", "180", "--out", str(tmp_path / "x.exr")], "fov"),
        (["render", "--camera", "0,0,0,0,0,0", "--out", str(tmp_path / "x.exr")], "differ from the eye"),
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and match in err[0], (argv, err)
    # A mesh rendered from the boundary of its solid voxelization: the voxels it reports
    # are `solid_boundary`'s, and the image sees them.
    sphere = tmp_path / "sphere.obj"
    trimesh.creation.icosphere(subdivisions=2).export(sphere)
    solid_exr = tmp_path / "solid.exr"
    view = ["--size", f"{W}x{H}", "--spp", "1", "--bounces", "0", "--resolution", "16", "--out", str(solid_exr)]
    assert main(["render", str(sphere), "--voxels", "solid-boundary", *view]) == 0
    mesh = jv.load_mesh(sphere)
    count = int(jv.solid_boundary(mesh, jv.Grid.fit(mesh, resolution=16)).count)
    assert f"-> {count:,} solid-boundary voxels at 16^3" in capsys.readouterr().out
    assert _interior(np.isfinite(jv.read_exr(solid_exr)["Z"])).sum() > 20
    with pytest.raises(SystemExit) as exit_info:
        main(["render", "--no-such-option"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--no-such-option" in err[0]


def test_cli_render_subprocess(tmp_path):
    """`python -m jaxvox render` of the default scene. Its scene, resolution and image are
    notebooks/04_render.py's smoke run (upright default scene with its colours, 32^3, 64x48,
    2 spp, 2 bounces, sky): both processes share the suite's compilation cache
    ($JAXVOX_CACHE_DIR, set by conftest), so whichever runs second compiles nothing. The
    command line would configure one CPU device per core (and shard, compiling other
    programs); it runs on one device here, as the tests do."""
    out = tmp_path / "tiny.exr"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "jaxvox",
            "render",
            "--resolution",
            "32",
            "--size",
            "64x48",
            "--spp",
            "2",
            "--bounces",
            "2",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
        env=dict(os.environ, JAX_NUM_CPU_DEVICES="1"),
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert out.exists() and (tmp_path / "tiny.png").exists()
    assert str(tmp_path / "tiny.png") in result.stdout
    channels = jv.read_exr(out)
    assert {"R", "G", "B", "Z", "N.X", "N.Y", "N.Z"} <= set(channels) and channels["R"].shape == (48, 64)


def test_mesh_renderer_furnace_and_agreement_with_voxels(scene):
    pytest.importorskip("embreex")
    tree, eye, target, mesh = scene
    furnace = jv.render_mesh(
        mesh, eye, target, env=jv.uniform_environment(rgb=1.0), albedo=(1.0, 1.0, 1.0), bounces=48, key=1, **SETTINGS
    )
    rgb = np.asarray(furnace.radiance)
    assert rgb.max() <= 1.0 + 1e-6 and abs(rgb.mean() - 1.0) < 1e-3
    assert np.isfinite(np.asarray(furnace.depth)).mean() > 0.3
    a = jv.render_mesh(mesh, eye, target, env=jv.sky_environment(), bounces=2, key=5, **SETTINGS)
    b = jv.render_mesh(mesh, eye, target, env=jv.sky_environment(), bounces=2, key=5, **SETTINGS)
    np.testing.assert_array_equal(np.asarray(a.radiance), np.asarray(b.radiance))
    assert np.isfinite(np.asarray(a.radiance)).all()
    # Same key, same samples: on the slab's flat top the two renders nearly agree.
    voxels = jv.render(tree, eye, target, env=jv.sky_environment(), bounces=2, key=5, **SETTINGS)
    up = _interior((np.asarray(a.normal) == [0, 1, 0]).all(-1) & (np.asarray(voxels.normal) == [0, 1, 0]).all(-1))
    assert up.sum() > 50
    diff = np.abs(np.asarray(a.radiance)[up] - np.asarray(voxels.radiance)[up])
    assert np.median(diff) < 0.05 * np.median(np.asarray(a.radiance)[up])


def test_mesh_renderer_samples_the_texture(textured_quad):
    """A textured quad facing the camera, lit by a sun along its normal, no bounces: each
    quadrant shows its texel's linear colour / pi * E (as the voxels' albedo does)."""
    pytest.importorskip("embreex")
    from jaxvox.io.images import srgb_to_linear

    path, texels = textured_quad
    mesh = jv.load_mesh(path)
    env = jv.sky_environment(sun_direction=(0, 0, 1), sun_irradiance=(2.0, 2.0, 2.0), zenith=0, horizon=0, ground=0)
    result = jv.render_mesh(
        mesh, (0.5, 0.5, 2.0), (0.5, 0.5, 0.0), env=env, albedo="mesh", bounces=0, key=0, fov=20.0, **SETTINGS
    )
    rgb = np.asarray(result.radiance)
    # Pixel rows run top to bottom, as do texture rows (v = 1, y = 1 on top). Quadrant
    # centres, x and y = 0.25 and 0.75, lie where the bilinear lookup blends one colour.
    scale = H / (2 * 2.0 * np.tan(np.radians(10.0)))  # pixels per world unit at distance 2
    for row in (0, 1):
        for col in (0, 1):
            i = int(H / 2 + (row - 0.5) * 0.5 * scale)
            j = int(W / 2 + (col - 0.5) * 0.5 * scale)
            expected = srgb_to_linear(texels[2 * row, 2 * col]) / np.pi * 2.0
            np.testing.assert_allclose(rgb[i, j], expected, atol=1e-4)
    with pytest.raises(jv.JaxvoxError, match="neither a texture nor vertex colours"):
        jv.render_mesh(jv.Mesh(mesh.vertices, mesh.faces), (0.5, 0.5, 2.0), (0.5, 0.5, 0.0), albedo="mesh", **SETTINGS)


def test_cosine_sampling_moments():
    """Cosine-weighted directions: unit, in the hemisphere, E[cos] = 2/3, E[cos^2] = 1/2, no preferred azimuth."""
    import jax

    from jaxvox.render.integrator import _cosine_direction

    rng = np.random.default_rng(3)
    normals = rng.standard_normal((6, 3))
    normals = np.concatenate([np.eye(3), -np.eye(3), normals / np.linalg.norm(normals, axis=1, keepdims=True)])
    u = np.asarray(jax.random.uniform(jax.random.key(0), (40000, 2)))
    for n in normals.astype(np.float32):
        d = np.asarray(_cosine_direction(np.broadcast_to(n, (len(u), 3)), u), np.float64)
        cos = d @ n
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
        assert (cos > 0).all()
        assert abs(cos.mean() - 2 / 3) < 0.01 and abs((cos**2).mean() - 0.5) < 0.01
        tangential = d - cos[:, None] * n
        assert np.linalg.norm(tangential.mean(0)) < 0.01


def test_empty_tree_shows_the_environment():
    mesh = jv.Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    tree = jv.build_dag(jv.voxelize(mesh, jv.Grid(origin=(-1, -1, -1), voxel_size=2 / 16, resolution=16)))
    result = jv.render(
        tree, (0, 0, 3), (0, 0, 0), env=jv.uniform_environment(rgb=(0.25, 0.5, 1.0)), bounces=2, key=0, **SETTINGS
    )
    np.testing.assert_array_equal(np.asarray(result.radiance), np.broadcast_to(np.float32([0.25, 0.5, 1.0]), (H, W, 3)))
    assert np.isinf(np.asarray(result.depth)).all() and (np.asarray(result.normal) == 0).all()


def test_shading_normals_equal_to_the_faces_change_nothing():
    """A flat slab seen from above through its top faces only: per-voxel normals equal to
    the face normal (either way round, or zero rows) render the same bits as face normals."""
    slab = trimesh.creation.box(extents=[2.0, 0.1, 2.0])
    mesh = jv.Mesh(np.asarray(slab.vertices, np.float32), np.asarray(slab.faces, np.int32))
    vox = jv.voxelize(mesh, jv.Grid.fit(mesh, resolution=32))
    tree = jv.build_dag(vox)
    eye, target = (0.05, 1.0, 0.03), (0.0, 0.0, 0.0)
    settings = dict(SETTINGS, env=jv.sky_environment(), fov=20.0, bounces=3, key=3)
    faces = jv.render(tree, eye, target, **settings)
    assert np.isfinite(np.asarray(faces.depth)).all()  # every pixel sees the top faces
    count = int(vox.count)
    for rows in ([0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 0.0]):
        shaded = jv.render(tree, eye, target, normals=np.tile(rows, (count, 1)), **settings)
        np.testing.assert_array_equal(np.asarray(shaded.radiance), np.asarray(faces.radiance))


def test_shading_normals_keep_the_furnace_and_leave_every_face(scene):
    """Random per-voxel normals: albedo 1 under a uniform environment still gives exactly 1
    per path (the mirrored bounces lose no energy), no path starts inside a voxel, and a
    tilted normal changes the image under the sun."""
    tree, eye, target, _ = scene
    count = int(tree.voxel_count)
    normals = np.random.default_rng(0).normal(size=(count, 3)).astype(np.float32)
    result = jv.render(
        tree,
        eye,
        target,
        env=jv.uniform_environment(rgb=1.0),
        albedo=(1.0, 1.0, 1.0),
        normals=normals,
        bounces=48,
        key=1,
        **SETTINGS,
    )
    rgb = np.asarray(result.radiance)
    assert rgb.max() <= 1.0 + 1e-6 and abs(rgb.mean() - 1.0) < 1e-3
    assert int(result.stopped) == 0
    sunny = dict(SETTINGS, env=jv.sky_environment(), bounces=1, key=2)
    plain = np.asarray(jv.render(tree, eye, target, **sunny).radiance)
    tilted = jv.render(tree, eye, target, normals=normals, **sunny)
    assert int(tilted.stopped) == 0 and not np.allclose(np.asarray(tilted.radiance), plain)
    with pytest.raises(jv.JaxvoxError, match="render normals"):
        jv.render(tree, eye, target, normals=normals[:5], **SETTINGS)
    with pytest.raises(jv.JaxvoxError, match="render normals"):
        jv.render(tree, eye, target, normals=np.full((count, 3), np.nan), **SETTINGS)


def test_device_tables_on_the_ladder_are_used_as_they_are(scene):
    """Per-voxel tables: a host array is checked and padded to the voxel-list ladder on
    the host, for `render` to place (a memmap whose file holds the ladder's rows is not
    copied: tests/test_mesh_to_dag.py); a float32 device table already on the ladder is
    taken with no copy (checked on the device), and one that is not valid still gets the
    host path's error."""
    from jaxvox._core.shapes import voxel_bucket
    from jaxvox.render.materials import normal_table, rgb_table

    tree = scene[0]
    rows, resolution = int(tree.voxel_count), tree.grid.resolution
    host = np.random.default_rng(0).uniform(size=(rows, 3)).astype(np.float32)
    albedo = lambda value: rgb_table("render albedo", value, rows, "voxel", (0.7, 0.7, 0.7), resolution)
    table = albedo(host)
    assert isinstance(table, np.ndarray) and table.shape == (voxel_bucket(rows, resolution), 3)
    assert table.shape[0] > rows and not np.shares_memory(table, host)
    np.testing.assert_array_equal(table[:rows], host)
    assert not table[rows:].any()
    device = jnp.asarray(table)
    assert albedo(device) is device and normal_table("render normals", device, rows, resolution) is device
    assert albedo(jnp.asarray(host)).shape == table.shape  # off the ladder: padded
    with pytest.raises(jv.JaxvoxError, match="render albedo: must be finite and non-negative"):
        albedo(-device)
    with pytest.raises(jv.JaxvoxError, match="render normals: must be finite"):
        normal_table("render normals", device.at[3, 1].set(jnp.inf), rows, resolution)


def test_smooth_normals_on_a_staircase_see_the_sun():
    """A slab tilted 25 degrees, voxelized into a staircase, with the slab's own normals
    per voxel and a low sun 20 degrees above its top: the whole top is lit. Shadow rays
    from the voxel faces met the next step of the staircase (acne: 31% of the top
    went dark); they now start `SHADOW_LIFT` edges above the hit along the normal."""
    slab = trimesh.creation.box(extents=[2.0, 0.3, 2.0])
    tilt = np.radians(25.0)
    slab.apply_transform(trimesh.transformations.rotation_matrix(tilt, [0, 0, 1]))
    mesh = jv.Mesh(np.asarray(slab.vertices, np.float32), np.asarray(slab.faces, np.int32))
    vox = jv.voxelize(mesh, jv.Grid.fit(mesh, resolution=32), triangle_ids=True)
    tree = jv.build_dag(vox)
    normals = np.asarray(jv.voxel_attributes(mesh, vox)["normal"])[: int(vox.count)]
    top = np.array([-np.sin(tilt), np.cos(tilt), 0.0])
    # The sun 20 degrees above the top face, across the staircase's steps.
    sun = np.cos(np.radians(20.0)) * np.array([np.cos(tilt), np.sin(tilt), 0.0]) + np.sin(np.radians(20.0)) * top
    env = jv.sky_environment(sun_direction=sun, sun_irradiance=(1.0, 1.0, 1.0), zenith=0, horizon=0, ground=0)
    eye = 1.5 * top
    result = jv.render(tree, eye, (0.0, 0.0, 0.0), env=env, normals=normals, bounces=0, fov=30.0, key=1, **SETTINGS)
    seen = _interior(np.isfinite(np.asarray(result.depth)))
    lit = (np.asarray(result.radiance) > 0).all(-1)
    assert seen.sum() > 0.5 * W * H
    assert lit[seen].mean() > 0.995, lit[seen].mean()
