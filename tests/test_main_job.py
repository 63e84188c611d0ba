"""The main job: the built-in ``cube_kappa`` scene that ``prdp-fem study`` runs by default.

Its size is part of what it shows (solves must dominate: at least 100k state dofs); the
scene at one refinement less keeps its point -- PRDP reaches the converged run's error band
with a fraction of the CG iterations -- at a size a test can run.
"""

from pathlib import Path

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


def test_the_references_example_is_the_main_job_problem_with_converged_solvers_only():
    """``examples/scenes/cube_kappa_references.toml`` (the fastest converged solver for the
    main job, in docs/benchmarks.md) must stay the main job's problem, fewer steps apart."""
    example = Path(__file__).resolve().parent.parent / "examples" / "scenes" / \
        "cube_kappa_references.toml"
    references, main = load_scene(example), load_scene("cube_kappa")
    steps = references.optimizer.steps
    main = with_overrides(main, {"optimizer": {"steps": steps}})
    runs = dict(references.runs())
    assert len(runs) == 4 and all(v.refinement.kind == "converged" for v in runs.values())
    assert all(main.same_problem(v) for v in runs.values())
    assert {v.solver.preconditioner for v in runs.values()} == {"jacobi", "amg"}


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
