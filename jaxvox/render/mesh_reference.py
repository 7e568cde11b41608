"""A reference path tracer for triangle meshes, with Embree: `render`'s estimator on the exact surface.

`render_mesh` shares the integrator's camera rays, shading, lighting and random numbers
(`jaxvox.render.integrator`), so that a voxel render and a mesh render of the same scene
with the same key differ only by the geometry. Embree (embreex, the ``bench`` extra)
traces on the host, one call per path segment, and is imported only when a mesh is
rendered.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.checks import check_type, refuse
from jaxvox._core.errors import JaxvoxError
from jaxvox.io.images import srgb_to_linear
from jaxvox.mesh import sample_texture, validate_mesh
from jaxvox.render.environment import Environment, sky_environment
from jaxvox.render.integrator import (
    LIGHT_STREAM,
    RenderResult,
    Surface,
    as_key,
    camera_path,
    camera_rays,
    check_settings,
    checked_camera,
    environment_sample,
    progress_bar,
    shade,
    uniforms,
)
from jaxvox.render.materials import rgb_table
from jaxvox.trace import valid_rays


def _embree(mesh):
    """An Embree intersector of `mesh`: (o [N, 3], d [N, 3]) -> (t, prim, u, v, unit Ng), numpy."""
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError:
        raise JaxvoxError("render_mesh needs Embree: pip install 'jaxvox[bench]' (embreex)") from None
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, np.asarray(mesh.vertices, np.float32)[np.asarray(mesh.faces)])

    def intersect(o, d):
        out = scene.run(np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32), output=1)
        ng = out["Ng"]
        length = np.linalg.norm(ng, axis=-1, keepdims=True)
        return out["tfar"], out["primID"], out["u"], out["v"], ng / np.where(length > 0, length, 1.0)

    return intersect


@functools.partial(jax.jit, static_argnames=("width", "height"))
def _mesh_camera(camera, key, ids, valid, *, width, height):
    path, keys = camera_path(camera, key, jnp.where(valid, ids, 0), width=width, height=height)
    return path._replace(direction=jnp.where(valid[:, None], path.direction, 0.0)), keys


@functools.partial(jax.jit, static_argnames=("first",))
def _mesh_shade(path, surf, visible, light, keys, k, rho, emitted, env, last, *, first):
    return shade(
        path,
        surf,
        visible,
        uniforms(keys, k + 1, 2),
        rho=rho,
        emitted=emitted,
        env=env,
        first=first,
        last=last,
        light=light,
    )


@jax.jit
def _mesh_light(env, surf, keys, k, last):
    return environment_sample(env, surf, uniforms(keys, LIGHT_STREAM + k, 3), last)


def _mesh_tables(mesh, albedo, emission):
    """(albedo, per-vertex flag, emission) for `render_mesh`: [F, 3] per-face tables, or
    None and True for the mesh's own colours (interpolated at each hit)."""
    faces = mesh.num_faces
    if isinstance(albedo, str):
        if albedo != "mesh":
            raise refuse("render_mesh albedo", "must be an RGB triple, a [faces, 3] array or 'mesh'", albedo)
        if mesh.colors is None and mesh.texture is None:
            raise refuse(
                "render_mesh albedo",
                "'mesh' needs a texture or vertex colours, but the mesh has neither a texture nor vertex colours",
                albedo,
            )
        rho, per_vertex = None, True
    else:
        rho, per_vertex = np.asarray(rgb_table("render_mesh albedo", albedo, faces, "face", (0.7, 0.7, 0.7))), False
    return rho, per_vertex, np.asarray(rgb_table("render_mesh emission", emission, faces, "face", (0.0, 0.0, 0.0)))


def _mesh_colour(mesh, face, weights):
    """Linear albedo [N, 3] of a mesh's texture (or vertex colours) at barycentric `weights` [N, 3] of `face` [N]."""
    corners = np.asarray(mesh.faces)[face]
    if mesh.texture is not None:
        uv = np.einsum("nk,nkd->nd", weights, np.asarray(mesh.uvs)[corners])
        colour = np.asarray(sample_texture(mesh.texture, jnp.asarray(uv, jnp.float32)))
    else:
        colour = np.einsum("nk,nkd->nd", weights, np.asarray(mesh.colors)[corners])
    return srgb_to_linear(colour[:, :3]).astype(np.float32)


