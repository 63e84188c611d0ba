"""The learning rate of an epoch's steps relative to the run's first: what a controller that
judges stalls per unit learning rate (``prdp(per_learning_rate=True)``) is fed."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ..errors import SolverConfigError
from ..inverse.refinement import Refinement


def epoch_scales(refinement: Refinement, learning_rate, batches: int,
                 default_optimizer: bool) -> Callable[[int], float] | None:
    """``scale(epoch)``: the mean learning rate of epoch ``epoch``'s ``batches`` steps (1-based
    epochs) over the first step's, or ``None`` when ``refinement`` does not ask for it.

    ``learning_rate``: an optax schedule of the update count, a number, or ``None`` -- a
    constant rate, allowed only with the trainers' default optimizer (whose rate is
    constant): with an optimiser of the caller's the controller cannot know its rate."""
    if not refinement.scaled_by_learning_rate:
        return None
    if learning_rate is None:
        if not default_optimizer:
            raise SolverConfigError(
                "refinement judges stalls per unit learning rate (prdp(per_learning_rate="
                "True)): pass the optimiser's learning rate as learning_rate= (an optax "
                "schedule or a number)")
        return lambda epoch: 1.0
    if not callable(learning_rate):
        if not (isinstance(learning_rate, int | float) and not isinstance(learning_rate, bool)
                and math.isfinite(learning_rate) and learning_rate > 0):
            raise SolverConfigError(f"learning_rate={learning_rate!r}: expected a finite "
                                    "number > 0 or an optax schedule")
        return lambda epoch: 1.0
    first = float(learning_rate(0))
    if not (math.isfinite(first) and first > 0):
        raise SolverConfigError(f"learning_rate(0) = {first!r}: expected a finite number > 0 "
                                "(the rate the scales are relative to)")

    def scale(epoch: int) -> float:
        counts = np.arange((epoch - 1) * batches, epoch * batches)
        return float(np.mean(np.asarray(learning_rate(counts), np.float64))) / first
    return scale
