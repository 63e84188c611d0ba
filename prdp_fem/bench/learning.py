r"""PRDP's saving when networks train through the solver, over seeds (``prdp-fem bench learning``).

A learned or heat study (:func:`~prdp_fem.studies.runner.run_study`) follows one draw of data,
splits and initial network: its saving is one sample. :func:`learning_saving` runs a scene's
study once per seed (``learned.seed`` / ``heat.seed``: the data, the splits, the network's
initialisation and the mini-batch order), each into a directory of its own, and reads from each
study's summary, per run:

* the held-out test error at the end, and its gap to the error of the run's converged partner
  (the converged run of the same optimiser and batch, or of the same setup and mode);
* the saving by the project's rule: one minus the PRDP run's time (CG iterations) up to the
  epoch from which its test error stays within ``study.band`` of the partner's final test error,
  over the partner's *own* time (iterations) to that band -- never over its whole run.

:func:`learning_summary` counts, per run over the seeds, the instances that reach the band and
those that meet the goal (:data:`GOAL_TIME_SAVING` of the wall time and
:data:`GOAL_ITERATION_SAVING` of the CG iterations, both), with the median and range of the
savings over the instances that reach it and of the test error over all; :func:`rankings`
orders a scene's runs by test error per seed (ONE / NOG / WIG on the nonlinear scene) and
counts how often each order occurs. :func:`coarse_ceiling` bounds what any refinement schedule
could save where a run's cost per epoch is not the solves' alone.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..errors import SolverConfigError

__all__ = [
    "GOAL_ITERATION_SAVING",
    "GOAL_TIME_SAVING",
    "LEARNING_SCENES",
    "LearningRow",
    "LearningSummary",
    "Ranking",
    "coarse_ceiling",
    "learning_rows",
    "learning_saving",
    "learning_summary",
    "rankings",
    "seeded_scene",
    "throughput",
]

#: The goal a PRDP run meets in one instance: at least this share of the converged run's own
#: time to the band saved, and :data:`GOAL_ITERATION_SAVING` of its CG iterations.
GOAL_TIME_SAVING = 0.6
GOAL_ITERATION_SAVING = 0.8

#: The built-in scenes ``bench learning`` runs by default (the learned inverse at size,
#: ``learned_plate``, takes about 18 minutes a seed on 2 cores: ask for it by name).
LEARNING_SCENES = ("heat_emulator", "reaction_diffusion")


class LearningRow(NamedTuple):
    """One run of one study (one seed of a learned or heat scene)."""

    scene: str
    seed: int
    run: str
    converged_run: str | None   # the partner its saving is measured against (None: none)
    test_error: float           # held-out test error at the end
    error_gap: float            # test_error / the partner's final test error - 1 (NaN: none)
    time_s: float               # the whole run's training time (compilation excluded)
    cg_iterations: int          # the whole run's primal + adjoint CG iterations
    reached_epoch: int | None   # from which the test error stays in the band (None: never)
    time_saving: float          # to the band, against the partner's own time to it (NaN: none)
    iteration_saving: float
    time_ceiling: float = math.nan       # the saving of a run that never left its first level
    iteration_ceiling: float = math.nan  # (coarse_ceiling; NaN: no partner or no records)
    samples_per_s: float = math.nan      # training samples (heat: windows) per training second

    @property
    def goal_met(self) -> bool:
        """Both savings at least the goal's (a run that never reaches the band saves nothing)."""
        return (self.reached_epoch is not None and self.time_saving >= GOAL_TIME_SAVING
                and self.iteration_saving >= GOAL_ITERATION_SAVING)


class LearningSummary(NamedTuple):
    """One run of one scene over the seeds."""

    scene: str
    run: str
    instances: int
    reached: int                # seeds in which it reaches the partner's band
    met: int                    # seeds in which it meets the goal (LearningRow.goal_met)
    time_saving: float          # median over the seeds that reach the band (NaN: none)
    time_saving_low: float
    time_saving_high: float
    iteration_saving: float
    iteration_saving_low: float
    iteration_saving_high: float
    test_error: float           # median over all seeds
    test_error_low: float
    test_error_high: float
    error_gap: float            # median over all seeds (NaN: no partner)
    time_ceiling: float         # medians over all seeds (NaN: no partner)
    iteration_ceiling: float
    samples_per_s: float        # median over all seeds


