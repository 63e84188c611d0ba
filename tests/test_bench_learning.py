"""``prdp-fem bench learning`` (issue 57): a learned or heat scene's study once per seed, the
rows read from each study's summary, the goal counted per run, the runs ranked per seed."""

import csv
import math

import numpy as np
import pytest

from prdp_fem.bench.learning import (
    GOAL_ITERATION_SAVING,
    GOAL_TIME_SAVING,
    LearningRow,
    coarse_ceiling,
    learning_rows,
    learning_saving,
    learning_summary,
    rankings,
    seeded_scene,
    throughput,
)
from prdp_fem.cli.main import main
from prdp_fem.errors import SolverConfigError
from prdp_fem.scene import load_scene
from prdp_fem.studies.runner import StudyError, heat_history, study_histories

TINY_HEAT = """
name = "tiny_heat"
[mesh]
n = 4
[pde]
source = 0.0
[heat]
dt = 0.02
steps = 3
trajectories = 4
validation_trajectories = 2
test_trajectories = 2
hidden = [6]
unroll = 2
epochs = 3
batch_size = 3
[refinement]
kind = "prdp"
rtol = 1e-2
rtol_min = 1e-10
restart = false
[optimizer]
name = "adam"
learning_rate = 3e-3
[study]
band = 0.5
[[study.runs]]
name = "nog prdp"
[[study.runs]]
name = "nog converged"
refinement = { kind = "converged", rtol = 1e-10 }
[[study.runs]]
name = "prediction"
heat = { setup = "prediction" }
"""


def _row(**changes) -> LearningRow:
    row = LearningRow("s", 0, "prdp", "converged", 1.0, 0.005, 10.0, 1000, 7, 0.7, 0.9)
    return row._replace(**changes)


# --------------------------------------------------------------------------------------
# rows, summary and rankings from study summaries
# --------------------------------------------------------------------------------------


def test_heat_rows_pair_each_run_with_its_converged_partner():
    summary = [
        {"run": "nog prdp", "converged_run": "nog converged", "test_error": 0.0102,
         "time_s": 5.0, "cg_iterations": 400, "reached_epoch": 9, "time_saving": 0.65,
         "iteration_saving": 0.85},
        {"run": "nog converged", "converged_run": "", "test_error": 0.01, "time_s": 9.0,
         "cg_iterations": 2000, "reached_epoch": "", "time_saving": math.nan,
         "iteration_saving": math.nan},
        {"run": "emulator", "converged_run": "", "test_error": 0.5, "time_s": 1.0,
         "cg_iterations": 0, "reached_epoch": "", "time_saving": math.nan,
         "iteration_saving": math.nan}]
    prdp, converged, emulator = learning_rows("heat", 3, "heat", summary)
    assert (prdp.scene, prdp.seed, prdp.converged_run, prdp.reached_epoch) == (
        "heat", 3, "nog converged", 9)
    assert prdp.error_gap == pytest.approx(0.02) and prdp.goal_met
    assert converged.converged_run is None and math.isnan(converged.error_gap)
    assert not converged.goal_met and converged.cg_iterations == 2000
    assert emulator.converged_run is None and emulator.reached_epoch is None


def test_learned_rows_read_the_learned_summary_and_its_own_reference():
    """A learned study's converged run names itself as its reference: no partner, no saving."""
    summary = [
        {"run": "converged", "reference": "converged", "final_error": 0.32, "time_s": 700.0,
         "cg_iterations": 15_000_000, "reached_step": 16, "time_saving": 0.0,
         "iteration_saving": 0.0},
        {"run": "prdp", "reference": "converged", "final_error": 0.3204, "time_s": 360.0,
         "cg_iterations": 6_000_000, "reached_step": 16, "time_saving": 0.5,
         "iteration_saving": 0.61},
        {"run": "lbfgs prdp", "reference": None, "final_error": 0.4, "time_s": 100.0,
         "cg_iterations": 10, "reached_step": "", "time_saving": math.nan,
         "iteration_saving": math.nan}]
    converged, prdp, other = learning_rows("plate", 0, "learned", summary)
    assert converged.converged_run is None and math.isnan(converged.time_saving)
    assert converged.reached_epoch is None
    assert prdp.error_gap == pytest.approx(0.3204 / 0.32 - 1)
    assert (prdp.reached_epoch, prdp.time_saving, prdp.iteration_saving) == (16, 0.5, 0.61)
    assert not prdp.goal_met  # 50 % of the wall time: below the goal
    assert other.converged_run is None and math.isnan(other.error_gap)
    with pytest.raises(SolverConfigError, match="kind='inverse'"):
        learning_rows("plate", 0, "inverse", summary)


