"""Validation at the door: one message style for every refused input.

Every check raises `JaxvoxError("<what>: <why>, got <value>")`, where ``<what>`` names the
parameter (``"Grid voxel_size"``, ``"trace t_max"``) and ``<value>`` shows what was passed
(arrays by their values when small, by shape and dtype otherwise). Checks of array values
run only on concrete inputs: under `jax.jit` a traced value passes unchecked, and the
jittable code reports bad items by status instead.
"""

from __future__ import annotations

import math
import numbers
import os

import jax
import numpy as np

from jaxvox._core.errors import JaxvoxError


def is_concrete(x) -> bool:
    """True unless `x` is a tracer (a value inside `jax.jit`, `jax.vmap`, ...)."""
    return not isinstance(x, jax.core.Tracer)


def shown(value) -> str:
    """`value` as it appears after "got" in a message: small arrays by value, big ones by shape."""
    if isinstance(value, (np.ndarray, jax.Array)) and not isinstance(value, jax.core.Tracer):
        a = np.asarray(value)
        return repr(a.tolist()) if a.size <= 12 else f"an array of shape {a.shape} and dtype {a.dtype}"
    if isinstance(value, jax.core.Tracer):
        return f"a traced array of shape {value.shape}"
    if isinstance(value, type):
        return value.__name__
    if isinstance(value, np.generic):
        value = value.item()
    text = repr(value)
    return text if len(text) <= 120 else text[:117] + "..."


def refuse(what: str, why: str, value) -> JaxvoxError:
    """The error for a refused input (raise it): ``"<what>: <why>, got <value>"``."""
    return JaxvoxError(f"{what}: {why}, got {shown(value)}")


def check_choice(what: str, value, options):
    """`value` if it is one of `options`; otherwise raises naming them."""
    if not isinstance(value, str) or value not in options:
        raise refuse(what, f"expected one of {', '.join(map(repr, options))}", value)
    return value


def check_type(what: str, value, cls):
    """`value` if it is an instance of `cls` (a class or a tuple of classes); otherwise
    raises naming the expected type."""
    if not isinstance(value, cls):
        names = " or ".join(f"jaxvox.{c.__name__}" for c in (cls if isinstance(cls, tuple) else (cls,)))
        raise refuse(what, f"expected a {names}", type(value))
    return value


def check_int(what: str, value, *, minimum: int | None = None, maximum: int | None = None) -> int:
    """`value` as a Python int; raises if it is not an integer (bools refused) or out of range."""
    integral = isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))
    if not integral:
        raise refuse(what, "must be an integer", value)
    value = int(value)
    if minimum is not None and value < minimum:
        raise refuse(what, f"must be at least {minimum}", value)
    if maximum is not None and value > maximum:
        raise refuse(what, f"must be at most {maximum}", value)
    return value


def check_number(
    what: str,
    value,
    *,
    above: float | None = None,
    minimum: float | None = None,
    maximum: float | None = None,
    below: float | None = None,
    finite: bool = True,
) -> float:
    """`value` as a float; raises if it is not a real number, is NaN (or inf when `finite`),
    or lies outside ``(above, below)`` / ``[minimum, maximum]``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        if not (
            isinstance(value, (np.ndarray, jax.Array))
            and np.ndim(value) == 0
            and np.issubdtype(np.asarray(value).dtype, np.number)
        ):
            raise refuse(what, "must be a real number", value)
    x = float(value)
    if math.isnan(x) or (finite and math.isinf(x)):
        raise refuse(what, "must be finite" if finite else "must not be NaN", value)
    for bound, bad, relation in (
        (above, lambda b: x <= b, ">"),
        (minimum, lambda b: x < b, ">="),
        (maximum, lambda b: x > b, "<="),
        (below, lambda b: x >= b, "<"),
    ):
        if bound is not None and bad(bound):
            raise refuse(what, f"must be {relation} {bound}", value)
    return x


def check_vector(what: str, value, size: int) -> np.ndarray:
    """`value` as a finite float64 numpy vector of `size` numbers; raises otherwise."""
    try:
        v = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise refuse(what, f"must be {size} numbers", value) from None
    if v.shape != (size,):
        raise refuse(what, f"must be {size} numbers", value)
    if not np.isfinite(v).all():
        raise refuse(what, "must be finite", value)
    return v


def check_output_path(what: str, path) -> str:
    """`path` as a string if its directory exists (a file can be written there); raises otherwise."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        raise refuse(what, "is a directory, expected a file name", path)
    if not os.path.isdir(folder):
        raise refuse(what, f"its folder {folder} does not exist", path)
    return path
