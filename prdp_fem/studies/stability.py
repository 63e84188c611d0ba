r"""The stability suite: every extreme case through every solver path, checked and tabulated.

For each :class:`~prdp_fem.studies.stability_cases.StabilityCase`, :func:`run_case`

1. estimates the condition numbers :math:`\kappa(A)` and :math:`\kappa(D^{-1}A)` from the
   Lanczos tridiagonal of CG (:mod:`prdp_fem.studies.conditioning`);
2. counts the iterations to ``rtol = 1e-8`` with the identity and Jacobi preconditioners (and
   pyamg's smoothed aggregation as a reference: prdp_fem has no AMG preconditioner yet);
3. solves to convergence (``ConvergedCG``) and with ``K = 10 n`` truncated PCG in both gradient
   modes, and compares each with a direct solve in float64 (SuperLU; bordered for a
   nullspace) in the relative energy norm :math:`\|x - x_*\|_A / \|x_*\|_A`;
4. sweeps ``K = 0, 1, 2, 4, ..., 10 n`` and checks that the energy-norm error never grows
   (CG minimises it over a growing Krylov space) beyond a round-off floor;
5. differentiates :math:`J = \tfrac12 \|x_K(\kappa)\|^2` with respect to ``kappa`` in both
   gradient modes at ``K = 0, 1, 10 n`` and counts non-finite entries.

Tolerances scale with the Jacobi-scaled condition estimate ``c`` and the working precision
``eps``: a converged result must agree within ``tolerance = 1e-10 + 100 c eps`` (float64
reaches far below that; see the README's table). Where ``c eps > 1e-3`` nothing better than a
few digits can be promised: a miss there is *flagged* ("not trusted"), not failed. NaN/Inf in
any solution or gradient is always a failure, as is a miss a well-conditioned case should not
have.

The ``K`` sweep, for ``n = 36`` free dofs:

>>> _sweep_counts(36).tolist()
[0, 1, 2, 4, 8, 16, 32, 64, 128, 256, 360]
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from .._atomic import atomic_path
from ..errors import PrdpFemError
from ..fem.reference import amg_solve, direct_solve
from ..fem.system import LinearSystem
from ..linalg.cg import ConvergedCG, Status, TruncatedCG, solve
from ..linalg.operator import SparseMatrix
from .conditioning import condition_estimate
from .stability_cases import CASES, CaseProblem, StabilityCase

__all__ = ["CaseResult", "format_markdown", "run_case", "run_suite", "suite_passed",
           "write_csv"]

ITERATIONS_RTOL = 1e-8  # the table's "iterations to 1e-8"
UNTRUSTED = 1e-3  # c * eps above this: a few digits at best, misses are flagged not failed
COLUMNS = ("case", "group", "dofs", "dtype", "cond_A", "cond_jacobi", "its_identity",
           "its_jacobi", "its_pyamg", "error", "tolerance", "nonfinite", "gradients_finite",
           "monotone", "verdict", "note", "seconds")


class CaseResult(NamedTuple):
    """One row of the report (see :data:`COLUMNS`); ``its_*`` is ``-1`` when not reached."""

    case: str
    group: str
    dofs: int
    dtype: str
    cond_A: float
    cond_jacobi: float
    its_identity: int
    its_jacobi: int
    its_pyamg: int
    error: float
    tolerance: float
    nonfinite: int
    gradients_finite: bool
    monotone: bool
    verdict: str  # "ok", "flagged" (stated limit) or "FAIL"
    note: str
    seconds: float


class _Setup(NamedTuple):
    """A case's problem, in the working precision, with its float64 reference."""

    system: LinearSystem
    kappa: jax.Array
    source: jax.Array
    dtype: jnp.dtype
    matrix: sp.csr_matrix  # float64
    rhs: np.ndarray  # float64
    reference: np.ndarray
    nullspace: np.ndarray | None


def run_suite(cases: Sequence[StabilityCase] = CASES,
              progress: Callable[[StabilityCase], None] | None = None) -> list[CaseResult]:
    """Run ``cases`` in order (``progress(case)`` before each)."""
    results = []
    for case in cases:
        if progress is not None:
            progress(case)
        results.append(run_case(case))
    return results


