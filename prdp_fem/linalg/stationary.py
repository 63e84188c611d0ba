r"""Truncated stationary (damped) Jacobi sweeps, differentiable two ways.

The solver of the PRDP reference code's 1-D Poisson inverse problem, offered beside truncated
PCG (:class:`~prdp_fem.linalg.cg.TruncatedCG`) with the same interface: a frozen solver object
checked at construction, and :func:`prdp_fem.solve` (which dispatches here) returning the
solution, its diagnostics and a status::

    sol = solve(A, b, TruncatedJacobi(iterations=25))
    sol.x, sol.iterations, sol.residual_norm, sol.status

One sweep, from ``x0`` (zero by default), with ``D = diag(A)``:

.. math:: r_k = b - A x_k, \qquad x_{k+1} = x_k + \omega D^{-1} r_k

(``omega = 1``: plain Jacobi, ``x_{k+1} = D^{-1} (b - (A - D) x_k)``). ``K`` sweeps are a fixed
linear map of ``(b, x0)``,

.. math:: x_K = G^K x_0 + \sum_{j<K} G^j \omega D^{-1} b, \qquad G = I - \omega D^{-1} A,

which converges to ``A^{-1} b`` iff the spectral radius ``rho(G) < 1`` (for a symmetric ``A``
with a positive -- or negative -- diagonal: ``A`` (or ``-A``) positive definite and
``omega < 2 / lambda_max(D^{-1} A)``; the undamped sweep converges on the 1-D and 2-D
Laplacians, slowly: ``rho = cos(pi h)``).

Gradient modes
--------------
``"unrolled"``
    Reverse and forward mode through the ``K`` sweeps: the derivative of the ``K``-sweep map
    itself, in ``b``, ``x0`` and the operator's values (the diagonal ``D`` included). ``K`` is
    static, or traced below a static ``scan_length`` (the sweeps past ``K`` pass the state on).
``"implicit"``
    A ``jax.custom_jvp`` whose tangent is ``dx = A^{-1} (db - dA x)``, that system solved by
    ``adjoint_iterations`` Jacobi sweeps from zero through ``lax.custom_linear_solve``; reverse
    mode transposes it into the truncated adjoint solve ``A^T lambda = x_bar`` (``K_adj``
    sweeps on ``A^T``, from zero) with ``b_bar = lambda`` and
    ``values_bar[k] = -lambda[row_k] x[col_k]``; ``x0`` and ``omega`` get no derivative (the
    fixed point depends on neither). Exact at convergence, the PRDP approximation when
    truncated. For a symmetric ``A``, ``x0 = 0`` and ``K_adj = K``, the derivative in ``b`` is
    the unrolled one (the ``K``-sweep map of a symmetric ``A`` is symmetric): the reference's
    setting, where the two modes take the same steps to round-off. ``K`` and ``K_adj`` may be
    traced.

Status
------
``Solution.status`` (:class:`~prdp_fem.linalg.cg.Status`): ``SUCCESS``; ``BREAKDOWN`` (a zero or
non-finite diagonal entry: ``D^{-1}`` does not exist; ``x = x0``); ``NONFINITE`` (NaN/Inf in
the inputs or the result); ``DIVERGED`` (the ``D^{-1/2}``-weighted residual grew: ``rho(G) >= 1``,
e.g. a matrix far from diagonally dominant, or ``omega`` too large). A sweep runs only while
that residual is within ``1/sqrt(eps)`` of its start, so a divergent sweep stops there and
``x`` (the last iterate below) stays finite -- its gradients too. For a symmetric ``A`` with
``rho(G) < 1`` the weighted residual never grows, so ``DIVERGED`` is never a false alarm there;
a sweep with ``rho(G) = 1`` exactly, which stalls without growing, is not flagged (its
``residual_norm`` does not fall). Called eagerly, a ``BREAKDOWN``, ``DIVERGED`` or
``NONFINITE`` raises (:class:`~prdp_fem.errors.SolverBreakdownError`,
:class:`~prdp_fem.errors.DataError`); under ``jit``, check ``status``.

>>> import numpy as np, scipy.sparse as sp
>>> from prdp_fem import solve
>>> from prdp_fem.linalg.operator import SparseMatrix
>>> A = SparseMatrix.from_scipy(sp.diags([4.0, 4.0]) + sp.eye(2, k=1) + sp.eye(2, k=-1))
>>> sol = solve(A, np.array([3.0, 5.0]), TruncatedJacobi(iterations=60))
>>> np.round(np.asarray(sol.x), 12).tolist(), int(sol.iterations), Status(sol.status).name
([0.466666666667, 1.133333333333], 60, 'SUCCESS')
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import is_traced
from ..errors import DataError, ShapeError, SolverBreakdownError, SolverConfigError
from ._tally import IterationCounter, ReverseTally, counted_linear_solve, live_tangent, tap
from .cg import Solution, Status, adjoint_tap, check_finite_inputs, check_truncation
from .operator import SparseMatrix, diagonal, prepare, rmatvec

__all__ = ["TruncatedJacobi", "jacobi_solve"]


@dataclasses.dataclass(frozen=True)
class TruncatedJacobi:
    """Exactly ``iterations`` (damped) Jacobi sweeps ``x <- x + omega D^{-1} (b - A x)``.

    Parameters
    ----------
    iterations
        ``K >= 0``; ``K = 0`` returns ``x0``. Static in unrolled mode unless a ``scan_length``
        is given; may be traced in implicit mode.
    omega
        Damping, ``0 < omega < 2`` (``1``: the undamped sweep of the reference code); may be
        a traced scalar.
    gradient
        ``"unrolled"`` or ``"implicit"`` (see the module docstring).
    adjoint_iterations
        ``K_adj``, the sweeps of the implicit tangent and adjoint solves; ``None``: ``K``.
    history_size
        Implicit mode: length of the residual-history buffer minus one.
    scan_length
        Unrolled mode: a static scan of this many sweeps whose first ``iterations`` run and
        the rest pass the state on, so ``iterations`` may be traced (``K <= scan_length``).
    """

    iterations: Any
    omega: Any = 1.0
    gradient: str = "unrolled"
    adjoint_iterations: Any = None
    history_size: int = 0
    scan_length: int | None = None

    def __post_init__(self):
        check_truncation(self)  # gradient, scan_length and the counts, as TruncatedCG's
        if not isinstance(self.omega, jax.core.Tracer):
            if isinstance(self.omega, bool) or np.ndim(self.omega) != 0 or not (
                    np.issubdtype(np.asarray(self.omega).dtype, np.number)
                    and math.isfinite(float(self.omega)) and 0.0 < float(self.omega) < 2.0):
                raise SolverConfigError(
                    f"omega={self.omega!r}: expected a number with 0 < omega < 2 (outside, "
                    "the sweep diverges on every symmetric positive definite matrix)")
            object.__setattr__(self, "omega", float(self.omega))


def jacobi_solve(matrix: SparseMatrix, b: jax.Array, solver: TruncatedJacobi,
                 x0: jax.Array | None = None, *,
                 counter: IterationCounter | None = None) -> Solution:
    """``solver.iterations`` Jacobi sweeps on ``A x = b`` from ``x0`` (zero when ``None``).

    :func:`prdp_fem.solve` calls this for a :class:`TruncatedJacobi`. Eagerly it runs as one
    compiled program (``K`` in implicit mode or below a ``scan_length``, ``K_adj`` and
    ``omega`` are its arguments) and raises on a bad status; under ``jit`` it sets ``status``.
    """
    if not isinstance(solver, TruncatedJacobi):
        raise SolverConfigError(f"solver={solver!r}: expected TruncatedJacobi")
    b = jnp.asarray(b, dtype=matrix.values.dtype)
    x0 = None if x0 is None else jnp.asarray(x0, dtype=b.dtype)
    if matrix.shape[0] != matrix.shape[1] or b.shape != (matrix.shape[0],) or (
            x0 is not None and x0.shape != b.shape):
        raise ShapeError(
            f"matrix{tuple(matrix.shape)}, b{tuple(b.shape)}, x0"
            f"{tuple(b.shape if x0 is None else x0.shape)}: expected a square operator and "
            "vectors of its size")
    dynamic, static = _split(solver)
    if counter is not None or is_traced(matrix.values, b, x0, dynamic):
        return _solve_traced(matrix, b, x0, solver, counter)
    check_finite_inputs(matrix, b, x0)
    sol = _COMPILED(matrix, b, x0, dynamic, static)
    _raise_on_status(sol)
    return sol


def _split(solver: TruncatedJacobi) -> tuple[dict, tuple]:
    """The solver's numbers an eager compiled solve takes as arguments, and the rest (its key)."""
    fields = {f.name: getattr(solver, f.name) for f in dataclasses.fields(solver)}
    names = ["omega"]
    if solver.gradient == "implicit":
        if fields["adjoint_iterations"] is None:
            fields["adjoint_iterations"] = fields["iterations"]
        names += ["iterations", "adjoint_iterations"]
    else:
        fields["adjoint_iterations"] = None
        if solver.scan_length is not None:
            names.append("iterations")
    types = {"omega": np.float64, "iterations": np.int32, "adjoint_iterations": np.int32}
    dynamic = {name: fields.pop(name) for name in names}
    dynamic = {name: value if is_traced(value) else np.asarray(value, types[name])
               for name, value in dynamic.items()}
    return dynamic, tuple(fields.items())


