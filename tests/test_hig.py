"""Half-inverse gradients: closed forms, dropping, matrix-free SVD, residuals, invert, scenes."""

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.sparse as sp

import prdp_fem as pf
from prdp_fem.errors import SolverConfigError
from prdp_fem.fem import full_field, point_sensors, regularizer, square_root_factor, with_noise
from prdp_fem.inverse import converged, inverse_problem, invert, taylor_test
from prdp_fem.linalg import ConvergedCG, TruncatedCG
from prdp_fem.optim import hig, hig_direction, hig_update, randomized_svd, residual_jacobian
from prdp_fem.scene import build, parse_scene
from prdp_fem.scene.spec import SceneSolverConfigError


def _linear_least_squares(m=30, n=12, seed=0):
    """``r(theta) = A theta - b`` with singular values spread over four decades."""
    rng = np.random.default_rng(seed)
    u, _ = np.linalg.qr(rng.standard_normal((m, n)))
    v, _ = np.linalg.qr(rng.standard_normal((n, n)))
    A = u @ np.diag(np.logspace(0, -4, n)) @ v.T
    return A, rng.standard_normal(m), rng.standard_normal(n)


def _numpy_step(A, r, exponent, eta, keep=None):
    U, S, Vt = np.linalg.svd(A, full_matrices=False)
    keep = np.ones_like(S, bool) if keep is None else keep
    return -eta * Vt.T @ (np.where(keep, S, 1.0) ** exponent * keep * (U.T @ r))


def _rel(a, b):
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(b))


def _apply(transformation, theta, residual_fn):
    state = transformation.init(theta)
    step, state = transformation.update(jnp.zeros_like(theta), state, theta,
                                        residual_fn=residual_fn)
    return step, state


# --- the update against closed forms ---------------------------------------------------


@pytest.mark.parametrize("exponent", [-0.5, -1.0, 1.0, 0.25])
def test_update_equals_numpy_closed_form(exponent):
    A, b, theta = _linear_least_squares()
    r = A @ theta - b
    expected = _numpy_step(A, r, exponent, 0.7)
    step, info = hig_update(jnp.asarray(A), jnp.asarray(r), learning_rate=0.7,
                            exponent=exponent)
    assert _rel(step, expected) < 1e-10
    assert int(info.rank) == 12 and float(info.s_max) == pytest.approx(1.0, rel=1e-12)
    for mode in ("reverse", "forward"):  # the optax transformation, explicit Jacobian
        transformed, state = _apply(hig(0.7, exponent, jacobian=mode), jnp.asarray(theta),
                                    lambda t: jnp.asarray(A) @ t - b)
        assert _rel(transformed, expected) < 1e-10
        assert (int(state.rank), int(state.count)) == (12, 1)


def test_gauss_newton_step_lands_on_the_least_squares_minimiser():
    A, b, theta = _linear_least_squares()
    q, R = np.linalg.qr(A)  # a dense QR solve (normal equations would square cond = 1e4)
    minimiser = np.linalg.solve(R, q.T @ b)
    step, _ = _apply(hig(1.0, exponent=-1.0), jnp.asarray(theta),
                     lambda t: jnp.asarray(A) @ t - b)
    assert _rel(theta + step, minimiser) < 1e-10


def test_exponent_one_is_the_gradient_also_for_pytree_parameters():
    A, b, theta = _linear_least_squares()
    step, _ = hig_update(jnp.asarray(A), jnp.asarray(A @ theta - b), learning_rate=0.3,
                         exponent=1.0, tau=0.0)
    assert _rel(step, -0.3 * A.T @ (A @ theta - b)) < 1e-13
    # a small network, residuals stacked over a (batch, outputs) array
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    params = {"w1": jax.random.normal(keys[0], (3, 5)), "b1": jnp.zeros(5),
              "w2": jax.random.normal(keys[1], (5, 2))}
    x, y = jax.random.normal(keys[2], (7, 3)), jax.random.normal(keys[3], (7, 2))

    def residual(p):
        return jnp.tanh(x @ p["w1"] + p["b1"]) @ p["w2"] - y

    # jitted: one program each instead of the network's ops compiled one by one
    step, info = jax.jit(lambda p: hig_update(jax.jacrev(residual)(p), residual(p),
                                              learning_rate=0.5, exponent=1.0, tau=0.0))(params)
    gradient = jax.jit(jax.grad(lambda p: 0.5 * jnp.sum(residual(p) ** 2)))(params)
    for name in params:
        assert _rel(step[name], -0.5 * gradient[name]) < 1e-12
    assert int(info.rank) == 14  # min(7 x 2 residuals, 27 parameters)