class Ranking(NamedTuple):
    """An order of a scene's runs by final test error (best first), and in how many seeds."""

    scene: str
    order: tuple[str, ...]
    seeds: tuple[int, ...]
    instances: int


def seeded_scene(scene, seed: int, label: str | None = None):
    """``scene`` (a learned or heat scene) with its data and network drawn from ``seed``;
    ``label`` (e.g. ``"--seed 3"``) opens the errors in place of the scene's file or seed."""
    from ..scene.spec import with_overrides

    kind = scene.study.kind
    if kind not in ("learned", "heat"):
        raise SolverConfigError(f"{label or scene.source}: study.kind = {kind!r}; expected a "
                                "learned or heat scene (its data and network's seed)")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise SolverConfigError(f"{label or f'seed={seed!r}'}: expected an integer >= 0")
    return with_overrides(scene, {kind: {"seed": int(seed)}})


def _number(value: Any) -> float:
    return math.nan if value in (None, "") else float(value)


def _count(value: Any) -> int:
    number = _number(value)
    return 0 if math.isnan(number) else int(number)


def learning_rows(scene_name: str, seed: int, kind: str,
                  summary: Sequence[dict]) -> list[LearningRow]:
    """The rows of one study's ``summary`` (a learned or heat study's, ``kind``)."""
    if kind not in ("learned", "heat"):
        raise SolverConfigError(f"kind={kind!r}: expected 'learned' or 'heat'")
    finals = {row["run"]: _number(row["final_error" if kind == "learned" else "test_error"])
              for row in summary}
    rows = []
    for row in summary:
        partner = row.get("reference" if kind == "learned" else "converged_run") or None
        if partner == row["run"]:  # the converged run is its own reference: no saving
            partner = None
        reached = row["reached_step" if kind == "learned" else "reached_epoch"]
        error = finals[row["run"]]
        gap = error / finals[partner] - 1 if partner in finals else math.nan
        rows.append(LearningRow(
            scene=scene_name, seed=int(seed), run=row["run"], converged_run=partner,
            test_error=error, error_gap=gap, time_s=_number(row["time_s"]),
            cg_iterations=_count(row["cg_iterations"]),
            reached_epoch=None if partner is None or reached in (None, "") else int(reached),
            time_saving=_number(row["time_saving"]) if partner else math.nan,
            iteration_saving=_number(row["iteration_saving"]) if partner else math.nan))
    return rows


def coarse_ceiling(history, partner) -> tuple[float, float]:
    """``(time, CG iterations)``: what a run would save had it trained every epoch at its
    first, coarsest level (its leading epochs before the first refinement) and reached the band
    in as many epochs as its converged ``partner`` -- one minus its cost per epoch there over
    the partner's cost per epoch. A schedule that refines can save no more unless it reaches
    the band in fewer epochs: where the cost the solves do not touch (the network's passes)
    dominates, the time ceiling is low whatever the schedule."""
    if not len(history) or not len(partner):
        return math.nan, math.nan
    first = [record for record in history if record.refinements == 0]
    if not first:
        return math.nan, math.nan
    coarse = first[-1]
    base = partner[-1]
    time = 1 - (coarse.time / len(first)) / (base.time / len(partner)) \
        if base.time > 0 else math.nan
    iterations = 1 - (coarse.total_iterations / len(first)) / (
        base.total_iterations / len(partner)) if base.total_iterations > 0 else math.nan
    return time, iterations


def throughput(history, samples_per_epoch: int) -> float:
    """Training samples (a heat scene's windows) per second of a run's training time
    (compilation excluded; validation and test evaluations included, as in its time)."""
    if not len(history) or not history[-1].time > 0:
        return math.nan
    return samples_per_epoch * len(history) / history[-1].time


