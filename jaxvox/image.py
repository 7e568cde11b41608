"""Image files: linear HDR EXR (OpenEXR) with extra channels, tone mapping, sRGB PNG.

EXR files hold 32-bit float channels, one 2-D array per channel name, losslessly
compressed (ZIP), so a write followed by a read gives back the same bits. The renderer
writes ``R``, ``G``, ``B`` (linear radiance), ``Z`` (depth) and ``N.X``, ``N.Y``,
``N.Z`` (normal), the usual layer naming of compositing tools.
"""

from __future__ import annotations

import os

import numpy as np

from jaxvox._errors import JaxvoxError

TONEMAP_CURVES = ("aces", "clip")  # `tonemap` curves


def write_exr(path: str | os.PathLike, channels: dict) -> None:
    """Writes float32 channels to a scanline EXR file (ZIP compression, lossless).

    Args:
      path: destination ``.exr`` file.
      channels: mapping of channel name (e.g. ``"R"``, ``"Z"``, ``"N.X"``) to a
        [H, W] array (converted to float32); all of the same shape.

    Raises:
      JaxvoxError: no channels, channels of different or non-2-D shapes.
    """
    import OpenEXR

    if not channels:
        raise JaxvoxError("write_exr: no channels to write")
    arrays = {str(name): np.ascontiguousarray(np.asarray(a, np.float32)) for name, a in channels.items()}
    shapes = {a.shape for a in arrays.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise JaxvoxError(f"write_exr: channels must all be [H, W] arrays of one shape, got {sorted(shapes)}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, arrays) as exr:
        exr.write(os.fspath(path))


def read_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Reads every channel of an EXR file: ``{name: [H, W] float32}`` (half and uint become float32).

    Raises:
      JaxvoxError: missing or unreadable file.
    """
    import OpenEXR

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise JaxvoxError(f"EXR file not found: {path}")
    try:
        with OpenEXR.File(path, separate_channels=True) as exr:
            return {name: np.asarray(c.pixels, np.float32) for name, c in exr.channels().items()}
    except (RuntimeError, ValueError) as exc:
        raise JaxvoxError(f"cannot read EXR file {path}: {exc}") from None


def tonemap(radiance, *, exposure: float = 0.0, curve: str = "aces") -> np.ndarray:
    """Linear radiance [..., 3] -> 8-bit sRGB [..., 3] uint8.

    Scales by ``2**exposure``, applies the tone curve (``"aces"``: Narkowicz's fit of the
    ACES filmic curve, which rolls highlights off; ``"clip"``: clamp to [0, 1]), then
    the sRGB transfer function. NaN becomes 0.
    """
    if curve not in TONEMAP_CURVES:
        raise JaxvoxError(f"unknown tone curve {curve!r}; expected one of {TONEMAP_CURVES}")
    x = np.nan_to_num(np.asarray(radiance, np.float64), nan=0.0, posinf=1e30) * 2.0**exposure
    x = np.maximum(x, 0.0)
    if curve == "aces":
        x = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14)
    x = np.clip(x, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return (srgb * 255.0 + 0.5).astype(np.uint8)


def srgb_to_linear(c):
    """sRGB-encoded values in [0, 1] -> linear values (numpy, any shape)."""
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def write_png(path: str | os.PathLike, rgb) -> None:
    """Writes an 8-bit image ([H, W] or [H, W, 3] uint8) as PNG."""
    import imageio.v3 as iio

    iio.imwrite(os.fspath(path), np.asarray(rgb, np.uint8), extension=".png")