def test_relative_learning_rate_scales_by_the_top_singular_value():
    A, b, theta = _linear_least_squares()
    A = 40.0 * A  # s_max = 40
    for exponent in (1.0, -0.5):
        step, state = _apply(hig(0.5, exponent, relative=True), jnp.asarray(theta),
                             lambda t, A=A: jnp.asarray(A) @ t - b)
        expected = _numpy_step(A, A @ theta - b, exponent, 0.5 * 40.0 ** -(1.0 + exponent))
        assert _rel(step, expected) < 1e-10
        assert float(state.s_max) == pytest.approx(40.0, rel=1e-12)


def test_singular_values_below_tau_are_dropped_not_clamped():
    rng = np.random.default_rng(1)
    u, _ = np.linalg.qr(rng.standard_normal((8, 4)))
    v, _ = np.linalg.qr(rng.standard_normal((4, 4)))
    s = np.array([3.0, 1.0, 0.5, 1e-9])  # 1e-9 < tau s_max = 3e-6
    J, r = u @ np.diag(s) @ v.T, rng.standard_normal(8)
    step, info = hig_update(jnp.asarray(J), jnp.asarray(r), exponent=-0.5, tau=1e-6)
    assert int(info.rank) == 3
    assert _rel(step, _numpy_step(J, r, -0.5, 1.0, keep=s > 3e-6)) < 1e-10
    # no component along the dropped direction (a clamped 1e-9^-1/2 would be ~3e4 there)
    assert abs(float(v[:, 3] @ step)) < 1e-13 * float(jnp.linalg.norm(step))
    kept_everything, _ = hig_update(jnp.asarray(J), jnp.asarray(r), exponent=-0.5, tau=0.0)
    assert abs(float(v[:, 3] @ kept_everything)) == pytest.approx(
        abs(u[:, 3] @ r) / np.sqrt(1e-9), rel=1e-5)


def test_all_singular_values_dropped_gives_a_zero_step():
    step, info = hig_update(jnp.zeros((5, 3)), jnp.ones(5), exponent=-1.0)
    assert step.tolist() == [0.0, 0.0, 0.0]
    assert (int(info.rank), float(info.s_max)) == (0, 0.0)
    d, _ = hig_direction(jnp.eye(2), jnp.zeros(2), jnp.eye(2), jnp.ones(2), exponent=-1.0)
    assert d.tolist() == [0.0, 0.0]


# --- matrix-free truncated SVD -----------------------------------------------------------


def test_randomized_svd_is_exact_on_an_exact_rank_k_operator():
    rng = np.random.default_rng(2)
    J = rng.standard_normal((40, 4)) @ rng.standard_normal((4, 25))
    u, s, vt = randomized_svd(lambda v: J @ v, lambda w: J.T @ w, J.shape, 4,
                              jax.random.PRNGKey(0), oversample=3, power_iterations=0)
    assert np.allclose(s, np.linalg.svd(J, compute_uv=False)[:4], rtol=1e-12)
    assert _rel((u * s) @ vt, J) < 1e-12