def suite_passed(results: Iterable[CaseResult]) -> bool:
    """No NaN/Inf anywhere and no unflagged failure."""
    return all(r.nonfinite == 0 and r.verdict != "FAIL" for r in results)


def run_case(case: StabilityCase) -> CaseResult:
    """Run every check on one case (see the module docstring)."""
    start = time.perf_counter()
    setup = _setup(case.build(), case.dtype)
    if case.expected_error is not None:
        return _expected_error_row(case, setup, start)
    n = setup.matrix.shape[0]
    eps = float(jnp.finfo(setup.dtype).eps)
    cond_A = condition_estimate(setup.matrix, preconditioner="identity",
                                nullspace=setup.nullspace).condition
    cond_J = condition_estimate(setup.matrix, nullspace=setup.nullspace).condition
    tolerance = 1e-10 + 100.0 * cond_J * eps
    trusted = cond_J * eps <= UNTRUSTED
    A, b = _operator(setup), _rhs(setup)

    its = {p: _iterations_to(A, b, p, setup) for p in ("identity", "jacobi")}
    its_pyamg = _pyamg_iterations(setup)
    converged_rtol = max(1e-12, 100.0 * eps)
    solutions = {  # the Jacobi-preconditioned paths, held to the Jacobi-scaled tolerance
        "converged jacobi": solve(A, b, ConvergedCG(rtol=converged_rtol),
                                  nullspace=_null(setup)),
        "K=10n unrolled": solve(A, b, TruncatedCG(10 * n), nullspace=_null(setup)),
        "K=10n implicit": solve(A, b, TruncatedCG(10 * n, gradient="implicit"),
                                nullspace=_null(setup)),
    }
    plain = solve(A, b, ConvergedCG(rtol=converged_rtol, preconditioner="identity"),
                  nullspace=_null(setup))
    errors = {name: _energy_error(setup, sol.x) for name, sol in solutions.items()}
    nonfinite = sum(int((~np.isfinite(np.asarray(sol.x))).sum())
                    for sol in (*solutions.values(), plain))
    breakdowns = [name for name, sol in (*solutions.items(), ("converged identity", plain))
                  if int(sol.status) == Status.BREAKDOWN]

    sweep_errors, sweep_nonfinite = _sweep(A, b, setup)
    monotone = _monotone(sweep_errors, floor=max(2.0 * min(errors.values()), 10.0 * eps))
    gradient_nonfinite = _gradient_nonfinite(setup)

    error = max(errors.values()) if all(np.isfinite(list(errors.values()))) else math.inf
    # (problem, excused): a limit of the precision or the conditioning is flagged, not failed
    problems = []
    if error > tolerance:
        worst = max(errors, key=errors.get)
        problems.append((f"{worst} error {error:.1e} > tolerance", not trusted))
    problems.extend(_identity_problems(setup, plain, cond_A, eps))
    if not monotone:
        problems.append(("energy error grew with K", not trusted))
    if breakdowns:
        problems.append(("breakdown in " + ", ".join(breakdowns), not trusted))
    if its["jacobi"] < 0:
        below_round_off = ITERATIONS_RTOL < 100.0 * eps
        problems.append((f"rtol {ITERATIONS_RTOL:g} is below {case.dtype} round-off"
                         if below_round_off else f"jacobi did not reach rtol {ITERATIONS_RTOL:g}",
                         below_round_off or not trusted))
    verdict, note = _verdict(problems, nonfinite + sweep_nonfinite + gradient_nonfinite,
                             cond_J * eps)
    return CaseResult(case.name, case.group, n, case.dtype, cond_A, cond_J, its["identity"],
                      its["jacobi"], its_pyamg, error, tolerance,
                      nonfinite + sweep_nonfinite + gradient_nonfinite,
                      gradient_nonfinite == 0, monotone, verdict, note,
                      time.perf_counter() - start)


