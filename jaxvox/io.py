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
                      dtype, shape and byte offset from the start of the data
pad                   zeros up to a multiple of 8 bytes
...                   array data, each array at an 8-byte aligned offset
4                     uint32 CRC-32 of every byte before it
====================  ==========================================================

Any flipped byte changes the CRC-32; a truncated file is shorter than its header
says. Both raise `JaxvoxError` naming the problem.
"""

from __future__ import annotations

import json
import os
import struct
import zlib

import jax.numpy as jnp
import numpy as np

from jaxvox._errors import JaxvoxError
from jaxvox.grid import Grid
from jaxvox.octree import EMPTY, Octree, compact

MAGIC = b"\x89JVX\r\n\x1a\n"
FORMAT_VERSION = 1
_PREFIX = struct.Struct("<8sII")
_ALIGN = 8


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
      JaxvoxError: the tree is truncated (overflow set) or an attribute is too short.
    """
    if int(tree.overflow):
        raise JaxvoxError(f"refusing to save a truncated tree (overflow flags {int(tree.overflow)})")
    tree = compact(tree)
    n = int(tree.voxel_count)
    arrays = {"mask": tree.mask, "child": tree.child, "prefix": tree.prefix}
    for name, value in (attributes or {}).items():
        value = np.asarray(value)
        if value.ndim == 0 or value.shape[0] < n:
            raise JaxvoxError(f"attribute {name!r} has shape {value.shape}; it needs {n} rows")
        arrays[f"attribute/{name}"] = value[:n]
    entries, blobs, offset = [], [], 0
    for name, value in arrays.items():
        value = np.ascontiguousarray(np.asarray(value))
        if value.dtype.byteorder == ">":
            value = value.astype(value.dtype.newbyteorder("<"))
        entries.append(dict(name=name, dtype=value.dtype.str, shape=list(value.shape), offset=offset))
        blobs.append(value)
        offset += -(-value.nbytes // _ALIGN) * _ALIGN
    header = dict(
        kind="dag" if tree.dag else "octree", mode=tree.mode,
        grid=dict(origin=[float(x) for x in np.asarray(tree.grid.origin)],
                  voxel_size=float(tree.grid.voxel_size), resolution=tree.grid.resolution),
        level_sizes=list(tree.level_sizes), voxel_count=n, arrays=entries)
    head = json.dumps(header).encode()
    head += b" " * (-(len(head) + _PREFIX.size) % _ALIGN)
    path = os.fspath(path)
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "wb") as fh:
        crc = 0
        for chunk in [_PREFIX.pack(MAGIC, FORMAT_VERSION, len(head)), head, *blobs]:
            data = memoryview(chunk).cast("B") if isinstance(chunk, np.ndarray) else chunk
            fh.write(data)
            crc = zlib.crc32(data, crc)
            pad = -len(data) % _ALIGN if isinstance(chunk, np.ndarray) else 0
            fh.write(b"\0" * pad)
            crc = zlib.crc32(b"\0" * pad, crc)
        fh.write(struct.pack("<I", crc))
    os.replace(tmp, path)


def _read(path) -> tuple[dict, dict[str, np.ndarray]]:
    """Reads and verifies a file; returns (header, arrays by name)."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as exc:
        raise JaxvoxError(f"cannot read {path}: {exc.strerror or exc}") from exc
    if len(data) < _PREFIX.size or data[:8] != MAGIC:
        raise JaxvoxError(f"{path} is not a jaxvox tree file (bad magic bytes)")
    _, version, head_len = _PREFIX.unpack_from(data)
    if version != FORMAT_VERSION:
        raise JaxvoxError(f"{path} has format version {version}; this jaxvox reads version {FORMAT_VERSION}")
    start = _PREFIX.size + head_len
    if start > len(data):
        raise JaxvoxError(f"{path} is truncated: {len(data)} bytes, the header alone needs {start}")
    try:
        header = json.loads(data[_PREFIX.size:start])
        entries = header["arrays"]
        sizes = [int(np.prod(e["shape"], dtype=np.int64)) * np.dtype(e["dtype"]).itemsize for e in entries]
        end = start + max([e["offset"] + s for e, s in zip(entries, sizes)], default=0)
    except (ValueError, KeyError, TypeError) as exc:
        raise JaxvoxError(f"{path} is corrupt: unreadable header ({exc})") from exc
    end = -(-end // _ALIGN) * _ALIGN
    if len(data) < end + 4:
        raise JaxvoxError(f"{path} is truncated: {len(data)} bytes, expected {end + 4}")
    if len(data) > end + 4:
        raise JaxvoxError(f"{path} is corrupt: {len(data) - end - 4} unexpected trailing bytes")
    (stored,) = struct.unpack_from("<I", data, end)
    if zlib.crc32(memoryview(data)[:end]) != stored:
        raise JaxvoxError(f"{path} is corrupt: checksum mismatch")
    arrays = {}
    for e, size in zip(entries, sizes):
        offset = start + e["offset"]
        arrays[e["name"]] = np.frombuffer(data, np.dtype(e["dtype"]), size // np.dtype(e["dtype"]).itemsize,
                                          offset).reshape(e["shape"])
    return header, arrays


def _check_tree(path, header, arrays) -> None:
    """Structural checks beyond the checksum (a file written by other software)."""
    sizes = header["level_sizes"]
    sizes = [max(sizes[0], 1)] + sizes[1:]  # the root row always exists
    n_nodes, n_inner = sum(sizes), sum(sizes[:-1])
    expect = {"mask": ((n_nodes,), np.uint8), "child": ((n_inner, 8), np.uint32), "prefix": ((n_inner, 8), np.uint32)}
    for name, (shape, dtype) in expect.items():
        a = arrays.get(name)
        if a is None or a.shape != shape or a.dtype != dtype:
            got = None if a is None else (a.shape, str(a.dtype))
            raise JaxvoxError(f"{path} is inconsistent: {name} should be {shape} {np.dtype(dtype)}, got {got}")
    child = arrays["child"]
    if ((child != EMPTY) & (child >= n_nodes)).any():
        raise JaxvoxError(f"{path} is inconsistent: child pointers past the {n_nodes} nodes")


def load(path: str | os.PathLike) -> Octree:
    """Reads a tree written by `save`.

    Raises:
      JaxvoxError: missing file, not a jaxvox file, unsupported version, truncated or
        corrupt (checksum mismatch), or inconsistent contents.
    """
    header, arrays = _read(path)
    _check_tree(os.fspath(path), header, arrays)
    g = header["grid"]
    grid = Grid(origin=np.float32(g["origin"]), voxel_size=np.float32(g["voxel_size"]), resolution=g["resolution"])
    sizes = tuple(int(s) for s in header["level_sizes"])
    return Octree(
        mask=jnp.asarray(arrays["mask"]), child=jnp.asarray(arrays["child"]), prefix=jnp.asarray(arrays["prefix"]),
        level_count=jnp.asarray(sizes, jnp.int32), voxel_count=jnp.int32(header["voxel_count"]),
        overflow=jnp.int32(0), grid=grid, level_capacity=(max(sizes[0], 1),) + sizes[1:],
        dag=header["kind"] == "dag", mode=header["mode"])


def load_attributes(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The attribute arrays saved with a tree (``{}`` if none), each [voxel_count, ...].

    Raises:
      JaxvoxError: as `load`.
    """
    _, arrays = _read(path)
    prefix = "attribute/"
    return {name[len(prefix):]: a for name, a in arrays.items() if name.startswith(prefix)}