def _compiled_solve(matrix, b, x0, dynamic, static) -> Solution:
    return _solve_traced(matrix, b, x0, TruncatedJacobi(**dict(static), **dynamic), None)


_COMPILED = jax.jit(_compiled_solve, static_argnames=("static",))


def _raise_on_status(sol: Solution) -> None:
    status = Status(int(sol.status))
    if status == Status.BREAKDOWN:
        raise SolverBreakdownError(
            "Jacobi: the operator has a zero or non-finite diagonal entry, so D^-1 does not "
            "exist; expected a non-zero diagonal (or use TruncatedCG)")
    if status == Status.DIVERGED:
        raise SolverBreakdownError(
            f"Jacobi diverged: ||b - A x|| went from {float(sol.initial_residual_norm):.3g} to "
            f"{float(sol.residual_norm):.3g} in {int(sol.iterations)} sweeps, "
            "so the sweep's spectral radius is >= 1; expected a (nearly) diagonally dominant "
            "or positive definite operator with a smaller omega, or TruncatedCG")
    if status == Status.NONFINITE:
        raise DataError(f"Jacobi: NaN/Inf after {int(sol.iterations)} sweeps from finite inputs "
                        "(overflow: rescale the problem); expected finite values")


# --------------------------------------------------------------------------------------
# the sweeps
# --------------------------------------------------------------------------------------


