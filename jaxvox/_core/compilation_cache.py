"""A persistent cache of compiled XLA programs, so a new process skips recompiling."""

from __future__ import annotations

import os

DEFAULT_DIR = os.path.join("~", ".cache", "jaxvox", "xla")


def enable_compilation_cache(*, path: str | os.PathLike | None = None) -> str | None:
    """Keeps every program jaxvox (and the rest of the process) compiles in a folder on disk.

    A later process that compiles the same program (same shapes, same JAX and jaxlib)
    reads it back instead of compiling it again: with jaxvox's shape ladder, a warm
    cache makes a new session's first call on a mesh cost about its work. Call it once,
    before the first jaxvox call; it sets JAX's process-wide options
    ``jax_compilation_cache_dir`` and ``jax_persistent_cache_min_compile_time_secs``
    (to 0: small programs are cached too).

    Args:
      path: the folder; default ``$JAXVOX_CACHE_DIR`` if set, else
        ``~/.cache/jaxvox/xla``. ``JAXVOX_CACHE_DIR=`` (set and empty) with no `path`
        turns the cache off.

    Returns:
      The folder used, or None when the cache stays off.

    Raises:
      JaxvoxError: the folder cannot be created (a file of that name, no permission).
    """
    import jax

    from jaxvox._core.checks import refuse

    folder = os.fspath(path) if path is not None else os.environ.get("JAXVOX_CACHE_DIR", DEFAULT_DIR)
    if not folder:
        return None
    folder = os.path.abspath(os.path.expanduser(folder))
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        raise refuse(
            "enable_compilation_cache path", f"cannot create the folder ({exc.strerror or exc})", folder
        ) from None
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return folder
