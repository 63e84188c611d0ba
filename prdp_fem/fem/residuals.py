r"""The objective as a sum of squares: factors that turn ``J(z)`` into ``1/2 ||r(z)||^2``.

Gauss-Newton-type optimisers (:mod:`prdp_fem.optim.hig`) need the residual *vector*, not the scalar.
With a factor ``L_W`` of the misfit weight (``L_W^T L_W = W``) and one of the regulariser,

.. math::

    r(z) = \begin{pmatrix} L_W (B u(z) - d) \\ r_R(z) \end{pmatrix}, \qquad
    \tfrac12 \|r\|^2 = \tfrac12 \|B u - d\|_W^2 + \alpha R(m),

where, with ``g = D m`` and the regulariser's point weights ``w_p`` (see
:mod:`prdp_fem.fem.regularizers`):

* L2: ``r_R = sqrt(alpha) L_M (m - m_0)`` with ``L_M^T L_M = M``, the parameter mass matrix;
* H1: ``r_R = sqrt(alpha) diag(sqrt(w_p)) D (m - m_0)`` (one row per gradient component and
  point), since ``R = 1/2 sum_p w_p |g_p|^2``;
* TV: ``r_{R,p} = sqrt(2 alpha w_p) (|g_p|^2 + eps^2)^{1/4}``, one row per point, so that
  ``1/2 r_p^2 = alpha w_p sqrt(|g_p|^2 + eps^2)`` exactly. TV is not a sum of squares of
  anything linear: the Gauss-Newton matrix of this residual keeps only the radial part
  ``D^T g g^T D / |.|^3`` of TV's Hessian (not its lagged-diffusivity part), so a Gauss-Newton
  or half-inverse step on TV is a different method from IRLS / lagged diffusivity. The fourth
  root is differentiable because ``eps > 0``.

The factor of a symmetric positive definite sparse ``W`` is its sparse ``L D L^T`` (SuperLU
with a symmetric fill-reducing ordering and no pivoting), ``F = D^{1/2} L^T P``: square
(``n_obs`` rows) and sparse, so the misfit block of the residual has as many rows as there are
observations. Any factor gives the same Gauss-Newton and half-inverse step (the step depends
on ``J^T J`` and ``J^T r`` only). A diagonal ``W`` (sensors, nodal full field) gets
``sqrt(W)``.

>>> import numpy as np, scipy.sparse as sp
>>> W = sp.csr_matrix(np.array([[2.0, 1.0, 0.0], [1.0, 2.0, 1.0], [0.0, 1.0, 2.0]]))
>>> F = square_root_factor(W, "W")
>>> bool(np.allclose((F.T @ F).toarray(), W.toarray(), rtol=0, atol=1e-14))
True
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import SolverConfigError
from ..linalg.operator import SparseMatrix
from .observations import Observation
from .regularizers import Regularizer

__all__ = ["ResidualFactors", "residual_factors", "square_root_factor"]

# relative mismatch ||F^T F - W||_max / ||W||_max above which a factor is rejected
FACTOR_TOLERANCE = 1e-10
# a W that is neither diagonal nor positive definite gets a dense eigen-factor up to this size
DENSE_LIMIT = 2000


class ResidualFactors(NamedTuple):
    """Factors of the misfit weight and of a quadratic regulariser (``None`` for TV)."""

    misfit: SparseMatrix
    regularization: SparseMatrix | None


def square_root_factor(W: sp.spmatrix, name: str) -> sp.csr_matrix:
    """A sparse ``F`` with ``F^T F = W`` for a symmetric positive semi-definite ``W``.

    Diagonal: ``sqrt(W)``. Otherwise the sparse ``L D L^T`` factor (see the module), checked
    against ``W``; should that fail (``W`` singular), a dense eigen-factor
    ``diag(sqrt(lambda)) Q^T`` up to :data:`DENSE_LIMIT` rows. Raises
    :class:`~prdp_fem.errors.SolverConfigError` naming ``name`` when ``W`` is not symmetric
    positive semi-definite or too large for the dense fallback.
    """
    W = sp.csr_matrix(W, dtype=float)
    W.sum_duplicates()
    W.eliminate_zeros()
    n = W.shape[0]
    if W.shape != (n, n) or _max_abs(W - W.T) > FACTOR_TOLERANCE * _scale(W):
        raise SolverConfigError(f"{name}: a {W.shape} matrix that is not symmetric; expected a "
                                "symmetric positive semi-definite weight")
    diagonal = W.diagonal()
    if W.nnz == np.count_nonzero(diagonal):  # no off-diagonal entries
        if (diagonal < 0).any():
            raise SolverConfigError(f"{name}: negative diagonal weights (min "
                                    f"{diagonal.min()!r}); expected weights >= 0")
        return sp.diags(np.sqrt(diagonal)).tocsr()
    factor = _ldl_factor(W)
    if factor is not None and _reproduces(factor, W):
        return factor
    if n > DENSE_LIMIT:
        raise SolverConfigError(
            f"{name}: no sparse factor F^T F = W of this {n} x {n} weight (it is not positive "
            f"definite) and it is too large for a dense one (> {DENSE_LIMIT} rows); expected a "
            "symmetric positive definite or diagonal weight")
    eigenvalues, vectors = la.eigh(W.toarray())
    if eigenvalues.min() < -FACTOR_TOLERANCE * max(eigenvalues.max(), 0.0):
        raise SolverConfigError(f"{name}: an indefinite weight (smallest eigenvalue "
                                f"{eigenvalues.min():.3e}); expected a positive "
                                "semi-definite one")
    dense = np.sqrt(np.maximum(eigenvalues, 0.0))[:, None] * vectors.T
    return sp.csr_matrix(dense)


def _max_abs(M: sp.spmatrix) -> float:
    M = sp.csr_matrix(M)
    return float(abs(M).max()) if M.nnz else 0.0


def _scale(W: sp.csr_matrix) -> float:
    return max(_max_abs(W), 1e-300)


def _reproduces(F: sp.spmatrix, W: sp.csr_matrix) -> bool:
    return _max_abs(F.T @ F - W) <= FACTOR_TOLERANCE * _scale(W)


def _ldl_factor(W: sp.csr_matrix) -> sp.csr_matrix | None:
    """``D^{1/2} L^T P`` from SuperLU run as a symmetric (Cholesky-like) factorisation."""
    try:
        lu = spla.splu(W.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})
    except RuntimeError:  # exactly singular
        return None
    pivots = lu.U.diagonal()
    if not (np.array_equal(lu.perm_r, lu.perm_c) and (pivots > 0).all()):
        return None  # SuperLU pivoted after all, or W is not positive definite
    n = W.shape[0]
    # Pr W Pc = L U with Pr = Pc^T; U = diag(pivots) L^T for a symmetric W
    permutation = sp.csr_matrix((np.ones(n), (lu.perm_r, np.arange(n))), shape=(n, n))
    return (sp.diags(np.sqrt(pivots)) @ lu.L.T @ permutation).tocsr()


def residual_factors(observation: Observation, regularizer: Regularizer) -> ResidualFactors:
    """The factors :meth:`~prdp_fem.inverse.InverseProblem.residual` needs (built on the host)."""
    misfit = square_root_factor(observation.weight.to_scipy(), "observation weight W")
    if regularizer.kind == "tv":
        reg = None
    elif regularizer.kind == "l2":
        reg = square_root_factor(regularizer.matrix.to_scipy(), "L2 regulariser mass M")
    else:  # h1: sqrt(w_p) on every gradient component of point p
        weights = np.repeat(np.sqrt(np.asarray(regularizer.weights)), regularizer.dim)
        reg = sp.diags(weights) @ regularizer.matrix.to_scipy()
    return ResidualFactors(SparseMatrix.from_scipy(misfit),
                           None if reg is None else SparseMatrix.from_scipy(reg))
