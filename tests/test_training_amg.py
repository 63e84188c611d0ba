"""AMG-preconditioned training: ``solver.preconditioner = "amg"`` in learned and heat scenes
builds one hierarchy from the fixed operator, trains to the Jacobi run's result with far
fewer CG iterations, pairs its PRDP run with the converged AMG run, and evaluates with it."""

import numpy as np
import pytest

from prdp_fem.learning import heat
from prdp_fem.linalg import AMGCycle
from prdp_fem.scene import parse_scene
from prdp_fem.scene.build import (
    build_heat,
    build_learned,
    heat_train_options,
    training_preconditioner,
)
from prdp_fem.scene.spec import SceneSolverConfigError
from prdp_fem.studies import run_study
from prdp_fem.studies.evaluation import evaluate_study
from prdp_fem.studies.runner import ResultsLog

LEARNED = {
    "name": "amg_learned",
    "mesh": {"n": 12},
    "inverse": {"unknown": "source"},
    "learned": {"samples": 8, "validation_samples": 4, "test_samples": 4, "hidden": [4],
                "epochs": 3, "batch_size": 4},
    "refinement": {"kind": "prdp", "rtol": 1e-2, "rtol_min": 1e-10, "restart": False},
    "optimizer": {"name": "adam", "learning_rate": 3e-3},
    "study": {"kind": "learned", "reference": "converged", "runs": [
        {"name": "converged", "refinement": {"kind": "converged", "rtol": 1e-10}},
        {"name": "converged amg", "refinement": {"kind": "converged", "rtol": 1e-10},
         "solver": {"preconditioner": "amg"}},
        {"name": "prdp amg", "solver": {"preconditioner": "amg"}}]},
}

HEAT = {
    "name": "amg_heat",
    "mesh": {"n": 12},
    "pde": {"source": 0.0},
    "heat": {"dt": 0.02, "steps": 4, "trajectories": 4, "validation_trajectories": 2,
             "test_trajectories": 2, "hidden": [8], "unroll": 2, "epochs": 2, "batch_size": 4,
             "mode": "wig"},
    "refinement": {"kind": "converged", "rtol": 1e-10},
    "optimizer": {"name": "adam", "learning_rate": 3e-3},
    "study": {"kind": "heat", "runs": [
        {"name": "jacobi"}, {"name": "amg", "solver": {"preconditioner": "amg"}}]},
}


def _runs(table):
    return dict(parse_scene(table, source="amg.toml").runs())


def test_learned_amg_runs_match_jacobi_in_fewer_iterations_and_evaluate_with_their_hierarchy(
        tmp_path):
    """One study of the three runs (the trainings and the evaluation share its programs):
    the converged AMG run trains as the converged Jacobi run with a fraction of the
    iterations, and the AMG runs' checkpoints evaluate with the same hierarchy."""
    runs = _runs(LEARNED)
    scene = parse_scene(LEARNED, source="amg.toml")
    out = tmp_path / "study"
    run_study(scene, out)
    epochs = {}
    for record in ResultsLog(out / "results.jsonl").records():
        if record["type"] == "epoch":
            epochs.setdefault(record["run"], []).append(record)
    setup = build_learned(runs["converged amg"])
    assert isinstance(training_preconditioner(runs["converged amg"], setup.problem),
                      AMGCycle)
    jacobi, amg = epochs["converged"], epochs["converged amg"]
    # the same training: converged solves, whichever the preconditioner
    for key in ("train_loss", "validation_misfit", "test_error"):
        np.testing.assert_allclose([r[key] for r in amg], [r[key] for r in jacobi], rtol=1e-7)
    # ... with a fraction of the iterations (121 dofs: Jacobi-PCG needs about 25 a solve)
    assert amg[-1]["primal_iterations"] < 0.5 * jacobi[-1]["primal_iterations"]
    assert amg[-1]["validation_iterations"] < 0.5 * jacobi[-1]["validation_iterations"]
    rows = {row["run"]: row for row in evaluate_study(scene, out, samples=0)}
    for run in ("converged amg", "prdp amg"):
        assert rows[run]["test_error"] == pytest.approx(epochs[run][-1]["test_error"],
                                                        rel=1e-10)


def test_amg_prdp_run_is_measured_against_the_converged_amg_run():
    scene = parse_scene(LEARNED, source="amg.toml")
    assert scene.reference_of("prdp amg") == "converged amg"
    assert scene.reference_of("converged amg") == "converged"


def test_heat_training_with_amg_matches_jacobi():
    runs = _runs(HEAT)
    setup = build_heat(runs["jacobi"])  # the runs differ in their solver's preconditioner only
    records = {}
    for name in ("jacobi", "amg"):
        records[name] = heat.train(setup.problem, setup.network, setup.train_set,
                                   setup.validation_set, test_set=setup.test_set,
                                   **heat_train_options(runs[name], setup.problem)).records
    for key in ("train_loss", "validation_error", "test_error"):
        np.testing.assert_allclose([getattr(r, key) for r in records["amg"]],
                                   [getattr(r, key) for r in records["jacobi"]], rtol=1e-7)
    assert records["amg"][-1].primal_iterations < records["jacobi"][-1].primal_iterations


@pytest.mark.parametrize("kind", ["learned", "heat"])
def test_a_training_refuses_amg_rebuilds(kind):
    table = LEARNED if kind == "learned" else HEAT
    table = dict(table, solver={"preconditioner": "amg", "rebuild_every": 5})
    with pytest.raises(SceneSolverConfigError,
                       match=f"rebuild_factor with study.kind = '{kind}': expected 0"):
        parse_scene(table, source="amg.toml")