def _identity_problems(setup: _Setup, plain, cond_A: float, eps: float) -> list:
    """Unpreconditioned CG answers to ``cond(A)``, not the Jacobi-scaled condition."""
    trusted = cond_A * eps <= UNTRUSTED
    if int(plain.status) == Status.NOT_CONVERGED:
        # CG's bound: 0.5 sqrt(cond) ln(2 / rtol) iterations; beyond 10 n that is expected
        n = setup.matrix.shape[0]
        expected = 0.5 * math.sqrt(cond_A) * math.log(2.0 / max(1e-12, 100.0 * eps)) > 10 * n
        return [(f"identity PCG not converged in 10 n iterations (cond(A) {cond_A:.1e})",
                 expected or not trusted or setup.dtype != jnp.float64)]
    error = _energy_error(setup, plain.x)
    if error > 1e-10 + 100.0 * cond_A * eps:
        return [(f"converged identity error {error:.1e} > its tolerance", not trusted)]
    return []


def _verdict(problems: list[tuple[str, bool]], nonfinite: int,
             cond_eps: float) -> tuple[str, str]:
    text = "; ".join(message for message, _ in problems)
    if nonfinite:
        return "FAIL", f"{nonfinite} NaN/Inf values; {text}".rstrip("; ")
    if not problems:
        return "ok", ""
    if not all(excused for _, excused in problems):
        return "FAIL", text
    if cond_eps > UNTRUSTED:
        return "flagged", f"cond*eps = {cond_eps:.1e}; {text}"
    return "flagged", text


# --------------------------------------------------------------------------------------
# set-up: working precision and the float64 reference
# --------------------------------------------------------------------------------------


def _setup(problem: CaseProblem, dtype: str) -> _Setup:
    disc = problem.disc
    matrix = disc.stiffness_matrix(problem.kappa)
    rhs = disc.rhs(problem.kappa, problem.source)
    nullspace = disc.nullspace
    reference = direct_solve(matrix, rhs, nullspace=nullspace).x
    return _Setup(disc.system, jnp.asarray(problem.kappa), jnp.asarray(problem.source),
                  jnp.dtype(dtype), matrix, rhs, reference, nullspace)


def _operator(setup: _Setup, kappa: jax.Array | None = None) -> SparseMatrix:
    """``A(kappa)`` assembled in float64, then rounded to the working precision."""
    return setup.system.operator(setup.kappa if kappa is None else kappa).astype(setup.dtype)


def _rhs(setup: _Setup, kappa: jax.Array | None = None) -> jax.Array:
    b = setup.system.rhs(setup.kappa if kappa is None else kappa, setup.source)
    return b.astype(setup.dtype)


def _null(setup: _Setup) -> jax.Array | None:
    return None if setup.nullspace is None else jnp.asarray(setup.nullspace, setup.dtype)


def _energy_error(setup: _Setup, x: jax.Array) -> float:
    e = np.asarray(x, dtype=float) - setup.reference
    ref = setup.reference
    return float(np.sqrt(abs(e @ (setup.matrix @ e)) / (ref @ (setup.matrix @ ref))))


# --------------------------------------------------------------------------------------
# the checks
# --------------------------------------------------------------------------------------


def _iterations_to(A, b, preconditioner: str, setup: _Setup) -> int:
    solver = ConvergedCG(rtol=ITERATIONS_RTOL, preconditioner=preconditioner)
    sol = solve(A, b, solver, nullspace=_null(setup))
    return int(sol.iterations) if int(sol.status) == Status.SUCCESS else -1


def _pyamg_iterations(setup: _Setup) -> int:
    if setup.nullspace is not None:
        return -1  # pyamg's reference solver is not set up for a singular operator here
    limit = 500
    result = amg_solve(setup.matrix, setup.rhs, rtol=ITERATIONS_RTOL, max_iterations=limit)
    return result.iterations if result.iterations < limit else -1


def _sweep_counts(n: int) -> np.ndarray:
    counts = [0] + [2 ** j for j in range(int(math.log2(10 * n)) + 1)] + [10 * n]
    return np.unique(np.asarray(counts, dtype=np.int32))


def _sweep(A, b, setup: _Setup) -> tuple[np.ndarray, int]:
    """Relative energy errors for ``K = 0, 1, 2, 4, ..., 10 n`` (implicit mode: ``K`` traced)."""
    counts = _sweep_counts(A.shape[0])
    null = _null(setup)
    run = jax.jit(jax.vmap(lambda K: solve(A, b, TruncatedCG(K, gradient="implicit"),
                                           nullspace=null).x))
    xs = np.asarray(run(jnp.asarray(counts)))
    nonfinite = int((~np.isfinite(xs)).sum())
    return np.array([_energy_error(setup, x) for x in xs]), nonfinite


