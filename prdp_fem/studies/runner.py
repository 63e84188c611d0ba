"""Convergence studies: sweep a scene's configurations, record every step, resume, summarise.

A study directory holds

* ``study.json``     what was run (scene name, file, fingerprint, kind, configurations);
* ``results.jsonl``  one JSON object per optimiser step / solve, appended, flushed and fsynced
  as it lands; a configuration ends with a ``{"type": "done"}`` record;
* ``summary.csv``    one row per configuration (rewritten atomically from the records);
* ``figures/*.png``  and ``fields/*.vtu``.

Everything after the records is derived from ``results.jsonl`` alone, so a killed study loses
at most the configuration in flight: ``resume=True`` skips the configurations with a ``done``
record and reruns the others as a new *attempt* (the records of an unfinished attempt stay in
the file and are ignored). A torn last line (a kill mid-write) is skipped.

Study kinds: ``"inverse"`` (inversions with error, time and CG iterations per step),
``"forward"`` (truncated-PCG error against K and time), ``"h"`` (discretisation error
against h and run time for each element, with pyamg timed beside) and ``"learned"`` (a
network trained through the solver, :mod:`prdp_fem.learning.learned`: one ``"epoch"`` record per
epoch with the validation misfit, the held-out source error, cumulative run time without
compilation, cumulative primal and adjoint CG iterations, optimiser steps and ``K``) and
``"heat"`` (a learned heat stepper, :mod:`prdp_fem.learning.heat`: one ``"epoch"`` record per epoch
with
the held-out rollout error, the validation rollout error, run time, CG iterations and ``K``;
the summary pairs each run with the converged run of the same setup and mode for PRDP's
saving).

Savings, in every summary: same target, both sides. A run's *time-to-target* is its run time
(compilation excluded) and its cumulative CG iterations (primal, adjoint, line-search trials,
validation solves) at the first step from which its error stays within ``study.band`` of the
target (the scene's ``target_error``, else the reference run's final error; with
``study.reached = "at_or_below"``, at most ``1 + band`` times it). The saving is ``1 -`` that
over the reference run's own time-to-target -- never over its whole run, which goes on after
it has arrived. A run that never settles has no saving (NaN) and its ``error_gap`` (final
error / target - 1) says how far off it ended; ``ends_at_or_below`` says apart, never as a
saving, whether it ended at most ``1 + band`` times the target.
"""

from __future__ import annotations

import json
import math
import os
import re
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from .._atomic import output_error, write_csv_atomic, write_text_atomic
from .._lock import LOCK_NAME, directory_lock
from .._xla_options import solver_options
from ..errors import PrdpFemError
from ..fem.reference import amg_solve, l2_error
from ..inverse.comparison import settled
from ..inverse.driver import invert
from ..inverse.history import History, StepRecord
from ..inverse.posterior import laplace_posterior
from ..learning import heat
from ..learning.checkpoint import Checkpoints
from ..learning.learned import train
from ..linalg.cg import ConvergedCG, solve
from ..linalg.operator import SparseMatrix
from ..mesh.vtu import write_vtu
from ..scene.build import (
    build_discretization,
    build_heat,
    build_inverse,
    build_learned,
    build_mesh,
    coefficient,
    field_function,
    heat_train_options,
    invert_options,
    operator_at_coefficient,
    solver_preconditioner,
    train_options,
)
from ..scene.spec import Scene
from . import plots
from .forward import Scene as ForwardScene
from .forward import forward_convergence

__all__ = [
    "DEFAULT_FORWARD_ITERATIONS",
    "Progress",
    "ResultsLog",
    "StudyError",
    "StudyOutput",
    "run_study",
    "summarize",
]

RESULTS, SUMMARY, MANIFEST = "results.jsonl", "summary.csv", "study.json"
DEFAULT_FORWARD_ITERATIONS = (0, 5, 10, 20, 40, 80, 160, 320, 640)


class StudyError(PrdpFemError):
    """A study directory that cannot be (re)used as asked."""


class Progress(Protocol):
    """What a study reports while it runs (the CLI draws bars; the default does nothing)."""

    def run_started(self, name: str, steps: int) -> None: ...
    def step(self) -> None: ...
    def run_finished(self, name: str, skipped: bool) -> None: ...
    def stop_if_requested(self) -> None: ...  # a requested stop lands here (before a study)


class _Silent:
    def run_started(self, name: str, steps: int) -> None:
        pass

    def step(self) -> None:
        pass

    def run_finished(self, name: str, skipped: bool) -> None:
        pass

    def stop_if_requested(self) -> None:
        pass


