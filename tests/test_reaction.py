"""The nonlinear stepper: Fisher-KPP reaction-diffusion, the reaction explicit (IMEX).

A constant field without Dirichlet data follows the logistic map exactly (the diffusion of a
constant is zero), which converges at first order to the logistic ODE's solution; the
reference trajectories converge at first order in the substep; WIG's gradient through the
nonlinear steps passes a Taylor test; the heat scene's linear steps are unchanged."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import prdp_fem as pf
from prdp_fem.errors import SolverConfigError
from prdp_fem.inverse import prdp
from prdp_fem.learning import heat, learned

RATE = 5.0


def logistic(u0, r, t):
    return u0 * np.exp(r * t) / (1 - u0 + u0 * np.exp(r * t))


def test_a_constant_field_follows_the_logistic_map_and_converges_at_first_order():
    disc = pf.discretize(pf.unit_square(4), dirichlet=None)  # the constants are in
    errors = []
    for steps in (20, 40, 80):
        dt = 1.0 / steps
        problem = heat.heat_problem(disc, dt, reaction=RATE)
        u, mapped = jnp.full(problem.n_free, 0.1), 0.1
        for _ in range(steps):
            u = heat.heat_step(problem, u, pf.ConvergedCG(rtol=1e-13))[0]
            mapped = mapped + dt * RATE * mapped * (1 - mapped)
        np.testing.assert_allclose(np.asarray(u), mapped, rtol=1e-11)
        errors.append(abs(mapped - logistic(0.1, RATE, 1.0)))
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all((rates > 0.9) & (rates < 1.1)), rates


def test_reference_trajectories_converge_at_first_order_in_the_substep():
    disc = pf.discretize(pf.unit_square(8), dirichlet=0.0)
    initial = heat.random_initial_states(disc, 2, seed=3, width=0.15)

    def final(substeps):
        return np.asarray(heat.reference_trajectories(
            disc, initial, dt=0.1, steps=5, substeps=substeps, kappa=0.05,
            reaction=RATE).states[:, -1])

    finest = final(256)
    errors = [np.linalg.norm(final(s) - finest) for s in (4, 8, 16)]
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all((rates > 0.85) & (rates < 1.15)), rates
    # the reaction acts: the fronts spread and saturate near 1 (measured: mean 0.62, where
    # the heat equation's states have decayed to 0.31)
    linear = heat.reference_trajectories(disc, initial, dt=0.1, steps=5, kappa=0.05)
    assert finest.mean() > 1.8 * np.asarray(linear.states[:, -1]).mean()
    assert 0.9 < finest.max() < 1.0


@pytest.fixture(scope="module")
def fisher():
    disc = pf.discretize(pf.unit_square(6), dirichlet=0.0)
    problem = heat.heat_problem(disc, 0.05, kappa=0.05, reaction=RATE)
    data = heat.reference_trajectories(disc, heat.random_initial_states(disc, 12, seed=0),
                                       dt=0.05, steps=6, kappa=0.05, reaction=RATE)
    return disc, problem, data.take(np.arange(8)), data.take(np.arange(8, 12))


def test_wig_gradient_through_the_nonlinear_steps_passes_a_taylor_test(fisher):
    _, problem, trajectories, _ = fisher
    network = learned.mlp_init(jax.random.PRNGKey(0), [problem.n_free, 16, problem.n_free],
                               output_scale=0.05)
    batch = heat.windows(trajectories, 2)[:4]  # two steps: the second starts from a learned state
    solver = pf.TruncatedCG(4, gradient="unrolled")

    def loss(layers):
        return heat.batch_loss(network._replace(layers=layers), problem, batch, solver,
                               setup="correction", mode="wig")[0]

    # the loss and its gradient in one program, which the Taylor test evaluates too (a
    # separately jitted loss would compile the solves once more)
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    result = pf.taylor_test(lambda layers: value_and_grad(layers)[0], network.layers,
                            gradient=value_and_grad(network.layers)[1], h0=1e-2)
    assert result.passed(), result.rates


def test_the_nonlinear_correction_is_not_homogeneous(fisher):
    """A nonlinear step is not linear in ``u``: the network sees ``u`` itself, and the
    stepper of a reaction problem scales no input."""
    _, problem, trajectories, _ = fisher
    network = learned.mlp_init(jax.random.PRNGKey(1), [problem.n_free, 8, problem.n_free])
    u = trajectories.states[0, 1]
    for scale in (0.5, 2.0):
        scaled = heat.correction(network, scale * u, homogeneous=False)
        np.testing.assert_allclose(scaled, network(scale * u), rtol=0, atol=0)
    step, _ = heat.stepper("prediction", network, problem, u, None)
    np.testing.assert_allclose(step, u + network(u), rtol=1e-15)


def test_training_the_fisher_corrector_lowers_the_validation_rollout_error(fisher):
    _, problem, trajectories, validation = fisher
    network = heat.initial_network(problem, trajectories, "correction", (32,))
    start = heat.rollout_error(network, problem, validation, pf.ConvergedCG(rtol=1e-10))[0]
    coarse = heat.rollout_error(None, problem, validation, pf.ConvergedCG(rtol=1e-10))[0]
    training = heat.train(problem, network, trajectories, validation, mode="wig", unroll=3,
                          optimizer=optax.adam(3e-3), refinement=prdp(K0=2, dK=2),
                          epochs=50, batch_size=16)
    # measured: 0.73 of the coarse solver's error after 50 epochs (8 training trajectories;
    # 0.71 after 80: the programs' compile, not the epochs, is most of the time)
    assert training.records[-1].validation_error < 0.8 * float(coarse)
    assert float(start) == pytest.approx(float(coarse), rel=0.5)  # small untrained output


def test_bad_reaction_rates_are_refused():
    disc = pf.discretize(pf.unit_square(3), dirichlet=0.0)
    for bad in (-1.0, float("nan"), True):
        with pytest.raises(SolverConfigError, match="reaction="):
            heat.heat_problem(disc, 0.1, reaction=bad)
    with pytest.raises(SolverConfigError, match="non-finite states"):
        heat.reference_trajectories(disc, np.full((1, disc.n_dofs), 0.5), dt=1.0, steps=8,
                                    substeps=1, reaction=1e3)
