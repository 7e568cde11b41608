"""File reading shared by the file formats (tree files, HDR images)."""

from __future__ import annotations

import os

from jaxvox._errors import JaxvoxError


def read_bytes(path) -> bytes:
    """The whole file at `path`; a `JaxvoxError` naming it when it cannot be read."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            return fh.read()
    except OSError as exc:
        raise JaxvoxError(f"cannot read {path}: {exc.strerror or exc}") from exc