@pytest.mark.parametrize(("changes", "met"), [
    ({}, True),
    ({"time_saving": GOAL_TIME_SAVING, "iteration_saving": GOAL_ITERATION_SAVING}, True),
    ({"time_saving": GOAL_TIME_SAVING - 1e-9}, False),
    ({"iteration_saving": GOAL_ITERATION_SAVING - 1e-9}, False),
    ({"reached_epoch": None}, False),
    ({"time_saving": math.nan}, False),
])
def test_the_goal_needs_both_savings_in_the_band(changes, met):
    assert _row(**changes).goal_met is met


def _epochs(levels, seconds, iterations):
    """Heat epoch records: epoch i at tolerance levels[i], costing seconds[i] and
    iterations[i] (cumulated, as the records hold them)."""
    return heat_history([
        {"epoch": i + 1, "iterations": 0, "adjoint_iterations": 0, "rtol": rtol,
         "primal_iterations": int(sum(iterations[:i + 1])), "adjoint_iterations_total": 0,
         "time": float(sum(seconds[:i + 1])), "train_loss": 1.0, "validation_error": 1.0,
         "test_error": 1.0}
        for i, rtol in enumerate(levels)])


def test_the_coarse_ceiling_is_the_first_level_s_cost_per_epoch_over_the_partner_s():
    """Three epochs at 1e-2 (1 s, 20 its each), then finer; the partner: 2 s and 100 its per
    epoch. Never refining, the run would save 1 - 1/2 of the time and 1 - 20/100 of the CG
    iterations, however its later epochs went."""
    run = _epochs([1e-2] * 3 + [1e-4, 1e-6], [1, 1, 1, 3, 5], [20, 20, 20, 90, 200])
    partner = _epochs([1e-10] * 4, [2] * 4, [100] * 4)
    assert coarse_ceiling(run, partner) == pytest.approx((0.5, 0.8))
    never = _epochs([1e-2] * 2, [3, 3], [50, 50])  # never refines: all its epochs count
    assert coarse_ceiling(never, partner) == pytest.approx((-0.5, 0.5))
    assert all(math.isnan(v) for v in coarse_ceiling(_epochs([], [], []), partner))


def test_throughput_is_samples_per_second_of_training():
    history = _epochs([1e-2] * 4, [0.5] * 4, [10] * 4)  # 4 epochs in 2 s
    assert throughput(history, 64) == pytest.approx(128.0)
    assert math.isnan(throughput(_epochs([], [], []), 64))


def test_study_histories_refuse_a_study_without_epochs_or_steps(tmp_path):
    with pytest.raises(StudyError, match=r"study.kind = 'h'; expected an inverse, learned or "
                                         r"heat study"):
        study_histories(load_scene("poisson_h"), tmp_path)


def test_the_summary_takes_savings_over_the_seeds_in_the_band_and_errors_over_all():
    rows = [_row(seed=0),
            _row(seed=1, time_saving=0.3, iteration_saving=0.5, test_error=3.0),
            _row(seed=2, reached_epoch=None, time_saving=np.nan, iteration_saving=np.nan,
                 test_error=2.0, error_gap=0.03),
            _row(seed=0, run="converged", converged_run=None, time_saving=np.nan,
                 iteration_saving=np.nan, reached_epoch=None, error_gap=np.nan)]
    prdp, converged = learning_summary(rows)
    assert (prdp.run, prdp.instances, prdp.reached, prdp.met) == ("prdp", 3, 2, 1)
    assert prdp.time_saving == pytest.approx(0.5)       # median of 0.7 and 0.3
    assert (prdp.time_saving_low, prdp.time_saving_high) == (0.3, 0.7)
    assert prdp.iteration_saving == pytest.approx(0.7)  # median of 0.9 and 0.5
    assert (prdp.test_error, prdp.test_error_low, prdp.test_error_high) == (2.0, 1.0, 3.0)
    assert prdp.error_gap == pytest.approx(0.005)       # median of 0.5 %, 0.5 %, 3 %
    assert (converged.instances, converged.reached, converged.met) == (1, 0, 0)
    assert math.isnan(converged.time_saving) and math.isnan(converged.error_gap)


def test_rankings_count_each_order_of_the_runs_by_test_error():
    def seed(number, one, nog, wig):
        return [_row(seed=number, run=name, test_error=error)
                for name, error in (("one", one), ("nog", nog), ("wig", wig))]

    rows = seed(0, 3.0, 2.0, 1.0) + seed(1, 3.0, 1.0, 2.0) + seed(2, 0.3, 0.2, 0.1)
    first, second = rankings(rows)
    assert (first.order, first.seeds, first.instances) == (("wig", "nog", "one"), (0, 2), 3)
    assert (second.order, second.seeds) == (("nog", "wig", "one"), (1,))


