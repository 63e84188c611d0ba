"""The built-in learning scenes at size: what their tables promise (state dofs, weights,
samples, splits, a nonlinear problem), and each trains, shrunk by its scaling keys, as a study
whose held-out error falls."""

import itertools
import math

import pytest

from prdp_fem.scene import load_scene
from prdp_fem.scene.build import build_discretization
from prdp_fem.scene.spec import with_overrides
from prdp_fem.studies.runner import ResultsLog, run_study


def mlp_weights(sizes) -> int:
    return sum(a * b + b for a, b in itertools.pairwise(sizes))


def test_learned_plate_is_a_mesh_file_of_10k_dofs_a_2m_weight_network_and_1000_samples():
    scene = load_scene("learned_plate")
    spec = scene.learned
    disc = build_discretization(scene)
    assert scene.mesh.file.endswith(".msh") and disc.n_dofs >= 10_000
    n_obs = scene.inverse.sensors
    assert mlp_weights([n_obs, *spec.hidden, disc.n_dofs]) >= 1_000_000
    assert spec.samples + spec.validation_samples + spec.test_samples >= 1000
    assert min(spec.samples, spec.validation_samples, spec.test_samples) >= 100


@pytest.mark.parametrize("name", ["heat_emulator", "reaction_diffusion"])
def test_the_time_dependent_scenes_have_900_dofs_and_a_1m_weight_network(name):
    scene = load_scene(name)
    disc = build_discretization(scene)
    free = len(disc.free_dofs)
    assert free >= 900
    assert mlp_weights([free, *scene.heat.hidden, free]) >= 1_000_000
    setups = {variant.heat.setup for _, variant in scene.runs()}
    modes = {variant.heat.mode for _, variant in scene.runs()}
    assert "correction" in setups and {"nog", "wig"} <= modes
    if name == "heat_emulator":
        assert "prediction" in setups  # the emulator
    else:
        assert scene.heat.reaction > 0 and modes == {"one", "nog", "wig"}


SHRUNK = {
    "learned_plate": {"mesh": {"refine": 1}, "inverse": {"sensors": 30},
                      "learned": {"samples": 40, "validation_samples": 8, "test_samples": 8,
                                  "hidden": [16], "epochs": 6, "batch_size": 10}},
    "heat_emulator": {"mesh": {"n": 8}, "heat": {"trajectories": 12,
                                                 "validation_trajectories": 4,
                                                 "test_trajectories": 4, "hidden": [32],
                                                 "epochs": 8, "batch_size": 12}},
    "reaction_diffusion": {"mesh": {"n": 8}, "heat": {"trajectories": 8, "steps": 10,
                                                      "validation_trajectories": 4,
                                                      "test_trajectories": 4, "hidden": [32],
                                                      "epochs": 8, "batch_size": 12}},
}


def shrunk(name: str):
    """The scene with its size keys shrunk and only its first run (a PRDP run)."""
    scene = load_scene(name)
    first = scene.runs()[0][0]
    return with_overrides(scene, {**SHRUNK[name], "study": {"runs": [{"name": first}]}})


@pytest.mark.slow  # three studies, about 25 s
@pytest.mark.parametrize("name", list(SHRUNK))
def test_each_large_scene_trains_shrunk_and_its_test_error_falls(name, tmp_path):
    scene = shrunk(name)
    run_study(scene, tmp_path)
    records = [r for r in ResultsLog(tmp_path / "results.jsonl").records()
               if r["type"] == "epoch"]
    errors = [r["test_error"] for r in records]
    assert all(math.isfinite(e) for e in errors) and errors[-1] < errors[0], errors
