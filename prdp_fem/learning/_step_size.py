"""A trainer's controller update after an epoch: fed the learning rate of the epoch's steps
relative to the run's first where the controller judges stalls per unit learning rate
(``prdp(per_learning_rate=True)``)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from ..errors import SolverConfigError
from ..inverse.refinement import Refinement


def epoch_update(refinement: Refinement, learning_rate, batches: int,
                 default_optimizer: bool) -> Callable[[Any, float, int], Any]:
    """``update(state, value, epoch)``: ``refinement.update`` after epoch ``epoch`` (1-based)
    of ``batches`` steps, fed the mean learning rate of its steps over the first step's when
    the controller asks for it.

    ``learning_rate``: an optax schedule of the update count, a number, or ``None`` -- a
    constant rate, allowed only with the trainers' default optimizer (whose rate is
    constant): with an optimiser of the caller's the controller cannot know its rate."""
    if not refinement.scaled_by_learning_rate:
        return lambda state, value, epoch: refinement.update(state, value)
    scale = _epoch_scale(learning_rate, batches, default_optimizer)
    return lambda state, value, epoch: refinement.update(state, value,
                                                         learning_rate_scale=scale(epoch))


def _epoch_scale(learning_rate, batches: int, default_optimizer: bool
                 ) -> Callable[[int], float]:
    """``scale(epoch)``: the mean learning rate of epoch ``epoch``'s steps over the first's."""
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
