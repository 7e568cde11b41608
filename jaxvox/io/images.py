"""Image files: linear HDR EXR (OpenEXR) with extra channels, tone mapping, sRGB PNG, Radiance HDR.

EXR files hold 32-bit float channels, one 2-D array per channel name, losslessly
compressed (ZIP), so a write followed by a read gives back the same bits. A render's
channels are written by `jaxvox.render.output.save_render` with these functions.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np

from jaxvox._core.checks import check_choice, check_number, check_output_path, refuse
from jaxvox.io.files import read_bytes

TONEMAP_CURVES = ("aces", "clip")  # `tonemap` curves


def write_exr(path: str | os.PathLike, channels: dict) -> None:
    """Writes float32 channels to a scanline EXR file (ZIP compression, lossless).

    Args:
      path: destination ``.exr`` file.
      channels: mapping of channel name (e.g. ``"R"``, ``"Z"``, ``"N.X"``) to a
        [H, W] array (converted to float32); all of the same shape.

    Raises:
      JaxvoxError: a missing folder, no channels, non-numeric channels, or channels of
        different or non-2-D shapes.
    """
    import OpenEXR

    path = check_output_path("write_exr path", path)
    if not isinstance(channels, Mapping) or not channels:
        raise refuse("write_exr channels", "must be a non-empty dict of channel name to [H, W] array", channels)
    arrays = {}
    for name, a in channels.items():
        try:
            arrays[str(name)] = np.ascontiguousarray(np.asarray(a, np.float32))
        except (TypeError, ValueError):
            raise refuse(f"write_exr channels[{name!r}]", "must be an [H, W] array of numbers", a) from None
    shapes = sorted({a.shape for a in arrays.values()})
    if len(shapes) != 1 or len(shapes[0]) != 2:
        raise refuse("write_exr channels", "must all be [H, W] arrays of one shape", shapes)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, arrays) as exr:
        exr.write(path)


def read_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Reads every channel of an EXR file: ``{name: [H, W] float32}`` (half and uint become float32).

    Raises:
      JaxvoxError: missing or unreadable file.
    """
    import OpenEXR

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise refuse(
            "read_exr path", "is a directory, expected a file" if os.path.isdir(path) else "file not found", path
        )
    try:
        with OpenEXR.File(path, separate_channels=True) as exr:
            return {name: np.asarray(c.pixels, np.float32) for name, c in exr.channels().items()}
    except (RuntimeError, ValueError) as exc:
        raise refuse("read_exr path", f"not a readable EXR file ({exc})", path) from None


def read_hdr(path: str | os.PathLike) -> np.ndarray:
    """Reads a Radiance RGBE (``.hdr``) image: [H, W, 3] float32, row 0 at the top.

    Handles flat and run-length encoded scanlines and the standard ``-Y H +X W``
    orientation (the one every common tool writes).

    Raises:
      JaxvoxError: missing file, not an RGBE file, another orientation, or truncated data.
    """
    path = os.fspath(path)
    data = read_bytes("read_hdr path", path)
    if not data.startswith(b"#?"):
        raise refuse("read_hdr path", "not a Radiance HDR file", path)
    end = data.find(b"\n\n")
    line_end = data.find(b"\n", end + 2)
    if end < 0 or line_end < 0:
        raise refuse("read_hdr path", "truncated HDR header", path)
    if b"FORMAT=" in data[:end] and b"FORMAT=32-bit_rle_rgbe" not in data[:end]:
        raise refuse("read_hdr path", "only 32-bit_rle_rgbe HDR files are read", path)
    size = data[end + 2 : line_end].split()
    if len(size) != 4 or size[0] != b"-Y" or size[2] != b"+X" or not (size[1].isdigit() and size[3].isdigit()):
        raise refuse(
            "read_hdr path", f"unsupported HDR size line {data[end + 2 : line_end]!r} (expected -Y H +X W)", path
        )
    height, width = int(size[1]), int(size[3])
    buf, pos = np.frombuffer(data, np.uint8), line_end + 1
    # A run-length encoded pixel takes at least 8/127 bytes (two per run of up to 127 per channel).
    if height * width > 16 * (len(data) - pos):
        raise refuse(
            "read_hdr path", f"truncated HDR pixel data ({len(data) - pos} bytes for {height}x{width} pixels)", path
        )
    rgbe = np.empty((height, width, 4), np.uint8)
    try:
        for row in range(height):
            head = buf[pos : pos + 4]
            if 8 <= width < 32768 and head[0] == 2 and head[1] == 2 and (int(head[2]) << 8 | head[3]) == width:
                pos += 4
                for c in range(4):  # each channel run-length encoded on its own
                    x = 0
                    while x < width:
                        count = int(buf[pos])
                        if count > 128:
                            rgbe[row, x : x + count - 128, c] = buf[pos + 1]
                            x, pos = x + count - 128, pos + 2
                        else:
                            if count == 0 or x + count > width:
                                raise IndexError
                            rgbe[row, x : x + count, c] = buf[pos + 1 : pos + 1 + count]
                            x, pos = x + count, pos + 1 + count
            else:
                rgbe[row] = buf[pos : pos + 4 * width].reshape(width, 4)
                pos += 4 * width
    except (IndexError, ValueError):
        raise refuse("read_hdr path", "truncated or corrupt HDR pixel data", path) from None
    exponent = rgbe[..., 3:].astype(np.int32)
    scale = np.where(exponent > 0, np.ldexp(1.0, exponent - 136), 0.0)
    return (rgbe[..., :3].astype(np.float64) * scale).astype(np.float32)


def tonemap(radiance, *, exposure: float = 0.0, curve: str = "aces") -> np.ndarray:
    """Linear radiance [..., 3] -> 8-bit sRGB [..., 3] uint8.

    Scales by ``2**exposure``, applies the tone curve (``"aces"``: Narkowicz's fit of the
    ACES filmic curve, which rolls highlights off; ``"clip"``: clamp to [0, 1]), then
    the sRGB transfer function. NaN becomes 0.

    Raises:
      JaxvoxError: an unknown curve, an exposure that is not a finite number, or
        radiance that is not an array of numbers.
    """
    check_choice("tonemap curve", curve, TONEMAP_CURVES)
    exposure = check_number("tonemap exposure", exposure)
    try:
        x = np.asarray(radiance, np.float64)
    except (TypeError, ValueError):
        raise refuse("tonemap radiance", "must be an array of numbers", radiance) from None
    x = np.nan_to_num(x, nan=0.0, posinf=1e30) * 2.0**exposure
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
    """Writes an 8-bit image ([H, W] grey, [H, W, 3] RGB or [H, W, 4] RGBA; uint8, or
    integers in [0, 255]) as PNG.

    Raises:
      JaxvoxError: another shape, values outside [0, 255] or fractional, a missing folder.
    """
    import imageio.v3 as iio

    a = np.asarray(rgb)
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (3, 4))) or min(a.shape[:2], default=0) < 1:
        raise refuse("write_png rgb", "must be an [H, W], [H, W, 3] or [H, W, 4] image", a.shape)
    if a.dtype != np.uint8 and not (a.dtype.kind in "iuf" and np.all((a >= 0) & (a <= 255) & (a == np.round(a)))):
        raise refuse("write_png rgb", "must be uint8 or integers in [0, 255] (tone-map float images first)", a.dtype)
    iio.imwrite(check_output_path("write_png path", path), a.astype(np.uint8), extension=".png")
