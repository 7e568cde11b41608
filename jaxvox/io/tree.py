"""Saving and loading octrees and DAGs in a versioned, self-describing, checksummed file.

File layout (little-endian):

====================  ==========================================================
bytes                 content
====================  ==========================================================
8                     magic ``\\x89JVX\\r\\n\\x1a\\n``
4                     uint32 format version (`FORMAT_VERSION`)
4                     uint32 header length H
H                     UTF-8 JSON header: kind ("octree" or "dag"), mode, grid,
                      level sizes, voxel count, and for every array its name,
                      dtype (little-endian bool, int, uint or float), shape and
                      byte offset from the start of the data; padded with spaces
                      so that 16 + H is a multiple of 8
...                   array data from byte 16 + H, each array at an 8-byte
                      aligned offset, zeros between arrays
4                     uint32 CRC-32 of every byte before it
====================  ==========================================================

Any flipped byte changes the CRC-32; a truncated file is shorter than its header
says. Both raise `JaxvoxError` naming the problem, as does a header or a table that does
not describe a valid tree (checked in full on load: shapes, pointer targets, prefix sums
and the voxel count), so a file from another writer cannot produce a wrong tree.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from collections.abc import Mapping
from mmap import ACCESS_READ
from mmap import mmap as memory_map
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxvox._core.checks import check_output_path, check_type, refuse
from jaxvox._core.errors import JaxvoxError
from jaxvox.grid import Grid, check_resolution
from jaxvox.io.files import read_bytes
from jaxvox.octree import EMPTY, Octree, compact, padded, stored_sizes
from jaxvox.overflow import check_overflow
from jaxvox.voxelize import SET_MODES

MAGIC = b"\x89JVX\r\n\x1a\n"
FORMAT_VERSION = 1
_PREFIX = struct.Struct("<8sII")
_ALIGN = 8
_KINDS = "biuf"  # numpy dtype kinds an array may have: bool, signed, unsigned, float


def save(path: str | os.PathLike, tree: Octree, *, attributes: dict | None = None) -> None:
    """Writes a tree (and optionally per-voxel attribute arrays) to `path`.

    Args:
      path: destination file; written to a temporary file and renamed, so a crash never
        leaves a half-written file under the name.
      tree: an `Octree` (SVO or DAG); padding rows are dropped first.
      attributes: optional mapping of name to array whose first axis indexes voxels in
        Morton order (``[voxel_count or more, ...]``, e.g. from `voxel_attributes`);
        the first ``voxel_count`` rows are stored. Read back with `load_attributes`.

    Raises:
      JaxvoxError: not an `Octree`, a path whose folder does not exist, the tree is
        truncated (overflow set), `attributes` not a dict, or an attribute that is too
        short or not a bool, integer or float array.
    """
    path = check_output_path("save path", path)
    check_type("save tree", tree, Octree)
    if attributes is not None and not isinstance(attributes, Mapping):
        raise refuse("save attributes", "expected a dict of arrays", type(attributes))
    check_overflow("save tree", tree.overflow, "refusing to save a truncated tree")
    tree = compact(tree)
    n = int(tree.voxel_count)
    arrays: dict[str, Any] = {"mask": tree.mask, "child": tree.child, "prefix": tree.prefix}
    for name, value in (attributes or {}).items():
        value = np.asarray(value)
        if value.ndim == 0 or value.shape[0] < n:
            raise refuse(f"save attributes[{name!r}]", f"needs at least {n} rows (one per voxel)", value.shape)
        if value.dtype.kind not in _KINDS or value.dtype.fields is not None:
            raise refuse(f"save attributes[{name!r}]", "must have a bool, integer or float dtype", value.dtype)
        arrays[f"attribute/{name}"] = value[:n]
    entries, blobs, offset = [], [], 0
    for name, value in arrays.items():
        value = np.ascontiguousarray(np.asarray(value))
        value = value.astype(value.dtype.newbyteorder("<"), copy=False)  # no copy unless big-endian
        entries.append(dict(name=name, dtype=value.dtype.str, shape=list(value.shape), offset=offset))
        blobs.append(value)
        offset += -(-value.nbytes // _ALIGN) * _ALIGN
    header = dict(
        kind="dag" if tree.dag else "octree",
        mode=tree.mode,
        grid=dict(
            origin=[float(x) for x in np.asarray(tree.grid.origin)],
            voxel_size=float(tree.grid.voxel_size),
            resolution=tree.grid.resolution,
        ),
        level_sizes=list(tree.level_sizes),
        voxel_count=n,
        arrays=entries,
    )
    head = json.dumps(header).encode()
    head += b" " * (-(len(head) + _PREFIX.size) % _ALIGN)
    path = os.fspath(path)
    tmp = f"{path}.tmp{os.getpid()}"
    try:
        with open(tmp, "wb") as fh:
            crc = 0
            chunk: Any
            for chunk in [_PREFIX.pack(MAGIC, FORMAT_VERSION, len(head)), head, *blobs]:
                if isinstance(chunk, np.ndarray):  # (a zero-size array cannot be cast)
                    chunk = memoryview(chunk.reshape(-1)).cast("B") if chunk.size else b""  # type: ignore[arg-type]
                pad = b"\0" * (-len(chunk) % _ALIGN)
                for data in (chunk, pad):
                    fh.write(data)
                    crc = zlib.crc32(data, crc)
            fh.write(struct.pack("<I", crc))
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def _entry_bytes(entry: dict) -> int:
    """Byte size of one array descriptor; ValueError unless it is well formed."""
    dtype = np.dtype(entry["dtype"])
    shape, offset = entry["shape"], entry["offset"]
    if (
        not isinstance(entry["name"], str)
        or dtype.kind not in _KINDS
        or dtype.byteorder == ">"
        or not isinstance(shape, list)
        or not all(type(d) is int and d >= 0 for d in shape)
        or type(offset) is not int
        or offset < 0
        or offset % _ALIGN
    ):
        raise ValueError(f"bad array descriptor {entry}")
    return int(np.prod(shape, dtype=np.int64)) * dtype.itemsize


def _mapped(what: str, path: str) -> Any:
    """The file at `path` memory-mapped read-only (bytes if it is empty, which mmap refuses);
    errors as `read_bytes`."""
    if not os.path.isfile(path) or os.path.getsize(path) == 0:
        return read_bytes(what, path)  # its errors, or the empty file's bytes
    try:
        with open(path, "rb") as fh:
            return memory_map(fh.fileno(), 0, access=ACCESS_READ)
    except OSError as exc:
        raise refuse(what, f"cannot read it ({exc.strerror or exc})", path) from exc


def _read(what: str, path, *, mapped: bool = False) -> tuple[dict, dict[str, np.ndarray]]:
    """Reads and verifies a file; returns (header, arrays by name). Errors name `what`.
    With `mapped` the arrays are read-only views of the file memory-mapped (the checksum
    still reads every byte once, through the page cache)."""
    path = os.fspath(path)
    data = _mapped(what, path) if mapped else read_bytes(what, path)
    if len(data) < _PREFIX.size or bytes(data[:8]) != MAGIC:
        raise refuse(what, "not a jaxvox tree file (bad magic bytes)", path)
    _, version, head_len = _PREFIX.unpack_from(data)
    if version != FORMAT_VERSION:
        raise refuse(what, f"unsupported format version {version} (this jaxvox reads version {FORMAT_VERSION})", path)
    start = _PREFIX.size + head_len
    if start > len(data):
        raise refuse(what, f"truncated ({len(data)} bytes, the header alone needs {start})", path)
    try:
        header = json.loads(data[_PREFIX.size : start])
        entries = header["arrays"]
        sizes = [_entry_bytes(e) for e in entries]
        end = start + max([e["offset"] + s for e, s in zip(entries, sizes)], default=0)
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise refuse(what, f"corrupt (unreadable header: {exc})", path) from exc
    end = -(-end // _ALIGN) * _ALIGN
    if len(data) < end + 4:
        raise refuse(what, f"truncated ({len(data)} bytes, expected {end + 4})", path)
    if len(data) > end + 4:
        raise refuse(what, f"corrupt ({len(data) - end - 4} unexpected trailing bytes)", path)
    (stored,) = struct.unpack_from("<I", data, end)
    if zlib.crc32(memoryview(data)[:end]) != stored:
        raise refuse(what, "corrupt (checksum mismatch)", path)
    arrays = {}
    for e, size in zip(entries, sizes):
        offset = start + e["offset"]
        arrays[e["name"]] = np.frombuffer(
            data, np.dtype(e["dtype"]), size // np.dtype(e["dtype"]).itemsize, offset
        ).reshape(e["shape"])
    return header, arrays


def _check_tree(what: str, path, header, arrays) -> None:
    """Checks that the header and tables describe a valid tree (beyond the checksum).

    Shapes and dtypes, the level count against the resolution, every child pointer
    against the level below, every prefix sum against the voxel counts of the children,
    and the total against ``voxel_count``: one vectorised pass per level. Errors name `what`.
    """

    def bad(problem):
        raise refuse(what, f"inconsistent ({problem})", path)

    try:
        resolution = check_resolution(header["grid"]["resolution"])
        sizes = [int(x) for x in header["level_sizes"]]
        voxel_count = int(header["voxel_count"])
        kind, mode = header["kind"], header["mode"]
        origin = [float(x) for x in header["grid"]["origin"]]
        voxel_size = float(header["grid"]["voxel_size"])
    except (JaxvoxError, KeyError, TypeError, ValueError) as exc:
        bad(f"header fields ({exc})")
    depth = resolution.bit_length() - 1
    if (
        len(sizes) != depth
        or min(sizes) < 0
        or sizes[0] > 1
        or kind not in ("octree", "dag")
        or mode not in SET_MODES
        or len(origin) != 3
        or not np.isfinite(origin + [voxel_size]).all()
        or not voxel_size > 0
    ):
        bad(
            f"level sizes {sizes} for resolution {resolution}, kind {kind!r}, mode {mode!r}, origin {origin}, "
            f"voxel_size {voxel_size}"
        )
    stored = stored_sizes(sizes)
    n_nodes, n_inner = sum(stored), sum(stored[:-1])
    expect = {"mask": ((n_nodes,), np.uint8), "child": ((n_inner, 8), np.uint32), "prefix": ((n_inner, 8), np.uint32)}
    for name, (shape, dtype) in expect.items():
        a = arrays.get(name)
        if a is None or a.shape != shape or a.dtype != dtype:
            bad(f"{name} should be {shape} {np.dtype(dtype)}, got {None if a is None else (a.shape, str(a.dtype))}")
    mask, child, prefix = arrays["mask"], arrays["child"], arrays["prefix"]
    starts = np.cumsum((0,) + stored)
    bits = (mask[:, None] >> np.arange(8, dtype=np.uint8)) & 1 == 1  # [N, 8] present children
    counts = bits[starts[-2] :].sum(1).astype(np.int64)  # voxels below each node, bottom level first
    for level in range(depth - 2, -1, -1):
        rows = slice(starts[level], starts[level + 1])
        c, present = child[rows], bits[rows]
        if ((c != EMPTY) != present).any():
            bad(f"child pointers disagree with the masks at level {level}")
        target = np.where(present, c.astype(np.int64) - starts[level + 1], stored[level + 1])
        if (present & ((target < 0) | (target >= stored[level + 1]))).any():
            bad(f"child pointers of level {level} leave level {level + 1}")
        per_slot = np.append(counts, 0)[target]  # absent children read the appended 0
        if (np.cumsum(per_slot, axis=1) - per_slot != prefix[rows]).any():
            bad(f"prefix sums of level {level} disagree with the voxel counts below")
        counts = per_slot.sum(1)
    if int(counts[: sizes[0]].sum()) != voxel_count:
        bad(f"voxel_count {voxel_count} but the tree holds {int(counts[: sizes[0]].sum())} voxels")


def load(path: str | os.PathLike) -> Octree:
    """Reads a tree written by `save`, laid out on the shape ladder (see `Octree`).

    Raises:
      JaxvoxError: missing file, not a jaxvox file, unsupported version, truncated or
        corrupt (checksum mismatch), or inconsistent contents.
    """
    header, arrays = _read("load path", path)
    _check_tree("load path", os.fspath(path), header, arrays)
    g = header["grid"]
    grid = Grid(origin=np.float32(g["origin"]), voxel_size=np.float32(g["voxel_size"]), resolution=g["resolution"])
    sizes = tuple(int(s) for s in header["level_sizes"])
    return padded(
        Octree(
            mask=jnp.asarray(arrays["mask"]),
            child=jnp.asarray(arrays["child"]),
            prefix=jnp.asarray(arrays["prefix"]),
            level_count=jnp.asarray(sizes, jnp.int32),
            voxel_count=jax.device_put(np.uint32(header["voxel_count"])),
            overflow=jnp.int32(0),
            grid=grid,
            level_capacity=jnp.asarray(stored_sizes(sizes), jnp.int32),
            dag=header["kind"] == "dag",
            mode=header["mode"],
        )
    )


def load_attributes(path: str | os.PathLike, *, mmap: bool = False) -> dict[str, np.ndarray]:
    """The attribute arrays saved with a tree (``{}`` if none), each [voxel_count, ...].

    Args:
      path: a file written by `save` (or ``jaxvox build``).
      mmap: return read-only views of the file memory-mapped instead of reading it into
        memory, for attributes larger than memory (e.g. a DAG built by `mesh_to_dag` at
        16384^3): rows are read from disk as they are indexed, e.g. by `voxel_index`.
        The checksum is still verified, reading the file once.

    Raises:
      JaxvoxError: as `load`.
    """
    _, arrays = _read("load_attributes path", path, mapped=mmap)
    prefix = "attribute/"
    return {name[len(prefix) :]: a for name, a in arrays.items() if name.startswith(prefix)}
