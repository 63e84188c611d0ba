"""Inverse problems: gradients (Taylor), observations, regularisers, the loop, alpha choice."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.sparse.linalg as spla
from conftest import json_from_a_process, shared_compiles_made

import prdp_fem as pf
from prdp_fem.errors import PrdpFemError, SolverConfigError
from prdp_fem.fem import boundary_values, full_field, point_sensors, regularizer, with_noise
from prdp_fem.inverse import (
    History,
    InversionError,
    Validation,
    converged,
    fixed,
    inverse_problem,
    invert,
    l_curve,
    morozov,
    prdp,
    settled,
)
from prdp_fem.inverse.steps import step_failed
from prdp_fem.linalg import ConvergedCG, IterationCounter, TruncatedCG, solve, zero_counts
from prdp_fem.optim import Evaluation


def _coefficient_problem(n=10, kappa_space="P1", noise=0.0, alpha=1e-6, reg="h1",
                         observation="full", bounds=None):
    disc = pf.discretize(pf.unit_square(n), element="P1", kappa_space=kappa_space,
                         dirichlet=0.0)
    m_true = disc.interpolate_kappa(lambda x: 0.5 * np.sin(np.pi * x[0]) * x[1])
    f = np.ones(disc.n_dofs)
    kappa = np.exp(m_true)
    u = disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f)).x)
    if observation == "full":
        obs = full_field(disc, u_true=u)
    else:
        pts = np.random.default_rng(0).uniform(0.05, 0.95, (25, 2))
        obs = point_sensors(disc, pts, u_true=u)
    if noise:
        obs = with_noise(obs, noise, seed=3)
    if reg == "tv":  # smooth enough for finite differences at h ~ 1e-2
        reg = regularizer(disc, "log_kappa", "tv", epsilon=0.5)
    problem = inverse_problem(disc, obs, unknown="log_kappa", alpha=alpha, regularization=reg,
                              known=f, truth=m_true, bounds=bounds)
    return disc, problem


def _source_problem(n=12, alpha=1e-4):
    disc = pf.discretize(pf.unit_square(n), element="P1", dirichlet=0.0)
    data = disc.project(lambda x: np.sin(np.pi * x[0]) * np.sin(np.pi * x[1]) / 20)
    return disc, inverse_problem(disc, full_field(disc, data=data), unknown="source",
                                 alpha=alpha, regularization="l2")


# --- counting CG work -------------------------------------------------------------------


@pytest.mark.parametrize("solver, primal, adjoint", [
    (TruncatedCG(7, gradient="implicit", adjoint_iterations=3), 7, 3),
    # test_tally's grad-count cases count an unrolled solve's sweeps in the default suite
    pytest.param(TruncatedCG(5, gradient="unrolled"), 5, 5, marks=pytest.mark.slow),
])
def test_counter_tallies_forward_and_backward_iterations(small_problem, solver, primal, adjoint):
    disc, kappa, f = small_problem
    system = disc.system
    counter = IterationCounter()

    @jax.jit
    def loss(k):
        return jnp.sum(solve(system.operator(k), system.rhs(k, f), solver, counter=counter).x)
    jax.block_until_ready(jax.grad(loss)(jnp.asarray(kappa)))
    assert counter.snapshot() == (primal, adjoint)
    jax.block_until_ready(loss(jnp.asarray(kappa)))  # forward only: no adjoint solve
    assert counter.snapshot() == (2 * primal, adjoint)


@pytest.mark.slow  # test_tally's eager-solve test counts a converged solve in the default suite
def test_counter_matches_converged_iterations(small_problem):
    disc, kappa, f = small_problem
    A, b = disc.system.operator(kappa), disc.system.rhs(kappa, f)
    counter = IterationCounter()
    sol = solve(A, b, ConvergedCG(rtol=1e-10), counter=counter)
    jax.block_until_ready(sol.x)
    assert counter.primal == int(sol.iterations) > 0 and counter.adjoint == 0


# --- gradients of the objective: Taylor tests -------------------------------------------


@pytest.mark.parametrize("kappa_space, reg, observation, bounds", [
    # test_coefficient_maps' log-kappa Taylor test checks this gradient (P1, H1, full field)
    pytest.param("P1", "h1", "full", None, marks=pytest.mark.slow),
    ("P0", "tv", "sensors", None),
    ("P1", "l2", "sensors", (-1.0, 2.0)),
])
def test_objective_gradient_taylor(kappa_space, reg, observation, bounds):
    _, problem = _coefficient_problem(kappa_space=kappa_space, reg=reg, observation=observation,
                                      alpha=1e-3, bounds=bounds)
    z = problem.parameterization.from_field(
        0.2 + 0.1 * np.random.default_rng(1).standard_normal(problem.n_parameters))
    # one program for the values and the gradient (one compile, not two)
    value_and_grad = jax.jit(jax.value_and_grad(
        lambda p: problem.loss(p, ConvergedCG(rtol=1e-13))[0]))
    result = pf.taylor_test(lambda p: value_and_grad(p)[0], z, gradient=value_and_grad(z)[1])
    assert result.passed(), result


def test_unrolled_gradient_is_exact_for_the_truncated_objective():
    _, problem = _source_problem()
    z = jnp.asarray(np.random.default_rng(2).standard_normal(problem.n_parameters))
    # one program for the values and the gradient (one compile, not two)
    value_and_grad = jax.jit(jax.value_and_grad(
        lambda p: problem.loss(p, TruncatedCG(6, gradient="unrolled"))[0]))
    result = pf.taylor_test(lambda p: value_and_grad(p)[0], z, gradient=value_and_grad(z)[1])
    assert result.passed(), result


# --- observations, noise, regularisers --------------------------------------------------


def test_point_sensors_interpolate_linear_states_exactly():
    disc = pf.discretize(pf.unit_square(6), element="P1", dirichlet=0.0)
    pts = np.array([[0.13, 0.71], [0.5, 0.5], [0.91, 0.07]])
    obs = point_sensors(disc, pts, u_true=disc.interpolate(lambda x: 2 * x[0] - x[1]))
    np.testing.assert_allclose(np.asarray(obs.data), 2 * pts[:, 0] - pts[:, 1], atol=1e-13)
    with pytest.raises(PrdpFemError, match=r"inside the mesh|outside"):
        point_sensors(disc, [[1.5, 0.5]], data=[0.0])


def test_boundary_values_select_tagged_dofs():
    disc = pf.discretize(pf.unit_square(6), element="P1", dirichlet=None)
    obs = boundary_values(disc, ["left"], u_true=disc.interpolate(lambda x: 1 + x[1]))
    assert obs.size == 7
    np.testing.assert_allclose(np.sort(np.asarray(obs.data)), 1 + np.linspace(0, 1, 7))
    with pytest.raises(PrdpFemError, match="expected names among"):
        boundary_values(disc, ["nowhere"], data=[0.0])


def test_noise_is_seeded_and_at_the_stated_level():
    disc = pf.discretize(pf.unit_square(16), element="P1", dirichlet=0.0)
    clean = full_field(disc, u_true=disc.interpolate(lambda x: np.sin(3 * x[0]) + 2),
                       norm="nodal")
    a, b = with_noise(clean, 0.05, seed=7), with_noise(clean, 0.05, seed=7)
    np.testing.assert_array_equal(np.asarray(a.data), np.asarray(b.data))
    eta = np.asarray(a.data) - np.asarray(clean.data)
    sigma = 0.05 * np.max(np.abs(np.asarray(clean.data)))
    assert float(a.noise_std) == pytest.approx(sigma)
    assert np.std(eta) == pytest.approx(sigma, rel=0.1)
    # E ||eta||_W = sigma sqrt(tr W); the realised norm is within a few percent at 289 samples
    assert np.linalg.norm(eta) == pytest.approx(float(a.noise_norm()), rel=0.1)


_SETUP_COMPILES = """
import json
import jax
compiled = []
def listener(event, duration, **kwargs):
    if event == "/jax/core/compile/backend_compile_duration":
        compiled.append(kwargs.get("fun_name"))
