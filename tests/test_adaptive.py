"""The residual-aware controller (prdp.adaptive_tolerance) and the descent check."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prdp_fem as pf
from prdp_fem.errors import SolverConfigError
from prdp_fem.fem import full_field, with_noise
from prdp_fem.inverse import (
    IterateRecorder,
    Objective,
    adaptive_tolerance,
    converged,
    descent_check,
    fixed,
    initial_params,
    inverse_problem,
    invert,
)
from prdp_fem.linalg import ConvergedCG


def _coefficient_problem(n=12):
    disc = pf.discretize(pf.unit_square(n), element="P1", kappa_space="P1", dirichlet=0.0)
    m_true = disc.interpolate_kappa(lambda x: 0.6 * np.sin(np.pi * x[0]) * x[1])
    f = np.ones(disc.n_dofs)
    kappa = np.exp(m_true)
    u = disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f)).x)
    obs = with_noise(full_field(disc, u_true=u), 0.01, seed=2)
    return inverse_problem(disc, obs, unknown="log_kappa", alpha=1e-6, regularization="h1",
                           known=f, truth=m_true)


# --- the rule ---------------------------------------------------------------------------


def test_the_tolerance_follows_the_gradient_and_never_loosens():
    controller = adaptive_tolerance(1e-2, power=1.0, rtol_min=1e-9)
    state = controller.init()
    assert float(state.rtol) == 1e-2 and controller.tolerance_mode
    seen = []
    for g in [2.0, 0.2, 1.0, 2e-3, 1e-12]:
        state = controller.update(state, g)
        seen.append(float(state.rtol))
    # rtol0 (|g| / |g_1|): 1e-2, 1e-3, kept at 1e-3 (never looser), 1e-5, the floor
    np.testing.assert_allclose(seen, [1e-2, 1e-3, 1e-3, 1e-5, 1e-9], rtol=1e-12)
    assert int(state.refinements) == 3 and float(state.checkpoint) == 2.0
    assert int(state.iterations) == 100_000


def test_the_power_and_rtol0_are_read():
    a = adaptive_tolerance(1e-1, power=0.5).init()
    b = adaptive_tolerance(1e-1, power=0.5)
    state = b.update(b.update(a, 1.0), 0.01)
    assert float(state.rtol) == pytest.approx(1e-1 * 0.01 ** 0.5)


def test_a_failed_step_or_a_non_finite_gradient_tightens_the_tolerance():
    controller = adaptive_tolerance(1e-2, failure_factor=0.25)
    first = controller.update(controller.init(), 1.0, True)  # the first step is exempt
    assert float(first.rtol) == 1e-2
    failed = controller.update(first, 1.0, True)
    assert float(failed.rtol) == pytest.approx(2.5e-3)
    broken = controller.update(failed, math.nan)
    assert float(broken.rtol) == pytest.approx(2.5e-3 * 0.25)
    assert float(broken.checkpoint) == 1.0  # a NaN does not become the reference


def test_the_rule_runs_under_jit_as_on_the_host():
    import jax
    controller = adaptive_tolerance(1e-2)
    host = controller.update(controller.update(controller.init(), 3.0), 0.03)
    traced = jax.jit(controller.update)(
        jax.tree.map(jnp.asarray, controller.update(controller.init(), 3.0)), jnp.asarray(0.03))
    assert float(traced.rtol) == pytest.approx(float(host.rtol)) == pytest.approx(1e-4)


@pytest.mark.parametrize("kwargs", [dict(rtol0=1.0), dict(rtol0=1e-3, rtol_min=1e-2),
                                    dict(power=0.0), dict(failure_factor=1.0),
                                    dict(max_iterations=0), dict(max_iterations=True)])
def test_bad_settings_are_refused_with_their_names(kwargs):
    with pytest.raises(SolverConfigError, match=next(iter(kwargs))):
        adaptive_tolerance(**kwargs)


# --- in an inversion ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def problem():
    return _coefficient_problem()


def test_an_adaptive_run_reaches_the_converged_optimum_with_looser_first_solves(problem):
    steps = 40
    reference = invert(problem, refinement=converged(1e-10), steps=steps)
    adaptive = invert(problem, refinement=adaptive_tolerance(1e-2), steps=steps)
    field, field_ref = np.asarray(adaptive.field), np.asarray(reference.field)
    # the tolerance follows the gradient down: the run ends at the converged optimum, not at
    # a nearby stationary point of a truncated objective as a fixed K does
    assert np.linalg.norm(field - field_ref) <= 1e-4 * np.linalg.norm(field_ref)
    truncated = invert(problem, refinement=fixed(3), steps=steps)
    assert np.linalg.norm(np.asarray(truncated.field) - field_ref) > \
        100 * np.linalg.norm(field - field_ref)
    # the first step solves to rtol0 = 1e-2: fewer iterations per solve than to 1e-10
    per_solve = [h[0].primal_iterations / h[0].evaluations
                 for h in (adaptive.history, reference.history)]
    assert per_solve[0] < 0.5 * per_solve[1]
    rtols = adaptive.history.column("rtol")
    assert rtols[0] == 1e-2 and np.all(np.diff(rtols) <= 0) and rtols[-1] < 1e-6


def test_the_controller_picks_its_monitor_and_refuses_another(problem):
    with pytest.raises(SolverConfigError, match="monitor='loss'"):
        invert(problem, refinement=adaptive_tolerance(), monitor="loss", steps=1)
    with pytest.raises(SolverConfigError, match="tolerance-mode"):
        invert(problem, refinement=adaptive_tolerance(), gradient="unrolled", steps=1)


def test_training_refuses_a_controller_fed_the_gradient():
    import jax

    from prdp_fem.learning import learned
    disc = pf.discretize(pf.unit_square(4), element="P1", kappa_space="P0", dirichlet=0.0)
    problem = learned.learned_inverse(disc, pf.full_field(disc, data=np.zeros(disc.n_dofs)),
                                      kappa=2.0, supervised=1e-2)
    samples = learned.source_samples(problem, learned.random_sources(disc, 4, seed=0),
                                     noise=0.0, seed=1)
    network = learned.mlp_init(jax.random.PRNGKey(0), [disc.n_dofs, 4, disc.n_dofs])
    with pytest.raises(SolverConfigError, match="'gradient' norm"):
        learned.train(problem, network, samples, samples, refinement=adaptive_tolerance(),
                      epochs=1, batch_size=2)


# --- the descent check ---------------------------------------------------------------------


def test_the_descent_slope_is_the_converged_objective_s_directional_derivative(problem):
    rng = np.random.default_rng(0)
    z0 = np.asarray(initial_params(problem))
    steps = [z0, z0 + 0.1 * rng.standard_normal(z0.size)]
    steps.append(steps[1] - 0.05 * rng.standard_normal(z0.size))
    steps.append(steps[2])  # a step that did not move
    check = descent_check(problem, np.stack(steps))
    J = jax.jit(Objective(problem, ConvergedCG(rtol=1e-12)))  # compiled once, not op by op
    for k in range(2):
        d = steps[k + 1] - steps[k]
        h = 1e-6
        fd = (float(J(jnp.asarray(steps[k] + h * d))) - float(J(jnp.asarray(steps[k] - h * d)))
              ) / (2 * h)
        assert check.slopes[k] == pytest.approx(fd, rel=1e-5)
    assert list(check.moved) == [True, True, False] and math.isnan(check.cosines[2])
    assert check.descending == int(np.sum(check.slopes[:2] < 0))


def test_a_converged_run_descends_at_every_step_and_the_recorder_keeps_the_start(problem):
    recorder = IterateRecorder()
    result = invert(problem, refinement=converged(1e-10), steps=8, callback=recorder)
    iterates = recorder.iterates(problem)
    assert iterates.shape == (9, problem.n_parameters)
    np.testing.assert_array_equal(iterates[-1], np.asarray(result.params))
    check = descent_check(problem, iterates)
    assert check.fraction == 1.0 and check.median_cosine > 0.1
    with pytest.raises(ValueError, match="iterates"):
        descent_check(problem, iterates[:1])
