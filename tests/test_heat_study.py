"""Heat studies (issue 6): the [heat] scene table, its build, the study's records and summary
against the scripting API, resume, the CLI, and the scene shipped in examples/scenes."""

import math
from pathlib import Path

import numpy as np
import optax
import pytest
from conftest import resume_after_losing_done

from prdp_fem.cli.main import main
from prdp_fem.inverse import settled
from prdp_fem.learning import heat
from prdp_fem.scene import SceneError, load_scene, parse_scene
from prdp_fem.scene.build import build_heat, heat_train_options, optimizer
from prdp_fem.scene.spec import SceneSolverConfigError, with_overrides
from prdp_fem.studies import run_study
from prdp_fem.studies.runner import ResultsLog, heat_history

SCENES = Path(__file__).resolve().parent.parent / "examples" / "scenes"

TINY_HEAT = """
name = "tiny_heat"
[mesh]
n = 4
[pde]
source = 0.0
[heat]
dt = 0.02
steps = 4
trajectories = 6
validation_trajectories = 3
test_trajectories = 2
hidden = [8]
unroll = 2
epochs = 4
batch_size = 6
[refinement]
kind = "prdp"
rtol = 1e-2
rtol_min = 1e-10
restart = false
[optimizer]
name = "adam"
learning_rate = 3e-3
decay = "cosine"
[study]
band = 0.05
reached = "at_or_below"
[[study.runs]]
name = "nog prdp"
[[study.runs]]
name = "nog converged"
refinement = { kind = "converged", rtol = 1e-10 }
[[study.runs]]
name = "wig prdp"
heat = { mode = "wig" }
[[study.runs]]
name = "prediction"
heat = { setup = "prediction" }
"""


@pytest.fixture
def tiny(tmp_path):
    path = tmp_path / "heat.toml"
    path.write_text(TINY_HEAT)
    return load_scene(path)


# --------------------------------------------------------------------------------------
# the scene table
# --------------------------------------------------------------------------------------


def test_a_heat_table_makes_a_heat_study_and_runs_merge_it(tiny):
    assert tiny.study.kind == "heat" and tiny.inverse is None
    assert tiny.heat.windows == 6 * 3 and tiny.refinement.rtol_min == 1e-10
    runs = dict(tiny.runs())
    assert runs["wig prdp"].heat.mode == "wig" and runs["wig prdp"].heat.hidden == (8,)
    assert runs["prediction"].heat.setup == "prediction"
    assert runs["nog converged"].refinement.kind == "converged"
    # no runs given: the scene and a converged baseline (correction), the scene alone else
    bare = parse_scene({"heat": {}})
    assert [n for n, _ in bare.runs()] == ["converged", "scene"]
    assert bare.optimizer.name == "adam"  # heat's default: mini-batches
    alone = parse_scene({"heat": {"setup": "prediction"}})
    assert [n for n, _ in alone.runs()] == ["scene"]


@pytest.mark.parametrize(("table", "error", "match"), [
    ({"heat": {"unroll": 11}}, SceneError, r"heat.unroll = 11: expected an integer from 1 to "
                                           r"heat.steps = 10"),
    ({"heat": {"batch_size": 300}}, SceneError, r"heat.batch_size = 300: expected at most the "
                                                r"256 training windows"),
    ({"heat": {"mode": "full"}}, SceneError, r"heat.mode = 'full': expected one of"),
    ({"heat": {"setup": "hybrid"}}, SceneError, r"heat.setup = 'hybrid'"),
    ({"heat": {"dt": 0}}, SceneError, r"heat.dt = 0: expected a finite number > 0"),
    ({"heat": {"epoch": 3}}, SceneError, r"unknown key 'heat.epoch'"),
    ({"heat": {}, "inverse": {}}, SceneError, r"an \[inverse\] section with study.kind = "
                                              r"'heat'"),
    ({"heat": {}, "study": {"kind": "inverse"}, "inverse": {"truth": "x"}}, SceneError,
     r"a \[heat\] section with study.kind = 'inverse'"),
    ({"heat": {}, "optimizer": {"name": "lbfgs"}}, SceneSolverConfigError,
     r"optimizer.name = 'lbfgs' with study.kind = 'heat': expected 'adam' or 'sgd'"),
    ({"optimizer": {"name": "lbfgs", "decay": "cosine"}}, SceneSolverConfigError,
     r"optimizer.decay = 'cosine' with optimizer.name = 'lbfgs'"),
    ({"refinement": {"rtol": 1e-2, "rtol_factor": 1.5}}, SceneError,
     r"refinement.rtol_factor = 1.5"),
])
def test_bad_heat_tables_name_the_key_and_the_expectation(table, error, match):
    with pytest.raises(error, match=match):
        parse_scene({"name": "bad", **table}, source="bad.toml")


