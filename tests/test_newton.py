"""Newton-CG and Gauss-Newton (prdp_fem.optim.newton): against dense solves, closed forms and
hIPPYlib."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import prdp_fem as pf
from prdp_fem.fem import full_field, point_sensors, with_noise
from prdp_fem.inverse import converged, inverse_problem, invert
from prdp_fem.linalg import ConvergedCG
from prdp_fem.optim import gauss_newton, newton_cg


def update(optimizer, state, z, fn, **extra):
    """One update of ``optimizer`` at ``z`` on the objective ``fn``: (new z, new state)."""
    value, grad = jax.value_and_grad(fn)(z)
    updates, state = optimizer.update(grad, state, z, value=value, grad=grad, value_fn=fn,
                                      **extra)
    return optax.apply_updates(z, updates), state


@functools.cache
def _jitted_update(optimizer, fn):
    return jax.jit(lambda state, z: update(optimizer, state, z, fn))


def jitted_update(optimizer, state, z, fn):
    """:func:`update` as one program per optimizer and objective (op by op, every call
    compiled the update's loops anew)."""
    return _jitted_update(optimizer, fn)(state, z)


# ------------------------------------------------------------------------------------------
# a linear least-squares problem: one Gauss-Newton step is the minimiser
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def source():
    """Source inversion, P1 on 6 x 6, H1 regularisation: J is quadratic. Its dense pieces."""
    disc = pf.discretize(pf.unit_square(6), element="P1", kappa_space="P0",
                         dirichlet={"left": 0.5, "bottom": 0.0})
    kappa = disc.interpolate_kappa(lambda x: 1.0 + x[0])
    f_true = disc.interpolate(lambda x: np.sin(np.pi * x[0]) * np.sin(np.pi * x[1]))
    u_true = disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa),
                                         disc.rhs(kappa, f_true)).x)
    data = with_noise(full_field(disc, u_true=u_true), 0.05, 0)
    alpha = 1e-4
    problem = inverse_problem(disc, data, unknown="source", alpha=alpha, regularization="h1",
                              known=kappa)
    # J(f) = 1/2 ||E A^-1 (S f + c) + g - d||_W^2 + alpha/2 f' L f, c the lifting, g Dirichlet
    A = disc.stiffness_matrix(kappa).toarray()
    E = np.zeros((disc.n_dofs, disc.n_free))
    E[disc.free_dofs, np.arange(disc.n_free)] = 1.0
    G = E @ np.linalg.solve(A, disc.source_matrix.toarray())
    offset = disc.expand(np.linalg.solve(A, disc.rhs(kappa)))  # u at f = 0, Dirichlet included
    W, L = disc.mass_matrix.toarray(), disc.laplace_matrix.toarray()
    H = G.T @ W @ G + alpha * L
    minimiser = np.linalg.solve(H, G.T @ W @ (np.asarray(data.data) - offset))
    return disc, problem, H, minimiser


@pytest.mark.parametrize("optimizer", [pytest.param("gauss_newton", marks=pytest.mark.slow),
                                       "exact"])
def test_one_newton_step_reaches_the_least_squares_minimiser(source, optimizer):
    disc, problem, _, minimiser = source
    opt = gauss_newton(max_cg=200, forcing=1e-12) if optimizer == "gauss_newton" \
        else newton_cg(max_cg=200, forcing=1e-12)
    result = invert(problem, optimizer=opt, refinement=converged(1e-13), steps=1)
    error = np.linalg.norm(np.asarray(result.field) - minimiser) / np.linalg.norm(minimiser)
    assert error < 1e-8  # measured 4e-15
    state = result.optimizer_state
    assert int(state.steps) == 1 and float(state.step_size) == 1.0
    assert int(state.line_search_evaluations) == 1  # the unit step is accepted at once
    assert 1 <= int(state.cg_iterations) <= disc.n_dofs


