"""Sparse matrices as JAX pytrees: row-sorted COO (BCOO-compatible) with one matvec kernel.

A :class:`SparseMatrix` holds integer ``rows``/``cols`` and float ``values`` as pytree leaves and
its ``shape`` as static metadata, so it is passed *as an argument* to jitted code (never closed
over: a closed-over sparse matrix is constant-folded slowly) and is differentiable in ``values``.

All products go through :func:`matvec`; it is the one place where the kernel is chosen.

.. math:: (A x)_i = \\sum_{k:\\, \\mathrm{row}_k = i} \\mathrm{values}_k \\, x_{\\mathrm{col}_k}

>>> import numpy as np, scipy.sparse as sp
>>> from prdp_fem.operator import SparseMatrix, matvec
>>> A = SparseMatrix.from_scipy(sp.csr_matrix(np.array([[2.0, -1.0], [-1.0, 2.0]])))
>>> np.asarray(matvec(A, np.array([1.0, 1.0]))).tolist()
[1.0, 1.0]
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jax.experimental import sparse as jsparse

__all__ = ["SparseMatrix", "diagonal", "matvec", "rmatvec"]


@partial(jax.tree_util.register_dataclass, data_fields=["rows", "cols", "values"],
         meta_fields=["shape"])
@dataclasses.dataclass(frozen=True)
class SparseMatrix:
    """COO matrix with entries sorted by row (duplicates allowed; they add up).

    The constructor trusts its input (it runs inside jit); build from unsorted data with
    :meth:`from_coo`, :meth:`from_scipy` or :meth:`from_bcoo`, which sort.

    Attributes
    ----------
    rows, cols
        Integer index arrays of length ``nnz``; ``rows`` is non-decreasing.
    values
        Float array of length ``nnz`` (the differentiable part).
    shape
        ``(n_rows, n_cols)``, static.
    """

    rows: jax.Array
    cols: jax.Array
    values: jax.Array
    shape: tuple[int, int]

    @property
    def nnz(self) -> int:
        return int(self.values.shape[-1])

    def with_values(self, values: jax.Array) -> SparseMatrix:
        """Same sparsity pattern, new values (e.g. ``G @ kappa``)."""
        return dataclasses.replace(self, values=values)

    def astype(self, dtype) -> SparseMatrix:
        """The values in another precision (``solve`` then runs in it: e.g. float32, whose
        limits -- rtol >= ~1e-5, errors ~ cond * 1e-7 -- the stability suite states)."""
        return self.with_values(self.values.astype(dtype))

    @classmethod
    def from_coo(cls, rows, cols, values, shape: tuple[int, int]) -> SparseMatrix:
        """From COO arrays in any order (sorted by row here; the constructor assumes it)."""
        rows, cols = np.asarray(rows), np.asarray(cols)
        order = np.lexsort((cols, rows))
        return cls(jnp.asarray(rows[order], dtype=jnp.int32),
                   jnp.asarray(cols[order], dtype=jnp.int32),
                   jnp.asarray(values, dtype=float)[order], (int(shape[0]), int(shape[1])))

    @classmethod
    def from_scipy(cls, matrix: sp.spmatrix | sp.sparray) -> SparseMatrix:
        csr = sp.csr_matrix(matrix)
        csr.sum_duplicates()
        coo = csr.tocoo()  # from a canonical CSR: sorted by row, then column
        return cls(jnp.asarray(coo.row, dtype=jnp.int32), jnp.asarray(coo.col, dtype=jnp.int32),
                   jnp.asarray(coo.data, dtype=float), tuple(int(s) for s in csr.shape))

    def to_scipy(self) -> sp.csr_matrix:
        return sp.csr_matrix(
            (np.asarray(self.values), (np.asarray(self.rows), np.asarray(self.cols))),
            shape=self.shape)

    def to_bcoo(self) -> jsparse.BCOO:
        indices = jnp.stack([self.rows, self.cols], axis=-1)
        return jsparse.BCOO((self.values, indices), shape=self.shape,
                            indices_sorted=True, unique_indices=False)

    @classmethod
    def from_bcoo(cls, matrix: jsparse.BCOO) -> SparseMatrix:
        indices = np.asarray(matrix.indices)
        return cls.from_coo(indices[:, 0], indices[:, 1], matrix.data, matrix.shape)

    def todense(self) -> jax.Array:
        return jnp.zeros(self.shape, self.values.dtype).at[self.rows, self.cols].add(self.values)


def matvec(matrix: SparseMatrix, x: jax.Array) -> jax.Array:
    """``A @ x``: gather, multiply, sorted segment sum (differentiable in values and x)."""
    products = matrix.values * x[matrix.cols]
    return jax.ops.segment_sum(products, matrix.rows, num_segments=matrix.shape[0],
                               indices_are_sorted=True)


def rmatvec(matrix: SparseMatrix, y: jax.Array) -> jax.Array:
    """``A.T @ y``."""
    return jax.ops.segment_sum(matrix.values * y[matrix.rows], matrix.cols,
                               num_segments=matrix.shape[1])


def diagonal(matrix: SparseMatrix) -> jax.Array:
    """Main diagonal (zero where a row stores no diagonal entry)."""
    on_diagonal = matrix.rows == matrix.cols
    return jax.ops.segment_sum(jnp.where(on_diagonal, matrix.values, 0.0), matrix.rows,
                               num_segments=matrix.shape[0], indices_are_sorted=True)
