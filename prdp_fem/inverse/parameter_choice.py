r"""Choosing the regularisation parameter ``alpha``: discrepancy principle and L-curve.

Morozov's discrepancy principle, for data with known noise ``sigma``: pick ``alpha`` with

.. math::

    \|B u(z_\alpha) - d\|_W = \tau\, \delta, \qquad \delta = \sigma \sqrt{\operatorname{tr} W},

found by bracketing in ``log alpha`` (the misfit grows with ``alpha``) and then bisection with
secant steps, each inversion warm-started from the nearest previous one.

The L-curve, when the noise is unknown: sweep ``alpha`` over a grid and take the point of
maximum curvature of ``(log ||B u - d||_W, log R(z))`` (Hansen), measured as the Menger curvature
of consecutive triples.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import numpy as np

from ..errors import DataError, PrdpFemError, SolverConfigError
from ..linalg.cg import ConvergedCG
from .driver import InverseProblem, invert
from .refinement import converged

__all__ = ["AlphaChoice", "l_curve", "morozov"]


class AlphaChoice(NamedTuple):
    alpha: float
    params: np.ndarray                  # z at the chosen alpha
    misfit_norm: float                  # ||B u - d||_W there
    target: float                       # tau delta (Morozov) or NaN (L-curve)
    # (alpha, misfit norm, R, parameter error or NaN) per inversion, in the order run
    trials: tuple[tuple[float, float, float, float], ...]


def _default_solve(problem: InverseProblem, init):
    return invert(problem, refinement=converged(1e-10), steps=200, init=init)


@jax.jit
def _converged_misfit(problem: InverseProblem, z) -> jax.Array:
    return problem.loss(z, ConvergedCG(rtol=1e-10))[1].misfit


def _evaluate(problem, alpha, init, solve) -> tuple[np.ndarray, tuple]:
    """Invert at ``alpha``: the field and ``(alpha, misfit norm, R, parameter error)``."""
    trial = problem.with_alpha(alpha)
    result = solve(trial, init)
    misfit = float(np.sqrt(2.0 * max(float(_converged_misfit(trial, result.params)), 0.0)))
    reg = float(trial.regularizer(trial.field(result.params)))
    return np.asarray(result.field), (alpha, misfit, reg,
                                      float(trial.parameter_error(result.params)))


def morozov(problem: InverseProblem, *, alpha0: float = 1e-6, tau: float = 1.0,
            rtol: float = 0.01, max_inversions: int = 20,
            solve: Callable | None = None) -> AlphaChoice:
    """``alpha`` with ``||B u - d||_W = tau * delta`` to relative tolerance ``rtol``.

    ``solve(problem, init_field) -> Inversion`` runs one inversion (default: L-BFGS, converged
    solves, 200 steps). Raises if the observation carries no noise level.
    """
    for name, value in (("alpha0", alpha0), ("tau", tau), ("rtol", rtol)):
        if not _positive(value):
            raise SolverConfigError(f"morozov: {name}={value!r}: expected a finite number > 0")
    if isinstance(max_inversions, bool) or not isinstance(max_inversions, int) \
            or max_inversions < 1:
        raise SolverConfigError(f"morozov: max_inversions={max_inversions!r}: expected an "
                                "integer >= 1")
    target = tau * float(problem.observation.noise_norm())
    if not target > 0:
        raise DataError("morozov: the observation has no noise level (noise_std = 0); use "
                        "observations.with_noise or choose alpha by l_curve")
    solve = _default_solve if solve is None else solve
    trials, fields = [], {}

    def g(log_alpha: float, init) -> float:
        field, trial = _evaluate(problem, math.exp(log_alpha), init, solve)
        trials.append(trial)
        fields[log_alpha] = field
        return math.log(trial[1] / target)

    def nearest(log_alpha):
        return fields[min(fields, key=lambda a: abs(a - log_alpha))] if fields else None

    lo = hi = math.log(alpha0)
    g_lo = g_hi = g(lo, None)
    step = math.log(10.0)
    while g_lo > 0 and len(trials) < max_inversions:   # misfit too large: smaller alpha
        hi, g_hi = lo, g_lo
        lo -= step
        g_lo = g(lo, nearest(lo))
    while g_hi < 0 and len(trials) < max_inversions:   # misfit too small: larger alpha
        lo, g_lo = hi, g_hi
        hi += step
        g_hi = g(hi, nearest(hi))
    if not (g_lo <= 0 <= g_hi):
        raise PrdpFemError(f"morozov: no alpha bracketed the discrepancy within "
                           f"{max_inversions} inversions (trials: {trials})")
    best = lo if abs(g_lo) < abs(g_hi) else hi
    while min(abs(g_lo), abs(g_hi)) > math.log1p(rtol) and len(trials) < max_inversions:
        secant = lo - g_lo * (hi - lo) / (g_hi - g_lo) if g_hi != g_lo else 0.5 * (lo + hi)
        mid = min(max(secant, lo + 0.1 * (hi - lo)), hi - 0.1 * (hi - lo))
        g_mid = g(mid, nearest(mid))
        lo, g_lo, hi, g_hi = (mid, g_mid, hi, g_hi) if g_mid < 0 else (lo, g_lo, mid, g_mid)
        best = lo if abs(g_lo) < abs(g_hi) else hi
    alpha = math.exp(best)
    misfit = next(t[1] for t in trials if t[0] == alpha)
    return AlphaChoice(alpha, problem.parameterization.from_field(fields[best]), misfit, target,
                       tuple(trials))


def l_curve(problem: InverseProblem, alphas: Sequence[float], *,
            solve: Callable | None = None) -> AlphaChoice:
    """The grid ``alpha`` at the L-curve's corner (maximum Menger curvature)."""
    try:
        alphas = sorted({float(a) for a in alphas})
    except (TypeError, ValueError):
        raise SolverConfigError(f"alphas={alphas!r}: expected at least 3 distinct finite "
                                "positive values") from None
    if len(alphas) < 3 or not all(_positive(a) for a in alphas):
        raise SolverConfigError(f"alphas={alphas!r}: expected at least 3 distinct finite "
                                "positive values")
    solve = _default_solve if solve is None else solve
    trials, fields, init = [], [], None
    for alpha in reversed(alphas):  # large to small: each warm-starts the next
        field, trial = _evaluate(problem, alpha, init, solve)
        trials.append(trial)
        fields.append(field)
        init = field
    trials.reverse()
    fields.reverse()
    points = np.log([[t[1], max(t[2], 1e-300)] for t in trials])
    curvature = [_menger(points[i - 1], points[i], points[i + 1])
                 for i in range(1, len(points) - 1)]
    corner = 1 + int(np.argmax(curvature))
    return AlphaChoice(alphas[corner], problem.parameterization.from_field(fields[corner]),
                       trials[corner][1], math.nan, tuple(trials))


def _positive(value) -> bool:
    try:
        return np.ndim(value) == 0 and bool(np.isfinite(value) and value > 0)
    except (TypeError, ValueError):
        return False


def _menger(a, b, c) -> float:
    """Signed curvature of the circle through three points (positive: the L's corner)."""
    ab, bc, ca = b - a, c - b, a - c
    cross = ab[0] * bc[1] - ab[1] * bc[0]
    return 2.0 * cross / (np.linalg.norm(ab) * np.linalg.norm(bc) * np.linalg.norm(ca))