def test_gauss_newton_and_exact_hessian_products_equal_the_dense_hessian(source):
    disc, problem, H, _ = source
    solver = ConvergedCG(rtol=1e-13)
    z = jnp.asarray(np.random.default_rng(1).normal(size=disc.n_dofs))
    v = jnp.asarray(np.random.default_rng(2).normal(size=disc.n_dofs))
    # the problem is an argument of the jitted function, not a constant folded into it; both
    # products in one program (one compile, not two)
    gauss_newton_v, exact_v = jax.jit(lambda p, z, v: (
        p.gauss_newton_product(z, v, solver),
        jax.jvp(jax.grad(lambda z: p.loss(z, solver)[0]), (z,), (v,))[1]))(problem, z, v)
    dense = H @ np.asarray(v)
    np.testing.assert_allclose(gauss_newton_v, dense, rtol=1e-9, atol=1e-9 * abs(dense).max())
    np.testing.assert_allclose(exact_v, dense, rtol=1e-9, atol=1e-9 * abs(dense).max())


def test_gauss_newton_operator_is_jacobian_transpose_w_jacobian_plus_the_regulariser():
    """Nonlinear (log-kappa) problem: H_GN v against J^T W J v + alpha L v with J = jacfwd."""
    disc = pf.discretize(pf.unit_square(4), element="P1", kappa_space="P1", dirichlet=0.0)
    sensors = np.array([[0.3, 0.4], [0.6, 0.5], [0.5, 0.75]])
    f = np.ones(disc.n_dofs)
    problem = inverse_problem(disc, point_sensors(disc, sensors, data=np.ones(3)),
                              unknown="log_kappa", alpha=1e-3, known=f)
    solver = ConvergedCG(rtol=1e-13)
    z = jnp.asarray(disc.interpolate_kappa(lambda x: 0.3 * x[0] - 0.2 * x[1]))

    def observed(problem, z):
        return pf.linalg.matvec(problem.observation.operator,
                         problem.system.expand(problem.state(z, solver).x))

    v = jnp.asarray(np.random.default_rng(3).normal(size=z.shape))
    # the Jacobian, the regulariser's Hessian and the product in one program (one compile)
    J, L, product = (np.asarray(a) for a in jax.jit(lambda p, z, v: (
        jax.jacfwd(observed, argnums=1)(p, z), jax.hessian(lambda m: p.regularizer(m))(z),
        p.gauss_newton_product(z, v, solver)))(problem, z, v))
    W = problem.observation.weight.to_scipy().toarray()
    expected = J.T @ W @ J @ v + 1e-3 * L @ v
    np.testing.assert_allclose(product, expected, rtol=1e-10, atol=1e-12 * abs(expected).max())


# ------------------------------------------------------------------------------------------
# the algorithm on small analytic objectives
# ------------------------------------------------------------------------------------------


def quartic(z):
    """Non-convex at the origin (Hessian diag(-1, 2)), minimised at (+-1, 0)."""
    return 0.25 * z[0] ** 4 - 0.5 * z[0] ** 2 + z[1] ** 2 + 0.1 * z[0] + 0.3 * z[1]


def test_negative_curvature_takes_the_steepest_descent_direction():
    opt = newton_cg()
    z = jnp.zeros(2)
    z1, state = jitted_update(opt, opt.init(z), z, quartic)
    # the first CG direction -g = (-0.1, -0.3) has d.Hd = -0.01 + 0.18 > 0; the second
    # meets negative curvature, so the step is the first CG iterate, alpha d = -(rz / dHd) g
    g = np.array([0.1, 0.3])
    H = np.diag([-1.0, 2.0])
    alpha = (g @ g) / (g @ H @ g)
    assert bool(state.negative_curvature)
    assert int(state.cg_iterations) == 2
    np.testing.assert_allclose(z1, -alpha * g * float(state.step_size), rtol=1e-12)
    assert float(quartic(z1)) < float(quartic(z))


def test_negative_curvature_at_the_first_direction_steps_along_minus_g():
    def fn(z):
        return -0.5 * jnp.sum(z ** 2) + 0.1 * jnp.sum(z ** 4) + jnp.sum(z)

    opt = newton_cg(max_backtracking=30)
    z = jnp.zeros(3)
    z1, state = update(opt, opt.init(z), z, fn)
    assert bool(state.negative_curvature) and int(state.cg_iterations) == 1
    t = float(state.step_size)
    np.testing.assert_allclose(z1, -t * np.ones(3), rtol=1e-14)  # p = -g = -(1, 1, 1)
    assert float(fn(z1)) <= float(fn(z)) + 1e-4 * t * (-3.0)  # Armijo


