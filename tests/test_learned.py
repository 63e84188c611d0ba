"""Learned inverse: data against reference solves, batched losses against a loop, Taylor tests
of the training gradient, and training that lowers the validation misfit."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.sparse.linalg as spla
from skfem.models.poisson import laplace

import prdp_fem as pf
from prdp_fem import learned
from prdp_fem.errors import SolverConfigError
from prdp_fem.learned import EpochRecord
from prdp_fem.prdp import converged, fixed, prdp


@pytest.fixture(scope="module")
def small():
    disc = pf.discretize(pf.unit_square(8), element="P1", kappa_space="P0", dirichlet=0.0)
    problem = learned.learned_inverse(disc, pf.full_field(disc, data=np.zeros(disc.n_dofs)),
                                      kappa=2.0, supervised=1e-2)
    sources = learned.random_sources(disc, 40, seed=0, width=0.2)
    samples = learned.source_samples(problem, sources, noise=0.01, seed=1)
    network = learned.mlp_init(
        jax.random.PRNGKey(0), [disc.n_dofs, 32, disc.n_dofs],
        input_scale=float(np.std(np.asarray(samples.observations))),
        output_scale=float(np.std(sources)))
    return disc, problem, samples, network


def test_random_sources_are_seeded_and_smooth(small):
    disc = small[0]
    a, b = (learned.random_sources(disc, 5, seed=3) for _ in range(2))
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - learned.random_sources(disc, 5, seed=4)).max() > 1.0
    # smooth: the Rayleigh quotient |f|_H1^2 / |f|_L2^2 stays near 1 / width^2, far below a
    # nodal white noise's (~ 1 / h^2)
    stiffness = laplace.assemble(disc.basis)
    quotient = [f @ (stiffness @ f) / (f @ (disc.mass_matrix @ f)) for f in (*a, noise(disc))]
    assert max(quotient[:-1]) < 40 < 400 < quotient[-1]


def noise(disc):
    return np.random.default_rng(0).standard_normal(disc.n_dofs)


def test_observations_are_converged_solves_plus_seeded_noise(small):
    _, problem, samples, _ = small
    clean = learned.source_samples(problem, samples.sources[:3], noise=0.0)
    system = problem.system
    A = system.operator(problem.kappa).to_scipy()
    for f, d in zip(samples.sources[:3], clean.observations, strict=True):
        u = spla.spsolve(A.tocsc(), np.asarray(system.rhs(problem.kappa, f)))
        np.testing.assert_allclose(d, np.asarray(system.expand(jnp.asarray(u))), rtol=1e-9,
                                   atol=1e-12)
    noise = np.asarray(samples.observations[:3] - clean.observations)
    rms = np.sqrt(np.mean(np.asarray(clean.observations) ** 2, axis=1))
    assert 0.005 < float(np.std(noise / rms[:, None])) < 0.02  # 1 % of each sample's RMS


def test_batched_loss_equals_the_per_sample_loop(small):
    _, problem, samples, network = small
    solver = pf.TruncatedCG(6)
    batch = samples.take(np.arange(5))
    loss, iterations = learned.batch_loss(network, problem, batch, solver)
    misfit_of = jax.jit(lambda f, d: problem.misfit(f, d, solver)[0])
    per_sample = []
    for f_true, d in zip(batch.sources, batch.observations, strict=True):
        f = learned.mlp_apply(network, d)
        misfit = misfit_of(f, d)
        e = f - f_true
        per_sample.append(misfit + 1e-2 * 0.5 * float(e @ (problem.mass.to_scipy() @ e)))
    np.testing.assert_allclose(float(loss), np.mean(per_sample), rtol=1e-12)
    assert int(iterations) == 5 * 6


@pytest.mark.parametrize("gradient", ["implicit", "unrolled"])
def test_training_gradient_passes_a_taylor_test(small, gradient):
    """The gradient of the batched loss through K = 6 truncated solves, in the weights."""
    _, problem, samples, network = small
    batch = samples.take(np.arange(4))
    solver = pf.TruncatedCG(6, gradient=gradient)

    def loss(layers):
        return learned.batch_loss(network._replace(layers=layers), problem, batch, solver)[0]

    result = pf.taylor_test(jax.jit(loss), network.layers,
                            gradient=jax.jit(jax.grad(loss))(network.layers), h0=1e-2)
    assert result.passed(), result.rates


def test_training_lowers_the_validation_misfit_and_prdp_refines(small):
    _, problem, samples, network = small
    train_set, validation_set = samples.take(np.arange(32)), samples.take(np.arange(32, 40))
    training = learned.train(problem, network, train_set, validation_set,
                             optimizer=optax.adam(3e-3), refinement=prdp(K0=2, dK=2),
                             epochs=25, batch_size=8)
    first, last = training.records[0], training.records[-1]
    assert last.validation_misfit < 0.5 * first.validation_misfit
    assert last.validation_error < 0.9 * first.validation_error
    assert int(training.refinement.refinements) >= 1
    assert int(training.refinement.iterations) > 2
    # the tally is exact: K per solve, one solve per sample and step
    epochs_at = {}
    for record in training.records:
        epochs_at[record.iterations] = epochs_at.get(record.iterations, 0) + 1
    assert last.primal_iterations == sum(K * n * 32 for K, n in epochs_at.items())
    times = [record.time for record in training.records]
    assert times == sorted(times)


def test_converged_and_fixed_training_agree_when_K_is_enough(small):
    """K = 60 > the ~25 iterations CG needs here: fixed-K training is converged training."""
    _, problem, samples, network = small
    kwargs = dict(optimizer=optax.sgd(1e-3), epochs=1, batch_size=8)
    a = learned.train(problem, network, samples.take(np.arange(16)), samples.take(
        np.arange(16, 24)), refinement=fixed(60), **kwargs)
    b = learned.train(problem, network, samples.take(np.arange(16)), samples.take(
        np.arange(16, 24)), refinement=converged(1e-12), **kwargs)
    np.testing.assert_allclose(a.records[-1].validation_misfit, b.records[-1].validation_misfit,
                               rtol=1e-8)


def test_training_saving_reads_the_first_epoch_at_the_converged_level():
    def records(misfits, dt, its):
        return [EpochRecord(i + 1, 5, 5, 0.0, its * (i + 1), dt * (i + 1), m, m, m)
                for i, m in enumerate(misfits)]

    base = records([4.0, 2.0, 1.0, 1.0], 1.0, 100)
    run = records([3.0, 1.005, 0.9], 0.5, 10)
    saving = learned.training_saving(run, base)
    assert saving["epoch"] == 2 and saving["time_saving"] == pytest.approx(1 - 1.0 / 4.0)
    assert saving["iteration_saving"] == pytest.approx(1 - 20 / 400)
    assert learned.training_saving(records([3.0], 1, 1), base)["epoch"] is None


def test_bad_options_are_refused_with_their_names(small):
    disc, problem, samples, network = small
    with pytest.raises(SolverConfigError, match="n_samples"):
        learned.random_sources(disc, 0)
    with pytest.raises(SolverConfigError, match="batch_size=99"):
        learned.train(problem, network, samples, samples, batch_size=99)
    with pytest.raises(SolverConfigError, match="gradient='forward'"):
        learned.train(problem, network, samples, samples, gradient="forward")
    with pytest.raises(SolverConfigError, match="supervised"):
        learned.learned_inverse(disc, pf.full_field(disc, data=np.zeros(disc.n_dofs)),
                                supervised=-1.0)
    with pytest.raises(pf.ShapeError, match="sources"):
        learned.source_samples(problem, np.zeros((2, 3)))
