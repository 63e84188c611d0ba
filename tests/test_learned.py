"""Learned inverse: data against reference solves, batched losses against a loop, Taylor tests
of the training gradient, and training that lowers the validation misfit."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.sparse.linalg as spla
from conftest import learning_rate_spy, shared_compiles_made
from skfem.models.poisson import laplace

import prdp_fem as pf
from prdp_fem.errors import SolverConfigError
from prdp_fem.inverse import converged, fixed, prdp
from prdp_fem.learning import EpochRecord, learned


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
    # both sides jitted (op by op the batched loss compiled some 140 small programs)
    loss, iterations = jax.jit(lambda network, batch: learned.batch_loss(
        network, problem, batch, solver))(network, batch)
    misfit_of = jax.jit(lambda f, d: problem.misfit(f, d, solver)[0])
    apply = jax.jit(learned.mlp_apply)
    per_sample = []
    for f_true, d in zip(batch.sources, batch.observations, strict=True):
        f = apply(network, d)
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

    # the loss and its gradient in one program, which the Taylor test evaluates too (a
    # separately jitted loss would compile the solves once more)
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    result = pf.taylor_test(lambda layers: value_and_grad(layers)[0], network.layers,
                            gradient=value_and_grad(network.layers)[1], h0=1e-2)
    assert result.passed(), result.rates


@pytest.mark.slow  # compile sharing (start-up time)
def test_trainings_with_equal_settings_share_one_kept_step(small, monkeypatch):
    """Equal settings (the same optimizer object): one step, traced once, and the same
    records; another optimizer object is another step."""
    learned._step_program.cache_clear()
    made = shared_compiles_made(monkeypatch)
    _, problem, samples, network = small
    train_set, validation_set = samples.take(np.arange(16)), samples.take(np.arange(16, 20))
    adam = optax.adam(3e-3)

    def train(optimizer):
        return learned.train(problem, network, train_set, validation_set, optimizer=optimizer,
                             refinement=prdp(K0=2, dK=2), epochs=2, batch_size=8)

    first, again = train(adam), train(adam)
    assert len([c for c in made if c._static_argnum == 6]) == 1
    assert [r._replace(time=0.0) for r in again.records] == \
        [r._replace(time=0.0) for r in first.records]
    train(optax.adam(3e-3))
    assert len([c for c in made if c._static_argnum == 6]) == 2


@pytest.mark.slow  # compile sharing (start-up time)
def test_trainings_with_amg_cycles_of_equal_shapes_share_one_step(small, monkeypatch):
    """The JAX AMG cycle is an argument of the step: the hierarchy of 2 A (M / 2, the same
    PCG iterates) runs the step compiled for A's."""
    learned._step_program.cache_clear()
    made = shared_compiles_made(monkeypatch)
    _, problem, samples, network = small
    train_set, validation_set = samples.take(np.arange(16)), samples.take(np.arange(16, 20))
    operator = problem.system.operator(problem.kappa)
    adam = optax.adam(3e-3)
    runs = [learned.train(problem, network, train_set, validation_set, optimizer=adam,
                          refinement=prdp(K0=2, dK=2), epochs=2, batch_size=8,
                          preconditioner=pf.amg_preconditioner(matrix))
            for matrix in (operator, operator.with_values(2.0 * operator.values))]
    [step] = [c for c in made if c._static_argnum == 6]
    assert len(step._cache) == 1
    np.testing.assert_allclose([r.train_loss for r in runs[1].records],
                               [r.train_loss for r in runs[0].records], rtol=1e-10)


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
    # and every validation solve that ran: the last epoch's are the trained network's
    before = training.records[-2].validation_iterations
    _, _, final = jax.jit(learned.validation)(training.network, problem, validation_set)
    assert 0 < before and last.validation_iterations - before == int(final)


@pytest.mark.slow  # two runs agree; training through the solver stays in the default suite
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


def test_training_saving_reads_the_first_epoch_that_stays_at_the_converged_level():
    def records(misfits, dt, its):
        return [EpochRecord(i + 1, 5, 5, 0.0, its * (i + 1), dt * (i + 1), m, m, m)
                for i, m in enumerate(misfits)]

    base = records([4.0, 2.0, 1.0, 1.0], 1.0, 100)
    run = records([3.0, 1.005, 0.995], 0.5, 10)
    saving = learned.training_saving(run, base)
    # same target, both sides: the converged run settles at epoch 3 (3 s, 300 iterations)
    assert saving["epoch"] == 2 and saving["time_saving"] == pytest.approx(1 - 1.0 / 3.0)
    assert saving["iteration_saving"] == pytest.approx(1 - 20 / 300)
    assert learned.training_saving(records([3.0], 1, 1), base)["epoch"] is None
    # passing through the band does not count: it must stay there
    assert learned.training_saving(records([1.0, 3.0, 0.999], 0.5, 10), base)["epoch"] == 3
    assert learned.training_saving(records([1.0, 3.0], 0.5, 10), base)["epoch"] is None
    # ending lower is not a saving, unless the at-or-below reading is asked for by name
    lower = records([3.0, 1.005, 0.9], 0.5, 10)
    assert learned.training_saving(lower, base)["epoch"] is None
    assert learned.training_saving(lower, base, at_or_below=True)["epoch"] == 2


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