def test_matrix_free_matches_explicit_on_a_rank_k_network():
    """A nonlinear residual whose Jacobian has rank exactly 3 (a width-3 bottleneck)."""
    rng = np.random.default_rng(3)
    W1, W2 = jnp.asarray(rng.standard_normal((3, 20))), jnp.asarray(rng.standard_normal((30, 3)))
    data = jnp.asarray(rng.standard_normal(30))

    def residual(theta):
        return jnp.tanh(W2 @ jnp.tanh(W1 @ theta)) - data

    theta = jnp.asarray(0.3 * rng.standard_normal(20))
    explicit, explicit_state = jax.jit(lambda t: _apply(hig(0.5), t, residual))(theta)
    free, free_state = jax.jit(lambda t: _apply(hig(0.5, rank=3), t, residual))(theta)
    assert int(explicit_state.rank) == int(free_state.rank) == 3
    assert float(free_state.s_max) == pytest.approx(float(explicit_state.s_max), rel=1e-12)
    assert _rel(free, explicit) < 1e-9


@pytest.mark.slow  # the matrix-free product is checked on a network in the default suite
def test_matrix_free_through_an_unrolled_solve_matches_explicit():
    """Five point sensors of a source problem: the misfit Jacobian has rank 5."""
    disc = pf.discretize(pf.unit_square(8), element="P1", dirichlet=0.0)
    sensors = np.random.default_rng(4).uniform(0.1, 0.9, (5, 2))
    u_true = disc.expand(pf.direct_solve(disc.stiffness_matrix(disc.check_kappa(1.0)),
                                         disc.rhs(disc.check_kappa(1.0), np.ones(81))).x)
    problem = inverse_problem(disc, point_sensors(disc, sensors, u_true=u_true),
                              unknown="source", alpha=1e-4, residual=True)
    solver = TruncatedCG(30, gradient="unrolled")

    def residual(z):
        return problem.misfit_residual(z, solver)

    z = jnp.asarray(np.random.default_rng(5).standard_normal(problem.n_parameters))
    explicit, explicit_state = jax.jit(lambda z: _apply(hig(1.0), z, residual))(z)
    free, free_state = jax.jit(lambda z: _apply(hig(1.0, rank=5), z, residual))(z)
    assert int(explicit_state.rank) == int(free_state.rank) == 5
    assert _rel(free, explicit) < 1e-9


@pytest.mark.slow  # 5 s; test_forward_mode checks jvp against vjp through implicit solves
def test_forward_mode_through_an_implicit_solve_equals_reverse_mode():
    # implicit solves are a custom_jvp (tangent solves), so forward-mode Jacobians and the
    # matrix-free SVD go through them; converged here, so every mode gives one Jacobian
    disc, problem = _coefficient_problem(n=4)
    solver = TruncatedCG(60, gradient="implicit", adjoint_iterations=60)
    z = problem.parameterization.from_field(0.5 * np.asarray(problem.truth))

    def residual(z):
        return problem.misfit_residual(z, solver)

    _, forward = jax.jit(lambda z: residual_jacobian(residual, z, "forward"))(z)
    _, reverse = jax.jit(lambda z: residual_jacobian(residual, z, "reverse"))(z)
    assert forward.shape == (disc.n_dofs, problem.n_parameters)
    assert _rel(forward, reverse) < 1e-8
    explicit, _ = jax.jit(lambda z: _apply(hig(1.0), z, residual))(z)
    free, _ = jax.jit(lambda z: _apply(hig(1.0, rank=problem.n_parameters), z, residual))(z)
    assert _rel(free, explicit) < 1e-7


def test_a_residual_without_forward_mode_falls_back_or_raises_clearly():
    @jax.custom_vjp
    def square(x):
        return x ** 2

    square.defvjp(lambda x: (x ** 2, x), lambda x, g: (2.0 * x * g,))
    x = jnp.array([1.0, 2.0])
    tall = (lambda x: jnp.concatenate([square(x), square(x), x]),)   # m > n: auto tries jvp
    _, automatic = residual_jacobian(tall, x, "auto")
    _, reverse = residual_jacobian(tall, x, "reverse")
    assert _rel(automatic, reverse) == 0.0
    with pytest.raises(SolverConfigError, match="forward mode"):
        residual_jacobian(tall, x, "forward")


