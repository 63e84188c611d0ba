"""Truncated and converged preconditioned conjugate gradients, differentiable two ways.

Solvers are frozen objects checked at construction (lineax style) and :func:`solve` returns the
solution *and* its diagnostics::

    sol = solve(A, b, TruncatedCG(iterations=25, gradient="implicit"))
    sol.x, sol.iterations, sol.residual_norm

PCG, ``K`` iterations from ``x0``::

    r = b - A x; z = M r; p = z; rz = r.z
    repeat K:  q = A p; alpha = rz / p.q; x += alpha p; r -= alpha q
               z = M r; rz' = r.z; p = z + (rz'/rz) p

The while loops (implicit and converged modes) run the same operations rotated when there is
a preconditioner to apply: each iteration starts with ``z = M r``, so ``K`` iterations apply
``M`` ``K`` times (not ``K + 1``) and the program holds one copy of it per loop (the AMG
V-cycle inlined before each loop was 13-24 % of an L-BFGS step's compile).

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
    static (one compile per distinct ``K``), or traced below a static ``scan_length`` (one
    compile per length; :func:`unrolled_length` buckets ``K`` by powers of two). Reverse mode
    stores every iteration's intermediates, ``O(K)`` n-vectors; ``checkpoint=True`` stores the
    state only at the starts of segments of ``ceil(sqrt(K))`` iterations and recomputes one
    segment at a time in the backward pass: ``O(sqrt(K))`` n-vectors for about one more forward
    sweep (1.6 GB -> 0.13 GB at 65k dofs and K = 1000, ``prdp-fem bench memory``).

    Two cases are not differentiated through the iterations:

    - *Converged.* Once the relative preconditioned residual ``sqrt(r.z / r0.z0)`` is below
      ``sqrt(eps)`` before or at ``K``, the map is the solution map to half the working
      precision: the scan's iterate is returned and its derivative taken implicitly (the
      tangent or adjoint solved to a relative residual of ``1e-12`` through
      ``lax.custom_linear_solve``, as in implicit mode; the forward sweep solves nothing
      more). Reverse and forward mode through the last iterations lose digits to round-off as
      the residual falls (2e-5 relative at 3e-11, 5 % at 5e-13; through frozen iterations,
      the lagging derivative of the last moving iterate, 0.7 % to 24 % off). Where CG
      terminated in an invariant subspace (e.g. eigenvector data), the K-iteration map's own
      derivative differs from the solution map's; the latter is returned.
    - *Unreliable.* The derivative holds the frozen map ``(1 - R_K(MA)) A^{-1}``, with
      ``R_K`` CG's residual polynomial. Where the data has (next to) no weight on part of the
      spectrum -- a right-hand side in a small invariant subspace, e.g. ``sin(pi x) y`` on a
      structured grid -- CG fits ``R_K`` to the rest and it grows by orders of magnitude
      there: the exact derivative of the K-iteration map is then that large in the
      directions that reach it (the map is linear only on scales far below any useful
      step), and round-off in both sweeps is amplified alike (derivatives 1e14 off were
      measured). ``max |R_K|`` over the spectrum is evaluated from the step coefficients
      after the scan (a Gershgorin bound of the spectrum; with AMG or a nullspace, that of
      CG's Lanczos matrix); above ``1/sqrt(eps)`` the solve's ``status`` is
      ``UNRELIABLE_DERIVATIVE``. ``x`` is unaffected, and an eager solve does not raise.
``"implicit"``
    The solve is a ``jax.custom_jvp`` whose tangent is ``dx = A^{-1} (db - dA x)``, the
    tangent system solved with ``adjoint_iterations`` PCG iterations through
    ``lax.custom_linear_solve`` (same prepared operator and preconditioner, same tolerances).
    Reverse mode transposes that linear map: the adjoint solve ``A lambda = x_bar``
    (``K_adj`` iterations) with ``b_bar = lambda``, ``values_bar[k] = -lambda[row_k] x[col_k]``
    (and zero for ``x0``: at convergence ``x`` does not depend on it). Forward mode
    (``jax.jvp``: ``J v``) solves the tangent system with ``K_adj`` iterations too, and both
    compose to any order: ``jax.jvp(jax.grad(f))`` (a Hessian-vector product) runs one tangent
    and one second-order adjoint solve per product. Exact at convergence, the PRDP
    approximation when truncated: a truncated CG sweep is not a linear map of its right-hand
    side (its Krylov polynomial depends on it), so ``<J v, w> = <v, J^T w>`` holds to
    round-off only where the sweeps converge. ``K`` and ``K_adj`` are traced: changing them
    does not recompile, and iterations stop early once the residual reaches round-off.

Status and bad input
--------------------
``Solution.status`` says whether the result can be trusted (:class:`Status`): ``SUCCESS``;
``BREAKDOWN`` (``p.Ap <= 0`` before round-off: the operator is not positive definite, e.g. a
``kappa <= 0``; ``x`` is the last iterate before it); ``NONFINITE`` (NaN/Inf in the inputs or
the result); ``INCOMPATIBLE`` (a singular system whose right-hand side has a component in the
nullspace); ``NOT_CONVERGED`` (:class:`ConvergedCG` ran out of iterations);
``UNRELIABLE_DERIVATIVE`` (unrolled mode: ``x`` is right, its derivative cannot be trusted);
``DIVERGED`` (:class:`~prdp_fem.linalg.TruncatedJacobi` only: the sweep's spectral radius is
``>= 1``).
Called eagerly (no tracers), :func:`solve` raises instead (except for
``UNRELIABLE_DERIVATIVE``): :class:`~prdp_fem.errors.DataError` for non-finite inputs before
running, :class:`~prdp_fem.errors.SolverBreakdownError` /
:class:`~prdp_fem.errors.IncompatibleDataError` after. Inside ``jit`` it cannot raise: check
``status`` (the inverse driver does).

Singular operators
------------------
``nullspace=v`` solves a symmetric positive *semi*-definite system with ``null(A) = span(v)``
(pure Neumann: ``v`` = constants). The right-hand side must be orthogonal to ``v`` up to
``sqrt(eps)`` relative (else ``INCOMPATIBLE``: the *discrete* data must balance, which
interpolated or quadrature data of a balanced continuous problem do only up to the
discretisation error; :meth:`~prdp_fem.fem.discretization.Discretization.balance_source` shifts a
source so that they do). The component is removed either way; CG then runs on the complement
of ``v``: the initial residual and every preconditioned residual are projected
(``z = P M P r``, still symmetric), and the returned ``x`` is orthogonal to ``v``. Both
gradient modes differentiate ``x = P A^+ P b``.

Limits (by design): in unrolled mode at ``b - A x0 = 0`` the K-iteration map is
not differentiable (it is positively homogeneous in the residual) and the gradient returned
there is zero: start a source inversion from a non-zero residual, or use implicit mode, whose
gradient at zero residual is the (truncated) adjoint solution as usual.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import is_traced
from .._xla_options import CLASSIC_EMITTERS, solver_options
from ..errors import (
    DataError,
    IncompatibleDataError,
    ShapeError,
    SolverBreakdownError,
    SolverConfigError,
)
from ._products import symmetric_product
from ._tally import (
    COUNTS,
    IterationCounter,
    ReverseTally,
    counted_linear_solve,
    live_tangent,
    read_counts,
    tap,
    zero_counts,
)
from .operator import SparseMatrix, prepare
from .precond import PRECONDITIONERS, JacobiPreconditioner, make_preconditioner
from .sharding import Partition

__all__ = ["COUNTS", "ConvergedCG", "IterationCounter", "ReverseTally", "Solution", "Status",
           "TruncatedCG", "read_counts", "solve", "unrolled_length", "zero_counts"]

GRADIENT_MODES = ("unrolled", "implicit")


class Status(enum.IntEnum):
    """What ``Solution.status`` holds (an int32 array, so that it survives ``jit``)."""

    SUCCESS = 0
    BREAKDOWN = 1  # p.Ap <= 0 before round-off: the operator is not positive definite
    NONFINITE = 2  # NaN/Inf in the inputs or in the result
    INCOMPATIBLE = 3  # b has a component in the nullspace given to solve()
    NOT_CONVERGED = 4  # ConvergedCG: max_iterations reached above the tolerance
    # TruncatedCG, unrolled: x is the K-iteration map's value, but its derivative cannot be
    # trusted (the CG polynomial amplifies part of the spectrum past 1/sqrt(eps))
    UNRELIABLE_DERIVATIVE = 5
    # TruncatedJacobi (prdp_fem.linalg.stationary): the weighted residual grew, the sweep's spectral
    # radius is >= 1; x is the last iterate before the growth passed 1/sqrt(eps)
    DIVERGED = 6


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
        ``||r_k||_2`` for ``k = 0..K`` (unrolled mode; with a ``scan_length``, its
        ``scan_length + 1`` entries padded with the final value); in implicit/converged mode a
        buffer of ``history_size + 1`` entries, padded with the final value.
    status
        A :class:`Status` code (int32): ``0`` when ``x`` (and, unrolled, its derivative) can
        be trusted; ``UNRELIABLE_DERIVATIVE`` when ``x`` can be and its derivative cannot.
    """

    x: jax.Array
    iterations: jax.Array
    residual_norm: jax.Array
    initial_residual_norm: jax.Array
    residual_history: jax.Array
    status: jax.Array