def test_backtracking_halves_until_armijo_holds():
    """J(z) = sqrt(1 + z^2): Newton's unit step from z = 2 overshoots to -8; t = 1/4 is the
    first halving with J(z + t p) <= J(z) + c1 t g p."""
    def fn(z):
        return jnp.sum(jnp.sqrt(1.0 + z ** 2))

    opt = newton_cg(forcing=1e-10)
    z = jnp.array([2.0])
    z1, state = update(opt, opt.init(z), z, fn)
    p = -2.0 * (1 + 4.0)  # -g/h with g = z/sqrt(1+z^2), h = (1+z^2)^(-3/2): -z (1 + z^2)
    g = 2.0 / math.sqrt(5.0)
    accepted = [t for t in (1.0, 0.5, 0.25, 0.125)
                if math.sqrt(1 + (2 + t * p) ** 2) <= math.sqrt(5.0) + 1e-4 * t * g * p]
    assert float(state.step_size) == accepted[0] == 0.25
    assert int(state.line_search_evaluations) == 3
    np.testing.assert_allclose(z1, [2.0 + 0.25 * p], rtol=1e-12)


def test_forcing_terms_follow_their_formulas():
    def fn(z):
        return jnp.sum(jnp.exp(z) - z) + 0.5 * jnp.sum(jnp.arange(1.0, 5.0) * z ** 2)

    z0 = jnp.linspace(-1.0, 1.0, 4)
    for forcing in ("eisenstat_walker", "hippylib"):
        opt = newton_cg(forcing=forcing, forcing_max=0.5)
        z1, state = jitted_update(opt, opt.init(z0), z0, fn)
        assert float(state.forcing) == 0.5  # eta_0 = forcing_max under both rules
        _, state = jitted_update(opt, state, z1, fn)
        ratio = float(state.grad_norm) / float(state.initial_grad_norm)
        if forcing == "hippylib":
            expected = min(0.5, math.sqrt(ratio))
        else:  # choice 2, gamma = 0.9, exponent 2, safeguard 0.9 * 0.5^2 = 0.225 > 0.1
            expected = min(0.5, max(0.9 * ratio ** 2, 0.9 * 0.5 ** 2))
        assert float(state.forcing) == pytest.approx(expected, rel=1e-12)


def test_inner_cg_stops_at_the_forcing_tolerance_and_counts_products():
    """Quadratic with H = diag(1..6): CG needs 6 products to converge exactly; with eta the
    preconditioned residual must fall below eta ||g|| after the reported products."""
    scale = jnp.arange(1.0, 7.0)

    def fn(z):
        return 0.5 * jnp.sum(scale * z ** 2) - jnp.sum(z)

    z = jnp.zeros(6)
    exact = newton_cg(forcing=1e-12)
    z1, state = jitted_update(exact, exact.init(z), z, fn)
    assert int(state.cg_iterations) == 6
    np.testing.assert_allclose(z1, 1.0 / scale, rtol=1e-12)
    loose = newton_cg(forcing=0.3, max_cg=50)
    z1, state = jitted_update(loose, loose.init(z), z, fn)
    k = int(state.cg_iterations)
    assert 1 <= k < 6
    p = np.asarray(z1) / float(state.step_size)
    residual = np.linalg.norm(1.0 - np.asarray(scale) * p)
    assert residual <= 0.3 * np.linalg.norm(np.ones(6))


def test_converged_updates_are_skipped():
    opt = newton_cg(rtol=1e-6)
    z = jnp.array([0.5, -0.25])

    def fn(z):
        return jnp.sum(jnp.cosh(z))

    state = opt.init(z)
    for _ in range(6):
        z, state = jitted_update(opt, state, z, fn)
    assert bool(state.converged)
    assert int(state.cg_iterations) == int(state.line_search_evaluations) == 0
    assert float(jnp.max(jnp.abs(z))) < 1e-10  # quadratic convergence to 0 well before step 6
    assert int(state.steps) < 6