# --------------------------------------------------------------------------------------
# the append-only record file
# --------------------------------------------------------------------------------------


def _json_safe(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return _json_safe(value.item())
    return value


class ResultsLog:
    """Append-only JSON lines; every record is one ``write`` of a whole line, then fsync."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._checked_tail = False

    def records(self) -> list[dict]:
        """Every complete record; a torn (unterminated or unparsable) line is skipped."""
        if not self.path.exists():
            return []
        records = []
        for line in self.path.read_text().split("\n")[:-1]:
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(record, dict):
                records.append(record)
        return records

    def append(self, record: dict) -> None:
        try:
            self._append(record)
        except OSError as error:  # a full disk: name the file, not "output"
            raise output_error(self.path, error) from error

    def _append(self, record: dict) -> None:
        line = json.dumps({k: _json_safe(v) for k, v in record.items()}) + "\n"
        with open(self.path, "ab") as stream:
            if not self._checked_tail:  # a torn last line must not swallow this record
                self._checked_tail = True
                if stream.tell() > 0:
                    with open(self.path, "rb") as tail:
                        tail.seek(-1, os.SEEK_END)
                        if tail.read(1) != b"\n":
                            stream.write(b"\n")
            stream.write(line.encode())
            stream.flush()
            os.fsync(stream.fileno())


def run_file_name(name: str) -> str:
    """A run's name as one file or directory name (its outputs are named by it)."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "run"


def _field_file(out: Path, run: str) -> Path:
    return out / "fields" / f"{run_file_name(run)}.vtu"


def completed(records: list[dict]) -> dict[str, int]:
    """``{run name: attempt}`` of the configurations that finished."""
    return {r["run"]: r["attempt"] for r in records if r.get("type") == "done"}


def _next_attempt(records: list[dict], name: str) -> int:
    return 1 + max((r.get("attempt", 0) for r in records if r.get("run") == name), default=0)


# --------------------------------------------------------------------------------------
# configurations
# --------------------------------------------------------------------------------------


def configurations(scene: Scene) -> list[tuple[str, Any]]:
    """``(name, what to run)``: scene variants, or ``(element, level)`` for h-studies."""
    if scene.study.kind == "h":
        return [(f"{element} level {level}", (element, level))
                for element in scene.study.elements for level in scene.study.levels]
    return scene.runs()


def _manifest(scene: Scene) -> dict:
    return {"scene": scene.name, "file": scene.source, "fingerprint": scene.fingerprint,
            "kind": scene.study.kind, "configurations": [n for n, _ in configurations(scene)],
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}


def _open(scene: Scene, out: Path, resume: bool) -> ResultsLog:
    out.mkdir(parents=True, exist_ok=True)
    log = ResultsLog(out / RESULTS)
    manifest = out / MANIFEST
    started = log.path.exists() and log.path.stat().st_size > 0
    if started and not resume:
        raise StudyError(f"{out}: holds a study already ({RESULTS}); pass --resume to continue "
                         "it or choose another output directory")
    if started or (resume and manifest.exists()):
        try:
            previous = json.loads(manifest.read_text())
        except (OSError, json.JSONDecodeError):
            raise StudyError(f"{manifest}: missing or unreadable; expected the manifest of the "
                             "study to resume") from None
        if previous.get("fingerprint") != scene.fingerprint:
            raise StudyError(
                f"{out}: was started from another scene or settings ({previous.get('file')}, "
                f"fingerprint {previous.get('fingerprint')}); expected {scene.source} as it was "
                f"(fingerprint {scene.fingerprint})")
    else:
        write_text_atomic(manifest, json.dumps(_manifest(scene), indent=2) + "\n")
    return log


# --------------------------------------------------------------------------------------
# runners: one configuration each, appending records as they land
# --------------------------------------------------------------------------------------


class _Setups:
    """``build(variant)`` shared by the configurations whose ``key(variant)`` is equal (they
    differ only in solver or training settings): one study builds each problem once."""

    def __init__(self, build: Callable[[Scene], Any], key: Callable[[Scene], tuple]):
        self._build, self._key, self._cache = build, key, {}

    def __call__(self, variant: Scene):
        key = self._key(variant)
        if key not in self._cache:
            self._cache[key] = self._build(variant)
        return self._cache[key]


def _inverse_key(variant: Scene) -> tuple:
    # hig needs the residual factors: a problem built without them is not shared with it
    return (variant.mesh, variant.pde, variant.inverse, variant.directory,
            variant.optimizer.name == "hig")


def _learned_key(variant: Scene) -> tuple:  # what the datasets and the network depend on
    spec = variant.learned
    return (variant.mesh, variant.pde, variant.inverse, variant.directory, spec.samples,
            spec.validation_samples, spec.noise, spec.width, spec.hidden, spec.seed,
            spec.supervised, spec.test_samples)


def _heat_key(variant: Scene) -> tuple:  # what the trajectories and the network depend on
    spec = variant.heat
    return (variant.mesh, variant.pde, variant.directory, spec.dt, spec.steps, spec.substeps,
            spec.trajectories, spec.validation_trajectories, spec.test_trajectories,
            spec.width, spec.hidden, spec.setup, spec.seed, spec.reaction)


def _epoch_logger(name: str, attempt: int, log: ResultsLog, progress: Progress):
    """A training callback appending each epoch record as it lands."""
    def record_epoch(record) -> None:
        log.append({"type": "epoch", "run": name, "attempt": attempt, **record._asdict()})
        progress.step()

    return record_epoch


def _run_inverse(name, variant: Scene, attempt, log, progress, out: Path, setups) -> None:
    progress.run_started(name, variant.optimizer.steps)  # before the build: a stop lands here
    setup = setups(variant)

    def record_step(record: StepRecord, params) -> None:
        log.append({"type": "step", "run": name, "attempt": attempt, **record._asdict()})
        progress.step()

    result = invert(setup.problem, callback=record_step, **invert_options(variant, setup.disc,
                                                                       setup.problem))
    space = "nodal" if variant.inverse.unknown == "source" else variant.pde.kappa_space
    fields = {"recovered": (space, np.asarray(result.field))}
    if setup.truth is not None:
        fields["truth"] = (space, setup.truth)
        fields["error"] = (space, np.asarray(result.field) - setup.truth)
    write_vtu(setup.disc.mesh, _field_file(out, name), fields)
    rank, samples = variant.inverse.posterior
    if rank:
        _write_posterior(setup, result.params, rank, samples,
                         _field_file(out, f"{name} posterior"))


#: the largest parameter count whose prior variance is computed exactly (dense, n^2)
_EXACT_VARIANCE_LIMIT = 4096


def _write_posterior(setup, params, rank: int, samples: int, path: Path) -> None:
    """The Laplace posterior at a run's final parameters, written beside its fields: mean,
    pointwise variance (randomised above :data:`_EXACT_VARIANCE_LIMIT` parameters) and
    ``samples`` draws."""
    posterior = laplace_posterior(setup.problem, params, setup.prior, rank=rank)
    method = "exact" if setup.problem.n_parameters <= _EXACT_VARIANCE_LIMIT else "randomized"
    posterior.write_vtu(path, setup.disc, samples=samples, variance=method)


CHECKPOINTS = "checkpoints"


def checkpoint_directory(out: Path, run: str) -> Path:
    """Where a learned or heat study's run saves its training states."""
    return Path(out) / CHECKPOINTS / run_file_name(run)


def run_checkpoints(out: Path, name: str, variant: Scene, split: dict) -> Checkpoints:
    """The checkpoints of run ``name``: every ``checkpoint_every`` epochs of its
    ``[learned]``/``[heat]`` table, named by the run, its settings' fingerprint and the data
    split (a checkpoint of another scene or split is refused). A run that starts again
    continues from its last checkpoint: only a study that was resumed reaches a run whose
    directory holds some."""
    spec = variant.learned if variant.learned is not None else variant.heat
    return Checkpoints(checkpoint_directory(out, name), every=spec.checkpoint_every,
                       resume=True, metadata={"run": name, "fingerprint": variant.fingerprint,
                                              "split": split})


def _run_learned(name, variant: Scene, attempt, log, progress, out: Path, setups) -> None:
    progress.run_started(name, variant.learned.epochs)  # before the data: a stop lands here
    setup = setups(variant)
    train(setup.problem, setup.network, setup.train_set, setup.validation_set,
          test_set=setup.test_set, checkpoints=run_checkpoints(out, name, variant, setup.split),
          callback=_epoch_logger(name, attempt, log, progress),
          **train_options(variant, setup.problem))


def _run_heat(name, variant: Scene, attempt, log, progress, out: Path, setups) -> None:
    progress.run_started(name, variant.heat.epochs)  # before the data: a stop lands here
    setup = setups(variant)
    heat.train(setup.problem, setup.network, setup.train_set, setup.validation_set,
               test_set=setup.test_set, checkpoints=run_checkpoints(out, name, variant,
                                                                    setup.split),
               callback=_epoch_logger(name, attempt, log, progress),
               **heat_train_options(variant, setup.problem))


def _run_forward(name, variant: Scene, attempt, log, progress, out: Path, _setups) -> None:
    iterations = variant.solver.iterations or DEFAULT_FORWARD_ITERATIONS
    progress.run_started(name, len(iterations))  # before the build: a stop lands here
    disc = build_discretization(variant)
    dim = disc.mesh.dim()
    source = disc.interpolate(field_function(variant, "pde.source", variant.pde.source, dim))
    scene = ForwardScene(disc, coefficient(variant, disc), source)

    def record(r) -> None:
        log.append({"type": "forward", "run": name, "attempt": attempt,
                    "dofs": disc.n_free, **r._asdict()})
        progress.step()

    matrix = disc.host_system_at(scene.kappa)[0] if variant.solver.preconditioner == "amg" \
        else None  # only an AMG hierarchy is built from the matrix
    preconditioner = solver_preconditioner(variant, matrix)
    forward_convergence(scene, iterations, preconditioner=preconditioner, on_record=record)


def _timed(fn: Callable, *args):
    start = time.perf_counter()
    value = jax.block_until_ready(fn(*args))
    return value, time.perf_counter() - start


def _run_level(name, config, attempt, log, progress, out: Path, scene: Scene) -> None:
    element, level = config
    progress.run_started(name, 1)
    mesh = build_mesh(scene, level)
    disc = build_discretization(scene, mesh, element)
    dim = mesh.dim()
    exact = field_function(scene, "pde.exact", scene.pde.exact, dim)
    A, b = operator_at_coefficient(scene, disc)  # kappa at the quadrature points, no map G
    b = b + disc.load_vector(field_function(scene, "pde.source", scene.pde.source, dim))
    # our setup (the operator's layout, an AMG hierarchy) is timed as pyamg's is in amg_time
    (A_jax, preconditioner), setup_time = _timed(
        lambda: (SparseMatrix.from_scipy(A), solver_preconditioner(scene, A)))
    solver = ConvergedCG(rtol=scene.solver.rtol, preconditioner=preconditioner)
    run = jax.jit(lambda A, b: solve(A, b, solver),
                  compiler_options=solver_options(preconditioner))
    b_jax = jnp.asarray(b)
    _, compile_time = _timed(run, A_jax, b_jax)
    solution, cg_time = _timed(run, A_jax, b_jax)
    reference, amg_time = _timed(lambda: amg_solve(A, b, rtol=scene.solver.rtol))
    x = np.asarray(solution.x)
    log.append({
        "type": "level", "run": name, "attempt": attempt, "element": element, "level": level,
        "h": float(mesh.param()), "dofs": disc.n_free,
        "l2_error": l2_error(disc, disc.expand(x), exact),
        "cg_iterations": int(solution.iterations), "cg_time": cg_time,
        "cg_setup_time": setup_time, "compile_time": max(compile_time - cg_time, 0.0),
        "amg_iterations": reference.iterations, "amg_time": amg_time,
        "algebraic_error": float(np.linalg.norm(x - reference.x)
                                 / max(np.linalg.norm(reference.x), 1e-300))})
    progress.step()


# --------------------------------------------------------------------------------------
# the study
# --------------------------------------------------------------------------------------


class StudyOutput(NamedTuple):
    directory: Path
    summary: list[dict]      # the rows of summary.csv
    figures: list[Path]
    ran: list[str]           # configurations run now (the others were done already)


def run_study(scene: Scene, out: str | Path, *, resume: bool = False,
              progress: Progress | None = None, client=None) -> StudyOutput:
    """Run every configuration of ``scene`` not yet done in ``out``; summarise and plot.

    ``client``: a ``dask.distributed.Client`` (:func:`prdp_fem.studies.cluster.cluster_client`)
    to run the configurations as its tasks, one each, at once; this process alone writes
    ``out``, each configuration's records when its task has finished
    (:mod:`prdp_fem.studies.cluster`). ``None``: one after another, here.
    """
    out = Path(out)
    progress = _Silent() if progress is None else progress
    progress.stop_if_requested()  # a stop asked for before this study: nothing built yet
    if scene.study.kind == "h" and scene.pde.exact is None:
        raise StudyError(f"{scene.source}: study.kind = 'h' needs pde.exact (the exact "
                         "solution to measure the error against)")
    context = _context(scene)
    new = not out.exists()
    if not _holds_records(out):
        _preflight(scene, context)  # a scene its first problem rejects creates no directory
    with directory_lock(out):  # one writer: a second study on ``out`` fails at once
        try:
            return _run_locked(scene, out, resume, progress, context, client)
        except PrdpFemError:
            if not _holds_records(out):  # rejected before its first record: leave nothing
                for name in (MANIFEST, LOCK_NAME):
                    (out / name).unlink(missing_ok=True)
            raise
        finally:
            if new and not any(out.iterdir()):
                out.rmdir()


def _holds_records(out: Path) -> bool:
    results = out / RESULTS
    return results.exists() and results.stat().st_size > 0


def shared_setups(scene: Scene) -> Callable[[Scene], Any]:
    """``setup(variant)`` for a learned or heat scene's runs: each problem, dataset and
    untrained network built once for the runs that share them."""
    return _Setups(build_learned, _learned_key) if scene.study.kind == "learned" else \
        _Setups(build_heat, _heat_key)


def _context(scene: Scene):
    """What the runners of ``scene``'s configurations share: the scene (h-studies) or a
    cache of the problems they build (:class:`_Setups`)."""
    if scene.study.kind in ("learned", "heat"):
        return shared_setups(scene)
    return scene if scene.study.kind == "h" else _Setups(build_inverse, _inverse_key)


def _preflight(scene: Scene, context) -> None:
    """Build the first configuration's problem (kept in ``context`` for its run), so that a
    scene whose mesh, boundary data or coefficient fail on the mesh is refused before the
    output directory is created; forward and h studies, which build per run, build the
    first mesh and coefficient here."""
    first = configurations(scene)[0][1]
    if isinstance(context, _Setups):
        if scene.study.kind != "forward":
            context(first)
            return
        coefficient(first, build_discretization(first))
        return
    element, level = first
    disc = build_discretization(scene, build_mesh(scene, level), element)
    coefficient(scene, disc)


def _runner(scene: Scene) -> Callable:
    return {"inverse": _run_inverse, "forward": _run_forward, "h": _run_level,
            "learned": _run_learned, "heat": _run_heat}[scene.study.kind]


def _run_locked(scene: Scene, out: Path, resume: bool, progress: Progress,
                context, client) -> StudyOutput:
    log = _open(scene, out, resume)
    records = log.records()
    done = completed(records)
    ran, remote = [], []
    for name, config in configurations(scene):
        if name in done:
            progress.run_finished(name, skipped=True)
            continue
        attempt = _next_attempt(records, name)
        if client is not None:
            remote.append((scene, name, config, attempt))
            continue
        _runner(scene)(name, config, attempt, log, progress, out, context)
        log.append({"type": "done", "run": name, "attempt": attempt})
        progress.run_finished(name, skipped=False)
        ran.append(name)
    if remote:
        from .cluster import run_tasks, write_files

        def finished(item, result) -> None:
            _, name, _, attempt = item
            run_records, files = result
            for record in run_records:
                log.append(record)
            write_files(out, files)
            log.append({"type": "done", "run": name, "attempt": attempt})
            ran.append(name)
            progress.run_finished(name, skipped=False)

        run_tasks(client, run_remote, remote, finished)
    summary, figures = summarize(scene, out)
    return StudyOutput(out, summary, figures, ran)


class _Collected:
    """A :class:`ResultsLog` stand-in in a worker: the records stay in memory, to be handed
    back to the study's process, which alone writes ``results.jsonl``."""

    def __init__(self):
        self.collected: list[dict] = []

    def append(self, record: dict) -> None:
        self.collected.append({k: _json_safe(v) for k, v in record.items()})


def run_remote(scene: Scene, name: str, config, attempt: int
               ) -> tuple[list[dict], dict[str, bytes]]:
    """One configuration of ``scene`` as a cluster task: its records (without ``done``) and
    the files it wrote, by path relative to the study directory. It builds its own problem
    and writes nothing outside a scratch directory, so running it again (a worker died)
    repeats it exactly."""
    import tempfile

    from .cluster import collected_files

    log = _Collected()
    with tempfile.TemporaryDirectory(prefix="prdp-fem-task-") as scratch:
        _runner(scene)(name, config, attempt, log, _Silent(), Path(scratch), _context(scene))
        return log.collected, collected_files(Path(scratch))


def _finished_records(scene: Scene, records: list[dict]) -> dict[str, list[dict]]:
    done = completed(records)
    by_run: dict[str, list[dict]] = {name: [] for name, _ in configurations(scene)
                                     if name in done}
    for r in records:
        if r.get("type") != "done" and r.get("run") in by_run and \
                r.get("attempt") == done[r["run"]]:
            by_run[r["run"]].append(r)
    return by_run


LEARNED_METRIC = "mean relative L2 error of held-out test sources"


def _epoch_history(rows: list[dict], *, evaluations: str, misfit: str,
                   error: str) -> History:
    """Epoch records as a :class:`~prdp_fem.inverse.history.History` (``step`` is the epoch; the
    named columns become ``evaluations``, ``misfit`` and ``parameter_error``), so that the
    inverse study's summary and figures apply. A refinement is a change of ``K``."""
    records, refinements, previous = [], 0, None
    for r in rows:
        K = (r["iterations"], r["adjoint_iterations"], r["rtol"])
        refinements += previous is not None and K != previous
        previous = K
        records.append(StepRecord(
            step=r["epoch"], iterations=r["iterations"],
            adjoint_iterations=r["adjoint_iterations"], rtol=r["rtol"],
            refinements=refinements, primal_iterations=r["primal_iterations"],
            adjoint_iterations_total=r["adjoint_iterations_total"],
            # records written before validation solves were counted lack them
            validation_iterations=r.get("validation_iterations", 0),
            evaluations=r[evaluations], time=r["time"], compile_time=math.nan,
            loss=_finite(r["train_loss"]), misfit=_finite(r[misfit]),
            parameter_error=_finite(r[error]), state_error=math.nan))
    return History(records)


def learned_history(rows: list[dict]) -> History:
    """A learned study's epoch records as a History: ``parameter_error`` is the source error
    of the held-out test samples (of the validation samples in records written before test
    splits), ``misfit`` the validation misfit (the PRDP signal), ``evaluations`` the
    optimiser steps."""
    return _epoch_history(rows, evaluations="steps", misfit="validation_misfit",
                          error=learned_error(rows))


def learned_error(rows: list[dict]) -> str:
    """The error a learned study reports: the test samples' where its records carry it."""
    tested = all(r.get("test_error") is not None for r in rows)
    return "test_error" if tested else "validation_error"


HEAT_METRIC = "held-out rollout error"


def heat_history(rows: list[dict]) -> History:
    """A heat study's epoch records as a History: ``parameter_error`` is the held-out rollout
    error, ``misfit`` the validation rollout error (the PRDP signal), ``evaluations`` the
    epoch."""
    return _epoch_history(rows, evaluations="epoch", misfit="validation_error",
                          error="test_error")


def _heat_summary(scene: Scene, histories: dict[str, History]) -> list[dict]:
    """One row per run: setup, mode, training (its refinement kind, ``none`` without a
    solver), the final held-out and validation rollout errors, cost, and -- for a run with a
    converged partner of the same setup and mode -- PRDP's saving: the time and CG iterations
    at which the held-out error settles at the partner's final one (``study.band``,
    ``study.reached``) over the partner's totals, and the equal-epochs ratios."""
    variants = dict(scene.runs())
    rows = []
    for name, history in histories.items():
        if not len(history):
            continue
        spec, kind = variants[name].heat, variants[name].refinement.kind
        solves = spec.solves
        partner = next((other for other, v in variants.items()
                        if other != name and other in histories and len(histories[other])
                        and v.refinement.kind == "converged" and v.heat.setup == spec.setup
                        and v.heat.mode == spec.mode), None) if solves else None
        last = history[-1]
        row = {"run": name, "setup": spec.setup, "mode": spec.mode,
               "training": kind if solves else "none", "epochs": last.step,
               "test_error": last.parameter_error, "validation_error": last.misfit,
               "final_K": ("tol" if last.rtol > 0 else last.iterations) if solves else "",
               "final_rtol": last.rtol if solves and last.rtol > 0 else math.nan,
               "cg_iterations": last.total_iterations, "time_s": last.time, "converged_run": "",
               "reached_epoch": "", "time_saving": math.nan, "iteration_saving": math.nan,
               "equal_epochs_time_ratio": math.nan,
               "equal_epochs_iteration_ratio": math.nan}
        if partner is not None:
            base = histories[partner][-1]
            at_or_below = scene.study.reached == "at_or_below"
            hit = _settled(history, base.parameter_error, scene.study.band, "parameter_error",
                           at_or_below)
            # the partner's own epoch from which it stays at its final error: same target
            base_hit = _settled(histories[partner], base.parameter_error, scene.study.band,
                                "parameter_error", at_or_below)
            row.update(
                converged_run=partner, reached_epoch=hit.step if hit else "",
                time_saving=_saving(hit.time if hit else math.nan,
                                    base_hit.time if base_hit else math.nan),
                iteration_saving=_saving(hit.total_iterations if hit else math.nan,
                                         base_hit.total_iterations if base_hit else math.nan),
                equal_epochs_time_ratio=last.time / base.time,
                equal_epochs_iteration_ratio=last.total_iterations / base.total_iterations)
        rows.append(row)
    return rows


def _learned_row(row: dict, history: History, metric: str) -> dict:
    """An inverse summary row in a learned study's words: epochs, optimiser steps, and the
    final validation misfit beside the held-out source error (``metric``)."""
    renamed = {("epochs" if k == "steps" else k): v for k, v in row.items()
               if k not in ("compile_s", "evaluations")}
    return {**renamed, "metric": metric, "validation_misfit": history[-1].misfit,
            "optimizer_steps": history[-1].evaluations}


def _finite(value) -> float:
    return math.nan if value is None else float(value)


def _history(rows: list[dict]) -> History:
    def field(row: dict, name: str):
        value = row.get(name, StepRecord._field_defaults.get(name))  # older rows lack some
        return math.nan if value is None else value
    return History(StepRecord(**{k: field(r, k) for k in StepRecord._fields}) for r in rows)


def summarize(scene: Scene, out: str | Path) -> tuple[list[dict], list[Path]]:
    """Write ``summary.csv`` and the figures from ``results.jsonl``; return the rows."""
    out = Path(out)
    by_run = _finished_records(scene, ResultsLog(out / RESULTS).records())
    kind = scene.study.kind
    if kind == "inverse":
        histories = {n: _history(r) for n, r in by_run.items()}
        metric = metric_of(histories)
        rows = _inverse_summary(scene, histories, metric)
        figures = plots.inverse_figures(scene.name, histories, metric, out,
                                        {n: _field_file(out, n) for n in histories})
    elif kind == "learned":
        histories = {n: learned_history(r) for n, r in by_run.items()}
        rows = [_learned_row(row, histories[row["run"]], learned_error(by_run[row["run"]]))
                for row in _inverse_summary(scene, histories, "parameter_error",
                                            partial(learned_reference, scene))]
        figures = plots.inverse_figures(scene.name, histories, "parameter_error", out, {},
                                        metric_label=LEARNED_METRIC, step_label="epoch")
    elif kind == "heat":
        histories = {n: heat_history(r) for n, r in by_run.items()}
        rows = _heat_summary(scene, histories)
        figures = plots.inverse_figures(scene.name, histories, "parameter_error", out, {},
                                        metric_label=HEAT_METRIC, step_label="epoch")
    elif kind == "forward":
        rows = [{"run": name, **{k: v for k, v in r.items() if k not in ("type", "run")}}
                for name, records in by_run.items() for r in records]
        figures = plots.forward_figures(by_run, out)
    else:
        rows = _h_summary(by_run)
        figures = plots.h_figures(rows, out)
    write_csv_atomic(out / SUMMARY, rows)
    return rows, figures


def metric_of(histories: dict[str, History]) -> str:
    """The parameter error when a truth is known, else the misfit."""
    last = [h[-1].parameter_error for h in histories.values() if len(h)]
    return "parameter_error" if any(not math.isnan(v) for v in last) else "misfit"


def inverse_histories(scene: Scene, out: str | Path) -> dict[str, History]:
    """The step records of every finished configuration of an inverse study in ``out``."""
    return _read_histories(scene, out, _history)


def _read_histories(scene: Scene, out: str | Path, read) -> dict[str, History]:
    by_run = _finished_records(scene, ResultsLog(Path(out) / RESULTS).records())
    return {name: read(rows) for name, rows in by_run.items()}


def study_histories(scene: Scene, out: str | Path) -> dict[str, History]:
    """The records of every finished run of an inverse, learned or heat study in ``out`` as
    histories (a learned or heat study's as :func:`learned_history` / :func:`heat_history`
    give them: one record per epoch)."""
    read = {"inverse": _history, "learned": learned_history, "heat": heat_history}
    if scene.study.kind not in read:
        raise StudyError(f"{scene.source}: study.kind = {scene.study.kind!r}; expected an "
                         "inverse, learned or heat study")
    return _read_histories(scene, out, read[scene.study.kind])


def learned_reference(scene: Scene, name: str) -> str | None:
    """The converged run a learned study's run ``name`` is measured against: one that trains
    the same network on the same data with the same optimiser, batch size and
    preconditioner (only the solves differ); ``None`` where the scene has none -- a saving
    against another optimiser's run would be the optimiser's, not the refinement's."""
    variants = dict(scene.runs())
    run = variants[name]
    return next((other for other, v in variants.items()
                 if v.refinement.kind == "converged" and v.learned == run.learned
                 and v.solver.preconditioner == run.solver.preconditioner
                 and v.same_problem(run)), None)


def _inverse_summary(scene: Scene, histories: dict[str, History], metric: str,
                     reference_of: Callable[[str], str | None] | None = None) -> list[dict]:
    """Inverse rows; ``reference_of(name)``: each run's own reference, whose final error is
    then its target (default: ``scene.reference_of``, one target for all, the reference
    run's final error)."""
    finals = {n: getattr(h[-1], metric) for n, h in histories.items() if len(h)}
    reference = histories.get(scene.study.reference)
    if scene.study.target_error is not None:
        common = scene.study.target_error
    elif reference is not None and len(reference):
        common = getattr(reference[-1], metric)
    else:
        common = min(finals.values(), default=math.nan)
    band, at_or_below = scene.study.band, scene.study.reached == "at_or_below"

    def target_of(compared_with: str | None) -> float:
        if reference_of is None or scene.study.target_error is not None:
            return common
        return finals.get(compared_with, math.nan)

    def time_to_target(name: str | None, target: float):
        # same target, both sides: the reference's own time to the target, not its whole run
        history = histories.get(name)
        return _settled(history, target, band, metric, at_or_below) \
            if history is not None and len(history) else None

    rows = []
    for name, history in histories.items():
        if not len(history):
            continue
        last = history[-1]
        compared_with = (scene.reference_of if reference_of is None else reference_of)(name)
        target = target_of(compared_with)
        base = time_to_target(compared_with, target)
        hit = _settled(history, target, band, metric, at_or_below) \
            if not math.isnan(target) else None
        iterations = last.total_iterations
        hit_iterations = hit.total_iterations if hit else math.nan
        final = getattr(last, metric)
        rows.append({
            "run": name, "reference": compared_with, "steps": last.step, "metric": metric,
            "final_error": getattr(last, metric), "final_loss": last.loss,
            "final_K": "tol" if last.rtol > 0 else last.iterations,
            "refinements": last.refinements, "time_s": last.time,
            "compile_s": last.compile_time, "cg_iterations": iterations,
            "evaluations": last.evaluations, "failed_steps": last.failed_steps,
            "target_error": target,
            "error_gap": final / target - 1 if target else math.nan,
            "ends_at_or_below": bool(final <= (1 + band) * target),
            "reached_step": hit.step if hit else "",
            "time_to_target_s": hit.time if hit else math.nan,
            "iterations_to_target": hit_iterations,
            "converged_time_to_target_s": base.time if base else math.nan,
            "time_saving": _saving(hit.time if hit else math.nan,
                                   base.time if base else math.nan),
            "iteration_saving": _saving(hit_iterations,
                                        base.total_iterations if base else math.nan)})
    return rows


def _saving(cost: float, reference_cost: float) -> float:
    """``1 - cost / reference_cost``, both to the same target (NaN where either is missing)."""
    if math.isnan(cost) or math.isnan(reference_cost) or reference_cost <= 0:
        return math.nan
    return 1 - cost / reference_cost


def _settled(history: History, target: float, band: float, metric: str,
             at_or_below: bool = False):
    if metric != "parameter_error":  # settled() reads parameter_error: give it the metric
        history = History(r._replace(parameter_error=getattr(r, metric)) for r in history)
    return settled(history, target, band, at_or_below=at_or_below)


def _h_summary(by_run: dict[str, list[dict]]) -> list[dict]:
    rows = sorted((r for records in by_run.values() for r in records),
                  key=lambda r: (r["element"], r["level"]))
    out, previous = [], None
    for r in rows:
        setup = r.get("cg_setup_time", math.nan)  # not measured in records written before
        rate = math.nan
        if previous is not None and previous["element"] == r["element"]:
            rate = math.log(previous["l2_error"] / r["l2_error"]) / math.log(
                previous["h"] / r["h"])
        out.append({"run": r["run"], **{k: r[k] for k in (
            "element", "level", "h", "dofs", "l2_error")}, "rate": rate,
            **{k: r[k] for k in ("cg_iterations", "cg_time")},
            "cg_setup_time": setup,
            **{k: r[k] for k in ("amg_iterations", "amg_time", "algebraic_error")},
            # amg_time is pyamg's setup and solve: compare it with ours
            "cg_over_amg_time": (setup + r["cg_time"]) / r["amg_time"]})
        previous = r
    return out


