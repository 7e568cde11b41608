"""Voxel sets in files other programs exchange: binvox, npz, and PLY / OBJ surfaces.

=========  ======================================================================
extension  content
=========  ======================================================================
.binvox    Patrick Min's binvox format (viewvox, binvox-rw, trimesh): an ASCII header
           ``#binvox 1``, ``dim R R R``, ``translate tx ty tz``, ``scale s``, ``data``,
           then (value, count) byte pairs run-length encoding the dense grid with
           the y index varying fastest, then z, then x (linear index
           ``(i * R + k) * R + j`` for voxel (i, j, k)); counts are 1..255. Placement:
           voxel (i, j, k) spans ``translate + (i, j, k) * scale / R`` to
           ``translate + (i+1, j+1, k+1) * scale / R``, so ``translate`` is the grid's
           origin and ``scale = R * voxel_size`` its edge.
.npz       numpy arrays ``ijk`` (int32 [N, 3], Morton order), ``origin`` (float32
           [3]), ``voxel_size`` (float32 []), ``resolution`` (int) and ``mode`` (str),
           as written by ``jaxvox voxelize``.
.ply .obj  the voxels' boundary surface (`voxels_to_mesh`) as a triangle mesh
           (`save_mesh`); written only.
=========  ======================================================================

Binvox runs are made from the sorted linear indices of the voxels (gaps become runs of
0, consecutive indices runs of 1) and read back with `np.repeat` over the runs, so no
dense ``R^3`` array is formed either way. (trimesh places binvox voxel centres at
``translate + index * scale / (R - 1)``, a different convention; the indices agree.)
"""

from __future__ import annotations

import io
import os

import numpy as np

from jaxvox._core.checks import check_choice, check_output_path, check_type, refuse
from jaxvox._core.errors import JaxvoxError
from jaxvox.grid import MAX_RESOLUTION, Grid
from jaxvox.io.files import read_bytes
from jaxvox.io.meshes import file_format, save_mesh
from jaxvox.voxelize import CONSERVATIVE, SET_MODES, Voxels
from jaxvox.voxelize.surface import voxels_to_mesh

SAVE_FORMATS = (".binvox", ".npz", ".ply", ".obj")
LOAD_FORMATS = (".binvox", ".npz")
BINVOX_MAX_RUN = 255  # largest count of one binvox run
BINVOX_MAX_PAIRS = 1 << 31  # most (value, count) pairs `save_binvox` writes (4 GiB)
_BINVOX_HEADER_LINES = 64  # lines read before giving up on finding "data"
_NPZ_KEYS = ("ijk", "origin", "voxel_size", "resolution", "mode")


def _read(what: str, path: str) -> bytes:
    """The bytes of the file at `path`; a `JaxvoxError` naming it when unreadable or empty."""
    data = read_bytes(what, path)
    if not data:
        raise refuse(what, "is an empty file", path)
    return data


def _voxels(what: str, path: str, ijk, origin, voxel_size, resolution: int, mode: str) -> Voxels:
    """`Voxels.from_coords` on a file's contents; its refusals name the file."""
    try:
        return Voxels.from_coords(ijk, Grid(origin, voxel_size, resolution), mode=mode)
    except JaxvoxError as exc:
        raise refuse(what, f"holds bad voxel data ({exc})", path) from exc


def _binvox_order(ijk: np.ndarray, resolution: int) -> np.ndarray:
    """Linear binvox indices (y fastest, then z, then x): int [N, 3] -> int64 [N]."""
    i, j, k = (ijk[:, a].astype(np.int64) for a in range(3))
    return (i * resolution + k) * resolution + j


