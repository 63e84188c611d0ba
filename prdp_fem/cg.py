"""Truncated and converged preconditioned conjugate gradients, differentiable two ways.

Solvers are frozen objects checked at construction (lineax style) and :func:`solve` returns the
solution *and* its diagnostics::

    sol = solve(A, b, TruncatedCG(iterations=25, gradient="implicit"))
    sol.x, sol.iterations, sol.residual_norm

PCG, ``K`` iterations from ``x0``::

    r = b - A x; z = M r; p = z; rz = r.z
    repeat K:  q = A p; alpha = rz / p.q; x += alpha p; r -= alpha q
               z = M r; rz' = r.z; p = z + (rz'/rz) p

CG runs on the correction ``d = (x - x0) / ||r0||`` (the same iterates, with O(1) inner
products whatever the size of ``b``). Every division is made safe *before* dividing: once
``r.z`` has fallen to ``eps^2 (r0.z0)`` (round-off for the working dtype) or ``p.q`` is not
positive, the step length and the direction update are exactly zero, so ``K`` far past
convergence, ``b = 0`` or an exact ``x0`` return the converged ``x`` with finite values *and*
finite gradients (a ``jnp.where`` on an unsafe quotient would still send NaN through reverse
mode). Diagnostics are never differentiated (``stop_gradient`` in both modes).

Gradient modes
--------------
``"unrolled"``
    Reverse (and forward) mode through the ``K`` iterations: the derivative of the truncated
    map itself, including the Jacobi preconditioner's dependence on the operator. ``K`` is
    static (one compile per distinct ``K``); ``checkpoint=True`` recomputes each iteration in the
    backward pass instead of storing its intermediates.
``"implicit"``
    ``jax.custom_vjp``: the backward pass solves ``A lambda = x_bar`` with ``adjoint_iterations``
    PCG iterations and returns ``b_bar = lambda``, ``values_bar[k] = -lambda[row_k] x[col_k]``
    (and zero for ``x0``: at convergence ``x`` does not depend on it). Exact at convergence, the
    PRDP approximation when truncated. ``K`` and ``K_adj`` are traced: changing them does not
    recompile, and iterations stop early once the residual reaches round-off.

Limits (by design): implicit mode is first-order reverse mode only (``jax.jvp`` raises; a
Hessian through it is not exact). In unrolled mode at ``b - A x0 = 0`` the K-iteration map is
not differentiable (it is positively homogeneous in the residual) and the gradient returned
there is zero: start a source inversion from a non-zero residual, or use implicit mode, whose
gradient at zero residual is the (truncated) adjoint solution as usual.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import io_callback

from .errors import SolverConfigError
from .operator import SparseMatrix, matvec
from .precond import PRECONDITIONERS, make_preconditioner

__all__ = ["ConvergedCG", "IterationCounter", "Solution", "TruncatedCG", "solve"]

GRADIENT_MODES = ("unrolled", "implicit")


class Solution(NamedTuple):
    """Result of :func:`solve`.

    Attributes
    ----------
    x
        The iterate after the solve.
    iterations
        Iterations that moved ``x`` (a frozen, converged iteration does not count).
    residual_norm
        ``||r||_2`` of the recursively updated residual at the end.
    initial_residual_norm
        ``||b - A x0||_2``.
    residual_history
        ``||r_k||_2`` for ``k = 0..K`` (unrolled mode); in implicit/converged mode a buffer of
        ``history_size + 1`` entries, padded with the final value.
    """

    x: jax.Array
    iterations: jax.Array
    residual_norm: jax.Array
    initial_residual_norm: jax.Array
    residual_history: jax.Array


class IterationCounter:
    """Host-side tally of the CG iterations that actually ran, primal and adjoint.

    Pass one to :func:`solve` (``counter=``): every forward solve adds its iterations to
    ``primal`` and every backward (adjoint) solve -- the truncated adjoint PCG in implicit mode,
    the reversed scan in unrolled mode -- adds its own to ``adjoint``, through
    ``jax.experimental.io_callback``, so the tally is exact even inside jitted line searches that
    evaluate the objective an unknown number of times. One counter belongs to one run (it is
    hashed by identity and is part of the compiled function); read it after the results are
    ready (``jax.block_until_ready``). Not for use under ``vmap``.
    """

    def __init__(self):
        self.primal = 0
        self.adjoint = 0
        self.primal_solves = 0
        self.adjoint_solves = 0

    def _add_primal(self, iterations) -> None:
        self.primal += int(iterations)
        self.primal_solves += 1

    def _add_adjoint(self, iterations) -> None:
        self.adjoint += int(iterations)
        self.adjoint_solves += 1

    def snapshot(self) -> tuple[int, int]:
        """``(primal, adjoint)`` iterations so far."""
        return self.primal, self.adjoint


def _tap(counter: IterationCounter | None, kind: str, iterations: jax.Array) -> None:
    if counter is not None:
        target = counter._add_primal if kind == "primal" else counter._add_adjoint
        io_callback(target, None, iterations, ordered=False)


def _check_count(value: Any, name: str, allow_none: bool = False) -> None:
    if value is None and allow_none:
        return
    if isinstance(value, jax.core.Tracer):
        return  # traced: a negative count runs zero iterations (the loop test is k < K)
    if (isinstance(value, bool) or np.ndim(value) != 0
            or not np.issubdtype(np.asarray(value).dtype, np.integer) or int(value) < 0):
        raise SolverConfigError(f"{name}={value!r}: expected an integer >= 0")


def _check_preconditioner(spec: Any) -> None:
    if isinstance(spec, str) and spec in PRECONDITIONERS:
        return
    if callable(spec) and not isinstance(spec, str) and all(
            hasattr(leaf, "dtype") or isinstance(leaf, int | float)
            for leaf in jax.tree_util.tree_leaves(spec)):
        return
    raise SolverConfigError(
        f"preconditioner={spec!r}: expected one of {PRECONDITIONERS} or a callable pytree of "
        "arrays (e.g. a registered dataclass with __call__; a plain function is not a pytree)")


@dataclasses.dataclass(frozen=True)
class TruncatedCG:
    """Exactly ``iterations`` PCG iterations (fewer only once converged to round-off).

    Parameters
    ----------
    iterations
        ``K >= 0``; ``K = 0`` returns ``x0``. Static in unrolled mode; may be a traced integer
        in implicit mode (pass it to :func:`solve` through a jitted function's arguments).
    preconditioner
        ``"jacobi"`` (default), ``"identity"`` or a preconditioner pytree.
    gradient
        ``"unrolled"`` or ``"implicit"`` (see module docstring).
    adjoint_iterations
        ``K_adj`` for the implicit backward solve; ``None`` means ``K_adj = K``.
    checkpoint
        Unrolled mode: recompute iterations in the backward pass (memory ~ O(1) per step).
    history_size
        Implicit mode: length of the residual-history buffer minus one.
    """

    iterations: Any
    preconditioner: Any = "jacobi"
    gradient: str = "unrolled"
    adjoint_iterations: Any = None
    checkpoint: bool = False
    history_size: int = 0

    def __post_init__(self):
        if self.gradient not in GRADIENT_MODES:
            raise SolverConfigError(
                f"gradient={self.gradient!r}: expected one of {GRADIENT_MODES}")
        _check_preconditioner(self.preconditioner)
        if self.gradient == "unrolled":
            if isinstance(self.iterations, jax.core.Tracer):
                raise SolverConfigError(
                    "iterations is traced but gradient='unrolled' needs a static K (reverse "
                    "mode through a loop needs its length); use gradient='implicit' for a "
                    "traced K, or mark K static in jax.jit")
            _check_count(self.iterations, "iterations")
            object.__setattr__(self, "iterations", int(self.iterations))
        else:
            _check_count(self.iterations, "iterations")
        _check_count(self.adjoint_iterations, "adjoint_iterations", allow_none=True)
        _check_count(self.history_size, "history_size")
        object.__setattr__(self, "history_size", int(self.history_size))


@dataclasses.dataclass(frozen=True)
class ConvergedCG:
    """PCG until ``||r|| <= max(rtol ||b||, atol)`` or ``max_iterations``; implicit gradients.

    The adjoint solve uses the same tolerances. ``max_iterations=None`` means ``10 n``.
    ``rtol`` may be a traced scalar (a tolerance schedule inside a jitted step).
    """

    rtol: float = 1e-12
    atol: float = 0.0
    max_iterations: int | None = None
    preconditioner: Any = "jacobi"
    history_size: int = 0

    def __post_init__(self):
        if isinstance(self.rtol, jax.core.Tracer):
            pass  # checked where it was chosen (e.g. the refinement controller)
        elif not (np.isfinite(self.rtol) and self.rtol >= 0 and np.isfinite(self.atol)
                and self.atol >= 0) or (self.rtol == 0 and self.atol == 0):
            raise SolverConfigError(
                f"rtol={self.rtol!r}, atol={self.atol!r}: expected finite, non-negative "
                "tolerances, not both zero")
        _check_count(self.max_iterations, "max_iterations", allow_none=True)
        _check_count(self.history_size, "history_size")
        _check_preconditioner(self.preconditioner)
        object.__setattr__(self, "history_size", int(self.history_size))


def solve(matrix: SparseMatrix, b: jax.Array, solver: TruncatedCG | ConvergedCG,
          x0: jax.Array | None = None, *, counter: IterationCounter | None = None) -> Solution:
    """Solve ``A x = b`` (``A`` symmetric positive definite) with ``solver``.

    ``counter`` (an :class:`IterationCounter`) tallies the iterations run forward and backward.

    >>> import numpy as np, scipy.sparse as sp
    >>> from prdp_fem.operator import SparseMatrix
    >>> A = SparseMatrix.from_scipy(sp.diags([4.0, 2.0]) + sp.eye(2, k=1) + sp.eye(2, k=-1))
    >>> sol = solve(A, np.array([1.0, 2.0]), TruncatedCG(iterations=2))
    >>> np.allclose(A.todense() @ sol.x, [1.0, 2.0]), int(sol.iterations)
    (True, 2)
    """
    b = jnp.asarray(b, dtype=matrix.values.dtype)
    x0 = jnp.zeros_like(b) if x0 is None else jnp.asarray(x0, dtype=b.dtype)
    if b.shape != (matrix.shape[0],) or x0.shape != b.shape:
        raise SolverConfigError(
            f"b{tuple(b.shape)} / x0{tuple(x0.shape)}: expected vectors of length "
            f"{matrix.shape[0]} to match the operator")
    if isinstance(solver, TruncatedCG):
        if solver.gradient == "unrolled":
            precond = make_preconditioner(solver.preconditioner, matrix)
            sol = _unrolled(matrix, precond, b, x0, solver.iterations, solver.checkpoint)
            if counter is not None:
                sol = sol._replace(x=_adjoint_tap(sol.x, sol.iterations, counter))
        else:
            k_adj = solver.iterations if solver.adjoint_iterations is None \
                else solver.adjoint_iterations
            sol = _implicit_solve(matrix, b, x0, solver.iterations, k_adj,
                                  solver.preconditioner, 0.0, 0.0, solver.history_size, counter)
    elif isinstance(solver, ConvergedCG):
        max_iterations = 10 * matrix.shape[0] if solver.max_iterations is None \
            else solver.max_iterations
        sol = _implicit_solve(matrix, b, x0, max_iterations, max_iterations,
                              solver.preconditioner, solver.rtol, solver.atol,
                              solver.history_size, counter)
    else:
        raise SolverConfigError(f"solver={solver!r}: expected TruncatedCG or ConvergedCG")
    _tap(counter, "primal", sol.iterations)
    return sol




# --------------------------------------------------------------------------------------
# one PCG iteration, guarded
# --------------------------------------------------------------------------------------


class _CGState(NamedTuple):
    """PCG on the scaled correction: ``x = x0 + scale * d`` with ``A d = r0 / scale``."""

    d: jax.Array
    r: jax.Array
    p: jax.Array
    rz: jax.Array
    freeze_level: jax.Array  # eps^2 * r0.z0: below it r.z is round-off and CG stops moving


def _safe_ratio(num: jax.Array, den: jax.Array, ok: jax.Array) -> jax.Array:
    """``num / den`` where ``ok``, else exactly 0; the denominator is made safe first."""
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _init(matrix, precond, b, x0) -> tuple[_CGState, jax.Array, jax.Array]:
    """Initial state of CG on the correction, scaled to a unit residual.

    CG from ``x0`` equals CG from zero on ``A d = r0``; solving for ``d`` scaled by
    ``1/||r0||`` keeps every inner product O(1), so neither the values nor their derivatives
    (``d(a/b)/db = -a/b^2``) under- or overflow for tiny or huge right-hand sides.
    """
    r0 = b - matvec(matrix, x0)
    r0_norm = _norm(r0)
    scale = jnp.where(r0_norm > 0, r0_norm, 1.0)
    r = r0 / scale
    z = precond(r)
    rz = jnp.vdot(r, z)
    eps = jnp.finfo(r.dtype).eps
    return _CGState(jnp.zeros_like(r), r, z, rz, eps * eps * rz), r0_norm, scale


def _norm(v: jax.Array) -> jax.Array:
    # sqrt has an infinite derivative at 0: guard it so a zero residual keeps gradients finite
    sq = jnp.vdot(v, v)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def _active(state: _CGState) -> jax.Array:
    return state.rz > state.freeze_level


def _step(matrix, precond, state: _CGState) -> tuple[_CGState, jax.Array]:
    """One PCG iteration; returns the new state and whether it moved ``x``."""
    q = matvec(matrix, state.p)
    pq = jnp.vdot(state.p, q)
    moving = _active(state) & (pq > 0)
    alpha = _safe_ratio(state.rz, pq, moving)
    d = state.d + alpha * state.p
    r = state.r - alpha * q
    z = precond(r)
    rz_new = jnp.vdot(r, z)
    beta = _safe_ratio(rz_new, state.rz, moving)
    p = jnp.where(moving, z + beta * state.p, state.p)
    rz_new = jnp.where(moving, rz_new, state.rz)
    return _CGState(d, r, p, rz_new, state.freeze_level), moving


# --------------------------------------------------------------------------------------
# unrolled: a fixed-length scan, differentiated by JAX
# --------------------------------------------------------------------------------------


def _unrolled(matrix, precond, b, x0, iterations: int, checkpoint: bool) -> Solution:
    state, r0_norm, scale = _init(matrix, precond, b, x0)

    def body(carry, _):
        new, moving = _step(matrix, precond, carry)
        return new, (moving, _norm(new.r))

    if checkpoint:
        body = jax.checkpoint(body)
    state, (moved, norms) = jax.lax.scan(body, state, None, length=iterations)
    history = jax.lax.stop_gradient(scale * jnp.concatenate([jnp.ones(1, norms.dtype), norms]))
    return Solution(x0 + scale * state.d, jnp.sum(moved).astype(jnp.int32), history[-1],
                    jax.lax.stop_gradient(r0_norm), history)


@partial(jax.custom_vjp, nondiff_argnums=(2,))
def _adjoint_tap(x, iterations, counter):
    """Identity on ``x`` whose backward pass counts the reversed scan's iterations."""
    return x


def _adjoint_tap_fwd(x, iterations, counter):
    return x, iterations


def _adjoint_tap_bwd(counter, iterations, x_bar):
    _tap(counter, "adjoint", iterations)
    return x_bar, None


_adjoint_tap.defvjp(_adjoint_tap_fwd, _adjoint_tap_bwd)


# --------------------------------------------------------------------------------------
# implicit: while loop forward, truncated adjoint solve backward
# --------------------------------------------------------------------------------------


def _while_solve(matrix, precond, b, x0, max_iterations, tolerances, history_size: int):
    """PCG while ``k < max_iterations``, still moving and ``||r|| > max(rtol ||b||, atol)``."""
    state, r0_norm, scale = _init(matrix, precond, b, x0)
    target = jnp.maximum(tolerances[0] * _norm(b), tolerances[1]) / scale
    positions = jnp.arange(history_size + 1)

    def cond(carry):
        k, st, norm, _, moved = carry
        return (k < max_iterations) & moved & _active(st) & (norm > target)

    def body(carry):
        k, st, _, hist, _ = carry
        new, moving = _step(matrix, precond, st)
        norm = _norm(new.r)
        hist = jnp.where(positions > k, norm, hist)  # pads the tail with the latest value
        return k + moving.astype(k.dtype), new, norm, hist, moving

    unit = jnp.ones((), b.dtype) * (r0_norm > 0)
    init = (jnp.zeros((), jnp.int32), state, unit, jnp.full(history_size + 1, unit),
            jnp.asarray(True))
    k, state, norm, history, _ = jax.lax.while_loop(cond, body, init)
    return Solution(x0 + scale * state.d, k, scale * norm, r0_norm, scale * history)


def _implicit_solve(matrix, b, x0, iterations, adjoint_iterations, precond_spec, rtol, atol,
                    history_size, counter=None) -> Solution:
    precond = make_preconditioner(precond_spec, matrix)
    precond = jax.tree_util.tree_map(jax.lax.stop_gradient, precond)
    tolerances = jnp.asarray([rtol, atol], dtype=b.dtype)
    sol = _implicit_core(matrix.values, b, x0, jnp.asarray(iterations, jnp.int32),
                         jnp.asarray(adjoint_iterations, jnp.int32), matrix.rows, matrix.cols,
                         precond, tolerances, matrix.shape, history_size, counter)
    diagnostics = jax.lax.stop_gradient(sol[1:])  # as in unrolled mode: not differentiated
    return Solution(sol.x, *diagnostics)


@partial(jax.custom_vjp, nondiff_argnums=(9, 10, 11))
def _implicit_core(values, b, x0, iterations, adjoint_iterations, rows, cols, precond,
                   tolerances, shape, history_size, counter):
    matrix = SparseMatrix(rows, cols, values, shape)
    return _while_solve(matrix, precond, b, x0, iterations, tolerances, history_size)


def _implicit_fwd(values, b, x0, iterations, adjoint_iterations, rows, cols, precond,
                  tolerances, shape, history_size, counter):
    matrix = SparseMatrix(rows, cols, values, shape)
    sol = _while_solve(matrix, precond, b, x0, iterations, tolerances, history_size)
    return sol, (values, sol.x, adjoint_iterations, rows, cols, precond, tolerances)


def _implicit_bwd(shape, history_size, counter, residuals, cotangent: Solution):
    values, x, adjoint_iterations, rows, cols, precond, tolerances = residuals
    matrix = SparseMatrix(rows, cols, values, shape)
    # A is symmetric: the adjoint system is A lambda = x_bar, solved the same (truncated) way
    adjoint_solution = _while_solve(matrix, precond, cotangent.x, jnp.zeros_like(cotangent.x),
                                    adjoint_iterations, tolerances, 0)
    _tap(counter, "adjoint", adjoint_solution.iterations)
    adjoint = adjoint_solution.x
    values_bar = -adjoint[rows] * x[cols]
    zeros = partial(jax.tree_util.tree_map, jnp.zeros_like)
    return (values_bar, adjoint, jnp.zeros_like(x), None, None, None, None, zeros(precond),
            jnp.zeros_like(tolerances))


_implicit_core.defvjp(_implicit_fwd, _implicit_bwd)
