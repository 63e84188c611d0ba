"""The prdp-fem commands: outputs, exit codes 0 / 2 / 130, kill and resume (in a fresh process
where the test needs one: killed, interrupted, or exiting through the program)."""

import contextlib
import csv
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import meshio
import numpy as np
import pytest
from conftest import SMALL_STUDY as SMALL

from prdp_fem.cli._shared import Bars, stop_between_steps
from prdp_fem.cli.main import main

ROOT = Path(__file__).resolve().parent.parent
MESHES = sorted((ROOT / "meshes").glob("*.msh"))
DETERMINISTIC = ("run", "final_error", "final_K", "cg_iterations", "evaluations",
                 "reached_step", "iterations_to_target")


# subprocesses import this checkout's package, whatever is installed and whatever their cwd
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(
    [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}


def cli(*args, cwd=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "prdp_fem.cli.main", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=timeout, env=ENV)


def in_process(*args) -> subprocess.CompletedProcess:
    """What ``cli(*args)`` gives, by main() in this process (its imports and the programs it
    compiled are this process's: a second study of a scene compiles nothing new)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in args])
    return subprocess.CompletedProcess(args, code, out.getvalue(), err.getvalue())


def start(*args, cwd=None):
    return subprocess.Popen([sys.executable, "-m", "prdp_fem.cli.main", *map(str, args)], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)


@pytest.fixture
def scene(tmp_path):
    path = tmp_path / "small.toml"
    path.write_text(SMALL.replace("STEPS", "12"))
    return path


@pytest.fixture(scope="module")
def finished_study(tmp_path_factory):
    """``(scene, out, done)``: the small study run to the end once, by the command's main (its
    outputs are read, never written, by the tests that share it)."""
    root = tmp_path_factory.mktemp("finished")
    path = root / "small.toml"
    path.write_text(SMALL.replace("STEPS", "12"))
    return path, root / "out", in_process("study", path, "--out", root / "out")


def summary(directory: Path) -> list[dict]:
    with open(directory / "summary.csv") as stream:
        return [{k: row[k] for k in DETERMINISTIC} for row in csv.DictReader(stream)]


def assert_png(path: Path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000, path


def test_study_writes_every_output_and_they_parse(finished_study):
    scene, out, done = finished_study
    assert done.returncode == 0, done.stderr
    manifest = json.loads((out / "study.json").read_text())
    assert manifest["configurations"] == ["converged", "fixed K=3", "prdp"]
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert sum(r["type"] == "step" for r in records) == 36
    rows = summary(out)
    assert [r["run"] for r in rows] == manifest["configurations"]
    assert all(0 < float(r["final_error"]) < 0.3 for r in rows)  # 12 L-BFGS steps, n = 8
    for name in ("error_vs_time", "error_vs_iterations", "iterations_over_steps", "fields"):
        assert_png(out / "figures" / f"{name}.png")
    for run in ("converged", "fixed_K_3", "prdp"):
        field = meshio.read(out / "fields" / f"{run}.vtu")
        assert {"recovered", "truth", "error"} <= set(field.point_data)
        assert np.isfinite(field.point_data["recovered"]).all()
    assert "converged" in done.stdout and "time_saving" in done.stdout
    # one plain line on the PRDP run, by the summary's same-target rule
    with open(out / "summary.csv") as stream:
        prdp_row = {r["run"]: r for r in csv.DictReader(stream)}["prdp"]
    lines = done.stdout.splitlines()
    [headline] = [line for line in lines if line.startswith("PRDP (prdp)")]
    # the table opens with it: the line comes before the table's header
    assert lines.index(headline) < next(i for i, line in enumerate(lines) if "time_saving" in line)
    if prdp_row["reached_step"]:
        assert headline.startswith("PRDP (prdp) reached the converged run's error in ")
        assert f"{100 * float(prdp_row['time_saving']):.0f} % less wall time" in headline
    else:
        assert "did not settle within +-1 %" in headline and "no saving" in headline
    # nothing is overwritten: a second study into the same directory is refused
    again = in_process("study", scene, "--out", out)
    assert again.returncode == 2 and "pass --resume" in again.stderr
    assert again.stderr.count("\n") == 1 and "Traceback" not in again.stderr
    assert summary(out) == rows


def test_killed_study_resumes_to_the_same_summary(finished_study, tmp_path):
    scene, reference_out, reference = finished_study  # the same scene run uninterrupted
    assert reference.returncode == 0, reference.stderr
    out = tmp_path / "killed"
    process = start("study", scene, "--out", out)
    results = out / "results.jsonl"
    deadline = time.time() + 240
    while time.time() < deadline:  # kill once the first configuration has finished
        if results.exists() and '"type": "done"' in results.read_text():
            break
        time.sleep(0.005)
    process.send_signal(signal.SIGKILL)
    process.communicate()
    lines = results.read_text().splitlines()
    finished = [json.loads(x)["run"] for x in lines if '"type": "done"' in x]
    assert 1 <= len(finished) < 3, "the kill should land mid-study"
    resumed = in_process("study", scene, "--out", out, "--resume")
    assert resumed.returncode == 0, resumed.stderr
    assert summary(out) == summary(reference_out)
    records = [json.loads(x) for x in results.read_text().splitlines() if x.startswith("{")]
    assert sum(r["type"] == "done" for r in records) == 3
    assert [r["run"] for r in records if r["type"] == "done"][:len(finished)] == finished


def test_ctrl_c_keeps_records_and_exits_130(tmp_path):
    path = tmp_path / "long.toml"
    path.write_text(SMALL.replace("STEPS", "100000"))
    out = tmp_path / "out"
    process = start("study", path, "--out", out)
    results = out / "results.jsonl"
    deadline = time.time() + 240
    while time.time() < deadline and not (results.exists() and results.stat().st_size > 2000):
        time.sleep(0.02)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130
    assert "interrupted; finished records are kept in" in err and "--resume" in err
    assert "Traceback" not in err
    records = [json.loads(x) for x in results.read_text().splitlines()]
    assert len(records) >= 5 and all(r["type"] == "step" for r in records)


def _interrupts(action) -> bool:
    """Whether ``action`` (then a short wait for the signal's delivery) raises Ctrl-C."""
    try:
        action()
        time.sleep(0.05)
    except KeyboardInterrupt:
        return True
    return False


def test_first_ctrl_c_stops_between_steps_and_a_second_at_once():
    """No KeyboardInterrupt inside a running step (it could land in a JAX host callback)."""
    bars = Bars(total=1)
    ctrl_c = lambda: os.kill(os.getpid(), signal.SIGINT)  # noqa: E731
    before = signal.getsignal(signal.SIGINT)
    with stop_between_steps(bars):
        bars.run_started("run", steps=3)
        assert not _interrupts(ctrl_c) and bars.stop_requested  # deferred to the step's end
        assert _interrupts(bars.step)  # the step's record is written: the stop is here
        assert _interrupts(ctrl_c)  # a second Ctrl-C is not deferred
    assert signal.getsignal(signal.SIGINT) is before
    bars.close()


def test_a_ctrl_c_between_two_runs_stops_before_the_next_one_starts():
    """The stop asked for after a run finished (a study writing its summary, a benchmark
    between two seeds' studies) lands before the next run builds anything, not at the end
    of its first step."""
    bars = Bars(total=2)
    with stop_between_steps(bars):
        bars.run_started("first", steps=1)
        bars.step()
        bars.run_finished("first", skipped=False)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        assert bars.stop_requested
        assert _interrupts(lambda: bars.run_started("second", steps=1))
    bars.close()


BAD_INPUT = [
    (["study", "nope.toml"], "nope.toml: scene file does not exist"),
    (["study", "torus"], "expected a .toml file or a built-in scene"),
    (["invert", "BAD"], "unknown key 'colour'"),
    (["solve", "missing.msh"], "missing.msh: file does not exist"),
    (["solve", "BROKEN"], "could not be read as a mesh"),
    (["mesh-info", "BROKEN"], "could not be read as a mesh"),
    (["study", "mother", "--steps", "-1"], "--steps -1: expected an integer >= 0"),
    (["solve", "poisson_h", "--out", "BAD/u.vtu"], "expected a writable path"),
]


def _bad_input_args(tmp_path, args) -> list[str]:
    bad = tmp_path / "bad.toml"
    bad.write_text("colour = 'red'\n")
    broken = tmp_path / "broken.msh"
    broken.write_text("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 2")
    return [a.replace("BAD", str(bad)).replace("BROKEN", str(broken)) for a in args]


def _assert_one_line_exit_2(code, err, message):
    assert code == 2, err
    assert err.startswith("prdp-fem: error: ") and message in err
    assert err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize(("args", "message"), BAD_INPUT)
def test_bad_input_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys, args, message):
    # main() in this process (the program exits with its code: test_cli.py, and the
    # subprocess case below); relative paths are the working directory's
    args = _bad_input_args(tmp_path, args)
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    try:
        code = main(args)
    except SystemExit as exit:  # an option argparse refuses
        code = exit.code
    _assert_one_line_exit_2(code, capsys.readouterr().err, message)