# --------------------------------------------------------------------------------------
# every optimiser: HIG, Gauss-Newton, Newton-CG, L-BFGS on the network's weights
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny():
    """6 x 6 mesh, 12 training and 6 validation samples, an MLP [49, 6, 49] (649 weights)."""
    disc = pf.discretize(pf.unit_square(6), element="P1", kappa_space="P0", dirichlet=0.0)
    problem = learned.learned_inverse(disc, pf.full_field(disc, data=np.zeros(disc.n_dofs)),
                                      supervised=1e-2).with_residual()
    sources = learned.random_sources(disc, 18, seed=0, width=0.2)
    samples = learned.source_samples(problem, sources, noise=0.01, seed=1)
    network = learned.mlp_init(
        jax.random.PRNGKey(0), [disc.n_dofs, 6, disc.n_dofs],
        input_scale=float(np.std(np.asarray(samples.observations))),
        output_scale=float(np.std(sources)))
    return problem, samples.take(np.arange(12)), samples.take(np.arange(12, 18)), network


def _step(tree_after, tree_before) -> np.ndarray:
    return np.concatenate([np.ravel(a - b) for a, b in zip(
        jax.tree_util.tree_leaves(tree_after), jax.tree_util.tree_leaves(tree_before),
        strict=True)])


@pytest.mark.slow  # about 25 s: explicit Jacobians of every sample (test_hig pins HIG)
def test_hig_network_step_equals_the_svd_of_the_explicitly_stacked_jacobian(tiny):
    problem, samples, validation_set, network = tiny
    train_set = samples.take(np.arange(4))
    eta, exponent = 0.3, -0.5
    training = learned.train(problem, network, train_set, validation_set,
                             optimizer=pf.hig(eta, exponent), refinement=fixed(8),
                             epochs=1, batch_size=4)
    step = _step(training.network.layers, network.layers)
    # by hand: the residual stacked over the batch, its Jacobian by reverse mode through the
    # whole stack (no per-sample structure), a numpy SVD, -eta V S^-1/2 U^T r
    objective = learned.BatchObjective(problem, network, train_set,
                                       pf.TruncatedCG(8, gradient="implicit"))
    r = np.asarray(objective.residual(network.layers))
    jacobian = jax.jacrev(objective.residual)(network.layers)
    matrix = np.concatenate([np.reshape(leaf, (r.size, -1))
                             for leaf in jax.tree_util.tree_leaves(jacobian)], axis=1)
    u, s, vt = np.linalg.svd(matrix, full_matrices=False)
    keep = s >= 1e-6 * s[0]
    expected = -eta * vt[keep].T @ (s[keep] ** exponent * (u[:, keep].T @ r))
    np.testing.assert_allclose(step, expected, rtol=1e-7, atol=1e-10 * np.abs(expected).max())
    # hig_update on the same stacked Jacobian agrees, and 1/2 |r|^2 is the batch loss
    update, info = pf.optim.hig_update(jacobian, r, learning_rate=eta, exponent=exponent)
    np.testing.assert_allclose(_step(update, jax.tree_util.tree_map(jnp.zeros_like, update)),
                               expected, rtol=1e-7, atol=1e-10 * np.abs(expected).max())
    assert int(info.rank) == int(keep.sum())
    assert 0.5 * float(r @ r) == pytest.approx(float(objective(network.layers)), rel=1e-12)
    # the per-sample Jacobian (what hig uses) is the stacked one
    r_mine, J_mine = objective.residual_jacobian(network.layers, "reverse")
    np.testing.assert_allclose(np.asarray(r_mine), r, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(J_mine), matrix, rtol=1e-9,
                               atol=1e-12 * np.abs(matrix).max())


@pytest.mark.slow  # 9 s: two Jacobians through 60-iteration solves, each compiled
def test_forward_and_reverse_jacobians_agree_with_converged_solves(tiny):
    """Truncated, a tangent solve (CG on J's column) and an adjoint solve (CG on a row) are
    different polynomials in A; converged (K = 60 > 25 free dofs) they are both A^-1."""
    problem, train_set, _, network = tiny
    objective = learned.BatchObjective(problem, network, train_set.take(np.arange(2)),
                                       pf.TruncatedCG(60, gradient="implicit"))
    _, forward = objective.residual_jacobian(network.layers, "forward")
    _, reverse = objective.residual_jacobian(network.layers, "reverse")
    scale = float(np.abs(reverse).max())
    assert scale > 0
    np.testing.assert_allclose(np.asarray(forward), np.asarray(reverse), rtol=1e-8,
                               atol=1e-10 * scale)