def test_seeded_scene_sets_the_learned_or_heat_seed_and_refuses_others():
    heat = seeded_scene(load_scene("heat_emulator"), 4)
    assert heat.heat.seed == 4
    assert seeded_scene(load_scene("learned_plate"), 2).learned.seed == 2
    with pytest.raises(SolverConfigError, match=r"study.kind = 'inverse'"):
        seeded_scene(load_scene("mother"), 1)
    for bad in (-1, True, 1.5):
        with pytest.raises(SolverConfigError, match="expected an integer >= 0"):
            seeded_scene(load_scene("heat_emulator"), bad)


# --------------------------------------------------------------------------------------
# the command
# --------------------------------------------------------------------------------------


@pytest.fixture
def tiny_heat(tmp_path):
    path = tmp_path / "tiny_heat.toml"
    path.write_text(TINY_HEAT)
    return path


def _csv(path) -> list[dict]:
    with open(path) as stream:
        return list(csv.DictReader(stream))


def test_bench_learning_runs_a_study_per_seed_and_reports_its_own_figures(tiny_heat, tmp_path,
                                                                          capsys):
    """Each seed's study lands in its own directory, draws its own data (other errors), and
    the bench's rows are that study's summary figures; the summary counts them; a resumed
    bench reads every run back and writes the same tables."""
    out = tmp_path / "bench"
    command = ["bench", "learning", "--scene", str(tiny_heat), "--seeds", "0", "1",
               "--out", str(out)]
    assert main(command) == 0
    printed = capsys.readouterr().out
    header = printed.splitlines()[0]  # the device: "CPU", or "N x CPU" with forced devices
    assert header.startswith(f"learning saving: 1 scene(s) x 2 seed(s), 6 run(s) into {out}/ "
                             "on ") and header.endswith("CPU")
    written = _csv(out / "learning.csv")
    assert [(r["seed"], r["run"]) for r in written] == [
        (seed, run) for seed in "01" for run in ("nog prdp", "nog converged", "prediction")]
    for seed in "01":
        study = {r["run"]: r for r in _csv(out / "tiny_heat" / f"seed-{seed}" / "summary.csv")}
        assert load_scene(tiny_heat).heat.seed == 0  # the bench's seed, not the file's
        mine = {r["run"]: r for r in written if r["seed"] == seed}
        for run, row in mine.items():
            assert float(row["test_error"]) == float(study[run]["test_error"])
            assert int(row["cg_iterations"]) == int(float(study[run]["cg_iterations"]))
        prdp = mine["nog prdp"]
        assert prdp["converged_run"] == "nog converged"
        assert mine["prediction"]["converged_run"] == ""
        assert float(prdp["error_gap"]) == pytest.approx(
            float(study["nog prdp"]["test_error"]) / float(study["nog converged"]["test_error"])
            - 1, rel=1e-12)
        assert prdp["reached_epoch"] == study["nog prdp"]["reached_epoch"]
        histories = study_histories(seeded_scene(load_scene(tiny_heat), int(seed)),
                                    out / "tiny_heat" / f"seed-{seed}")
        ceiling = coarse_ceiling(histories["nog prdp"], histories["nog converged"])
        assert (float(prdp["time_ceiling"]), float(prdp["iteration_ceiling"])) == ceiling
        assert prdp["time_ceiling"] != "nan" and mine["prediction"]["time_ceiling"] == "nan"
        assert load_scene(tiny_heat).heat.windows == 8  # 4 trajectories x 2 windows
        for run, row in mine.items():  # every run's throughput, the emulator's too: two
            history = histories[run]   # batches of 3 windows an epoch (the last 2 dropped)
            assert float(row["samples_per_s"]) == pytest.approx(
                6 * 3 / history[-1].time, rel=1e-12)
        saving = float(study["nog prdp"]["time_saving"])
        assert (math.isnan(saving) and prdp["time_saving"] == "nan") or \
            float(prdp["time_saving"]) == saving
    errors = {r["seed"]: float(r["test_error"]) for r in written if r["run"] == "prediction"}
    assert errors["0"] != errors["1"]  # another seed: other data and network
    summary = {r["run"]: r for r in _csv(out / "seeds.csv")}
    reached = [r for r in written if r["run"] == "nog prdp" and r["reached_epoch"]]
    assert summary["nog prdp"]["instances"] == "2"
    assert int(summary["nog prdp"]["reached"]) == len(reached)
    assert float(summary["prediction"]["test_error_high"]) == max(errors.values())
    ranking = _csv(out / "ranking.csv")
    assert sorted(seed for r in ranking for seed in r["seeds"].split()) == ["0", "1"]
    for order in ranking:  # each seed's runs sorted by their test errors
        for seed in order["seeds"].split():
            runs = sorted((r for r in written if r["seed"] == seed),
                          key=lambda r: float(r["test_error"]))
            assert order["order"] == " < ".join(r["run"] for r in runs)

    assert main([*command, "--resume"]) == 0  # everything read back, nothing run
    printed = capsys.readouterr().out
    assert "6 of 6 run(s) read back" in printed
    assert _csv(out / "learning.csv") == written
    assert main(["bench", "learning", "--scene", str(tiny_heat), "--seeds", "0",
                 "--out", str(out), "--resume"]) == 2  # other options: not this run
    assert "was run with other --seeds" in capsys.readouterr().err


