r"""Preconditioned MINRES and Chebyshev semi-iteration in NumPy/SciPy, on the host.

MINRES solves a symmetric, possibly indefinite system ``A x = b`` with a symmetric positive
definite preconditioner ``P`` (applied as ``z = P^{-1} v``): the saddle-point systems of
:mod:`prdp_fem.inverse.kkt`. It is the Lanczos process in the ``P``-inner product with
Givens rotations (Paige and Saunders 1975; the recurrences of Elman, Silvester and Wathen,
*Finite Elements and Fast Iterative Solvers*, Algorithm 4.1), and it minimises
``||b - A x_k||_{P^{-1}}`` over the Krylov space, a norm it tracks for free:

.. math::

    z_j = P^{-1} v_j / \gamma_j,\quad \delta_j = z_j^\top A z_j,\quad
    v_{j+1} = A z_j - \tfrac{\delta_j}{\gamma_j} v_j - \tfrac{\gamma_j}{\gamma_{j-1}} v_{j-1},
    \quad \gamma_{j+1} = \sqrt{v_{j+1}^\top P^{-1} v_{j+1}},

the rotation of each new column gives the update direction ``w`` and ``x_j = x_{j-1} +
c_{j+1} \eta_j w_{j+1}``, ``|\eta_j| = ||r_j||_{P^{-1}}``. Unlike SciPy's ``minres`` it hands
every iterate to a callback that may stop the run, and says why it stopped.

:func:`chebyshev_inverse` approximates ``M^{-1}`` of a matrix whose Jacobi-scaled spectrum is
bounded, as a mass matrix's is (``D^{-1} M`` in ``[1/2, (d+2)/2]`` for P1 simplices, Wathen
1987): ``k`` steps of the Chebyshev semi-iteration are a fixed polynomial in ``M`` -- a linear,
symmetric, positive definite map, which a Krylov preconditioner must be and a few steps of CG
are not.

>>> import numpy as np, scipy.sparse as sp
>>> A = sp.csr_matrix(np.array([[2.0, 1.0], [1.0, -1.0]]))
>>> solution = minres(A.dot, np.array([1.0, 0.0]), lambda v: v, rtol=1e-12)
>>> np.round(solution.x, 12).tolist(), solution.result
([0.333333333333, 0.333333333333], 'converged')
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from ..errors import SolverBreakdownError, SolverConfigError
from .host_cg import dot

__all__ = ["MINRES_RESULTS", "MinresSolution", "chebyshev_inverse", "minres"]

#: why :func:`minres` stopped: the residual test was met, the iterations ran out, the callback
#: asked, or the Krylov space is exhausted (``A x = b`` solved exactly: ``gamma = 0``)
MINRES_RESULTS = ("converged", "max_iterations", "stopped", "exhausted")


class MinresSolution(NamedTuple):
    """What :func:`minres` returns."""

    x: np.ndarray
    iterations: int
    residual_norm: float            # ||b - A x||_{P^{-1}} (MINRES's recursive estimate)
    initial_residual_norm: float    # ||b - A x_0||_{P^{-1}}
    result: str                     # one of MINRES_RESULTS
    residual_history: tuple[float, ...]  # the residual norm after each iteration


def minres(apply_a: Callable[[np.ndarray], np.ndarray], b: np.ndarray,
           apply_preconditioner: Callable[[np.ndarray], np.ndarray], *, rtol: float = 1e-10,
           max_iterations: int = 1000, x0: np.ndarray | None = None,
           callback: Callable[[int, np.ndarray], bool | None] | None = None) -> MinresSolution:
    """Solve the symmetric ``A x = b`` by MINRES preconditioned with the SPD ``P``.

    Parameters
    ----------
    apply_a, apply_preconditioner
        ``v -> A v`` and ``v -> P^{-1} v``; both symmetric, ``P`` positive definite.
    rtol
        Stop once ``||r_k||_{P^{-1}} <= rtol ||r_0||_{P^{-1}}``.
    callback
        ``callback(iteration, x)`` after every iteration; ``True`` stops the run
        (``result="stopped"``).

    Raises
    ------
    SolverBreakdownError
        ``P^{-1}`` is not positive definite along the Krylov space, or a NaN/Inf appeared.
    """
    if not (isinstance(rtol, float | int) and 0 <= rtol < 1):
        raise SolverConfigError(f"rtol={rtol!r}: expected a number in [0, 1)")
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, int) \
            or max_iterations < 0:
        raise SolverConfigError(f"max_iterations={max_iterations!r}: expected an integer >= 0")
    b = np.asarray(b, dtype=float)
    x = np.zeros_like(b) if x0 is None else np.array(x0, dtype=float)
    v = b - apply_a(x) if x0 is not None else b.copy()
    z = apply_preconditioner(v)
    gamma = _preconditioned_norm(v, z, 1)
    initial, eta = gamma, gamma
    history: list[float] = []
    if gamma == 0.0:
        return MinresSolution(x, 0, 0.0, 0.0, "converged", ())
    v_previous = np.zeros_like(b)
    w, w_previous = np.zeros_like(b), np.zeros_like(b)
    gamma_previous, c, c_previous, s, s_previous = 1.0, 1.0, 1.0, 0.0, 0.0
    result = "max_iterations"
    for iteration in range(1, max_iterations + 1):
        z /= gamma
        q = apply_a(z)
        delta = dot(z, q)
        v_next = q - (delta / gamma) * v - (gamma / gamma_previous) * v_previous
        z_next = apply_preconditioner(v_next)
        gamma_next = _preconditioned_norm(v_next, z_next, iteration + 1)
        # the new column of the tridiagonal matrix, rotated by the two previous rotations
        alpha0 = c * delta - c_previous * s * gamma
        alpha1 = math.hypot(alpha0, gamma_next)
        alpha2 = s * delta + c_previous * c * gamma
        alpha3 = s_previous * gamma
        if alpha1 == 0.0:  # A is singular on the Krylov space: no further progress
            raise SolverBreakdownError(
                f"MINRES iteration {iteration}: the operator is singular on the Krylov space "
                "(a zero rotated pivot); expected a nonsingular symmetric system")
        c_next, s_next = alpha0 / alpha1, gamma_next / alpha1
        w_next = (z - alpha3 * w_previous - alpha2 * w) / alpha1
        x += (c_next * eta) * w_next
        eta = -s_next * eta
        history.append(abs(eta))
        v_previous, v, z = v, v_next, z_next
        w_previous, w = w, w_next
        gamma_previous, gamma = gamma, gamma_next
        c_previous, c, s_previous, s = c, c_next, s, s_next
        if callback is not None and callback(iteration, x):
            result = "stopped"
            break
        if abs(eta) <= rtol * initial:
            result = "converged"
            break
        if gamma == 0.0:  # the Krylov space is invariant: x solves A x = b
            result = "exhausted"
            break
    return MinresSolution(x, len(history), abs(eta), initial, result, tuple(history))


def _preconditioned_norm(v: np.ndarray, z: np.ndarray, iteration: int) -> float:
    """``sqrt(v . P^{-1} v)``; a typed error where it is negative or not finite."""
    vz = dot(v, z)
    if not math.isfinite(vz) or vz < -1e-14 * math.sqrt(abs(dot(v, v) * dot(z, z))):
        raise SolverBreakdownError(
            f"MINRES Lanczos vector {iteration}: v . P^-1 v = {vz!r}; expected a finite, "
            "non-negative number (a symmetric positive definite preconditioner and finite "
            "operands)")
    return math.sqrt(max(vz, 0.0))


def chebyshev_inverse(matrix: sp.spmatrix | sp.sparray, steps: int
                      ) -> Callable[[np.ndarray], np.ndarray]:
    """``b -> p(D^{-1} M) D^{-1} b ~ M^{-1} b``: ``steps`` Chebyshev semi-iterations on the
    Jacobi-scaled SPD ``M`` (Golub and Varga 1961; for mass matrices, Wathen and Rees 2009).

    The spectrum of ``D^{-1} M`` is taken in ``[lam_max / 4, lam_max]``, ``lam_max`` its
    Gershgorin bound (the largest absolute row sum of ``D^{-1} M``): for P1 mass matrices
    the exact upper end (2 on triangles) and the lower end 1/2 of triangles. The map is
    symmetric positive definite for any spectrum inside ``(0, 5 lam_max / 4)``, so a bound
    that misses the lower end only slows it down.
    """
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise SolverConfigError(f"steps={steps!r}: expected an integer >= 1")
    csr = sp.csr_matrix(matrix)
    diagonal = csr.diagonal()
    if not (np.all(np.isfinite(diagonal)) and np.all(diagonal > 0)):
        raise SolverConfigError("chebyshev_inverse: the matrix has a non-positive or non-finite "
                                "diagonal entry; expected a symmetric positive definite matrix")
    inverse_diagonal = 1.0 / diagonal
    upper = float(np.max(inverse_diagonal * np.asarray(abs(csr).sum(axis=1)).ravel()))
    lower = upper / 4.0
    theta, half_width = (upper + lower) / 2.0, (upper - lower) / 2.0
    sigma = theta / half_width

    def apply(b: np.ndarray) -> np.ndarray:
        residual = np.array(b, dtype=float)
        direction = (inverse_diagonal * residual) / theta
        x = np.zeros_like(residual)
        rho = 1.0 / sigma
        for step in range(steps):
            x += direction
            if step == steps - 1:
                break
            residual -= csr @ direction
            rho_next = 1.0 / (2.0 * sigma - rho)
            direction = (rho_next * rho) * direction + \
                (2.0 * rho_next / half_width) * (inverse_diagonal * residual)
            rho = rho_next
        return x

    return apply