@pytest.mark.slow  # about 15 s: explicit Jacobians (test_newton pins the GN operator)
def test_gauss_newton_operator_is_the_stacked_jacobian_squared(tiny):
    problem, train_set, _, network = tiny
    objective = learned.BatchObjective(problem, network, train_set.take(np.arange(3)),
                                       pf.TruncatedCG(60, gradient="implicit"))
    _, J = objective.residual_jacobian(network.layers)
    v = jax.tree_util.tree_map(lambda x: jnp.cos(jnp.arange(x.size).reshape(x.shape)),
                               network.layers)
    flat_v = _step(v, jax.tree_util.tree_map(jnp.zeros_like, v))
    product = _step(objective.gauss_newton_operator(network.layers)(v),
                    jax.tree_util.tree_map(jnp.zeros_like, v))
    J = np.asarray(J)
    np.testing.assert_allclose(product, J.T @ (J @ flat_v), rtol=1e-9,
                               atol=1e-12 * np.abs(product).max())


FULL_BATCH_OPTIMIZERS = {
    "gauss_newton": lambda: pf.newton_cg(hessian="gauss_newton", max_cg=20),
    "newton_cg": lambda: pf.newton_cg(hessian="exact", max_cg=20),
    "lbfgs": lambda: optax.lbfgs(),
    "hig": lambda: pf.hig(0.5, relative=True),
}


@pytest.mark.parametrize("name", [  # each compiles a training: HIG's runs by default
    pytest.param("gauss_newton", marks=pytest.mark.slow),  # the learned study trains with it
    pytest.param("newton_cg", marks=pytest.mark.slow),
    pytest.param("lbfgs", marks=pytest.mark.slow), "hig"])
def test_full_batch_optimisers_lower_the_validation_misfit(tiny, name):
    problem, train_set, validation_set, network = tiny
    K = 8
    start = float(jax.jit(learned.validation)(network, problem, validation_set)[0])
    training = learned.train(problem, network, train_set, validation_set,
                             optimizer=FULL_BATCH_OPTIMIZERS[name](), refinement=fixed(K),
                             epochs=5, batch_size=12)
    last = training.records[-1]
    assert last.validation_misfit < 0.5 * start, (start, last.validation_misfit)
    # the scales never train; every primal solve runs K iterations on 12 samples, and the
    # line searches' trials are in the tally (more primal solves than one per step)
    assert float(training.network.input_scale) == float(network.input_scale)
    assert float(training.network.output_scale) == float(network.output_scale)
    assert last.steps == 5 and last.primal_iterations % (K * 12) == 0
    assert last.primal_iterations > 5 * K * 12
    assert last.adjoint_iterations_total > 0


@pytest.mark.slow  # the refresh is checked on inversions (test_inverse) in the default suite
def test_an_l_bfgs_training_refreshes_its_stale_value_in_the_search(tiny, monkeypatch):
    """``pf.lbfgs`` trains through the step that holds the objective once (its search
    refreshes the value at a step's start, see ``prdp_fem.inverse.steps``): the same losses to
    round-off and the same tally as with an evaluation before the update."""
    from prdp_fem.inverse import steps

    problem, train_set, validation_set, network = tiny

    def training():
        learned._step_program.cache_clear()
        return learned.train(problem, network, train_set, validation_set,
                             optimizer=pf.lbfgs(), refinement=fixed(8), epochs=3,
                             batch_size=12).records

    refreshed = training()
    monkeypatch.setattr(steps, "_refreshes", lambda opt_state: False)
    evaluated_first = training()
    learned._step_program.cache_clear()  # no step with the patched test kept for later tests
    for mine, theirs in zip(refreshed, evaluated_first, strict=True):
        assert mine.train_loss == pytest.approx(theirs.train_loss, rel=1e-10)
        assert mine.validation_misfit == pytest.approx(theirs.validation_misfit, rel=1e-10)
        assert mine.primal_iterations == theirs.primal_iterations
        assert mine.adjoint_iterations_total == theirs.adjoint_iterations_total
    assert refreshed[-1].train_loss < 0.8 * refreshed[0].train_loss  # it trains