# --- the inverse problem as a sum of squares --------------------------------------------


def _coefficient_problem(reg="h1", observation="full", n=6, alpha=1e-3):
    disc = pf.discretize(pf.unit_square(n), element="P1", kappa_space="P1", dirichlet=0.0)
    m_true = disc.interpolate_kappa(lambda x: 0.5 * np.sin(np.pi * x[0]) * x[1])
    f = np.ones(disc.n_dofs)
    u = disc.expand(pf.direct_solve(disc.stiffness_matrix(np.exp(m_true)),
                                    disc.rhs(np.exp(m_true), f)).x)
    obs = full_field(disc, u_true=u) if observation == "full" else point_sensors(
        disc, np.random.default_rng(0).uniform(0.1, 0.9, (12, 2)), u_true=u)
    if reg == "tv":  # smooth enough for finite differences at h ~ 1e-2
        reg = regularizer(disc, "log_kappa", "tv", epsilon=0.5)
    return disc, inverse_problem(disc, with_noise(obs, 0.01, seed=1), unknown="log_kappa",
                                 alpha=alpha, regularization=reg, known=f, truth=m_true,
                                 residual=True)


@pytest.mark.parametrize("reg", ["l2", "h1", "tv"])
@pytest.mark.parametrize("observation", ["full", "sensors"])
def test_half_squared_residual_is_the_loss(reg, observation):
    _, problem = _coefficient_problem(reg, observation)
    z = jnp.asarray(np.random.default_rng(6).standard_normal(problem.n_parameters))
    solver = ConvergedCG(rtol=1e-12)
    r = problem.residual(z, solver)
    loss, parts = problem.loss(z, solver)
    assert 0.5 * float(r @ r) == pytest.approx(float(loss), rel=1e-12)
    misfit = problem.misfit_residual(z, solver)
    assert 0.5 * float(misfit @ misfit) == pytest.approx(float(parts.misfit), rel=1e-12)


# h1 with the slow cases (7 s): tv's Jacobian holds the same misfit block and more
@pytest.mark.parametrize("reg", [pytest.param("h1", marks=pytest.mark.slow), "tv"])
def test_residual_jacobian_taylor(reg):
    """``J v`` from the Jacobian HIG uses (reverse mode, implicit solves) against r itself."""
    _, problem = _coefficient_problem(reg, alpha=1e-2)
    solver = ConvergedCG(rtol=1e-13)
    z = problem.parameterization.from_field(0.5 * np.asarray(problem.truth))
    blocks = (lambda z: problem.misfit_residual(z, solver), problem.regularization_residual)
    # jitted: the Jacobian and the residual compile once each, not op by op per evaluation
    r0, J = jax.jit(lambda z: residual_jacobian(blocks, z, "reverse"))(z)
    residual = jax.jit(lambda z: problem.residual(z, solver))
    assert _rel(r0, residual(z)) < 1e-14
    dz = jnp.asarray(np.random.default_rng(7).standard_normal(z.shape))
    # for every component at once: the Taylor test of <w, r(z)> with gradient J^T w
    w = jnp.asarray(np.random.default_rng(8).standard_normal(r0.shape))
    result = taylor_test(lambda z: w @ residual(z), z, dz, gradient=J.T @ w)
    assert result.passed()
    assert np.median(result.rates[np.isfinite(result.rates)]) == pytest.approx(2.0, abs=0.15)
    # and the vector remainder ||r(z + h dz) - r(z) - h J dz|| falls as h^2
    remainders = [float(jnp.linalg.norm(residual(z + h * dz) - r0 - h * J @ dz))
                  for h in (1e-2, 5e-3)]
    assert np.log2(remainders[0] / remainders[1]) == pytest.approx(2.0, abs=0.15)


