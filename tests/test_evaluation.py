"""Held-out evaluation: the metrics ``prdp-fem evaluate`` writes are the test errors the
trainings recorded (the same model, the same converged solves), its VTU and .pvd files hold
the predictions, and a checkpoint of another scene is refused with one line, exit 2."""

import json
import tomllib
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest

import prdp_fem as pf
from prdp_fem.cli.main import main
from prdp_fem.learning import heat, load_params
from prdp_fem.learning.evaluation import evaluate_learned, evaluate_rollouts
from prdp_fem.scene import parse_scene
from prdp_fem.scene.build import build_heat, build_learned
from prdp_fem.studies.runner import ResultsLog, checkpoint_directory, run_checkpoints, run_study

LEARNED = """
name = "tiny_learned"
[mesh]
n = 5
[inverse]
unknown = "source"
[learned]
samples = 8
validation_samples = 4
test_samples = 5
hidden = [4]
epochs = 3
batch_size = 4
[optimizer]
name = "adam"
learning_rate = 3e-3
[[study.runs]]
name = "prdp run"
"""

HEAT = """
name = "tiny_heat"
[mesh]
n = 4
[pde]
source = 0.0
dirichlet = 0.0
[heat]
steps = 4
trajectories = 6
validation_trajectories = 2
test_trajectories = 3
hidden = [8]
unroll = 2
epochs = 3
batch_size = 6
mode = "wig"
[[study.runs]]
name = "wig"
"""


def last_record(out, run):
    return [r for r in ResultsLog(out / "results.jsonl").records()
            if r["type"] == "epoch" and r["run"] == run][-1]


def write_scene(tmp_path, text, name):
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


def test_learned_evaluation_is_the_recorded_test_error_and_writes_the_predictions(
        tmp_path, capsys):
    path = write_scene(tmp_path, LEARNED, "learned")
    scene = parse_scene(tomllib.loads(LEARNED), source=str(path), directory=str(tmp_path))
    out = tmp_path / "study"
    run_study(scene, out)
    assert main(["evaluate", str(path), "--out", str(out), "--samples", "2"]) == 0
    assert "test metrics of 1 run(s)" in capsys.readouterr().out
    metrics = json.loads((out / "evaluation" / "prdp_run" / "metrics.json").read_text())
    assert metrics["epoch"] == 3 and metrics["samples"] == 5
    assert metrics["test_error"] == pytest.approx(last_record(out, "prdp run")["test_error"],
                                                  rel=1e-12)
    # the files hold the trained model's predictions of the first two test samples
    variant = dict(scene.runs())["prdp run"]
    setup = build_learned(variant)
    checkpoints = run_checkpoints(out, "prdp run", variant, setup.split)
    params, _ = load_params(checkpoints.directory, setup.network.params, kind="learned",
                            metadata=checkpoints.metadata)
    evaluation = evaluate_learned(setup.problem, setup.network.replace_params(params),
                                  setup.test_set)
    files = sorted((out / "evaluation" / "prdp_run").glob("*.vtu"))
    assert [f.name for f in files] == ["sample_000.vtu", "sample_001.vtu"]
    second = meshio.read(files[1])
    np.testing.assert_allclose(second.point_data["predicted"], evaluation.predictions[1],
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(second.point_data["true"], setup.test_set.sources[1], rtol=0,
                               atol=0)
    rows = (out / "evaluation.csv").read_text().splitlines()
    assert rows[0].startswith("run,epoch,samples,test_error") and len(rows) == 2

    # a scene changed after training: its checkpoints are of another one
    changed = write_scene(tmp_path, LEARNED.replace("hidden = [4]", "hidden = [5]"),
                          "changed")
    assert main(["evaluate", str(changed), "--out", str(out)]) == 2
    message = capsys.readouterr().err.strip()
    assert message.startswith("prdp-fem: error:") and "another metadata" in message
    assert len(message.splitlines()) == 1


def test_heat_evaluation_rolls_out_the_test_trajectories_as_a_pvd_series(tmp_path):
    from prdp_fem.studies.evaluation import evaluate_study

    path = write_scene(tmp_path, HEAT, "heat")
    scene = parse_scene(tomllib.loads(HEAT), source=str(path), directory=str(tmp_path))
    out = tmp_path / "study"
    run_study(scene, out)
    [row] = evaluate_study(scene, out, samples=1)
    assert row["test_error"] == pytest.approx(last_record(out, "wig")["test_error"], rel=1e-12)
    # against the trainer's own rollout error, with the restored model
    variant = dict(scene.runs())["wig"]
    setup = build_heat(variant)
    checkpoints = run_checkpoints(out, "wig", variant, setup.split)
    params, _ = load_params(checkpoints.directory, setup.network.params, kind="heat",
                            metadata=checkpoints.metadata)
    model = setup.network.replace_params(params)
    evaluation = evaluate_rollouts(setup.problem, model, setup.test_set)
    expected, _ = heat.rollout_error(model, setup.problem, setup.test_set,
                                     pf.ConvergedCG(rtol=1e-10, max_iterations=100_000))
    assert float(np.mean(evaluation.errors)) == pytest.approx(float(expected), rel=1e-12)
    series = ET.parse(out / "evaluation" / "wig" / "rollout_000.pvd").getroot()
    steps = series.find("Collection").findall("DataSet")
    assert [float(s.get("timestep")) for s in steps] == pytest.approx(
        [0.02 * n for n in range(5)])
    last = meshio.read(out / "evaluation" / "wig" / steps[-1].get("file"))
    full = np.zeros(setup.disc.n_dofs)
    full[setup.disc.free_dofs] = evaluation.rollouts[0, -1]
    np.testing.assert_allclose(last.point_data["predicted"], full, rtol=1e-12, atol=1e-15)
    assert checkpoint_directory(out, "wig").is_dir()


def test_seed_sets_a_learning_scenes_data_seed_and_is_refused_elsewhere(tmp_path, capsys):
    from prdp_fem.cli._shared import scene_for

    scene = scene_for("reaction_diffusion", None, 3)
    assert all(variant.heat.seed == 3 for _, variant in scene.runs())
    assert scene.fingerprint != scene_for("reaction_diffusion", None).fingerprint
    assert main(["study", "mother", "--seed", "1", "--out", str(tmp_path / "x")]) == 2
    message = capsys.readouterr().err.strip()
    assert "--seed 1: study.kind = 'inverse'" in message and len(message.splitlines()) == 1
    assert not (tmp_path / "x").exists()