def test_a_stop_asked_for_during_a_seeds_study_lands_before_the_next_seed(tiny_heat,
                                                                          tmp_path):
    """A Ctrl-C that arrives while a seed's study finishes (its summary, figures) stops the
    benchmark before the next seed draws its data: its directory is never made."""
    class StopAfterFirstStudy:
        def __init__(self):
            self.finished, self.stop = [], False

        def run_started(self, name, steps):
            self.stop_if_requested()

        def step(self):
            pass

        def run_finished(self, name, skipped):
            self.finished.append(name)
            self.stop = len(self.finished) == 3  # the seed's last run: the request lands

        def stop_if_requested(self):
            if self.stop:
                raise KeyboardInterrupt

    progress, out = StopAfterFirstStudy(), tmp_path / "bench"
    with pytest.raises(KeyboardInterrupt):
        learning_saving(load_scene(tiny_heat), [0, 1], out, progress=progress)
    assert progress.finished == ["nog prdp", "nog converged", "prediction"]
    assert (out / "seed-0" / "summary.csv").exists() and not (out / "seed-1").exists()


@pytest.mark.parametrize(("argv", "message"), [
    (["--scene", "mother"], "study.kind = 'inverse'; expected a learned or heat scene"),
    (["--seeds", "1", "1"], "--seeds 1 1: expected distinct integers >= 0"),
    (["--seeds", "-1"], "--seeds -1: expected distinct integers >= 0"),
    (["--resume"], "--resume: expected --out DIR"),
    (["--scene", "heat_emulator", "heat_emulator"], "expected scenes of distinct names"),
])
def test_bench_learning_bad_options_are_one_line_and_exit_2(argv, message, capsys):
    assert main(["bench", "learning", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


TINY_LEARNED = """
name = "tiny_learned"
[mesh]
n = 5
[inverse]
unknown = "source"
[learned]
samples = 8
validation_samples = 4
test_samples = 3
hidden = [4]
epochs = 3
batch_size = 3
[optimizer]
name = "adam"
learning_rate = 3e-3
[[study.runs]]
name = "prdp"
[[study.runs]]
name = "converged"
refinement = { kind = "converged", rtol = 1e-10 }
"""


@pytest.mark.slow  # the heat scene's end-to-end test covers the command in the default suite
def test_bench_learning_reads_a_learned_study_against_its_own_converged_run(tmp_path, capsys):
    """A learned scene: the PRDP run's partner is the converged run of its optimiser and
    batch (the learned summary's reference), the test error its final error, and the
    throughput counts the samples trained (two batches of 3 of the 8 an epoch)."""
    scene = tmp_path / "tiny_learned.toml"
    scene.write_text(TINY_LEARNED)
    out = tmp_path / "bench"
    assert main(["bench", "learning", "--scene", str(scene), "--seeds", "3", "--out",
                 str(out)]) == 0
    rows = {r["run"]: r for r in _csv(out / "learning.csv")}
    study = {r["run"]: r for r in _csv(out / "tiny_learned" / "seed-3" / "summary.csv")}
    assert rows["prdp"]["converged_run"] == "converged" == study["prdp"]["reference"]
    assert rows["converged"]["converged_run"] == ""
    for run, row in rows.items():
        assert float(row["test_error"]) == float(study[run]["final_error"])
        assert row["seed"] == "3"
    assert float(rows["prdp"]["error_gap"]) == pytest.approx(
        float(study["prdp"]["final_error"]) / float(study["converged"]["final_error"]) - 1)
    histories = study_histories(seeded_scene(load_scene(scene), 3),
                                out / "tiny_learned" / "seed-3")
    assert histories["prdp"][-1].validation_iterations > 0  # every solve that ran counts
    assert int(rows["prdp"]["cg_iterations"]) == histories["prdp"][-1].total_iterations
    assert float(rows["prdp"]["samples_per_s"]) == pytest.approx(
        6 * 3 / histories["prdp"][-1].time, rel=1e-12)
