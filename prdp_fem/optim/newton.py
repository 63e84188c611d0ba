r"""Newton-CG and Gauss-Newton as optax transformations (inexact Newton, Armijo backtracking).

One update at ``z`` with gradient ``g`` (the ``updates`` optax passes in) and objective ``J``
(``value_fn``):

.. math::

    H p = -g \;\text{ by PCG to }\; \|r_k\|_P \le \eta\, \|r_0\|_P, \qquad
    z_{+} = z + t\, p, \quad t = \beta^j \text{ the first with }
    J(z + t p) \le J(z) + c_1\, t\, g^\top p,

with ``||r||_P = sqrt(r.P r)`` for the preconditioner ``P`` (identity by default). The
Hessian ``H`` is

``hessian="exact"``
    the Hessian of ``J``: ``H v = d/de grad J(z + e v)``, forward mode over reverse mode
    (``jax.linearize(jax.grad(value_fn), z)``: the state and adjoint solves run once per update,
    then every product costs one tangent and one second-order adjoint solve; see
    :mod:`prdp_fem.linalg.cg` for how the implicit solves are differentiated in forward mode).
``hessian="gauss_newton"``
    ``H_GN v = J_r^T W J_r v + \nabla^2 (\alpha R \circ \mathrm{field})(z)\, v`` for the misfit
    ``1/2 ||r(z)||_W^2`` with ``r(z) = B u(z) - d``: the second derivative of the state map is
    dropped, the regulariser's Hessian is kept exactly. The operator
    (``params -> (v -> H_GN v)``) is ``value_fn.gauss_newton_operator``:
    :func:`prdp_fem.inverse.invert` passes an :class:`~prdp_fem.inverse.Objective`, whose
    method is :meth:`~prdp_fem.inverse.driver.InverseProblem.gauss_newton_operator`; other drivers
    may pass the extra argument ``gauss_newton_fn`` instead. ``H_GN`` is positive
    semi-definite whenever ``alpha R o field`` is convex: L2 and H1 (quadratic), and smoothed TV
    ``int sqrt(|grad m|^2 + eps^2)`` (convex, not quadratic: Gauss-Newton keeps its exact
    Hessian, not a lagged-diffusivity approximation) with an unbounded parameterisation. With
    ``bounds`` the sigmoid makes ``R o field`` non-convex and the negative-curvature exit below
    may trigger.

Inner CG (Steihaug's truncation without a trust region): stops at the forcing tolerance
``eta``, after ``max_cg`` Hessian products, or at the first direction ``d`` with
``d.Hd <= 0`` (or a non-finite product); the iterate before it is kept, and if that is the
very first direction the step is the preconditioned steepest descent ``p = -P g``. Every
iterate is a descent direction (``g.p < 0``), so the line search is well posed.

Forcing terms ``eta`` (``forcing=``):

``"eisenstat_walker"`` (default)
    Eisenstat and Walker's choice 2, ``eta_k = gamma (||g_k|| / ||g_{k-1}||)^a`` with
    ``gamma = 0.9``, ``a = 2``, safeguarded by ``max(eta_k, gamma eta_{k-1}^a)`` when
    ``gamma eta_{k-1}^a > 0.1``, capped at ``forcing_max``; ``eta_0 = forcing_max``.
``"hippylib"``
    hIPPYlib's rule ``eta_k = min(forcing_max, sqrt(||g_k|| / ||g_0||))``.
a number in ``(0, 1)``
    A constant tolerance.

Norms of ``g`` are Euclidean (a ratio: the forcing terms do not depend on the norm's scale).
The update is skipped (zero, no products, no line search) once
``||g|| <= max(gtol, rtol ||g_0||)``; a driver sees that ``z`` stops moving. A non-finite
value or gradient gives NaN updates (never a silent zero step); a line search that finds no
sufficient decrease in ``max_backtracking`` halvings gives a zero update and sets
``line_search_failed``.

>>> import jax.numpy as jnp, optax
>>> J = lambda z: 0.5 * jnp.sum(jnp.array([1.0, 10.0]) * z ** 2) + jnp.sum(z)
>>> opt = newton_cg()
>>> z = jnp.zeros(2); state = opt.init(z)
>>> value, grad = J(z), jax.grad(J)(z)
>>> updates, state = opt.update(grad, state, z, value=value, grad=grad, value_fn=J)
>>> [round(float(v), 12) for v in optax.apply_updates(z, updates)], int(state.cg_iterations)
([-1.0, -0.1], 2)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optax.tree_utils as otu
import scipy.sparse as sp

from ..errors import SolverConfigError
from ..fem.regularizers import gradient_gram
from ..linalg.amg import amg_preconditioner
from ..linalg.operator import SparseMatrix, matvec

__all__ = ["FORCING_TERMS", "HESSIANS", "CycledPreconditioner", "NewtonCGState", "gauss_newton",
           "newton_cg", "regularization_preconditioner"]

HESSIANS = ("exact", "gauss_newton")
FORCING_TERMS = ("eisenstat_walker", "hippylib")

# Eisenstat-Walker choice 2 (SIAM J. Sci. Comput. 17, 1996): gamma in (0, 1], exponent in (1, 2]
_EW_GAMMA = 0.9
_EW_EXPONENT = 2.0
_EW_SAFEGUARD = 0.1  # above it, eta may not drop faster than gamma eta_prev^a (oversolving)


class NewtonCGState(NamedTuple):
    """State of :func:`newton_cg` (all arrays; the per-update fields describe the last update).

    Attributes
    ----------
    steps
        Newton updates computed (skipped, converged updates do not count).
    cg_iterations, total_cg_iterations
        Inner CG iterations (Hessian products) of the last update, and over all updates.
    line_search_evaluations, total_line_search_evaluations
        ``value_fn`` calls of the last line search, and over all updates.
    step_size
        The accepted ``t`` (0 when the line search failed or the update was skipped).
    forcing
        The inner tolerance ``eta`` of the last update.
    grad_norm, initial_grad_norm
        ``||g||`` at the last update and at the first (NaN before the first).
    negative_curvature, line_search_failed, converged
        Flags of the last update.
    preconditioner
        The inner CG's preconditioner (a pytree with ``__call__``; ``None``: identity). It
        lives in the state so that its arrays are arguments of the jitted step, not constants.
    """

    steps: jax.Array
    cg_iterations: jax.Array
    total_cg_iterations: jax.Array
    line_search_evaluations: jax.Array
    total_line_search_evaluations: jax.Array
    step_size: jax.Array
    forcing: jax.Array
    grad_norm: jax.Array
    initial_grad_norm: jax.Array
    negative_curvature: jax.Array
    line_search_failed: jax.Array
    converged: jax.Array
    preconditioner: Any


class _Options(NamedTuple):
    hessian: str
    max_cg: int
    forcing: str | float
    forcing_max: float
    c1: float
    shrink: float
    max_backtracking: int
    gtol: float
    rtol: float
    gauss_newton_steps: int


def newton_cg(*, hessian: str = "exact", max_cg: int = 100,
              forcing: str | float = "eisenstat_walker", forcing_max: float = 0.5,
              c1: float = 1e-4, shrink: float = 0.5, max_backtracking: int = 10,
              preconditioner: Any = None, gtol: float = 0.0,
              rtol: float = 0.0, gauss_newton_steps: int = 0
              ) -> optax.GradientTransformationExtraArgs:
    """Inexact Newton-CG with Armijo backtracking (see the module docstring for the maths).

    Parameters
    ----------
    hessian
        ``"exact"`` (forward-over-reverse Hessian products of ``value_fn``) or
        ``"gauss_newton"`` (products from the ``gauss_newton_fn`` extra argument).
    max_cg
        Inner CG iterations (Hessian products) per update, ``>= 1``.
    forcing, forcing_max
        The inner tolerance rule (``"eisenstat_walker"``, ``"hippylib"`` or a number in
        ``(0, 1)``) and its cap in ``(0, 1)``.
    c1, shrink, max_backtracking
        Armijo constant in ``(0, 1/2)``, backtracking factor in ``(0, 1)``, and the number of
        reductions after the unit step (``>= 0``).
    preconditioner
        ``None`` or a pytree of arrays with ``__call__(v) -> P v``, ``P`` symmetric positive
        definite (e.g. :func:`regularization_preconditioner`).
    gtol, rtol
        Skip the update once ``||g|| <= max(gtol, rtol ||g_0||)`` (both ``>= 0``; ``0``: never).
    gauss_newton_steps
        With ``hessian="exact"``: the first this many Newton updates use the Gauss-Newton
        Hessian (positive semi-definite far from the minimiser), the rest the exact one, as
        hIPPYlib's Newton-CG does (its default: 5). ``0``: exact throughout.

    Notes
    -----
    The update needs ``params``, ``value`` and ``value_fn`` as :func:`optax.lbfgs` does (the
    :func:`~prdp_fem.inverse.driver.invert` driver passes them).
    """
    options = _checked_options(hessian, max_cg, forcing, forcing_max, c1, shrink,
                               max_backtracking, gtol, rtol, gauss_newton_steps)
    _check_preconditioner(preconditioner)

    def init_fn(params) -> NewtonCGState:
        zero, false = jnp.zeros((), jnp.int32), jnp.asarray(False)
        return NewtonCGState(zero, zero, zero, zero, zero, jnp.zeros(()), jnp.zeros(()),
                             jnp.full((), jnp.nan), jnp.full((), jnp.nan), false, false, false,
                             preconditioner)

    def update_fn(updates, state: NewtonCGState, params=None, *, value=None, grad=None,
                  value_fn=None, **extra_args):
        del grad  # the gradient is ``updates`` (optax's convention)
        if params is None or value is None or value_fn is None:
            raise SolverConfigError(
                "newton_cg: update() needs params, value= and value_fn= (as optax.lbfgs "
                "does); prdp_fem.invert passes them")
        def hessian():  # linearised inside the Newton branch: a skipped update solves nothing
            exact = _hessian_operator(options.hessian, value_fn, params, extra_args)
            if not options.gauss_newton_steps:
                return exact
            gauss_newton = _hessian_operator("gauss_newton", value_fn, params, extra_args)
            early = state.steps < options.gauss_newton_steps
            return lambda v: jax.lax.cond(early, gauss_newton, exact, v)

        return _update(options, updates, state, params, jnp.asarray(value), value_fn, hessian)

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


def gauss_newton(**options) -> optax.GradientTransformationExtraArgs:
    """:func:`newton_cg` with ``hessian="gauss_newton"`` (same options)."""
    if "hessian" in options:
        raise SolverConfigError(f"gauss_newton(hessian={options['hessian']!r}): the Hessian "
                                "is the Gauss-Newton one; use newton_cg(hessian=...) to choose")
    return newton_cg(hessian="gauss_newton", **options)


# --------------------------------------------------------------------------------------
# options
# --------------------------------------------------------------------------------------


def _is_int(value) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return (isinstance(value, int | float | np.integer | np.floating)
            and not isinstance(value, bool) and math.isfinite(float(value)))


def _checked_options(hessian, max_cg, forcing, forcing_max, c1, shrink, max_backtracking,
                     gtol, rtol, gauss_newton_steps=0) -> _Options:
    if hessian not in HESSIANS:
        raise SolverConfigError(f"hessian={hessian!r}: expected one of {HESSIANS}")
    if not (_is_int(max_cg) and max_cg >= 1):
        raise SolverConfigError(f"max_cg={max_cg!r}: expected an integer >= 1")
    if isinstance(forcing, str):
        if forcing not in FORCING_TERMS:
            raise SolverConfigError(f"forcing={forcing!r}: expected one of {FORCING_TERMS} or "
                                    "a number in (0, 1)")
    elif not (_is_number(forcing) and 0 < forcing < 1):
        raise SolverConfigError(f"forcing={forcing!r}: expected one of {FORCING_TERMS} or a "
                                "number in (0, 1)")
    checks = (("forcing_max", forcing_max, 0, 1), ("c1", c1, 0, 0.5), ("shrink", shrink, 0, 1))
    for name, value, low, high in checks:
        if not (_is_number(value) and low < value < high):
            raise SolverConfigError(f"{name}={value!r}: expected a number in ({low}, {high})")
    if not (_is_int(max_backtracking) and max_backtracking >= 0):
        raise SolverConfigError(f"max_backtracking={max_backtracking!r}: expected an integer "
                                ">= 0")
    for name, value in (("gtol", gtol), ("rtol", rtol)):
        if not (_is_number(value) and value >= 0):
            raise SolverConfigError(f"{name}={value!r}: expected a finite number >= 0")
    if not (_is_int(gauss_newton_steps) and gauss_newton_steps >= 0):
        raise SolverConfigError(f"gauss_newton_steps={gauss_newton_steps!r}: expected an "
                                "integer >= 0")
    if gauss_newton_steps and hessian != "exact":
        raise SolverConfigError(f"gauss_newton_steps={gauss_newton_steps} with "
                                f"hessian={hessian!r}: expected hessian='exact' (the steps "
                                "after them use it)")
    return _Options(hessian, int(max_cg), forcing if isinstance(forcing, str) else float(forcing),
                    float(forcing_max), float(c1), float(shrink), int(max_backtracking),
                    float(gtol), float(rtol), int(gauss_newton_steps))


def _check_preconditioner(preconditioner) -> None:
    if preconditioner is None:
        return
    leaves = jax.tree_util.tree_leaves(preconditioner)
    if callable(preconditioner) and all(hasattr(leaf, "dtype") or isinstance(leaf, int | float)
                                        for leaf in leaves):
        return
    raise SolverConfigError(
        f"preconditioner={preconditioner!r}: expected None or a pytree of arrays with "
        "__call__ (e.g. regularization_preconditioner(problem) or "
        "prdp_fem.amg_preconditioner(matrix)); a plain function is not a pytree")


# --------------------------------------------------------------------------------------
# Hessian products
# --------------------------------------------------------------------------------------


def _hessian_operator(hessian: str, value_fn, params, extra_args) -> Callable:
    """``v -> H v`` at ``params``, linearised once (the products reuse the state solves)."""
    if hessian == "exact":
        return jax.linearize(jax.grad(value_fn), params)[1]
    gauss_newton_fn = extra_args.get("gauss_newton_fn",
                                     getattr(value_fn, "gauss_newton_operator", None))
    if gauss_newton_fn is None:
        raise SolverConfigError(
            "newton_cg(hessian='gauss_newton'): expected value_fn with a "
            "gauss_newton_operator method (prdp_fem.inverse.Objective, what invert passes) or "
            "the extra argument gauss_newton_fn (params -> (v -> H_GN v))")
    return gauss_newton_fn(params)


# --------------------------------------------------------------------------------------
# one update
# --------------------------------------------------------------------------------------


class _Step(NamedTuple):
    updates: Any
    cg_iterations: jax.Array
    evaluations: jax.Array
    step_size: jax.Array
    forcing: jax.Array
    negative_curvature: jax.Array
    failed: jax.Array


def _update(options: _Options, grad, state: NewtonCGState, params, value, value_fn,
            hessian: Callable[[], Callable]):
    grad_norm = otu.tree_norm(grad)
    first = state.steps == 0
    initial = jnp.where(jnp.isnan(state.initial_grad_norm), grad_norm, state.initial_grad_norm)
    converged = grad_norm <= jnp.maximum(options.gtol, options.rtol * initial)
    finite = jnp.isfinite(grad_norm) & jnp.isfinite(value)
    forcing = _forcing(options, grad_norm, initial, state, first)
    precondition = _preconditioner_map(state.preconditioner)

    def newton(_):
        p, iterations, negative = _inner_cg(hessian(), grad, precondition, forcing,
                                            options.max_cg)
        # CG iterates descend for a symmetric H; Hessian products through truncated solves
        # are not exactly symmetric, so check, and fall back to preconditioned steepest descent
        descent = otu.tree_vdot(grad, p) < 0
        p = _tree_where(descent, p, precondition(otu.tree_scale(-1.0, grad)))
        t, evaluations, accepted = _armijo(options, value_fn, params, value, grad, p)
        updates = otu.tree_scale(jnp.where(accepted, t, 0.0), p)
        return _Step(updates, iterations, evaluations, jnp.where(accepted, t, 0.0), forcing,
                     negative, ~accepted)

    def skip(_):
        zero = jnp.zeros((), jnp.int32)
        return _Step(otu.tree_zeros_like(grad), zero, zero, jnp.zeros(()), forcing,
                     jnp.asarray(False), jnp.asarray(False))

    step = jax.lax.cond(converged | ~finite, skip, newton, None)
    # a NaN/Inf value or gradient: NaN updates, so the driver sees it (never a silent zero step)
    updates = jax.tree_util.tree_map(lambda u: jnp.where(finite, u, jnp.nan), step.updates)
    moved = ~converged & finite
    new_state = NewtonCGState(
        steps=state.steps + moved.astype(jnp.int32),
        cg_iterations=step.cg_iterations,
        total_cg_iterations=state.total_cg_iterations + step.cg_iterations,
        line_search_evaluations=step.evaluations,
        total_line_search_evaluations=state.total_line_search_evaluations + step.evaluations,
        step_size=step.step_size,
        forcing=jnp.where(moved, step.forcing, state.forcing),
        grad_norm=grad_norm,
        initial_grad_norm=initial,
        negative_curvature=step.negative_curvature,
        line_search_failed=step.failed,
        converged=converged & finite,
        preconditioner=state.preconditioner)
    return updates, new_state


def _forcing(options: _Options, grad_norm, initial, state: NewtonCGState, first) -> jax.Array:
    """The inner tolerance ``eta`` (see the module docstring), in ``(0, forcing_max]``."""
    cap = options.forcing_max
    if not isinstance(options.forcing, str):
        return jnp.asarray(options.forcing)
    if options.forcing == "hippylib":
        ratio = grad_norm / jnp.where(initial > 0, initial, 1.0)
        return jnp.minimum(cap, jnp.sqrt(jnp.maximum(ratio, 0.0)))
    previous = jnp.where(state.grad_norm > 0, state.grad_norm, 1.0)
    eta = _EW_GAMMA * (grad_norm / previous) ** _EW_EXPONENT
    safeguard = _EW_GAMMA * state.forcing ** _EW_EXPONENT
    eta = jnp.where(safeguard > _EW_SAFEGUARD, jnp.maximum(eta, safeguard), eta)
    return jnp.where(first, cap, jnp.minimum(eta, cap))


def _preconditioner_map(preconditioner) -> Callable:
    if preconditioner is None:
        return lambda v: v
    return preconditioner


class _CG(NamedTuple):
    k: jax.Array
    p: Any  # the Newton step so far
    r: Any  # -g - H p
    z: Any  # P r
    d: Any  # search direction
    rz: jax.Array
    done: jax.Array
    negative: jax.Array


def _inner_cg(hvp, grad, precondition, eta, max_cg: int):
    """PCG on ``H p = -g`` from ``p = 0``: ``(p, Hessian products, negative curvature met)``.

    Stops when ``r.Pr <= eta^2 r0.Pr0``, after ``max_cg`` products, or at a direction with
    ``d.Hd <= 0`` or a non-finite product (the iterate before it is kept; at the first
    direction, ``p = d = -P g``).
    """
    r0 = otu.tree_scale(-1.0, grad)
    z0 = precondition(r0)
    rz0 = otu.tree_vdot(r0, z0)
    target = eta * eta * rz0

    def cond(s: _CG):
        return ~s.done & (s.k < max_cg)

    def body(s: _CG) -> _CG:
        q = hvp(s.d)
        curvature = otu.tree_vdot(s.d, q)
        positive = curvature > 0  # False for NaN: a non-finite product stops CG too
        alpha = s.rz / jnp.where(positive, curvature, 1.0)
        p = otu.tree_add_scale(s.p, alpha, s.d)
        r = otu.tree_add_scale(s.r, -alpha, q)
        z = precondition(r)
        rz = otu.tree_vdot(r, z)
        usable = positive & jnp.isfinite(rz)
        beta = rz / jnp.where(s.rz > 0, s.rz, 1.0)
        d = otu.tree_add_scale(z, beta, s.d)
        # negative curvature at the first direction: step along it (-P g), else keep p
        fallback = jax.tree_util.tree_map(
            lambda old, direction: jnp.where(s.k == 0, direction, old), s.p, s.d)
        pick = _tree_where(usable, p, fallback)
        new = _CG(s.k + 1, pick, _tree_where(usable, r, s.r), _tree_where(usable, z, s.z),
                  _tree_where(usable, d, s.d), jnp.where(usable, rz, s.rz),
                  ~usable | (rz <= target), s.negative | ~positive)
        return new

    start = _CG(jnp.zeros((), jnp.int32), otu.tree_zeros_like(grad), r0, z0, z0, rz0,
                ~(rz0 > target) | ~(rz0 > 0), jnp.asarray(False))
    final = jax.lax.while_loop(cond, body, start)
    return final.p, final.k, final.negative


def _tree_where(condition, a, b):
    return jax.tree_util.tree_map(lambda x, y: jnp.where(condition, x, y), a, b)


def _armijo(options: _Options, value_fn, params, value, grad, p):
    """Backtracking from ``t = 1``: ``(t, value_fn calls, accepted)``.

    ``J(z + t p) <= J(z) + c1 t g.p``; a NaN value counts as no decrease. At most
    ``1 + max_backtracking`` evaluations; ``p = 0`` (a zero gradient) is accepted unevaluated.
    """
    slope = otu.tree_vdot(grad, p)
    descent = slope < 0  # else (p = 0, or a non-finite p) there is nothing to search

    def cond(carry):
        _, evaluations, accepted = carry
        return ~accepted & descent & (evaluations <= options.max_backtracking)

    def body(carry):
        t, evaluations, _ = carry
        trial = value_fn(otu.tree_add_scale(params, t, p))
        accepted = trial <= value + options.c1 * t * slope
        return jnp.where(accepted, t, t * options.shrink), evaluations + 1, accepted

    t, evaluations, accepted = jax.lax.while_loop(
        cond, body, (jnp.ones(()), jnp.zeros((), jnp.int32), slope == 0))
    return t, evaluations, accepted


# --------------------------------------------------------------------------------------
# a preconditioner from the regulariser (hIPPYlib's R + gamma M)
# --------------------------------------------------------------------------------------


@partial(jax.tree_util.register_dataclass, data_fields=["matrix", "cycle"],
         meta_fields=["cycles"])
@dataclasses.dataclass(frozen=True)
class CycledPreconditioner:
    """``cycles`` V-cycles of ``cycle`` as a stationary iteration on ``matrix x = v`` from
    ``x = 0``: a symmetric positive definite map for a convergent symmetric cycle, closer to
    ``matrix^{-1}`` with every cycle (one cycle: the cycle itself)."""

    matrix: SparseMatrix
    cycle: Any
    cycles: int

    def __call__(self, v):
        x = self.cycle(v)
        for _ in range(self.cycles - 1):
            x = x + self.cycle(v - matvec(self.matrix, x))
        return x


def regularization_preconditioner(problem, cycles: int = 1, **amg_options):
    """``cycles`` AMG V-cycles of ``R'' + M`` in the parameter space: ``P ~ (R'' + M)^{-1}``.

    hIPPYlib preconditions its Newton-CG with the regularisation operator plus a mass shift,
    ``gamma (L + M)``, solved exactly; PCG does not see the factor ``gamma``. Here ``L = D^T
    diag(w) D`` is the H1-seminorm Gram matrix of the problem's regulariser (H1, and the
    smoothed TV's quadratic surrogate), ``M`` the parameter mass matrix (which is ``R''`` for
    L2). One V-cycle is the cheapest; more cycles (a stationary iteration, see
    :class:`CycledPreconditioner`) approach the exact solve, and fewer inner CG iterations
    follow (hIPPYlib's tutorial at 64 x 64: 45 with one cycle, 26 with an exact solve, as
    hIPPYlib's). Built on the host, once; the result is a pytree to pass as
    ``newton_cg(preconditioner=...)``. ``amg_options`` go to
    :func:`~prdp_fem.linalg.amg.amg_preconditioner`.
    """
    if isinstance(cycles, bool) or not isinstance(cycles, int) or cycles < 1:
        raise SolverConfigError(f"cycles={cycles!r}: expected an integer >= 1")
    mass = problem.parameter_mass.to_scipy()
    regularizer = problem.regularizer
    if regularizer.kind == "l2":
        matrix = mass
    else:
        matrix = gradient_gram(regularizer.matrix.to_scipy(), regularizer.weights,
                               regularizer.dim) + mass
    matrix = sp.csr_matrix(matrix)
    cycle = amg_preconditioner(matrix, **amg_options)
    if cycles == 1:
        return cycle
    return CycledPreconditioner(SparseMatrix.from_scipy(matrix), cycle, cycles)