def test_line_search_trials_are_counted_exactly(tiny):
    """Gauss-Newton: the tally of one step is the gradient's and the linearisation's solves
    plus one primal solve per Armijo trial, as the optimiser's state reports them."""
    problem, train_set, _, network = tiny
    K, B = 8, 12
    counter = pf.IterationCounter()
    objective = learned.BatchObjective(problem, network, train_set,
                                       pf.TruncatedCG(K, gradient="implicit"), counter)
    optimizer = pf.newton_cg(hessian="gauss_newton", max_cg=5)
    state = optimizer.init(network.layers)

    @jax.jit
    def step(layers, state):
        value, grad = jax.value_and_grad(objective)(layers)
        return optimizer.update(grad, state, layers, value=value, grad=grad,
                                value_fn=objective)

    _, state = jax.block_until_ready(step(network.layers, state))
    trials = int(state.line_search_evaluations)
    assert trials >= 1
    # value_and_grad: B solves; the Gauss-Newton linearisation: B; each trial: B
    assert counter.primal == K * B * (2 + trials)
    # adjoint: the gradient's B, then a tangent and an adjoint solve per sample and product
    products = int(state.cg_iterations)
    assert products >= 1
    assert counter.adjoint == K * B * (1 + 2 * products)


def test_bad_optimiser_combinations_are_refused(tiny):
    problem, train_set, validation_set, network = tiny
    with pytest.raises(SolverConfigError, match="full batch"):
        learned.train(problem, network, train_set, validation_set, optimizer=optax.lbfgs(),
                      batch_size=4)
    with pytest.raises(SolverConfigError, match="GradientTransformation"):
        learned.train(problem, network, train_set, validation_set, optimizer="adam",
                      batch_size=12)
    objective = learned.BatchObjective(problem, network, train_set, pf.TruncatedCG(4))
    with pytest.raises(SolverConfigError, match="jacobian='sideways'"):
        objective.residual_jacobian(network.layers, "sideways")
    with pytest.raises(SolverConfigError, match="with_residual"):  # traced: raised before
        # anything runs (run op by op, the network and a solve compile some 130 programs)
        jax.jit(learned.BatchObjective(dataclasses.replace(problem, factors=None), network,
                                       train_set, pf.TruncatedCG(4)).residual)(network.layers)


@pytest.mark.slow  # compile sharing; test_executables keeps the inversion case
def test_trainings_of_one_program_compile_once_and_keep_their_own_tallies(tiny, monkeypatch):
    """The counter and K are step arguments: a second training with another K and another
    controller runs the first one's executable, and counts exactly what a training compiled
    for itself counts."""
    problem, train_set, validation_set, network = tiny

    def run(optimizer, refinement):
        return learned.train(problem, network, train_set, validation_set,
                             optimizer=optimizer, refinement=refinement, epochs=2,
                             batch_size=4)

    learned._step_program.cache_clear()
    made = shared_compiles_made(monkeypatch)
    adam = optax.adam(1e-3)
    run(adam, fixed(3))
    shared = run(adam, prdp(K0=5, dK=5))
    [step] = [c for c in made if c._static_argnum == 6]
    assert len(step._cache) == 1
    learned._step_program.cache_clear()
    alone = run(adam, prdp(K0=5, dK=5))
    tallies = [[(r.primal_iterations, r.adjoint_iterations_total, r.steps) for r in t.records]
               for t in (shared, alone)]
    assert tallies[0] == tallies[1] and tallies[0][-1][0] > 0


def test_a_per_learning_rate_controller_is_fed_each_epoch_s_mean_rate(tiny):
    """12 samples in batches of 4: 3 steps an epoch under a cosine schedule over 6 steps; the
    controller sees each epoch's mean rate over the first step's (closed form
    ``(1 + cos(pi k / 6)) / 2``), and 1 under the default optimiser's constant rate. With an
    optimiser of the caller's and no ``learning_rate`` the training refuses to guess."""
    problem, train_set, validation_set, network = tiny
    spy, fed = learning_rate_spy(prdp(K0=2, dK=2, per_learning_rate=True))
    schedule = optax.cosine_decay_schedule(1e-3, 6)
    learned.train(problem, network, train_set, validation_set, optimizer=optax.adam(schedule),
                  learning_rate=schedule, refinement=spy, epochs=2, batch_size=4)
    learned.train(problem, network, train_set, validation_set, refinement=spy, epochs=1,
                  batch_size=4)
    expected = [np.mean([(1 + np.cos(np.pi * k / 6)) / 2 for k in range(3 * e, 3 * e + 3)])
                for e in range(2)]
    np.testing.assert_allclose(fed, [*expected, 1.0], rtol=1e-6)  # a float32 schedule
    with pytest.raises(SolverConfigError, match="learning_rate="):
        learned.train(problem, network, train_set, validation_set,
                      optimizer=optax.adam(schedule), refinement=spy, epochs=1, batch_size=4)