def _monotone(errors: np.ndarray, floor: float) -> bool:
    """``e_{j+1} <= e_j`` up to a relative ``1e-6`` and the converged error's floor."""
    return bool(np.all(errors[1:] <= errors[:-1] * (1 + 1e-6) + floor))


def _gradient_nonfinite(setup: _Setup) -> int:
    """NaN/Inf count in ``d/dkappa 0.5 ||x_K||^2``: implicit mode at ``K = 0, 1, 10 n`` (one
    compile, ``K`` traced), unrolled at ``K = 1, 10 n`` (its ``K = 0`` gradient is ``x0``'s)."""
    n = setup.matrix.shape[0]
    null = _null(setup)

    def objective(kappa, solver):
        x = solve(_operator(setup, kappa), _rhs(setup, kappa), solver, nullspace=null).x
        return 0.5 * jnp.sum(x.astype(jnp.float64) ** 2)

    implicit = jax.jit(jax.vmap(jax.grad(lambda kappa, K: objective(
        kappa, TruncatedCG(K, gradient="implicit"))), in_axes=(None, 0)))
    gradients = [implicit(setup.kappa, jnp.asarray([0, 1, 10 * n]))]
    for K in (1, 10 * n):
        unrolled = jax.jit(jax.grad(lambda kappa, K=K: objective(kappa, TruncatedCG(K))))
        gradients.append(unrolled(setup.kappa))
    return sum(int((~np.isfinite(np.asarray(g))).sum()) for g in gradients)


def _expected_error_row(case: StabilityCase, setup: _Setup, start: float) -> CaseResult:
    """The case must raise ``case.expected_error`` eagerly and flag it under ``jit``."""
    A, b = _operator(setup), _rhs(setup)
    n = A.shape[0]
    problems = []
    try:
        solve(A, b, TruncatedCG(10), nullspace=_null(setup))
        problems.append(f"no {case.expected_error.__name__} raised")
    except PrdpFemError as exc:
        if not isinstance(exc, case.expected_error):
            problems.append(f"raised {type(exc).__name__}, expected "
                            f"{case.expected_error.__name__}")
    null = _null(setup)
    flagged = jax.jit(lambda A, b: solve(A, b, ConvergedCG(), nullspace=null))(A, b)
    nonfinite = int((~np.isfinite(np.asarray(flagged.x))).sum())
    if int(flagged.status) != Status.INCOMPATIBLE:
        problems.append(f"status {Status(int(flagged.status)).name} under jit, expected "
                        "INCOMPATIBLE")
    verdict = "FAIL" if problems or nonfinite else "ok"
    note = "; ".join(problems) or (f"refused: {case.expected_error.__name__} eagerly, status "
                                   "INCOMPATIBLE under jit")
    return CaseResult(case.name, case.group, n, case.dtype, math.nan, math.nan, -1, -1, -1,
                      math.nan, math.nan, nonfinite, True, True, verdict, note,
                      time.perf_counter() - start)


# --------------------------------------------------------------------------------------
# the report
# --------------------------------------------------------------------------------------


def _cell(value) -> str:
    if isinstance(value, bool):
        return "yes" if value else "NO"
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.1e}"
    if isinstance(value, int) and value < 0:
        return "-"
    return str(value)


def format_markdown(results: Sequence[CaseResult]) -> str:
    """A Markdown table of ``results`` (``-``: not applicable or not reached)."""
    header = ("case", "dofs", "dtype", "cond(A)", "cond(D^-1 A)", "its identity",
              "its jacobi", "its pyamg", "max error", "tolerance", "NaN/Inf", "grads finite",
              "monotone", "verdict", "note")
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in results:
        cells = (r.case, r.dofs, r.dtype, r.cond_A, r.cond_jacobi, r.its_identity,
                 r.its_jacobi, r.its_pyamg, r.error, r.tolerance, str(r.nonfinite),
                 r.gradients_finite, r.monotone, r.verdict, r.note)
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


def write_csv(results: Sequence[CaseResult], path: str | Path) -> None:
    """All columns of :data:`COLUMNS`, full precision, written atomically."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        for r in results:
            writer.writerow([repr(v) if isinstance(v, float) else v for v in r])
