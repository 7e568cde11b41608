"""Pictures of voxel sets as PNG files, with no plotting library (numpy + imageio)."""

from __future__ import annotations

import numpy as np


def projection_image(ijk: np.ndarray, resolution: int, axis: int, size: int = 384) -> np.ndarray:
    """Depth-shaded orthographic projection of voxels along `axis`.

    Args:
      ijk: [N, 3] int voxel indices.
      resolution: grid resolution R.
      axis: 0, 1 or 2, the viewing axis (looking from the high side).
      size: output edge in pixels (voxels are binned when R > size).

    Returns:
      uint8 [size, size] image: nearer voxels brighter, empty pixels black.
    """
    scale = max(resolution // size, 1)
    n = resolution // scale
    a, b = [c for c in range(3) if c != axis]
    u, v = ijk[:, a] // scale, ijk[:, b] // scale
    depth = np.full(n * n, -1, np.int64)
    np.maximum.at(depth, u * n + v, ijk[:, axis].astype(np.int64))
    shade = np.where(depth >= 0, 60 + 195 * (depth + 1) / resolution, 0).reshape(n, n)
    img = np.flipud(shade.T).astype(np.uint8)  # b up, a right
    reps = max(size // n, 1)
    return np.kron(img, np.ones((reps, reps), np.uint8))


def save_projections(path: str, sets: dict[str, np.ndarray], resolution: int, size: int = 384) -> None:
    """Writes a PNG with one row per voxel set and one column per viewing axis (x, y, z)."""
    import imageio.v3 as iio

    rows = []
    for ijk in sets.values():
        tiles = [projection_image(ijk, resolution, axis, size) for axis in (0, 1, 2)]
        gap = np.full((tiles[0].shape[0], 8), 255, np.uint8)
        rows.append(np.concatenate([tiles[0], gap, tiles[1], gap, tiles[2]], axis=1))
    sep = np.full((8, rows[0].shape[1]), 255, np.uint8)
    out = rows[0]
    for r in rows[1:]:
        out = np.concatenate([out, sep, r], axis=0)
    iio.imwrite(path, out)


def hit_image(hit, shading: str = "normal") -> np.ndarray:
    """An 8-bit RGB image of a traced `Hit` of shape [H, W]: white where rays missed.

    ``shading="normal"`` maps the entry face normal n to ``0.5 + 0.5 n`` (rays starting
    inside a voxel get mid grey); ``"depth"`` shades near hits bright and far hits dark.
    """
    from jaxvox.trace import HIT

    hits = np.asarray(hit.status) == HIT
    if shading == "normal":
        rgb = 0.5 + 0.5 * np.asarray(hit.normal)
    elif shading == "depth":
        t = np.asarray(hit.t)
        lo, hi = (np.min(t[hits]), np.max(t[hits])) if hits.any() else (0.0, 1.0)
        rgb = np.repeat((0.9 - 0.75 * (t - lo) / max(hi - lo, 1e-12))[..., None], 3, axis=-1)
    else:
        raise ValueError(f"unknown shading {shading!r}; expected 'normal' or 'depth'")
    rgb = np.where(hits[..., None], rgb, 1.0)
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