def test_bad_input_through_the_program_is_one_line_and_exit_2(tmp_path):
    args, message = BAD_INPUT[2]
    done = cli(*_bad_input_args(tmp_path, args), cwd=tmp_path)
    _assert_one_line_exit_2(done.returncode, done.stderr, message)


def test_solve_a_bare_mesh_file_writes_the_solution(tmp_path):
    out = tmp_path / "u.vtu"
    done = in_process("solve", ROOT / "meshes" / "plate_hole.msh", "--out", out, "--reference")
    assert done.returncode == 0, done.stderr
    error = float(done.stdout.split("relative l2 error against pyamg (rtol 1e-12): ")[1].split()[0])
    assert error < 1e-8
    field = meshio.read(out)
    assert field.point_data["u"].min() >= -1e-12 and field.point_data["u"].max() > 0


@pytest.mark.parametrize("mesh", MESHES, ids=[m.name for m in MESHES])
def test_mesh_info_on_each_shipped_mesh(mesh, capsys):
    assert main(["mesh-info", str(mesh)]) == 0
    out = capsys.readouterr().out
    assert "n_cells" in out and "boundary:" in out and "problems:" in out


def test_mesh_info_reports_repairable_problems(tmp_path, capsys):
    points = np.array([[0, 0], [1, 0], [0, 1], [1, 1], [5, 5]], dtype=float)  # node 4 unused
    path = tmp_path / "extra.vtu"
    meshio.write(path, meshio.Mesh(points, [("triangle", np.array([[0, 1, 2], [1, 3, 2]]))]))
    assert main(["mesh-info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "repairable" in out and "unused" in out and "none found" not in out
    assert "n_nodes: 4" in out  # reported after the repair


def test_help_of_every_command_has_examples(capsys):
    for command in ("study", "invert", "solve", "mesh-info", "scenes"):
        with pytest.raises(SystemExit) as done:
            main([command, "--help"])
        assert done.value.code == 0 and "examples:" in capsys.readouterr().out, command


def test_scenes_lists_and_prints(capsys):
    assert main(["scenes"]) == 0
    listing = capsys.readouterr().out
    assert all(name in listing for name in ("mother", "inclusion", "plate_hole", "cube"))
    assert main(["scenes", "cube"]) == 0
    assert 'generator = "unit_cube"' in capsys.readouterr().out


@pytest.mark.slow  # a whole study for the progress bars
def test_progress_is_quiet_when_not_a_terminal(scene, tmp_path):
    done = cli("invert", scene, "--out", tmp_path / "inv", "--steps", "3")
    assert done.returncode == 0, done.stderr
    assert "configurations" not in done.stderr and "it/s" not in done.stderr
    rows = summary(tmp_path / "inv")
    assert [r["run"] for r in rows] == ["small"]


def test_invert_a_builtin_scene_in_3d(tmp_path):
    done = in_process("invert", "cube", "--out", tmp_path / "cube", "--steps", "5")
    assert done.returncode == 0, done.stderr
    field = meshio.read(tmp_path / "cube" / "fields" / "cube.vtu")
    assert field.cells[0].type == "tetra"
    rows = list(csv.DictReader(open(tmp_path / "cube" / "summary.csv")))
    assert float(rows[0]["final_error"]) < 1.0