_MAX_COUNT = int(np.iinfo(np.int32).max)


def check_count(value: Any, name: str, allow_none: bool = False) -> None:
    if value is None and allow_none:
        return
    if isinstance(value, jax.core.Tracer):
        return  # traced: a negative count runs zero iterations (the loop test is k < K)
    if (isinstance(value, bool) or np.ndim(value) != 0
            or not np.issubdtype(np.asarray(value).dtype, np.integer) or int(value) < 0):
        raise SolverConfigError(f"{name}={value!r}: expected an integer >= 0")
    if int(value) > _MAX_COUNT:  # the loops count in int32
        raise SolverConfigError(f"{name}={value!r}: expected an integer <= {_MAX_COUNT}")


def check_truncation(solver: Any) -> None:
    """The checks a truncated solver (:class:`TruncatedCG`,
    :class:`~prdp_fem.linalg.stationary.TruncatedJacobi`) makes at construction, and the
    normalisation of its counts: ``gradient``, ``scan_length``, ``iterations``,
    ``adjoint_iterations``, ``history_size``. Run from a frozen dataclass's ``__post_init__``.
    """
    if solver.gradient not in GRADIENT_MODES:
        raise SolverConfigError(
            f"gradient={solver.gradient!r}: expected one of {GRADIENT_MODES}")
    check_count(solver.scan_length, "scan_length", allow_none=True)
    if solver.scan_length is not None:
        if solver.gradient != "unrolled":
            raise SolverConfigError(
                f"scan_length={solver.scan_length!r} with gradient={solver.gradient!r}: a scan "
                "length is for gradient='unrolled' (implicit mode takes a traced K as is)")
        object.__setattr__(solver, "scan_length", int(solver.scan_length))
    if solver.gradient == "unrolled" and solver.scan_length is None:
        if isinstance(solver.iterations, jax.core.Tracer):
            raise SolverConfigError(
                "iterations is traced but gradient='unrolled' needs a static K (reverse "
                "mode through a loop needs its length); give a static scan_length >= K "
                "(see unrolled_length), use gradient='implicit' for a traced K, or mark K "
                "static in jax.jit")
        check_count(solver.iterations, "iterations")
        object.__setattr__(solver, "iterations", int(solver.iterations))
    else:
        check_count(solver.iterations, "iterations")
        if solver.scan_length is not None and not isinstance(solver.iterations, jax.core.Tracer) \
                and int(solver.iterations) > solver.scan_length:
            raise SolverConfigError(
                f"iterations={solver.iterations!r} > scan_length={solver.scan_length}: "
                "expected K <= scan_length (see unrolled_length)")
    check_count(solver.adjoint_iterations, "adjoint_iterations", allow_none=True)
    check_count(solver.history_size, "history_size")
    object.__setattr__(solver, "history_size", int(solver.history_size))


