"""Any JAX model trains through the solver: a plain function of parameters, an Equinox module
and a Flax module, in the learned inverse and the heat hybrid."""

import equinox as eqx
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import prdp_fem as pf
from prdp_fem.errors import ShapeError, SolverConfigError
from prdp_fem.inverse import fixed, taylor_test
from prdp_fem.learning import (
    Model,
    equinox_model,
    flax_model,
    heat,
    learned,
    mlp_apply,
)


@pytest.fixture(scope="module")
def small():
    disc = pf.discretize(pf.unit_square(4), element="P1", kappa_space="P0", dirichlet=0.0)
    problem = learned.learned_inverse(disc, pf.full_field(disc, data=np.zeros(disc.n_dofs)),
                                      kappa=2.0, supervised=1e-2)
    sources = learned.random_sources(disc, 24, seed=0, width=0.2)
    samples = learned.source_samples(problem, sources, noise=0.01, seed=1)
    network = learned.mlp_init(
        jax.random.PRNGKey(0), [disc.n_dofs, 16, disc.n_dofs],
        input_scale=float(np.std(np.asarray(samples.observations))),
        output_scale=float(np.std(sources)))
    return disc, problem, samples.take(np.arange(16)), samples.take(np.arange(16, 24)), network


def _train(small, model, epochs=4):
    _, problem, train_set, validation_set, _ = small
    return learned.train(problem, model, train_set, validation_set, epochs=epochs,
                         batch_size=8, optimizer=optax.adam(3e-3), refinement=fixed(8))


def _mlp(scales):
    input_scale, output_scale = scales

    def apply(layers, d):
        return mlp_apply(learned.Network(layers, input_scale, output_scale), d)

    return apply


def test_a_plain_jax_model_trains_as_the_built_in_mlp(small):
    """The built-in MLP written as Model(apply, params): the same records, the same weights
    (to round-off: the scales are constants of its program, arguments of the MLP's)."""
    network = small[4]
    model = Model(_mlp((network.input_scale, network.output_scale)), network.layers)
    built_in, plain = _train(small, network), _train(small, model)
    for name in ("train_loss", "validation_misfit", "primal_iterations"):
        np.testing.assert_allclose([getattr(r, name) for r in plain.records],
                                   [getattr(r, name) for r in built_in.records], rtol=1e-12)
    assert isinstance(plain.network, Model)
    for (w, b), (w_ref, b_ref) in zip(plain.network.params, built_in.network.layers,
                                      strict=True):
        np.testing.assert_allclose(w, w_ref, rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(b, b_ref, rtol=1e-10, atol=1e-13)


def _equinox(n):
    return equinox_model(eqx.nn.MLP(n, n, 16, 1, activation=jnp.tanh,
                                    key=jax.random.PRNGKey(2)))


class _Dense(nn.Module):
    width: int
    out: int

    @nn.compact
    def __call__(self, x):
        return nn.Dense(self.out)(jnp.tanh(nn.Dense(self.width)(x)))


def _flax(n):
    module = _Dense(16, n)
    return flax_model(module, module.init(jax.random.PRNGKey(3), jnp.zeros(n)))


def _scaled(model: Model, network) -> Model:
    """``model`` between the data's scales, as the built-in MLP has them."""
    inner, input_scale, output_scale = model.apply, network.input_scale, network.output_scale

    def apply(params, d):
        return output_scale * inner(params, d / input_scale)

    return Model(apply, model.params)


# flax with the slow cases (6 s): the same trainer path as Equinox's, through its adapter
@pytest.mark.parametrize("make", [_equinox, pytest.param(_flax, marks=pytest.mark.slow)],
                         ids=["equinox", "flax"])
def test_equinox_and_flax_models_train_through_the_solver(small, make):
    """Each lowers the validation misfit, and the trained model predicts with its new
    parameters."""
    disc, _, train_set, _, network = small
    model = _scaled(make(disc.n_dofs), network)
    training = _train(small, model, epochs=6)
    misfits = [r.validation_misfit for r in training.records]
    assert misfits[-1] < 0.7 * misfits[0]
    d = train_set.observations[0]
    trained = training.network
    assert float(jnp.max(jnp.abs(trained(d) - model(d)))) > 0  # new parameters
    np.testing.assert_allclose(trained(d), trained.predict(trained.params, d), rtol=1e-15)


@pytest.mark.slow  # the objective's gradient program (5 s)
def test_an_equinox_model_s_gradient_through_truncated_solves_passes_the_taylor_test(small):
    disc, problem, train_set, _, network = small
    model = _scaled(_equinox(disc.n_dofs), network)
    objective = learned.BatchObjective(problem.with_residual(), model, train_set.take(
        np.arange(2)), pf.TruncatedCG(6), None)
    result = taylor_test(objective, model.params, h0=1e-2, n_steps=4)
    assert result.passed(), result.rates


@pytest.mark.slow  # the heat hybrid's programs (6 s)
def test_a_model_trains_the_heat_hybrid_as_the_built_in_mlp():
    """heat.train trains the model's params: the MLP's layers, its scales fixed."""
    disc = pf.discretize(pf.unit_square(4), element="P1", kappa_space="P0", dirichlet=0.0)
    problem = heat.heat_problem(disc, dt=0.01)
    states = heat.reference_trajectories(disc, heat.random_initial_states(disc, 6, seed=0),
                                         dt=0.01, steps=4).states
    train_set, validation_set = heat.Trajectories(states[:4]), heat.Trajectories(states[4:])
    network = heat.initial_network(problem, train_set, "correction", hidden=(8,), seed=0)
    model = Model(_mlp((network.input_scale, network.output_scale)), network.layers)

    def run(net):
        return heat.train(problem, net, train_set, validation_set, setup="correction",
                          mode="nog", unroll=2, epochs=3, batch_size=4,
                          refinement=fixed(3)).records

    errors = [r.validation_error for r in run(network)]
    np.testing.assert_allclose([r.validation_error for r in run(model)], errors, rtol=1e-12)
    assert errors[-1] < errors[0]  # it trained


def test_a_model_that_does_not_fit_is_refused(small):
    disc, problem, train_set, validation_set, _ = small
    n = disc.n_dofs
    wrong_size = Model(lambda p, d: p @ d, jnp.ones((n - 1, n)))
    with pytest.raises(ShapeError, match=rf"an input of {n} values gives \({n - 1},\)"):
        learned.train(problem, wrong_size, train_set, validation_set, epochs=1)
    broken = Model(lambda p, d: p @ d[:3], jnp.ones((n, n)))
    with pytest.raises(ShapeError, match="applying it to an input of"):
        learned.train(problem, broken, train_set, validation_set, epochs=1)
    with pytest.raises(SolverConfigError, match="without params, predict, replace_params"):
        learned.train(problem, lambda d: d, train_set, validation_set, epochs=1)