def test_nan_gradient_gives_nan_updates_and_a_failed_search_a_zero_step():
    opt = newton_cg(max_backtracking=3)
    z = jnp.array([1.0])
    nan_fn = lambda z: jnp.sum(jnp.sqrt(z - 2.0))  # noqa: E731 (NaN value and gradient)
    z1, _ = update(opt, opt.init(z), z, nan_fn)
    assert np.isnan(np.asarray(z1)).all()

    def wall(z):  # a minimum at 0, but every trial point is +inf
        return jnp.where(z[0] == 1.0, 1.0, jnp.inf) + 0.5 * jnp.sum(z ** 2)

    z1, state = update(opt, opt.init(z), z, wall)
    assert bool(state.line_search_failed)
    assert int(state.line_search_evaluations) == 4  # the unit step and 3 halvings
    np.testing.assert_array_equal(z1, z)


def test_jit_and_pytree_parameters():
    def fn(params):
        return jnp.sum((params["a"] - 1.0) ** 2) + jnp.sum(jnp.cosh(params["b"]))

    opt = newton_cg(forcing=1e-10)
    params = {"a": jnp.zeros(2), "b": jnp.ones(3)}
    step = jax.jit(lambda p, s: update(opt, s, p, fn))
    state = opt.init(params)
    for _ in range(5):
        params, state = step(params, state)
    np.testing.assert_allclose(params["a"], 1.0, rtol=1e-12)
    np.testing.assert_allclose(params["b"], 0.0, atol=1e-12)


@pytest.mark.parametrize("kwargs, message", [
    ({"hessian": "bfgs"}, "hessian='bfgs'"),
    ({"max_cg": 0}, "max_cg=0"),
    ({"max_cg": 2.5}, "max_cg=2.5"),
    ({"forcing": "ew"}, "forcing='ew'"),
    ({"forcing": 1.5}, "forcing=1.5"),
    ({"forcing_max": 1.0}, "forcing_max=1.0"),
    ({"c1": 0.7}, "c1=0.7"),
    ({"shrink": 0.0}, "shrink=0.0"),
    ({"max_backtracking": -1}, "max_backtracking=-1"),
    ({"gtol": float("nan")}, "gtol=nan"),
    ({"rtol": -1.0}, "rtol=-1.0"),
    ({"preconditioner": lambda v: v}, "preconditioner="),
])
def test_bad_options_name_the_option(kwargs, message):
    with pytest.raises(pf.SolverConfigError, match=message):
        newton_cg(**kwargs)


def test_gauss_newton_needs_its_operator():
    opt = gauss_newton()
    z = jnp.zeros(2)
    with pytest.raises(pf.SolverConfigError, match="gauss_newton_fn"):
        update(opt, opt.init(z), z, lambda z: jnp.sum(z ** 2))
    with pytest.raises(pf.SolverConfigError, match="hessian="):
        gauss_newton(hessian="exact")


# ------------------------------------------------------------------------------------------
# hIPPYlib's coefficient problem, small
# ------------------------------------------------------------------------------------------


def test_newton_cg_on_the_hippylib_problem_at_16(load_example):
    result = load_example("newton_coefficient").run(16)
    # measured: 8 Newton steps, 38 CG, ||g||/||g_0|| = 5.4e-7 (hIPPYlib at 64 x 64: 7 / 41)
    assert result["converged"] and result["gradient_reduction"] <= 1e-6
    assert 6 <= result["newton_iterations"] <= 10
    assert result["cg_iterations"] <= 60
    # the same minimiser as L-BFGS's converged run (test_examples pins 0.079 there)
    assert result["parameter_error"] == pytest.approx(0.079, abs=0.003)
    # misfit at the noise level (the discrepancy principle's target for gamma = 1e-8)
    assert result["relative_misfit"] == pytest.approx(result["noise_level"], rel=0.05)


