"""The main job: the built-in ``cube_kappa`` scene that ``prdp-fem study`` runs by default.

Its size is part of what it shows (solves must dominate: at least 100k state dofs); the
scene at one refinement less keeps its point -- PRDP reaches the converged run's error band
with a fraction of the CG iterations -- at a size a test can run.
"""

import numpy as np
import pytest

from prdp_fem.build import build_mesh
from prdp_fem.cli import _parser
from prdp_fem.scene import load_scene, with_overrides
from prdp_fem.study import run_study


def test_study_runs_the_main_job_by_default():
    assert _parser().parse_args(["study"]).scene == "cube_kappa"


def test_the_main_job_has_at_least_100k_free_dofs():
    scene = load_scene("cube_kappa")
    mesh = build_mesh(scene)
    x = mesh.p[0]
    # P1, Dirichlet on the faces x = 0 and x = 1 only: the free dofs are the other nodes
    free = int(np.count_nonzero((x > 1e-12) & (x < 1 - 1e-12)))
    assert free >= 100_000, free
    assert scene.inverse.unknown == "log_kappa" and scene.optimizer.steps >= 100


@pytest.mark.slow(reason="two 150-step inversions on 13k dofs, about a minute on 2 cores")
def test_main_job_one_level_coarser_prdp_reaches_the_band_with_fewer_iterations(tmp_path):
    scene = with_overrides(load_scene("cube_kappa"),
                           {"mesh": {"refine": 2}, "optimizer": {"steps": 150}})
    rows = {row["run"]: row for row in run_study(scene, tmp_path).summary}
    prdp, converged = rows["prdp"], rows["converged"]
    assert prdp["reached_step"] != ""  # settles within +-1 % of the converged error
    assert abs(prdp["error_gap"]) <= 0.01
    assert prdp["iteration_saving"] >= 0.5, prdp
    assert converged["final_K"] == "tol"