def render_mesh(
    mesh,
    eye,
    target,
    *,
    env: Environment | None = None,
    albedo=None,
    emission=None,
    width: int = 320,
    height: int = 240,
    fov: float = 40.0,
    up=(0.0, 1.0, 0.0),
    spp: int = 16,
    bounces: int = 8,
    key=0,
    batch_rays: int = 1 << 18,
    progress: bool | None = None,
) -> RenderResult:
    """Path-traces a triangle mesh with Embree: `render`'s estimator on the exact surface.

    Needs embreex (the ``bench`` extra). The shading, the lighting and the random
    numbers are `render`'s (the same key gives the same camera rays and bounce samples),
    so a voxel render and a mesh render differ only by the geometry. Surfaces are
    two-sided Lambertian with the geometric triangle normal; bounce origins move off the
    surface by ``1e-4`` of the mesh's extent. Embree runs on the host, one call per path
    segment, so this is not jittable.

    Args:
      mesh: a `Mesh`.
      albedo: an RGB triple, a [F, 3] per-face array, or ``"mesh"``: the mesh's texture
        or else its vertex colours (sRGB, decoded to linear) at the hit, as
        `voxel_attributes` takes them for voxels. Default 0.7 grey.
      emission: None, an RGB triple or a [F, 3] per-face array.
      eye, target, env, width, height, fov, up, spp, bounces, key, batch_rays, progress:
        as in `render`.

    Returns:
      A `RenderResult`; ``depth`` and ``normal`` are those of the triangles (normals face
      the camera).

    Raises:
      JaxvoxError: a malformed mesh, not an `Environment`, bad settings, camera, albedo
        or emission, or no Embree.
    """
    validate_mesh(mesh)
    check_settings("render_mesh", width, height, spp, bounces, batch_rays)
    env = sky_environment() if env is None else check_type("render_mesh env", env, Environment)
    rho_table, per_vertex, emit_table = _mesh_tables(mesh, albedo, emission)
    vertices = np.asarray(mesh.vertices, np.float64)
    eps = 1e-4 * float(np.max(vertices.max(0) - vertices.min(0))) if len(vertices) else 1e-4
    intersect = _embree(mesh)
    camera = checked_camera("render_mesh", eye, target, up, fov)
    key = as_key(key)
    total = width * height * spp
    batch = min(int(batch_rays), total)
    image = np.zeros((width * height, 3), np.float64)
    sun = np.asarray(env.sun_direction)

    def surface(o, d):
        live = np.asarray(valid_rays(o, d))
        n = len(o)
        t, prim, u, v, ng = (
            np.full(n, np.inf, np.float32),
            np.full(n, -1, np.int32),
            np.zeros(n, np.float32),
            np.zeros(n, np.float32),
            np.zeros((n, 3), np.float32),
        )
        if live.any():
            t[live], prim[live], u[live], v[live], ng[live] = intersect(o[live], d[live])
        hit = prim >= 0
        ng = np.where((np.sum(ng * d, -1) > 0)[:, None], -ng, ng)
        point = np.where(hit[:, None], o + np.where(hit, t, 0)[:, None] * d + eps * ng, o).astype(np.float32)
        face = np.maximum(prim, 0)
        if per_vertex:
            rho = _mesh_colour(mesh, face, np.stack([1 - u - v, u, v], -1))
        else:
            rho = rho_table[np.minimum(face, len(rho_table) - 1)]
        emitted = emit_table[np.minimum(face, len(emit_table) - 1)]
        surf = Surface(
            hit=hit, escaped=live & ~hit, stopped=np.zeros(n, bool), point=point, normal=ng, shading=ng, index=face
        )
        return surf, t, rho.astype(np.float32), emitted

    n_batches = -(-total // batch)
    with progress_bar(n_batches, progress, "render mesh") as bar:
        for b in range(n_batches):
            ids = np.int32(b * batch) + np.arange(batch, dtype=np.int32)
            valid = ids < total
            path, keys = _mesh_camera(camera, key, jnp.asarray(ids), jnp.asarray(valid), width=width, height=height)
            for k in range(bounces + 1):
                o, d = np.asarray(path.origin), np.asarray(path.direction)
                if not np.asarray(valid_rays(o, d)).any():
                    break
                surf, _, rho, emitted = surface(o, d)
                visible = np.zeros(batch, np.float32)
                if env.sun:
                    lit = surf.hit & (np.sum(surf.normal * sun, -1) > 0)
                    if lit.any():
                        _, prim, _, _, _ = intersect(surf.point[lit], np.broadcast_to(sun, (int(lit.sum()), 3)))
                        visible[lit] = prim < 0
                surf = jax.tree.map(jnp.asarray, surf)
                light = None
                if env.sampled:
                    d, pdf = (np.asarray(a) for a in _mesh_light(env, surf, keys, k, jnp.asarray(k >= bounces)))
                    seen = np.zeros(batch, np.float32)
                    use = pdf > 0
                    if use.any():
                        seen[use] = intersect(np.asarray(surf.point)[use], d[use])[1] < 0
                    light = (jnp.asarray(d), jnp.asarray(pdf), jnp.asarray(seen))
                path = _mesh_shade(
                    path,
                    surf,
                    jnp.asarray(visible),
                    light,
                    keys,
                    k,
                    jnp.asarray(rho),
                    jnp.asarray(emitted),
                    env,
                    jnp.asarray(k >= bounces),
                    first=k == 0,
                )
            np.add.at(image, ids[valid] % (width * height), np.asarray(path.radiance, np.float64)[valid])
            bar.update(1)
    j, i = np.meshgrid(np.arange(width), np.arange(height))
    d = np.asarray(
        camera_rays(
            camera,
            jnp.asarray(j.reshape(-1) + 0.5, jnp.float32),
            jnp.asarray(i.reshape(-1) + 0.5, jnp.float32),
            width=width,
            height=height,
        )
    )
    surf, t, _, _ = surface(np.broadcast_to(np.asarray(camera[0]), d.shape).astype(np.float32), d)
    depth = np.where(surf.hit, t, np.inf).astype(np.float32).reshape(height, width)
    normal = np.where(surf.hit[:, None], surf.normal, 0.0).astype(np.float32).reshape(height, width, 3)
    return RenderResult(
        radiance=jnp.asarray((image / spp).astype(np.float32).reshape(height, width, 3)),
        depth=jnp.asarray(depth),
        normal=jnp.asarray(normal),
        stopped=jnp.int32(0),
    )