# ------------------------------------------------------------------------------------------
# scenes: [optimizer] name = "newton_cg" | "gauss_newton"
# ------------------------------------------------------------------------------------------


def newton_scene(**optimizer):
    from prdp_fem.scene import parse_scene
    return parse_scene({"mesh": {"n": 4},
                        "inverse": {"unknown": "source", "truth": "x*y", "alpha": 1e-4,
                                    "regularization": "h1"},
                        "refinement": {"kind": "converged", "rtol": 1e-12},
                        "optimizer": optimizer})


def test_scene_selects_newton_and_its_options():
    from prdp_fem.scene import build
    scene = newton_scene(name="gauss_newton", steps=1, max_cg=300, forcing=1e-12,
                         c1=1e-3, max_backtracking=4, gradient_rtol=1e-8)
    spec = scene.optimizer
    assert (spec.name, spec.max_cg, spec.forcing, spec.c1, spec.max_backtracking,
            spec.gradient_rtol) == ("gauss_newton", 300, 1e-12, 1e-3, 4, 1e-8)
    setup = build.build_inverse(scene)
    result = invert(setup.problem, **build.invert_options(scene, setup.disc))
    # a quadratic problem (source, H1): the one Gauss-Newton step solves it, so the gradient
    # at the result vanishes against the first one
    problem = setup.problem
    grad = jax.jit(jax.grad(lambda z, p: p.loss(z, ConvergedCG(rtol=1e-13))[0]))
    g0 = np.linalg.norm(grad(jnp.zeros(problem.n_parameters), problem))
    assert np.linalg.norm(grad(result.params, problem)) < 1e-9 * g0
    assert int(result.optimizer_state.steps) == 1
    assert newton_scene(name="newton_cg").optimizer.forcing == "eisenstat_walker"


@pytest.mark.parametrize("key, value, expected", [
    ("name", "newton", "optimizer.name = 'newton'"),
    ("max_cg", 0, "optimizer.max_cg = 0: expected an integer >= 1"),
    ("forcing", "ew", "optimizer.forcing = 'ew': expected 'eisenstat_walker', 'hippylib'"),
    ("forcing", 1.0, "optimizer.forcing = 1.0"),
    ("c1", 0.5, "optimizer.c1 = 0.5: expected a number in \\(0, 0.5\\)"),
    ("max_backtracking", -1, "optimizer.max_backtracking = -1"),
    ("gradient_rtol", -1e-3, "optimizer.gradient_rtol = -0.001"),
])
def test_scene_rejects_bad_newton_options(key, value, expected):
    from prdp_fem.scene.spec import SceneSolverConfigError
    with pytest.raises(SceneSolverConfigError, match=expected):
        newton_scene(**{"name": "newton_cg", key: value})


@pytest.mark.slow  # 5 s; the pin is checked in test_discretization and test_scene, Newton-CG's
# convergence on the inclusion at 16 x 16 above
def test_the_hippylib_tutorial_problem_at_16_pins_its_state_and_converges(load_example):
    """hIPPYlib's tutorial itself (flux on the whole boundary, the state pinned at the
    centre): the pin holds, Gauss-Newton-CG with Eisenstat-Walker forcing converges."""
    example = load_example("newton_coefficient")
    disc, _ = example.build_tutorial(16)
    centre = int(np.argmin(np.linalg.norm(disc.basis.doflocs - 0.5, axis=0)))
    assert disc.dirichlet_dofs.tolist() == [centre] and disc.dirichlet_values.tolist() == [0.0]
    result = example.run(16, "gauss_newton", "eisenstat_walker", problem="tutorial", cycles=8)
    assert result["converged"] and result["newton_iterations"] <= 8
    assert result["relative_misfit"] == pytest.approx(result["noise_level"], rel=0.1)


