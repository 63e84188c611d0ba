"""Warm starts: solves that start from the previous evaluation's solutions.

The adjoint solution leaves an evaluation as the gradient with respect to a reverse tally's
``adjoint_start`` (checked against a direct solve); ``invert(warm_start=True)`` carries the
state and adjoint solutions from step to step, so a truncated solve reaches the converged
run's answer where the same ``K`` from zero stalls, and a converged run needs fewer
iterations for the same steps.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.sparse as sp

import prdp_fem as pf
from prdp_fem.errors import SolverConfigError
from prdp_fem.fem import full_field, with_noise
from prdp_fem.inverse import Objective, WarmStart, converged, fixed, inverse_problem, invert
from prdp_fem.linalg import (
    ConvergedCG,
    ReverseTally,
    SparseMatrix,
    TruncatedCG,
    read_counts,
    solve,
    zero_counts,
)
from prdp_fem.scene import SceneError, parse_scene

N = 40
_A = sp.diags([-1.0, 2.2, -1.0], [-1, 0, 1], shape=(N, N)).tocsr()
_B = np.random.default_rng(0).standard_normal(N)
_W = np.random.default_rng(1).standard_normal(N)


def _value_and_grads(solver, start):
    """``d/ds w.x(s b)`` at ``s = 1``, the counts and the adjoint solution (the gradient with
    respect to the start)."""
    _, (grad, counts, adjoint) = _program(solver)(1.0, zero_counts(), start)
    return float(grad), read_counts(counts), np.asarray(adjoint)


@functools.cache
def _program(solver):
    """The value and gradients above, one program per solver (the start an argument: a
    cold and a warm start run one compiled program)."""
    matrix = SparseMatrix.from_scipy(_A)

    def J(scale, seed, adjoint_start):
        sol = solve(matrix, jnp.asarray(_B) * scale, solver,
                    counter=ReverseTally(seed, adjoint_start))
        return jnp.vdot(jnp.asarray(_W), sol.x)

    return jax.jit(jax.value_and_grad(J, argnums=(0, 1, 2)))


def test_the_adjoint_solution_leaves_as_the_starts_gradient():
    exact = np.linalg.solve(_A.toarray(), _W)  # A symmetric: the adjoint system is A
    grad, counts, adjoint = _value_and_grads(ConvergedCG(rtol=1e-12), jnp.zeros(N))
    np.testing.assert_allclose(adjoint, exact, rtol=1e-9)
    np.testing.assert_allclose(grad, _W @ np.linalg.solve(_A.toarray(), _B), rtol=1e-9)
    # from a start near the solution the converged adjoint solve needs fewer iterations,
    # and gives the same gradient
    warm_grad, warm_counts, warm_adjoint = _value_and_grads(ConvergedCG(rtol=1e-12),
                                                            jnp.asarray(exact + 1e-10))
    assert warm_counts["adjoint"] < counts["adjoint"] // 2
    assert warm_counts["primal"] == counts["primal"]
    np.testing.assert_allclose(warm_grad, grad, rtol=1e-9)
    np.testing.assert_allclose(warm_adjoint, exact, rtol=1e-9)


def test_a_truncated_adjoint_from_a_close_start_gives_the_converged_gradient():
    exact_grad = _W @ np.linalg.solve(_A.toarray(), _B)
    solver = TruncatedCG(8, gradient="implicit")
    cold, _, _ = _value_and_grads(solver, jnp.zeros(N))
    start = np.linalg.solve(_A.toarray(), _W) + 1e-7
    warm, counts, _ = _value_and_grads(solver, jnp.asarray(start))
    assert counts == {"primal": 8, "adjoint": 8, "primal_solves": 1, "adjoint_solves": 1}
    # the primal's 8 iterations from zero still truncate the value's dependence on b, but the
    # gradient is the adjoint's: exact to the start's error
    assert abs(cold - exact_grad) > 1e-2 * abs(exact_grad)
    assert abs(warm - exact_grad) < 1e-5 * abs(exact_grad)


def test_solvers_without_an_adjoint_solve_give_a_cold_start():
    _, _, adjoint = _value_and_grads(TruncatedCG(8, gradient="unrolled"), jnp.ones(N))
    assert not adjoint.any()


# --- the inversion ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def coefficient_problem():
    disc = pf.discretize(pf.unit_square(16), element="P1", kappa_space="P1", dirichlet=0.0)
    m_true = disc.interpolate_kappa(lambda x: np.log(2 + np.sin(2 * np.pi * x[0]) * x[1]))
    f = np.ones(disc.n_dofs)
    kappa = np.exp(m_true)
    u = disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f)).x)
    observation = with_noise(full_field(disc, u_true=u), 0.01, seed=3)
    return inverse_problem(disc, observation, unknown="log_kappa", alpha=1e-5,
                           regularization="h1", known=f, truth=m_true)


def test_the_evaluation_returns_the_state_and_adjoint_solutions(coefficient_problem):
    problem = coefficient_problem
    n = problem.system.n_free
    z = jnp.full(problem.n_parameters, 0.2)
    solver = ConvergedCG(rtol=1e-12)
    evaluate_from = jax.jit(
        lambda params, start: Objective(problem, solver, warm_start=start).evaluate(params))
    evaluation = evaluate_from(z, WarmStart.cold(n))
    plain = Objective(problem, solver).evaluate(z)
    assert plain.warm_start is None
    np.testing.assert_allclose(evaluation.value, plain.value, rtol=1e-12)
    np.testing.assert_allclose(evaluation.grad, plain.grad, rtol=1e-8, atol=1e-14)
    # the state: A(kappa) u = b; the adjoint of J = misfit(u) + alpha R: A lambda = dJ/du
    # up to its sign, on the free dofs
    # the system at z and the misfit's gradient jitted: one program each, not op by op
    @jax.jit
    def system_at(z):
        kappa, f = problem.parameterization.coefficients(z, problem.known)
        return problem.system.operator(kappa), problem.system.rhs(kappa, f)

    operator, rhs = system_at(z)
    A = operator.to_scipy().tocsc()
    state = sp.linalg.spsolve(A, np.asarray(rhs))
    np.testing.assert_allclose(evaluation.warm_start.state, state, rtol=1e-9)
    misfit_gradient = jax.jit(jax.grad(
        lambda x: problem.observation.misfit(problem.system.expand(x))))
    adjoint = sp.linalg.spsolve(A, np.asarray(misfit_gradient(jnp.asarray(state))))
    returned = np.asarray(evaluation.warm_start.adjoint)
    np.testing.assert_allclose(np.abs(returned), np.abs(adjoint), rtol=1e-7,
                               atol=1e-12 * np.abs(returned).max())
    # started where it ended, a converged evaluation runs fewer iterations
    again = evaluate_from(z, evaluation.warm_start)
    assert read_counts(again.counts)["primal"] < read_counts(evaluation.counts)["primal"] // 2
    assert read_counts(again.counts)["adjoint"] < read_counts(evaluation.counts)["adjoint"] // 2


def test_a_warm_truncated_run_reaches_the_converged_error_where_a_cold_one_stalls(
        coefficient_problem):
    problem = coefficient_problem
    steps = 40
    # K = 400 from zero is a converged solve here (225 unknowns), in the same program as K = 5
    reference = invert(problem, refinement=fixed(400), steps=steps)
    cold = invert(problem, refinement=fixed(5), steps=steps)
    warm = invert(problem, refinement=fixed(5), steps=steps, warm_start=True)
    target = reference.history[-1].parameter_error
    assert abs(warm.history[-1].parameter_error / target - 1) < 0.01
    assert cold.history[-1].parameter_error > 1.05 * target
    # five iterations a solve: a fifth of the converged run's work or less, every step
    # refreshed included (the objective moves with its start)
    assert warm.history[-1].total_iterations < 0.25 * reference.history[-1].total_iterations


@pytest.mark.slow
def test_a_warm_converged_run_takes_the_same_steps_with_fewer_iterations(coefficient_problem):
    problem = coefficient_problem
    cold = invert(problem, refinement=converged(1e-10), steps=30)
    warm = invert(problem, refinement=converged(1e-10), steps=30, warm_start=True)
    np.testing.assert_allclose(warm.params, cold.params, rtol=1e-6, atol=1e-8)
    assert warm.history[-1].total_iterations < 0.95 * cold.history[-1].total_iterations


def test_a_transformation_without_a_search_carries_the_start(coefficient_problem):
    # a step of length zero: every step evaluates at the same point, each from where the
    # last one's solves ended, so the truncated loss approaches the converged one
    problem = coefficient_problem
    still = optax.sgd(0.0)
    losses = {name: [r.loss for r in invert(problem, optimizer=still, refinement=refinement,
                                            steps=8, warm_start=warm).history]
              for name, refinement, warm in (("converged", fixed(400), False),
                                             ("cold", fixed(5), False),
                                             ("warm", fixed(5), True))}
    exact = losses["converged"][-1]
    assert np.allclose(losses["cold"], losses["cold"][0])  # the same truncated solve each time
    # moved every third step: three steps from one start, then the next start
    every_third = [r.loss for r in invert(problem, optimizer=still, refinement=fixed(5),
                                          steps=6, warm_start=True,
                                          warm_start_every=3).history]
    assert every_third[0] == every_third[1] == every_third[2] == losses["cold"][0]
    assert every_third[3] == every_third[4] == every_third[5] == losses["warm"][1]
    assert abs(losses["warm"][0] - losses["cold"][0]) < 1e-12 * abs(exact)
    # eight restarts of five Jacobi-PCG iterations: the gap to the converged loss 15x smaller
    assert abs(losses["warm"][-1] - exact) < 0.1 * abs(losses["cold"][-1] - exact)


def test_warm_start_is_refused_where_a_search_keeps_the_solutions_to_itself(
        coefficient_problem):
    with pytest.raises(SolverConfigError, match="warm_start=True"):
        invert(coefficient_problem, optimizer=optax.lbfgs(), steps=1, warm_start=True)
    with pytest.raises(SolverConfigError, match="warm_start="):
        invert(coefficient_problem, steps=1, warm_start="yes")
    with pytest.raises(SolverConfigError, match="warm_start_every"):
        invert(coefficient_problem, steps=1, warm_start=True, warm_start_every=0)


def test_the_scene_keys_reach_the_inversion():
    scene = parse_scene({"mesh": {"n": 4},
                         "inverse": {"unknown": "source", "truth": "x*y"},
                         "solver": {"warm_start": True, "warm_start_every": 2}}, source="s")
    assert (scene.solver.warm_start, scene.solver.warm_start_every) == (True, 2)
    with pytest.raises(SceneError, match=r"solver\.warm_start_every"):
        parse_scene({"mesh": {"n": 4},
                     "inverse": {"unknown": "source", "truth": "x*y"},
                     "solver": {"warm_start_every": 2}}, source="s")
    with pytest.raises(SceneError, match=r"solver\.warm_start"):
        parse_scene({"mesh": {"n": 4},
                     "inverse": {"unknown": "source", "truth": "x*y"},
                     "solver": {"warm_start": "yes"}}, source="s")
