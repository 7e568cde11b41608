"""Host buffers for large results: page-aligned arrays that `jax.device_put` aliases
instead of copying, address-space-only reservations whose pages cost memory once written,
row joins that never hold the parts and the whole at once, the return of freed heap
memory (between the sparse distance field's regions), and the progress-bar switch of the
region loops. Used by the voxelizer, the sparse distance fields and the solid boundary."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import mmap
import sys

import numpy as np


def progress_off(progress: bool | None, regions: int) -> bool:
    """Whether the progress bar over `regions` regions is off (`progress` None: on for several)."""
    return regions < 2 if progress is None else not progress


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim``, or None (another C library, or none found)."""
    name = ctypes.util.find_library("c") if sys.platform.startswith("linux") else None
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None


def release_free_memory() -> None:
    """Returns the heap memory freed so far to the system (glibc's ``malloc_trim(0)``;
    nothing elsewhere). A region loop frees arrays of a few MiB to tens of MiB per region
    on several threads; glibc keeps such freed chunks in its per-thread heaps, so
    without this the resident memory grows region after region as if nothing were freed."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def aligned_empty(shape: tuple[int, ...], dtype) -> np.ndarray:
    """An uninitialized host array in its own anonymous memory map: page-aligned, so
    `jax.device_put` (``may_alias=True``) on the CPU uses the buffer itself instead of
    copying it (numpy's own buffers are only 16-byte aligned), and advised to use
    transparent huge pages, which makes the first write of each page cheaper."""
    size = _nbytes(shape, dtype)
    if size == 0:
        return np.empty(shape, dtype)
    buffer = mmap.mmap(-1, size)
    if hasattr(mmap, "MADV_HUGEPAGE"):  # Linux
        buffer.madvise(mmap.MADV_HUGEPAGE)
    return np.frombuffer(buffer, dtype).reshape(shape)


# Linux's value where Python does not name it (before 3.13); elsewhere a plain private map.
MAP_NORESERVE = getattr(mmap, "MAP_NORESERVE", 0x4000 if sys.platform.startswith("linux") else 0)


def reserved_empty(shape: tuple[int, ...], dtype) -> np.ndarray | None:
    """Like `aligned_empty`, but address space only (a private map that reserves no
    memory): a page costs memory once written, so `shape` may be a generous bound, e.g.
    every voxel of the grid, for rows whose count is found as they are written. None
    where the system refuses the map (strict overcommit, a small address space)."""
    try:
        buffer = mmap.mmap(-1, max(_nbytes(shape, dtype), 1), flags=mmap.MAP_PRIVATE | MAP_NORESERVE)
    except (OSError, OverflowError, ValueError, AttributeError):  # (AttributeError: no MAP_PRIVATE on Windows)
        return None
    return np.frombuffer(buffer, dtype, count=int(np.prod(shape, dtype=np.int64))).reshape(shape)


def _nbytes(shape: tuple[int, ...], dtype) -> int:
    """Bytes of an array of `shape` and `dtype` (int64 arithmetic)."""
    return int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize


def join_rows(parts: list[np.ndarray], shape: tuple[int, ...] | None = None, fill=0, dtype=None) -> np.ndarray:
    """Concatenates host arrays along their first axis into one buffer of `shape` (default:
    just their rows) of `dtype` (default the parts'), the rows past them set to `fill`.

    Empties `parts` as it goes, and the buffer's pages are only touched as they are
    filled, so the parts and the whole buffer are never held at once. The buffer is
    aligned for `jax.device_put` without a copy (`aligned_empty`).
    """
    if shape is None:
        shape = (sum(len(p) for p in parts),) + parts[0].shape[1:]
    out = aligned_empty(shape, dtype or (parts[0].dtype if parts else np.int32))
    start = 0
    parts.reverse()
    while parts:
        part = parts.pop()
        out[start : start + len(part)] = part
        start += len(part)
    out[start:] = fill
    return out
