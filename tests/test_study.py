"""Studies in-process: records and summaries against the scripting API, resume, h/forward."""

import csv
import json
import math
import tomllib
from pathlib import Path

import meshio
import numpy as np
import pytest
from conftest import SMALL_STUDY, resume_after_losing_done

import prdp_fem as pf
from prdp_fem.scene import builtin_scene_path, load_scene, parse_scene
from prdp_fem.scene.build import build_inverse, invert_options
from prdp_fem.scene.spec import with_overrides
from prdp_fem.studies import StudyError, run_study
from prdp_fem.studies import runner as study_module
from prdp_fem.studies.runner import ResultsLog


@pytest.fixture
def no_amg(monkeypatch):
    """pyamg's hierarchy setup (used by every reference solve) raises if called."""
    import pyamg

    def forbidden(*args, **kwargs):
        raise AssertionError("an AMG hierarchy was built")

    monkeypatch.setattr(pyamg, "smoothed_aggregation_solver", forbidden)


@pytest.fixture
def no_kappa_map(monkeypatch):
    """Building the map kappa -> A (Discretization.system, stiffness_matrix) raises."""
    from prdp_fem.fem import discretization

    def forbidden(*args, **kwargs):
        raise AssertionError("the map kappa -> A was built")

    monkeypatch.setattr(discretization, "_assembly_maps", forbidden)