def test_a_cosine_decay_runs_the_learning_rate_down_to_zero_over_the_updates():
    """SGD on f(x) = x: each update is -learning_rate(t); cosine from 0.1 over 10 updates."""
    scene = parse_scene({"heat": {}, "optimizer": {"name": "sgd", "learning_rate": 0.1,
                                                   "decay": "cosine"}})
    transform = optimizer(scene, 10)
    state, steps = transform.init(np.zeros(())), []
    for _ in range(11):
        update, state = transform.update(np.ones(()), state)
        steps.append(-float(update))
    expected = [0.05 * (1 + math.cos(math.pi * min(t, 10) / 10)) for t in range(11)]
    np.testing.assert_allclose(steps, expected, rtol=1e-12, atol=1e-15)
    constant = optimizer(with_overrides(scene, {"optimizer": {"decay": "constant"}}), 10)
    assert -float(constant.update(np.ones(()), constant.init(np.zeros(())))[0]) == 0.1


def test_build_heat_splits_one_draw_of_trajectories_and_passes_kappa_and_source():
    """kappa = 2 and a source: the trajectories are those of heat.reference_trajectories with
    the same data, split train / validation / test in that order."""
    import prdp_fem as pf

    scene = parse_scene({"mesh": {"n": 4}, "pde": {"kappa": 2.0, "source": "x"}, "heat": {
        "steps": 3, "trajectories": 2, "validation_trajectories": 1, "test_trajectories": 1,
        "unroll": 1, "batch_size": 2, "hidden": [4]}})
    setup = build_heat(scene)
    disc = setup.disc
    initial = heat.random_initial_states(disc, 4, seed=0, width=0.2)
    expected = heat.reference_trajectories(disc, initial, dt=0.02, steps=3, kappa=2.0,
                                           source=disc.interpolate(lambda x: x[0]))
    np.testing.assert_allclose(np.concatenate([setup.train_set.states,
                                               setup.validation_set.states,
                                               setup.test_set.states]),
                               expected.states, rtol=1e-12, atol=1e-14)
    u = setup.train_set.states[0, 0]
    step = heat.heat_step(setup.problem, u, pf.ConvergedCG(rtol=1e-12))[0]
    direct = heat.heat_step(heat.heat_problem(disc, 0.02, kappa=2.0, source=disc.interpolate(
        lambda x: x[0])), u, pf.ConvergedCG(rtol=1e-12))[0]
    np.testing.assert_allclose(step, direct, rtol=1e-12)


# --------------------------------------------------------------------------------------
# the study
# --------------------------------------------------------------------------------------


