r"""Condition-number estimates from the Lanczos tridiagonal that CG builds for free.

PCG's step lengths :math:`\alpha_j` and direction updates :math:`\beta_j` are the entries of the
Lanczos tridiagonal of :math:`M A` (Saad, *Iterative Methods*, sec. 6.7.3):

.. math::

    T_{00} = \frac{1}{\alpha_0}, \quad
    T_{jj} = \frac{1}{\alpha_j} + \frac{\beta_{j-1}}{\alpha_{j-1}}, \quad
    T_{j,j+1} = \frac{\sqrt{\beta_j}}{\alpha_j},

whose extreme eigenvalues (Ritz values) converge to those of :math:`M A` from inside, the
largest fast, the smallest once CG has resolved the slowest mode: run to a tight tolerance, the
ratio is a good (lower) estimate of :math:`\kappa(M A)`. NumPy/SciPy reference path, for
diagnostics and error bounds, not for the hot loop.

>>> import scipy.sparse as sp
>>> est = condition_estimate(sp.diags([1.0, 10.0, 100.0]), preconditioner="identity")
>>> round(est.condition, 6), est.iterations
(100.0, 3)
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from ..errors import SolverConfigError

__all__ = ["ConditionEstimate", "condition_estimate"]


class ConditionEstimate(NamedTuple):
    smallest: float  # smallest Ritz value of M A
    largest: float  # largest Ritz value of M A
    condition: float  # largest / smallest
    iterations: int  # CG iterations behind the estimate


def condition_estimate(matrix: sp.spmatrix, *, preconditioner: str = "jacobi",
                       nullspace: np.ndarray | None = None, rtol: float = 1e-10,
                       max_iterations: int | None = None, seed: int = 0) -> ConditionEstimate:
    """Estimate ``kappa(M A)`` (``M = I`` or ``diag(A)^-1``) with CG on a random right-hand side.

    ``nullspace`` (a vector) restricts the estimate to its complement (pure Neumann operators).
    A random right-hand side excites every eigenvector; the iteration stops at
    ``||r|| <= rtol ||b||`` or ``max_iterations`` (default ``2 n``).
    """
    if preconditioner not in ("identity", "jacobi"):
        raise SolverConfigError(f"preconditioner={preconditioner!r}: expected 'identity' or "
                                "'jacobi'")
    matrix = sp.csr_matrix(matrix, dtype=float)
    n = matrix.shape[0]
    diag = matrix.diagonal()
    inverse_diag = np.ones(n) if preconditioner == "identity" else \
        np.where(diag > 0, 1.0 / np.where(diag > 0, diag, 1.0), 1.0)
    project = _projector(nullspace, n)
    b = project(np.random.default_rng(seed).standard_normal(n))
    alphas, betas = _cg_coefficients(matrix, inverse_diag, project, b, rtol,
                                     2 * n if max_iterations is None else max_iterations)
    if not alphas:
        return ConditionEstimate(np.nan, np.nan, np.nan, 0)
    ritz = _ritz_values(np.asarray(alphas), np.asarray(betas))
    smallest, largest = float(ritz[0]), float(ritz[-1])
    condition = largest / smallest if smallest > 0 else np.inf
    return ConditionEstimate(smallest, largest, condition, len(alphas))


def _projector(nullspace, n):
    if nullspace is None:
        return lambda v: v
    v = np.asarray(nullspace, dtype=float)
    v = v / np.linalg.norm(v)
    return lambda w: w - (v @ w) * v


def _cg_coefficients(matrix, inverse_diag, project, b, rtol, max_iterations):
    """PCG from zero, recording ``alpha_j`` and ``beta_j``; stops on tolerance or breakdown."""
    r = b.copy()
    z = project(inverse_diag * r)
    p = z.copy()
    rz = r @ z
    target = rtol * np.linalg.norm(b)
    alphas, betas = [], []
    for _ in range(max_iterations):
        q = matrix @ p
        pq = p @ q
        if not (pq > 0 and rz > 0):
            break
        alpha = rz / pq
        r = r - alpha * q
        z = project(inverse_diag * project(r))
        rz_new = r @ z
        alphas.append(alpha)
        betas.append(rz_new / rz)
        if np.linalg.norm(r) <= target:
            break
        p = z + betas[-1] * p
        rz = rz_new
    return alphas, betas


def _ritz_values(alphas: np.ndarray, betas: np.ndarray) -> np.ndarray:
    diagonal = 1.0 / alphas
    diagonal[1:] += betas[:-1] / alphas[:-1]
    off = np.sqrt(np.maximum(betas[:-1], 0.0)) / alphas[:-1]
    return sla.eigvalsh_tridiagonal(diagonal, off)