jax.monitoring.register_event_duration_secs_listener(listener)
import numpy as np
import prdp_fem as pf
disc = pf.discretize(pf.unit_square(6), element="P1", dirichlet=0.0)
data = disc.project(lambda x: x[0] * x[1])
observation = pf.full_field(disc, data=data)
for obs in (observation, observation.clean(data)):
    problem = pf.inverse_problem(disc, obs, unknown="source", alpha=1e-6, regularization="l2")
print(json.dumps({"setup": compiled,
                  "noise": [str(problem.observation.noise_std.dtype),
                            problem.observation.noise_std.weak_type]}))
"""


def test_the_setup_compiles_no_program():
    # jnp constructors (an observation's zero noise level) compiled a program each per
    # process, about 0.05 s apiece on 2 CPU cores; in a fresh process, since a program
    # compiled once is cached after
    child = json_from_a_process(_SETUP_COMPILES, "0")
    assert child["setup"] == []
    assert child["noise"] == ["float64", False]


def test_h1_regularizer_equals_the_stiffness_quadratic_form():
    disc = pf.discretize(pf.unit_square(5), element="P2", dirichlet=0.0)
    m = np.random.default_rng(0).standard_normal(disc.n_dofs)
    reg = regularizer(disc, "source", "h1")
    assert float(reg(m)) == pytest.approx(0.5 * m @ disc.laplace_matrix @ m, rel=1e-12)
    l2 = regularizer(disc, "source", "l2", reference=1.0)
    assert float(l2(m)) == pytest.approx(0.5 * (m - 1) @ disc.mass_matrix @ (m - 1), rel=1e-12)


def test_tv_of_a_piecewise_constant_field_is_its_jump_length():
    disc = pf.discretize(pf.unit_square(8), element="P1", kappa_space="P0", dirichlet=0.0)
    m = disc.interpolate_kappa(lambda x: 3.0 * (x[0] < 0.5))  # jump 3 across x = 1/2
    tv = regularizer(disc, "log_kappa", "tv", epsilon=1e-9)
    assert float(tv(m)) == pytest.approx(3.0, rel=1e-6)
    tv_p1 = regularizer(pf.discretize(pf.unit_square(8), element="P1", kappa_space="P1",
                                      dirichlet=0.0), "log_kappa", "tv", epsilon=1e-9)
    linear = pf.discretize(pf.unit_square(8), kappa_space="P1").interpolate_kappa(
        lambda x: 2 * x[0] + x[1])
    assert float(tv_p1(linear)) == pytest.approx(math.sqrt(5.0), rel=1e-6)


def test_bad_problem_input_is_rejected_at_the_edge():
    disc, problem = _source_problem()
    obs = problem.observation
    with pytest.raises(PrdpFemError, match="truth"):
        inverse_problem(disc, obs, unknown="source", alpha=1.0, truth=np.ones(3))
    with pytest.raises(PrdpFemError, match="unknown"):
        inverse_problem(disc, obs, unknown="velocity", alpha=1.0)
    with pytest.raises(PrdpFemError, match="alpha"):
        inverse_problem(disc, obs, unknown="source", alpha=float("nan"))
    with pytest.raises(PrdpFemError, match="bounds"):
        inverse_problem(disc, obs, unknown="source", alpha=1.0, bounds=(1.0, 0.0))


# --- the loop ---------------------------------------------------------------------------


def _discrete_optimum(disc, problem):
    """Reduced normal equations of the source problem, solved by SciPy (independent path)."""
    M, S = disc.mass_matrix, disc.source_matrix
    A = disc.stiffness_matrix(np.ones(disc.n_kappa))
    lu = spla.splu(A.tocsc())
    W = disc.mass_matrix[disc.free_dofs][:, disc.free_dofs]
    alpha, d = float(problem.alpha), np.asarray(problem.observation.data)
    c = (M @ d)[disc.free_dofs]

    def hessian(f):
        return S.T @ lu.solve(W @ lu.solve(S @ f)) + alpha * (M @ f)
    H = spla.LinearOperator((disc.n_dofs,) * 2, matvec=hessian)
    f, info = spla.cg(H, S.T @ lu.solve(c), rtol=1e-13, maxiter=10_000)
    assert info == 0
    return f


def test_invert_reaches_the_discrete_optimum_and_records_costs():
    disc, problem = _source_problem()
    f_opt = _discrete_optimum(disc, problem)
    result = invert(problem, refinement=converged(1e-12), steps=150)
    e = np.asarray(result.field) - f_opt
    M = disc.mass_matrix
    assert math.sqrt(e @ M @ e / (f_opt @ M @ f_opt)) < 1e-4
    h = result.history
    for name in ("primal_iterations", "adjoint_iterations_total", "time", "evaluations"):
        assert np.all(np.diff(h.column(name)) >= 0), name
    assert h[-1].primal_iterations > h[-1].evaluations > len(h) // 2


def test_a_controller_written_with_jnp_runs_in_the_host_loop():
    """invert updates its controller eagerly on the host state; a user's controller written
    with jnp (device arrays from its first update on) steers the same run as the NumPy one."""
    from prdp_fem.inverse import Refinement

    _disc, problem = _source_problem(n=6)
    base = prdp(K0=2, dK=3, tau_step=0.5, tau_stop=0.99)

    def device_update(state, value, failed=False):
        state = jax.tree.map(jnp.asarray, state)
        return base.update(state, jnp.asarray(value), failed)  # computes with jnp

    host = invert(problem, refinement=base, steps=12)
    device = invert(problem, refinement=Refinement(base.init, device_update), steps=12)
    assert isinstance(device.refinement.iterations, jax.Array)
    assert isinstance(host.refinement.iterations, np.ndarray | np.generic)
    columns = ("iterations", "refinements", "evaluations", "primal_iterations")
    assert int(host.refinement.refinements) >= 1  # the controller did steer
    for name in columns:
        assert list(host.history.column(name)) == list(device.history.column(name)), name
    np.testing.assert_allclose(device.history.column("loss"), host.history.column("loss"),
                               rtol=1e-12)


def test_prdp_refines_during_inversion_and_history_round_trips(tmp_path):
    _disc, problem = _coefficient_problem(n=12, noise=0.01, alpha=1e-7)
    params = []
    result = invert(problem, refinement=prdp(K0=2, dK=4, restart=True, stall_on_failure=True),
                    steps=40, callback=lambda record, z: params.append(np.asarray(z)))
    ks = result.history.column("iterations")
    assert np.all(np.diff(ks) >= 0) and ks[-1] > ks[0]
    assert result.history[-1].parameter_error < result.history[0].parameter_error
    # at K = 2 the implicit gradient misleads L-BFGS's line search: its first failure is
    # a stall, so the next step already runs at a larger K
    failures = result.history.column("failed_steps")
    first = int(np.flatnonzero(failures)[0])
    assert failures[first] == 1 and ks[first] == 2 and ks[first + 1] > 2
    # the contradicted search gives up after three or four evaluations (optax's zoom spends
    # all 20) and takes no step: the parameters stay where the step before left them
    assert 3 <= np.diff(result.history.column("evaluations"), prepend=0)[first] <= 4
    np.testing.assert_array_equal(params[first], params[first - 1])
    # a fixed K run counts exactly K primal iterations per solve
    run = invert(problem, refinement=fixed(6, 4), steps=5).history[-1]
    assert run.primal_iterations == 6 * run.evaluations
    path = tmp_path / "history.jsonl"
    result.history.to_jsonl(path)
    assert History.from_jsonl(path)[-1] == result.history[-1]


@pytest.mark.slow  # test_prdp_refines (through invert) and test_linesearch's wrong-sign test
def test_a_truncated_gradient_s_failed_line_search_costs_three_or_four_evaluations():
    # at K = 2 the implicit gradient says "down" where the truncated loss rises: optax's zoom
    # search spends all 20 evaluations; prdp_fem's stops once three trials show it
    _disc, problem = _coefficient_problem(n=12, noise=0.01, alpha=1e-7)
    ours = pf.lbfgs()  # one object for both of its runs below: one compiled step
    runs = {name: invert(problem, optimizer=optimizer, refinement=fixed(2, 2), steps=2)
            for name, optimizer in (("optax", optax.lbfgs()), ("prdp_fem", ours))}
    for name, run in runs.items():
        failures = np.diff(run.history.column("failed_steps"), prepend=0)
        assert list(failures) == [0, 1], name
    evaluations = {name: np.diff(run.history.column("evaluations"), prepend=0)
                   for name, run in runs.items()}
    assert evaluations["optax"][0] == evaluations["prdp_fem"][0]  # the same first search
    assert evaluations["optax"][1] == 20
    assert 3 <= evaluations["prdp_fem"][1] <= 4
    # the contradicted search takes no step: the parameters stay where step 1 left them
    one_step = invert(problem, optimizer=ours, refinement=fixed(2, 2), steps=1)
    np.testing.assert_array_equal(runs["prdp_fem"].params, one_step.params)


def test_a_refinement_discards_the_optimizer_s_stored_value_and_gradient():
    """When K changes, the line search's stored value and gradient belong to the old solver:
    invert marks them stale (inf), so the next step's loss is the new solver's, and the
    line search knows the objective changed (pf.optim.scale_by_zoom_linesearch's restart)."""
    from prdp_fem.inverse import Objective, Refinement

    _disc, problem = _coefficient_problem(n=8, alpha=1e-6)
    base = fixed(2, 2)

    def refine_after_the_first_step(state, value, failed=False):
        state = base.update(state, value, failed)
        return state._replace(iterations=jnp.where(state.count >= 1, 30, 2),
                              adjoint_iterations=jnp.where(state.count >= 1, 30, 2))

    params = []
    result = invert(problem, refinement=Refinement(base.init, refine_after_the_first_step),
                    steps=2, callback=lambda record, z: params.append(np.asarray(z)))
    assert list(result.history.column("iterations")) == [2, 30]
    @jax.jit  # K traced: one program for both objectives, not op by op
    def objective(z, K):
        return Objective(problem, TruncatedCG(K, "jacobi", gradient="implicit",
                                              adjoint_iterations=K), None)(z)

    fresh = float(objective(jnp.asarray(params[0]), 30))
    assert result.history[1].loss == pytest.approx(fresh, rel=1e-12)
    stale = float(objective(jnp.asarray(params[0]), 2))
    assert abs(fresh - stale) > 1e-6 * abs(fresh)  # the test can tell them apart


def _step_programs_made(monkeypatch) -> list:
    """The step programs (SharedCompile with a static scan length) built from now on."""
    from prdp_fem.inverse import driver as inverse

    inverse._step_program.cache_clear()
    return shared_compiles_made(monkeypatch)


@pytest.mark.slow  # compile sharing; test_executables keeps one such case in the default suite
def test_inversions_with_equal_settings_share_one_step_and_time_its_compile_once(
        monkeypatch):
    """A study's runs or an alpha sweep call invert again and again with equal settings: the
    step is traced and compiled once, and each run's compile time is its own."""
    _, problem = _source_problem(n=6)
    made = _step_programs_made(monkeypatch)
    first = invert(problem, refinement=fixed(3), steps=3)
    second = invert(problem, refinement=fixed(3), steps=3)
    other_alpha = invert(dataclasses.replace(problem, alpha=1e-3), refinement=fixed(3), steps=3)
    steps = [c for c in made if c._static_argnum == 5]
    assert len(steps) == 1
    # no run counts another's compilation: together they are at most what was compiled
    runs = (first, second, other_alpha)
    assert sum(run.history[-1].compile_time for run in runs) <= sum(c.seconds for c in made)
    assert first.history[-1].compile_time > 0
    for name in ("loss", "primal_iterations", "adjoint_iterations_total", "evaluations"):
        assert np.array_equal(first.history.column(name), second.history.column(name)), name
    assert other_alpha.history[-1].loss != first.history[-1].loss
    # another optimizer object is another step; a plain optax transform given twice is one
    invert(problem, optimizer=pf.lbfgs(), refinement=fixed(3), steps=1)
    adam = optax.adam(1e-2)
    invert(problem, optimizer=adam, refinement=fixed(3), steps=1)
    invert(problem, optimizer=adam, refinement=fixed(3), steps=1)
    assert len([c for c in made if c._static_argnum == 5]) == 3


@pytest.mark.slow  # the programs compiled, not a number a user sees
def test_an_unrolled_run_compiles_one_step_per_scan_length(monkeypatch):
    """Unrolled K = 10 and 16 share one program (scan length 16), K = 20 takes another
    (32); every run's losses are those of the static K-iteration objective."""
    _, problem = _coefficient_problem(n=8, alpha=1e-5)
    made = _step_programs_made(monkeypatch)
    sgd = optax.sgd(1e-3)  # the scan lengths are the step's, whatever its optimiser
    runs = {K: invert(problem, optimizer=sgd, refinement=fixed(K), gradient="unrolled",
                      steps=2)
            for K in (10, 16, 20)}
    [step] = [c for c in made if c._static_argnum == 5]
    assert sorted(key[0] for key in step._cache) == [16, 32]
    z0 = jnp.zeros(problem.n_parameters)
    for K, run in runs.items():
        expected = problem.loss(z0, TruncatedCG(K, gradient="unrolled"))[0]
        assert run.history[0].loss == pytest.approx(float(expected), rel=1e-12)
        assert run.history[0].iterations == K


@pytest.mark.slow  # the program's structure (trace count)
def test_a_step_traces_its_objective_once(monkeypatch):
    """The stored value's check and both branches of the zoom search's step evaluate
    ``value_and_grad``: one nested program, traced once (three traces before), with the
    same losses."""
    from prdp_fem.inverse import driver as inverse

    _, problem = _coefficient_problem(n=6, alpha=1e-5)
    reference = invert(problem, refinement=fixed(8), steps=3)
    traced, original = [], inverse.InverseProblem.loss

    def counting(self, *args, **kwargs):
        traced.append(1)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(inverse.InverseProblem, "loss", counting)
    inverse._step_program.cache_clear()
    again = invert(problem, refinement=fixed(8), steps=3)
    assert len(traced) == 1
    assert np.array_equal(again.history.column("loss"), reference.history.column("loss"))


def _compiled_text(fn, *args) -> str:
    return jax.jit(fn, static_argnums=5 if len(args) > 5 else None).lower(*args).compile() \
        .as_text()


def _compiled_step(problem, optimizer) -> tuple[int, int]:
    """``(host calls, while loops)`` in a compiled implicit-mode step (a host call is the
    iteration tally's; every CG solve is a loop)."""
    from prdp_fem.inverse import driver as inverse
    from prdp_fem.inverse import steps

    optimizer = optax.with_extra_args_support(optimizer)
    z = jnp.zeros(problem.n_parameters)
    step = inverse.make_step(optimizer, "implicit", False, "jacobi")
    text = _compiled_text(step, problem, IterationCounter(), z, optimizer.init(z), None, 0,
                          *steps.device_settings((8, 8, 0.0)))
    return text.count("custom-call("), text.count(" while(")


@pytest.mark.slow  # the program's structure, not a number a user sees
def test_an_l_bfgs_step_holds_its_objective_once_and_no_host_call(monkeypatch):
    """A step whose stored value is stale (none yet, or PRDP refined K) gets the value and
    gradient at its start from the line search's own trial (``pf.lbfgs``'s search refreshes
    a non-finite value), so the compiled step holds the objective -- a CG solve and its
    adjoint, each compiled anew where it appears -- once, where the evaluation before the
    update held it twice. Its evaluations return their iteration counts
    (``Objective.evaluate``): the step holds no host call, where optax's own
    search evaluates the plain objective (host-counted) in both of its branches."""
    from prdp_fem.inverse import driver as inverse
    from prdp_fem.inverse import steps

    _, problem = _coefficient_problem(n=6, alpha=1e-5)
    solver = TruncatedCG(8, "jacobi", gradient="implicit", adjoint_iterations=8)
    counted = _compiled_text(inverse.Objective(problem, solver, None).evaluate,
                             jnp.zeros(problem.n_parameters))
    loops_per_objective = counted.count(" while(")
    assert counted.count("custom-call(") == 0 and loops_per_objective >= 2
    host = _compiled_text(lambda z, counter: inverse.Objective(problem, solver, counter)
                          .value_and_grad(z), jnp.zeros(problem.n_parameters),
                          IterationCounter())
    assert host.count("custom-call(") == 2  # the primal and the adjoint solve's tallies
    host_calls, loops = _compiled_step(problem, pf.lbfgs())
    assert host_calls == 0
    assert _compiled_step(problem, optax.lbfgs())[0] == 2 * 2  # both branches, host-counted
    monkeypatch.setattr(steps, "_refreshes", lambda opt_state: False)
    assert _compiled_step(problem, pf.lbfgs()) == (0, loops + loops_per_objective)


@pytest.mark.slow  # two implementations of one step agree
def test_a_refreshed_step_takes_the_steps_of_an_evaluation_before_the_update(monkeypatch):
    """A PRDP run that refines K (the stored value goes stale) gives the same losses, to
    round-off (the objective is compiled in another place), evaluations and iterations with
    the value refreshed by the search as with an evaluation before the update."""
    from prdp_fem.inverse import driver as inverse
    from prdp_fem.inverse import steps

    _, problem = _coefficient_problem(n=6, alpha=1e-5)
    refreshed = invert(problem, refinement=prdp(), steps=30).history
    assert refreshed[-1].refinements >= 1
    monkeypatch.setattr(steps, "_refreshes", lambda opt_state: False)
    inverse._step_program.cache_clear()
    evaluated_first = invert(problem, refinement=prdp(), steps=30).history
    np.testing.assert_allclose(refreshed.column("loss"), evaluated_first.column("loss"),
                               rtol=1e-10)
    for name in ("evaluations", "primal_iterations", "adjoint_iterations_total",
                 "failed_steps"):
        assert np.array_equal(refreshed.column(name), evaluated_first.column(name)), name
    inverse._step_program.cache_clear()  # no step with the patched test kept for later tests


@pytest.mark.parametrize("gradient, refinement", [
    ("implicit", prdp(K0=3, dK=3)),
    # 8 + 4 s; the solves' counts in these modes: test_tally.py's reverse-tally cases
    pytest.param("unrolled", fixed(6), marks=pytest.mark.slow),
    pytest.param("implicit", converged(1e-8), marks=pytest.mark.slow)])
def test_a_step_returns_the_counts_the_host_counter_would_hear(monkeypatch, gradient,
                                                               refinement):
    """``pf.lbfgs``'s evaluations return their iteration counts as outputs
    (``Objective.evaluate``); forced through the host counter instead, a run has
    the same losses and the same counts at every step."""
    from prdp_fem.inverse import driver as inverse

    # 8 x 8, as the runs of the tests above: the first run here reuses their step program
    _, problem = _coefficient_problem(n=8, alpha=1e-5)
    returned = invert(problem, refinement=refinement, gradient=gradient, steps=12).history

    def host_counted(objective):
        value_and_grad = objective.value_and_grad  # counts into the objective's counter
        return lambda z: Evaluation(*value_and_grad(z), zero_counts())

    monkeypatch.setattr(inverse.Objective, "evaluate", property(host_counted))
    inverse._step_program.cache_clear()
    heard = invert(problem, refinement=refinement, gradient=gradient, steps=12).history
    inverse._step_program.cache_clear()  # no step with the patched objective kept
    np.testing.assert_allclose(returned.column("loss"), heard.column("loss"), rtol=1e-12)
    for name in ("evaluations", "primal_iterations", "adjoint_iterations_total"):
        assert np.array_equal(returned.column(name), heard.column(name)), name
    assert returned[-1].adjoint_iterations_total > 0


def test_a_kept_step_program_does_not_keep_a_finished_run_s_problem_alive():
    import gc
    import weakref

    def run():
        _, problem = _source_problem(n=7)
        leaves = [leaf for leaf in jax.tree_util.tree_leaves(problem)
                  if isinstance(leaf, jax.Array) and leaf.size]
        invert(problem, refinement=fixed(3), steps=2)
        return [weakref.ref(leaf) for leaf in leaves]

    references = run()
    gc.collect()
    assert len(references) > 20 and not any(reference() is not None
                                            for reference in references)


def test_amg_cycles_of_equal_shapes_share_one_step_and_a_callback_cycle_gets_its_own(
        monkeypatch):
    disc, problem = _source_problem(n=6)
    operator = disc.system.operator(jnp.ones(disc.n_kappa))
    # the hierarchy of 2 A is A's with every level scaled: equal shapes, other values
    cycles = [pf.amg_preconditioner(operator), pf.amg_preconditioner(operator.with_values(
        2.0 * operator.values))]
    made = _step_programs_made(monkeypatch)
    sgd = optax.sgd(1e-3)  # a small step program: the test is about how many compile
    runs = [invert(problem, optimizer=sgd, refinement=fixed(3), steps=2, preconditioner=cycle)
            for cycle in cycles]
    steps = [c for c in made if c._static_argnum == 5]
    assert len(steps) == 1 and len(steps[0]._cache) == 1  # the cycle is an argument
    # M / 2 takes the same PCG iterates as M: the second run is not the first one's replay
    losses = [run.history.column("loss") for run in runs]
    np.testing.assert_allclose(losses[1], losses[0], rtol=1e-12)
    assert not np.array_equal(cycles[0].coarse_map, cycles[1].coarse_map)
    # pyamg's own cycle is a host callback: closed over, a step of its own per object
    callback = pf.amg_preconditioner(operator, implementation="callback")
    for _ in range(2):
        invert(problem, optimizer=sgd, refinement=fixed(3), steps=2, preconditioner=callback)
    assert len([c for c in made if c._static_argnum == 5]) == 3


def test_a_failed_line_search_is_read_from_the_optimizer_state():
    def f(x):
        return jnp.sum(x ** 2)
    x = jnp.array([1.0, -2.0])
    g = jax.grad(f)(x)
    for optimizer in (optax.lbfgs(), optax.chain(optax.sgd(1.0),
                                                 optax.scale_by_backtracking_linesearch(5))):
        # one program for both updates (the gradient's sign an argument), not op by op
        @jax.jit
        def update(g, optimizer=optimizer):
            return optimizer.update(g, optimizer.init(x), x, value=f(x), grad=g,
                                    value_fn=f)[1]
        good, ascent = update(g), update(-g)
        assert not bool(step_failed(good)) and bool(step_failed(ascent))
    adam = optax.adam(0.1)
    assert not bool(step_failed(adam.update(g, adam.init(x), x)[1]))  # reports nothing


def test_unrolled_and_validation_monitor_run_and_agree_with_converged():
    _, problem = _coefficient_problem(n=8, alpha=1e-5)
    # K = 400 from zero solves the 49 unknowns to round-off: the converged answer, from the
    # step program the PRDP run below uses
    ref = invert(problem, refinement=fixed(400), steps=30).history[-1].parameter_error
    unrolled = invert(problem, refinement=fixed(40), gradient="unrolled", steps=30)
    validated = invert(problem, refinement=prdp(K0=5, dK=10), steps=30,
                       monitor=Validation(every=2))
    assert unrolled.history[-1].parameter_error == pytest.approx(ref, rel=0.02)
    assert validated.history[-1].validation_iterations > 0


def test_loop_configuration_errors():
    _, problem = _source_problem()
    with pytest.raises(SolverConfigError, match="gradient"):
        invert(problem, gradient="adjoint", steps=1)
    with pytest.raises(SolverConfigError, match="zero right-hand side"):
        invert(problem, gradient="unrolled", refinement=fixed(3), steps=1)
    with pytest.raises(SolverConfigError, match="tolerance-mode"):
        invert(problem, gradient="unrolled", refinement=converged(), steps=1, init=1.0)
    with pytest.raises(SolverConfigError, match="monitor"):
        invert(problem, monitor="misfit", steps=1)


def test_non_finite_parameters_raise_with_the_step():
    _, problem = _source_problem()
    blow_up = optax.scale(float("nan"))
    with pytest.raises(InversionError, match=r"step 1: .*non-finite"):
        invert(problem, optimizer=blow_up, refinement=fixed(3), steps=2)


def test_settled_ignores_pass_throughs():
    from prdp_fem.inverse import StepRecord
    errors = [1.0, 0.5, 0.2, 0.31, 0.298, 0.301, 0.3]
    records = [StepRecord(i + 1, 1, 1, 0.0, 0, 0, 0, 0, 0, float(i), 0.0, 0.0, 0.0, e,
                          math.nan) for i, e in enumerate(errors)]
    hit = settled(History(records), 0.3)
    assert hit.step == 5  # 0.2 passes through the target, 0.31 is outside the 1 % band


# --- choosing alpha ---------------------------------------------------------------------


def test_morozov_misfit_matches_the_noise_level():
    _, problem = _coefficient_problem(n=12, noise=0.02, alpha=1.0)
    choice = morozov(problem, alpha0=1e-6, rtol=0.01)
    assert choice.misfit_norm == pytest.approx(choice.target, rel=0.05)
    assert choice.target == pytest.approx(float(problem.observation.noise_norm()))


def test_morozov_needs_a_noise_level():
    _, problem = _coefficient_problem(n=6)
    with pytest.raises(PrdpFemError, match="noise level"):
        morozov(problem)


@pytest.mark.slow  # 21 s; Morozov's choice is the default suite's parameter-choice test
def test_l_curve_corner_is_interior_and_near_the_best_alpha():
    _, problem = _coefficient_problem(n=12, noise=0.02, alpha=1.0)
    alphas = np.logspace(-10, -3, 8)
    choice = l_curve(problem, alphas)
    assert alphas[0] < choice.alpha < alphas[-1]
    errors = {a: error for a, _, _, error in choice.trials}
    assert errors[choice.alpha] <= 3 * min(errors.values())


def test_state_error_against_pyamg_when_asked():
    _, problem = _coefficient_problem(n=8, alpha=1e-5)
    truncated = invert(problem, refinement=fixed(2), steps=2, reference_every=1).history
    # K = 400 solves the 49 unknowns to round-off, in the same step program as K = 2
    exact = invert(problem, refinement=fixed(400), steps=2, reference_every=2).history
    assert truncated[0].state_error > 1e-3 and truncated[1].state_error > 1e-3
    assert math.isnan(exact[0].state_error) and exact[1].state_error < 1e-8


@pytest.mark.parametrize("regularization", ["l2", "h1"])
def test_an_evaluation_lays_out_no_constant_matrix(regularization):
    """The observation's B and W and the regulariser's Gram matrix are laid out once, when
    the problem is built: an evaluation's program pads and gathers none of their values
    (the mother problem at 66k unknowns copied and gathered W's and the Gram matrix's 460k
    values in every evaluation, 3 ms of 8 at K = 0), and its value and gradient are the
    SciPy ones."""
    disc = pf.discretize(pf.unit_square(8), element="P1", dirichlet=0.0)
    data = disc.project(lambda x: x[0] * x[1])
    problem = inverse_problem(disc, full_field(disc, data=data), unknown="source", alpha=1e-3,
                              regularization=regularization)
    W = problem.observation.weight.to_scipy()
    gram = problem.regularizer.gram.to_scipy()
    solver = ConvergedCG(rtol=1e-13)

    def J(z):
        return problem.loss(z, solver)[0]

    z = jnp.asarray(np.cos(np.arange(problem.n_parameters, dtype=float)))
    jaxpr = str(jax.make_jaxpr(jax.value_and_grad(J))(z))
    for nnz in {W.nnz, gram.nnz}:
        assert f"f64[{nnz + 1}]" not in jaxpr  # a padded copy of the values
    A, S = disc.stiffness_matrix(np.ones(disc.n_kappa)), disc.source_matrix
    u = disc.expand(spla.spsolve(A.tocsc(), S @ np.asarray(z)))
    r = u - np.asarray(data)
    value, grad = jax.jit(jax.value_and_grad(J))(z)  # one program, not op by op
    expected = 0.5 * r @ (W @ r) + 0.5e-3 * np.asarray(z) @ (gram @ np.asarray(z))
    np.testing.assert_allclose(value, expected, rtol=1e-10)
    adjoint = spla.spsolve(A.T.tocsc(), (W @ r)[disc.free_dofs])
    np.testing.assert_allclose(grad, S.T @ adjoint + 1e-3 * gram @ np.asarray(z), rtol=1e-8,
                               atol=1e-12 * np.abs(grad).max())