def _scalings(matrix: SparseMatrix, omega):
    """``(omega D^{-1}, D^{-1/2} (held), usable)``: zero where a diagonal entry is unusable."""
    d = diagonal(matrix)
    usable = jnp.isfinite(d) & (d != 0)
    safe = jnp.where(usable, d, 1.0)
    step = jnp.where(usable, omega / safe, 0.0)
    held = jax.lax.stop_gradient(safe)
    weight = jnp.where(usable, 1.0 / jnp.sqrt(jnp.abs(held)), 0.0)
    return step, weight, jax.lax.stop_gradient(jnp.all(usable))


def _weighted(weight, r):
    return jnp.linalg.norm(jax.lax.stop_gradient(weight * r))


# a sweep runs while the weighted residual is within this factor of its start
def _growth_cap(dtype) -> float:
    return 1.0 / math.sqrt(float(jnp.finfo(dtype).eps))


def _diverged(weight, norm0, norm, b, d_x):
    """The weighted residual ended above its start, beyond round-off of ``b`` and ``D x``."""
    eps = math.sqrt(float(jnp.finfo(b.dtype).eps))
    floor = eps * (_weighted(weight, b) + _weighted(weight, d_x))
    return (norm > (1.0 + eps) * norm0 + floor) | ~jnp.isfinite(norm)