def learning_saving(scene, seeds: Iterable[int], out: str | Path, *, resume: bool = False,
                    progress=None, client=None) -> list[LearningRow]:
    """Run ``scene``'s study once per seed into ``out/seed-<S>`` and return every run's row.

    ``resume``: the studies already there keep their finished runs (read back, with the
    times measured when they ran) and run only the rest; a run killed mid-way continues from
    its last checkpoint. ``client``: a ``dask.distributed.Client`` for each study's runs (runs
    sharing a machine's cores slow each other: their time savings compare contended runs).
    """
    from ..studies.runner import run_study, study_histories  # here: they import matplotlib

    seeds = list(seeds)
    if not seeds or len(set(seeds)) < len(seeds):
        raise SolverConfigError(f"seeds={seeds!r}: expected one or more distinct seeds")
    variants = [(seed, seeded_scene(scene, seed)) for seed in seeds]  # all checked first
    rows = []
    for seed, variant in variants:
        directory = Path(out) / f"seed-{seed}"
        result = run_study(variant, directory, resume=resume, progress=progress, client=client)
        histories = study_histories(variant, directory)
        spec = variant.learned if variant.study.kind == "learned" else variant.heat
        available = spec.samples if variant.study.kind == "learned" else spec.windows
        batch = min(spec.batch_size, available)
        per_epoch = available // batch * batch  # the trainers drop a last, partial batch
        for row in learning_rows(scene.name, seed, scene.study.kind, result.summary):
            row = row._replace(samples_per_s=throughput(histories[row.run], per_epoch))
            if row.converged_run is not None:
                time, iterations = coarse_ceiling(histories[row.run],
                                                  histories[row.converged_run])
                row = row._replace(time_ceiling=time, iteration_ceiling=iterations)
            rows.append(row)
    return rows


def _spread(values: list[float]) -> tuple[float, float, float]:
    finite = [v for v in values if not math.isnan(v)]
    if not finite:
        return math.nan, math.nan, math.nan
    return float(np.median(finite)), float(np.min(finite)), float(np.max(finite))


def learning_summary(rows: Iterable[LearningRow]) -> list[LearningSummary]:
    """Per ``(scene, run)``, in the order of ``rows``: instances, band reached, goal met, and
    the median and range of the savings (over the seeds that reach the band) and test errors."""
    groups: dict[tuple[str, str], list[LearningRow]] = {}
    for row in rows:
        groups.setdefault((row.scene, row.run), []).append(row)
    summaries = []
    for (scene, run), group in groups.items():
        reached = [r for r in group if r.reached_epoch is not None]
        summaries.append(LearningSummary(
            scene, run, len(group), len(reached), sum(r.goal_met for r in group),
            *_spread([r.time_saving for r in reached]),
            *_spread([r.iteration_saving for r in reached]),
            *_spread([r.test_error for r in group]),
            _spread([r.error_gap for r in group])[0],
            _spread([r.time_ceiling for r in group])[0],
            _spread([r.iteration_ceiling for r in group])[0],
            _spread([r.samples_per_s for r in group])[0]))
    return summaries


def rankings(rows: Iterable[LearningRow]) -> list[Ranking]:
    """Per scene, each order of its runs by final test error (best first) that occurs, most
    frequent first, with the seeds it occurs in."""
    per_seed: dict[tuple[str, int], list[LearningRow]] = {}
    for row in rows:
        per_seed.setdefault((row.scene, row.seed), []).append(row)
    orders: dict[str, Counter] = {}
    seeds_of: dict[tuple[str, tuple[str, ...]], list[int]] = {}
    for (scene, seed), group in per_seed.items():
        order = tuple(r.run for r in sorted(group, key=lambda r: r.test_error))
        orders.setdefault(scene, Counter())[order] += 1
        seeds_of.setdefault((scene, order), []).append(seed)
    return [Ranking(scene, order, tuple(seeds_of[scene, order]), sum(counter.values()))
            for scene, counter in orders.items() for order, _ in counter.most_common()]