@pytest.fixture
def tiny(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(SMALL_STUDY.replace("STEPS", "12"))
    return load_scene(path)


def test_inverse_study_records_every_step_and_matches_the_scripting_api(tiny, tmp_path,
                                                                        no_amg):
    result = run_study(tiny, tmp_path / "out")  # Jacobi runs: no AMG hierarchy is built
    records = ResultsLog(tmp_path / "out" / "results.jsonl").records()
    steps = [r for r in records if r["type"] == "step"]
    assert [r["run"] for r in records if r["type"] == "done"] == ["converged", "fixed K=3",
                                                                  "prdp"]
    assert len(steps) == 3 * 12
    # the study's converged run is exactly what invert() gives from a script
    name, variant = tiny.runs()[0]
    setup = build_inverse(variant)
    direct = pf.invert(setup.problem, **invert_options(variant, setup.disc)).history
    mine = [r for r in steps if r["run"] == name]
    np.testing.assert_allclose([r["parameter_error"] for r in mine],
                               direct.column("parameter_error"), rtol=1e-10)
    assert [r["primal_iterations"] for r in mine] == list(direct.column("primal_iterations"))
    # summary rows are the last records; savings are measured against the converged run
    rows = {row["run"]: row for row in result.summary}
    for run, row in rows.items():
        last = [r for r in steps if r["run"] == run][-1]
        assert row["final_error"] == last["parameter_error"]
        assert row["cg_iterations"] == last["primal_iterations"] + last[
            "adjoint_iterations_total"]
    assert rows["converged"]["target_error"] == rows["converged"]["final_error"]
    assert rows["fixed K=3"]["final_K"] == 3 and rows["converged"]["final_K"] == "tol"
    reached = rows["converged"]["reached_step"]
    assert 1 <= reached <= 12
    # same target, both sides: the reference against itself saves nothing, and every run's
    # saving is against the reference's own time to the target, not its whole run
    base = rows["converged"]
    assert base["time_saving"] == 0.0 and base["iteration_saving"] == 0.0
    assert base["converged_time_to_target_s"] == base["time_to_target_s"] < base["time_s"] \
        or reached == 12
    for row in rows.values():
        if row["reached_step"] != "":
            assert row["iteration_saving"] == pytest.approx(
                1 - row["iterations_to_target"] / base["iterations_to_target"])
            assert row["time_saving"] == pytest.approx(
                1 - row["time_to_target_s"] / base["time_to_target_s"])
        else:
            assert math.isnan(row["time_saving"]) and math.isnan(row["iteration_saving"])
        assert row["error_gap"] == pytest.approx(row["final_error"] / base["final_error"] - 1)
        assert row["ends_at_or_below"] == (row["final_error"] <= 1.01 * base["final_error"])
    with open(tmp_path / "out" / "summary.csv") as stream:
        table = list(csv.DictReader(stream))
    assert [t["run"] for t in table] == ["converged", "fixed K=3", "prdp"]
    assert float(table[1]["final_error"]) == pytest.approx(rows["fixed K=3"]["final_error"],
                                                           rel=1e-12)
    # the fields are valid VTU with the recovered field and the truth
    fields = meshio.read(tmp_path / "out" / "fields" / "converged.vtu")
    np.testing.assert_allclose(fields.point_data["truth"],
                               np.asarray(setup.truth)[:fields.points.shape[0]])
    assert len(result.figures) == 4


@pytest.mark.slow  # 22 s; the kill -9 / --resume subprocess test covers resuming by default
def test_resume_skips_finished_runs_and_ignores_unfinished_attempts(tiny, tmp_path,
                                                                    monkeypatch):
    out = tmp_path / "out"
    uninterrupted = run_study(tiny, tmp_path / "ref").summary
    # a study killed during its second configuration: one done run, a half-written attempt
    full = ResultsLog(tmp_path / "ref" / "results.jsonl").records()
    first_done = next(i for i, r in enumerate(full) if r["type"] == "done")
    run_study(tiny, out)  # to get the manifest; then cut the records back
    kept = full[:first_done + 1] + [r for r in full if r.get("run") == "fixed K=3"][:5]
    text = "".join(json.dumps(r) + "\n" for r in kept) + '{"type": "step", "run": "fi'
    (out / "results.jsonl").write_text(text)
    calls = []
    original = study_module._run_inverse
    monkeypatch.setattr(study_module, "_run_inverse",
                        lambda name, *a: (calls.append(name), original(name, *a)))
    with pytest.raises(StudyError, match="pass --resume"):
        run_study(tiny, out)
    resumed = run_study(tiny, out, resume=True)
    assert calls == ["fixed K=3", "prdp"] and resumed.ran == ["fixed K=3", "prdp"]
    records = ResultsLog(out / "results.jsonl").records()
    assert {r["attempt"] for r in records if r["run"] == "fixed K=3"} == {1, 2}
    deterministic = ("run", "final_error", "final_K", "cg_iterations", "evaluations",
                     "reached_step", "iterations_to_target")
    for a, b in zip(uninterrupted, resumed.summary, strict=True):
        for key in deterministic:
            assert a[key] == b[key] or (isinstance(a[key], float) and math.isnan(a[key])
                                        and math.isnan(b[key])), key


def test_resume_refuses_a_changed_scene(tiny, tmp_path):
    run_study(parse_scene({"mesh": {"n": 4}, "solver": {"iterations": [1]}}), tmp_path / "o")
    with pytest.raises(StudyError, match="was started from another scene"):
        run_study(tiny, tmp_path / "o", resume=True)


def test_torn_last_line_is_skipped_and_the_next_record_starts_clean(tmp_path):
    log = ResultsLog(tmp_path / "r.jsonl")
    log.append({"a": 1, "b": math.nan})
    with open(log.path, "a") as stream:
        stream.write('{"a": 2, "b"')  # killed mid-write
    assert ResultsLog(log.path).records() == [{"a": 1, "b": None}]
    fresh = ResultsLog(log.path)
    fresh.append({"a": 3})
    assert fresh.records() == [{"a": 1, "b": None}, {"a": 3}]


@pytest.mark.slow  # constant kappa: the built-in scene's variable-kappa test below covers it
def test_h_study_measures_the_p1_and_p2_rates(tmp_path):
    scene = parse_scene({
        "pde": {"source": "2*pi**2*sin(pi*x)*sin(pi*y)", "exact": "sin(pi*x)*sin(pi*y)"},
        "solver": {"rtol": 1e-12}, "study": {"kind": "h", "levels": [4, 8, 16, 32]}})
    rows = run_study(scene, tmp_path / "h").summary
    rates = {e: [r["rate"] for r in rows if r["element"] == e][-1] for e in ("P1", "P2")}
    assert rates["P1"] == pytest.approx(2.0, abs=0.05)
    assert rates["P2"] == pytest.approx(3.0, abs=0.05)
    assert all(r["algebraic_error"] < 1e-9 for r in rows)


def test_the_built_in_h_study_keeps_p2_s_rate_with_a_variable_kappa(tmp_path, no_kappa_map):
    """poisson_h (kappa = 1 + x^2 y): the coefficient is assembled at the quadrature points,
    so P2 converges at L2 rate 3 and P1 at 2 (a P1-interpolated kappa held P2 to 2). An
    h-study never changes kappa: it assembles at it and builds no map kappa -> A."""
    table = tomllib.loads(builtin_scene_path("poisson_h").read_text())
    table["study"]["levels"] = [16, 32]  # the rate is the last pair's
    scene = parse_scene(table)
    rows = run_study(scene, tmp_path / "h").summary
    rates = {e: [r["rate"] for r in rows if r["element"] == e][-1] for e in ("P1", "P2")}
    assert rates["P1"] == pytest.approx(2.0, abs=0.05)
    assert rates["P2"] == pytest.approx(3.0, abs=0.05)
    assert all(r["algebraic_error"] < 1e-9 for r in rows)


def test_h_study_with_amg_times_its_setup_as_pyamg_time_is(tmp_path):
    """pyamg's time holds its hierarchy's setup; ours is timed apart and added to the ratio."""
    scene = parse_scene({
        "pde": {"source": "2*pi**2*sin(pi*x)*sin(pi*y)", "exact": "sin(pi*x)*sin(pi*y)"},
        "solver": {"rtol": 1e-10, "preconditioner": "amg"},
        "study": {"kind": "h", "levels": [16, 32], "elements": ["P1"]}})
    rows = run_study(scene, tmp_path / "h").summary
    for r in rows:
        assert r["algebraic_error"] < 1e-8 and r["cg_setup_time"] > 0
        assert r["cg_over_amg_time"] == pytest.approx(
            (r["cg_setup_time"] + r["cg_time"]) / r["amg_time"])
    assert rows[-1]["rate"] == pytest.approx(2.0, abs=0.05)
    # a multigrid preconditioner: the iterations do not grow with the mesh (Jacobi's double)
    assert rows[1]["cg_iterations"] <= rows[0]["cg_iterations"] + 2


def test_h_study_needs_an_exact_solution(tmp_path):
    with pytest.raises(StudyError, match=r"needs pde\.exact"):
        run_study(parse_scene({"study": {"kind": "h"}}), tmp_path / "h")


def test_forward_study_errors_fall_with_K(tmp_path, no_kappa_map):
    """A variable kappa, assembled at it: a forward study builds no map kappa -> A."""
    scene = parse_scene({"mesh": {"n": 16}, "pde": {"kappa": "1 + x"},
                         "solver": {"iterations": [0, 10, 400]},
                         "study": {"runs": [{"name": "jacobi"},
                                            {"name": "identity",
                                             "solver": {"preconditioner": "identity"}}]}})
    rows = run_study(scene, tmp_path / "f").summary
    for run in ("jacobi", "identity"):
        errors = [r["relative_energy_error"] for r in rows if r["run"] == run]
        assert errors[0] == pytest.approx(1.0) and errors[1] < 0.5 and errors[2] < 1e-10


# --------------------------------------------------------------------------------------
# learned studies
# --------------------------------------------------------------------------------------

TINY_LEARNED = """
name = "tiny_learned"
[mesh]
n = 6
[inverse]
unknown = "source"
[learned]
samples = 8
validation_samples = 4
hidden = [4]
epochs = 3
batch_size = 4
[refinement]
kind = "prdp"
K0 = 2
dK = 2
[optimizer]
name = "adam"
learning_rate = 3e-3
[[study.runs]]
name = "converged"
refinement = { kind = "converged" }
[[study.runs]]
name = "prdp"
[[study.runs]]
name = "gauss_newton"
optimizer = { name = "gauss_newton", max_cg = 10 }
learned = { batch_size = 8 }
"""


@pytest.mark.slow  # records and resume are checked on the inverse study
def test_learned_study_records_every_epoch_resumes_and_matches_train(tmp_path, monkeypatch):
    from prdp_fem.learning.learned import train
    from prdp_fem.scene.build import build_learned, train_options

    path = tmp_path / "learned.toml"
    path.write_text(TINY_LEARNED)
    scene = load_scene(path)
    out = tmp_path / "out"
    result = run_study(scene, out)
    records = ResultsLog(out / "results.jsonl").records()
    epochs = [r for r in records if r["type"] == "epoch"]
    assert [r["run"] for r in records if r["type"] == "done"] == ["converged", "prdp",
                                                                  "gauss_newton"]
    assert len(epochs) == 3 * 3
    for run in ("converged", "prdp", "gauss_newton"):
        mine = [r for r in epochs if r["run"] == run]
        for key in ("primal_iterations", "adjoint_iterations_total", "time", "steps"):
            values = [r[key] for r in mine]
            assert values == sorted(values) and values[0] > 0, (run, key)
    # the study's PRDP run is what train() gives from a script, epoch by epoch
    variant = dict(scene.runs())["prdp"]
    setup = build_learned(variant)
    direct = train(setup.problem, setup.network, setup.train_set, setup.validation_set,
                   **train_options(variant, setup.problem)).records
    mine = [r for r in epochs if r["run"] == "prdp"]
    np.testing.assert_allclose([r["validation_misfit"] for r in mine],
                               [r.validation_misfit for r in direct], rtol=1e-10)
    assert [r["primal_iterations"] for r in mine] == [r.primal_iterations for r in direct]
    assert [r["iterations"] for r in mine] == [r.iterations for r in direct]
    # PRDP's K = 2 solves cost less than converged ones; the summary reads the last records
    rows = {row["run"]: row for row in result.summary}
    assert rows["prdp"]["cg_iterations"] < rows["converged"]["cg_iterations"]
    assert rows["gauss_newton"]["final_error"] == [r for r in epochs if r["run"] ==
                                                  "gauss_newton"][-1]["test_error"]
    assert rows["gauss_newton"]["optimizer_steps"] == 3 and rows["prdp"]["optimizer_steps"] == 6
    # savings against the converged run of the same optimiser and batch only: Gauss-Newton
    # has none in this scene, so it has no saving (not one against Adam's converged run)
    assert rows["prdp"]["reference"] == "converged" and rows["gauss_newton"]["reference"] is None
    assert np.isnan(rows["gauss_newton"]["time_saving"])
    assert rows["prdp"]["target_error"] == rows["converged"]["final_error"]
    assert sorted(p.name for p in result.figures) == [
        "error_vs_iterations.png", "error_vs_time.png", "iterations_over_steps.png"]
    # resume: nothing left to run; a run whose 'done' record is lost runs again, alone
    assert run_study(scene, out, resume=True).ran == []
    resumed = resume_after_losing_done(scene, out, "gauss_newton", "_run_learned", monkeypatch)
    again = {row["run"]: row for row in resumed.summary}
    assert again["gauss_newton"]["final_error"] == pytest.approx(
        rows["gauss_newton"]["final_error"], rel=1e-9)


# --------------------------------------------------------------------------------------
# the optimiser comparison scenes (issue 7): each run, shrunk, lowers its error
# --------------------------------------------------------------------------------------

SCENES = Path(__file__).resolve().parent.parent / "examples" / "scenes"


def _tiny_inverse_error(variant, n: int | None = 8) -> tuple[float, pf.History]:
    """The run for 3 steps on an ``n x n`` mesh (``None``: the scene's): the initial field's
    error and the history."""
    from prdp_fem.inverse import initial_params

    variant = with_overrides(variant, {"optimizer": {"steps": 3}})
    if n is not None:
        variant = with_overrides(variant, {"mesh": {"n": n}})
    setup = build_inverse(variant)
    options = invert_options(variant, setup.disc)
    start = float(setup.problem.parameter_error(initial_params(setup.problem,
                                                                options["init"])))
    return start, pf.invert(setup.problem, **options).history


@pytest.mark.slow  # about a minute: eight runs, each compiled
@pytest.mark.parametrize(("name", "n"), [("optimizers_source", None),
                                         ("optimizers_coefficient", 8)])
def test_optimizer_scene_runs_each_lower_the_parameter_error(name, n):
    """Source: the scene's 24 x 24 mesh (Adam's step is tuned to its scaling); coefficient:
    8 x 8 instead of 16 x 16."""
    scene = load_scene(SCENES / f"{name}.toml")
    names = [n for n, _ in scene.runs()]
    assert {"adam", "lbfgs", "gauss_newton", "newton_cg", "hig", "hig rank 40"} <= set(names)
    for run, variant in scene.runs():
        start, history = _tiny_inverse_error(variant, n)
        errors = history.column("parameter_error")
        assert np.all(np.isfinite(errors)) and len(errors) == 3, run
        assert errors[-1] < 0.9 * start, (run, start, errors)


@pytest.mark.slow  # four optimisers' programs (8 s)
def test_optimizer_scene_second_order_runs_lower_the_error():
    """The default-suite slice of the test above: Gauss-Newton and HIG on the source scene.
    The error falls from the zero start, and the objective falls at every step (the error
    itself need not: on a coarse mesh the discrete optimum is farther from the continuous
    truth than an intermediate iterate may be)."""
    scene = load_scene(SCENES / "optimizers_source.toml")
    runs = dict(scene.runs())
    for run in ("gauss_newton", "hig"):
        start, history = _tiny_inverse_error(runs[run])
        errors, losses = history.column("parameter_error"), history.column("loss")
        assert np.all(np.isfinite(errors)) and errors[-1] < 0.5 * start, (run, errors)
        assert np.all(np.diff(losses) <= 1e-12 * losses[0]), (run, losses)


@pytest.mark.slow  # about a minute: six trainings, each compiled
def test_learned_scene_runs_each_lower_the_validation_misfit():
    from prdp_fem.learning.learned import train, validation
    from prdp_fem.scene.build import build_learned, train_options

    scene = load_scene(SCENES / "learned.toml")
    for run, variant in scene.runs():
        full_batch = variant.learned.batch_size == variant.learned.samples
        variant = with_overrides(variant, {"mesh": {"n": 5}, "learned": {
            "samples": 8, "validation_samples": 4, "epochs": 3,
            "batch_size": 8 if full_batch else 4}})
        setup = build_learned(variant)
        start = float(validation(setup.network, setup.problem, setup.validation_set)[0])
        records = train(setup.problem, setup.network, setup.train_set, setup.validation_set,
                        **train_options(variant, setup.problem)).records
        misfits = np.array([r.validation_misfit for r in records])
        assert np.all(np.isfinite(misfits)) and misfits[-1] < start, (run, start, misfits)