def _check_preconditioner(spec: Any) -> None:
    if isinstance(spec, str) and spec in PRECONDITIONERS:
        return
    if callable(spec) and not isinstance(spec, str) and all(
            hasattr(leaf, "dtype") or isinstance(leaf, int | float)
            for leaf in jax.tree_util.tree_leaves(spec)):
        return
    if isinstance(spec, str) and spec.lower() == "amg":
        # an AMG hierarchy is built on the host from concrete values; solve's matrix may be
        # traced, so the preconditioner is built by the caller, once, outside the transformation
        raise SolverConfigError(
            f"preconditioner={spec!r}: the AMG hierarchy cannot be built inside solve (its "
            "matrix may be traced); expected a preconditioner built once, outside jit: "
            "preconditioner=prdp_fem.amg_preconditioner(A)")
    from .amg import RebuiltAMG  # here: amg builds on the solvers' modules

    if isinstance(spec, RebuiltAMG):
        raise SolverConfigError(
            f"preconditioner={spec!r}: a RebuiltAMG is built from the operator by invert() "
            "only; expected here a preconditioner built once: prdp_fem.amg_preconditioner(A)")
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
        ``K_adj`` for the implicit adjoint (reverse mode) and tangent (forward mode) solves;
        ``None`` means ``K_adj = K``.
    checkpoint
        Unrolled mode: bound the memory of reverse mode by recomputing iterations in the
        backward pass. ``False`` stores every iteration's intermediates (``O(K)`` n-vectors);
        ``True`` splits the ``K`` iterations into checkpointed segments of
        ``s = ceil(sqrt(K))``, storing only the state at each segment start and recomputing one
        segment at a time (``O(sqrt(K))`` n-vectors, about one extra forward sweep); an integer
        ``s >= 1`` sets the segment length (``s = 1``: the state after every iteration is
        stored). Same ``x``, gradients and diagnostics as without. No effect in implicit mode,
        whose memory does not depend on ``K``.
    history_size
        Implicit mode: length of the residual-history buffer minus one.
    scan_length
        Unrolled mode: a static scan of this many steps whose first ``iterations`` run PCG
        and the rest pass the state on unchanged. ``iterations`` may then be traced, so one
        compiled program serves every ``K <= scan_length`` (:func:`unrolled_length` buckets
        ``K`` by powers of two); at most ``scan_length`` iterations run
        (``Solution.iterations`` says how many did). The values and derivatives are those of
        the ``K``-iteration scan (to round-off; the built-in scenes' unrolled runs take the
        same steps bit for bit); the time and reverse mode's memory are those of
        ``scan_length`` iterations (a passed-on step computes an iteration with a zero step
        length, as CG takes a frozen one).
        ``None`` (default): a scan of exactly ``iterations`` (static) steps.
    """

    iterations: Any
    preconditioner: Any = "jacobi"
    gradient: str = "unrolled"
    adjoint_iterations: Any = None
    checkpoint: bool | int = False
    history_size: int = 0
    scan_length: int | None = None

    def __post_init__(self):
        check_truncation(self)
        _check_preconditioner(self.preconditioner)
        object.__setattr__(self, "checkpoint", _checked_checkpoint(self.checkpoint))


def _checked_checkpoint(value: Any) -> bool | int:
    """``True``, ``False`` or a segment length ``>= 1`` (as a Python int)."""
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if (np.ndim(value) == 0 and not isinstance(value, jax.core.Tracer)
            and np.issubdtype(np.asarray(value).dtype, np.integer) and int(value) >= 1):
        return int(value)
    raise SolverConfigError(f"checkpoint={value!r}: expected True (segments of ceil(sqrt(K)) "
                            "iterations), False or a segment length >= 1")


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
        check_count(self.max_iterations, "max_iterations", allow_none=True)
        check_count(self.history_size, "history_size")
        _check_preconditioner(self.preconditioner)
        object.__setattr__(self, "history_size", int(self.history_size))


def solve(matrix: SparseMatrix, b: jax.Array, solver: Any,
          x0: jax.Array | None = None, *, nullspace: jax.Array | None = None,
          counter: IterationCounter | None = None) -> Solution:
    """Solve ``A x = b`` (``A`` symmetric positive definite) with ``solver``.

    ``nullspace`` (a vector ``v``) makes ``A`` positive *semi*-definite with ``A v = 0``: the
    solution orthogonal to ``v`` is returned (see the module docstring). ``counter`` (an
    :class:`IterationCounter`) tallies the iterations run forward and backward. Called eagerly,
    bad input and a breakdown raise typed errors; under ``jit`` they set ``status``.
    ``solver`` may also be a :class:`~prdp_fem.linalg.stationary.TruncatedJacobi` (stationary Jacobi
    sweeps, :func:`~prdp_fem.linalg.stationary.jacobi_solve`; no ``nullspace``).

    An eager call (no tracers, no counter) runs as one compiled program, kept per shape and
    solver form: ``K`` (implicit mode, or unrolled below a ``scan_length``), ``K_adj``
    (implicit mode), ``rtol``, ``atol``, ``max_iterations`` and a preconditioner pytree of
    arrays are its arguments, so new values reuse it; an unrolled ``K`` without a
    ``scan_length`` is the scan's length and compiles anew. A preconditioner holding Python
    numbers, or a counter, runs op by op (run so, a solve on a new shape compiled some 35
    small programs), which may round differently in the last bits.

    >>> import numpy as np, scipy.sparse as sp
    >>> from prdp_fem.linalg.operator import SparseMatrix
    >>> A = SparseMatrix.from_scipy(sp.diags([4.0, 2.0]) + sp.eye(2, k=1) + sp.eye(2, k=-1))
    >>> sol = solve(A, np.array([1.0, 2.0]), TruncatedCG(iterations=2))
    >>> np.allclose(A.todense() @ sol.x, [1.0, 2.0]), int(sol.iterations), Status(sol.status)
    (True, 2, <Status.SUCCESS: 0>)
    """
    b = jnp.asarray(b, dtype=matrix.values.dtype)
    # x0 = None is a zero start: the solvers then skip the product A x0 (a whole SpMV)
    x0 = None if x0 is None else jnp.asarray(x0, dtype=b.dtype)
    if b.shape != (matrix.shape[0],) or (x0 is not None and x0.shape != b.shape):
        raise ShapeError(
            f"b{tuple(b.shape)} / x0{tuple(b.shape if x0 is None else x0.shape)}: expected "
            f"vectors of length {matrix.shape[0]} to match the operator")
    from .stationary import TruncatedJacobi, jacobi_solve  # here: it builds on this module

    if isinstance(solver, TruncatedJacobi):
        if nullspace is not None:
            raise SolverConfigError("nullspace: TruncatedJacobi solves non-singular systems "
                                    "only; expected TruncatedCG or ConvergedCG with a nullspace")
        return jacobi_solve(matrix, b, solver, x0, counter=counter)
    if not isinstance(solver, TruncatedCG | ConvergedCG):
        raise SolverConfigError(
            f"solver={solver!r}: expected TruncatedCG, ConvergedCG or TruncatedJacobi")
    if isinstance(matrix.layout, Partition) and not isinstance(solver.preconditioner, str):
        raise SolverConfigError(
            f"preconditioner={type(solver.preconditioner).__name__}: a matrix spread over "
            "devices (linalg.shard) is preconditioned by 'jacobi' or 'identity'; an AMG "
            "hierarchy is built for one device")
    dynamic, static = _split_solver(solver, matrix.shape[0])
    if is_traced(matrix.values, b, x0, nullspace, dynamic):
        return _solve_traced(matrix, b, x0, solver, nullspace, counter)
    check_finite_inputs(matrix, b, x0)
    if nullspace is not None:
        _check_nullspace(nullspace, b)  # inside the compiled solve it is traced
    if counter is None and _compilable(dynamic):
        program = _compiled_program(solver.preconditioner)
        sol = program(matrix, b, x0, nullspace, _typed(dynamic), static)
    else:  # a counter's host calls, or a preconditioner's Python numbers: op by op
        sol = _solve_traced(matrix, b, x0, solver, nullspace, counter)
    _raise_on_status(sol)
    return sol


def _split_solver(solver: TruncatedCG | ConvergedCG, n: int) -> tuple[dict, tuple]:
    """``(dynamic, static)``: the solver's numbers a compiled solve takes as arguments (the
    counts and tolerances its loops read as arrays, a preconditioner pytree) and the rest,
    hashable, as its cache key. A new ``K`` or ``rtol`` then reuses the program. Defaults are
    resolved first, so that ``None`` against a number does not change its signature."""
    fields = {f.name: getattr(solver, f.name) for f in dataclasses.fields(solver)}
    if isinstance(solver, ConvergedCG):
        if fields["max_iterations"] is None:
            fields["max_iterations"] = 10 * n
        names = ["rtol", "atol", "max_iterations"]
    elif solver.gradient == "implicit":
        if fields["adjoint_iterations"] is None:
            fields["adjoint_iterations"] = fields["iterations"]
        names = ["iterations", "adjoint_iterations"]
    else:  # unrolled: K is the scan's length unless a scan_length is; K_adj is not read
        fields["adjoint_iterations"] = None
        names = [] if solver.scan_length is None else ["iterations"]
    if not isinstance(solver.preconditioner, str):
        names.append("preconditioner")
    return {name: fields.pop(name) for name in names}, (type(solver), tuple(fields.items()))


# the types of the dynamic numbers in a compiled eager solve: a NumPy integer against a Python
# one (or an int rtol) would otherwise be another signature, another program. The loops count
# in int32 (check_count keeps counts within it)
_NUMBER_TYPES = {"rtol": np.float64, "atol": np.float64, "max_iterations": np.int32,
                 "iterations": np.int32, "adjoint_iterations": np.int32}


def _compilable(dynamic: dict) -> bool:
    """Whether every dynamic leaf is an array: a preconditioner pytree may hold Python numbers
    (a sweep count read by ``range``), which a compiled solve would trace."""
    leaves = jax.tree_util.tree_leaves(dynamic.get("preconditioner"))
    return all(hasattr(leaf, "dtype") for leaf in leaves)


def _typed(dynamic: dict) -> dict:
    return {name: np.asarray(value, _NUMBER_TYPES[name]) if name in _NUMBER_TYPES else value
            for name, value in dynamic.items()}


def _compiled_solve(matrix, b, x0, nullspace, dynamic, static) -> Solution:
    """An eager :func:`solve` as one program: run op by op, a solve on a new shape compiled
    some 35 small programs (1.0-1.5 s on 2 CPU cores) where this compiles one (0.3-0.4 s)."""
    kind, fields = static
    return _solve_traced(matrix, b, x0, kind(**dict(fields), **dynamic), nullspace, None)


_COMPILED_SOLVE = jax.jit(_compiled_solve, static_argnames=("static",))
# a named preconditioner (identity, Jacobi) applies no AMG cycle: XLA's classic CPU emitters
# compile and run it faster (prdp_fem._xla_options); a preconditioner pytree may be a cycle
_COMPILED_SOLVE_CLASSIC = jax.jit(_compiled_solve, static_argnames=("static",),
                                  compiler_options=dict(CLASSIC_EMITTERS))


def _compiled_program(preconditioner):
    """The eager solve's jitted program: XLA's classic CPU emitters for a named preconditioner
    where they apply (:func:`~prdp_fem._xla_options.solver_options`), else JAX's options."""
    return _COMPILED_SOLVE_CLASSIC if solver_options(preconditioner) else _COMPILED_SOLVE


def _solve_traced(matrix, b, x0, solver, nullspace, counter) -> Solution:
    """The solve, with its outcome in ``status`` (``x0``: ``None`` for a zero start)."""
    if isinstance(matrix.layout, Partition):  # spread over devices: solve it renumbered
        part = matrix.layout
        start, direction = (None if v is None else part.to_partitioned(v)
                            for v in (x0, nullspace))
        sol = _solve_traced(part.partitioned(matrix), part.to_partitioned(b), start, solver,
                            direction, counter)
        return sol._replace(x=part.from_partitioned(sol.x))
    precond = make_preconditioner(solver.preconditioner, matrix)
    incompatible = jnp.asarray(False)
    start = x0
    if nullspace is not None:
        direction = _unit_nullspace(nullspace, b)
        precond = _Projected(precond, direction)
        incompatible = _incompatible(direction, b)
        b = precond.project(b)
        start = None if x0 is None else precond.project(x0)
    if isinstance(solver, TruncatedCG) and solver.gradient == "unrolled":
        sol = _unrolled(matrix, precond, b, start, solver.iterations, solver.checkpoint,
                        solver.scan_length)
        if isinstance(counter, ReverseTally):  # counts when the reverse pass runs it
            sol = sol._replace(x=tap(counter, "adjoint", sol.iterations, sol.x))
        elif counter is not None:
            sol = sol._replace(x=adjoint_tap(sol.x, sol.iterations, counter))
    elif isinstance(solver, TruncatedCG):
        k_adj = solver.iterations if solver.adjoint_iterations is None \
            else solver.adjoint_iterations
        sol = _implicit_solve(matrix, b, start, solver.iterations, k_adj, precond, 0.0, 0.0,
                              solver.history_size, solver.history_size > 0, counter)
    else:
        max_iterations = 10 * matrix.shape[0] if solver.max_iterations is None \
            else solver.max_iterations
        sol = _implicit_solve(matrix, b, start, max_iterations, max_iterations, precond,
                              solver.rtol, solver.atol, solver.history_size, True, counter)
    inputs = (matrix.values, b) if x0 is None else (matrix.values, b, x0)
    sol = sol._replace(status=_final_status(sol, incompatible, _all_finite(*inputs)))
    return sol._replace(x=tap(counter, "primal", sol.iterations, sol.x))


# --------------------------------------------------------------------------------------
# input checks, status, nullspace
# --------------------------------------------------------------------------------------


def check_finite_inputs(matrix: SparseMatrix, b: jax.Array, x0: jax.Array | None) -> None:
    for name, value in (("operator values", matrix.values), ("b", b), ("x0", x0)):
        if value is None:
            continue
        bad = ~np.isfinite(np.asarray(value))
        if bad.any():
            hint = " (check kappa)" if name == "operator values" else ""
            raise DataError(f"{name}: {int(bad.sum())} of {bad.size} entries are NaN/Inf "
                            f"(first: index {int(np.flatnonzero(bad)[0])}){hint}; expected "
                            "finite values")


