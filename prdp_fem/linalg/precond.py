"""Preconditioners: fixed symmetric positive-definite linear maps ``z = M r``.

A preconditioner is a small pytree with ``__call__(r) -> z``. It is built once per solve from the
operator (never per CG iteration). In unrolled mode its dependence on the operator values is
differentiated like everything else (the K-iteration map includes it); in implicit mode it is
treated as a constant, since the converged solution does not depend on it. Algebraic multigrid
(a fixed map built on the host from the operator's values) is in :mod:`prdp_fem.linalg.amg`.

>>> import numpy as np, scipy.sparse as sp
>>> from prdp_fem.linalg.operator import SparseMatrix
>>> A = SparseMatrix.from_scipy(sp.diags([2.0, 4.0]))
>>> np.asarray(jacobi(A)(np.array([2.0, 4.0]))).tolist()
[1.0, 1.0]
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp

from ..errors import SolverConfigError
from .operator import SparseMatrix, diagonal

__all__ = ["IdentityPreconditioner", "JacobiPreconditioner", "jacobi", "make_preconditioner"]

PRECONDITIONERS = ("identity", "jacobi")


@partial(jax.tree_util.register_dataclass, data_fields=[], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class IdentityPreconditioner:
    """``M = I``."""

    def __call__(self, r: jax.Array) -> jax.Array:
        return r


@partial(jax.tree_util.register_dataclass, data_fields=["inverse_diagonal"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class JacobiPreconditioner:
    """``M = diag(A)^{-1}``."""

    inverse_diagonal: jax.Array

    def __call__(self, r: jax.Array) -> jax.Array:
        return self.inverse_diagonal * r


def jacobi(matrix: SparseMatrix) -> JacobiPreconditioner:
    """Jacobi preconditioner; a non-positive diagonal entry falls back to 1 (keeps M SPD)."""
    d = diagonal(matrix)
    positive = d > 0
    return JacobiPreconditioner(jnp.where(positive, 1.0 / jnp.where(positive, d, 1.0), 1.0))


def make_preconditioner(spec, matrix: SparseMatrix):
    """``spec``: ``"identity"``, ``"jacobi"`` or an already built preconditioner pytree."""
    if spec == "identity":
        return IdentityPreconditioner()
    if spec == "jacobi":
        return jacobi(matrix)
    if callable(spec):
        return spec
    raise SolverConfigError(
        f"preconditioner={spec!r}: expected one of {PRECONDITIONERS} or a callable pytree")