def test_square_root_factor_of_a_mass_matrix_and_bad_weights():
    disc = pf.discretize(pf.unit_square(6), element="P2", dirichlet=0.0)
    M = disc.mass_matrix
    F = square_root_factor(M, "M")
    assert F.shape == M.shape
    assert abs(F.T @ F - M).max() <= 1e-13 * abs(M).max()
    with pytest.raises(SolverConfigError, match="W: an indefinite weight"):
        square_root_factor(sp.csr_matrix(np.array([[1.0, 2.0], [2.0, 1.0]])), "W")
    with pytest.raises(SolverConfigError, match="W: negative diagonal weights"):
        square_root_factor(sp.diags([1.0, -1.0]), "W")
    with pytest.raises(SolverConfigError, match="not symmetric"):
        square_root_factor(sp.csr_matrix(np.array([[1.0, 0.5], [0.0, 1.0]])), "W")


def test_residual_without_factors_names_the_fix():
    _, problem = _coefficient_problem()
    bare = dataclasses.replace(problem, residual_factors=None)
    with pytest.raises(SolverConfigError, match=r"residual=True"):
        bare.residual(jnp.zeros(bare.n_parameters), ConvergedCG())
    with pytest.raises(SolverConfigError, match=r"residual=True"):
        invert(bare, optimizer=hig(1.0), refinement=converged(1e-8), steps=1)


# --- invert ------------------------------------------------------------------------------


def _source_problem(alpha=1e-6):
    """The mother problem on an 8 x 8 mesh, and its discrete minimiser (a dense solve)."""
    disc = pf.discretize(pf.unit_square(8), element="P1", dirichlet=0.0)
    data = disc.project(lambda x: np.sin(np.pi * x[0]) * np.sin(np.pi * x[1]) / (2 * np.pi ** 2))
    truth = disc.interpolate(
        lambda x: np.sin(np.pi * x[0]) * np.sin(np.pi * x[1]) / (1 + 4 * alpha * np.pi ** 4))
    problem = inverse_problem(disc, full_field(disc, data=data), unknown="source", alpha=alpha,
                              regularization="l2", truth=truth, residual=True)
    A = disc.stiffness_matrix(disc.check_kappa(1.0)).toarray()
    expand = np.zeros((disc.n_dofs, disc.n_free))
    expand[disc.free_dofs, np.arange(disc.n_free)] = 1.0
    G = expand @ np.linalg.solve(A, disc.source_matrix.toarray())
    M = disc.mass_matrix.toarray()
    return problem, np.linalg.solve(G.T @ M @ G + alpha * M, G.T @ M @ data)


def test_invert_gauss_newton_lands_on_the_minimiser_and_hig_lowers_the_error():
    problem, minimiser = _source_problem()
    gn = invert(problem, optimizer=hig(1.0, exponent=-1.0), refinement=converged(1e-12),
                steps=1)
    assert _rel(gn.field, minimiser) < 1e-9
    assert int(gn.optimizer_state.rank) == problem.n_parameters
    run = invert(problem, optimizer=hig(3.0), refinement=converged(1e-12), steps=5)
    errors = [r.parameter_error for r in run.history]
    assert all(a > b for a, b in itertools.pairwise(errors))
    # from 1.0 at z = 0: 0.753, 0.564, 0.419, 0.308, 0.223
    assert errors[-1] == pytest.approx(0.2230, rel=1e-2)
    assert errors[-1] < 0.25 * float(problem.parameter_error(jnp.zeros(problem.n_parameters)))


# adam: a second optimiser through the same path (a residual problem run by a first-order
# optimiser); the L-BFGS case keeps it in the default suite
@pytest.mark.parametrize("optimizer", [None, pytest.param(optax.adam(0.1),
                                                          marks=pytest.mark.slow)],
                         ids=["lbfgs", "adam"])
def test_lbfgs_and_adam_still_run_next_to_the_residual(optimizer):
    problem, _ = _source_problem()
    run = invert(problem, optimizer=optimizer, refinement=converged(1e-10), steps=2)
    assert run.history[-1].parameter_error < 0.999


