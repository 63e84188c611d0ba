"""The inverse benchmarks and the reduced-Hessian CG under them, at tiny sizes, against references.

No timings are asserted: only errors, iteration counts, the bookkeeping of the fresh-process
runs and the saving figures against the study's own summary.
"""

import csv
import dataclasses
import importlib.util
import os
import struct
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from conftest import SMALL_STUDY

import prdp_fem as pf
from prdp_fem.bench import inverse as bench_inverse
from prdp_fem.bench.inverse import (
    GOALS,
    TARGET_FACTOR,
    PeerFigure,
    check_mother_options,
    mother_optimum,
    mother_optimum_field,
    mother_problem,
    mother_whole_process,
    prdp_saving,
    saving_configurations,
    saving_rows,
    seed_summary,
    seed_variants,
    solve_mother,
)
from prdp_fem.cli.main import main
from prdp_fem.errors import SceneError, SolverConfigError
from prdp_fem.inverse import History, StepRecord, converged, fixed, homogeneous, reduced, reduced_cg
from prdp_fem.scene import load_scene, parse_scene
from prdp_fem.studies import runner as study


def kkt_optimum(problem) -> np.ndarray:
    """The discrete optimum f of a mother-type problem by one sparse LU of its KKT system.

    ``alpha M f - S' lam = 0``, ``M_II u - (M d)_I + A lam = 0``, ``A u - S f = 0`` (the misfit
    ``1/2 (E u - d)' M (E u - d)`` on the expanded state, ``E`` the free-dof injection).
    """
    system = problem.system
    A = system.operator(problem.known).to_scipy()
    S = system.source.to_scipy()
    M = problem.parameter_mass.to_scipy()
    W = problem.observation.weight.to_scipy()
    free = np.asarray(system.free_dofs)
    E = sp.csr_matrix((np.ones(len(free)), (free, np.arange(len(free)))),
                      shape=(system.n_dofs, len(free)))
    alpha = float(problem.alpha)
    kkt = sp.bmat([[alpha * M, None, -S.T], [None, E.T @ W @ E, A], [-S, A, None]]).tocsc()
    rhs = np.concatenate([np.zeros(system.n_dofs),
                          E.T @ (W @ np.asarray(problem.observation.data)),
                          np.zeros(len(free))])
    return spla.spsolve(kkt, rhs)[:system.n_dofs]


def relative_l2(problem, f) -> float:
    M = problem.parameter_mass.to_scipy()
    truth = np.asarray(problem.truth)
    e = f - truth
    return float(np.sqrt(e @ M @ e / (truth @ M @ truth)))


@pytest.fixture(scope="module")
def mother16():
    problem = mother_problem(16)
    optimum = kkt_optimum(problem)
    return problem, optimum, relative_l2(problem, optimum)


def keep_iterate(step: int, fields: dict):
    """A ``reduced_cg`` callback that keeps the field after outer iteration ``step`` in
    ``fields`` and never stops the run: a shorter run's result, without compiling one."""
    def callback(record, field):
        if record.step == step:
            fields[step] = field
        return False
    return callback


@pytest.fixture(scope="module")
def converged16(mother16):
    """``(result, fields)``: Jacobi-preconditioned converged inner solves to the optimum, and
    its iterate after 3 outer iterations."""
    fields = {}
    result = reduced_cg(mother16[0], refinement=converged(1e-12), iterations=200, rtol=1e-10,
                        callback=keep_iterate(3, fields))
    return result, fields


@pytest.fixture(scope="module")
def early16(mother16):
    """The mother solve stopped at the optimum's error (one outer step)."""
    return solve_mother(16, target=mother16[2], solver="reduced")


def test_reduced_cg_converges_to_the_kkt_optimum(mother16, converged16):
    _, optimum, optimum_error = mother16
    result = converged16[0]
    assert result.residual_norm <= 1e-10 * result.initial_residual_norm
    assert np.linalg.norm(result.field - optimum) <= 1e-7 * np.linalg.norm(optimum)
    assert result.history[-1].parameter_error == pytest.approx(optimum_error, rel=1e-6)
    # the discretisation error of P1/P1 at n = 16 (4.06e-2; 6.69e-4 at n = 128: O(h^2))
    assert optimum_error == pytest.approx(4.063e-2, rel=1e-3)
    # Riesz-preconditioned: cond = (alpha + mu_1) / alpha ~ 2600, far fewer steps than the
    # 289 unknowns (the data excite few modes)
    assert result.history[-1].step <= 60


def test_reduced_cg_scales_with_its_data_to_the_extremes(mother16):
    """The optimum is linear in the data: data times 2^-540 (1e-163) or 2^540 give the field
    times the same factor, in the same steps. The outer CG's r.z underflowed to 0 at 1e-163
    (the run stopped at f = 0 after no step) and overflowed at 1e163 (NaN)."""
    problem = mother16[0]
    reference = reduced_cg(problem, refinement=converged(1e-12), iterations=8)
    for scale in (2.0 ** -540, 2.0 ** 540):
        observation = dataclasses.replace(problem.observation,
                                          data=problem.observation.data * scale)
        scaled = reduced_cg(dataclasses.replace(problem, observation=observation),
                            refinement=converged(1e-12), iterations=8)
        assert len(scaled.history) == len(reference.history) == 8
        np.testing.assert_allclose(np.asarray(scaled.field) / scale, reference.field,
                                   rtol=1e-12, atol=1e-14 * abs(reference.field).max())
        assert scaled.residual_norm / scale == pytest.approx(reference.residual_norm,
                                                             rel=1e-10)


def test_reduced_cg_with_an_amg_cycle_reaches_the_same_optimum(mother16, converged16):
    """The JAX AMG cycle is an argument of the compiled gradient (not a constant in it)."""
    problem, optimum, _ = mother16
    jacobi, jacobi_fields = converged16
    cycle = pf.amg_preconditioner(problem.system.operator(jnp.asarray(problem.known)))
    fields = {}
    result = reduced_cg(problem, refinement=converged(1e-12), iterations=200, rtol=1e-10,
                        preconditioner=cycle, callback=keep_iterate(3, fields))
    assert np.linalg.norm(result.field - optimum) <= 1e-7 * np.linalg.norm(optimum)
    # converged inner solves: the same outer iterates, with fewer inner iterations
    np.testing.assert_allclose(fields[3], jacobi_fields[3], rtol=1e-8, atol=1e-12)
    assert result.history[2].step == jacobi.history[2].step == 3
    assert result.history[2].primal_iterations < jacobi.history[2].primal_iterations