def _raise_on_status(sol: Solution) -> None:
    status = Status(int(sol.status))
    if status == Status.BREAKDOWN:
        raise SolverBreakdownError(
            f"CG broke down after {int(sol.iterations)} iterations (p.Ap <= 0 with residual "
            f"{float(sol.residual_norm):.3g}): the operator is not positive definite; expected "
            "kappa > 0 (a positive definite tensor) and a Dirichlet boundary or a nullspace")
    if status == Status.INCOMPATIBLE:
        raise IncompatibleDataError(
            "b: has a component along the nullspace, so A x = b has no solution (pure Neumann: "
            "the discrete int f + int h is not 0); expected balanced data, e.g. "
            "Discretization.balance_source(f) or b - mean(b)")
    if status == Status.NONFINITE:
        raise DataError(f"solution: NaN/Inf after {int(sol.iterations)} iterations from finite "
                        "inputs (overflow: rescale the problem); expected finite values")


def _final_status(sol: Solution, incompatible: jax.Array, inputs_finite: jax.Array) -> jax.Array:
    """The solver's own status, overridden by non-finite data or results, incompatible data.

    Non-finite inputs must be checked apart: a NaN initial residual freezes CG at ``x0``
    (``NaN > level`` is false), which would otherwise look like a finite, converged result.
    """
    status = jnp.where(incompatible, Status.INCOMPATIBLE, sol.status)
    finite = jnp.all(jnp.isfinite(jax.lax.stop_gradient(sol.x))) & inputs_finite
    return jnp.where(finite, status, Status.NONFINITE).astype(jnp.int32)


def _all_finite(*arrays: jax.Array) -> jax.Array:
    # every entry, not the sum: a sum of finite data of 1e306 overflows
    return jax.lax.stop_gradient(
        jnp.all(jnp.asarray([jnp.all(jnp.isfinite(a)) for a in arrays])))


def _check_nullspace(nullspace: Any, b: jax.Array) -> None:
    """A nullspace vector of ``b``'s shape and, where concrete, finite and not zero."""
    if np.shape(nullspace) != b.shape:
        raise ShapeError(f"nullspace{tuple(np.shape(nullspace))}: expected a vector of length "
                         f"{b.shape[0]} spanning the operator's nullspace")
    if is_traced(nullspace):
        return
    v = np.asarray(nullspace)
    if not (np.isfinite(v).all() and np.any(v)):
        raise SolverConfigError("nullspace: expected a finite, non-zero vector")


def _unit_nullspace(nullspace: jax.Array, b: jax.Array) -> jax.Array:
    _check_nullspace(nullspace, b)
    v = jnp.asarray(nullspace, dtype=b.dtype)
    return v / _robust_norm(v)


def _incompatible(direction: jax.Array, b: jax.Array) -> jax.Array:
    """``|v.b| > sqrt(eps) ||b||``: ``b`` is not in the range of ``A`` (to round-off)."""
    along = jnp.abs(jnp.vdot(direction, b))
    return jax.lax.stop_gradient(along > jnp.sqrt(jnp.finfo(b.dtype).eps) * _robust_norm(b))


