"""Evaluate the trained runs of a learned or heat study on their held-out test sets.

:func:`evaluate_study` loads each run's last checkpoint (``<out>/checkpoints/<run>``, refused
when it is of another scene, settings, data split or version), evaluates the model on the
scene's test set with converged solves, and writes, beside the study's own files,

* ``evaluation.csv``                one row of test metrics per run;
* ``evaluation/<run>/metrics.json`` the run's metrics (a heat run's also per step);
* ``evaluation/<run>/sample_000.vtu ...``  (learned) predicted and true sources and their
  difference, or ``evaluation/<run>/rollout_000.pvd`` (heat) a ParaView time series of the
  predicted and reference states.
"""

from __future__ import annotations

import json
from pathlib import Path

from .._atomic import write_csv_atomic, write_text_atomic
from .._lock import directory_lock
from ..errors import CheckpointError
from ..learning.checkpoint import load_params, read_metadata
from ..learning.evaluation import (
    evaluate_learned,
    evaluate_rollouts,
    write_rollouts,
    write_source_predictions,
)
from ..scene.build import training_preconditioner
from ..scene.spec import Scene
from .runner import MANIFEST, StudyError, run_checkpoints, run_file_name, shared_setups

__all__ = ["EVALUATION", "evaluate_study"]

EVALUATION = "evaluation"


def evaluate_study(scene: Scene, out: str | Path, *, runs: list[str] | None = None,
                   samples: int = 4) -> list[dict]:
    """Test metrics of ``scene``'s runs trained in the study directory ``out`` (``runs``:
    these only; default: every run with a checkpoint), with predictions of the first
    ``samples`` test samples or trajectories written on the mesh. Returns the rows of
    ``evaluation.csv``."""
    out = Path(out)
    kind = scene.study.kind
    if kind not in ("learned", "heat"):
        raise StudyError(f"{scene.source}: a {kind} study; expected a learned or heat study "
                         "(trained models to evaluate)")
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 0:
        raise StudyError(f"samples={samples!r}: expected an integer >= 0 (predictions to "
                         "write)")
    if not (out / MANIFEST).is_file():
        raise StudyError(f"{out}: no study there ({MANIFEST} missing); expected the directory "
                         f"of prdp-fem study {scene.source}")
    variants = dict(scene.runs())
    unknown = [name for name in runs or [] if name not in variants]
    if unknown:
        raise StudyError(f"{scene.source}: no run {unknown[0]!r}; expected one of "
                         f"{list(variants)}")
    setups = shared_setups(scene)
    with directory_lock(out):  # one writer: not while the study itself writes here
        rows = []
        for name in runs or list(variants):
            variant = variants[name]
            setup = setups(variant)
            checkpoints = run_checkpoints(out, name, variant, setup.split)
            if not runs and not _has_checkpoint(checkpoints.directory):
                continue  # a run not trained yet: evaluated once it is
            rows.append(_evaluate_run(kind, name, variant, setup, checkpoints, out, samples))
        if not rows:
            raise StudyError(f"{out}: no run has a checkpoint; expected a study trained by "
                             f"prdp-fem study {scene.source}")
        write_csv_atomic(out / f"{EVALUATION}.csv", rows)
    return rows


def _has_checkpoint(directory: Path) -> bool:
    try:
        read_metadata(directory)
    except CheckpointError:  # none finished there
        return False
    return True


def _evaluate_run(kind: str, name: str, variant: Scene, setup, checkpoints, out: Path,
                  samples: int) -> dict:
    params, epoch = load_params(checkpoints.directory, setup.network.params, kind=kind,
                                metadata=checkpoints.metadata)
    model = setup.network.replace_params(params)
    target = out / EVALUATION / run_file_name(name)
    options = dict(rtol=variant.refinement.validation_rtol,
                   preconditioner=training_preconditioner(variant, setup.problem))
    if kind == "learned":
        evaluation = evaluate_learned(setup.problem, model, setup.test_set, **options)
        write_source_predictions(target, setup.disc, setup.test_set, evaluation, samples)
    else:
        evaluation = evaluate_rollouts(setup.problem, model, setup.test_set,
                                       setup=variant.heat.setup, **options)
        write_rollouts(target, setup.disc, setup.test_set, evaluation, variant.heat.dt,
                       samples)
    metrics = {"run": name, "epoch": epoch, **evaluation.metrics()}
    target.mkdir(parents=True, exist_ok=True)  # no predictions written (samples = 0): no folder yet
    write_text_atomic(target / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    return {k: v for k, v in metrics.items() if not isinstance(v, list)}