def _sweeps(product, b, x0, step, weight, usable, iterations, length):
    """``length`` (static) scanned sweeps of which the first ``iterations`` run: unrolled mode.

    Returns ``x``, the sweeps that ran, the residual norms ``||r_k||`` (k = 0..length), the
    weighted residual norms at the start and the end.
    """
    x = jnp.zeros_like(b) if x0 is None else x0
    r = b if x0 is None else b - product(x)
    norm0 = _weighted(weight, r)
    limit = _growth_cap(b.dtype) * norm0

    def body(carry, k):
        x, r, moved = carry
        go = jax.lax.stop_gradient(usable & (k < iterations) & (_weighted(weight, r) <= limit))
        x = x + jnp.where(go, step * r, 0.0)
        r = b - product(x)
        return (x, r, moved + go.astype(jnp.int32)), jnp.linalg.norm(jax.lax.stop_gradient(r))

    start = jnp.linalg.norm(jax.lax.stop_gradient(r))
    (x, r, moved), norms = jax.lax.scan(body, (x, r, jnp.zeros((), jnp.int32)),
                                        jnp.arange(length))
    history = jnp.concatenate([start[None], norms])
    return x, r, moved, history, norm0, _weighted(weight, r)


def _while_sweeps(product, b, x0, step, weight, usable, iterations, history_size: int):
    """Sweeps in a while loop (``iterations`` may be traced): implicit mode and the adjoint."""
    x = jnp.zeros_like(b) if x0 is None else x0
    r = b if x0 is None else b - product(x)
    norm0 = _weighted(weight, r)
    limit = _growth_cap(b.dtype) * norm0
    positions = jnp.arange(history_size + 1)
    start = jnp.linalg.norm(r)

    def cond(carry):
        k, _, r, _ = carry
        return usable & (k < iterations) & (_weighted(weight, r) <= limit)

    def body(carry):
        k, x, r, history = carry
        x = x + step * r
        r = b - product(x)
        if history_size:
            history = jnp.where(positions > k, jnp.linalg.norm(r), history)
        return k + 1, x, r, history

    k, x, r, history = jax.lax.while_loop(
        cond, body, (jnp.zeros((), jnp.int32), x, r, jnp.full(history_size + 1, start)))
    return x, r, k, history, norm0, _weighted(weight, r)


def _status(sol_x, usable, diverged, inputs_finite):
    status = jnp.where(usable, jnp.where(diverged, Status.DIVERGED, Status.SUCCESS),
                       Status.BREAKDOWN)
    finite = jnp.all(jnp.isfinite(jax.lax.stop_gradient(sol_x))) & inputs_finite
    return jnp.where(finite, status, Status.NONFINITE).astype(jnp.int32)


def _solve_traced(matrix, b, x0, solver: TruncatedJacobi, counter) -> Solution:
    inputs = [matrix.values, b] + ([] if x0 is None else [x0])
    inputs_finite = jax.lax.stop_gradient(
        jnp.all(jnp.asarray([jnp.all(jnp.isfinite(a)) for a in inputs])))
    omega = jnp.asarray(solver.omega, b.dtype)
    if solver.gradient == "unrolled":
        product = prepare(matrix)
        step, weight, usable = _scalings(matrix, omega)
        length = solver.iterations if solver.scan_length is None else solver.scan_length
        x, r, moved, history, norm0, norm = _sweeps(product, b, x0, step, weight, usable,
                                                    solver.iterations, length)
        d_x = jax.lax.stop_gradient(diagonal(matrix) * x)
        diverged = _diverged(weight, norm0, norm, b, d_x)
        if isinstance(counter, ReverseTally):  # counts when the reverse pass runs it
            x = tap(counter, "adjoint", moved, x)
        elif counter is not None:
            x = adjoint_tap(x, moved, counter)
        sol = Solution(x, moved, jnp.linalg.norm(jax.lax.stop_gradient(r)),
                       history[0], history, jnp.int32(0))
    else:
        k_adj = solver.iterations if solver.adjoint_iterations is None \
            else solver.adjoint_iterations
        pattern = (matrix.rows, matrix.cols, matrix.layout)
        form = (matrix.shape, matrix.kernel)
        # a reverse tally's seed is an input to differentiate (see linalg.cg)
        seed = counter.seed if isinstance(counter, ReverseTally) else None
        host = None if isinstance(counter, ReverseTally) else counter
        x, moved, residual, initial, history, diverged = _implicit_core(
            matrix.values, b, x0, jnp.asarray(solver.iterations, jnp.int32),
            jnp.asarray(k_adj, jnp.int32), omega, pattern, seed, form, solver.history_size,
            host)
        diagnostics = jax.lax.stop_gradient((moved, residual, initial, history, diverged))
        moved, residual, initial, history, diverged = diagnostics
        usable = jax.lax.stop_gradient(_scalings(matrix, omega)[2])
        sol = Solution(x, moved, residual, initial, history, jnp.int32(0))
    sol = sol._replace(status=_status(sol.x, usable, diverged, inputs_finite))
    return sol._replace(x=tap(counter, "primal", sol.iterations, sol.x))


