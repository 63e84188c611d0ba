"""Heat equation: implicit Euler against SciPy and the discrete eigenmodes, warm starts, the
ONE / NOG / WIG training modes (NOG provably never differentiates the solver, WIG's gradient
passes a Taylor test), the exact iteration tally and bad options."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.linalg
import scipy.sparse.linalg as spla
import skfem
from conftest import shared_compiles_made, small_heat_case

import prdp_fem as pf
from prdp_fem.errors import ShapeError, SolverConfigError
from prdp_fem.inverse import InversionError, prdp
from prdp_fem.learning import heat, learned

DT = 0.02


@pytest.fixture(scope="module")
def small():
    """6x6 P1 (25 free dofs), 12 training and 4 validation trajectories of 6 steps."""
    return small_heat_case(DT)


def network_for(problem, hidden=32, seed=0, output_scale=0.05):
    """An untrained MLP whose scales are float64 arrays, as a trained network holds them (a
    program compiled for one serves the other; Python-float scales compile it anew)."""
    return jax.tree.map(np.asarray, learned.mlp_init(
        jax.random.PRNGKey(seed), [problem.n_free, hidden, problem.n_free],
        output_scale=output_scale))


@partial(jax.jit, static_argnames="setup")
def converged_rollout_error(network, problem, trajectories, setup="correction"):
    """The rollout error and iterations of converged solves (the trainer's validation), one
    program per shape (run op by op, every rollout would compile its scan anew)."""
    return heat.rollout_error(network, problem, trajectories,
                              pf.ConvergedCG(rtol=1e-10, max_iterations=100_000), setup=setup)


# --------------------------------------------------------------------------------------
# the step
# --------------------------------------------------------------------------------------


def test_step_matches_a_scipy_solve_of_the_full_system():
    """Non-zero Dirichlet data, a source, kappa = 2: the condensed step against skfem's
    condense + spsolve of (M + dt A) u' = M u + dt M f on all dofs."""
    disc = pf.discretize(pf.unit_square(8), dirichlet=lambda x: 0.5 + x[0])
    f = disc.interpolate(lambda x: np.cos(2 * x[0]) + x[1])
    problem = heat.heat_problem(disc, 0.05, kappa=2.0, source=f)
    g = disc.expand(np.zeros(disc.n_free))  # the Dirichlet data, zero inside
    u_full = disc.interpolate(lambda x: np.sin(3 * x[0]) * x[1]) + 0.0
    u_full[disc.dirichlet_dofs] = g[disc.dirichlet_dofs]
    M, A = disc.mass_matrix, 2.0 * disc.laplace_matrix
    system = (M + 0.05 * A).tocsr()
    rhs = M @ u_full + 0.05 * (M @ f)
    reference = skfem.solve(*skfem.condense(system, rhs, x=g, D=disc.dirichlet_dofs))
    u_next, iterations = heat.heat_step(problem, u_full[disc.free_dofs],
                                        pf.ConvergedCG(rtol=1e-13))
    np.testing.assert_allclose(np.asarray(u_next), reference[disc.free_dofs], rtol=0,
                               atol=1e-11 * np.abs(reference).max())
    assert 0 < int(iterations) < 100


def test_a_discrete_eigenmode_decays_like_the_implicit_euler_factor():
    """A v = lambda_h M v: n steps from v give (1 + dt lambda_h)^-n v; lambda_h of the lowest
    mode is within 3 % of the continuous 2 pi^2 (kappa = 1)."""
    disc = pf.discretize(pf.unit_square(12), dirichlet=0.0)
    problem = heat.heat_problem(disc, DT)
    free = disc.free_dofs
    A = disc.laplace_matrix[free][:, free].toarray()
    M = disc.mass_matrix[free][:, free].toarray()
    eigenvalues, vectors = scipy.linalg.eigh(A, M)
    lam, v = eigenvalues[0], vectors[:, 0]
    assert lam == pytest.approx(2 * np.pi**2, rel=0.03)
    u, solver = jnp.asarray(v), pf.ConvergedCG(rtol=1e-13)
    for _ in range(5):
        u, _ = heat.heat_step(problem, u, solver)
    np.testing.assert_allclose(np.asarray(u), (1 + DT * lam) ** -5 * v, rtol=0,
                               atol=1e-11 * np.abs(v).max())


def test_the_warm_start_from_u_n_saves_iterations():
    """From u_n the initial residual is dt (b - A u_n), against M u_n from zero: for a smooth
    state and a small step (dt lambda ~ 0.04) that is ~25 times smaller."""
    disc = pf.discretize(pf.unit_square(16), dirichlet=0.0)
    problem = heat.heat_problem(disc, 0.002)
    u = jnp.asarray(disc.interpolate(lambda x: np.sin(np.pi * x[0]) * np.sin(np.pi * x[1])
                                     * (1 + x[0]))[disc.free_dofs])
    solver = pf.ConvergedCG(rtol=1e-8)
    warm = heat.heat_step(problem, u, solver)[1]
    cold = pf.solve(problem.matrix, problem.rhs(u), solver).iterations
    assert int(warm) <= int(cold) - 3, (int(warm), int(cold))
    # and at a fixed K the warm start is the more accurate
    exact = heat.heat_step(problem, u, pf.ConvergedCG(rtol=1e-13))[0]
    truncated = pf.TruncatedCG(2)
    warm_error = jnp.linalg.norm(heat.heat_step(problem, u, truncated)[0] - exact)
    cold_error = jnp.linalg.norm(pf.solve(problem.matrix, problem.rhs(u), truncated).x - exact)
    assert float(warm_error) < 0.3 * float(cold_error), (float(warm_error), float(cold_error))


def test_reference_trajectories_are_substepped_direct_solves(small):
    disc, _, trajectories, _ = small
    fine = heat.heat_problem(disc, DT / 4)
    u = trajectories.states[3, 0]
    for _ in range(4):
        u = spla.spsolve(fine.matrix.to_scipy().tocsc(), np.asarray(fine.rhs(u)))
    np.testing.assert_allclose(np.asarray(trajectories.states[3, 1]), u, rtol=1e-10,
                               atol=1e-14)
    # the coarse step (one solve of size dt) has a real, learnable error: several percent
    coarse = heat.heat_step(heat.heat_problem(disc, DT), trajectories.states[3, 0],
                            pf.ConvergedCG(rtol=1e-13))[0]
    relative = float(jnp.linalg.norm(coarse - trajectories.states[3, 1])
                     / jnp.linalg.norm(trajectories.states[3, 1]))
    assert 0.01 < relative < 0.5


def test_windows_cover_every_start_of_every_trajectory(small):
    _, _, trajectories, _ = small
    w = heat.windows(trajectories, 3)
    assert w.shape == (12 * 4, 4, trajectories.states.shape[-1])
    np.testing.assert_array_equal(np.asarray(w[5]), np.asarray(trajectories.states[1, 1:5]))


# --------------------------------------------------------------------------------------
# the training modes
# --------------------------------------------------------------------------------------


class SolverDifferentiated(Exception):
    pass


def jvp_raising_step(problem, u, solver):
    """heat_step whose forward-mode derivative raises (custom_jvp)."""

    @jax.custom_jvp
    def step(problem, u):
        return heat.heat_step(problem, u, solver)

    @step.defjvp
    def _(primals, tangents):
        raise SolverDifferentiated("jvp of the solver")

    return step(problem, u)


def vjp_raising_step(problem, u, solver):
    """heat_step whose reverse-mode derivative raises (custom_vjp)."""

    @jax.custom_vjp
    def step(problem, u):
        return heat.heat_step(problem, u, solver)

    def forward(problem, u):
        return step(problem, u), None

    def backward(_, cotangent):
        raise SolverDifferentiated("vjp of the solver")

    step.defvjp(forward, backward)
    return step(problem, u)


def loss_gradients(problem, batch, modes, step):
    """The loss gradient of each mode, all in one program."""
    network, solver = network_for(problem), pf.TruncatedCG(3, gradient="implicit")
    return jax.jit(lambda net: {mode: jax.grad(lambda net, mode=mode: heat.batch_loss(
        net, problem, batch, solver, setup="correction", mode=mode, step=step)[0])(net)
        for mode in modes})(network)


@pytest.fixture(scope="module")
def real_gradients(small):
    _, problem, trajectories, _ = small
    batch = heat.windows(trajectories, 2)[:6]
    return batch, loss_gradients(problem, batch, ("nog", "one"), heat.heat_step)


@pytest.mark.parametrize("stand_in", [jvp_raising_step, vjp_raising_step])
def test_nog_and_one_never_differentiate_the_solver_and_wig_does(small, real_gradients,
                                                                  stand_in):
    """A solver whose derivative raises gives NOG and ONE the very same gradients as the real
    one (bit for bit), and makes WIG raise: the stand-in has teeth."""
    problem = small[1]
    batch, real = real_gradients
    standin = loss_gradients(problem, batch, ("nog", "one"), stand_in)
    for mode in ("nog", "one"):
        for a, b in zip(jax.tree_util.tree_leaves(real[mode]),
                        jax.tree_util.tree_leaves(standin[mode]), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(SolverDifferentiated):
        loss_gradients(problem, batch, ("wig",), stand_in)


@pytest.mark.parametrize("solver", [
    # test_reaction's Taylor test differentiates WIG through unrolled truncated solves
    pytest.param(pf.TruncatedCG(3, gradient="unrolled"), marks=pytest.mark.slow),
    pf.ConvergedCG(rtol=1e-13)], ids=["unrolled-K3", "converged"])
def test_wig_gradient_over_a_two_step_unroll_passes_a_taylor_test(small, solver):
    _, problem, trajectories, _ = small
    network = network_for(problem)
    batch = heat.windows(trajectories, 2)[:4]

    def loss(layers, mode="wig"):
        return heat.batch_loss(network._replace(layers=layers), problem, batch, solver,
                               setup="correction", mode=mode)[0]

    # the loss, WIG's gradient and NOG's in one program, which the Taylor test evaluates
    # too (a separately jitted loss would compile the solves once more)
    both = jax.jit(lambda layers: (jax.value_and_grad(loss)(layers),
                                   jax.grad(lambda layers: loss(layers, "nog"))(layers)))
    (_, wig), nog = both(network.layers)
    # the direction in NumPy, scaled per leaf as taylor_test's default: the moved points are
    # then NumPy sums, not a compile per operation and leaf shape
    rng = np.random.default_rng(0)
    dx = jax.tree.map(lambda a: rng.standard_normal(a.shape)
                      * (np.linalg.norm(a) / np.sqrt(max(a.size, 1)) + 1.0), network.layers)
    result = pf.taylor_test(lambda layers: both(layers)[0][0], network.layers, dx,
                            gradient=wig, h0=1e-2)
    assert result.passed(), result.rates
    # the temporal path matters: NOG's gradient (no gradient between the steps) is another one
    difference = jnp.sqrt(sum(jnp.sum((a - b) ** 2) for a, b in zip(
        jax.tree_util.tree_leaves(wig), jax.tree_util.tree_leaves(nog), strict=True)))
    assert float(difference) > 1e-3 * float(optax.tree.norm(wig))


@pytest.mark.parametrize(("setup", "mode", "fraction"), [
    pytest.param("correction", "one", 0.6, marks=pytest.mark.slow),  # trains as NOG does
    ("correction", "nog", 0.6),
    pytest.param("correction", "wig", 0.6, marks=pytest.mark.slow),  # prediction trains WIG
    ("prediction", "wig", 0.4)])
def test_training_lowers_the_validation_rollout_error(small, setup, mode, fraction):
    """20 epochs of 5 batches: the rollout error of the validation trajectories (converged
    coarse solves) falls below ``fraction`` of the untrained network's (measured for the
    default cases: 0.40 with NOG, 0.31 with prediction WIG; 0.32 and 0.22 after 40 epochs).
    NOG trains with the black-box stand-in: it needs no derivative."""
    _, problem, trajectories, validation = small
    network = network_for(problem, output_scale=0.05 if setup == "correction" else 0.3)
    start = converged_rollout_error(network, problem, validation, setup=setup)[0]
    training = heat.train(problem, network, trajectories, validation, setup=setup, mode=mode,
                          unroll=2, optimizer=optax.adam(3e-3), refinement=prdp(K0=1, dK=1),
                          epochs=20, batch_size=12,
                          step=vjp_raising_step if mode == "nog" else heat.heat_step)
    last = training.records[-1]
    assert last.validation_error < fraction * float(start), (float(start), last)
    times = [r.time for r in training.records]
    assert times == sorted(times)
    if setup == "prediction":  # no solver ran
        assert last.primal_iterations == 0 and last.iterations == 0
    else:  # PRDP refined from K0 = 1; the tally is exact: K per solve, 2 solves per window,
        # all 60 windows (5 full batches of 12) per epoch
        assert int(training.refinement.iterations) > 1
        assert last.primal_iterations == sum(r.iterations * 2 * 60 for r in training.records)


@pytest.fixture(scope="module")
def fixed_k_training(small):
    """``train(mode)``: the fixed K = 3, K_adj = 5 training of 2 epochs (unroll 2, batches of
    12) with the first 2 validation trajectories as its test set, and the records its
    callback saw; one per mode for the module (the test set changes no training number)."""
    from prdp_fem.inverse import fixed

    _, problem, trajectories, validation = small
    trained = {}

    def train(mode):
        if mode not in trained:
            seen = []
            training = heat.train(problem, network_for(problem), trajectories, validation,
                                  mode=mode, unroll=2, refinement=fixed(3, 5), epochs=2,
                                  batch_size=12, test_set=validation.take(np.arange(2)),
                                  callback=seen.append)
            trained[mode] = training, seen
        return trained[mode]

    return train


@pytest.mark.parametrize("mode", ["nog", "wig"])  # ONE stops the solver's gradient as NOG
def test_the_adjoint_tally_counts_wig_solves_only_and_records_carry_the_test_error(
        small, fixed_k_training, mode):
    """Fixed K = 3, K_adj = 5, unroll 2, 12 trajectories x 5 windows per epoch. Primal: K per
    solve, 2 solves per window. Adjoint: WIG alone differentiates the solver, and only its
    *second* solve depends on the parameters (the first starts from ground truth), so
    K_adj x 1 x 60 per epoch; ONE and NOG run none. Every record reaches ``callback`` with the
    held-out rollout error of the network at that epoch (converged solves)."""
    _, problem, _, validation = small
    training, seen = fixed_k_training(mode)
    assert seen == training.records
    assert [r.primal_iterations for r in seen] == [3 * 2 * 60, 2 * 3 * 2 * 60]
    per_epoch = 5 * 60 if mode == "wig" else 0
    assert [r.adjoint_iterations_total for r in seen] == [per_epoch, 2 * per_epoch]
    final = converged_rollout_error(training.network, problem,
                                    validation.take(np.arange(2)))[0]
    assert seen[-1].test_error == pytest.approx(float(final), rel=1e-10)
    assert seen[0].test_error != seen[-1].test_error


def test_unrolled_training_refines_k_within_one_compiled_step(small, monkeypatch):
    """WIG through the unrolled solver while PRDP raises K from 1: every K up to 16 runs the
    same program (one scan length), and the tally stays exact: K per primal solve (2 per
    window) and, backward, K per differentiated solve (the second of each window)."""
    made = shared_compiles_made(monkeypatch)
    _, problem, trajectories, validation = small
    training = heat.train(problem, network_for(problem), trajectories, validation, mode="wig",
                          unroll=2, gradient="unrolled", optimizer=optax.adam(3e-3),
                          refinement=prdp(K0=1, dK=1, ema_window=1, delta=2, tau_step=0.5),
                          epochs=6, batch_size=12)
    ks = [r.iterations for r in training.records]
    assert len(set(ks)) > 1 and max(ks) <= 16, ks
    [step] = [c for c in made if c._static_argnum == 4]
    assert [key[0] for key in step._cache] == [16]
    last = training.records[-1]
    assert last.primal_iterations == sum(k * 2 * 60 for k in ks)
    assert last.adjoint_iterations_total == sum(k * 60 for k in ks)


@pytest.mark.slow  # compile sharing; the inversion test keeps it in the default suite
def test_trainings_with_equal_settings_share_one_kept_step(small, monkeypatch):
    """A study's PRDP and converged runs of one mode call train with equal settings: the
    step is traced once and the trainings are what they were alone; another optimizer
    object is another step."""
    from prdp_fem.inverse import converged, fixed


    heat._step_program.cache_clear()
    made = shared_compiles_made(monkeypatch)
    _, problem, trajectories, validation = small
    adam = optax.adam(3e-3)

    def train(optimizer, refinement):
        return heat.train(problem, network_for(problem), trajectories, validation, mode="wig",
                          unroll=2, optimizer=optimizer, refinement=refinement, epochs=2,
                          batch_size=12)

    first = train(adam, fixed(3))
    tolerance = train(adam, converged(1e-10))
    again = train(adam, fixed(3))
    steps = [c for c in made if c._static_argnum == 4]
    assert len(steps) == 2  # fixed K and the tolerance mode are two programs, kept
    assert [r._replace(time=0.0) for r in again.records] == \
        [r._replace(time=0.0) for r in first.records]
    assert tolerance.records[-1].rtol == 1e-10
    train(optax.adam(3e-3), fixed(3))
    assert len([c for c in made if c._static_argnum == 4]) == 3


def test_a_second_training_with_the_default_optimizer_compiles_nothing(small,
                                                                      backend_compiles):
    """Trainings that pass no optimizer share one default object, so their step, and their
    validation rollouts, are compiled once for the process (a bench's seeds, a script's
    loop)."""
    from prdp_fem.inverse import fixed

    _, problem, trajectories, validation = small

    def train(seed):
        return heat.train(problem, network_for(problem, seed=seed), trajectories, validation,
                          mode="nog", unroll=2, refinement=fixed(3), epochs=1, batch_size=12,
                          test_set=validation)

    first = train(0)
    compiled = len(backend_compiles)
    second = train(1)
    assert backend_compiles[compiled:] == []
    assert second.records[-1].validation_error != first.records[-1].validation_error


def test_the_initial_network_is_scaled_to_its_targets(small):
    """The output layer's scale is the spread of the relative one-step targets: the
    converged coarse step's error (correction, small) or the step itself (prediction)."""
    _, problem, trajectories, _ = small
    pairs = heat.windows(trajectories, 1)
    u, target = np.asarray(pairs[:, 0]), np.asarray(pairs[:, 1])
    rho = np.sqrt(np.mean(u**2, axis=1, keepdims=True))
    network = heat.initial_network(problem, trajectories, "prediction", (8,), seed=3)
    assert network.output_scale == pytest.approx(np.std((target - u) / rho), rel=1e-12)
    coarse = heat.initial_network(problem, trajectories, "correction", (8,), seed=3)
    assert 0 < coarse.output_scale < 0.5 * network.output_scale
    assert [w.shape for w, _ in network.layers] == [(problem.n_free, 8), (8, problem.n_free)]


def test_the_rollout_iteration_tally_is_exact(small):
    """K per step, every step of every trajectory (the training tally is checked above)."""
    _, problem, _, validation = small
    # jitted: one program, not a compile per operation of the rollout
    _, iterations = jax.jit(lambda problem, validation: heat.rollout_error(
        None, problem, validation, pf.TruncatedCG(3)))(problem, validation)
    assert int(iterations) == 3 * 6 * 4


def test_a_non_finite_loss_raises_with_the_setup_and_mode(small):
    _, problem, trajectories, validation = small

    def poisoned(problem, u, solver):
        return u * jnp.nan, jnp.zeros((), jnp.int32)

    with pytest.raises(InversionError, match=r"non-finite.*setup='correction', mode='nog'"):
        heat.train(problem, network_for(problem), trajectories, validation, mode="nog",
                   unroll=2, epochs=1, batch_size=12, step=poisoned)


def test_bad_options_are_refused_with_their_names(small):
    disc, problem, trajectories, validation = small
    network = network_for(problem)

    def train(**kwargs):
        heat.train(problem, kwargs.pop("network", network), kwargs.pop("train", trajectories),
                   validation, **kwargs)

    with pytest.raises(SolverConfigError, match="setup='hybrid'"):
        train(setup="hybrid")
    with pytest.raises(SolverConfigError, match="mode='full'"):
        train(mode="full")
    with pytest.raises(SolverConfigError, match="gradient='forward'"):
        train(gradient="forward")
    with pytest.raises(SolverConfigError, match="unroll=7: expected at most the 6 steps"):
        train(unroll=7)
    with pytest.raises(SolverConfigError, match="unroll=0"):
        train(unroll=0)
    with pytest.raises(SolverConfigError, match="batch_size=99: expected at most the 48"):
        train(batch_size=99)
    with pytest.raises(SolverConfigError, match="epochs=0"):
        train(epochs=0)
    with pytest.raises(ShapeError, match=r"an input of 25 values gives \(7,\)"):
        train(network=learned.mlp_init(jax.random.PRNGKey(0), [25, 4, 7]))
    with pytest.raises(ShapeError, match="train_set"):
        train(train=heat.Trajectories(trajectories.states[..., :5]))
    batch = heat.windows(trajectories, 2)[:2]
    with pytest.raises(SolverConfigError, match="mode='two'"):
        heat.batch_loss(network, problem, batch, pf.TruncatedCG(2), setup="correction",
                        mode="two")
    with pytest.raises(SolverConfigError, match="setup='both'"):
        heat.rollout(network, problem, batch[0, 0], 2, pf.TruncatedCG(2), setup="both")
    with pytest.raises(SolverConfigError, match="dt=0"):
        heat.heat_problem(disc, 0.0)
    with pytest.raises(SolverConfigError, match="dt=nan"):
        heat.heat_problem(disc, float("nan"))
    with pytest.raises(SolverConfigError, match="substeps=0"):
        heat.reference_trajectories(disc, np.zeros((1, disc.n_dofs)), dt=0.1, steps=2,
                                    substeps=0)
    with pytest.raises(ShapeError, match="initial"):
        heat.reference_trajectories(disc, np.zeros((2, 3)), dt=0.1, steps=2)
    with pytest.raises(pf.CoefficientError, match="kappa"):
        heat.heat_problem(disc, 0.1, kappa=-1.0)


def test_the_validation_rollouts_iterations_are_counted(small, fixed_k_training):
    """CG iterations count every solve that ran: each epoch's validation rollout (converged
    solves) adds its own iterations -- the last epoch's are the trained network's rollout's."""
    _, problem, _, validation = small
    training, _ = fixed_k_training("nog")
    first, last = training.records
    _, final = converged_rollout_error(training.network, problem, validation)
    assert 0 < first.validation_iterations < last.validation_iterations
    assert last.validation_iterations - first.validation_iterations == int(final)
