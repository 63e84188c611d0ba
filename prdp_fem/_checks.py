"""Checks at the edges of the public API: finite arrays of the right shape, valid coefficients.

Each check returns the input as a NumPy array (or leaves a JAX tracer alone: inside ``jit`` the
values are unknown, and the solver's ``status`` reports what went wrong instead) and raises a
typed :mod:`prdp_fem.errors` exception naming the field, what was found and what was expected.

>>> finite_vector([1.0, 2.0], "f", 2).tolist()
[1.0, 2.0]
>>> positive_coefficient([1.0, 0.0], "kappa", 2)  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
prdp_fem.errors.CoefficientError: kappa: 1 value(s) <= 0 (first: index 1, value 0.0); ...
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from .errors import CoefficientError, DataError, ShapeError, TracerError

__all__ = ["finite_vector", "host_values", "is_traced", "positive_coefficient", "real_array",
           "real_dtype"]


def is_traced(*values: Any) -> bool:
    """Whether any leaf of ``values`` is a JAX tracer (its values are unknown here)."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(values))


def host_values(value: Any, name: str) -> Any:
    """``value``, or a :class:`TracerError` where it is (or holds) a JAX tracer: ``name``
    needs concrete values, known outside ``jax.jit``/``jax.grad``."""
    if is_traced(value):
        raise TracerError(f"{name}: a JAX tracer (a value inside jax.jit, jax.grad or "
                          "jax.vmap); expected concrete values: call this outside the "
                          "transformed function")
    return value


def real_array(value: Any, name: str, *, error: type[DataError] = DataError) -> np.ndarray:
    """``value`` as a float array; complex values (which ``float`` would truncate to their
    real part) and non-numeric ones (strings, objects) raise ``error`` naming ``name``.

    >>> real_array([1, 2.5], "f").tolist()
    [1.0, 2.5]
    >>> real_array([1 + 2j], "kappa")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    prdp_fem.errors.DataError: kappa: complex values (first: index 0, value (1+2j)); ...
    """
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError) as exc:  # a ragged list, an object NumPy cannot hold
        reason = str(exc).split(". ")[0]
        raise error(f"{name}: {_shown(value)} is not an array of numbers ({reason}); "
                    "expected real numbers") from None
    if raw.dtype.kind in "USV":
        raise error(f"{name}: {_shown(value)} (dtype {raw.dtype}); expected real numbers, not "
                    "text")
    if raw.dtype.kind == "c":
        imaginary = np.flatnonzero(raw.imag.ravel() != 0)
        i = int(imaginary[0]) if imaginary.size else 0
        raise error(f"{name}: complex values (first: index {i}, value {raw.ravel()[i]}); "
                    "expected real numbers (the imaginary part would be dropped)")
    if raw.dtype.kind not in "biuf":  # objects: None (which float() makes NaN), ragged lists
        raise error(f"{name}: {_shown(value)} of type {type(value).__name__} (dtype "
                    f"{raw.dtype}); expected real numbers")
    return raw.astype(float, copy=False)


def real_dtype(value: Any, name: str, *, error: type[DataError] = DataError) -> None:
    """Refuse a complex or non-numeric ``value``; a JAX array's or tracer's dtype is read
    without its values (``jnp`` would otherwise compute with it, or drop an imaginary part)."""
    if not (isinstance(value, jax.Array) or is_traced(value)):
        real_array(value, name, error=error)
        return
    kind = np.dtype(value.dtype).kind
    if kind == "c":
        raise error(f"{name}: complex values (dtype {value.dtype}); expected real numbers "
                    "(the imaginary part would be dropped)")
    if kind not in "biuf":
        raise error(f"{name}: values of dtype {value.dtype}; expected real numbers")


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else f"{text[:60]}..."


def finite_vector(value: Any, name: str, size: int, *, error: type[DataError] = DataError):
    """``value`` as a float vector of length ``size`` (a scalar broadcasts), finite everywhere."""
    if is_traced(value):
        return value
    array = real_array(value, name, error=error)
    if array.ndim == 0:
        array = np.full(size, float(array))
    if array.shape != (size,):
        raise ShapeError(f"{name}: expected a vector of {size} values, got shape {array.shape}")
    bad = ~np.isfinite(array)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise error(f"{name}: {int(bad.sum())} value(s) are NaN/Inf (first: index {i}, value "
                    f"{array[i]}); expected finite values")
    return array


def positive_coefficient(value: Any, name: str, size: int):
    """A scalar coefficient vector: finite and ``> 0`` everywhere."""
    array = finite_vector(value, name, size, error=CoefficientError)
    if is_traced(array):
        return array
    bad = array <= 0
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise CoefficientError(f"{name}: {int(bad.sum())} value(s) <= 0 (first: index {i}, "
                               f"value {array[i]}); expected kappa > 0 everywhere")
    return array