# --------------------------------------------------------------------------------------
# implicit mode
# --------------------------------------------------------------------------------------


def _pattern_matrix(values, pattern, form) -> SparseMatrix:
    (rows, cols, layout), (shape, kernel) = pattern, form
    return SparseMatrix(rows, cols, values, shape, layout, kernel)


@partial(jax.custom_jvp, nondiff_argnums=(8, 9, 10))
def _implicit_core(values, b, x0, iterations, adjoint_iterations, omega, pattern, seed, form,
                   history_size, counter):
    """The forward sweeps; derivatives by :func:`_implicit_jvp`."""
    matrix = _pattern_matrix(values, pattern, form)
    step, weight, usable = _scalings(matrix, omega)
    x, r, moved, history, norm0, norm = _while_sweeps(prepare(matrix), b, x0, step, weight,
                                                      usable, iterations, history_size)
    diverged = _diverged(weight, norm0, norm, b, diagonal(matrix) * x)
    initial = jnp.linalg.norm(b if x0 is None else b - prepare(matrix)(x0))
    return x, moved, jnp.linalg.norm(r), initial, history, diverged


def _implicit_jvp(form, history_size, counter, primals, tangents):
    """``dx = A^{-1} (db - dA x)``, solved by ``K_adj`` sweeps (:func:`_linear_solve`); a
    differentiated reverse-tally ``seed`` takes the adjoint count (see linalg.cg)."""
    values, b, x0, iterations, adjoint_iterations, omega, pattern, seed = primals
    values_dot, b_dot = live_tangent(tangents[0]), live_tangent(tangents[1])
    out = _implicit_core(values, b, x0, iterations, adjoint_iterations, omega, pattern, seed,
                         form, history_size, counter)
    x = out[0]
    zeros = tuple(_zero_tangent(leaf) for leaf in out[1:])
    if values_dot is None and b_dot is None:  # only the seed (or x0) is differentiated
        return out, (jnp.zeros_like(x), *zeros)
    rhs = b_dot
    if values_dot is not None:
        rows, cols, _ = pattern
        minus_dA_x = -jax.ops.segment_sum(values_dot * x[cols], rows, num_segments=x.shape[0])
        rhs = minus_dA_x if rhs is None else rhs + minus_dA_x
    x_dot = _linear_solve(values, rhs, adjoint_iterations, omega, pattern, form, counter,
                          live_tangent(tangents[7]))
    return out, (x_dot, *zeros)


_implicit_core.defjvp(_implicit_jvp, symbolic_zeros=True)


def _linear_solve(values, rhs, iterations, omega, pattern, form, counter,
                  seed_dot=None) -> jax.Array:
    """``A^{-1} rhs`` by ``iterations`` sweeps from zero; its transpose sweeps ``A^T``."""
    matrix = jax.lax.stop_gradient(_pattern_matrix(values, pattern, form))
    omega = jax.lax.stop_gradient(omega)
    step, weight, usable = _scalings(matrix, omega)

    def sweeps(product, right):
        x = _while_sweeps(product, right, None, step, weight, usable, iterations, 0)
        return x[0], x[2]

    return counted_linear_solve(prepare(matrix), rhs, partial(sweeps, prepare(matrix)),
                                partial(sweeps, partial(rmatvec, matrix)), counter, seed_dot)


def _zero_tangent(leaf: jax.Array) -> jax.Array:
    if jnp.issubdtype(leaf.dtype, jnp.inexact):
        return jnp.zeros_like(leaf)
    return np.zeros(leaf.shape, dtype=jax.dtypes.float0)
