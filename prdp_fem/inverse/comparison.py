"""Side-by-side runs of one inverse problem and the PRDP saving against the converged run.

The saving follows ``BENCHMARKS.md``: a run *reaches* the converged run's final parameter error
``e*`` at the first step from which its error stays within ``band`` (1 %) of ``e*`` up to its
last step -- a pass-through on an oscillating error curve does not count, and a run that ends
outside the band never reaches it. Same target, both sides: its cost there (run time without
compilation, cumulative CG iterations, validation solves included) is compared with the
converged run's cost to the first step from which *it* stays in that band, never with the
converged run's whole run, which goes on after it has arrived.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

from .driver import InverseProblem, invert
from .history import History, StepRecord

__all__ = ["ComparisonRow", "compare", "first_settled", "format_table", "settled"]


class ComparisonRow(NamedTuple):
    method: str
    final_error: float
    final_K: int           # -1 for a tolerance-mode (converged) run
    time: float            # whole run, compilation excluded
    compile_time: float
    iterations: int        # cumulative primal + adjoint CG iterations, whole run
    reached_step: int | None
    time_to_reach: float   # NaN when the band is never reached
    iterations_to_reach: float
    time_saving: float     # 1 - time_to_reach / the converged run's own time_to_reach
    iteration_saving: float


def settled(history: History, target: float, band: float = 0.01, *,
            at_or_below: bool = False) -> StepRecord | None:
    """First record from which ``|error - target| <= band * target`` holds to the end.

    ``at_or_below=True``: from which ``error <= (1 + band) target`` holds (an error that ends
    *lower* than the target counts as reached, as "reach the converged run's error" reads).
    """
    first = first_settled([r.parameter_error for r in history], target, band,
                          at_or_below=at_or_below)
    return None if first is None else history[first]


def first_settled(errors: Sequence[float], target: float, band: float = 0.01, *,
                  at_or_below: bool = False) -> int | None:
    """Index of the first of ``errors`` from which each stays within ``band`` of ``target``
    (or at most ``(1 + band) target``) to the end; ``None`` where the last one is outside.

    >>> first_settled([0.5, 0.1, 0.3, 0.1005, 0.0995], 0.1)
    3
    >>> first_settled([0.5, 0.09], 0.1), first_settled([0.5, 0.09], 0.1, at_or_below=True)
    (None, 1)
    """
    def inside(error: float) -> bool:
        if at_or_below:
            return error <= (1 + band) * target
        return abs(error - target) <= band * target

    flags = [inside(error) for error in errors]
    if not flags or not flags[-1]:
        return None
    first = len(flags) - 1
    while first > 0 and flags[first - 1]:
        first -= 1
    return first


def compare(problem: InverseProblem, runs: Mapping[str, dict], *, steps: int,
            reference: str = "converged", band: float = 0.01) -> list[ComparisonRow]:
    """Run ``invert(problem, steps=steps, **runs[name])`` for every name; rows in that order.

    ``runs[reference]`` is the converged baseline whose final error and total cost the savings
    are measured against.
    """
    if reference not in runs:
        raise KeyError(f"reference run {reference!r} missing from {sorted(runs)}")
    histories = {name: invert(problem, steps=steps, **kwargs).history
                 for name, kwargs in runs.items()}
    target = histories[reference][-1].parameter_error
    base = settled(histories[reference], target, band)  # the reference's own time to it
    t_base = base.time if base else math.nan
    i_base = base.total_iterations if base else math.nan
    rows = []
    for name, history in histories.items():
        last = history[-1]
        hit = settled(history, target, band)
        t_hit = hit.time if hit else math.nan
        i_hit = hit.total_iterations if hit else math.nan
        rows.append(ComparisonRow(
            method=name, final_error=last.parameter_error,
            final_K=-1 if last.rtol > 0 else last.iterations,
            time=last.time, compile_time=last.compile_time,
            iterations=last.total_iterations,
            reached_step=hit.step if hit else None, time_to_reach=t_hit,
            iterations_to_reach=i_hit, time_saving=1.0 - t_hit / t_base,
            iteration_saving=1.0 - i_hit / i_base))
    return rows


def format_table(rows: list[ComparisonRow]) -> str:
    """A fixed-width text table of :func:`compare` rows."""
    head = (f"{'method':<12}{'final err':>11}{'K end':>7}{'time s':>9}{'compile s':>10}"
            f"{'CG its':>9}{'reach@':>8}{'t reach':>9}{'saving t':>10}{'saving its':>11}")
    lines = [head, "-" * len(head)]
    for r in rows:
        reach = "-" if r.reached_step is None else str(r.reached_step)
        def pct(x):
            return "-" if math.isnan(x) else f"{100 * x:.0f} %"
        t_reach = "-" if math.isnan(r.time_to_reach) else f"{r.time_to_reach:.2f}"
        K = "tol" if r.final_K < 0 else str(r.final_K)
        lines.append(f"{r.method:<12}{r.final_error:>11.4e}{K:>7}{r.time:>9.2f}"
                     f"{r.compile_time:>10.2f}{r.iterations:>9}{reach:>8}{t_reach:>9}"
                     f"{pct(r.time_saving):>10}{pct(r.iteration_saving):>11}")
    return "\n".join(lines)
