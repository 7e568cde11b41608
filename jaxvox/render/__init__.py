"""A diffuse path tracer over voxel octrees and DAGs, lit by an environment.

Every voxel is a Lambertian (diffuse) surface with a per-voxel albedo and an optional
per-voxel emitted radiance; the light comes from an `Environment`: a lat-long image, a
uniform colour or a gradient sky, and optionally a sun. `render` estimates each pixel by
unbiased Monte Carlo path tracing (cosine-weighted bounces, next-event estimation of the
sun and of an importance-sampled environment image, combined by multiple importance
sampling) and returns a `RenderResult`: radiance, depth and normal images, written to EXR
and PNG files by `jaxvox.save_render`. The same key and settings give the same bits,
however the samples are split into batches (up to the order of float32 sums).

One module per concern:

* `jaxvox.render.environment`: `Environment`, `uniform_environment`, `sky_environment`,
  `load_environment`, and the importance-sampling table of an environment image;
* `jaxvox.render.integrator`: `render`, `RenderResult`, the path state, shading, and
  the voxel surface a hit leaves from (the estimator in detail is in its docstring);
* `jaxvox.render.mesh_reference`: `render_mesh`, the same estimator on a triangle mesh
  traced by Embree, as a reference for the voxel renders;
* `jaxvox.render.materials`: per-voxel albedo and emission tables (`voxel_albedo`,
  `box_emission`).
"""

from jaxvox.render.environment import Environment, load_environment, sky_environment, uniform_environment
from jaxvox.render.integrator import RenderResult, render
from jaxvox.render.materials import box_emission, voxel_albedo
from jaxvox.render.mesh_reference import render_mesh
from jaxvox.render.output import save_render

__all__ = [
    "Environment",
    "RenderResult",
    "box_emission",
    "load_environment",
    "render",
    "render_mesh",
    "save_render",
    "sky_environment",
    "uniform_environment",
    "voxel_albedo",
]
