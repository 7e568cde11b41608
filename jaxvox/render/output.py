"""`save_render`: a render as a linear EXR and a tone-mapped sRGB PNG.

The EXR holds a render's ``R``, ``G``, ``B`` (linear radiance), ``Z`` (depth, +inf where
the pixel sees no surface unless it is given a finite ``far``), ``A`` (coverage) and
``N.X``, ``N.Y``, ``N.Z`` (normal), the usual layer naming of compositing tools.
"""

from __future__ import annotations

import os

import numpy as np

from jaxvox._core.checks import check_number, check_output_path, check_type
from jaxvox.io.images import tonemap, write_exr, write_png
from jaxvox.render.integrator import RenderResult


def save_render(
    path: str | os.PathLike,
    result: RenderResult,
    *,
    exposure: float = 0.0,
    curve: str = "aces",
    far: float = float("inf"),
) -> tuple[str, str]:
    """Writes a render as a linear EXR at `path` and a tone-mapped sRGB PNG beside it.

    The EXR holds float32 channels ``R, G, B`` (linear radiance, the environment
    included: not premultiplied), ``Z`` (depth: the distance from the eye to the surface
    seen through the pixel centre, ``far`` where that ray escapes), ``A`` (coverage: 1
    where the pixel centre sees a surface, 0 where it sees the environment; use it to
    mask ``Z`` and the normals or to composite) and ``N.X, N.Y, N.Z`` (unit normal, 0
    where the ray escapes). The PNG has the same name with the suffix ``.png``.

    Args:
      path: the ``.exr`` file to write.
      result: a `RenderResult` from `render` or `render_mesh`.
      exposure: stops applied before tone mapping the PNG (the EXR stays linear).
      curve: the PNG's tone curve, one of `jaxvox.io.images.TONEMAP_CURVES`.
      far: the depth written where the ray escapes; ``inf`` by default (legal in EXR,
        and what `RenderResult.depth` holds), or a finite value for tools that expect one.

    Returns:
      (exr path, png path).
    """
    path = check_output_path("save_render path", path)
    far = check_number("save_render far", far, above=0.0, finite=False)
    check_number("save_render exposure", exposure)
    check_type("save_render result", result, RenderResult)
    rgb, depth, normal = (np.asarray(a) for a in (result.radiance, result.depth, result.normal))
    covered = np.isfinite(depth)
    channels = {
        "R": rgb[..., 0],
        "G": rgb[..., 1],
        "B": rgb[..., 2],
        "Z": np.where(covered, depth, far),
        "A": covered.astype(np.float32),
        "N.X": normal[..., 0],
        "N.Y": normal[..., 1],
        "N.Z": normal[..., 2],
    }
    png = os.path.splitext(path)[0] + ".png"
    write_exr(path, channels)
    write_png(png, tonemap(rgb, exposure=exposure, curve=curve))
    return path, png
