"""Environment lights: lat-long lookup, the sky and the sun disc, and importance sampling of an image."""

from __future__ import annotations

import numpy as np
import trimesh

import jaxvox as jv


def test_environment_lookup(tmp_path):
    image = np.zeros((4, 8, 3), np.float32)
    image[0] = 1.0  # the row looking up
    image[2, 4] = [0.0, 5.0, 0.0]  # below the horizon, just right of -z
    np.save(tmp_path / "env.npy", image)
    env = jv.load_environment(tmp_path / "env.npy")
    out = np.asarray(env.radiance(np.array([[0, 1, 0], [0.01, -0.2, -1.0], [0, -1, 0]], np.float32)))
    np.testing.assert_array_equal(out, [[1, 1, 1], [0, 5, 0], [0, 0, 0]])
    uniform = jv.uniform_environment(rgb=(0.1, 0.2, 0.3))
    np.testing.assert_allclose(
        np.asarray(uniform.radiance(np.eye(3, dtype=np.float32))), np.tile([0.1, 0.2, 0.3], (3, 1)), rtol=1e-7
    )
    sky = jv.sky_environment(sun_direction=(0, 1, 0))
    assert np.asarray(sky.camera_radiance(np.array([[0, 1, 0]], np.float32)))[0, 0] > 1e3  # the sun disc
    assert np.asarray(sky.radiance(np.array([[0, 1, 0]], np.float32)))[0, 0] < 1.0


def test_environment_importance_sampling(tmp_path):
    """A small bright patch in a black environment over a slab, one bounce: the patch's
    irradiance is exact (sum of L * integral of cos over each pixel), both estimators
    are unbiased, importance sampling with MIS is far less noisy, and sampling's pdf is
    a density (E[1 / pdf] = 4 pi) that `Environment.pdf` reproduces."""
    import jax

    h, w = 16, 32
    image = np.zeros((h, w, 3), np.float32)
    image[4:6, 10:12] = 500.0
    np.save(tmp_path / "patch.npy", image)
    slab = trimesh.creation.box(extents=[2.0, 0.2, 2.0])
    mesh = jv.Mesh(np.asarray(slab.vertices, np.float32), np.asarray(slab.faces, np.int32))
    tree = jv.build_dag(jv.voxelize(mesh, jv.Grid.fit(mesh, resolution=16)))
    edges = np.cos(np.pi * np.arange(h + 1) / h)
    irradiance = 2 * 500.0 * 2 * np.pi / w * sum((edges[r] ** 2 - edges[r + 1] ** 2) / 2 for r in (4, 5))
    expected = 0.5 / np.pi * irradiance
    spread = {}
    for importance in (False, True):
        env = jv.load_environment(tmp_path / "patch.npy", importance=importance)
        assert env.sampled == importance
        result = jv.render(
            tree,
            (0.0, 3.0, 0.01),
            (0.0, 0.0, 0.0),
            env=env,
            albedo=(0.5, 0.5, 0.5),
            bounces=1,
            key=1,
            width=48,
            height=48,
            spp=4,
            batch_rays=48 * 48 * 4,
            fov=30.0,
        )
        top = np.asarray(result.radiance)[..., 0][(np.asarray(result.normal) == [0, 1, 0]).all(-1)]
        assert len(top) > 2000
        spread[importance] = top.std()
        assert abs(top.mean() - expected) < 4 * top.std() / np.sqrt(len(top)), (importance, top.mean(), expected)
    assert spread[True] < 0.1 * spread[False]
    np.save(tmp_path / "random.npy", np.random.default_rng(0).random((8, 16, 3)).astype(np.float32) ** 4)
    env = jv.load_environment(tmp_path / "random.npy")
    d, pdf = env.sample(jax.random.uniform(jax.random.key(0), (200_000, 3)))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(d), axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(env.pdf(d)), np.asarray(pdf), rtol=1e-5)
    assert abs(np.mean(1 / np.asarray(pdf)) / (4 * np.pi) - 1) < 0.02
