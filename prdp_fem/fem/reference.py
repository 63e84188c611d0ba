"""Converged reference solves (pyamg, SciPy) and finite-element error norms.

Not on the hot path: these run in NumPy/SciPy on the same condensed operator the JAX solvers
see, so differences measure the solver, not the discretisation.

Norms of a full nodal vector ``e`` (all dofs): discrete ``L2 = sqrt(e' M e)`` and
``H1 seminorm = sqrt(e' K1 e)`` with the mass matrix ``M`` and the unit-coefficient stiffness
``K1``; :func:`l2_error` / :func:`h1_error` integrate against an exact solution by quadrature.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import skfem
from skfem.helpers import dot, grad

from ..linalg.amg import seeded_numpy_random
from .discretization import Discretization

__all__ = [
    "ReferenceSolution",
    "amg_solve",
    "direct_solve",
    "h1_error",
    "h1_seminorm",
    "l2_error",
    "l2_norm",
    "relative_h1_error",
    "relative_l2_error",
]


class ReferenceSolution(NamedTuple):
    x: np.ndarray
    iterations: int
    residual_norm: float  # ||b - A x||_2, recomputed


def amg_solve(matrix: sp.spmatrix, b: np.ndarray, *, rtol: float = 1e-12,
              max_iterations: int = 500) -> ReferenceSolution:
    """pyamg smoothed aggregation as a CG preconditioner, to ``||r|| <= rtol ||b||``.

    The hierarchy is built with NumPy's global generator seeded (and restored after), so the
    same system gives the same solution bit for bit in every process: unseeded, pyamg's
    spectral-radius estimates moved the synthetic data of a learned study in its last bits
    from run to run, and Newton-CG trainings on it ended at different errors.
    """
    import pyamg  # here: only reference solves need it (see prdp_fem.linalg.amg)

    matrix = sp.csr_matrix(matrix)
    b = np.asarray(b, dtype=float)
    with seeded_numpy_random():
        hierarchy = pyamg.smoothed_aggregation_solver(matrix, symmetry="symmetric")
    residuals: list[float] = []
    x = hierarchy.solve(b, tol=rtol, accel="cg", maxiter=max_iterations, residuals=residuals)
    return ReferenceSolution(x, max(len(residuals) - 1, 0), float(np.linalg.norm(b - matrix @ x)))


def direct_solve(matrix: sp.spmatrix, b: np.ndarray, *,
                 nullspace: np.ndarray | None = None) -> ReferenceSolution:
    """Sparse LU (SciPy SuperLU); for small systems.

    With ``nullspace=v`` (``A v = 0``), the bordered system ``[[A, v], [v', 0]]`` gives the
    solution orthogonal to ``v`` of the projected system ``A x = P b`` (as :func:`~prdp_fem.solve`).
    """
    b = np.asarray(b, dtype=float)
    if nullspace is None:
        x = spla.splu(sp.csc_matrix(matrix)).solve(b)
        return ReferenceSolution(x, 0, float(np.linalg.norm(b - matrix @ x)))
    v = np.asarray(nullspace, dtype=float)
    v = v / np.linalg.norm(v)
    column = sp.csr_matrix(v[:, None])
    bordered = sp.bmat([[matrix, column], [column.T, None]], format="csc")
    b = b - (v @ b) * v
    x = spla.splu(bordered).solve(np.append(b, 0.0))[:-1]
    return ReferenceSolution(x, 0, float(np.linalg.norm(b - matrix @ x)))


def l2_norm(disc: Discretization, u: np.ndarray) -> float:
    """``sqrt(u' M u)`` for a full nodal vector ``u``."""
    u = np.asarray(u)
    return float(np.sqrt(max(u @ (disc.mass_matrix @ u), 0.0)))


def h1_seminorm(disc: Discretization, u: np.ndarray) -> float:
    """``sqrt(u' K1 u)`` = ``||grad u||_L2`` for a full nodal vector ``u``."""
    u = np.asarray(u)
    return float(np.sqrt(max(u @ (disc.laplace_matrix @ u), 0.0)))


def relative_l2_error(disc: Discretization, u: np.ndarray, u_ref: np.ndarray) -> float:
    """``||u - u_ref||_L2 / ||u_ref||_L2`` of two nodal vectors of ``disc`` (mass-matrix norms)."""
    return l2_norm(disc, np.asarray(u) - u_ref) / l2_norm(disc, u_ref)


def relative_h1_error(disc: Discretization, u: np.ndarray, u_ref: np.ndarray) -> float:
    """``|u - u_ref|_H1 / |u_ref|_H1`` of two nodal vectors of ``disc`` (H1 seminorms)."""
    return h1_seminorm(disc, np.asarray(u) - u_ref) / h1_seminorm(disc, u_ref)


def l2_error(disc: Discretization, u: np.ndarray,
             exact: Callable[[np.ndarray], np.ndarray]) -> float:
    """``||u_h - u||_L2`` by quadrature (``exact(x)``, ``x`` of shape ``(dim, ...)``)."""
    uh = disc.basis.interpolate(np.asarray(u))
    form = skfem.Functional(lambda w: (w.uh - exact(w.x)) ** 2)
    return float(np.sqrt(form.assemble(disc.basis, uh=uh)))


def h1_error(disc: Discretization, u: np.ndarray,
             exact_grad: Callable[[np.ndarray], np.ndarray]) -> float:
    """``||grad u_h - grad u||_L2`` by quadrature (``exact_grad(x)`` of shape ``(dim, ...)``)."""
    uh = disc.basis.interpolate(np.asarray(u))

    def integrand(w):
        diff = grad(w.uh) - exact_grad(w.x)
        return dot(diff, diff)

    return float(np.sqrt(skfem.Functional(integrand).assemble(disc.basis, uh=uh)))
