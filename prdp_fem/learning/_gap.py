"""The truncation gap a trainer feeds :func:`~prdp_fem.inverse.refinement.truncation_gap`.

Both trainers measure it the same way: their validation pass with converged solves and the
same pass with the training's own tolerance. :func:`first_level` also feeds the controller the
untrained model's gap before epoch 1, so that no epoch trains at a level the model can see
from the start. It cannot see a level that becomes visible during the first epoch: an
untrained model's error is large, a truncation's change of it small.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from functools import partial

import jax

from ..inverse.refinement import Refinement, RefinementState
from ..inverse.steps import device_settings

#: ``pass(K, rtol) -> (monitored value, CG iterations)`` at a tolerance (K: the cap).
Pass = Callable[..., tuple]


def gap(converged_value, truncated_value) -> float:
    """``|truncated / converged - 1|``: the relative change of a validation value that the
    truncation makes (NaN where it is undefined, which the controller treats as large)."""
    converged_value, truncated_value = float(converged_value), float(truncated_value)
    if not (math.isfinite(converged_value) and converged_value != 0):
        return math.nan
    return abs(truncated_value / converged_value - 1.0)


def compile_passes(converged: Callable[[], tuple], truncated: Pass | None, K, rtol) -> None:
    """Run the converged validation pass and (``truncated`` given) the pass at ``(K, rtol)``
    once, untimed: their compilation stays outside the timed region."""
    jax.block_until_ready(converged())
    if truncated is not None:
        jax.block_until_ready(truncated(K, rtol))


def first_level(refinement: Refinement, control: RefinementState,
                converged: Callable[[float], tuple], truncated: Pass,
                gap_of: Callable[[object, object], float] = gap, *,
                reference_follows_level: bool = False,
                ) -> tuple[RefinementState, int, float]:
    """Feed the controller the untrained model's gap (``gap_of(reference value, truncated
    value)``) until it stops tightening: returns the state, the CG iterations of those passes
    and their seconds (compilation excluded). ``converged(rtol)`` is the reference pass for
    the level ``rtol``: run once, or at every level tried where ``reference_follows_level``
    (a reference tied to the level, :class:`~prdp_fem.inverse.refinement.Refinement`'s
    ``reference_factor``)."""
    K, _, rtol = device_settings(control.settings())
    compile_passes(partial(converged, rtol), truncated, K, rtol)
    start = time.perf_counter()
    value, iterations = converged(rtol)
    total = int(iterations)
    while True:
        K, _, rtol = device_settings(control.settings())
        truncated_value, iterations = truncated(K, rtol)
        total += int(iterations)
        before = float(control.rtol)
        control = refinement.update(control, gap_of(value, truncated_value))
        if not float(control.rtol) < before:
            break
        if reference_follows_level:
            value, iterations = converged(float(control.rtol))
            total += int(iterations)
    return control, total, time.perf_counter() - start
