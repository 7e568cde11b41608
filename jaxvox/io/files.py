"""File reading shared by the file formats (tree files, HDR images)."""

from __future__ import annotations

import os

from jaxvox._core.checks import refuse


def read_bytes(what: str, path) -> bytes:
    """The whole file at `path`; a `JaxvoxError` naming `what` (the parameter, e.g.
    ``"load path"``) and the path when it is missing, a directory or unreadable."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise refuse(what, "is a directory, expected a file", path)
    if not os.path.exists(path):
        raise refuse(what, "file not found", path)
    try:
        with open(path, "rb") as fh:
            return fh.read()
    except OSError as exc:
        raise refuse(what, f"cannot read it ({exc.strerror or exc})", path) from exc