# --- options and scenes ------------------------------------------------------------------


@pytest.mark.parametrize("kwargs, message", [
    ({"learning_rate": 0.0}, "learning_rate=0.0"),
    ({"learning_rate": 1.0, "exponent": float("nan")}, "exponent=nan"),
    ({"learning_rate": 1.0, "tau": 1.0}, r"tau=1.0: expected a number in \[0, 1\)"),
    ({"learning_rate": 1.0, "rank": 0}, "rank=0"),
    ({"learning_rate": 1.0, "jacobian": "sideways"}, "jacobian='sideways'"),
    ({"learning_rate": 1.0, "oversample": -1}, "oversample=-1"),
])
def test_bad_options_name_the_option(kwargs, message):
    with pytest.raises(SolverConfigError, match=message):
        hig(**kwargs)


def test_hig_update_rejects_schedules_and_mismatched_jacobians():
    with pytest.raises(SolverConfigError, match=r"learning_rate=.*no schedule"):
        hig_update(jnp.eye(2), jnp.ones(2), learning_rate=optax.constant_schedule(1.0))
    with pytest.raises(SolverConfigError, match=r"residual.shape = \(3,\)"):
        hig_update(jnp.eye(2), jnp.ones(3))


def test_update_without_a_residual_is_a_clear_error():
    transformation = hig(1.0)
    with pytest.raises(SolverConfigError, match="residual_fn="):
        transformation.update(jnp.ones(2), transformation.init(jnp.ones(2)), jnp.ones(2))


def test_scene_selects_hig_and_validates_its_options():
    table = {"mesh": {"n": 6},
             "inverse": {"unknown": "source", "truth": "sin(pi*x)*sin(pi*y)", "alpha": 1e-6,
                         "regularization": "l2"},
             "refinement": {"kind": "converged", "rtol": 1e-12},
             "optimizer": {"name": "hig", "steps": 1, "learning_rate": 1.0, "exponent": -1,
                           "tau": 1e-9}}
    scene = parse_scene(table)
    spec = scene.optimizer
    assert (spec.name, spec.exponent, spec.tau, spec.rank, spec.relative) == (
        "hig", -1.0, 1e-9, None, False)
    relative = parse_scene({**table, "optimizer": {"name": "hig", "relative": True}})
    assert relative.optimizer.relative is True
    setup = build.build_inverse(scene)
    assert setup.problem.residual_factors is not None
    run = invert(setup.problem, **build.invert_options(scene, setup.disc))
    # noise-free data from the truth: one Gauss-Newton step comes close to it
    assert run.history[-1].parameter_error < 0.05
    for key, value, message in [("tau", 1.5, "optimizer.tau = 1.5: expected a number in [0, 1)"),
                                ("rank", 0, "optimizer.rank = 0: expected an integer >= 1"),
                                ("exponent", "half", "optimizer.exponent = 'half'"),
                                ("relative", 1, "optimizer.relative = 1: expected true or false")]:
        bad = {**table, "optimizer": {"name": "hig", key: value}}
        with pytest.raises(SceneSolverConfigError) as info:
            parse_scene(bad)
        assert message in str(info.value)


@pytest.mark.slow  # ~25 s: three inversions of the example, compiled separately
def test_comparison_example_pins_gauss_newton_and_hig(load_example):
    example = load_example("hig_comparison")
    result = example.main(n=6, steps=3, methods=("gauss-newton", "hig"), solvers=("converged",))
    rows = result["rows"]
    assert (result["n_parameters"], result["n_observations"]) == (49, 169)
    assert np.allclose(rows[("gauss-newton", "converged")]["errors"], [0.5681, 0.2335, 0.0796],
                       rtol=1e-3)
    hig_row = rows[("hig", "converged")]
    assert hig_row["rate"] == "1 rel"
    assert np.allclose(hig_row["errors"], [0.6081, 0.3196, 0.1717], rtol=1e-3)
    assert "gauss-newton" in example.format_rows(result)
