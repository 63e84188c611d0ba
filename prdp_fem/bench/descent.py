"""``prdp-fem bench descent``: how often each refinement rule's steps descend the converged
objective, and what the rule saves, per scene.

For every run of a scene comparable with its converged reference (PRDP, adaptive, fixed),
plus an ``adaptive`` run (:func:`prdp_fem.inverse.adaptive_tolerance`) where the scene has
none: the fraction of steps that moved along a descent direction of the converged objective
(:func:`prdp_fem.inverse.descent.descent_check`), over the whole run and over its *approach* (the
steps before it settles in the target band; after that a truncated run circles its own
optimum, which need not be the converged one), the median cosine with steepest descent,
and the same-target saving (each run's time and CG iterations to the first step from which
it stays within ``band`` of the converged run's final error, over the converged run's own).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from ..inverse.comparison import first_settled
from ..inverse.descent import IterateRecorder, descent_check
from ..inverse.driver import invert
from ..inverse.history import History
from ..scene.build import build_inverse, invert_options
from ..scene.spec import SceneError

__all__ = ["DescentRow", "descent_rows"]

#: The run added to a scene that has no adaptive run of its own.
ADAPTIVE_RUN = "adaptive"


class DescentRow(NamedTuple):
    scene: str
    run: str
    rule: str                  # the refinement kind
    steps: int
    moved: int                 # steps whose parameters changed
    descending: int            # ... along a descent direction of the converged objective
    fraction: float            # descending / moved
    approach_fraction: float   # the same over the steps before the run settles
    median_cosine: float
    final_error: float
    error_gap: float           # final error / the converged run's - 1
    settled_step: int | None   # first step from which the run stays in the band
    time_saving: float         # same target, both sides (NaN: not settled)
    iteration_saving: float


def descent_runs(scene) -> list[tuple[str, Any]]:
    """The converged reference first, then the converged runs of the other runs'
    preconditioners (:meth:`~prdp_fem.scene.spec.Scene.reference_of`), the comparable PRDP,
    adaptive and fixed runs, and an ``adaptive`` run where the scene has none."""
    if scene.study.kind != "inverse":
        raise SceneError(f"{scene.source}: study.kind = {scene.study.kind!r}; expected an "
                         "inverse study (the descent check follows an inversion's steps)")
    runs = dict(scene.runs())
    reference = runs.get(scene.study.reference)
    if reference is None or reference.refinement.kind != "converged":
        raise SceneError(f"{scene.source}: study.reference = {scene.study.reference!r}: "
                         "expected a run with refinement.kind = 'converged'")
    compared = [(name, variant) for name, variant in runs.items()
                if name != scene.study.reference and variant.same_problem(reference)
                and variant.refinement.kind in ("prdp", "adaptive", "fixed")]
    # each compared run's own reference too: the converged run of its preconditioner
    own = {scene.reference_of(name) for name, _ in compared} - {scene.study.reference}
    chosen = [(scene.study.reference, reference)] + \
        [(name, runs[name]) for name in runs if name in own] + compared
    if not any(variant.refinement.kind == "adaptive" for _, variant in chosen):
        chosen.append((ADAPTIVE_RUN, reference.variant({"refinement": {"kind": "adaptive"}},
                                                       ADAPTIVE_RUN)))
    return chosen


def _cost(history: History, i: int) -> tuple[float, int]:
    record = history[i]
    return record.time, (record.primal_iterations + record.adjoint_iterations_total
                         + record.validation_iterations)


def descent_rows(scene, *, band: float = 0.01, progress=None) -> list[DescentRow]:
    """Run :func:`descent_runs` of ``scene`` and check every step (a converged gradient per
    step, not counted as the runs' time)."""
    setup = build_inverse(scene)
    results = []
    for name, variant in descent_runs(scene):
        options = invert_options(variant, setup.disc, setup.problem)
        recorder = IterateRecorder()
        history = invert(setup.problem, callback=recorder, **options).history
        check = descent_check(setup.problem, recorder.iterates(setup.problem, options["init"]))
        results.append((name, variant.refinement.kind, history, check))
        if progress is not None:
            progress(name)
    errors_of = {name: np.asarray(h.column("parameter_error")) for name, _, h, _ in results}
    histories = {name: history for name, _, history, _ in results}
    target = float(errors_of[scene.study.reference][-1])
    rows = []
    for name, kind, history, check in results:
        errors = errors_of[name]
        settled = first_settled(errors, target, band)
        approach = slice(0, len(errors) if settled is None else settled + 1)
        moved, slopes = check.moved[approach], check.slopes[approach]
        # same target, both sides: against the converged run of the run's preconditioner
        compared_with = scene.reference_of(name)
        base = first_settled(errors_of[compared_with], target, band)
        time_saving = iteration_saving = math.nan
        if settled is not None and base is not None:
            (t, n), (t0, n0) = _cost(history, settled), _cost(histories[compared_with], base)
            time_saving, iteration_saving = 1 - t / t0, 1 - n / n0
        rows.append(DescentRow(
            scene=scene.name, run=name, rule=kind, steps=len(history),
            moved=int(check.moved.sum()), descending=check.descending,
            fraction=check.fraction,
            approach_fraction=float(np.sum(moved & (slopes < 0)) / max(int(moved.sum()), 1)),
            median_cosine=check.median_cosine, final_error=float(errors[-1]),
            error_gap=float(errors[-1] / target - 1),
            settled_step=None if settled is None else settled + 1,
            time_saving=time_saving, iteration_saving=iteration_saving))
    return rows
