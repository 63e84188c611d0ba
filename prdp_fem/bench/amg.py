"""AMG-PCG against pyamg's own CG-accelerated solve, measured side by side in one process.

For each problem (P1 Poisson, ``kappa = 1``, on the unit square or cube) and each
implementation of :mod:`prdp_fem.linalg.amg`, the hierarchy is built once and both solvers run on it
to ``rtol = 1e-10`` (``||r|| <= rtol ||b||`` for both):

- pyamg: ``ml.solve(b, tol=1e-10, accel='cg')`` on the hierarchy ``ml``;
- ours: the jitted ``solve(A, b, ConvergedCG(rtol=1e-10), preconditioner=M)`` with ``M`` built
  from the same ``ml`` (``"jax"``: damped-Jacobi smoothing, ``"callback"``: pyamg's symmetric
  Gauss-Seidel), so the two preconditioners are the same map and the iterations must agree.

Setup (pyamg's own ``smoothed_aggregation_solver`` with the same smoother, against our build,
which adds the conversion to JAX arrays and a check cycle) and solve are timed in alternated
pairs; the ratios are medians of the per-pair ratios, so that load drifting on a shared machine
cancels. The first jitted call is timed apart: ``compile_s`` is its excess over a steady call.

pyamg's cycle computes norms through BLAS; on a small shared machine, a multi-threaded BLAS
fighting other processes slows it down (``OPENBLAS_NUM_THREADS=1`` avoids that).
"""

from __future__ import annotations

import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import SolverConfigError
from ..linalg.amg import IMPLEMENTATIONS, amg_hierarchy, checked_cycle
from ..linalg.cg import ConvergedCG, solve
from ..linalg.operator import SparseMatrix
from .cg import poisson_operator

__all__ = ["AMGCost", "amg_cost"]

RTOL = 1e-10
SMOOTHER = {"jax": "jacobi", "callback": "gauss_seidel"}


class AMGCost(NamedTuple):
    """One problem and implementation: iterations, setup and solve time, ours and pyamg's."""

    dim: int
    n_dofs: int
    implementation: str
    iterations: int  # ours, to ||r|| <= 1e-10 ||b||
    pyamg_iterations: int  # ml.solve(accel='cg') on the same hierarchy
    setup_s: float  # median: our build (pyamg hierarchy + JAX arrays + check)
    pyamg_setup_s: float  # median: pyamg's own solver construction, same smoother
    setup_ratio: float  # median of the per-pair ratios
    solve_s: float  # median: our jitted solve, compile excluded
    pyamg_solve_s: float  # median: ml.solve(b, tol=1e-10, accel='cg')
    ratio: float  # median of the per-pair solve-time ratios (target <= 1.5)
    compile_s: float  # first jitted call minus a steady one

    @property
    def iterations_equal(self) -> bool:
        return self.iterations == self.pyamg_iterations


def _pyamg_setup(csr, smoother: str):
    """pyamg's own setup with the smoother our cycle uses (withrho: pyamg estimates rho)."""
    import pyamg  # here: importing this module must not import pyamg (see prdp_fem.linalg.amg)

    if smoother == "jacobi":
        relax = ("jacobi", {"omega": 4.0 / 3.0, "iterations": 1})
    else:
        relax = ("gauss_seidel", {"sweep": "symmetric", "iterations": 1})
    return pyamg.smoothed_aggregation_solver(csr, symmetry="symmetric", presmoother=relax,
                                             postsmoother=relax)


def _our_setup(matrix: SparseMatrix, implementation: str):
    """What ``amg_preconditioner`` does, keeping the hierarchy for pyamg's solve."""
    ml = amg_hierarchy(matrix, smoother=SMOOTHER[implementation])
    return ml, jax.block_until_ready(checked_cycle(ml, implementation))


def _timed(fn, *args):
    tic = time.perf_counter()
    out = fn(*args)
    return time.perf_counter() - tic, out


@jax.jit
def _converged_solve(matrix, b, precond):
    return solve(matrix, b, ConvergedCG(rtol=RTOL, preconditioner=precond))


def _pyamg_solve(ml, b: np.ndarray) -> int:
    residuals: list[float] = []
    ml.solve(b, tol=RTOL, accel="cg", maxiter=1000, residuals=residuals)
    return len(residuals) - 1


def _cost_of(matrix, b, implementation: str, repeats: int, dim: int) -> AMGCost:
    csr, b_host = matrix.to_scipy(), np.asarray(b)
    setups = []
    for _ in range(repeats):
        # a fresh copy: pyamg caches rho(D^-1 A) on the matrix object, and a rebuild (new
        # kappa) starts from a new matrix; reusing one object would skip that estimate
        t_pyamg, _ = _timed(_pyamg_setup, csr.copy(), SMOOTHER[implementation])
        t_ours, (ml, precond) = _timed(_our_setup, matrix, implementation)
        setups.append((t_ours, t_pyamg))
    first, sol = _timed(lambda: jax.block_until_ready(_converged_solve(matrix, b, precond)))
    solves = []
    for _ in range(repeats):
        t_ours, sol = _timed(lambda: jax.block_until_ready(_converged_solve(matrix, b, precond)))
        t_pyamg, pyamg_iterations = _timed(_pyamg_solve, ml, b_host)
        solves.append((t_ours, t_pyamg))
    setups, solves = np.array(setups), np.array(solves)
    steady = float(np.median(solves[:, 0]))
    return AMGCost(dim, csr.shape[0], implementation, int(sol.iterations), pyamg_iterations,
                   float(np.median(setups[:, 0])), float(np.median(setups[:, 1])),
                   float(np.median(setups[:, 0] / setups[:, 1])), steady,
                   float(np.median(solves[:, 1])), float(np.median(solves[:, 0] / solves[:, 1])),
                   max(first - steady, 0.0))


def amg_cost(n_side: int, *, dim: int = 2, implementations: tuple[str, ...] = IMPLEMENTATIONS,
             repeats: int = 5) -> list[AMGCost]:
    """:class:`AMGCost` of each implementation on P1 Poisson with ``n_side`` cells per side.

    2-D: ``n_side = 256`` -> 65k dofs, ``512`` -> 261k; 3-D: ``32`` -> 30k, ``64`` -> 250k.
    """
    if isinstance(n_side, bool) or not isinstance(n_side, int) or n_side < 2:
        raise SolverConfigError(f"n_side={n_side!r}: expected an integer >= 2")
    if dim not in (2, 3):
        raise SolverConfigError(f"dim={dim!r}: expected 2 or 3")
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise SolverConfigError(f"repeats={repeats!r}: expected an integer >= 1")
    unknown = [i for i in implementations if i not in IMPLEMENTATIONS]
    if unknown or not implementations:
        raise SolverConfigError(f"implementations={list(implementations)!r}: expected some of "
                                f"{IMPLEMENTATIONS}")
    matrix, b = poisson_operator(n_side, dim)
    b = jnp.asarray(b)
    return [_cost_of(matrix, b, implementation, repeats, dim)
            for implementation in implementations]