def _runs(values: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Runs of any length as binvox bytes: every run split into counts of at most 255.

    Args:
      values: uint8 [n] value of each run (0 or 1).
      lengths: int64 [n] positive run lengths.

    Returns:
      uint8 [2 * pairs] interleaved (value, count) bytes.
    """
    pieces = -(-lengths // BINVOX_MAX_RUN)  # ceil
    counts = np.full(int(pieces.sum()), BINVOX_MAX_RUN, np.int64)
    counts[np.cumsum(pieces) - 1] = lengths - BINVOX_MAX_RUN * (pieces - 1)
    return np.stack([np.repeat(values, pieces), counts], axis=1).astype(np.uint8).reshape(-1)


def save_binvox(path: str | os.PathLike, voxels: Voxels) -> None:
    """Writes a voxel set as a binvox file (``dim R R R``, translate = origin, scale = R * h).

    The file stores every voxel of the ``R^3`` grid, run-length encoded: at least
    ``2 R^3 / 255`` bytes however few voxels are set.

    Args:
      path: destination file.
      voxels: a `Voxels` set (one, not a batch).

    Raises:
      JaxvoxError: not a `Voxels`, an overflowed set, a missing folder, or a grid whose
        empty space needs more than `BINVOX_MAX_PAIRS` runs (use .npz).
    """
    path = check_output_path("save_binvox path", path)
    check_type("save_binvox voxels", voxels, Voxels)
    grid = voxels.grid
    r = grid.resolution
    linear = np.sort(_binvox_order(voxels.to_numpy(), r))
    # Set voxels form runs of consecutive indices: the grid splits at their first and
    # one-past-last indices into alternating runs of 0 and 1 (the first and last may be empty).
    starts = np.flatnonzero(np.diff(linear, prepend=-2) != 1)
    ends = np.append(linear[starts[1:] - 1], linear[-1:]) + 1
    lengths = np.diff(np.concatenate([[0], np.stack([linear[starts], ends], axis=1).reshape(-1), [r**3]]))
    values = (np.arange(len(lengths)) % 2).astype(np.uint8)
    values, lengths = values[lengths > 0], lengths[lengths > 0]
    pairs = int((-(-lengths // BINVOX_MAX_RUN)).sum())
    if pairs > BINVOX_MAX_PAIRS:
        raise refuse(
            "save_binvox resolution",
            f"binvox stores every empty voxel, and these need {pairs:,} runs, "
            f"more than {BINVOX_MAX_PAIRS:,}; save as .npz instead",
            r,
        )
    tx, ty, tz = (float(x) for x in np.asarray(grid.origin))
    scale = float(grid.voxel_size) * r  # exact: a float32 times a power of two
    header = f"#binvox 1\ndim {r} {r} {r}\ntranslate {tx!r} {ty!r} {tz!r}\nscale {scale!r}\ndata\n"
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(_runs(values, lengths).tobytes())


def _binvox_header(data: bytes, path: str) -> tuple[int, np.ndarray, float, int]:
    """Parses a binvox header: (dim, translate float64 [3], scale, offset of the run data)."""
    bad = lambda why: refuse("load_binvox path", why, path)
    fields, offset = {}, 0
    for number in range(_BINVOX_HEADER_LINES):
        end = data.find(b"\n", offset)
        if end < 0:
            raise bad(
                "is not a binvox file: the header ends before its 'data' line"
                if number
                else "is not a binvox file: it holds no header line"
            )
        words = data[offset:end].decode("ascii", "replace").split()
        offset = end + 1
        if number == 0:
            if words[:1] != ["#binvox"] or words[1:] not in (["1"], ["2"]):
                raise bad(
                    f"is not a binvox file: the first line must be '#binvox 1' (or 2), not {' '.join(words)[:40]!r}"
                )
            continue
        if not words or words[0].startswith("#"):
            continue
        key, args = words[0].lower(), words[1:]
        if key == "data":
            break
        expected = {"dim": 3, "translate": 3, "scale": 1}.get(key)
        if expected is None:
            raise bad(f"has an unknown binvox header line {' '.join(words)[:40]!r}")
        try:
            numbers = [(int if key == "dim" else float)(a) for a in args]
        except ValueError:
            numbers = []
        if len(numbers) != expected or not np.isfinite(numbers).all():
            raise bad(f"has a bad binvox header line {' '.join(words)[:40]!r}")
        fields[key] = numbers
    else:
        raise bad(f"is not a binvox file: no 'data' line in its first {_BINVOX_HEADER_LINES} lines")
    if "dim" not in fields:
        raise bad("has no 'dim' line in its binvox header")
    dims = fields["dim"]
    if len(set(dims)) != 1 or not 1 <= dims[0] <= MAX_RESOLUTION:
        raise bad(
            f"has dim {' '.join(map(str, dims))}; jaxvox reads cubic grids of 1 to {MAX_RESOLUTION} voxels per axis"
        )
    scale = fields.get("scale", [1.0])[0]
    if scale <= 0:
        raise bad(f"has scale {scale}; it must be > 0")
    return int(dims[0]), np.array(fields.get("translate", [0.0] * 3), np.float64), float(scale), offset


def load_binvox(path: str | os.PathLike, *, mode: str = CONSERVATIVE) -> Voxels:
    """Reads a binvox file (version 1, or 2 where any nonzero value is a set voxel).

    A grid of ``dim R R R`` with R not a power of two is padded into the next power of
    two at the high end: the voxel indices, the origin (``translate``) and the voxel
    size (``scale / R``) are kept, and saving it again writes the padded ``dim``.

    Args:
      path: a .binvox file.
      mode: the voxelization mode to record; binvox does not store how the voxels
        were made.

    Returns:
      `Voxels` in Morton order with capacity on the shape ladder.

    Raises:
      JaxvoxError: naming the file when it is missing or unreadable, is not a binvox
        file, has a bad or non-cubic header, or run data that is truncated, odd or
        longer than ``R^3``.
    """
    path = os.fspath(path)
    check_choice("load_binvox mode", mode, SET_MODES)
    data = _read("load_binvox path", path)
    r, translate, scale, offset = _binvox_header(data, path)
    runs = np.frombuffer(data, np.uint8, offset=offset)
    if len(runs) % 2:
        raise refuse("load_binvox path", f"is truncated: its run data has an odd length of {len(runs)} bytes", path)
    values, counts = runs[0::2], runs[1::2].astype(np.int64)
    ends = np.cumsum(counts)
    covered = int(ends[-1]) if len(ends) else 0
    if covered != r**3:
        why = "is truncated: its" if covered < r**3 else "has too much data: its"
        raise refuse(
            "load_binvox path", f"{why} runs cover {covered:,} of the {r**3:,} voxels of dim {r} {r} {r}", path
        )
    set_runs = values > 0
    first, length = (ends - counts)[set_runs], counts[set_runs]
    run_start = np.cumsum(length) - length
    linear = np.repeat(first - run_start, length) + np.arange(int(length.sum()), dtype=np.int64)
    ijk = np.stack([linear // (r * r), linear % r, linear // r % r], axis=1)
    resolution = max(2, 1 << (r - 1).bit_length())
    return _voxels("load_binvox path", path, ijk, translate, scale / r, resolution, mode)


def _save_npz(path: str, voxels: Voxels) -> None:
    """Writes the .npz format of the module docstring (the exact name given)."""
    grid = voxels.grid
    with open(path, "wb") as fh:  # a file object: numpy appends no ".npz" to its name
        np.savez_compressed(
            fh,
            ijk=voxels.to_numpy(),
            origin=np.asarray(grid.origin),
            voxel_size=np.asarray(grid.voxel_size),
            resolution=grid.resolution,
            mode=voxels.mode,
        )


def _load_npz(path: str) -> Voxels:
    """Reads the .npz format of the module docstring, checked in full."""
    data = _read("load_voxels path", path)
    if not data.startswith(b"PK"):
        raise refuse("load_voxels path", "is not an .npz file: it does not start with a zip signature", path)
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            missing = [k for k in _NPZ_KEYS if k not in npz.files]
            arrays = {k: npz[k] for k in _NPZ_KEYS if k in npz.files}
    except Exception as exc:  # numpy and zipfile raise many types for corrupt files
        raise refuse("load_voxels path", f"is not a readable .npz file ({type(exc).__name__}: {exc})", path) from exc
    if missing:
        raise refuse("load_voxels path", f"lacks the arrays {', '.join(missing)} of a jaxvox .npz voxel file", path)
    mode, resolution = arrays["mode"], arrays["resolution"]
    if mode.shape != () or str(mode) not in SET_MODES:
        raise refuse("load_voxels path", f"holds mode {mode!r}, expected one of {', '.join(SET_MODES)}", path)
    if resolution.shape != () or resolution.dtype.kind not in "iu":
        raise refuse("load_voxels path", f"holds resolution {resolution!r}, expected one integer", path)
    return _voxels(
        "load_voxels path", path, arrays["ijk"], arrays["origin"], arrays["voxel_size"], int(resolution), str(mode)
    )


def check_save_path(what: str, path: str | os.PathLike) -> tuple[str, str]:
    """(path, extension) where `save_voxels` can write; raises for an unknown extension or a missing folder."""
    ext = file_format(what, path, SAVE_FORMATS)
    return check_output_path(what, path), ext


def save_voxels(path: str | os.PathLike, voxels: Voxels) -> None:
    """Writes a voxel set in the format named by the extension of `path`.

    ``.binvox`` (`save_binvox`), ``.npz`` (indices, grid and mode; `load_voxels` reads
    both back), ``.ply`` (binary little-endian) or ``.obj``: the closed boundary surface
    of `voxels_to_mesh`, in world units. The file is written under exactly `path`.

    Args:
      path: destination file, ending in one of `SAVE_FORMATS` (any case).
      voxels: a `Voxels` set (one, not a batch).

    Raises:
      JaxvoxError: an unknown extension (checked first), a missing folder, not a
        `Voxels`, or an overflowed set.
    """
    path, ext = check_save_path("save_voxels path", path)
    check_type("save_voxels voxels", voxels, Voxels)
    if ext == ".binvox":
        save_binvox(path, voxels)
    elif ext == ".npz":
        _save_npz(path, voxels)
    else:
        save_mesh(path, voxels_to_mesh(voxels))


def load_voxels(path: str | os.PathLike) -> Voxels:
    """Reads a voxel set from a ``.binvox`` or ``.npz`` file (see `save_voxels`).

    Binvox voxels are recorded as conservative (`load_binvox` takes another mode);
    .npz files carry their mode.

    Returns:
      `Voxels` in Morton order with capacity on the shape ladder.

    Raises:
      JaxvoxError: naming the file: unknown extension, missing, unreadable, corrupt,
        or holding indices outside its grid.
    """
    path = os.fspath(path)
    ext = file_format("load_voxels path", path, LOAD_FORMATS)
    return load_binvox(path) if ext == ".binvox" else _load_npz(path)