@pytest.mark.slow  # 64 x 64 with converged solves: about 30 s on 2 cores
def test_the_hippylib_tutorial_at_64_meets_its_newton_and_cg_counts_and_misfit(load_example):
    """At hIPPYlib's size, the inner CG preconditioned by 8 V-cycles of the regularisation
    operator (hIPPYlib solves it exactly): at most its 6 Newton and 26 CG iterations (measured:
    5 / 26), a final misfit within 5 % of its 3.89e-8 (another noise draw)."""
    example = load_example("newton_coefficient")
    result = example.run(64, "gauss_newton", "eisenstat_walker", problem="tutorial", cycles=8)
    assert result["newton_iterations"] <= example.TUTORIAL_ANCHOR["newton"]
    assert result["cg_iterations"] <= example.TUTORIAL_ANCHOR["cg"]
    assert result["misfit"] == pytest.approx(example.TUTORIAL_ANCHOR["misfit"], rel=0.05)


def test_more_v_cycles_are_a_symmetric_map_closer_to_the_inverse(load_example):
    """CycledPreconditioner: symmetric, and ||I - P A|| falls with the number of cycles."""
    import scipy.sparse as sp

    from prdp_fem.optim import regularization_preconditioner

    _, problem = load_example("newton_coefficient").build_tutorial(8)
    reg = problem.regularizer
    A = (pf.fem.gradient_gram(reg.matrix.to_scipy(), reg.weights, reg.dim)
         + problem.parameter_mass.to_scipy()).toarray()
    eye = np.eye(A.shape[0])
    gaps = []
    for cycles in (1, 2, 8):
        P = np.asarray(jax.vmap(regularization_preconditioner(problem, cycles))(
            jnp.asarray(eye))).T
        assert np.abs(P - P.T).max() < 1e-10 * np.abs(P).max()
        gaps.append(np.linalg.norm(eye - P @ A, 2))
    assert gaps[0] > gaps[1] > gaps[2] and gaps[2] < 0.2  # measured: 1.23, 0.81, 0.10
    with pytest.raises(pf.SolverConfigError, match="cycles=0"):
        regularization_preconditioner(problem, 0)
    assert sp.issparse(problem.parameter_mass.to_scipy())


@pytest.mark.slow  # two 64 x 64 runs: about 45 s on 2 cores
def test_prdp_truncated_solves_reach_the_tutorial_s_answer_with_far_fewer_pcg_iterations(
        load_example):
    """The tutorial's PDE solves (state, adjoint, tangent) truncated under PRDP: the same
    misfit and parameter error within 1 % of the converged-solve run, with at most half its
    PCG iterations (measured: 18,200 against 68,911)."""
    example = load_example("newton_coefficient")
    runs = {solves: example.run(64, "gauss_newton", "eisenstat_walker", problem="tutorial",
                                cycles=8, max_steps=15, solves=solves)
            for solves in ("converged", "prdp")}
    exact, truncated = runs["converged"], runs["prdp"]
    assert truncated["misfit"] == pytest.approx(exact["misfit"], rel=0.01)
    assert truncated["parameter_error"] == pytest.approx(exact["parameter_error"], rel=0.01)
    assert truncated["pcg_iterations"] <= 0.5 * exact["pcg_iterations"]


def test_the_tutorial_scene_builds_a_preconditioned_newton_for_its_problem():
    """hippylib_tutorial: the pin, and a Gauss-Newton optimiser built for the problem with 8
    V-cycles of its regularisation operator; preconditioner_cycles is refused for L-BFGS."""
    import tomllib

    from prdp_fem.scene import build, builtin_scene_path, parse_scene

    table = tomllib.loads(builtin_scene_path("hippylib_tutorial").read_text())
    table["mesh"]["n"] = 4
    scene = parse_scene(table, source="t.toml")
    setup = build.build_inverse(scene)
    centre = int(np.argmin(np.linalg.norm(setup.disc.basis.doflocs - 0.5, axis=0)))
    assert setup.disc.dirichlet_dofs.tolist() == [centre]
    optimizer = build.invert_options(scene, setup.disc, setup.problem)["optimizer"]
    state = optimizer.init(jnp.zeros(setup.problem.n_parameters))
    assert state.preconditioner.cycles == 8 and optimizer is not build.optimizer(scene)
    with pytest.raises(pf.SceneError, match=r"needs the inverse problem"):
        build.invert_options(scene, setup.disc)
    with pytest.raises(pf.SceneError, match=r"preconditioner_cycles = 8 with optimizer\.name = "
                       "'lbfgs'"):
        newton_scene(name="lbfgs", preconditioner_cycles=8)