def test_mother_solve_reaches_the_discretisation_error_in_one_step(mother16, early16):
    _, _, optimum_error = mother16
    solve = early16
    assert solve.error <= optimum_error
    assert solve.outer_iterations == 1
    # K0 = 5 primal iterations of the Hessian product (the solve at f = 0 has b = 0), 2 x 5
    # adjoint ones: the data is the lowest mode, which five Jacobi-PCG iterations resolve
    assert solve.inner_iterations == 15
    assert solve.dofs == 17 * 17 and solve.final_K == 5
    converged_inner = solve_mother(16, target=optimum_error, inner_rtol=1e-10, solver="reduced")
    assert converged_inner.error == pytest.approx(solve.error, rel=0.05)
    assert converged_inner.inner_iterations > 5 * solve.inner_iterations


def test_the_hessian_product_is_the_homogeneous_gradient():
    """grad J(f + p) - grad J(f) = grad J_0(p): J_0 has no data, reference, Neumann, Dirichlet."""
    disc = pf.discretize(pf.unit_square(6), element="P1", kappa_space="P0",
                         dirichlet={"left": 1.0, "bottom": lambda x: x[0]},
                         neumann={"top": 0.5})
    state = disc.expand(pf.direct_solve(disc.stiffness_matrix(np.ones(disc.n_kappa)),
                                        disc.rhs(np.ones(disc.n_kappa))).x)
    observation = pf.with_noise(pf.full_field(disc, u_true=state), 0.05, seed=3)
    reference = disc.interpolate(lambda x: 1 + x[1])
    regularization = pf.regularizer(disc, "source", "h1", reference=reference)
    problem = pf.inverse_problem(disc, observation, unknown="source", alpha=1e-3,
                                 regularization=regularization,
                                 known=disc.interpolate_kappa(lambda x: 1 + x[0]))
    solver = pf.ConvergedCG(rtol=1e-13)

    @jax.jit  # one compile: the homogeneous problem has the same structure
    def gradient(which, f):
        return jax.grad(lambda z: which.loss(z, solver)[0])(f)

    rng = np.random.default_rng(0)
    f, p = rng.standard_normal((2, problem.n_parameters))
    difference = gradient(problem, f + p) - gradient(problem, f)
    np.testing.assert_allclose(gradient(homogeneous(problem), p), difference,
                               atol=1e-9 * np.abs(difference).max())