@pytest.mark.slow  # the learned and inverse studies check the same records and resume
def test_heat_study_records_every_epoch_matches_train_and_resumes(tiny, tmp_path,
                                                                  monkeypatch):
    out = tmp_path / "out"
    result = run_study(tiny, out)
    records = ResultsLog(out / "results.jsonl").records()
    names = ["nog prdp", "nog converged", "wig prdp", "prediction"]
    assert [r["run"] for r in records if r["type"] == "done"] == names
    epochs = {n: [r for r in records if r["type"] == "epoch" and r["run"] == n] for n in names}
    assert all(len(rows) == 4 for rows in epochs.values())
    # the study's run is what heat.train gives from a script, epoch by epoch
    variant = dict(tiny.runs())["wig prdp"]
    setup = build_heat(variant)
    direct = heat.train(setup.problem, setup.network, setup.train_set, setup.validation_set,
                        test_set=setup.test_set,
                        **heat_train_options(variant, setup.problem)).records
    mine = epochs["wig prdp"]
    for key in ("validation_error", "test_error", "train_loss"):
        np.testing.assert_allclose([r[key] for r in mine], [getattr(r, key) for r in direct],
                                   rtol=1e-9, err_msg=key)
    for key in ("primal_iterations", "adjoint_iterations_total", "validation_iterations",
                "rtol"):
        assert [r[key] for r in mine] == [getattr(r, key) for r in direct], key
    assert mine[-1]["adjoint_iterations_total"] > 0 == epochs["nog prdp"][-1][
        "adjoint_iterations_total"]
    # the summary: the paired converged run, the saving read from the records
    rows = {row["run"]: row for row in result.summary}
    prdp_row, base = rows["nog prdp"], rows["nog converged"]
    assert prdp_row["converged_run"] == "nog converged" and rows["wig prdp"]["converged_run"] == ""
    assert rows["prediction"]["training"] == "none" and rows["prediction"]["cg_iterations"] == 0
    assert prdp_row["test_error"] == epochs["nog prdp"][-1]["test_error"]
    history, base_history = heat_history(epochs["nog prdp"]), heat_history(epochs["nog converged"])
    hit = settled(history, base_history[-1].parameter_error, 0.05, at_or_below=True)
    if hit is None:
        assert math.isnan(prdp_row["time_saving"]) and prdp_row["reached_epoch"] == ""
    else:
        # same target, both sides: the converged partner's own epoch at its final error
        base_hit = settled(base_history, base_history[-1].parameter_error, 0.05,
                           at_or_below=True)
        assert prdp_row["reached_epoch"] == hit.step
        assert prdp_row["time_saving"] == pytest.approx(1 - hit.time / base_hit.time)
        # every CG iteration that ran: training and validation solves
        total = hit.primal_iterations + hit.adjoint_iterations_total + \
            hit.validation_iterations
        base_total = base_hit.primal_iterations + base_hit.adjoint_iterations_total + \
            base_hit.validation_iterations
        assert hit.validation_iterations > 0 and base_hit.validation_iterations > 0
        assert prdp_row["iteration_saving"] == pytest.approx(1 - total / base_total)
    assert prdp_row["equal_epochs_iteration_ratio"] == pytest.approx(
        prdp_row["cg_iterations"] / base["cg_iterations"])
    assert prdp_row["cg_iterations"] < base["cg_iterations"]  # rtol 1e-2 against 1e-10
    assert sorted(p.name for p in result.figures) == [
        "error_vs_iterations.png", "error_vs_time.png", "iterations_over_steps.png"]
    # resume: a run whose 'done' record is lost runs again, alone, to the same numbers
    resumed = resume_after_losing_done(tiny, out, "prediction", "_run_heat", monkeypatch)
    again = {row["run"]: row for row in resumed.summary}
    assert again["prediction"]["test_error"] == pytest.approx(
        rows["prediction"]["test_error"], rel=1e-9)


@pytest.mark.slow  # the study command is covered by the inverse and learned studies
def test_the_cli_runs_a_heat_study_with_epochs_from_steps(tmp_path, capsys):
    path = tmp_path / "two_runs.toml"  # the tiny scene's first two runs
    path.write_text(TINY_HEAT[:TINY_HEAT.index('[[study.runs]]\nname = "wig prdp"')])
    out = tmp_path / "cli"
    assert main(["study", str(path), "--steps", "2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "heat study of 2 configuration(s)" in printed and "test_error" in printed
    assert "time_saving" in printed and "nog converged" in printed
    epochs = [r for r in ResultsLog(out / "results.jsonl").records() if r["type"] == "epoch"]
    assert {r["epoch"] for r in epochs} == {1, 2} and len(epochs) == 2 * 2
    assert main(["study", str(path), "--steps", "0", "--out", str(tmp_path / "x")]) == 2
    assert "a heat study's epochs" in capsys.readouterr().err


def test_the_example_heat_scene_pairs_every_correction_mode_with_a_converged_run():
    scene = load_scene(SCENES / "heat.toml")
    runs = dict(scene.runs())
    grid = {(v.heat.setup, v.heat.mode, v.refinement.kind) for v in runs.values()}
    assert {(s, m) for s, m, _ in grid} == {(s, m) for s in ("correction", "prediction")
                                             for m in heat.MODES}
    for mode in heat.MODES:
        assert {("correction", mode, "prdp"), ("correction", mode, "converged")} <= grid
    variant = runs["correction wig prdp"]
    options = heat_train_options(variant, build_heat(variant).problem)
    assert options["mode"] == "wig" and options["unroll"] == 3
    assert isinstance(options["optimizer"], optax.GradientTransformation)
    assert options["refinement"].tolerance_mode