@partial(jax.tree_util.register_dataclass, data_fields=["inner", "direction"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class _Projected:
    """``z = P M P r`` with ``P = I - v v'``: a preconditioner on the complement of ``v``."""

    inner: Any
    direction: jax.Array

    def project(self, vector: jax.Array) -> jax.Array:
        return vector - jnp.vdot(self.direction, vector) * self.direction

    def __call__(self, r: jax.Array) -> jax.Array:
        return self.project(self.inner(self.project(r)))


# --------------------------------------------------------------------------------------
# the system as CG runs it: a prepared kernel, symmetrically scaled for Jacobi
# --------------------------------------------------------------------------------------


@partial(jax.tree_util.register_dataclass, data_fields=["operator", "precond", "scale"],
         meta_fields=[])
@dataclasses.dataclass(frozen=True)
class _Krylov:
    """``A x = b`` as CG runs it: ``(S A S) y = S b``, ``x = S y``, preconditioned by ``precond``.

    With a diagonal preconditioner ``M = S^2`` (Jacobi), PCG on ``A`` *is* CG on ``S A S``
    without a preconditioner: the iterates map as ``x = S y`` and ``r = S^{-1} r_s``, and
    ``r.z = r.M r = r_s.r_s``. The scaled form drops the ``z = M r`` pass and its vector from
    every iteration (one kernel preparation per solve pays for it): measured 1.75x -> 1.5x
    (65k dofs) and 1.3x -> 0.9x (261k) of a SciPy SpMV per iteration. Otherwise ``S = I``
    (``scale`` is ``None``) and ``precond`` is applied as usual.
    """

    operator: Any  # a prepared kernel (operator.prepare) of S A S
    precond: Any  # None: identity
    scale: jax.Array | None

    def product(self, vector: jax.Array) -> jax.Array:
        """``(S A S) v``; reverse mode transposes it as itself (CG's ``A`` is symmetric), with
        no scatter per ELL slot (:mod:`prdp_fem.linalg._products`)."""
        return symmetric_product(self.operator, vector)

    def scaled(self, vector: jax.Array) -> jax.Array:
        """``S v``: a right-hand side or residual into the scaled system, an iterate out of it."""
        return vector if self.scale is None else self.scale * vector

    def residual_norm(self, r: jax.Array) -> jax.Array:
        """``||S^{-1} r||_2``: the norm of the residual of ``A x = b``."""
        return _norm(r if self.scale is None else r / self.scale)

    def precondition(self, r: jax.Array) -> jax.Array:
        return r if self.precond is None else self.precond(r)


def _krylov(matrix: SparseMatrix, precond) -> _Krylov:
    kernel = prepare(matrix)
    if isinstance(precond, JacobiPreconditioner):
        scale = jnp.sqrt(precond.inverse_diagonal)
        return _Krylov(kernel.scaled(scale), None, scale)
    return _Krylov(kernel, precond, None)


# --------------------------------------------------------------------------------------
# one PCG iteration, guarded
# --------------------------------------------------------------------------------------


class _CGState(NamedTuple):
    """CG on the scaled correction: ``y = y0 + r0_scale * d`` with ``A_s d = r0 / r0_scale``.

    ``dr`` holds ``d`` and ``r``: a pair, or (``_init(..., stacked=True)``) one ``(2, n)``
    array. Stacked, both updates are one fused pass (``[d, r] += alpha [p, -q]``), ``r.r`` is a
    row reduction of it, and ``p``'s last reader is its own update, so XLA updates ``p`` in
    place: kept apart, the CPU backend ran the updates as two passes and copied ``p`` every
    iteration. The while loops run stacked where :func:`_stacks` says so (Jacobi above 16384
    unknowns: an iteration 0.83-0.9x the time at 65k-1M dofs); the scan of unrolled mode
    keeps the pair, whose reverse sweep is cheaper than the transposes of the stacking
    (stacked, a K = 100 gradient at 65k dofs took 1.1x the time, 1.25x with the symmetric
    product).
    """

    dr: jax.Array | tuple[jax.Array, jax.Array]  # [d, r]
    p: jax.Array
    rz: jax.Array
    freeze_level: jax.Array  # eps^2 * r0.z0: below it r.z is round-off and CG stops moving
    broken: jax.Array  # p.Ap <= 0 was met while still active: A is not positive definite

    @property
    def d(self) -> jax.Array:
        return self.dr[0]

    @property
    def r(self) -> jax.Array:
        return self.dr[1]


class _Start(NamedTuple):
    state: _CGState
    x0: jax.Array | None  # None: a zero start
    r0_norm: jax.Array  # ||b - A x0||_2
    r0_scale: jax.Array  # the normalisation of the correction (||r0|| in the scaled system)


def _safe_ratio(num: jax.Array, den: jax.Array, ok: jax.Array) -> jax.Array:
    """``num / den`` where ``ok``, else exactly 0; the denominator is made safe first."""
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _init(krylov: _Krylov, b, x0, *, stacked: bool, precondition: bool = True) -> _Start:
    """Initial state of CG on the correction, scaled to a unit residual.

    CG from ``x0`` equals CG from zero on ``A d = r0``; solving for ``d`` scaled by
    ``1/||r0||`` keeps every inner product O(1), so neither the values nor their derivatives
    (``d(a/b)/db = -a/b^2``) under- or overflow for tiny or huge right-hand sides. ``x0`` is
    ``None`` for a zero start: ``r0 = b`` without the product (XLA cannot drop ``A 0``: its
    gathers and ``0 * inf`` are not known to vanish), which was two SpMVs of an implicit
    gradient's fixed cost (primal and adjoint solve).

    ``precondition=False`` leaves ``z0 = M r0`` to the first iteration
    (:func:`_step_preconditioning_first`): ``p`` is zero, and ``rz`` and ``freeze_level`` are
    placeholders that iteration replaces.
    """
    if x0 is None:
        r0 = krylov.scaled(b)
    else:
        y0 = x0 if krylov.scale is None else x0 / krylov.scale
        r0 = krylov.scaled(b) - krylov.product(y0)
    if isinstance(krylov.precond, _Projected):  # round-off or a cotangent may leave a v part
        r0 = krylov.precond.project(r0)
    # held constant in derivatives: the K-step map r0 -> d is homogeneous of degree 1 (a
    # Krylov method with a linear preconditioner, and scale-free freeze and breakdown tests),
    # so s d(r0 / s) has the exact derivatives for a constant s, and the reverse sweep never
    # forms r0 / s^2 (which under- or overflows with s)
    r0_scale = jax.lax.stop_gradient(_robust_norm(r0))
    r0_scale = jnp.where(r0_scale > 0, r0_scale, 1.0)
    r = r0 / r0_scale
    dr = (jnp.zeros_like(r), r)
    if precondition:
        z = krylov.precondition(r)
        rz = jnp.vdot(r, z)
        p, freeze_level = z, _freeze_level(rz)
    else:
        p, rz, freeze_level = jnp.zeros_like(r), jnp.ones((), r.dtype), jnp.zeros((), r.dtype)
    state = _CGState(jnp.stack(dr) if stacked else dr, p, rz, freeze_level, jnp.asarray(False))
    return _Start(state, x0, r0_scale * krylov.residual_norm(r), r0_scale)


def _solution(krylov: _Krylov, start: _Start, d: jax.Array) -> jax.Array:
    # x0 + S (r0_scale d), not S (y0 + ...): K = 0 returns x0 bit for bit
    correction = krylov.scaled(start.r0_scale * d)
    return correction if start.x0 is None else start.x0 + correction


def _norm(v: jax.Array) -> jax.Array:
    # sqrt has an infinite derivative at 0: guard it so a zero residual keeps gradients finite
    sq = jnp.vdot(v, v)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def _robust_norm(v: jax.Array) -> jax.Array:
    """``||v||_2`` without under- or overflow in ``v.v``: ``2^e ||2^-e v||`` with ``2^e`` just
    above ``max |v_i|``.

    Entries below about 1e-154 square to subnormals or zero (a right-hand side of 1e-161 had
    ``b.b = 0`` and froze CG at ``x = 0``), entries above 1e154 to inf. Scaling by a power of
    two is exact, so wherever ``v.v`` neither under- nor overflows the result is ``||v||`` bit
    for bit (a norm rounded differently changed CG's iterates in the last bits, and a fragile
    run took another path). The scale is held constant in derivatives: the norm is
    homogeneous, so ``d||v|| = v.dv / ||v||`` is exact without it.
    """
    exponent = _scale_exponent(v)
    return _norm(v * _power_of_two(-exponent, v.dtype)) * _power_of_two(exponent, v.dtype)


def _scale_exponent(v: jax.Array) -> jax.Array:
    """``e`` with ``2^(e-1) <= max |v_i| < 2^e`` (0 for a zero ``v``), clipped so that both
    ``2^e`` and ``2^-e`` are normal numbers (XLA's CPU code flushes subnormals to zero)."""
    _, exponent = jnp.frexp(jax.lax.stop_gradient(jnp.max(jnp.abs(v), initial=0.0)))
    finfo = jnp.finfo(v.dtype)
    return jnp.clip(exponent, finfo.minexp, finfo.maxexp - 2)


def _power_of_two(exponent: jax.Array, dtype) -> jax.Array:
    """``2^exponent``, exactly (built from its bits: XLA does not fold it into a division)."""
    return jnp.ldexp(jnp.ones((), dtype), exponent)


def _active(state: _CGState) -> jax.Array:
    return state.rz > state.freeze_level


def _freeze_level(rz0: jax.Array) -> jax.Array:
    """``eps^2 r0.z0``: where ``r.z`` falls below it, it is round-off."""
    return jnp.square(jnp.finfo(rz0.dtype).eps) * rz0


# From this many unknowns on, the unpreconditioned ``r.r`` of a stacked state is a reduction over
# both rows of ``[d, r]`` (it reads ``d`` for nothing, but copies no slice of ``r``): measured on
# 2 CPU cores, 0.66-0.7x the slice-and-dot's iteration time at 20k-25k unknowns and 0.9x at
# 261k, but 1.1-1.2x at 16k, where the slice stays in cache.
_ROW_REDUCTION_FROM = 1 << 14


def _stacks(krylov: _Krylov, n: int) -> bool:
    """Whether a while loop over ``n`` unknowns keeps ``[d, r]`` stacked (:class:`_CGState`):
    only in Jacobi's scaled system above ``_ROW_REDUCTION_FROM``, where ``r.r`` is the row
    reduction of the stacked state.

    Elsewhere XLA's CPU backend copies the row ``r`` out of ``[d, r]`` every iteration for
    its dot products (and for ``||r||`` in a loop that tracks it), and the pair is the
    faster. Iteration time paired against stacked, on 2 CPU cores, the same iterates bit for
    bit (P1 Laplacian unless said; ``TruncatedCG`` implicit with a traced ``K``,
    ``ConvergedCG`` to rtol 1e-10):

    - Jacobi, truncated: 0.99-1.01 at 5k-9k unknowns, 0.63-0.86 at 12k-16k, 0.89 at 18k,
      1.16-1.64 at 25k-65k; P2: 0.27 at 4k, 1.03-1.04 at 9k-16k, 1.17 at 25k;
    - Jacobi, to a tolerance: 0.99-1.04 at 5k-11k, 0.66-0.91 at 12k-16k, 1.03-1.50 at
      18k-65k (two runs of 0.87 and 0.88 among them);
    - identity: 0.85-0.97 (truncated), 0.75-0.93 (to a tolerance) at 9k-65k;
    - smoothed-aggregation AMG: 0.95-1.02 and 0.87-0.96.
    """
    return krylov.precond is None and n > _ROW_REDUCTION_FROM


class _StepInfo(NamedTuple):
    """What one iteration of :func:`_step` says besides its state."""

    moving: jax.Array  # it moved ``x``
    alpha: jax.Array  # the step length (0 where it did not move)
    beta: jax.Array  # the direction update's coefficient (0 where it did not move)


def _step(krylov: _Krylov, state: _CGState,
          runs: jax.Array | bool = True) -> tuple[_CGState, _StepInfo]:
    """One PCG iteration; returns the new state and whether it moved ``x`` (with the step's
    coefficients, which the unrolled scan's derivative check reads).

    ``runs`` false: a step taken as CG takes a frozen one (a zero step length, ``p`` and
    ``r.z`` kept, no breakdown), so the state passes through unchanged to round-off (``d +
    0 p``) and its derivatives through exactly.
    """
    q = krylov.product(state.p)
    pq = jnp.vdot(state.p, q)
    active = _active(state) & runs
    moving = active & (pq > 0)
    alpha = _safe_ratio(state.rz, pq, moving)
    dr = _update(state.dr, alpha, state.p, q)
    r = dr[1]
    if krylov.precond is None and not isinstance(dr, tuple) and r.size > _ROW_REDUCTION_FROM:
        z, rz_new = r, jnp.sum(dr * dr, axis=1)[1]  # a row reduction: no copy of the slice r
    else:
        z = krylov.precondition(r)
        rz_new = jnp.vdot(r, z)
    beta = _safe_ratio(rz_new, state.rz, moving)
    p = jnp.where(moving, z + beta * state.p, state.p)
    rz_new = jnp.where(moving, rz_new, state.rz)
    broken = state.broken | (active & ~moving)
    return _CGState(dr, p, rz_new, state.freeze_level, broken), _StepInfo(moving, alpha, beta)


def _update(dr, alpha: jax.Array, p: jax.Array, q: jax.Array):
    """``[d, r] += alpha [p, -q]``, on a pair or on the stacked ``(2, n)`` array."""
    if isinstance(dr, tuple):
        return dr[0] + alpha * p, dr[1] - alpha * q
    return dr + alpha * jnp.stack([p, -q])


def _step_preconditioning_first(krylov: _Krylov, state: _CGState,
                                first: jax.Array) -> tuple[_CGState, jax.Array]:
    """One PCG iteration that preconditions the residual it starts from.

    The same operations as :func:`_step`, rotated: iteration ``k`` forms ``z_{k-1} = M
    r_{k-1}``, ``beta`` and ``p_{k-1}``, then steps; the state keeps ``p_{k-1}`` and
    ``r_{k-1}.z_{k-1}``, and ``first`` (the first iteration, traced) sets the freeze level
    from ``r0.z0``. A solve of ``K`` iterations applies ``M`` ``K`` times instead of ``K + 1``
    (the last ``z_K`` fed only the freeze test of an iteration that never runs), and the
    program holds one inlined copy of ``M`` per loop instead of two: with an AMG V-cycle, the
    copies before the loops were 13-24 % of an L-BFGS step's compile. The while
    loops use it whenever there is a preconditioner to apply; a loop that reaches the freeze
    level learns so one iteration later (a non-moving trip, not counted). The unrolled scan
    keeps :func:`_step`: its final test (frozen before ``K``: differentiate implicitly)
    reads ``r_K.z_K``.
    """
    r = state.r
    z = krylov.precondition(r)
    rz = jnp.vdot(r, z)
    freeze_level = jnp.where(first, _freeze_level(rz), state.freeze_level)
    active = rz > freeze_level
    beta = _safe_ratio(rz, state.rz, ~first)
    p = z + beta * state.p
    q = krylov.product(p)
    pq = jnp.vdot(p, q)
    moving = active & (pq > 0)
    alpha = _safe_ratio(rz, pq, moving)
    dr = _update(state.dr, alpha, p, q)
    broken = state.broken | (active & ~moving)
    return _CGState(dr, jnp.where(moving, p, state.p), jnp.where(moving, rz, state.rz),
                    freeze_level, broken), moving


def _solver_status(broken: jax.Array, not_converged: jax.Array) -> jax.Array:
    status = jnp.where(not_converged, Status.NOT_CONVERGED, Status.SUCCESS)
    return jax.lax.stop_gradient(jnp.where(broken, Status.BREAKDOWN, status).astype(jnp.int32))


# --------------------------------------------------------------------------------------
# unrolled: a fixed-length scan, differentiated by JAX
# --------------------------------------------------------------------------------------


# Unrolled mode differentiates the K-iteration map implicitly, as the solution map, once the
# relative (preconditioned) residual sqrt(r.z / r0.z0) is below sqrt(eps) of the working dtype
# (_solution_map_rtol): the map then equals the solution map to half the working precision,
# while reverse and forward mode through the last
# iterations lose digits to round-off as the residual falls (the P1 Laplacian, 4,096 unknowns,
# b = 1: 2e-5 relative at a residual of 3e-11, 4e-4 at 3e-12, 5 % at 5e-13, each against
# settled finite differences, which equal the solution map's derivative there)
def _solution_map_rtol(dtype) -> float:
    return float(np.sqrt(np.finfo(dtype).eps))


# The unrolled derivative is flagged (Status.UNRELIABLE_DERIVATIVE) once the frozen CG
# polynomial amplifies some part of the spectrum by more than 1 / sqrt(eps) (see
# _amplification):
# round-off is then amplified past half the working precision, and the exact derivative of the
# K-iteration map is that large in some direction, so the map is linear only on scales far
# below any useful step

# points of [0, mu_max] at which the residual polynomial is evaluated
_SPECTRUM_POINTS = 257


def _unrolled(matrix, precond, b, x0, iterations, checkpoint: bool | int,
              scan_length: int | None = None) -> Solution:
    krylov = _krylov(matrix, precond)
    start = _init(krylov, b, x0, stacked=False)

    def iterate(state, runs=True):
        new, info = _step(krylov, state, runs)
        return new, (info, krylov.residual_norm(new.r))

    if scan_length is None:
        length = iterations
        state, (steps, norms) = _scan_iterations(lambda carry, _: iterate(carry), start.state,
                                                 length, segment_length(length, checkpoint))
    else:
        length = scan_length
        state, (steps, norms) = _bounded_iterations(iterate, start.state, iterations, length,
                                                    segment_length(length, checkpoint))
    history = jax.lax.stop_gradient(jnp.concatenate(
        [start.r0_norm[None], start.r0_scale * norms]))
    if scan_length is not None:  # past K: the final norm, as the skipped steps held it
        ran = jnp.clip(iterations, 0, length)
        history = jnp.where(jnp.arange(length + 1) <= ran, history, history[ran])
    x = _solution(krylov, start, state.d)
    # converged (to half precision, or frozen at round-off) before K: the K-iteration map is
    # the solution map to that accuracy, but reverse and forward mode through the last
    # iterations return the derivative of Krylov iterates whose coefficients are ruled by
    # round-off (and through frozen iterations, that of the last moving iterate, which lags
    # the exact one): differentiate implicitly there
    converged = jax.lax.stop_gradient(_settled(state) & ~state.broken)
    x = jax.lax.cond(converged, lambda: _as_solution_map(x, matrix, precond, b), lambda: x)
    status = _solver_status(state.broken, jnp.asarray(False))
    amplification = _amplification(jax.lax.stop_gradient(steps),
                                   _spectrum_bound(matrix, krylov, steps))
    unreliable = ~converged & (amplification > 1.0 / _solution_map_rtol(state.rz.dtype))
    status = jnp.where(unreliable & (status == Status.SUCCESS), Status.UNRELIABLE_DERIVATIVE,
                       status).astype(jnp.int32)
    return Solution(x, jnp.sum(steps.moving).astype(jnp.int32), history[-1],
                    jax.lax.stop_gradient(start.r0_norm), history, status)


def _settled(state: _CGState) -> jax.Array:
    """``r.z <= rtol^2 r0.z0`` with ``rtol = sqrt(eps)`` (frozen states included)."""
    rz0 = state.freeze_level / jnp.square(jnp.finfo(state.rz.dtype).eps)
    return state.rz <= jnp.square(_solution_map_rtol(state.rz.dtype)) * rz0


def _spectrum_bound(matrix: SparseMatrix, krylov: _Krylov, steps: _StepInfo) -> jax.Array:
    """An upper bound of the spectrum of the operator CG runs on.

    Without a preconditioner to apply (identity, or Jacobi as the scaled ``S A S``): the
    Gershgorin bound ``max_i sum_j |a_ij| s_i s_j``, one pass over the entries. With one (AMG,
    a projected nullspace), whose spectrum cannot be bounded from the entries, the Gershgorin
    bound of the Lanczos matrix ``T_K`` that CG built (its step coefficients): an estimate
    from the part of the spectrum CG has seen.
    """
    steps = jax.lax.stop_gradient(steps)
    if krylov.precond is None:
        values = jnp.abs(jax.lax.stop_gradient(matrix.values))
        scale = jnp.ones(matrix.shape[0], values.dtype) if krylov.scale is None \
            else jax.lax.stop_gradient(krylov.scale)
        sums = jax.ops.segment_sum(values * scale[matrix.cols], matrix.rows,
                                   num_segments=matrix.shape[0]) * scale
        return jnp.max(sums, initial=0.0)
    # T_K of CG: diagonal 1/alpha_k + beta_{k-1}/alpha_{k-1}, off-diagonal sqrt(beta_k)/alpha_k
    moving, alpha, beta = steps
    inverse_alpha = _safe_ratio(jnp.ones_like(alpha), alpha, moving)
    carried = jnp.concatenate([jnp.zeros(1, alpha.dtype), (beta * inverse_alpha)[:-1]])
    off = jnp.sqrt(jnp.maximum(beta, 0.0)) * inverse_alpha
    off_before = jnp.concatenate([jnp.zeros(1, alpha.dtype), off[:-1]])
    rows = jnp.where(moving, inverse_alpha + carried + off + off_before, 0.0)
    return jnp.max(rows, initial=0.0)


def _amplification(steps: _StepInfo, bound: jax.Array) -> jax.Array:
    """``max |R_K(mu)|`` over ``mu`` in ``[0, bound]``: the CG residual polynomial's size.

    PCG's error is ``R_K(MA) e0``, with ``R_0 = P_0 = 1``, ``R_{k+1} = R_k - alpha_k mu P_k``
    and ``P_{k+1} = R_{k+1} + beta_k P_k``. The derivative of ``x_K`` holds the frozen map
    ``(1 - R_K(MA)) A^{-1}``: where the data has (next to) no weight on part of the spectrum,
    CG's polynomial is fitted to the rest and grows there by orders of magnitude, and so do
    the derivative's directions that reach that part, and round-off in them. Both values
    are rescaled every step (their logarithm is summed), so that no growth overflows.
    """
    mu = jnp.linspace(0.0, 1.0, _SPECTRUM_POINTS, dtype=steps.alpha.dtype) * bound

    def body(carry, step):
        residual, direction, log_size = carry
        moving, alpha, beta = step
        new_residual = residual - alpha * mu * direction
        new_direction = new_residual + beta * direction
        residual = jnp.where(moving, new_residual, residual)
        direction = jnp.where(moving, new_direction, direction)
        size = jnp.maximum(jnp.max(jnp.abs(residual)), jnp.max(jnp.abs(direction)))
        size = jnp.where(jnp.isfinite(size) & (size > 0), size, 1.0)
        return (residual / size, direction / size, log_size + jnp.log(size)), None

    ones = jnp.ones_like(mu)
    (residual, _, log_size), _ = jax.lax.scan(
        body, (ones, ones, jnp.zeros((), mu.dtype)), steps)
    return jnp.exp(log_size + jnp.log(jnp.max(jnp.abs(residual))))


def unrolled_length(iterations: int, smallest: int = 16) -> int:
    """The scan length for an unrolled ``K`` (``TruncatedCG(scan_length=...)``): the
    smallest power of two ``>= K``, at least ``smallest``.

    A refinement schedule's counts share a few lengths (K = 10, 20, ..., 60: 16, 32, 64), so
    an unrolled run compiles once per length, not once per ``K`` (a compile took 3-4 s on the
    ``inclusion`` scene), for at most twice the ``K`` iterations' time and memory.

    >>> [unrolled_length(k) for k in (0, 10, 16, 17, 60, 600)]
    [16, 16, 16, 32, 64, 1024]
    """
    check_count(iterations, "iterations")
    return max(int(smallest), 1 << max(int(iterations) - 1, 0).bit_length())


def _bounded_iterations(iterate, state, iterations, length: int, segment: int | None):
    """``length`` scan steps of which the first ``iterations`` (traced) apply ``iterate``;
    the rest take the step as CG takes a frozen one, ``iterate(state, runs=False)``, and keep
    the state they were given (outputs: not moving, a zero norm).

    Neither branched nor masked: with the step under a ``lax.cond``, reverse mode saved the
    operator's arrays once per step (the cond's residuals are not recognised as the loop
    invariants they are) and an iteration took 3x the time even where none was skipped; a
    select of the whole state after the step cost the forward and reverse sweeps a pass over
    each of its vectors.
    """
    def body(carry, _):
        current, k = carry
        runs = k < iterations
        new, (moving, norm) = iterate(current, runs)
        return (new, k + 1), (moving, jnp.where(runs, norm, 0.0))

    (state, _), outputs = _scan_iterations(body, (state, jnp.asarray(0, jnp.int32)), length,
                                           segment)
    return state, outputs


def segment_length(iterations: int, checkpoint: bool | int) -> int | None:
    """Iterations per checkpointed segment for ``TruncatedCG(iterations, checkpoint=...)``.

    ``False``: ``None`` (no checkpointing); ``True``: ``s = ceil(sqrt(K))`` (at least 1), which
    makes the stored carries (``K / s``) and one segment's recomputed iterations (``s``) grow
    alike, ``O(sqrt(K))`` n-vectors in all; an integer: that segment length.
    """
    if checkpoint is False:
        return None
    if checkpoint is True:
        return math.isqrt(iterations - 1) + 1 if iterations > 1 else 1
    return int(checkpoint)


def _scan_iterations(body, state, iterations: int, segment: int | None):
    """``iterations`` applications of the scan body ``body``, per-iteration outputs stacked.

    ``segment=None`` is one plain scan. Otherwise ``K = m s + t`` (``0 <= t < s``): an outer
    scan over ``m`` segments, each an inner scan of ``s`` iterations under ``jax.checkpoint``,
    then a plain scan of the ``t`` left over. Reverse mode then keeps the carry at the ``m``
    segment starts and, while it sweeps one segment backward, the intermediates of that
    segment's ``s`` iterations, recomputed from its stored carry: about ``m c + s R`` n-vectors
    instead of the plain scan's ``K R`` (``c`` n-vectors in the carry, ``R`` saved by one
    iteration; ``s = sqrt(K)`` gives ``O(sqrt(K))``), at the price of one more forward sweep.
    The operations and their order are those of the plain scan: the same ``K``-iteration map.
    """
    if segment is None:
        return jax.lax.scan(body, state, None, length=iterations)
    segments, left_over = divmod(iterations, segment)

    # prevent_cse=False: the outer scan already keeps XLA from merging the recomputation
    # with the forward sweep, and the barriers would only cost time
    @partial(jax.checkpoint, prevent_cse=False)
    def run_segment(carry, _):
        return jax.lax.scan(body, carry, None, length=segment)

    state, per_segment = jax.lax.scan(run_segment, state, None, length=segments)
    state, tail = jax.lax.scan(body, state, None, length=left_over)
    outputs = jax.tree_util.tree_map(
        lambda stacked, rest: jnp.concatenate([stacked.reshape(-1, *rest.shape[1:]), rest]),
        per_segment, tail)
    return state, outputs


# the tangent (and adjoint) solve of a converged unrolled solve: to the reference tolerance of
# ConvergedCG, within as many iterations as its default allows
_SOLUTION_MAP_TANGENT_RTOL = 1e-12


def _as_solution_map(x, matrix, precond, b) -> jax.Array:
    """``x``, a converged solve, differentiated as the solution map ``A^+ b``.

    The value is the iterate itself (the solution to the accuracy it converged to), so the
    forward sweep runs no second solve; the derivatives are the implicit ones of
    :func:`_frozen_jvp`, the tangent (reverse mode: the adjoint) solved by PCG to a relative
    residual of ``1e-12`` (at most ``10 n`` iterations, as :class:`ConvergedCG`) with the
    preconditioner held constant. A cap of ``K`` iterations, as the scan took, left a rough
    tangent direction unconverged (forward mode 2.5 % off on the P1 Laplacian at K = 90).
    """
    precond = jax.tree_util.tree_map(jax.lax.stop_gradient, precond)
    pattern, form = _pattern_and_form(matrix)
    return _frozen(x, matrix.values, b, pattern, precond, form)


@partial(jax.custom_jvp, nondiff_argnums=(5,))
def _frozen(x, values, b, pattern, precond, form):
    return x


@_frozen.defjvp
def _frozen_jvp(form, primals, tangents):
    """``dx = A^+ (db - dA x)``: the tangent of ``A x = b``, by :func:`_implicit_tangent`.

    ``x``'s own tangent (the sweep through the converged scan: the derivative of the last
    Krylov iterates, ruled by round-off) is dropped. The primal is this function called again,
    so a derivative of this derivative sees the implicit tangent of ``x`` too.
    """
    x, values, b, pattern, precond = primals
    values_dot, b_dot = tangents[1], tangents[2]
    x = _frozen(x, values, b, pattern, precond, form)
    tolerances = jnp.asarray([_SOLUTION_MAP_TANGENT_RTOL, 0.0], b.dtype)
    x_dot = _implicit_tangent(values, values_dot, b_dot, x, 10 * b.shape[-1], pattern, precond,
                              tolerances, form, True, None)
    return x, x_dot


@partial(jax.custom_jvp, nondiff_argnums=(2,))
def adjoint_tap(x, iterations, counter):
    """Identity on ``x`` whose transpose (the backward pass) counts the reversed scan.

    A ``custom_jvp`` whose tangent is the identity written as a ``custom_linear_solve``: its
    forward solve is the identity (forward mode through the scan runs no extra sweep, so it
    counts nothing) and its transpose solve taps ``counter``. Unlike a ``custom_vjp`` it lets
    forward mode (``jax.jvp``, Gauss-Newton products) through.
    """
    return x


@adjoint_tap.defjvp
def _adjoint_tap_jvp(counter, primals, tangents):
    x, iterations = primals

    def count_backward(_, cotangent):
        tap(counter, "adjoint", iterations, cotangent)
        return cotangent

    x_dot = jax.lax.custom_linear_solve(lambda v: v, tangents[0], lambda _, v: v,
                                        count_backward)
    return adjoint_tap(x, iterations, counter), x_dot


# --------------------------------------------------------------------------------------
# implicit: while loop forward, truncated tangent / adjoint solves for the derivatives
# --------------------------------------------------------------------------------------


def _while_solve(krylov: _Krylov, b, x0, max_iterations, tolerances, history_size: int, *,
                 track_norm: bool) -> Solution:
    """PCG while ``k < max_iterations``, still moving and ``||r|| > max(rtol ||b||, atol)``.

    ``track_norm`` (static): compute ``||r||`` every iteration, for a tolerance or a history;
    without it (zero tolerances, a truncated solve) the loop stops on ``r.z`` alone and the
    norm is taken once at the end -- a reduction pass less per iteration.
    """
    preconditioning_first = krylov.precond is not None
    start = _init(krylov, b, x0, stacked=_stacks(krylov, b.shape[-1]),
                  precondition=not preconditioning_first)
    # max(rtol ||b||, atol) / r0_scale with numerator and denominator scaled by 2^-e: the same
    # bits as unscaled, but rtol ||b|| cannot flush to 0 (below about 1e-298; XLA's CPU code
    # flushes subnormals), where it stopped nothing. The scalings are ldexp, from the bits:
    # written as divisions, XLA reassociated them back into rtol ||b|| under jit.
    exponent = _scale_exponent(b)
    b_norm = _norm(b * _power_of_two(-exponent, b.dtype))  # ||b|| 2^-e
    target = jnp.maximum(tolerances[0] * b_norm, jnp.ldexp(tolerances[1], -exponent)) \
        / jnp.ldexp(start.r0_scale, -exponent)
    positions = jnp.arange(history_size + 1)

    def cond(carry):
        k, st, norm, _, moved = carry
        return (k < max_iterations) & moved & _active(st) & (norm > target)

    def body(carry):
        k, st, norm, hist, _ = carry
        if preconditioning_first:
            new, moving = _step_preconditioning_first(krylov, st, k == 0)
        else:
            new, moving = _step(krylov, st)
            moving = moving.moving
        if track_norm:
            norm = krylov.residual_norm(new.r)
            hist = jnp.where(positions > k, norm, hist)  # pads the tail with the latest value
        return k + moving.astype(k.dtype), new, norm, hist, moving

    unit_norm = start.r0_norm / start.r0_scale
    init = (jnp.zeros((), jnp.int32), start.state, unit_norm,
            jnp.full(history_size + 1, unit_norm),
            jnp.asarray(True))
    k, state, norm, history, _ = jax.lax.while_loop(cond, body, init)
    if not track_norm:
        norm = krylov.residual_norm(state.r)
    # a tolerance was asked for (ConvergedCG) and not met: say so
    not_converged = (target > 0) & (norm > target)
    return Solution(_solution(krylov, start, state.d), k, start.r0_scale * norm, start.r0_norm,
                    start.r0_scale * history, _solver_status(state.broken, not_converged))


def _implicit_solve(matrix, b, x0, iterations, adjoint_iterations, precond, rtol, atol,
                    history_size, track_norm, counter=None) -> Solution:
    precond = jax.tree_util.tree_map(jax.lax.stop_gradient, precond)
    tolerances = jnp.asarray([rtol, atol], dtype=b.dtype)
    pattern, form = _pattern_and_form(matrix)
    # a reverse tally's seed is an input to differentiate (its tangent carries the adjoint
    # count back); a host counter is not
    # (and its adjoint start, whose cotangent carries the adjoint solution back)
    seed = counter.seed if isinstance(counter, ReverseTally) else None
    adjoint_start = counter.adjoint_start if isinstance(counter, ReverseTally) else None
    host = None if isinstance(counter, ReverseTally) else counter
    sol = _implicit_core(matrix.values, b, x0, jnp.asarray(iterations, jnp.int32),
                         jnp.asarray(adjoint_iterations, jnp.int32), pattern, precond,
                         tolerances, seed, adjoint_start, form, history_size, track_norm, host)
    diagnostics = jax.lax.stop_gradient(sol[1:])  # as in unrolled mode: not differentiated
    return Solution(sol.x, *diagnostics)


def _pattern_and_form(matrix: SparseMatrix) -> tuple[tuple, tuple]:
    """``matrix`` less its values: the index arrays (traced) and the static shape and kernel,
    as the custom rules take them (:func:`_pattern_matrix` puts them back together)."""
    return (matrix.rows, matrix.cols, matrix.layout), (matrix.shape, matrix.kernel)


def _pattern_matrix(values, pattern, form) -> SparseMatrix:
    (rows, cols, layout), (shape, kernel) = pattern, form  # form: static (shape, kernel)
    return SparseMatrix(rows, cols, values, shape, layout, kernel)


@partial(jax.custom_jvp, nondiff_argnums=(10, 11, 12, 13))
def _implicit_core(values, b, x0, iterations, adjoint_iterations, pattern, precond, tolerances,
                   seed, adjoint_start, form, history_size, track_norm, counter):
    """The truncated solve; derivatives by :func:`_implicit_jvp` (any order, both modes)."""
    krylov = _krylov(_pattern_matrix(values, pattern, form), precond)
    return _while_solve(krylov, b, x0, iterations, tolerances, history_size,
                        track_norm=track_norm)


def _implicit_jvp(form, history_size, track_norm, counter, primals, tangents):
    """``dx = A^{-1} (db - dA x)`` by ``lax.custom_linear_solve`` with ``K_adj`` iterations.

    Differentiating ``A x = b`` gives ``A dx = db - dA x``. The tangent system is solved by
    the same truncated PCG as the adjoint (``adjoint_iterations``, the forward sweep's
    tolerances), on a :class:`_Krylov` prepared from the same operator and preconditioner, and
    ``custom_linear_solve`` supplies the rest: reverse mode transposes the tangent map, which
    turns its solve into the adjoint solve ``A lambda = x_bar`` (``A`` symmetric) and the
    ``-dA x`` term into ``values_bar[k] = -lambda[row_k] x[col_k]``; higher orders
    differentiate the tangent and adjoint solves in turn. ``x0`` gets no derivative: at
    convergence ``x`` does not depend on it. The primal is this function called again, so a
    derivative of a derivative (``jax.jvp(jax.grad(f))``) sees the tangent of ``x`` too.

    ``seed`` and ``adjoint_start`` are a :class:`~prdp_fem.linalg.ReverseTally`'s (or
    ``None``): where the seed is differentiated, the adjoint solve adds its count to the
    seed's cotangent; it starts from ``adjoint_start``, and where that is differentiated its
    solution is the start's cotangent (the next evaluation's warm start).
    """
    (values, b, x0, iterations, adjoint_iterations, pattern, precond, tolerances, seed,
     adjoint_start) = primals
    values_dot, b_dot = live_tangent(tangents[0]), live_tangent(tangents[1])
    sol = _implicit_core(values, b, x0, iterations, adjoint_iterations, pattern, precond,
                         tolerances, seed, adjoint_start, form, history_size, track_norm,
                         counter)
    zeros = tuple(_zero_tangent(leaf) for leaf in sol[1:])
    if values_dot is None and b_dot is None:  # only the seed (or x0) is differentiated
        return sol, Solution(jnp.zeros_like(sol.x), *zeros)
    x_dot = _implicit_tangent(values, values_dot, b_dot, sol.x, adjoint_iterations, pattern,
                              precond, tolerances, form, track_norm, counter,
                              live_tangent(tangents[8]), adjoint_start,
                              live_tangent(tangents[9]))
    return sol, Solution(x_dot, *zeros)


_implicit_core.defjvp(_implicit_jvp, symbolic_zeros=True)


def _implicit_tangent(values, values_dot, b_dot, x, iterations, pattern, precond, tolerances,
                      form, track_norm, counter, seed_dot=None, adjoint_start=None,
                      start_dot=None) -> jax.Array:
    """``A^+ (db - dA x)``, the tangent of ``A x = b``, by :func:`_linear_solve` (``None``:
    a zero ``values_dot`` or ``b_dot``, not both)."""
    rows, cols, _ = pattern
    rhs = b_dot
    if values_dot is not None:
        # -dA x: the tangent of the product with x held fixed (values enter linearly)
        minus_dA_x = -jax.ops.segment_sum(values_dot * x[cols], rows, num_segments=x.shape[0],
                                          indices_are_sorted=True)
        rhs = minus_dA_x if rhs is None else rhs + minus_dA_x
    return _linear_solve(values, rhs, iterations, pattern, precond, tolerances, form,
                         track_norm, counter, seed_dot, adjoint_start, start_dot)


def _linear_solve(values, rhs, iterations, pattern, precond, tolerances, form, track_norm,
                  counter, seed_dot=None, adjoint_start=None, start_dot=None) -> jax.Array:
    """``A^{-1} rhs`` by ``iterations`` PCG sweeps, with exact linear-solve derivatives.

    ``lax.custom_linear_solve`` with ``symmetric=True``: the transpose solve is the same sweep,
    every sweep taps ``counter`` as an adjoint solve (tangent and adjoint solves alike), and
    ``A``'s dependence on ``values`` is differentiated through its product, so this map can be
    differentiated again. With ``seed_dot`` (a reverse tally's seed tangent) the adjoint solve
    counts into the seed instead (:func:`~prdp_fem.linalg._tally.counted_linear_solve`).
    The transpose solve starts from ``adjoint_start`` (zero where ``None``); with
    ``start_dot`` its solution leaves as the start's cotangent.
    """
    matrix = _pattern_matrix(values, pattern, form)
    # the solver is a fixed linear map: its arrays get no derivative (custom_linear_solve
    # ignores them anyway; stopping them keeps the solve's inputs out of the tangent trace)
    krylov = _krylov(jax.lax.stop_gradient(matrix), precond)

    def sweep(right, start=None):
        sol = _while_solve(krylov, right, start, iterations, tolerances, 0,
                           track_norm=track_norm)
        return sol.x, sol.iterations

    if adjoint_start is None:
        return counted_linear_solve(prepare(matrix), rhs, sweep, sweep, counter, seed_dot,
                                    symmetric=True, start_dot=start_dot)
    # the guess of the adjoint solve only: a tangent solve (forward mode) starts from zero
    start = jax.lax.stop_gradient(adjoint_start)
    return counted_linear_solve(prepare(matrix), rhs, sweep, partial(sweep, start=start),
                                counter, seed_dot, start_dot=start_dot)


def _zero_tangent(leaf: jax.Array) -> jax.Array:
    """A zero tangent for a diagnostic (``float0`` for integers, as JAX requires)."""
    if jnp.issubdtype(leaf.dtype, jnp.inexact):
        return jnp.zeros_like(leaf)
    return np.zeros(leaf.shape, dtype=jax.dtypes.float0)
