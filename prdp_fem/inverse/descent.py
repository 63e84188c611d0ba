"""Whether an inversion's steps descend the *converged* objective.

A truncated solve gives the optimiser a gradient of another objective (the truncated one,
exactly in unrolled mode) or of none at all (a truncated adjoint). A step can then lower the
truncated loss and raise the converged one. :func:`descent_check` measures it after a run:
for each step ``z_k -> z_{k+1}`` the slope ``grad J(z_k) . (z_{k+1} - z_k)`` of the
converged objective ``J`` (primal and adjoint solved to ``rtol``) and the cosine between
the step and ``-grad J(z_k)``. A step descends where the slope is negative.

>>> # recorder = IterateRecorder(); result = invert(problem, callback=recorder, ...)
>>> # check = descent_check(problem, recorder.iterates(problem, init))
>>> # check.fraction, check.median_cosine
"""

from __future__ import annotations

import itertools
from typing import Any, NamedTuple

import jax
import numpy as np

from ..linalg.cg import ConvergedCG
from .driver import InverseProblem, Objective, initial_params

__all__ = ["DescentCheck", "IterateRecorder", "descent_check"]


class DescentCheck(NamedTuple):
    """Per step ``k = 1 .. n``: the slope of the converged objective along the step, the
    cosine between the step and its steepest descent, and whether the step moved."""

    slopes: np.ndarray
    cosines: np.ndarray     # NaN where the step did not move
    moved: np.ndarray       # bool

    @property
    def descending(self) -> int:
        """Steps that moved along a descent direction of the converged objective."""
        return int(np.sum(self.moved & (self.slopes < 0)))

    @property
    def fraction(self) -> float:
        """Descending steps / steps that moved (NaN where none moved)."""
        moved = int(np.sum(self.moved))
        return self.descending / moved if moved else float("nan")

    @property
    def median_cosine(self) -> float:
        return float(np.nanmedian(self.cosines)) if np.any(self.moved) else float("nan")


class IterateRecorder:
    """An :func:`~prdp_fem.inverse.driver.invert` callback that keeps every step's parameters
    (host copies: a run's worth of vectors)."""

    def __init__(self):
        self._params: list[np.ndarray] = []

    def __call__(self, record: Any, params: jax.Array) -> None:
        del record
        self._params.append(np.asarray(params))

    def iterates(self, problem: InverseProblem, init: np.ndarray | None = None) -> np.ndarray:
        """``(steps + 1, n)``: the run's start (``init`` as given to ``invert``) and each
        step's parameters."""
        start = np.asarray(initial_params(problem, init))
        return np.stack([start, *self._params])


def descent_check(problem: InverseProblem, iterates: np.ndarray, *, rtol: float = 1e-10,
                  preconditioner: Any = "jacobi") -> DescentCheck:
    """Slopes and cosines of the converged objective along the steps ``iterates[k] ->
    iterates[k + 1]`` (one converged gradient per step: a diagnostic, not run time)."""
    iterates = np.asarray(iterates, np.float64)
    if iterates.ndim != 2 or iterates.shape[0] < 2:
        raise ValueError(f"iterates: shape {iterates.shape}; expected (steps + 1, n) with at "
                         "least one step")
    gradient = Objective(problem, ConvergedCG(rtol=rtol, preconditioner=preconditioner))
    value_and_grad = gradient.value_and_grad
    slopes, cosines, moved = [], [], []
    for z, z_next in itertools.pairwise(iterates):
        step = z_next - z
        _, g = value_and_grad(jax.numpy.asarray(z))
        g = np.asarray(g)
        if not np.all(np.isfinite(g)):
            raise FloatingPointError("descent_check: a converged gradient is not finite")
        step_norm, g_norm = np.linalg.norm(step), np.linalg.norm(g)
        slope = float(g @ step)
        slopes.append(slope)
        moving = step_norm > 0
        moved.append(moving)
        cosines.append(-slope / (step_norm * g_norm) if moving and g_norm > 0 else np.nan)
    return DescentCheck(np.asarray(slopes), np.asarray(cosines), np.asarray(moved, bool))
