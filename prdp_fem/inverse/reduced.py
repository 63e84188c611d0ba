r"""CG on the reduced Hessian of a linear inverse problem (the unknown is the source).

With ``unknown="source"`` the state ``u(f) = A^{-1} (S f + h - L kappa)`` is affine in ``f``,
so with an L2 or H1 regulariser the reduced objective is quadratic:

.. math::

    J(f) = \tfrac12 \|B u(f) - d\|_W^2 + \alpha R(f)
         = \tfrac12 f^\top H f - c^\top f + \text{const}, \qquad
    H = S^\top A^{-1} B^\top W B A^{-1} S + \alpha R'',

and the optimum solves ``H f = c``. :func:`reduced_cg` runs preconditioned CG on it, with the
L2 Riesz map (the parameter mass matrix ``M``) as preconditioner:

.. math::

    r_0 = -\nabla J(f_0),\; z_0 = M^{-1} r_0,\; p_0 = z_0; \qquad
    q_k = H p_k,\; a_k = \frac{r_k^\top z_k}{p_k^\top q_k},\;
    f_{k+1} = f_k + a_k p_k,

    r_{k+1} = r_k - a_k q_k,\; z_{k+1} = z_k - a_k M^{-1} q_k,\;
    p_{k+1} = z_{k+1} + \frac{r_{k+1}^\top z_{k+1}}{r_k^\top z_k} p_k .

``H p`` is the gradient at ``p`` of the *homogeneous* problem (:func:`homogeneous`: data,
regulariser reference, Neumann and Dirichlet data set to zero): one forward and one adjoint
truncated PCG solve, through :meth:`InverseProblem.loss` and implicit differentiation. Why
``M^{-1}``: the Euclidean gradient of nodal values carries a factor ``M`` (it is the L2
gradient times the mass matrix); undoing it makes the iterates discrete functions rather than
nodal vectors, so the outer iteration count does not grow with the mesh. On the mother problem
the first step with a lumped ``M`` instead had 5x the error (1.2e-3 against 2.5e-4 at
n = 128): ``M_L^{-1} S^T`` puts mass-matrix rows on the boundary nodes, ``M^{-1} S^T`` does not.

One compiled function serves every outer iteration: ``(J, grad J)`` of a problem at a point,
called on the problem at ``f_0`` and on the homogeneous problem at each ``p_k``; the CG vectors
and the Riesz map (Jacobi-PCG on ``M``, :mod:`prdp_fem.linalg.host_cg`) live on the host. The inner
solves take ``K``, ``K_adj`` or ``rtol`` from a
refinement controller (:mod:`prdp_fem.inverse.refinement`: ``fixed(K)``, ``prdp(...)`` watching the
residual
``sqrt(r.z)``, ``converged(rtol)``), and any inner preconditioner (``"jacobi"``, or a pytree such
as an AMG cycle). With truncated inner solves ``H p`` is only approximate, so CG restarts from
the true gradient whenever the controller changes the solver.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import numpy as np
import scipy.sparse.linalg as spla

from .._xla_options import compile_lowered, compiler_options
from ..errors import SolverConfigError
from ..linalg.cg import IterationCounter, TruncatedCG
from ..linalg.host_cg import dot, jacobi_pcg, power_of_two_scale
from .driver import InverseProblem, initial_params
from .history import History, StepRecord
from .refinement import Refinement, fixed, refuse_learning_rate_scaling
from .steps import (
    cycle_argument,
    preconditioner_key,
    step_solver,
)

__all__ = ["ReducedCG", "check_quadratic", "homogeneous", "reduced_cg"]


class ReducedCG(NamedTuple):
    """What :func:`reduced_cg` returns."""

    field: np.ndarray           # the recovered source (nodal)
    history: History            # one StepRecord per outer iteration
    riesz_iterations: int       # mass-matrix PCG iterations of the preconditioner M^{-1}
    residual_norm: float        # sqrt(r.z) = ||grad J||_{M^{-1}} at the end (recursive)
    initial_residual_norm: float


def homogeneous(problem: InverseProblem) -> InverseProblem:
    """The problem with every affine term zeroed: its gradient at ``p`` is ``H p``.

    Zeroed: the data, the regulariser's reference ``m_0``, the Neumann load and the Dirichlet
    values (they enter ``b`` and the misfit affinely, never ``H``).
    """
    def zeros(array):  # NumPy: a jnp constructor would compile a kernel per shape
        return np.zeros(array.shape, array.dtype)

    system = dataclasses.replace(problem.system, neumann=zeros(problem.system.neumann),
                                 dirichlet_values=zeros(problem.system.dirichlet_values))
    observation = dataclasses.replace(problem.observation,
                                      data=zeros(problem.observation.data),
                                      noise_std=zeros(problem.observation.noise_std))
    regularizer = dataclasses.replace(problem.regularizer,
                                      reference=zeros(problem.regularizer.reference))
    return dataclasses.replace(problem, system=system, observation=observation,
                               regularizer=regularizer)


def check_quadratic(problem: InverseProblem, caller: str = "reduced_cg",
                    regularizations: tuple[str, ...] = ("l2", "h1"),
                    why: str = "TV is not quadratic; use invert()") -> None:
    """Refuse a problem whose objective is not quadratic in a source (a SolverConfigError
    naming ``caller``), or whose regulariser is not one of ``regularizations`` (``why``)."""
    parameterization = problem.parameterization
    if parameterization.unknown != "source" or parameterization.bounds is not None:
        raise SolverConfigError(
            f"{caller}: unknown={parameterization.unknown!r}, "
            f"bounds={parameterization.bounds!r}; expected unknown='source' without bounds "
            "(a quadratic objective; use invert() otherwise)")
    if problem.regularizer.kind not in regularizations:
        expected = " or ".join(repr(kind) for kind in regularizations)
        raise SolverConfigError(
            f"{caller}: regularization={problem.regularizer.kind!r}; expected {expected} "
            f"({why})")


def _make_gradient(tolerance_mode: bool, preconditioner: Any):
    """``(problem, f, K, K_adj, rtol, counter[, cycle]) -> (J(f), grad J(f))`` through the
    inner solves; a JAX AMG cycle comes as the last argument (an argument ran 30 % faster than
    the same arrays closed over as constants: :func:`prdp_fem.inverse.steps.preconditioner_key`).
    The counter is an argument too, so the program does not depend on which counter counts."""

    def gradient(problem, f, K, K_adj, rtol, counter, cycle=None):
        solver = step_solver("implicit", tolerance_mode, K, K_adj, rtol,
                         preconditioner if cycle is None else cycle)
        return jax.value_and_grad(lambda z: problem.loss(z, solver, counter=counter)[0])(f)

    return gradient


class _Riesz:
    """``M^{-1} g``: Jacobi-PCG on the parameter mass matrix, on the host.

    Host-side because ``M`` is fixed and well conditioned (a few dozen iterations): inside the
    compiled gradient it was one more loop to compile, about 0.2 s of every run's start.
    """

    def __init__(self, problem: InverseProblem, rtol: float):
        self._mass, self._rtol, self.iterations = problem.parameter_mass.to_scipy(), rtol, 0

    def __call__(self, g: np.ndarray) -> np.ndarray:
        solution = jacobi_pcg(self._mass, g, self._rtol)
        if solution is None:  # not a mass matrix after all: factorise
            return spla.spsolve(self._mass.tocsc(), g)
        self.iterations += solution.iterations
        return solution.x


def _compile(fn: Callable, *example) -> tuple[Callable, float]:
    """``fn`` compiled for arguments like ``example`` (traced values: no recompiles); timed."""
    start = time.perf_counter()
    traced = jax.jit(fn).trace(*example)
    executable = compile_lowered(traced.lower(), compiler_options(traced.jaxpr))
    return executable, time.perf_counter() - start


class _Relative:
    """Relative L2 error ``||f - t||_M / ||t||_M`` on the host (no extra compilation)."""

    def __init__(self, problem: InverseProblem):
        self._truth = None if problem.truth is None else np.asarray(problem.truth)
        self._mass = problem.parameter_mass.to_scipy()
        if self._truth is not None:
            self._truth_norm2 = dot(self._truth, self._mass @ self._truth)

    def __call__(self, f: np.ndarray) -> float:
        if self._truth is None:
            return math.nan
        e = f - self._truth
        return math.sqrt(dot(e, self._mass @ e) / self._truth_norm2)


def reduced_cg(problem: InverseProblem, *, refinement: Refinement | None = None,
               iterations: int = 50, rtol: float = 0.0, init: np.ndarray | None = None,
               preconditioner: Any = "jacobi", riesz_rtol: float = 1e-10,
               callback: Callable[[StepRecord, np.ndarray], bool | None] | None = None,
               ) -> ReducedCG:
    """Minimise the quadratic ``J`` by Riesz-preconditioned CG on its reduced Hessian.

    Parameters
    ----------
    refinement
        Picks the inner solves (``K``, ``K_adj`` or a tolerance) before every outer iteration
        and sees the residual ``sqrt(r.z)`` after it; default ``fixed(50)``.
    iterations
        At most this many outer iterations (Hessian products).
    rtol
        Stop once ``sqrt(r.z) <= rtol sqrt(r_0.z_0)`` (0: never).
    init
        Initial source field; default zeros.
    preconditioner
        Of the inner state and adjoint solves (``"jacobi"``, ``"identity"`` or a pytree).
    riesz_rtol
        Relative tolerance of the mass-matrix solves that apply ``M^{-1}``.
    callback
        ``callback(record, field)`` after every outer iteration; ``True`` stops the run.

    Notes
    -----
    The records are :class:`~prdp_fem.inverse.history.StepRecord` s: ``loss`` is ``J`` at the step's
    start (tracked by the exact quadratic identity ``J(f + a p) = J(f) - a r.p + a^2 p.q / 2``),
    ``misfit`` and ``state_error`` are NaN, ``evaluations`` counts the gradient evaluations,
    ``refinements`` those before the step (the controller sees the residual after the record
    and the callback).
    """
    check_quadratic(problem)
    refinement = fixed(50) if refinement is None else refinement
    refuse_learning_rate_scaling(refinement, "reduced_cg")
    _check_options(refinement, iterations, rtol, riesz_rtol, preconditioner)
    counter = IterationCounter()
    f = np.asarray(initial_params(problem, init))
    control = refinement.init()
    cycle = cycle_argument(preconditioner)
    # A compiled function records its arguments' structure as traced, and a counter traces as
    # a reference to its slot: called with the counter itself it raises a pytree mismatch. So
    # the lowering and every call take that reference (a pytree map over a counter gives it).
    counter_ref = jax.tree_util.tree_map(lambda slot: slot, counter)
    gradient, compile_time = _compile(
        _make_gradient(refinement.tolerance_mode, preconditioner_key(preconditioner)),
        problem, f, *control.settings(), counter_ref, *cycle)
    linear_part, error = homogeneous(problem), _Relative(problem)
    riesz = _Riesz(problem, riesz_rtol)

    def evaluate(which: InverseProblem, point: np.ndarray, key) -> tuple[float, np.ndarray]:
        value, grad = jax.block_until_ready(gradient(which, point, *key, counter_ref, *cycle))
        return float(value), np.asarray(grad)

    history, run_time, cg, solver_key = History(), 0.0, None, None
    for step in range(1, iterations + 1):
        start = time.perf_counter()
        key = control.settings()
        if key != solver_key:  # a new inner solver: restart from the true gradient
            loss, g = evaluate(problem, f, key)
            cg = _CGState.start(-g, -riesz(g), loss, cg)
            solver_key = key
        _, q = evaluate(linear_part, cg.p, key)
        loss_before = cg.loss
        moved, f = cg.step(f, q, riesz(q))
        if moved is None:  # H p is not positive along p: the truncation is too coarse to go on
            break
        cg = moved
        run_time += time.perf_counter() - start
        record = StepRecord(
            step=step, iterations=key[0], adjoint_iterations=key[1], rtol=key[2],
            refinements=int(control.refinements), primal_iterations=counter.primal,
            adjoint_iterations_total=counter.adjoint, validation_iterations=0,
            evaluations=counter.primal_solves, time=run_time, compile_time=compile_time,
            loss=loss_before, misfit=math.nan, parameter_error=error(f), state_error=math.nan)
        history = history.append(record)
        if callback is not None and callback(record, f):
            break
        if cg.residual_norm <= rtol * cg.initial_norm:
            break
        start = time.perf_counter()
        control = refinement.update(control, cg.residual_norm)
        run_time += time.perf_counter() - start
    return ReducedCG(f, history, riesz.iterations,
                     math.nan if cg is None else cg.residual_norm,
                     math.nan if cg is None else cg.initial_norm)


class _CGState(NamedTuple):
    """The outer CG's vectors divided by ``scale``, a power of two (exact): ``r.z`` and
    ``p.q`` of data of 1e-163 underflowed to 0 (the run stopped at ``f = 0`` as if ``H`` were
    not positive) and of 1e163 overflowed. ``H`` and ``M^{-1}`` are linear, so ``H p`` of the
    scaled ``p`` is scaled alike; the step length is scale-free."""

    r: np.ndarray        # -grad J / scale (recursive)
    z: np.ndarray        # M^{-1} r
    p: np.ndarray        # search direction / scale
    rz: float            # r.z of the scaled vectors
    loss: float          # J at the current iterate
    initial_norm: float  # sqrt(r_0.z_0) of the first start
    scale: float

    @property
    def residual_norm(self) -> float:
        """``sqrt(r.z) = ||grad J||_{M^{-1}}``."""
        return self.scale * math.sqrt(max(self.rz, 0.0))

    @classmethod
    def start(cls, r: np.ndarray, z: np.ndarray, loss: float, previous) -> _CGState:
        scale = power_of_two_scale(r)
        r, z = r / scale, z / scale
        rz = dot(r, z)
        initial = scale * math.sqrt(max(rz, 0.0)) if previous is None \
            else previous.initial_norm
        return cls(r, z, z.copy(), rz, loss, initial, scale)

    def step(self, f: np.ndarray, q: np.ndarray, riesz_q: np.ndarray):
        """``f + a p`` and the next state, or ``(None, f)`` if ``p.q <= 0``; ``q = H p`` of
        the stored (scaled) ``p``.

        ``J(f + a p) = J(f) - a r.p + a^2 p.q / 2`` tracks the objective; ``z = M^{-1} r`` is
        updated with ``M^{-1} q`` (``M^{-1}`` is linear): one Riesz map per step.
        """
        pq = dot(self.p, q)
        if not pq > 0:
            return None, f
        a = self.rz / pq
        decrease = (a * dot(self.r, self.p) - 0.5 * a * a * pq) * self.scale
        loss = self.loss - decrease * self.scale
        r, z = self.r - a * q, self.z - a * riesz_q
        rz = dot(r, z)
        p = z + (rz / self.rz) * self.p
        return self._replace(r=r, z=z, p=p, rz=rz, loss=loss), f + (a * self.scale) * self.p


def _check_options(refinement, iterations, rtol, riesz_rtol, preconditioner) -> None:
    if not isinstance(refinement, Refinement):
        raise SolverConfigError(f"refinement={refinement!r}: expected a controller from "
                                "prdp_fem.inverse.refinement (prdp(), fixed(K) or converged(rtol))")
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 0:
        raise SolverConfigError(f"iterations={iterations!r}: expected an integer >= 0")
    if not (0 <= rtol < 1 and 0 < riesz_rtol < 1):
        raise SolverConfigError(f"rtol={rtol!r}, riesz_rtol={riesz_rtol!r}: expected "
                                "0 <= rtol < 1 and 0 < riesz_rtol < 1")
    TruncatedCG(0, preconditioner)  # checks the preconditioner before compiling anything
