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

from .errors import CoefficientError, DataError, ShapeError

__all__ = ["finite_vector", "is_traced", "positive_coefficient"]


def is_traced(*values: Any) -> bool:
    """Whether any leaf of ``values`` is a JAX tracer (its values are unknown here)."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(values))


def finite_vector(value: Any, name: str, size: int, *, error: type[DataError] = DataError):
    """``value`` as a float vector of length ``size`` (a scalar broadcasts), finite everywhere."""
    if is_traced(value):
        return value
    array = np.asarray(value, dtype=float)
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
