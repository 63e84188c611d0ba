r"""All-at-once solve of a linear-quadratic source problem: MINRES on its KKT system.

With ``unknown="source"`` and an L2 regulariser the objective is quadratic and its optimum
solves one symmetric indefinite system in the state ``u`` (free dofs), the source ``f`` and
the adjoint ``lam`` together:

.. math::

    \begin{pmatrix} H & 0 & A^\top \\ 0 & \alpha R & -S^\top \\ A & -S & 0 \end{pmatrix}
    \begin{pmatrix} u \\ f \\ \lambda \end{pmatrix} =
    \begin{pmatrix} E^\top B^\top W (d - B u_D) \\ \alpha R m_0 \\ b_0 \end{pmatrix},

``H = E^T B^T W B E`` the misfit's Hessian on the free dofs (``E`` injects them), ``A`` the
stiffness matrix, ``S`` the source map, ``R`` the regulariser's mass matrix, ``u_D`` the
Dirichlet values and ``b_0`` the right-hand side at ``f = 0`` -- the same discrete problem
:func:`~prdp_fem.inverse.reduced.reduced_cg` and :func:`~prdp_fem.inverse.driver.invert` solve.
:func:`kkt_solve` runs :func:`~prdp_fem.linalg.host_minres.minres` on it with the
block-diagonal preconditioner of Pearson and Wathen (2012),

.. math::

    P = \mathrm{diag}\big(H,\; \alpha R,\; \hat S\big), \qquad
    \hat S = (A + H / \sqrt{\alpha})\, H^{-1} (A + H / \sqrt{\alpha})^\top,

where ``Ŝ`` matches the Schur complement ``A H^{-1} A^T + S (alpha R)^{-1} S^T`` when
``S R^{-1} S^T = H``: its eigenvalues against ``Ŝ`` lie in ``[1/2, 1]`` whatever the mesh
size and ``alpha``. That holds exactly for the tracking problem with full-field L2 data, an
L2 regulariser and a source in the state's space (dolfin-adjoint's "mother problem").
Elsewhere it is an approximation MINRES still converges with: a misfit weighted by ``w``
(``H = w M``) took 14-28 iterations for ``w`` from 1e-4 to 1e4, the same as the matching
rescaled for ``w``. ``H^{-1}`` and ``(alpha R)^{-1}`` are a few Chebyshev semi-iterations,
``(A + H / sqrt(alpha))^{-1}`` one AMG V-cycle (pyamg, symmetric Gauss-Seidel;
Ruge-Stueben by default, whose V-cycle on this matrix contracted by 0.05 at every size
measured, against 0.34-0.63 for smoothed aggregation, which made MINRES take twice the
iterations). Every operation is a SciPy sparse
product or a pyamg cycle on the host: nothing is compiled.

No truncation and no PRDP here: the iteration count of a robust preconditioner does not grow
with the mesh, so one converged solve of the coupled system costs a few dozen V-cycles,
where the reduced-space CG spends two inner solves per outer iteration.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from ..errors import SolverConfigError
from ..linalg.amg import amg_hierarchy
from ..linalg.host_minres import chebyshev_inverse, minres
from .driver import InverseProblem
from .reduced import check_quadratic

__all__ = ["KKTSolution", "KKTSystem", "kkt_solve", "kkt_system"]


class KKTSystem(NamedTuple):
    """The blocks of the KKT system (SciPy CSR, free state dofs) and its right-hand side."""

    misfit_hessian: sp.csr_matrix   # H = E^T B^T W B E
    stiffness: sp.csr_matrix        # A
    source: sp.csr_matrix           # S (free rows, every source dof)
    regularization: sp.csr_matrix   # R (the L2 regulariser's mass matrix)
    alpha: float
    rhs: np.ndarray                 # (state, source, adjoint) blocks stacked

    @property
    def sizes(self) -> tuple[int, int]:
        """``(free state dofs, source dofs)``."""
        return self.stiffness.shape[0], self.regularization.shape[0]

    def apply(self, x: np.ndarray) -> np.ndarray:
        """The KKT matrix times ``x = (u, f, lam)``."""
        n_u, n_f = self.sizes
        u, f, lam = x[:n_u], x[n_u:n_u + n_f], x[n_u + n_f:]
        stiff_u, stiff_lam = self.stiffness @ u, self.stiffness.T @ lam
        return np.concatenate([self.misfit_hessian @ u + stiff_lam,
                               self.alpha * (self.regularization @ f) - self.source.T @ lam,
                               stiff_u - self.source @ f])


class KKTSolution(NamedTuple):
    """What :func:`kkt_solve` returns: the optimum and the statistics of its solve."""

    field: np.ndarray               # the source f (every source dof)
    state: np.ndarray               # u on the free dofs (problem.system.expand gives all)
    adjoint: np.ndarray             # lam on the free dofs
    iterations: int                 # MINRES iterations
    vcycles: int                    # AMG V-cycles applied (two per preconditioner application)
    residual_norm: float            # ||r||_{P^-1} at the end
    initial_residual_norm: float
    result: str                     # see prdp_fem.linalg.host_minres.MINRES_RESULTS
    setup_time: float               # the blocks, the Chebyshev bounds and the AMG hierarchy
    solve_time: float               # the MINRES iterations


def kkt_system(problem: InverseProblem) -> KKTSystem:
    """The KKT blocks of ``problem`` read from its own operators (a quadratic source problem
    with an L2 regulariser; anything else is a :class:`SolverConfigError`)."""
    _check_problem(problem)
    system, observation = problem.system, problem.observation
    free = np.asarray(system.free_dofs)
    observed = observation.operator.to_scipy().tocsc()
    weight = observation.weight.to_scipy()
    observed_free = observed[:, free].tocsr()
    hessian = (observed_free.T @ (weight @ observed_free)).tocsr()
    stiffness = system.operator(problem.known).to_scipy().tocsr()
    source = system.source.to_scipy().tocsr()
    regularization = problem.regularizer.gram.to_scipy().tocsr()
    alpha = float(problem.alpha)
    dirichlet_state = np.zeros(system.n_dofs)
    dirichlet_state[np.asarray(system.dirichlet_dofs)] = np.asarray(system.dirichlet_values)
    data_residual = np.asarray(observation.data) - observed @ dirichlet_state
    rhs = np.concatenate([
        observed_free.T @ (weight @ data_residual),
        alpha * (regularization @ np.asarray(problem.regularizer.reference)),
        np.asarray(system.rhs(problem.known)),
    ])
    return KKTSystem(hessian, stiffness, source, regularization, alpha, rhs)


def _check_problem(problem: InverseProblem) -> None:
    check_quadratic(problem, "kkt_solve", ("l2",),
                    "its preconditioner needs an invertible regulariser; reduced_cg solves 'h1'")
    if problem.system.nullspace is not None:
        raise SolverConfigError("kkt_solve: the state equation has a nullspace (pure Neumann "
                                "data); expected a unique state (Dirichlet dofs or a pin)")
    if not float(problem.alpha) > 0:
        raise SolverConfigError(f"kkt_solve: alpha={float(problem.alpha)!r}; expected alpha > 0")


def kkt_solve(problem: InverseProblem, *, rtol: float = 1e-10, iterations: int = 500,
              amg: str = "rs", mass_steps: int = 4,
              callback: Callable[[int, np.ndarray], bool | None] | None = None
              ) -> KKTSolution:
    """The optimum of a linear-quadratic source problem by preconditioned MINRES on its KKT
    system (see the module's text).

    Parameters
    ----------
    rtol
        Stop once the preconditioned residual norm falls by this factor.
    iterations
        At most this many MINRES iterations.
    amg
        The hierarchy of ``A + H / sqrt(alpha)``: ``"rs"`` (Ruge-Stueben, default) or ``"sa"``
        (smoothed aggregation; cheaper to build in 3-D, twice the iterations in 2-D).
    mass_steps
        Chebyshev semi-iterations of each mass-type block.
    callback
        ``callback(iteration, field)`` after every iteration, ``field`` the current source;
        ``True`` stops the solve (``result="stopped"``).

    Raises
    ------
    SolverConfigError
        Not a quadratic source problem with an L2 regulariser, ``alpha <= 0``, a state with a
        nullspace, a state dof the misfit does not see (point sensors: ``H`` is singular), or
        a bad option.
    SolverBreakdownError
        A NaN/Inf or a breakdown of MINRES.
    """
    start = time.perf_counter()
    blocks = kkt_system(problem)
    hessian = blocks.misfit_hessian
    if not np.all(hessian.diagonal() > 0):
        unseen = int(np.sum(~(hessian.diagonal() > 0)))
        raise SolverConfigError(
            f"kkt_solve: {unseen} free state dof(s) carry no misfit weight (point or boundary "
            "sensors); expected every state dof observed (full_field), or use reduced_cg")
    preconditioner = _pearson_wathen(blocks, amg, mass_steps)
    setup = time.perf_counter() - start
    n_u, n_f = blocks.sizes
    outer = None if callback is None else (lambda k, x: callback(k, x[n_u:n_u + n_f]))
    start = time.perf_counter()
    solution = minres(blocks.apply, blocks.rhs, preconditioner, rtol=rtol,
                      max_iterations=iterations, callback=outer)
    x = solution.x
    return KKTSolution(
        field=x[n_u:n_u + n_f], state=x[:n_u], adjoint=x[n_u + n_f:],
        iterations=solution.iterations, vcycles=2 * (solution.iterations + 1),
        residual_norm=solution.residual_norm,
        initial_residual_norm=solution.initial_residual_norm, result=solution.result,
        setup_time=setup, solve_time=time.perf_counter() - start)


AMG_KINDS = ("rs", "sa")


def _pearson_wathen(blocks: KKTSystem, amg: str, mass_steps: int
                    ) -> Callable[[np.ndarray], np.ndarray]:
    """``P^{-1}`` of the module's text, built once."""
    if amg not in AMG_KINDS:
        raise SolverConfigError(f"amg={amg!r}: expected one of {list(AMG_KINDS)}")
    hessian, n_u, n_f = blocks.misfit_hessian, *blocks.sizes
    beta = 1.0 / math.sqrt(blocks.alpha)
    # the hierarchy's own symmetric Gauss-Seidel: one V-cycle is then a symmetric map
    cycle = amg_hierarchy((blocks.stiffness + beta * hessian).tocsr(), kind=amg,
                          smoother="gauss_seidel").aspreconditioner(cycle="V")
    hessian_inverse = chebyshev_inverse(hessian, mass_steps)
    regularization_inverse = chebyshev_inverse(blocks.regularization, mass_steps)

    def apply(v: np.ndarray) -> np.ndarray:
        return np.concatenate([
            hessian_inverse(v[:n_u]),
            regularization_inverse(v[n_u:n_u + n_f]) / blocks.alpha,
            cycle @ (hessian @ (cycle @ v[n_u + n_f:])),
        ])

    return apply
