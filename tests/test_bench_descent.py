"""``prdp-fem bench descent``: the rows it measures and the table it writes."""

import contextlib
import csv
import io

import pytest

from prdp_fem.bench.descent import descent_runs
from prdp_fem.cli.main import main
from prdp_fem.scene import SceneError, load_scene

SCENE = """
name = "tiny"
[mesh]
generator = "unit_square"
n = 8
[pde]
element = "P1"
kappa_space = "P1"
source = 1.0
dirichlet = 0.0
[inverse]
unknown = "log_kappa"
truth = "0.5*sin(3*x)*y"
observations = "full_field"
noise = 0.01
seed = 1
alpha = 1e-6
regularization = "h1"
[refinement]
kind = "prdp"
K0 = 2
dK = 2
[optimizer]
name = "lbfgs"
steps = 12
"""


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("descent") / "tiny.toml"
    path.write_text(SCENE)
    return path


def test_the_runs_are_the_reference_the_prdp_run_and_an_added_adaptive_run(scene_file):
    runs = descent_runs(load_scene(scene_file))
    assert [(name, variant.refinement.kind) for name, variant in runs] == [
        ("converged", "converged"), ("tiny", "prdp"), ("adaptive", "adaptive")]


def test_a_run_on_another_preconditioner_brings_its_own_converged_run():
    runs = [name for name, _ in descent_runs(load_scene("inclusion"))]
    assert runs[:2] == ["converged", "converged identity"]
    assert "prdp identity" in runs and runs.count("converged identity") == 1


@pytest.fixture(scope="module")
def bench(scene_file, tmp_path_factory):
    """``(out, printed)``: the command run once on the tiny scene for 8 of its 12 steps (its
    table is read, never written, by the tests that share it: the three inversions compile
    once)."""
    out = tmp_path_factory.mktemp("bench") / "bench"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(["bench", "descent", "--scene", str(scene_file), "--steps", "8",
                     "--out", str(out)])
    assert code == 0
    return out, printed.getvalue()


def _rows(out) -> dict:
    """The table's rows by run, in the types of ``descent_rows``' fields."""
    with open(out / "descent.csv") as table:
        rows = list(csv.DictReader(table))
    return {row["run"]: {key: value if key in ("scene", "run", "rule") else float(value)
                         for key, value in row.items() if value != ""} for row in rows}


def test_the_converged_and_adaptive_runs_descend_at_every_step(bench):
    rows = _rows(bench[0])
    converged, adaptive, prdp = rows["converged"], rows["adaptive"], rows["tiny"]
    assert converged["fraction"] == 1.0 and converged["moved"] == 8
    assert converged["error_gap"] == 0.0 and converged["iteration_saving"] == 0.0
    assert adaptive["fraction"] == 1.0 and abs(adaptive["error_gap"]) < 0.01
    # K = 2 on a coefficient problem: truncated adjoint gradients that do not all descend
    assert prdp["moved"] >= 1 and prdp["descending"] <= prdp["moved"]
    assert prdp["rule"] == "prdp" and 0.0 <= prdp["fraction"] <= 1.0


def test_the_command_writes_its_table_and_refuses_to_overwrite_it(bench, scene_file, capsys):
    out, printed = bench
    with open(out / "descent.csv") as table:
        rows = list(csv.DictReader(table))
    assert [row["run"] for row in rows] == ["converged", "tiny", "adaptive"]
    assert float(rows[0]["fraction"]) == 1.0 and rows[0]["steps"] == "8"  # not the scene's 12
    assert "descend" in printed
    assert main(["bench", "descent", "--scene", str(scene_file), "--out", str(out)]) == 2
    assert "descent.csv" in capsys.readouterr().err


def test_a_scene_without_a_converged_reference_is_refused(tmp_path):
    path = tmp_path / "noref.toml"
    path.write_text(SCENE + '[study]\nreference = "fixed"\n[[study.runs]]\nname = "fixed"\n'
                    'refinement = { kind = "fixed", K = 3 }\n')
    with pytest.raises(SceneError, match="converged"):
        descent_runs(load_scene(path))