@pytest.mark.slow  # two inversions and a study at 16 x 16: about 18 s
def test_the_tutorial_scene_preconditions_newton_with_its_regularisation_operator(tmp_path):
    """hippylib_tutorial at 16 x 16 through the study runner: the scene's pin and flux, a
    Gauss-Newton optimiser whose inner CG takes 8 V-cycles of the regularisation operator
    (fewer inner iterations than without), and a PRDP run that reaches the converged run's
    band with no more PCG iterations (at 16 x 16, K0 = 200 is about a converged solve; the
    64 x 64 saving is the slow test above). preconditioner_cycles is refused for L-BFGS."""
    import tomllib

    from prdp_fem.optim.newton import CycledPreconditioner
    from prdp_fem.scene import build, builtin_scene_path, parse_scene
    from prdp_fem.studies import run_study

    table = tomllib.loads(builtin_scene_path("hippylib_tutorial").read_text())
    table["mesh"]["n"] = 16
    scene = parse_scene(table, source="t.toml")
    setup = build.build_inverse(scene)
    options = build.invert_options(scene, setup.disc, setup.problem)
    assert setup.disc.dirichlet_dofs.size == 1 and scene.optimizer.preconditioner_cycles == 8
    cg_iterations = {}
    for cycles in (0, 8):
        variant = parse_scene({**table, "optimizer": {**table["optimizer"],
                                                      "preconditioner_cycles": cycles}})
        opts = build.invert_options(variant, setup.disc, setup.problem)
        opts["refinement"] = pf.converged(1e-10)
        state = invert(setup.problem, **opts).optimizer_state
        cg_iterations[cycles] = int(state.total_cg_iterations)
        if cycles:
            assert isinstance(state.preconditioner, CycledPreconditioner)
    assert cg_iterations[8] < cg_iterations[0]
    rows = {row["run"]: row for row in run_study(scene, tmp_path / "t").summary}
    assert rows["prdp"]["reached_step"] is not None and rows["prdp"]["iteration_saving"] >= 0
    assert options["optimizer"] is not build.optimizer(scene)  # built for this problem


@pytest.mark.slow  # four Newton runs at 12 x 12: about 19 s
def test_gauss_newton_first_then_exact_switches_at_the_given_update(load_example):
    """newton_cg(gauss_newton_steps=N): with N past the run's updates it is the Gauss-Newton
    run, update for update; with N = 0 the exact one."""
    example = load_example("newton_coefficient")
    runs = {label: example.run(12, hessian, "eisenstat_walker", problem="tutorial", cycles=8,
                               gauss_newton_steps=steps)
            for label, hessian, steps in [("gn", "gauss_newton", 0), ("exact", "exact", 0),
                                          ("gn first", "exact", 100)]}
    keys = ("newton_iterations", "cg_iterations", "line_search_evaluations")
    assert [runs["gn first"][k] for k in keys] == [runs["gn"][k] for k in keys]
    assert runs["gn"]["cg_iterations"] != runs["exact"]["cg_iterations"]
    assert all(run["converged"] for run in runs.values())


def test_gauss_newton_steps_are_checked_and_belong_to_newton_cg():
    """A bad N, or N with the Gauss-Newton Hessian, is refused; the scene key belongs to
    newton_cg only."""
    for bad, message in [(dict(gauss_newton_steps=-1), "expected an integer >= 0"),
                         (dict(hessian="gauss_newton", gauss_newton_steps=2),
                          "expected hessian='exact'")]:
        with pytest.raises(pf.SolverConfigError, match=message):
            newton_cg(**bad)
    with pytest.raises(pf.SceneError, match=r"gauss_newton_steps = 3 with optimizer\.name = "
                       "'gauss_newton'"):
        newton_scene(name="gauss_newton", gauss_newton_steps=3)
    assert newton_scene(name="newton_cg", gauss_newton_steps=5).optimizer.gauss_newton_steps == 5
