r"""Inverse problems through truncated solves, and the optimisation loop that refines them.

.. math::

    \min_z\; J(z) = \tfrac12 \|B u(z) - d\|_W^2 + \alpha R(\mathrm{field}(z)),
    \qquad A(\kappa) u = b(\kappa, f),

with ``(kappa, f)`` from :class:`~prdp_fem.fem.parameters.Parameterization` (a source or a
log-coefficient), ``u`` from truncated PCG (:mod:`prdp_fem.linalg.cg`), an
:class:`~prdp_fem.fem.Observation` and a :class:`~prdp_fem.fem.Regularizer`.

:func:`invert` runs any optax ``GradientTransformation`` (L-BFGS with its zoom line search by
default) while a refinement controller (:mod:`prdp_fem.inverse.refinement`) picks the CG iterations
of every
step, and records a :class:`~prdp_fem.inverse.history.History`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from functools import cached_property, lru_cache, partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh

from .._checks import finite_vector, host_values
from .._executables import SharedCompile, kept_programs
from .._transfer import as_jax
from ..errors import (
    CoefficientError,
    DataError,
    DiscretizationError,
    PrdpFemError,
    ShapeError,
    SolverConfigError,
)
from ..fem.discretization import Discretization
from ..fem.observations import Observation
from ..fem.parameters import Parameterization, parameter_basis, parameter_mass
from ..fem.reference import amg_solve
from ..fem.regularizers import Regularizer, regularizer
from ..fem.residuals import ResidualFactors, residual_factors
from ..fem.system import LinearSystem
from ..linalg.amg import RebuiltAMG
from ..linalg.cg import (
    ConvergedCG,
    IterationCounter,
    ReverseTally,
    Solution,
    TruncatedCG,
    zero_counts,
)
from ..linalg.operator import SparseMatrix, matvec
from ..optim.linesearch import Evaluation, has_search_state, lbfgs, with_warm_start_slot
from .history import History, StepRecord
from .refinement import Refinement, RefinementState, prdp, refuse_learning_rate_scaling
from .steps import (
    cycle_argument,
    device_settings,
    keeps_program,
    preconditioner_key,
    step_failed,
    step_scan_length,
    step_solver,
    uses_stored_value,
    value_grad_and_update,
    with_stale_value,
)

__all__ = [
    "InverseProblem",
    "Inversion",
    "InversionError",
    "Objective",
    "StepScalars",
    "Validation",
    "WarmStart",
    "default_optimizer",
    "initial_params",
    "inverse_problem",
    "invert",
    "make_step",
]


class InversionError(PrdpFemError):
    """An optimisation produced non-finite parameters (names the step and the solver)."""


class LossParts(NamedTuple):
    misfit: jax.Array
    regularization: jax.Array
    solution: Solution


@partial(jax.tree_util.register_dataclass,
         data_fields=["system", "observation", "regularizer", "alpha", "known", "truth",
                      "parameter_mass", "residual_factors"],
         meta_fields=["parameterization"])
@dataclasses.dataclass(frozen=True)
class InverseProblem:
    """Everything the objective needs, as a pytree (pass it to jitted code as an argument).

    ``known`` is the other coefficient: ``f`` (nodal in the solution space) when log-kappa is
    unknown. When the source is, ``kappa`` never changes, and :func:`inverse_problem` freezes
    the system at it (:meth:`~prdp_fem.fem.discretization.Discretization.system_at`): ``known``
    is then that system's one coefficient, the scale ``ones(1)`` (to differentiate in
    ``kappa``, or to change it, use ``dataclasses.replace(problem, system=disc.system,
    known=kappa)``). ``truth`` is the parameter *field* to measure errors against (``None``
    when unknown). ``alpha`` is a leaf: sweeping it does not recompile.
    ``residual_factors`` (:mod:`prdp_fem.fem.residuals`, from :meth:`with_residual`) let
    :meth:`residual` write ``J`` as a sum of squares for Gauss-Newton-type optimisers.
    """

    system: LinearSystem
    parameterization: Parameterization
    observation: Observation
    regularizer: Regularizer
    alpha: jax.Array
    known: jax.Array  # f, or a source inversion's system scale ones(1) (see above)
    truth: jax.Array | None
    parameter_mass: SparseMatrix
    residual_factors: ResidualFactors | None = None

    @property
    def n_parameters(self) -> int:
        return int(self.regularizer.reference.shape[0])

    def sharded(self, mesh: Mesh, *, parts: np.ndarray | None = None,
                axis: str | None = None) -> InverseProblem:
        """This problem with its state spread over the devices of ``mesh``
        (:meth:`~prdp_fem.fem.system.LinearSystem.sharded`): :func:`invert` then runs every
        solve sharded. Preconditioners: ``"jacobi"`` or ``"identity"``."""
        return dataclasses.replace(self, system=self.system.sharded(mesh, parts=parts,
                                                                    axis=axis))

    def with_alpha(self, alpha: float) -> InverseProblem:
        return dataclasses.replace(self, alpha=jnp.asarray(float(alpha)))

    def field(self, z: jax.Array) -> jax.Array:
        return self.parameterization.field(z)

    def state(self, z: jax.Array, solver, x0: jax.Array | None = None,
              counter: IterationCounter | None = None) -> Solution:
        """The (truncated) solve at ``z``; ``Solution.x`` on the free dofs."""
        kappa, f = self.parameterization.coefficients(z, self.known)
        return self.system.solve(kappa, f, solver, x0, counter=counter)

    def loss(self, z: jax.Array, solver, x0: jax.Array | None = None,
             counter: IterationCounter | None = None) -> tuple[jax.Array, LossParts]:
        """``J(z)`` and its parts (misfit, alpha R, the solve's diagnostics)."""
        sol = self.state(z, solver, x0, counter)
        misfit = self.observation.misfit(self.system.expand(sol.x))
        reg = self.alpha * self.regularizer(self.field(z))
        return misfit + reg, LossParts(misfit, reg, sol)

    def gauss_newton_operator(self, z: jax.Array, solver, x0: jax.Array | None = None,
                              counter: IterationCounter | None = None
                              ) -> Callable[[jax.Array], jax.Array]:
        r"""``v -> H_GN v``, the Gauss-Newton Hessian of ``J`` at ``z``, linearised once.

        .. math::

            H_{GN} v = J_r^\top W J_r v + \nabla^2 (\alpha R \circ \mathrm{field})(z)\, v,
            \qquad J_r = \frac{\partial\, B u(z)}{\partial z},

        the misfit's second-order (state curvature) term dropped, the regulariser's Hessian
        kept exactly (for smoothed TV: its exact Hessian, positive semi-definite as TV is
        convex). ``J_r v`` is a forward-mode tangent solve and ``J_r^T w`` its transpose, an
        adjoint solve (``K_adj`` iterations each with a truncated solver, see
        :mod:`prdp_fem.linalg.cg`); the state solve runs once, here. For a source (the state is
        affine in ``f``) with an L2/H1 regulariser ``H_GN`` is the exact Hessian.
        """
        def observed(params):
            sol = self.state(params, solver, x0, counter)
            return self.observation.operator(self.system.expand(sol.x))

        def regularization(params):
            return self.alpha * self.regularizer(self.field(params))

        _, forward = jax.linearize(observed, z)
        adjoint = jax.linear_transpose(forward, z)
        _, regularization_hessian = jax.linearize(jax.grad(regularization), z)

        def apply(v: jax.Array) -> jax.Array:
            (misfit_part,) = adjoint(self.observation.weight(forward(v)))
            return misfit_part + regularization_hessian(v)

        return apply

    def gauss_newton_product(self, z: jax.Array, v: jax.Array, solver,
                             x0: jax.Array | None = None,
                             counter: IterationCounter | None = None) -> jax.Array:
        """``H_GN(z) v`` (see :meth:`gauss_newton_operator`, which reuses the state solve)."""
        return self.gauss_newton_operator(z, solver, x0, counter)(v)

    def with_residual(self) -> InverseProblem:
        """The problem with the factors :meth:`residual` needs (built once, on the host)."""
        return dataclasses.replace(
            self, residual_factors=residual_factors(self.observation, self.regularizer))

    def misfit_residual(self, z: jax.Array, solver, x0: jax.Array | None = None,
                        counter: IterationCounter | None = None) -> jax.Array:
        """``L_W (B u(z) - d)``: half its squared norm is the misfit."""
        u = self.system.expand(self.state(z, solver, x0, counter).x)
        return matvec(self._factors().misfit, self.observation.residual(u))

    def regularization_residual(self, z: jax.Array) -> jax.Array:
        """``r_R(z)`` with ``1/2 ||r_R||^2 = alpha R`` (see :mod:`prdp_fem.fem.residuals`)."""
        reg, field = self.regularizer, self.field(z)
        factor = self._factors().regularization
        if factor is not None:  # L2, H1: linear in the field
            return jnp.sqrt(self.alpha) * matvec(factor, field - reg.reference)
        g = matvec(reg.matrix, field).reshape(-1, reg.dim)
        # (|g|^2 + eps^2)^(1/4) is smooth (eps > 0); sqrt(2 alpha w) is a constant factor,
        # so alpha = 0 or w = 0 give zero rows with finite derivatives
        return jnp.sqrt(2.0 * self.alpha * reg.weights) * \
            (jnp.sum(g * g, axis=1) + reg.epsilon ** 2) ** 0.25

    def residual(self, z: jax.Array, solver, x0: jax.Array | None = None,
                 counter: IterationCounter | None = None) -> jax.Array:
        """``r(z)`` with ``1/2 ||r||^2 = J(z)``: misfit rows, then regulariser rows."""
        return jnp.concatenate([self.misfit_residual(z, solver, x0, counter),
                                self.regularization_residual(z)])

    def _factors(self) -> ResidualFactors:
        if self.residual_factors is None:
            raise SolverConfigError(
                "InverseProblem.residual needs the factors of the misfit weight and the "
                "regulariser: build the problem with inverse_problem(..., residual=True) or "
                "call problem.with_residual() (outside jit)")
        return self.residual_factors

    def parameter_error(self, z: jax.Array) -> jax.Array:
        """Relative L2 error of ``field(z)`` against ``truth`` (NaN when no truth)."""
        if self.truth is None:
            return jnp.asarray(jnp.nan)
        e = self.field(z) - self.truth
        norm2 = jnp.vdot(self.truth, matvec(self.parameter_mass, self.truth))
        return jnp.sqrt(jnp.vdot(e, matvec(self.parameter_mass, e)) / norm2)


def inverse_problem(disc: Discretization, observation: Observation, *, unknown: str,
                    alpha: float, regularization: str | Regularizer = "h1",
                    known: np.ndarray | float | None = None, truth: np.ndarray | None = None,
                    bounds: tuple[float, float] | None = None,
                    coefficient_map: Callable | None = None,
                    residual: bool = False) -> InverseProblem:
    """Assemble an :class:`InverseProblem` on ``disc`` (checks sizes at the edge).

    ``unknown="source"``: ``f`` nodal in the solution space, ``known`` is ``kappa`` in the
    kappa space (default 1, the identity for a tensor ``kappa``); the problem's system is
    frozen at it, so no map ``kappa -> A`` is built (see :class:`InverseProblem`).
    ``unknown="log_kappa"``:
    ``m = log kappa`` in the kappa space, ``known`` is the nodal source ``f`` (default 0).
    ``unknown="density"``: a density ``rho`` in the kappa space, ``kappa`` from the SIMP law
    ``coefficient_map`` (default :func:`~prdp_fem.fem.parameters.simp`; ``bounds`` default
    ``(0, 1)``); ``unknown="coefficient"``: ``kappa = coefficient_map(field)``, any
    differentiable JAX function (see :class:`~prdp_fem.fem.parameters.Parameterization`).
    ``residual=True`` also factors the misfit weight and the regulariser, for
    :meth:`InverseProblem.residual` (needed by :func:`prdp_fem.optim.hig.hig`; a sparse factor of
    a mass-matrix weight costs about three times its memory, so it is off by default).

    Raises :class:`~prdp_fem.errors.CoefficientError` for a ``kappa`` (``known``) that is not
    finite and positive, or a NaN log-kappa ``truth``; :class:`~prdp_fem.errors.DataError` for a
    NaN/Inf source; :class:`~prdp_fem.errors.ShapeError` for arrays of the wrong length;
    :class:`~prdp_fem.errors.SolverConfigError` for bad ``unknown``, ``alpha`` or
    ``regularization``.
    """
    parameterization = Parameterization(unknown, bounds, coefficient_map)
    n_param = parameter_basis(disc, unknown).N
    if parameterization.is_coefficient and disc.kappa_kind != "scalar":
        raise DiscretizationError(
            f"unknown={unknown!r} on a discretisation with kappa_kind={disc.kappa_kind!r}: "
            "expected kappa_kind='scalar' (a mapped coefficient is one field)")
    try:
        valid_alpha = np.ndim(alpha) == 0 and bool(np.isfinite(alpha) and alpha >= 0)
    except (TypeError, ValueError):
        valid_alpha = False
    if not valid_alpha:
        raise SolverConfigError(f"alpha={alpha!r}: expected a finite number >= 0")
    if observation.operator.shape[1] != disc.n_dofs:
        raise ShapeError(f"observation: operator acts on {observation.operator.shape[1]} "
                         f"dofs, expected {disc.n_dofs} (built on another discretisation?)")
    if unknown == "source":
        if known is None:
            known = 1.0 if disc.kappa_kind == "scalar" else disc.interpolate_kappa(
                lambda x: np.eye(disc.mesh.dim()))
        # kappa never changes: the system frozen at it, whose one coefficient is a scale
        system = disc.system_at(known, "known (kappa of a source inversion)")
        known = np.ones(1)
    else:
        system = disc.system
        known = finite_vector(0.0 if known is None else known,
                              f"known (nodal source f of a {unknown} inversion)", disc.n_dofs)
    if truth is not None:
        truth = as_jax(finite_vector(
            truth, f"truth ({unknown} field)", n_param,
            error=CoefficientError if parameterization.is_coefficient else DataError))
    if isinstance(regularization, str):
        regularization = regularizer(disc, unknown, regularization)
    if not isinstance(regularization, Regularizer):
        raise SolverConfigError(f"regularization={regularization!r}: expected 'l2', 'h1', 'tv' "
                                "or a Regularizer")
    if regularization.reference.shape != (n_param,):
        raise ShapeError(f"regularization: built for {regularization.reference.shape[0]} "
                         f"parameters, expected {n_param}")
    problem = InverseProblem(system, parameterization, observation, regularization,
                             as_jax(float(alpha)), as_jax(known), truth,
                             SparseMatrix.from_scipy(parameter_mass(disc, unknown)))
    return problem.with_residual() if residual else problem


# --------------------------------------------------------------------------------------
# the optimisation loop
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Validation:
    """Monitor the misfit of a converged solve (``rtol``) every ``every`` steps.

    PRDP's preferred signal: unlike the training loss it does not move when K changes. Its
    solves count as run time and as ``validation_iterations``.
    """

    every: int = 1
    rtol: float = 1e-10

    def __post_init__(self):
        if not (isinstance(self.every, int) and self.every >= 1 and 0 < self.rtol < 1):
            raise SolverConfigError(f"{self!r}: expected every >= 1 and 0 < rtol < 1")


class WarmStart(NamedTuple):
    """Where an evaluation's solves start: the state solve from ``state``, the adjoint solve
    from ``adjoint`` (free dofs; zeros: a cold start).

    An optimiser moves the parameters a little per step, so the previous evaluation's
    solutions are close to the next one's: a truncated solve from them is more accurate than
    one from zero, and the truncation error left by earlier steps is not paid again. The
    adjoint starts warm only in implicit mode (:class:`~prdp_fem.linalg.TruncatedCG` with
    ``gradient="implicit"``, :class:`~prdp_fem.linalg.ConvergedCG`).
    """

    state: jax.Array
    adjoint: jax.Array

    @classmethod
    def cold(cls, n: int, dtype=jnp.float64) -> WarmStart:
        """Zeros of ``n`` free dofs: the first evaluation's start."""
        return cls(jnp.zeros(n, dtype), jnp.zeros(n, dtype))


class Inversion(NamedTuple):
    """What :func:`invert` returns."""

    params: jax.Array          # the optimisation vector z
    field: jax.Array           # the recovered field (source, log kappa, density, ...)
    refinement: RefinementState
    optimizer_state: Any
    history: History


@dataclasses.dataclass(frozen=True, eq=False)
class Objective:
    """``J`` with the solver of one step: the ``value_fn`` :func:`invert` hands to optax.

    Calling it gives ``J(params)``; :meth:`gauss_newton_operator` gives the Gauss-Newton
    Hessian there (:meth:`InverseProblem.gauss_newton_operator`), which
    :mod:`prdp_fem.optim.newton` looks for on ``value_fn``, and :meth:`residual_blocks` the residual
    that :func:`prdp_fem.optim.hig.hig` differentiates. An object rather than an extra update
    argument: optax's zoom line search passes every extra argument on to ``value_fn`` and
    refuses one it does not take.

    ``warm_start`` (a :class:`WarmStart`, or ``None`` for zero starts): the state solve of
    every evaluation starts from ``warm_start.state``, and :meth:`evaluate` 's adjoint solve
    from ``warm_start.adjoint``; :meth:`evaluate` returns both solutions as the next start.
    """

    problem: InverseProblem
    solver: Any
    counter: IterationCounter | None = None
    warm_start: WarmStart | None = None

    def __call__(self, params: jax.Array) -> jax.Array:
        return self.problem.loss(params, self.solver, self._state_start(),
                                 counter=self.counter)[0]

    def _state_start(self) -> jax.Array | None:
        return None if self.warm_start is None else self.warm_start.state

    @cached_property
    def value_and_grad(self) -> Callable[[jax.Array], tuple[jax.Array, jax.Array]]:
        """``jax.value_and_grad(self)`` as one nested program. A step evaluates it in up to
        three places (the stored value's check and the line search's two branches): traced
        once, they lower to calls of one function (a step's trace and lowering took
        0.33-0.40 s on ``plate_hole`` with three copies, 0.20-0.21 s with one)."""
        return jax.jit(jax.value_and_grad(self))

    @cached_property
    def evaluate(self) -> Callable[[jax.Array], Evaluation]:
        """``params -> Evaluation``: the value, the gradient and the iterations its solves
        ran (``[primal, adjoint, primal_solves, adjoint_solves]``) as ordinary outputs -- the
        gradient with respect to a :class:`~prdp_fem.linalg.ReverseTally`'s seed, no host
        call -- and, with a :attr:`warm_start`, the state and adjoint solutions as the next
        one (the adjoint's as the gradient with respect to the tally's ``adjoint_start``).
        Line searches and :func:`~prdp_fem.inverse.steps.value_grad_and_update` evaluate
        through it, so that a step whose every evaluation is one of these holds no host
        callback: JAX then dispatches it on its fast path, and its persistent cache can keep
        it."""
        warm = self.warm_start

        def J(params, seed, adjoint_start):
            loss, parts = self.problem.loss(params, self.solver, self._state_start(),
                                            counter=ReverseTally(seed, adjoint_start))
            return loss, parts.solution.x

        value_and_grads = jax.value_and_grad(J, argnums=(0, 1) if warm is None else (0, 1, 2),
                                             has_aux=True)

        def evaluate(params):
            (value, state), grads = value_and_grads(params, zero_counts(),
                                                    None if warm is None else warm.adjoint)
            following = None if warm is None else \
                WarmStart(jax.lax.stop_gradient(state), grads[2])
            return Evaluation(value, grads[0], grads[1], following)

        return jax.jit(evaluate)

    def gauss_newton_operator(self, params: jax.Array) -> Callable[[jax.Array], jax.Array]:
        return self.problem.gauss_newton_operator(params, self.solver, counter=self.counter)

    def residual_blocks(self) -> tuple[Callable[[jax.Array], jax.Array], ...]:
        """``(r_misfit, r_R)``: the blocks of :meth:`InverseProblem.residual` at this solver.

        :func:`prdp_fem.optim.hig.hig` differentiates them apart, so that the regulariser's block
        costs no solves.
        """
        return (partial(self.problem.misfit_residual, solver=self.solver, counter=self.counter),
                self.problem.regularization_residual)


def make_step(optimizer, gradient, tolerance_mode, preconditioner):
    """One optimiser step of :func:`invert` (and, vmapped, of
    :func:`~prdp_fem.inverse.batch.invert_batch`); the counter and (K, K_adj, rtol) are
    arguments, so that runs differing only in them run one compiled program (per scan length
    in unrolled mode).

    ``preconditioner`` is closed over, except :class:`~prdp_fem.linalg.AMGCycle` (pass the class):
    the cycle is then the step's last argument (see :func:`preconditioner_key`)."""

    def step(problem, counter, z, opt_state, warm_start, scan_length, K, K_adj, rtol,
             cycle=None):
        solver = step_solver(gradient, tolerance_mode, K, K_adj, rtol,
                         preconditioner if cycle is None else cycle, scan_length)

        value_fn = Objective(problem, solver, counter, warm_start)

        value, grad, updates, opt_state, counts, following = value_grad_and_update(
            optimizer, opt_state, z, value_fn)
        z_next = optax.apply_updates(z, updates)
        misfit = value - problem.alpha * problem.regularizer(problem.field(z))
        return z_next, opt_state, following, StepScalars(
            value, misfit, problem.parameter_error(z_next), optax.tree.norm(grad),
            step_failed(opt_state), jnp.all(jnp.isfinite(z_next)), *counts).packed()

    return step


class StepScalars(NamedTuple):
    """What the loop reads of a step, one float64 vector on the way out (:meth:`packed`):
    read one by one, the seven results cost about 50 us of a 0.4 ms ``plate_hole`` step
    (a wait per output leaf and a transfer per scalar)."""

    value: float
    misfit: float
    parameter_error: float
    grad_norm: float
    failed: float       # 1.0: the optimiser reports the step as failed
    finite_params: float  # 1.0: every new parameter is finite
    # the iterations of the evaluations that returned them (Objective.evaluate);
    # the rest (an optimiser's own products and searches) are in the host counter
    primal: float
    adjoint: float
    primal_solves: float
    adjoint_solves: float

    def packed(self) -> jax.Array:
        return jnp.stack([jnp.asarray(v, jnp.float64) for v in self])

    @classmethod
    def read(cls, packed: jax.Array) -> StepScalars:
        """The host values (waits for the step: the vector is among its outputs)."""
        return cls(*np.asarray(packed).tolist())


class _ReturnedCounts(NamedTuple):
    """The iterations the steps returned as outputs, summed over the run (host integers)."""

    primal: int = 0
    adjoint: int = 0
    primal_solves: int = 0

    def add(self, step: StepScalars) -> _ReturnedCounts:
        return _ReturnedCounts(self.primal + round(step.primal),
                               self.adjoint + round(step.adjoint),
                               self.primal_solves + round(step.primal_solves))


@lru_cache(maxsize=1)
def default_optimizer() -> optax.GradientTransformationExtraArgs:
    """:func:`~prdp_fem.optim.linesearch.lbfgs`, one object for every call that passes none (pure
    and immutable, as optax's transformations are): such runs share their compiled step."""
    return lbfgs()


def _new_step_program(optimizer, gradient, tolerance_mode, preconditioner) -> SharedCompile:
    optimizer = optax.with_extra_args_support(optimizer)  # keyed by the object as given
    return SharedCompile(make_step(optimizer, gradient, tolerance_mode, preconditioner),
                         static_argnum=5)


#: The compiled step per settings (the optimizer object as given, gradient, tolerance mode,
#: preconditioner name), kept for the process: inversions with equal settings -- the same
#: optimizer object, a study's runs, an alpha sweep's -- trace and lower their step once
#: (see :func:`~prdp_fem._executables.kept_programs`).
_step_program = kept_programs(_new_step_program)


def _make_validation(rtol, preconditioner):
    def misfit(problem, counter, z, cycle=None):
        solver = ConvergedCG(rtol=rtol, preconditioner=preconditioner if cycle is None else cycle)
        return problem.loss(z, solver, counter=counter)[1].misfit
    return SharedCompile(misfit)


#: The validation program per (rtol, preconditioner key), kept as the step is.
_validation_program = kept_programs(_make_validation)


def invert(problem: InverseProblem, *, optimizer: optax.GradientTransformation | None = None,
           refinement: Refinement | None = None, gradient: str = "implicit", steps: int = 100,
           init: np.ndarray | None = None, preconditioner: Any = "jacobi",
           monitor: str | Validation | None = None, reference_every: int = 0,
           callback: Callable[[StepRecord, jax.Array], bool | None] | None = None,
           warm_start: bool = False, warm_start_every: int = 1) -> Inversion:
    """Minimise ``J`` for ``steps`` optimiser steps while ``refinement`` picks the CG work.

    Parameters
    ----------
    optimizer
        Any optax ``GradientTransformation``; default :func:`prdp_fem.optim.linesearch.lbfgs`
        (optax's L-BFGS and zoom line search; the search gives up as soon as the values rise
        where a truncated gradient says they fall).
        Its update gets the extra arguments ``value``, ``grad`` and ``value_fn``, an
        :class:`Objective` (``J`` at the step's solver) whose ``gauss_newton_operator`` is
        what :func:`prdp_fem.optim.newton.gauss_newton` multiplies with.
    refinement
        A :mod:`prdp_fem.inverse.refinement` controller; default :func:`~prdp_fem.inverse.prdp`
        (reference
        defaults). Use :func:`~prdp_fem.inverse.refinement.converged` for the converged baseline and
        :func:`~prdp_fem.inverse.refinement.fixed` for a fixed ``K``.
    gradient
        ``"implicit"`` (truncated adjoint solve; ``K`` traced, one compile) or ``"unrolled"``
        (reverse mode through the ``K`` iterations; one compile per power of two that bounds
        ``K``: :func:`~prdp_fem.linalg.cg.unrolled_length`).
    init
        Initial *field* (source or log kappa); default zeros (kappa = 1).
    preconditioner
        The CG preconditioner: ``"jacobi"``, ``"identity"``, an object such as
        :func:`~prdp_fem.linalg.amg.amg_preconditioner`'s (fixed for the run), or a
        :class:`~prdp_fem.linalg.RebuiltAMG`, whose hierarchy is built at ``kappa(z_0)`` and built
        again at the current ``kappa`` when its policy says so (``StepRecord.rebuilds``).
    monitor
        What the controller watches: ``"loss"`` (the objective each step), ``"gradient"``
        (the norm of the computed gradient: no floor, unlike a misfit with noise or
        unreachable data, and it stalls exactly when truncated gradients stop the optimiser)
        or a :class:`Validation`. Default: what the controller asks for
        (``refinement.monitor``: ``"gradient"`` for
        :func:`~prdp_fem.inverse.refinement.adaptive_tolerance`), else ``"loss"``.
    reference_every
        Every that many steps record ``state_error`` against a pyamg solve (not timed).
    callback
        ``callback(record, params)`` after every step; returning ``True`` stops the run.
    warm_start
        Start every evaluation's state and adjoint solves from the previous evaluation's
        solutions (:class:`WarmStart`) instead of zero. A truncated solve then carries its
        accuracy from step to step: as the steps shrink, ``K`` iterations from a close guess
        approach the converged solve, and so the truncated gradient the exact one. A
        converged solve needs fewer iterations to its tolerance (relative to the right-hand
        side). Needs an optimiser that evaluates through the :class:`Objective` itself:
        :func:`prdp_fem.lbfgs` (its search keeps the last trial's solutions) or one with no
        stored value (a plain optax transformation, evaluated once per step); the adjoint
        starts warm in implicit mode only. With a truncated solver the objective changes
        with its start, so every step evaluates afresh at its point before its search (one
        evaluation more per step with :func:`prdp_fem.lbfgs`); with a converged one it does
        not, to its tolerance.
    warm_start_every
        With ``warm_start``: move the start to the latest solutions every that many steps
        (1: every step), and whenever the controller changes ``K``. In between, the steps'
        solves start from the same solutions, the objective stays one function, and no step
        evaluates afresh: fewer evaluations for a start a few steps old.

    Raises
    ------
    InversionError
        When a step produces non-finite parameters (with the step and the solver settings).
    """
    if gradient not in ("implicit", "unrolled"):
        raise SolverConfigError(f"gradient={gradient!r}: expected 'implicit' or 'unrolled'")
    if not (_is_count(steps) and steps >= 0):
        raise SolverConfigError(f"steps={steps!r}: expected an integer >= 0")
    if not (_is_count(reference_every) and reference_every >= 0):
        raise SolverConfigError(
            f"reference_every={reference_every!r}: expected an integer >= 0 (0: never)")
    if not (monitor is None or isinstance(monitor, Validation)
            or monitor in ("loss", "gradient")):
        raise SolverConfigError(
            f"monitor={monitor!r}: expected 'loss', 'gradient' or a Validation")
    if callback is not None and not callable(callback):
        raise SolverConfigError(f"callback={callback!r}: expected a callable or None")
    rebuilt = preconditioner if isinstance(preconditioner, RebuiltAMG) else None
    if rebuilt is None:
        TruncatedCG(0, preconditioner)  # checks it now, not inside the first step
    refinement = prdp() if refinement is None else refinement
    if not isinstance(refinement, Refinement):
        raise SolverConfigError(f"refinement={refinement!r}: expected a controller from "
                                "prdp_fem.inverse.refinement (prdp(), fixed(K) or converged(rtol))")
    monitor = _monitor_for(refinement, monitor)
    if refinement.tolerance_mode and gradient == "unrolled":
        raise SolverConfigError("a tolerance-mode controller needs gradient='implicit' (reverse "
                                "mode cannot run through a loop of unknown length)")
    given = default_optimizer() if optimizer is None else optimizer
    optimizer = optax.with_extra_args_support(given)  # a new wrapper for a plain transform

    if not isinstance(warm_start, bool):
        raise SolverConfigError(f"warm_start={warm_start!r}: expected True or False")
    if not (_is_count(warm_start_every) and warm_start_every >= 1):
        raise SolverConfigError(
            f"warm_start_every={warm_start_every!r}: expected an integer >= 1")
    z = _initial_params(problem, init)
    opt_state = optimizer.init(z)
    solves_from = None  # the next step's WarmStart, with warm_start
    if warm_start:
        solves_from = WarmStart.cold(problem.system.n_free)
        if has_search_state(opt_state):
            opt_state = with_warm_start_slot(opt_state, solves_from)
        elif uses_stored_value(opt_state):
            raise SolverConfigError(
                "warm_start=True with an optimiser whose own line search evaluates the "
                "objective (it does not hand the solutions back): use prdp_fem.lbfgs() or a "
                "transformation without a line search")
    control = refinement.init()  # host arrays: an update is NumPy work, no dispatch
    # the host counter hears the solves of evaluations that do not return their counts
    # (an optimiser's own products and searches, the validation); `returned` sums the rest
    counter, validation_counter = IterationCounter(), IterationCounter()
    returned = _ReturnedCounts()
    rebuild_state, setup_time = None, 0.0
    if rebuilt is not None:  # pyamg's setup is the method's cost: run time of the first step
        start = time.perf_counter()
        preconditioner = rebuilt.build(_operator(problem, z))
        setup_time = time.perf_counter() - start
        rebuild_state = None if rebuilt.policy is None else \
            rebuilt.policy.init(_coefficient(problem, z))
    if gradient == "unrolled":
        _check_unrolled_start(problem, z)
    step, validate = _programs(given, gradient, refinement.tolerance_mode, preconditioner,
                               monitor)
    compiled = _Compiled([step, validate])
    compiled_before_run = compiled.seconds()  # the step may be an earlier run's
    history, run_time, evaluations, failed_steps, rebuilds = History(), setup_time, 0, 0, 0
    failed_since_update = False  # a monitor read every few steps still hears of each failure
    rebuild_due = False  # decided after a step, done before the next (none after the last)
    settings = control.settings()
    arguments = device_settings(settings)
    for k in range(1, steps + 1):
        previous_K = settings
        start = time.perf_counter()
        if rebuild_due:  # pyamg's setup is the method's cost: run time
            preconditioner = rebuilt.build(_operator(problem, z))
            step, validate = _programs(given, gradient, refinement.tolerance_mode,
                                       preconditioner, monitor)
            compiled.use([step, validate])  # the same kept programs for an AMGCycle
            rebuilds, rebuild_due = rebuilds + 1, False
            # a truncated J depends on the preconditioner: the stored value belongs to
            # the old one (a converged J does not, beyond the tolerance)
            if uses_stored_value(opt_state) and not refinement.tolerance_mode:
                opt_state = with_stale_value(opt_state)
        compile_before = compiled.seconds()
        z_next, opt_state, following, packed = step(
            problem, counter, z, opt_state, solves_from,
            step_scan_length(gradient, settings[0]),
            *arguments, *cycle_argument(preconditioner))
        result = StepScalars.read(packed)
        returned = returned.add(result)
        monitored = result.grad_norm if monitor == "gradient" else result.value
        if validate is not None and k % monitor.every == 0:
            monitored = float(validate(problem, validation_counter, z_next,
                                       *cycle_argument(preconditioner)))
        failed = bool(result.failed)
        failed_since_update |= failed
        failed_steps += failed
        if validate is None or k % monitor.every == 0:
            control = refinement.update(control, monitored, failed_since_update)
            settings = control.settings()
            if settings != previous_K:
                arguments = device_settings(settings)
            failed_since_update = False
        if rebuild_state is not None:
            rebuild_due, rebuild_state = _rebuild_due(rebuilt, rebuild_state,
                                                      _coefficient(problem, z_next))
        compile_time = compiled.seconds()
        run_time += time.perf_counter() - start - (compile_time - compile_before)
        if not (math.isfinite(result.value) and math.isfinite(result.grad_norm)
                and result.finite_params):
            raise InversionError(
                f"step {k}: non-finite loss, gradient or parameters (loss {result.value!r}, "
                f"gradient norm {result.grad_norm!r}, "
                f"K={previous_K[0]}, K_adj={previous_K[1]}, rtol={previous_K[2]!r}); try a "
                "smaller step, more CG iterations or another gradient mode")
        z = z_next
        refined = settings != previous_K
        # a refinement refreshes the stored value anyway: the start moves with it
        moved = solves_from is not None and (k % warm_start_every == 0 or refined)
        if moved:
            solves_from = following
        # the stored value/gradient belong to the old solver, or (truncated) to the old
        # start: a search comparing them with trials from the new one compares two objectives
        # and stalls; a converged J does not move with its start, to its tolerance
        if (refined or (moved and not refinement.tolerance_mode)) and \
                uses_stored_value(opt_state):
            opt_state = with_stale_value(opt_state)
        evaluations = counter.primal_solves + returned.primal_solves
        state_error = _state_error(problem, z, gradient, refinement.tolerance_mode,
                                   *previous_K, preconditioner) \
            if reference_every and k % reference_every == 0 else math.nan
        record = StepRecord(
            step=k, iterations=previous_K[0], adjoint_iterations=previous_K[1],
            rtol=previous_K[2], refinements=int(control.refinements),
            primal_iterations=counter.primal + returned.primal,
            adjoint_iterations_total=counter.adjoint + returned.adjoint,
            validation_iterations=validation_counter.primal, evaluations=evaluations,
            time=run_time, compile_time=compile_time - compiled_before_run,
            loss=result.value, misfit=result.misfit, parameter_error=result.parameter_error,
            state_error=state_error, failed_steps=failed_steps, rebuilds=rebuilds)
        history = history.append(record)
        if callback is not None and callback(record, z):
            break
    return Inversion(z, problem.field(z), control, opt_state, history)


def _monitor_for(refinement: Refinement, monitor):
    """The run's monitor: the one given, the controller's, or ``"loss"``; a controller that
    must be fed one value refuses another."""
    refuse_learning_rate_scaling(refinement, "an inversion")
    wanted = getattr(refinement, "monitor", None)
    if wanted is None:
        return "loss" if monitor is None else monitor
    if wanted != "gradient":  # truncation_gap(): a training's validation rollouts feed it
        raise SolverConfigError(
            f"refinement: this controller is fed the {wanted!r} of a training's validation "
            "pass; an inversion cannot feed it (expected prdp(), fixed(K), converged(rtol) or "
            "adaptive_tolerance())")
    if monitor is not None and monitor != wanted:
        raise SolverConfigError(
            f"monitor={monitor!r}: this controller is fed the {wanted!r} norm of each step; "
            f"expected monitor={wanted!r} or none")
    return wanted


def _rebuild_due(rebuilt: RebuiltAMG, state, kappa: np.ndarray) -> tuple[bool, Any]:
    """Whether the policy asks for a new hierarchy at ``kappa``, and its next state."""
    rebuild, state = rebuilt.policy.update(state, kappa)
    return bool(rebuild), state


class _Compiled:
    """The programs a run calls, and the compile seconds of the ones it stopped calling (a
    preconditioner object closed over gets new programs at a rebuild)."""

    def __init__(self, programs: list):
        self._programs, self._retired = [p for p in programs if p is not None], 0.0

    def seconds(self) -> float:
        return self._retired + sum(p.seconds for p in self._programs)

    def use(self, programs: list) -> None:
        current = [p for p in programs if p is not None]
        for old in self._programs:
            if all(old is not p for p in current):
                self._retired += old.seconds
        self._programs = current


def _programs(optimizer, gradient, tolerance_mode, preconditioner, monitor):
    """The step program and the validation program (``None`` unless ``monitor`` is a
    :class:`Validation`) for ``preconditioner``."""
    key = preconditioner_key(preconditioner)
    step = _step_program(optimizer, gradient, tolerance_mode, key, keep=keeps_program(key))
    validate = None if isinstance(monitor, str) else \
        _validation_program(monitor.rtol, key, keep=keeps_program(key))
    return step, validate


def _coefficient(problem: InverseProblem, z: jax.Array) -> np.ndarray:
    """``kappa(z)`` on the host (a source inversion's frozen scale, which never moves): what
    a :class:`~prdp_fem.linalg.amg.RebuiltAMG` policy watches (its update is then NumPy work, no
    dispatch)."""
    return np.asarray(problem.parameterization.coefficients(z, problem.known)[0])


def _operator(problem: InverseProblem, z: jax.Array) -> SparseMatrix:
    return problem.system.operator(jnp.asarray(_coefficient(problem, z)))


def _check_unrolled_start(problem: InverseProblem, z: jax.Array) -> None:
    kappa, f = problem.parameterization.coefficients(z, problem.known)
    if not bool(jnp.any(problem.system.rhs(kappa, f) != 0)):
        raise SolverConfigError(
            "gradient='unrolled' at a zero right-hand side: the K-iteration map is not "
            "differentiable there (its gradient is zero and the optimiser would not move); "
            "start from a non-zero source (init=) or use gradient='implicit'")


def initial_params(problem: InverseProblem, init: np.ndarray | None = None) -> jax.Array:
    """The optimisation vector :func:`invert` starts from for ``init`` (an initial field or
    ``None``), checked as ``invert`` checks it."""
    return _initial_params(problem, init)


def _initial_params(problem: InverseProblem, init) -> jax.Array:
    n = problem.n_parameters
    if init is None:
        field = np.zeros(n)
        if problem.parameterization.bounds is not None:
            field = np.full(n, 0.5 * sum(problem.parameterization.bounds))
    else:
        unknown = problem.parameterization.unknown
        name = f"init (initial {unknown} field)"
        field = finite_vector(host_values(init, name), name, n)
        bounds = problem.parameterization.bounds
        if bounds is not None:
            outside = (field < bounds[0]) | (field > bounds[1])
            if outside.any():
                i = int(np.flatnonzero(outside)[0])
                raise DataError(
                    f"init (initial {unknown} field): {int(outside.sum())} value(s) outside "
                    f"bounds={bounds} (first: index {i}, value {field[i]}); expected values "
                    "within the bounds")
    return problem.parameterization.from_field(field)


def _is_count(value) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def _state_error(problem, z, gradient, tolerance_mode, K, K_adj, rtol, preconditioner) -> float:
    """Relative nodal l2 error of the step's truncated state against a pyamg solve."""
    solver = step_solver(gradient, tolerance_mode, int(K), int(K_adj), float(rtol), preconditioner)
    u = np.asarray(problem.state(z, solver).x)
    kappa, f = problem.parameterization.coefficients(z, problem.known)
    A = problem.system.operator(kappa).to_scipy()
    reference = amg_solve(A, np.asarray(problem.system.rhs(kappa, f))).x
    return float(np.linalg.norm(u - reference) / max(np.linalg.norm(reference), 1e-300))