@pytest.mark.parametrize(("settings", "message"), [
    (dict(unknown="log_kappa"), "unknown='log_kappa'"),
    (dict(unknown="source", bounds=(0.0, 1.0)), "bounds=(0.0, 1.0)"),
    (dict(unknown="source", regularization="tv"), "regularization='tv'"),
])
def test_reduced_cg_refuses_objectives_that_are_not_quadratic(settings, message):
    disc = pf.discretize(pf.unit_square(4), element="P1", kappa_space="P1")
    observation = pf.full_field(disc, data=np.zeros(disc.n_dofs))
    problem = pf.inverse_problem(disc, observation, alpha=1e-6, **settings)
    with pytest.raises(SolverConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        reduced_cg(problem)


def test_reduced_cg_stops_at_the_callback_and_counts_what_ran(mother16):
    problem, _, _ = mother16
    seen = []
    result = reduced_cg(problem, refinement=fixed(7), iterations=10,
                        callback=lambda record, field: seen.append(record.step) or len(seen) == 3)
    assert seen == [1, 2, 3] and len(result.history) == 3
    last = result.history[-1]
    # the restart at f = 0 (b = 0: no primal iterations) then one Hessian product per step
    assert (last.primal_iterations, last.adjoint_iterations_total) == (3 * 7, 4 * 7)
    assert last.evaluations == 4 and result.riesz_iterations > 0
    assert np.all(np.diff(result.history.column("loss")) < 0)


@pytest.mark.slow  # a fresh process: the command's test below runs one already
def test_mother_whole_process_times_a_fresh_process():
    bench = mother_whole_process(8, repeats=1, target=0.5, solver="reduced")
    assert bench.error <= 0.5 and bench.outer_iterations == 1 and bench.runs == 1
    phases = bench.import_s + bench.assembly_s + bench.compile_s + bench.solve_s
    assert bench.start_s > 0 and bench.exit_s > 0
    assert bench.whole_s == pytest.approx(bench.start_s + phases + bench.exit_s)
    assert bench.import_s > 0 and bench.compile_s > 0
    assert bench.peer is None and bench.goal_met is None and np.isnan(bench.ratio)


def test_mother_processes_start_cold_without_either_compilation_cache(monkeypatch):
    """The whole-process figure includes JIT compilation: a child process must not load
    programs from the package's persistent cache (on by default) nor from JAX's."""
    from prdp_fem.bench.inverse import _child_environment
    from prdp_fem.compilation_cache import cache_directory
    monkeypatch.setenv("PRDP_FEM_COMPILATION_CACHE", "/some/cache")
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", "/some/jax/cache")
    environment = _child_environment()
    assert cache_directory(environment) is None
    assert "JAX_COMPILATION_CACHE_DIR" not in environment
    warm = _child_environment("/a/primed/cache")
    assert str(cache_directory(warm)) == "/a/primed/cache"
    assert "JAX_COMPILATION_CACHE_DIR" not in warm


@pytest.mark.slow  # fresh processes of a benchmark
def test_warm_mother_processes_share_a_cache_an_untimed_process_filled(monkeypatch):
    """cache="warm": one untimed process fills a cache of the benchmark's own (JAX's
    persistent cache), the timed one reads it, and no goal is judged (its time includes
    compiling)."""
    directories = []
    run_child = bench_inverse._run_child

    def spying(arguments, timeout, environment):
        directories.append(environment["PRDP_FEM_COMPILATION_CACHE"])
        return run_child(arguments, timeout, environment)

    monkeypatch.setattr(bench_inverse, "_run_child", spying)
    bench = mother_whole_process(8, repeats=1, target=0.5, cache="warm", solver="reduced")
    assert len(directories) == 2 and directories[0] == directories[1]
    assert bench.cache == "warm" and bench.error <= 0.5 and bench.goal_met is None
    with pytest.raises(SolverConfigError, match="--cache 'hot': expected one of"):
        mother_whole_process(8, cache="hot")


def test_bench_mother_prints_a_cold_and_a_warm_row_per_size_and_judges_the_cold(
        capsys, monkeypatch):
    """--cache both: per size a cold row, then a warm one; only the cold row has a goal."""
    calls = []

    calls = []
    peer = {512: PeerFigure(20.0, 1e-4, 0.25, 6), 1024: PeerFigure(10.0, 2e-5, 0.15, 6)}

    def fake(n, *, cache, peer_python, **settings):
        calls.append((n, cache, peer_python))
        return bench_inverse.MotherBench(
            n=n, dofs=(n + 1) ** 2, target=1e-4, error=0.99e-4,
            outer_iterations=1, inner_iterations=15, riesz_iterations=9, start_s=0.1,
            import_s=1.0, assembly_s=0.8, compile_s=1.0 if cache == "cold" else 0.4,
            solve_s=0.1, exit_s=0.3, whole_s=3.3 if cache == "cold" else 2.7, runs=1,
            peer=peer[n], cache=cache)

    monkeypatch.setattr(bench_inverse, "mother_whole_process", fake)
    monkeypatch.setattr(bench_inverse, "mother_optimum", lambda n: 0.99e-4)
    assert main(["bench", "mother", "--sizes", "512", "1024", "--cache", "both",
                 "--peer-python", "peer/python"]) == 0
    assert calls == [(512, "cold", "peer/python"), (512, "warm", "peer/python"),
                     (1024, "cold", "peer/python"), (1024, "warm", "peer/python")]
    rows = [line.split() for line in capsys.readouterr().out.splitlines()[2:6]]
    assert [row[17:] for row in rows] == [["cold", "<=", "0.25", "met"], ["warm", "-"],
                                          ["cold", "<=", "0.15", "NOT", "met"], ["warm", "-"]]
    assert [float(row[10]) for row in rows] == [1.0, 0.4, 1.0, 0.4]  # the compile column
    assert [float(row[12]) for row in rows] == [0.3] * 4  # the exit column
    with pytest.raises(SystemExit):
        main(["bench", "mother", "--cache", "hot"])


def test_a_tree_without_bytecode_is_said_once_and_the_benchmark_runs(monkeypatch):
    monkeypatch.setattr(bench_inverse, "compile_package_bytecode", lambda: False)
    monkeypatch.setattr(bench_inverse, "_run_child", lambda arguments, timeout, environment: (
        {"dofs": 81, "error": 0.1, "outer_iterations": 1, "inner_iterations": 3,
         "riesz_iterations": 2, "import_s": 1.0, "assembly_s": 0.1, "compile_s": 0.5,
         "solve_s": 0.1}, 2.0, 0.25))
    with pytest.warns(RuntimeWarning, match="bytecode of .*prdp_fem could not be written"):
        bench = mother_whole_process(8, repeats=1, target=0.5)
    assert bench.whole_s == 2.0 and bench.exit_s == 0.25
    assert bench.start_s == pytest.approx(0.05)


def test_a_childs_exit_is_timed_from_its_last_print(monkeypatch):
    """The exit column is the time from the child's printed line to its end: a child whose
    shutdown sleeps 0.4 s (an exit handler) reads at least that, and its start does not."""
    child = ("import atexit, json, sys, time\n"
             "atexit.register(time.sleep, 0.4)\n"
             "print(json.dumps({'import_s': 0.0, 'printed_at': time.time()}), flush=True)\n")
    monkeypatch.setattr(bench_inverse, "_CHILD", child)
    phases, whole, shutdown = bench_inverse._run_child({}, 60.0, dict(os.environ))
    assert phases["import_s"] == 0.0
    assert 0.4 <= shutdown <= whole


def test_the_race_s_goals_and_its_target_the_discrete_optimum(mother16, early16):
    """The race is to the discrete optimum (a sparse LU of the KKT system here), not to an
    iterate passing an error on its way: a solve stops within 1 % of the optimum's error of
    the optimum itself."""
    problem, _, optimum_error = mother16
    assert GOALS == {512: 0.25, 1024: 0.15} and TARGET_FACTOR == 1.01
    field = mother_optimum_field(16)
    assert relative_l2(problem, field) == pytest.approx(optimum_error, rel=1e-8)
    assert mother_optimum(16) == pytest.approx(optimum_error, rel=1e-8)
    solve = solve_mother(16, inner_rtol=1e-8, preconditioner="amg", solver="reduced")
    assert abs(solve.error - optimum_error) <= 0.01 * optimum_error
    assert solve.target == pytest.approx(TARGET_FACTOR * optimum_error, rel=1e-8)
    # the early-stopped iterate (one outer step) passes below the optimum's error: not a race
    assert early16.outer_iterations == 1 < solve.outer_iterations
    # the race's solver: MINRES on the KKT system, stopped by the same test, compiling nothing
    kkt = solve_mother(16)
    assert kkt.solver == "kkt" and abs(kkt.error - optimum_error) <= 0.01 * optimum_error
    assert kkt.compile_s == 0 and kkt.inner_iterations == 2 * (kkt.outer_iterations + 1)
    check_mother_options([100, 3000])  # any size: the target is computed


# --------------------------------------------------------------------------------------
# PRDP saving
# --------------------------------------------------------------------------------------


def test_saving_compares_only_prdp_runs_on_the_reference_problem(tmp_path):
    small = tmp_path / "small.toml"
    small.write_text(SMALL_STUDY.replace("STEPS", "5"))
    assert saving_configurations(load_scene(small)) == ["converged", "prdp"]  # not fixed K=3
    assert saving_configurations(load_scene("cube")) == ["converged", "prdp"]  # not n = 4
    assert saving_configurations(load_scene("plate_hole")) == ["converged", "plate_hole"]
    with pytest.raises(SceneError, match="expected an inverse study"):
        saving_configurations(load_scene("poisson_h"))
    no_prdp = tmp_path / "no_prdp.toml"
    without_prdp_run = SMALL_STUDY.replace("STEPS", "5").split('[[study.runs]]\nname = "prdp"')[0]
    no_prdp.write_text(without_prdp_run)
    with pytest.raises(SceneError, match="no PRDP run comparable"):
        saving_configurations(load_scene(no_prdp))


def record(step, error, time, iterations, rtol=0.0):
    return StepRecord(step=step, iterations=10, adjoint_iterations=10, rtol=rtol, refinements=0,
                      primal_iterations=iterations, adjoint_iterations_total=iterations,
                      validation_iterations=0, evaluations=step, time=time, compile_time=1.0,
                      loss=error, misfit=error, parameter_error=error, state_error=float("nan"))


def test_saving_rows_are_the_study_figures():
    """The study's summary of known histories, read by the benchmark: the BENCHMARKS.md saving."""
    scene = load_scene("mother")
    converged_run = History(record(k, e, 2.0 * k, 100 * k, rtol=1e-10)
                            for k, e in enumerate([0.5, 0.2, 0.1, 0.1], start=1))
    # in the 1 % band from step 3 (0.1005), out of it at step 2 (0.15): reached at step 3
    reaching = History(record(k, e, 0.1 * k, 5 * k)
                       for k, e in enumerate([0.4, 0.15, 0.1005, 0.0995], start=1))
    passing = History(record(k, e, 0.1 * k, 5 * k)
                      for k, e in enumerate([0.4, 0.1, 0.2, 0.3], start=1))
    # ends 5 % more accurate than the converged run: never in the +-1 % band, but below it
    better = History(record(k, e, 0.1 * k, 5 * k)
                     for k, e in enumerate([0.4, 0.2, 0.0999, 0.095], start=1))
    histories = {"converged": converged_run, "prdp": reaching, "prdp passing": passing,
                 "prdp better": better}
    summary = study._inverse_summary(scene, histories, "parameter_error")
    reached, passed, below = saving_rows("mother", "converged", summary)
    assert (reached.run, reached.reached_step, reached.ends_at_or_below) == ("prdp", 3, True)
    assert reached.converged_s == 8.0 and reached.converged_iterations == 800
    # same target, both sides: the converged run settles in its own band at step 3 (6 s,
    # 600 iterations), not at its last step (8 s, 800)
    assert reached.time_saving == pytest.approx(1 - 0.3 / 6.0)
    assert reached.iteration_saving == pytest.approx(1 - 30 / 600)
    assert summary[1]["converged_time_to_target_s"] == 6.0
    assert reached.error_difference == pytest.approx(-0.005)
    assert reached.goal_met
    assert passed.reached_step is None and np.isnan(passed.time_saving)  # only passed through
    assert passed.error_difference == pytest.approx(2.0) and not passed.goal_met
    assert not passed.ends_at_or_below
    # ends 5 % below: not a saving, only its own column
    assert below.reached_step is None and np.isnan(below.time_saving) and below.ends_at_or_below
    assert below.error_difference == pytest.approx(-0.05)
    assert not below.goal_met
    assert summary[3]["error_gap"] == pytest.approx(-0.05)


def test_each_run_is_compared_with_the_converged_run_of_its_preconditioner():
    scene = load_scene("inclusion")
    assert scene.reference_of("prdp") == scene.reference_of("prdp unrolled") == "converged"
    assert scene.reference_of("prdp identity") == "converged identity"
    assert scene.reference_of("converged identity") == "converged"  # converged solvers compared
    assert saving_configurations(scene) == ["converged", "converged identity", "prdp",
                                            "prdp identity", "prdp unrolled"]
    # known histories: the unpreconditioned converged run takes 10x the time to the band
    converged_run = History(record(k, e, 2.0 * k, 100 * k, rtol=1e-10)
                            for k, e in enumerate([0.5, 0.2, 0.1, 0.1], start=1))
    identity_run = History(record(k, e, 20.0 * k, 1000 * k, rtol=1e-10)
                           for k, e in enumerate([0.5, 0.2, 0.1, 0.1], start=1))
    reaching = History(record(k, e, 0.1 * k, 5 * k)
                       for k, e in enumerate([0.4, 0.15, 0.1005, 0.0995], start=1))
    histories = {"converged": converged_run, "converged identity": identity_run,
                 "prdp": reaching, "prdp identity": reaching}
    summary = {row["run"]: row for row in
               study._inverse_summary(scene, histories, "parameter_error")}
    assert summary["prdp identity"]["reference"] == "converged identity"
    assert summary["prdp identity"]["converged_time_to_target_s"] == 60.0
    assert summary["prdp identity"]["time_saving"] == pytest.approx(1 - 0.3 / 60.0)
    assert summary["prdp"]["reference"] == "converged"
    assert summary["prdp"]["time_saving"] == pytest.approx(1 - 0.3 / 6.0)
    rows = {row.run: row for row in saving_rows("inclusion", "converged",
                                                list(summary.values()))}
    assert set(rows) == {"prdp", "prdp identity"}  # the references are no PRDP rows
    assert rows["prdp identity"].converged_iterations == 8000  # primal + adjoint
    assert rows["prdp identity"].iteration_saving == pytest.approx(1 - 15 / 3000)
    # no converged run of its preconditioner: the scene's reference
    plain = load_scene("plate_hole")
    assert plain.reference_of("plate_hole") == plain.study.reference


def test_the_study_command_names_the_runs_with_their_own_reference(monkeypatch, tmp_path,
                                                                   capsys):
    """``prdp-fem study`` prints, under its table, which runs compare with another converged
    run than the scene's reference (the summary of known histories, not a run)."""
    scene = load_scene("inclusion")
    runs = History(record(k, e, 2.0 * k, 100 * k, rtol=1e-10)
                   for k, e in enumerate([0.5, 0.2, 0.1, 0.1], start=1))
    histories = {name: runs for name, _ in scene.runs()}
    summary = study._inverse_summary(scene, histories, "parameter_error")
    monkeypatch.setattr(study, "run_study", lambda *args, **kwargs: study.StudyOutput(
        tmp_path, summary, [], []))
    assert main(["study", "inclusion", "--out", str(tmp_path / "s")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "savings of runs with their own preconditioner: prdp identity against converged " \
        "identity" in lines


@pytest.mark.slow  # two inversions compiled and a study's figures (about 15 s)
def test_saving_rows_are_the_study_summary(tmp_path):
    scene_file = tmp_path / "small.toml"  # no [[study.runs]]: converged + the scene's own PRDP
    scene_file.write_text(SMALL_STUDY.replace("STEPS", "12").split("[[study.runs]]")[0])
    scene = load_scene(scene_file)
    [row] = prdp_saving(scene, out=tmp_path / "study")
    with open(tmp_path / "study" / "summary.csv") as stream:
        summary = {r["run"]: r for r in csv.DictReader(stream)}
    assert set(summary) == {"converged", "small"}
    base, prdp_row = summary["converged"], summary["small"]
    assert row.run == "small" and row.converged_iterations == int(base["cg_iterations"])
    assert row.prdp_iterations == int(prdp_row["cg_iterations"])
    assert row.converged_error == pytest.approx(float(base["final_error"]), rel=1e-12)
    assert row.error_difference == pytest.approx(
        float(prdp_row["final_error"]) / float(base["final_error"]) - 1, rel=1e-9)
    if prdp_row["reached_step"]:
        assert row.reached_step == int(prdp_row["reached_step"])
        assert row.iteration_saving == pytest.approx(
            1 - float(prdp_row["iterations_to_target"]) / float(base["iterations_to_target"]))
        assert row.iteration_saving == pytest.approx(float(prdp_row["iteration_saving"]))
    else:
        assert row.reached_step is None and np.isnan(row.time_saving)
    history = study.inverse_histories(scene, tmp_path / "study")["small"]
    assert row.ends_at_or_below == (history[-1].parameter_error <= 1.01 * row.converged_error)
    assert row.goal_met == (row.time_saving >= 0.8 and abs(row.error_difference) <= 0.01)
    assert row.seed is None  # given data: the seed draws nothing


def test_saving_goal_needs_both_the_time_and_the_error():
    from prdp_fem.bench.inverse import SavingRow

    row = SavingRow("s", "prdp", 10.0, 1000, 1.0, 100, 5, 0.9, 0.9, True, 1.0, 1.005)
    assert row.goal_met
    assert not row._replace(prdp_error=1.02).goal_met
    assert not row._replace(prdp_error=0.95).goal_met  # 5 % better is outside the band
    assert not row._replace(time_saving=0.79).goal_met
    assert not row._replace(time_saving=float("nan"), reached_step=None).goal_met


def test_repeated_studies_give_medians_and_the_time_saving_range():
    from prdp_fem.bench.inverse import SavingRow, median_row

    row = SavingRow("s", "prdp", 10.0, 1000, 1.0, 100, 5, 0.9, 0.9, True, 1.0, 1.005)
    rows = [row._replace(converged_s=12.0, time_saving=0.7),
            row._replace(converged_s=8.0, prdp_s=3.0, time_saving=0.8, reached_step=7), row]
    merged = median_row(rows)
    assert (merged.converged_s, merged.prdp_s, merged.time_saving) == (10.0, 1.0, 0.8)
    assert merged.reached_step == 5 and merged.prdp_iterations == 100
    assert (merged.repeats, merged.time_saving_low, merged.time_saving_high) == (3, 0.7, 0.9)
    # a run that missed the band in one study has not reached it: no step, NaN saving
    missed = median_row([row, row._replace(reached_step=None, time_saving=float("nan"),
                                           ends_at_or_below=False)])
    assert missed.reached_step is None and np.isnan(missed.time_saving)
    assert not missed.goal_met and missed.ends_at_or_below is False  # only if every study
    with pytest.raises(ValueError, match="different runs"):
        median_row([row, row._replace(run="other")])


# --------------------------------------------------------------------------------------
# problem instances: the same scene under other noise and sensor draws
# --------------------------------------------------------------------------------------

NOISY_SENSORS = {"mesh": {"n": 8}, "inverse": {"truth": "x*y", "observations": "sensors",
                                                "sensors": 10, "noise": 0.01, "seed": 7}}


def test_seed_variants_draw_other_noise_and_sensors():
    from prdp_fem.scene.build import build_inverse

    scene = parse_scene(NOISY_SENSORS)
    variants = seed_variants(scene, [1, 2])
    assert [seed for seed, _ in variants] == [1, 2]
    assert [variant.inverse.seed for _, variant in variants] == [1, 2]
    # everything else is the scene's
    assert all(dataclasses.replace(variant.inverse, seed=7) == scene.inverse and
               (variant.mesh, variant.refinement) == (scene.mesh, scene.refinement)
               for _, variant in variants)
    data = [np.asarray(build_inverse(variant).problem.observation.data)
            for _, variant in variants]
    assert not np.allclose(data[0], data[1])  # other sensors and noise: other data
    assert seed_variants(scene, None) == [(None, scene)] == seed_variants(scene, [])


@pytest.mark.parametrize("inverse", [
    {"truth": "x*y"},                                         # no noise, the full field
    {"truth": "x*y", "observations": "sensors", "sensors": [[0.5, 0.5]]},  # fixed sensors
    {"truth": "x*y", "data": "x", "noise": 0.01},             # given data: nothing drawn
])
def test_seed_variants_run_once_where_the_data_draw_nothing(inverse):
    scene = parse_scene({"mesh": {"n": 8}, "inverse": inverse})
    assert seed_variants(scene, [1, 2, 3]) == [(None, scene)]


def test_mother_runs_once_and_numpy_seeds_are_seeds():
    assert seed_variants(load_scene("mother"), [1, 2]) == [(None, load_scene("mother"))]
    variants = seed_variants(parse_scene(NOISY_SENSORS), np.arange(2))
    assert [(seed, type(seed)) for seed, _ in variants] == [(0, int), (1, int)]


@pytest.mark.parametrize("seeds", [[-1], [1, 1], [True], [1.5]])
def test_seed_variants_refuse_bad_seeds(seeds):
    with pytest.raises(SolverConfigError, match="seeds="):
        seed_variants(parse_scene(NOISY_SENSORS), seeds)


def test_seed_summary_counts_the_instances_that_meet_the_goal():
    from prdp_fem.bench.inverse import SavingRow, median_row

    row = SavingRow("s", "prdp", 10.0, 1000, 1.0, 100, 5, 0.9, 0.9, True, 1.0, 1.005)
    rows = [row._replace(seed=1),                                        # met
            row._replace(seed=2, time_saving=0.7, iteration_saving=0.8),  # in the band, slow
            row._replace(seed=3, reached_step=None, time_saving=np.nan,  # never in the band,
                         iteration_saving=np.nan, prdp_error=0.9),        # ends below it
            row._replace(seed=1, run="prdp unrolled", prdp_error=1.05,
                         ends_at_or_below=False)]                         # 5 % above
    first, other = seed_summary(rows)
    assert (first.scene, first.run, first.instances) == ("s", "prdp", 3)
    assert (first.reached, first.met, first.ends_below) == (2, 1, 3)
    assert first.time_saving == pytest.approx(0.8)        # median of 0.9 and 0.7 (NaN left out)
    assert first.iteration_saving == pytest.approx(0.85)
    assert first.error_difference == pytest.approx(0.005)  # median of 0.5 %, 0.5 %, -10 %
    assert (other.run, other.instances, other.met, other.ends_below) == ("prdp unrolled", 1, 0, 0)
    with pytest.raises(ValueError, match="different runs"):  # repeats of one instance only
        median_row([row._replace(seed=1), row._replace(seed=2)])


def _stand_in_saving(seen, directories=None):
    """``prdp_saving`` without the studies: one row per scene, its seed stamped as the real
    one stamps it, the goal missed in the band for seed 2; ``directories`` receives each
    call's ``(out, resume)``."""
    from prdp_fem.bench.inverse import SavingRow, _seeded

    directories = [] if directories is None else directories

    def stand_in(scene, *, repeats=1, out=None, resume=False, progress=None, client=None):
        seen.append((scene.name, scene.inverse.seed, repeats))
        directories.append((out, resume))
        if resume:  # as a study that finds its run done: read back, not run
            progress.run_finished("prdp", skipped=True)
        met = scene.inverse.seed != 2 or not _seeded(scene)
        return [SavingRow(scene.name, "prdp", 10.0, 1000, 1.0, 100, 5, 0.9 if met else 0.5,
                          0.9, True, 1.0, 1.005,
                          seed=scene.inverse.seed if _seeded(scene) else None)]
    return stand_in


def test_bench_prdp_seeds_prints_a_row_per_instance_and_a_summary(monkeypatch, capsys,
                                                                   tmp_path):
    """The command runs every instance's study (here: stand-in rows) into a directory of its
    own and prints the seed column and the per-run summary, which it also writes as CSV; a
    scene whose data draw nothing runs once."""
    from prdp_fem.bench import inverse as bench_inverse

    seen, directories = [], []
    monkeypatch.setattr(bench_inverse, "prdp_saving", _stand_in_saving(seen, directories))
    out = tmp_path / "saving"
    assert main(["bench", "prdp", "--scene", "plate_hole", "mother", "--seeds", "1", "2",
                 "--repeats", "2", "--out", str(out)]) == 0
    mother_seed = load_scene("mother").inverse.seed  # its own: noise-free full-field data
    assert seen == [("plate_hole", 1, 2), ("plate_hole", 2, 2), ("mother", mother_seed, 2)]
    assert directories == [(out / "plate_hole" / "seed-1", False),
                           (out / "plate_hole" / "seed-2", False), (out / "mother", False)]
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"PRDP saving: 3 problem instance(s), 16 run(s) into {out}/"
    assert lines[1].split()[:3] == ["scene", "run", "seed"]
    rows = [line.split() for line in lines[2:5]]
    assert [row[:3] for row in rows] == [
        ["plate_hole", "prdp", "1"], ["plate_hole", "prdp", "2"], ["mother", "prdp", "-"]]
    assert lines[5] == ""
    assert lines[6].split()[:5] == ["scene", "run", "band", "met", "below"]
    assert lines[7].split()[:5] == ["plate_hole", "prdp", "2/2", "1/2", "2/2"]
    assert lines[8].split()[:5] == ["mother", "prdp", "1/1", "1/1", "1/1"]
    assert lines[-1] == (f"wrote {out}/: saving.csv, seeds.csv, and the studies in "
                         "plate_hole/, mother/")
    with open(out / "saving.csv") as stream:  # the figures at full precision
        written = list(csv.DictReader(stream))
    assert [(r["scene"], r["seed"], float(r["time_saving"]), r["met"]) for r in written] == [
        ("plate_hole", "1", 0.9, "True"), ("plate_hole", "2", 0.5, "False"),
        ("mother", "", 0.9, "True")]
    assert float(written[0]["error_difference"]) == pytest.approx(0.005)
    with open(out / "seeds.csv") as stream:
        assert [(r["scene"], r["instances"], r["met"]) for r in csv.DictReader(stream)] == [
            ("plate_hole", "2", "1"), ("mother", "1", "1")]


def test_bench_prdp_without_seeds_has_no_seed_column_or_summary(monkeypatch, capsys,
                                                                tmp_path):
    """Without --out the studies go to a new ./bench-prdp (never into an earlier one)."""
    from prdp_fem.bench import inverse as bench_inverse

    seen, directories = [], []
    monkeypatch.setattr(bench_inverse, "prdp_saving", _stand_in_saving(seen, directories))
    monkeypatch.chdir(tmp_path)
    assert main(["bench", "prdp", "--scene", "plate_hole"]) == 0
    assert seen == [("plate_hole", load_scene("plate_hole").inverse.seed, 1)]
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].split()[:3] == ["scene", "run", "conv_s"]
    assert len(lines) == 5 and lines[3].startswith("save: ")  # header, row, footnote
    assert main(["bench", "prdp", "--scene", "plate_hole"]) == 0
    assert directories == [(Path("bench-prdp") / "plate_hole", False),
                           (Path("bench-prdp-2") / "plate_hole", False)]
    assert (tmp_path / "bench-prdp" / "saving.csv").exists()


def test_bench_prdp_resumes_only_its_own_run(monkeypatch, capsys, tmp_path):
    """An output directory is refused unless resumed, and resumed only with the options it
    was run with (else its studies would start afresh beside the old ones); the table says
    how many runs were read back."""
    from prdp_fem.bench import inverse as bench_inverse

    seen, directories = [], []
    monkeypatch.setattr(bench_inverse, "prdp_saving", _stand_in_saving(seen, directories))
    out = tmp_path / "saving"
    command = ["bench", "prdp", "--scene", "plate_hole", "--seeds", "1", "--out", str(out)]
    assert main(command) == 0
    capsys.readouterr()
    assert main(command) == 2  # not resumed: refused before anything ran
    captured = capsys.readouterr()
    assert captured.out == "" and len(seen) == 1
    assert captured.err == (f"prdp-fem: error: --out {out}: is not empty; expected a new or "
                            "empty directory, or --resume to continue the run in it\n")
    assert main([*command, "--resume"]) == 0
    assert directories[-1] == (out / "plate_hole" / "seed-1", True)
    assert "1 of 2 run(s) read back from" in capsys.readouterr().out
    assert main(["bench", "prdp", "--scene", "plate_hole", "--seeds", "2", "--out", str(out),
                 "--resume"]) == 2
    assert capsys.readouterr().err.startswith(f"prdp-fem: error: --resume: {out} was run with "
                                              "other --seeds (")
    assert main(["bench", "prdp", "--out", str(tmp_path / "elsewhere"), "--resume"]) == 2
    assert "bench.json is missing or unreadable; expected the --out of an earlier bench prdp " \
        "run" in capsys.readouterr().err
    assert len(seen) == 2


def test_bench_prdp_scene_names_must_make_distinct_directories(tmp_path, capsys):
    def scene_named(file_name, name):
        path = tmp_path / file_name
        path.write_text(SMALL_STUDY.replace("STEPS", "3").replace('name = "small"',
                                                                  f'name = "{name}"'))
        return str(path)

    nested = scene_named("nested.toml", "a/b")
    assert main(["bench", "prdp", "--scene", nested, "--out", str(tmp_path / "o")]) == 2
    # refused where the scene is read: a name is one path component
    assert "name = 'a/b': expected a non-empty string usable as a file name" \
        in capsys.readouterr().err
    upper, lower = scene_named("upper.toml", "Small"), scene_named("lower.toml", "small")
    assert main(["bench", "prdp", "--scene", upper, lower, "--out", str(tmp_path / "o")]) == 2
    assert "expected scenes of distinct names" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # refused before anything was written


def test_an_interrupted_bench_prdp_says_how_to_resume_it(monkeypatch, capsys, tmp_path):
    """Ctrl-C in the second instance: the first one's rows are in its study; the message
    gives the command that continues the run (a scene path with a space quoted), and the
    exit code is 130."""
    from prdp_fem.bench import inverse as bench_inverse

    seen = []
    stand_in = _stand_in_saving(seen)

    def interrupted_on_seed_2(scene, **options):
        if scene.inverse.seed == 2:
            raise KeyboardInterrupt
        return stand_in(scene, **options)

    monkeypatch.setattr(bench_inverse, "prdp_saving", interrupted_on_seed_2)
    small = tmp_path / "my scenes" / "small.toml"
    small.parent.mkdir()
    small.write_text(SMALL_STUDY.replace("STEPS", "3"))
    out = tmp_path / "saving"
    assert main(["bench", "prdp", "--scene", "plate_hole", str(small), "--seeds", "1", "2",
                 "--steps", "7", "--repeats", "2", "--out", str(out)]) == 130
    assert seen == [("plate_hole", 1, 2)]
    assert capsys.readouterr().err == (
        f"prdp-fem: interrupted; finished runs are kept in {out}/ (continue with: prdp-fem "
        f"bench prdp --scene plate_hole '{small}' --steps 7 --repeats 2 --seeds 1 2 --out "
        f"{out} --resume)\n")


@pytest.mark.slow  # a killed study resuming is in test_cli_commands by default
def test_a_resumed_saving_reads_its_finished_runs_back(tmp_path):
    """A benchmark stopped after the converged run keeps it: resumed, only the PRDP run runs,
    and once both are done a resumed call runs nothing and returns the same row, times
    included (read back, not measured again)."""
    scene_file = tmp_path / "small.toml"
    scene_file.write_text(SMALL_STUDY.replace("STEPS", "3"))
    scene, out = load_scene(scene_file), tmp_path / "study"

    class StopAfter:  # a progress that records the runs, and stops after one of them
        def __init__(self, stop_after=None):
            self.finished, self.stop_after = [], stop_after

        def run_started(self, name, steps):
            pass

        def step(self):
            pass

        def run_finished(self, name, skipped):
            self.finished.append((name, skipped))
            if name == self.stop_after:
                raise KeyboardInterrupt

        def stop_if_requested(self):
            pass

    first = StopAfter(stop_after="converged")
    with pytest.raises(KeyboardInterrupt):
        prdp_saving(scene, out=out, progress=first)
    assert first.finished == [("converged", False)]
    resumed = StopAfter()
    [row] = prdp_saving(scene, out=out, resume=True, progress=resumed)
    assert resumed.finished == [("converged", True), ("prdp", False)]
    again = StopAfter()
    [again_row] = prdp_saving(scene, out=out, resume=True, progress=again)
    assert again.finished == [("converged", True), ("prdp", True)]
    assert (again_row.converged_s, again_row.prdp_s) == (row.converged_s, row.prdp_s)
    np.testing.assert_equal(list(again_row), list(row))  # NaN savings: the band not reached
    assert row.converged_iterations > row.prdp_iterations > 0
    with pytest.raises(study.StudyError, match="pass --resume"):  # not resumed: refused
        prdp_saving(scene, out=out)


# --------------------------------------------------------------------------------------
# the commands: bad options are one line and exit 2, before anything runs
# --------------------------------------------------------------------------------------


REDUCED_MOTHER = ("bench", "mother", "--solver", "reduced")


@pytest.mark.parametrize(("argv", "message"), [
    (["bench", "mother", "--sizes", "1"], "--sizes 1: expected integers >= 2"),
    (["bench", "mother", "--repeats", "0"], "--repeats 0: expected an integer >= 1"),
    ([*REDUCED_MOTHER, "--iterations", "0"], "--iterations 0: expected an integer >= 1"),
    ([*REDUCED_MOTHER, "--inner-rtol", "2"], "--inner-rtol 2.0: expected a number in (0, 1)"),
    ([*REDUCED_MOTHER, "--preconditioner", "ilu"], "--preconditioner 'ilu': expected one of"),
    ([*REDUCED_MOTHER, "--iterations", "5", "--inner-rtol", "1e-8"],
     "--iterations and --inner-rtol: expected one of them"),
    (["bench", "mother", "--iterations", "5", "--preconditioner", "amg"],
     "--iterations --preconditioner: options of the inner solves of --solver reduced"),
    (["bench", "mother", "--sizes", "16", "--target", "0"], "--target 0.0: expected"),
    (["bench", "prdp", "--scene", "poisson_h"], "expected an inverse study"),
    (["bench", "prdp", "--scene", "torus"], "scene 'torus': expected"),
    (["bench", "prdp", "--steps", "0"], "--steps 0: expected an integer >= 1"),
    (["bench", "prdp", "--repeats", "0"], "--repeats 0: expected an integer >= 1"),
    (["bench", "prdp", "--seeds", "1", "1"], "--seeds 1 1: expected distinct integers >= 0"),
    (["bench", "prdp", "--seeds", "-3"], "--seeds -3: expected distinct integers >= 0"),
    (["bench", "prdp", "--scene", "cube", "cube"], "expected scenes of distinct names"),
    (["bench", "prdp", "--scene", "mother", "poisson_h"], "expected an inverse study"),
    (["bench", "prdp", "--resume"], "--resume: expected --out DIR, the directory of the run"),
])
def test_bench_bad_options_are_one_line_and_exit_2(argv, message, capsys):
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == ""  # refused before the table header, before anything ran
    assert captured.err.count("\n") == 1
    assert captured.err.startswith("prdp-fem: error: ") and message in captured.err


def _bytecode_is_current(module) -> bool:
    """The module's cached bytecode exists and was compiled from its source as it is now."""
    source = Path(module.__file__)
    cached = Path(importlib.util.cache_from_source(str(source)))
    if not cached.exists():
        return False
    header = cached.read_bytes()[:16]  # PEP 552: magic, flags, then a time stamp or a hash
    if int.from_bytes(header[4:8], "little") & 1:  # hash-based (SOURCE_DATE_EPOCH set)
        return header[8:16] == importlib.util.source_hash(source.read_bytes())
    stat = source.stat()
    return header[8:16] == struct.pack("<II", int(stat.st_mtime) & 0xFFFFFFFF,
                                       stat.st_size & 0xFFFFFFFF)


def test_bench_mother_prints_one_row_per_size(capsys, monkeypatch):
    # the children read the package's bytecode, as a user's process reads an install's, even
    # where they may not write it (PYTHONDONTWRITEBYTECODE): the benchmark writes it first
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    for module in (bench_inverse, reduced):
        Path(importlib.util.cache_from_source(module.__file__)).unlink(missing_ok=True)
        assert not _bytecode_is_current(module)
    assert main(["bench", "mother", "--sizes", "8", "--target", "0.5", "--repeats", "1"]) == 0
    assert _bytecode_is_current(bench_inverse) and _bytecode_is_current(reduced)
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("all-at-once MINRES on the KKT system, Pearson-Wathen")
    assert lines[1].startswith("no peer given") and "pip install --no-deps dolfin-adjoint" \
        in lines[1]
    row = lines[3].split()
    assert row[:3] == ["8", "81", "nan"] and float(row[4]) <= 0.5
    assert row[-2:] == ["cold", "-"]
    start, imports, assembly, compile_, solve, shutdown, whole = map(float, row[7:14])
    assert min(start, imports, shutdown) > 0 and compile_ == 0  # MINRES compiles nothing
    # whole = the phases + the rest
    assert whole == pytest.approx(start + imports + assembly + compile_ + solve + shutdown,
                                  abs=0.035)  # six figures of 2 decimals


def test_the_peer_runs_alternated_with_the_project_each_in_a_cold_form_cache(
        monkeypatch, tmp_path):
    """--peer-python: after each of the project's processes one of the peer's (a stand-in
    script here), each with a new form-compiler cache (cold); the peer's figure is the median
    of its whole-process times and its own last error."""
    import sys

    stub = tmp_path / "peer.py"
    stub.write_text("import json, os, sys, time\n"
                    "print(json.dumps({'n': int(sys.argv[1]), 'error': 3e-4, 'evaluations': 7,"
                    " 'cache': os.environ['DIJITSO_CACHE_DIR'], 'printed_at': time.time()}))\n")
    monkeypatch.setattr(bench_inverse, "PEER_SCRIPT", stub)
    order, caches = [], []
    run_peer = bench_inverse._run_peer

    def peer(python, n, timeout, form_cache):
        order.append("peer")
        figures, whole = run_peer(python, n, timeout, form_cache)
        caches.append(figures["cache"])
        return figures, whole

    def child(arguments, timeout, environment):
        order.append("project")
        return ({"dofs": 81, "error": 0.1, "outer_iterations": 1, "inner_iterations": 3,
                 "riesz_iterations": 2, "import_s": 1.0, "assembly_s": 0.1, "compile_s": 0.5,
                 "solve_s": 0.1}, 2.0, 0.25)

    monkeypatch.setattr(bench_inverse, "_run_peer", peer)
    monkeypatch.setattr(bench_inverse, "_run_child", child)
    bench = mother_whole_process(512, repeats=3, target=0.5, peer_python=sys.executable)
    assert order == ["project", "peer"] * 3
    assert len(set(caches)) == 3  # cold: a new cache per run
    assert bench.peer.error == 3e-4 and bench.peer.evaluations == 7
    assert bench.peer.goal_ratio == 0.25 and bench.ratio == pytest.approx(2.0 / bench.peer.seconds)
    broken = tmp_path / "broken.py"
    broken.write_text("raise SystemExit('no dolfin here')\n")
    monkeypatch.setattr(bench_inverse, "PEER_SCRIPT", broken)
    monkeypatch.setattr(bench_inverse, "_run_peer", run_peer)
    with pytest.raises(SolverConfigError, match="no dolfin here; to install it: apt-get"):
        mother_whole_process(512, repeats=1, target=0.5, peer_python=sys.executable)
