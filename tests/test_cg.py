"""Truncated and converged PCG: forward accuracy, then grouped by transformation
(vjp: unrolled and implicit, jvp, jit/recompiles, vmap)."""

import dataclasses
import functools
from functools import partial
from typing import Any

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest

import prdp_fem as pf
from prdp_fem.linalg import ConvergedCG, TruncatedCG, solve


def solve_problem(disc, kappa, f, solver, x0=None):
    system = disc.system
    return solve(system.operator(kappa), system.rhs(kappa, f), solver, x0=x0)


def exact(disc, kappa, f):
    return pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f)).x


# ------------------------------------------------------------------------------------------
# forward
# ------------------------------------------------------------------------------------------


def test_zero_iterations_return_x0(small_problem):
    disc, kappa, f = small_problem
    x0 = np.linspace(-1, 1, disc.n_free)
    for mode in ("unrolled", "implicit"):
        sol = solve_problem(disc, kappa, f, TruncatedCG(0, gradient=mode), x0=x0)
        np.testing.assert_array_equal(sol.x, x0)
        assert int(sol.iterations) == 0


def _count_products(jaxpr) -> int:
    """Sparse products (the primitive of prdp_fem.linalg._products) in a jaxpr, nested ones too."""
    count = 0
    for eqn in jaxpr.eqns:
        count += eqn.primitive.name == "sparse_product"
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            count += _count_products(sub)
    return count


# unrolled: the slow twin (both modes start from _init, where the zero start skips A x0)
@pytest.mark.parametrize("mode", [pytest.param("unrolled", marks=pytest.mark.slow), "implicit"])
def test_zero_start_skips_the_product_and_changes_nothing(small_problem, mode):
    """x0=None runs CG from zero without forming A 0 (a whole SpMV per solve, two per
    implicit gradient); x0=zeros forms it. Same iterates, same gradient."""
    disc, kappa, f = small_problem
    zeros = np.zeros(disc.n_free)

    def loss(kappa, x0):
        x = solve_problem(disc, kappa, f, TruncatedCG(7, gradient=mode), x0=x0).x
        return jnp.sum(jnp.sin(x))

    # each program traced once: its jaxpr is counted, then it is compiled and run
    free, given = (jax.jit(jax.value_and_grad(lambda k, x0=x0: loss(k, x0))).trace(kappa)
                   for x0 in (None, zeros))
    assert _count_products(free.jaxpr.jaxpr) < _count_products(given.jaxpr.jaxpr)
    free_start = free.lower().compile()(kappa)
    given_start = given.lower().compile()(kappa)
    np.testing.assert_allclose(free_start[0], given_start[0], rtol=1e-13)
    np.testing.assert_allclose(free_start[1], given_start[1], rtol=1e-11,
                               atol=1e-13 * float(jnp.abs(given_start[1]).max()))


@pytest.mark.parametrize("preconditioner", ["identity", "jacobi"])
def test_energy_error_decreases_monotonically_in_k(small_problem, preconditioner):
    disc, kappa, f = small_problem
    A = disc.stiffness_matrix(kappa)
    x_star = exact(disc, kappa, f)
    # implicit mode takes K traced: one compile for the 40 counts (the forward iterates are
    # the unrolled ones; test_forward_iterates_agree_between_modes checks that)
    operator, rhs = disc.system.operator(kappa), disc.system.rhs(kappa, f)
    run = jax.jit(jax.vmap(lambda k: solve(
        operator, rhs, TruncatedCG(k, preconditioner, gradient="implicit")).x))
    xs = np.asarray(run(jnp.arange(40)))
    energy = np.sqrt(np.einsum("ki,ki->k", xs - x_star, (A @ (xs - x_star).T).T))
    assert np.all(np.diff(energy) <= 1e-12 * energy[0])
    assert energy[-1] < 1e-8 * energy[0]


# K = 0 and 3 with the slow cases: test_zero_iterations_return_x0 has both modes return x0 bit
# for bit, and K = 17 steps the same iterations past K = 3
@pytest.mark.parametrize("k", [pytest.param(0, marks=pytest.mark.slow),
                               pytest.param(3, marks=pytest.mark.slow), 17])
def test_forward_iterates_agree_between_modes(small_problem, k):
    disc, kappa, f = small_problem
    unrolled = solve_problem(disc, kappa, f, TruncatedCG(k)).x
    implicit = solve_problem(disc, kappa, f, TruncatedCG(k, gradient="implicit")).x
    np.testing.assert_allclose(unrolled, implicit, rtol=1e-13, atol=1e-15)


# 3969 and 16641 unknowns: both r.r reductions; a general preconditioner forms z = M r at any
# size, so its case above the row reduction is the slow twin of the 64 one
@pytest.mark.parametrize(("n_side", "jacobi"), [
    (64, True), (64, False), (130, True), pytest.param(130, False, marks=pytest.mark.slow)])
def test_stacked_and_paired_states_take_the_same_iterations(n_side, jacobi):
    # the while loops keep [d, r] stacked in one array, the scan keeps a pair: one iteration
    from prdp_fem.bench.cg import poisson_operator
    from prdp_fem.linalg.cg import _ROW_REDUCTION_FROM, _init, _krylov, _step

    op, b = poisson_operator(n_side)
    b = jnp.asarray(b)
    inverse_diagonal = pf.linalg.jacobi(op).inverse_diagonal
    precond = pf.linalg.JacobiPreconditioner(inverse_diagonal) if jacobi \
        else _DiagonalAsGeneral(inverse_diagonal)
    krylov = _krylov(op, precond)

    @jax.jit  # one program for both starts and six steps of each (op by op, dozens)
    def six_steps(krylov, b):
        starts = tuple(_init(krylov, b, jnp.zeros_like(b), stacked=flag).state
                       for flag in (True, False))
        return jax.lax.fori_loop(0, 6, lambda _, states: tuple(
            _step(krylov, state)[0] for state in states), starts)

    stacked, paired = six_steps(krylov, b)
    assert stacked.dr.shape == (2, b.size) and isinstance(paired.dr, tuple)
    assert (b.size > _ROW_REDUCTION_FROM) == (n_side == 130)
    for field in ("d", "r", "p", "rz"):
        np.testing.assert_allclose(getattr(stacked, field), getattr(paired, field),
                                   rtol=1e-13, atol=1e-15 * float(jnp.abs(paired.p).max()))
    assert float(jnp.abs(stacked.d).max()) > 0  # it moved


def _loop_states(jaxpr, n: int) -> list[bool]:
    """For each while loop in a jaxpr (nested ones too): whether it carries a stacked
    ``(2, n)`` state."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "while":
            found.append(any(getattr(v.aval, "shape", None) == (2, n) for v in eqn.outvars))
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            found += _loop_states(sub, n)
    return found


@pytest.mark.parametrize(("solver", "n_side", "stacked"), [
    (ConvergedCG(rtol=1e-10), 128, False),  # 16129 unknowns: r.r is a slice's dot product
    (ConvergedCG(rtol=1e-10), 130, True),  # 16641: r.r is the stacked state's row reduction
    (ConvergedCG(rtol=1e-10, preconditioner="identity"), 130, False),
    (TruncatedCG(20, gradient="implicit"), 128, False),
    (TruncatedCG(20, gradient="implicit"), 130, True),
    (TruncatedCG(20, "identity", gradient="implicit"), 130, False),
])
def test_a_while_loop_stacks_only_for_the_row_reduction(solver, n_side, stacked):
    """Stacked, a while loop copies the row r out of [d, r] every iteration for its dot
    products (and its norm); that pays off only where r.r is the row reduction of the
    stacked state (the measurements: cg._stacks)."""
    from prdp_fem.bench.cg import poisson_operator

    op, b = poisson_operator(n_side)
    b = jnp.asarray(b)
    jaxpr = jax.make_jaxpr(lambda b: solve(op, b, solver).x)(b).jaxpr
    assert _loop_states(jaxpr, b.size) == [stacked]


# the Jacobi cases with the slow ones: the identity case runs the same while loop, and
# test_stacked_and_paired_states_take_the_same_iterations steps it with Jacobi
@pytest.mark.parametrize("solver", [
    pytest.param(ConvergedCG(rtol=1e-10), marks=pytest.mark.slow),
    ConvergedCG(rtol=1e-10, preconditioner="identity"),
    pytest.param(TruncatedCG(200, gradient="implicit"), marks=pytest.mark.slow)])
def test_a_while_loop_takes_the_same_iterates_paired_or_stacked(monkeypatch, solver):
    from prdp_fem.bench.cg import poisson_operator
    from prdp_fem.linalg import cg

    op, b = poisson_operator(128)
    b = jnp.asarray(b)
    paired = jax.jit(lambda b: solve(op, b, solver)).trace(b)
    with monkeypatch.context() as patch:
        patch.setattr(cg, "_stacks", lambda krylov, n: True)
        stacked = jax.jit(lambda b: solve(op, b, solver)).trace(b)
    # each traced afresh (the patch was read, no cached trace reused) and compiled from its
    # trace, so no cache needs clearing (clearing them all made the tests after recompile)
    assert _loop_states(paired.jaxpr.jaxpr, b.size) == [False]
    assert _loop_states(stacked.jaxpr.jaxpr, b.size) == [True]
    paired, stacked = (traced.lower().compile()(b) for traced in (paired, stacked))
    assert int(paired.iterations) == int(stacked.iterations) > 100
    np.testing.assert_array_equal(paired.x, stacked.x)
    np.testing.assert_array_equal(paired.residual_norm, stacked.residual_norm)


# unrolled: the slow twin (test_extreme's frozen unrolled solve is pinned to the converged one,
# and test_preconditioned_while_loops_take_the_scans_iterations[past-*] counts its iterations)
@pytest.mark.parametrize("mode", [pytest.param("unrolled", marks=pytest.mark.slow), "implicit"])
def test_k_far_past_convergence_is_finite_and_exact(small_problem, mode):
    disc, kappa, f = small_problem
    k = 10 * disc.n_free
    sol = solve_problem(disc, kappa, f, TruncatedCG(k, gradient=mode))
    x_star = exact(disc, kappa, f)
    assert np.all(np.isfinite(sol.x))
    np.testing.assert_allclose(sol.x, x_star, rtol=1e-12, atol=1e-12 * abs(x_star).max())
    assert int(sol.iterations) < disc.n_free  # frozen after convergence, not counted
    assert np.all(np.isfinite(sol.residual_history))


@pytest.mark.parametrize("mode", ["unrolled", "implicit"])
def test_zero_rhs_and_exact_start_are_finite(small_problem, mode):
    disc, kappa, f = small_problem
    op = disc.system.operator(kappa)
    b = disc.system.rhs(kappa, f)
    zero = solve(op, jnp.zeros_like(b), TruncatedCG(25, gradient=mode))
    np.testing.assert_array_equal(zero.x, 0.0)
    x_star = exact(disc, kappa, f)
    started = solve(op, b, TruncatedCG(25, gradient=mode), x0=x_star)
    np.testing.assert_allclose(started.x, x_star, rtol=1e-12)


def test_converged_cg_agrees_with_pyamg():
    disc = pf.discretize(pf.rectangle_with_hole(12), element="P2", kappa_space="P1",
                         dirichlet={"left": 1.0, "hole": 0.0})
    kappa = disc.interpolate_kappa(lambda x: np.exp(np.sin(2 * x[0]) * x[1]))
    f = disc.interpolate(lambda x: x[0] * x[1])
    sol = solve_problem(disc, kappa, f, ConvergedCG(rtol=1e-13))
    ref = pf.amg_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f), rtol=1e-13)
    rel = np.linalg.norm(np.asarray(sol.x) - ref.x) / np.linalg.norm(ref.x)
    assert rel < 1e-10
    assert float(sol.residual_norm) <= 1e-13 * np.linalg.norm(disc.rhs(kappa, f)) * 1.0001


def test_converged_cg_respects_max_iterations(small_problem):
    disc, kappa, f = small_problem
    sol = solve_problem(disc, kappa, f, ConvergedCG(rtol=1e-14, max_iterations=3,
                                                    history_size=5))
    assert int(sol.iterations) == 3
    history = np.asarray(sol.residual_history)
    assert history[3] == history[4] == history[5] == float(sol.residual_norm)


def test_diagnostics_match_the_residual(small_problem):
    disc, kappa, f = small_problem
    sol = solve_problem(disc, kappa, f, TruncatedCG(12))
    A, b = disc.stiffness_matrix(kappa), disc.rhs(kappa, f)
    true_residual = np.linalg.norm(b - A @ np.asarray(sol.x))
    assert float(sol.residual_norm) == pytest.approx(true_residual, rel=1e-8)
    assert float(sol.initial_residual_norm) == pytest.approx(np.linalg.norm(b))
    assert sol.residual_history.shape == (13,)


def test_solver_options_are_checked_at_construction():
    with pytest.raises(pf.SolverConfigError, match="gradient='adjoint'"):
        TruncatedCG(5, gradient="adjoint")
    with pytest.raises(pf.SolverConfigError, match="iterations=-1"):
        TruncatedCG(-1)
    with pytest.raises(pf.SolverConfigError, match="preconditioner='ilu'"):
        TruncatedCG(5, preconditioner="ilu")
    with pytest.raises(pf.SolverConfigError, match="rtol=0"):
        ConvergedCG(rtol=0.0, atol=0.0)
    with pytest.raises(pf.ShapeError, match="expected vectors of length"):
        A = pf.SparseMatrix.from_scipy(np.eye(3))
        solve(A, np.ones(4), TruncatedCG(2))


# ------------------------------------------------------------------------------------------
# vjp: unrolled (exact derivative of the K-iteration map) and implicit (adjoint solve)
# ------------------------------------------------------------------------------------------

WEIGHTS_SEED = 5


def loss_fn(disc, solver, argument):
    """Scalar J = w . x_K as a function of kappa, of f, or of x0."""
    system = disc.system
    w = jax.random.normal(jax.random.PRNGKey(WEIGHTS_SEED), (disc.n_free,))

    def loss(kappa, f, x0):
        return w @ solve(system.operator(kappa), system.rhs(kappa, f), solver, x0=x0).x

    index = {"kappa": 0, "f": 1, "x0": 2}[argument]

    def partial_loss(value, args):
        args = list(args)
        args[index] = value
        return loss(*args)

    return jax.jit(partial_loss), index


@functools.cache
def _taylor_case(kappa_space):
    """``(fn, args, gradients)`` for J = w . x_8 on a 6 x 6 square as a function of ``args =
    (kappa, f, x0)``, jitted, and its jitted gradients with respect to all three: kept for the
    module, so that the Taylor tests below share one value and one gradient program."""
    disc = pf.discretize(pf.unit_square(6), element="P1", kappa_space=kappa_space,
                         dirichlet=lambda x: x[1])
    kappa = jnp.asarray(disc.interpolate_kappa(lambda x: 1.0 + x[0]))
    f = jnp.asarray(disc.interpolate(lambda x: np.sin(3 * x[0])))
    x0 = jnp.asarray(np.cos(np.arange(disc.n_free)))
    system = disc.system
    w = jax.random.normal(jax.random.PRNGKey(WEIGHTS_SEED), (disc.n_free,))

    def loss(kappa, f, x0):
        return w @ solve(system.operator(kappa), system.rhs(kappa, f), TruncatedCG(8),
                         x0=x0).x

    args = (kappa, f, x0)
    return jax.jit(loss), args, jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(*args)


def _along(fn, args, index):
    """``fn`` as a function of ``args[index]`` alone, the other arguments held."""
    def partial_fn(value):
        return fn(*args[:index], value, *args[index + 1:])

    return partial_fn


# the kappa space changes only the operator's map from kappa, the same in both modes, whose P1
# derivative test_implicit_gradient_at_large_k_equals_exact_adjoint checks: the P1 cases are
# the slow twins of the P0 ones
@pytest.mark.parametrize(("argument", "kappa_space"), [
    ("kappa", "P0"), pytest.param("kappa", "P1", marks=pytest.mark.slow), ("f", "P0"),
    pytest.param("f", "P1", marks=pytest.mark.slow), ("x0", "P0"),
    pytest.param("x0", "P1", marks=pytest.mark.slow)])
def test_unrolled_gradient_passes_taylor_test(kappa_space, argument):
    fn, args, gradients = _taylor_case(kappa_space)
    index = {"kappa": 0, "f": 1, "x0": 2}[argument]
    result = pf.taylor_test(_along(fn, args, index), args[index], gradient=gradients[index],
                            h0=1e-2)
    assert result.passed(), result.rates
    assert np.all(np.isfinite(result.rates[:3]))


def test_taylor_test_rejects_a_wrong_gradient():
    fn, args, gradients = _taylor_case("P0")  # the programs of the test above
    wrong = 1.2 * gradients[0]
    result = pf.taylor_test(_along(fn, args, 0), args[0], gradient=wrong)
    assert not result.passed()
    assert np.nanmedian(result.rates) == pytest.approx(1.0, abs=0.2)


def exact_gradients(disc, kappa, f, w):
    """dJ/dkappa and dJ/df of J = w . x* by the adjoint method, pyamg-converged."""
    A = disc.stiffness_matrix(kappa)
    x = pf.amg_solve(A, disc.rhs(kappa, f), rtol=1e-13).x
    lam = pf.amg_solve(A, w, rtol=1e-13).x
    rows, cols = disc.pattern
    values_bar = -lam[rows] * x[cols]
    kappa_bar = disc.assembly.T @ values_bar - disc.lifting.T @ lam
    f_bar = disc.mass_matrix[disc.free_dofs].T @ lam
    return kappa_bar, f_bar


@pytest.fixture(scope="module")
def p1_kappa_problem():
    disc = pf.discretize(pf.unit_square(10), element="P1", kappa_space="P1",
                         dirichlet={"left": 1.0, "right": 0.0})
    kappa = jnp.asarray(disc.interpolate_kappa(lambda x: 1.0 + 3 * x[0] * x[1]))
    f = jnp.asarray(disc.interpolate(lambda x: np.sin(2 * x[1])))
    w = np.asarray(jax.random.normal(jax.random.PRNGKey(WEIGHTS_SEED), (disc.n_free,)))
    return disc, kappa, f, w


@pytest.fixture(scope="module")
def implicit_gradients(p1_kappa_problem):
    """``gradients(kappa, K, K_adj)``: dJ/dkappa and dJ/df of J = w . x_K in implicit mode, K
    and K_adj traced, so one program serves every count of the tests below (loss_fn closes
    over its solver: a program per solver)."""
    disc, _, f, w = p1_kappa_problem
    system = disc.system

    @jax.jit
    def gradients(kappa, k, k_adj):
        solver = TruncatedCG(k, gradient="implicit", adjoint_iterations=k_adj)
        return jax.grad(lambda c, g: jnp.asarray(w) @ solve(
            system.operator(c), system.rhs(c, g), solver).x, argnums=(0, 1))(kappa, f)

    return gradients


def relative(a, b):
    return float(np.linalg.norm(np.asarray(a) - b) / np.linalg.norm(b))


def test_implicit_gradient_at_large_k_equals_exact_adjoint(p1_kappa_problem, implicit_gradients):
    disc, kappa, f, w = p1_kappa_problem
    kappa_bar, f_bar = exact_gradients(disc, np.asarray(kappa), np.asarray(f), w)
    big = 10 * disc.n_free  # K_adj = K, as TruncatedCG's default
    g_kappa, g_f = implicit_gradients(kappa, big, big)
    assert relative(g_kappa, kappa_bar) < 1e-8
    assert relative(g_f, f_bar) < 1e-8
    converged = jax.jit(jax.grad(loss_fn(disc, ConvergedCG(rtol=1e-13), "kappa")[0]))(
        kappa, (kappa, f, jnp.zeros(disc.n_free)))
    assert relative(converged, kappa_bar) < 1e-8


@pytest.mark.slow  # test_properties covers the same, over drawn cases
def test_truncated_gradients_are_finite_and_approach_exact(p1_kappa_problem,
                                                          implicit_gradients):
    disc, kappa, f, w = p1_kappa_problem
    kappa_bar, _ = exact_gradients(disc, np.asarray(kappa), np.asarray(f), w)
    errors = {"unrolled": [], "implicit": []}
    args = (kappa, f, jnp.zeros(disc.n_free))
    for k in (3, 10, 30):
        for mode in errors:  # the kappa gradient alone, jitted
            if mode == "implicit":  # K traced: one program for the three counts
                g = implicit_gradients(kappa, k, k)[0]
            else:  # a scan of K steps: a program per K
                g = jax.jit(jax.grad(loss_fn(disc, TruncatedCG(k), "kappa")[0]))(kappa, args)
            assert np.all(np.isfinite(g))
            errors[mode].append(relative(g, kappa_bar))
    for mode, errs in errors.items():
        assert errs[0] > 1e-2, mode  # truncation is visible at small K
        assert errs[0] > errs[1] > errs[2], (mode, errs)


def test_implicit_adjoint_iterations_are_separate(p1_kappa_problem, implicit_gradients):
    disc, kappa, f, w = p1_kappa_problem
    kappa_bar, _ = exact_gradients(disc, np.asarray(kappa), np.asarray(f), w)
    big = 10 * disc.n_free
    coarse_adjoint = implicit_gradients(kappa, big, 3)[0]
    fine_adjoint = implicit_gradients(kappa, big, big)[0]
    assert relative(fine_adjoint, kappa_bar) < 1e-8
    assert relative(coarse_adjoint, kappa_bar) > 1e-3


# unrolled: the slow twin (test_extreme pins the unrolled gradient far past convergence)
@pytest.mark.parametrize("mode", [pytest.param("unrolled", marks=pytest.mark.slow), "implicit"])
def test_gradients_finite_far_past_convergence_and_at_zero_rhs(small_problem, mode):
    disc, kappa, f = small_problem
    k = 10 * disc.n_free
    system = disc.system

    # the right-hand side scaled by an argument: one program serves b and b = 0 (x = 0, and
    # with it a zero cotangent)
    def loss(kappa, scale):
        x = solve(system.operator(kappa), scale * system.rhs(kappa, f),
                  TruncatedCG(k, gradient=mode)).x
        return jnp.sum(x ** 2)

    gradient = jax.jit(jax.grad(loss))
    for scale in (1.0, 0.0):
        assert np.all(np.isfinite(gradient(jnp.asarray(kappa), scale))), scale


@pytest.mark.slow  # test_scan_length_with_checkpoints_jvp_and_vmap checkpoints by default
def test_unrolled_checkpoint_gives_the_same_gradient(small_problem):
    disc, kappa, f = small_problem
    args = (jnp.asarray(kappa), jnp.asarray(f), jnp.zeros(disc.n_free))
    plain = jax.grad(loss_fn(disc, TruncatedCG(15), "kappa")[0])(args[0], args)
    checkpointed = jax.grad(loss_fn(disc, TruncatedCG(15, checkpoint=True), "kappa")[0])(
        args[0], args)
    np.testing.assert_allclose(checkpointed, plain, rtol=1e-12)


# ------------------------------------------------------------------------------------------
# jvp: forward mode through the unrolled iterations
# ------------------------------------------------------------------------------------------


@pytest.mark.slow  # test_forward_mode's counted unrolled solve checks its jvp against its vjp
def test_unrolled_jvp_matches_vjp(small_problem):
    disc, kappa, f = small_problem
    fn, _ = loss_fn(disc, TruncatedCG(10), "kappa")
    args = (jnp.asarray(kappa), jnp.asarray(f), jnp.zeros(disc.n_free))
    direction = jnp.asarray(np.random.default_rng(7).normal(size=disc.n_kappa))
    _, tangent = jax.jvp(lambda v: fn(v, args), (args[0],), (direction,))
    reverse = jax.grad(fn)(args[0], args) @ direction
    assert float(tangent) == pytest.approx(float(reverse), rel=1e-11)


# ------------------------------------------------------------------------------------------
# jit: traced K in implicit mode does not recompile
# ------------------------------------------------------------------------------------------


def test_implicit_k_is_traced_without_recompiling(small_problem):
    disc, kappa, f = small_problem
    system = disc.system
    traces = []

    @jax.jit
    def value_and_grad(kappa, k, k_adj):
        traces.append(1)

        def loss(kappa):
            solver = TruncatedCG(k, gradient="implicit", adjoint_iterations=k_adj)
            return jnp.sum(solve(system.operator(kappa), system.rhs(kappa, f), solver).x ** 2)

        return jax.value_and_grad(loss)(kappa)

    values = [value_and_grad(jnp.asarray(kappa), k, k + 2)[0] for k in (2, 5, 40, 400)]
    assert len(traces) == 1
    x_star = exact(disc, kappa, f)
    assert float(values[-1]) == pytest.approx(float(x_star @ x_star), rel=1e-12)
    assert float(values[0]) != pytest.approx(float(values[-1]), rel=1e-3)


def test_unrolled_with_traced_k_is_a_clear_error(small_problem):
    disc, kappa, f = small_problem

    @jax.jit
    def run(k):
        return solve_problem(disc, kappa, f, TruncatedCG(k)).x

    with pytest.raises(pf.SolverConfigError, match="needs a static K"):
        run(5)


# an eager solve is one program per shape and solver form; a count or tolerance is its argument
@pytest.mark.parametrize("first, second, programs", [
    (TruncatedCG(4, gradient="implicit"),  # a NumPy count and K_adj given: the same program
     TruncatedCG(np.int32(9), gradient="implicit", adjoint_iterations=2), 1),
    (ConvergedCG(rtol=1e-6), ConvergedCG(rtol=1e-10, max_iterations=500), 1),
    (TruncatedCG(3, scan_length=16), TruncatedCG(11, scan_length=16), 1),
    (TruncatedCG(3), TruncatedCG(5), 2),  # unrolled: the scan's length is K
], ids=["implicit", "converged", "scan_length", "unrolled"])
def test_an_eager_solve_compiles_one_program_and_reuses_it_for_new_numbers(
        backend_compiles, first, second, programs):
    # a shape of its own: 13 x 13 P1 has 144 free dofs
    disc = pf.discretize(pf.unit_square(13), element="P1", kappa_space="P1")
    kappa = disc.interpolate_kappa(lambda x: 1.0 + x[0] * x[1])
    A = disc.system.operator(jnp.asarray(kappa))
    b = np.asarray(disc.rhs(kappa, disc.interpolate(lambda x: np.sin(3 * x[0]))))
    backend_compiles.clear()
    eager = [solve(A, b, solver) for solver in (first, second)]
    # op by op an eager solve compiled some 35 small programs on a new shape
    assert len(backend_compiles) == programs, backend_compiles
    # each equals its solve traced anew (so the second did not run the first's numbers)
    assert int(eager[0].iterations) != int(eager[1].iterations)
    # (both traced into one program: compiling them apart cost a program more)
    references = jax.jit(lambda A, b: [solve(A, b, solver) for solver in (first, second)])(A, b)
    for sol, traced in zip(eager, references, strict=True):
        np.testing.assert_allclose(sol.x, traced.x, rtol=1e-13, atol=0)
        assert int(sol.iterations) == int(traced.iterations)


@partial(jax.tree_util.register_dataclass, data_fields=["scale"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class _Sweeps:
    """A preconditioner pytree with a Python-number leaf read by ``range`` (allowed)."""

    scale: Any

    def __call__(self, r):
        for _ in range(int(self.scale)):
            r = 0.5 * r
        return r


def test_an_eager_solve_keeps_what_op_by_op_did_at_the_edges(small_problem):
    """Found by review of the compiled eager solve: each worked (or raised) before it."""
    disc, kappa, f = small_problem
    A, b = disc.system.operator(jnp.asarray(kappa)), disc.system.rhs(kappa, f)
    # a concrete array K_adj in unrolled mode is not read: no unhashable cache key
    with_array = solve(A, b, TruncatedCG(5, adjoint_iterations=np.asarray(2)))
    np.testing.assert_array_equal(with_array.x, solve(A, b, TruncatedCG(5)).x)
    # a count beyond the loops' int32 is refused, not wrapped to a few iterations
    for solver in (lambda: TruncatedCG(2**32 + 3, gradient="implicit"),
                   lambda: ConvergedCG(max_iterations=2**31)):
        with pytest.raises(pf.SolverConfigError, match="expected an integer <= 2147483647"):
            solver()
    # a zero nullspace vector is named as such (inside the program it is traced)
    with pytest.raises(pf.SolverConfigError, match="nullspace: expected a finite, non-zero"):
        solve(A, b, ConvergedCG(), nullspace=np.zeros(disc.n_free))
    # a preconditioner with a Python number runs op by op: M = I / 4, so CG's iterates are
    # Jacobi-free CG's (a scaled identity does not change them)
    swept = solve(A, b, ConvergedCG(rtol=1e-10, preconditioner=_Sweeps(2)))
    plain = solve(A, b, ConvergedCG(rtol=1e-10, preconditioner="identity"))
    assert int(swept.iterations) == int(plain.iterations)
    np.testing.assert_allclose(swept.x, plain.x, rtol=1e-9)


def test_an_eager_system_solve_assembles_in_one_program_and_solves_in_another(
        backend_compiles):
    disc = pf.discretize(pf.unit_square(14), element="P1", kappa_space="P1",
                         dirichlet={"left": 1.0})  # a shape of its own, a lifting too
    kappa = disc.interpolate_kappa(lambda x: 1.0 + x[0] * x[1])
    f = disc.interpolate(lambda x: np.sin(3 * x[0]))
    assert disc.system is not None  # built before counting
    backend_compiles.clear()
    solver = ConvergedCG(rtol=1e-11)
    eager = disc.system.solve(kappa, f, solver)
    assert backend_compiles == ["jit(_assembled)", "jit(_compiled_solve)"]  # 52 op by op
    traced = jax.jit(lambda kappa, f: disc.system.solve(kappa, f, solver))(kappa, f)
    np.testing.assert_allclose(eager.x, traced.x, rtol=1e-13, atol=0)
    np.testing.assert_allclose(eager.x, exact(disc, kappa, f), rtol=1e-9)


# unrolled with a scan length: K traced below a static bound, one program per bound


def _scan_length_loss(disc, f, w, k, scan_length, checkpoint=False):
    """w . x_K(kappa) and its solution, unrolled (static K when scan_length is None)."""
    system = disc.system

    def loss(kappa):
        solver = TruncatedCG(k, gradient="unrolled", scan_length=scan_length,
                             checkpoint=checkpoint)
        sol = solve(system.operator(kappa), system.rhs(kappa, f), solver)
        return w @ sol.x, sol

    return loss


@functools.cache
def _static_scan(k):
    """``jit((kappa, system, f, w) -> ((w . x_K, Solution), dJ/dkappa))`` of the static K-step
    scan, the problem an argument: kept for the module, the scan-length tests share it."""
    def loss(kappa, system, f, w):
        sol = solve(system.operator(kappa), system.rhs(kappa, f),
                    TruncatedCG(k, gradient="unrolled"))
        return w @ sol.x, sol

    return jax.jit(jax.value_and_grad(loss, has_aux=True))


def test_scan_length_gives_the_k_iteration_map_and_its_gradient(small_problem):
    disc, kappa, f = small_problem
    kappa = jnp.asarray(kappa)
    w = jnp.cos(jnp.arange(disc.n_free))
    # one bounded program (K traced) serves every K; each static K is a program of its own
    traces = []

    @jax.jit
    def bounded(kappa, k):
        traces.append(k)
        return jax.value_and_grad(_scan_length_loss(disc, f, w, k, 16), has_aux=True)(kappa)

    for k in (0, 9, 16):  # none, some and all of the bounded scan's iterations
        if k:
            (value, sol), grad = _static_scan(k)(kappa, disc.system, f, w)
            x, iterations, history = sol.x, int(sol.iterations), sol.residual_history
        else:  # the 0-iteration map is x0 = 0 whatever kappa, its history ||b|| alone
            value, x, grad, iterations = 0.0, np.zeros(disc.n_free), np.zeros(kappa.shape), 0
            history = np.linalg.norm(disc.system.rhs(kappa, f))[None]
        (value_b, sol_b), grad_b = bounded(kappa, k)
        np.testing.assert_allclose(sol_b.x, x, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(grad_b, grad, rtol=1e-11, atol=1e-14 * np.abs(grad).max())
        assert float(value_b) == pytest.approx(float(value), rel=1e-13)
        assert int(sol_b.iterations) == iterations == k
        assert float(sol_b.residual_norm) == pytest.approx(float(history[-1]), rel=1e-13)
        # the history: k + 1 norms, then the final one repeated to scan_length + 1 entries
        assert sol_b.residual_history.shape == (17,)
        np.testing.assert_allclose(sol_b.residual_history[:k + 1], history, rtol=1e-13)
        np.testing.assert_array_equal(sol_b.residual_history[k:],
                                      sol_b.residual_history[k] * np.ones(17 - k))
    assert len(traces) == 1  # every K up to the scan length, the bound itself included


@pytest.mark.slow  # test_scan_length_gives_the_k_iteration_map_and_its_gradient counts its traces
def test_scan_length_traces_once_for_every_k_below_it(small_problem):
    disc, kappa, f = small_problem
    w = jnp.sin(jnp.arange(disc.n_free))
    traces = []

    @jax.jit
    def value(kappa, k):
        traces.append(k)
        return _scan_length_loss(disc, f, w, k, 32)(kappa)[0]

    for k in (3, 10, 32):
        assert float(value(jnp.asarray(kappa), k)) == pytest.approx(
            float(_scan_length_loss(disc, f, w, k, None)(jnp.asarray(kappa))[0]), rel=1e-13)
    assert len(traces) == 1


# test_scan_length_gives_the_k_iteration_map_and_its_gradient pins this gradient to the static
# scan's, which test_unrolled_gradient_passes_taylor_test checks
@pytest.mark.slow
def test_scan_length_passes_the_taylor_test(small_problem):
    disc, kappa, f = small_problem
    w = jnp.cos(jnp.arange(disc.n_free))
    loss = _scan_length_loss(disc, f, w, jnp.asarray(6), 16)
    fn = jax.jit(lambda kappa: loss(kappa)[0])
    result = pf.taylor_test(fn, jnp.asarray(kappa), h0=1e-2)
    assert result.passed(), result.rates


def test_scan_length_with_checkpoints_jvp_and_vmap(small_problem):
    """The scan-length map under checkpointed segments, forward mode and a batch (each
    jitted: one compile apiece; the static scan's is the test above's)."""
    disc, kappa, f = small_problem
    kappa = jnp.asarray(kappa)
    w = jnp.cos(jnp.arange(disc.n_free))
    k = jnp.asarray(9)
    static = _static_scan(9)
    bounded = _scan_length_loss(disc, f, w, k, 16)
    checkpointed = _scan_length_loss(disc, f, w, k, 16, checkpoint=True)
    plain = static(kappa, disc.system, f, w)[1]
    np.testing.assert_allclose(jax.jit(jax.grad(lambda c: checkpointed(c)[0]))(kappa), plain,
                               rtol=1e-11, atol=1e-14 * np.abs(plain).max())
    direction = jnp.asarray(np.random.default_rng(3).normal(size=kappa.shape))
    _, tangent = jax.jit(lambda c, d: jax.jvp(lambda x: bounded(x)[0], (c,), (d,)))(
        kappa, direction)
    assert float(tangent) == pytest.approx(float(plain @ direction), rel=1e-11)
    system = disc.system
    operator = system.operator(kappa)
    sources = jnp.stack([jnp.asarray(f) * s for s in (0.5, 2.0)])

    def solved(src, solver):
        return solve(operator, system.rhs(kappa, src), solver).x

    batched = jax.jit(jax.vmap(lambda src: solved(src, TruncatedCG(
        k, gradient="unrolled", scan_length=16))))(sources)
    for i, src in enumerate(sources):
        single = static(kappa, system, src, w)[0][1].x
        np.testing.assert_allclose(batched[i], single, rtol=1e-13, atol=1e-15)


def test_a_traced_k_beyond_the_scan_length_runs_the_scan_length(small_problem):
    disc, kappa, f = small_problem
    system = disc.system
    run = jax.jit(lambda k: solve(system.operator(kappa), system.rhs(kappa, f), TruncatedCG(
        k, gradient="unrolled", scan_length=4)))
    sol = run(9)
    assert int(sol.iterations) == 4
    reference = solve(system.operator(kappa), system.rhs(kappa, f), TruncatedCG(4))
    np.testing.assert_allclose(sol.x, reference.x, rtol=1e-13)


def test_scan_length_options_are_checked():
    with pytest.raises(pf.SolverConfigError, match="K <= scan_length"):
        TruncatedCG(20, gradient="unrolled", scan_length=16)
    with pytest.raises(pf.SolverConfigError, match="a scan length is for gradient='unrolled'"):
        TruncatedCG(5, gradient="implicit", scan_length=16)
    with pytest.raises(pf.SolverConfigError, match="scan_length"):
        TruncatedCG(5, gradient="unrolled", scan_length=-1)
    assert [pf.linalg.unrolled_length(k) for k in (0, 16, 17, 100)] == [16, 16, 32, 128]
    assert pf.linalg.unrolled_length(3, smallest=1) == 4


# ------------------------------------------------------------------------------------------
# vmap: a batch of right-hand sides
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", [pytest.param("unrolled", marks=pytest.mark.slow), "implicit"])
def test_vmap_over_sources_matches_loop(small_problem, mode):
    disc, kappa, f = small_problem
    system = disc.system
    op = system.operator(jnp.asarray(kappa))
    sources = jnp.stack([jnp.asarray(f) * s for s in (0.5, 1.0, 2.0)])
    solver = TruncatedCG(7, gradient=mode)
    # jitted: one program each way (op by op, the batch compiled some 60 small ones)
    single = jax.jit(lambda src: solve(op, system.rhs(kappa, src), solver).x)
    batched = jax.jit(jax.vmap(single))(sources)
    for i, src in enumerate(sources):
        np.testing.assert_allclose(batched[i], single(src), rtol=1e-12)


# ------------------------------------------------------------------------------------------
# scale, options and the Taylor utility itself
# ------------------------------------------------------------------------------------------


#: right-hand side scales, powers of two (so that b * s is exact): squares normal (about 1e-150,
#: 1e150), subnormal or zero (1e-170, 1e-301: b.b froze CG at x = 0) and infinite (1e200,
#: 1e300: the tolerance became NaN and the loop stopped at once, reporting success)
RHS_SCALES = tuple(2.0 ** e for e in (-500, -565, -1000, 500, 665, 997))


def test_the_scaled_norm_is_the_plain_norm_bit_for_bit_where_that_one_is_finite():
    """CG normalises its residual by ``2^e ||2^-e v||``: where ``v.v`` neither under- nor
    overflows this is ``||v||`` to the last bit, so no iterate moves (a norm rounded otherwise
    sent a fragile inversion down another path); beyond, it is finite and accurate where the
    plain norm gives 0 or inf, up to the largest float64, eagerly and under jit."""
    from prdp_fem.linalg.cg import _norm, _robust_norm

    v = jnp.asarray(np.random.default_rng(0).standard_normal(1000))
    for norm in (_robust_norm, jax.jit(_robust_norm)):
        for scale in (1e-140, 1e-3, 1.0, 7.3e4, 1e140):
            assert float(norm(v * scale)) == float(_norm(v * scale)), scale
        reference = float(_norm(v))
        for scale in (2.0 ** -600, 2.0 ** 600, 2.0 ** 1022):  # max |v| 2^1023.8
            plain, robust = float(_norm(v * scale)), float(norm(v * scale))
            assert plain in (0.0, np.inf)
            assert robust == pytest.approx(reference * scale, rel=1e-15)


@pytest.mark.parametrize("solver", [
    TruncatedCG(20, gradient="unrolled"),  # below convergence: a smooth map of b
    TruncatedCG(20, gradient="implicit"),
    TruncatedCG(2000, gradient="unrolled"),  # frozen at round-off: the implicit solution map
    ConvergedCG(rtol=1e-10),
    # the slow twin of "implicit": the same while loop, without Jacobi's scaling
    pytest.param(TruncatedCG(20, preconditioner="identity", gradient="implicit"),
                 marks=pytest.mark.slow),
], ids=["unrolled", "implicit", "unrolled-far", "converged", "identity"])
def test_rhs_of_any_scale_scales_x_and_keeps_the_gradient(small_problem, solver):
    """CG is homogeneous in b: b * s gives x * s, with the same status and iterations, and
    the gradient of x / s is that of the unscaled solve, for s from 1e-300 to 1e300."""
    disc, kappa, f = small_problem
    system = disc.system
    b = system.rhs(jnp.asarray(kappa), jnp.asarray(f))
    op = system.operator(jnp.asarray(kappa))
    weights = jnp.asarray(np.random.default_rng(0).standard_normal(b.shape))

    def loss(values, b, scale):
        scaled = solve(op.with_values(values), b * scale, solver)
        return jnp.vdot(weights, scaled.x) / scale, scaled

    # one compile for every scale (an argument); its solve is checked too, the jitted one
    # beside the eager one (XLA may reassociate under jit)
    gradient = jax.jit(jax.grad(loss, has_aux=True))
    sol = solve(op, b, solver)
    reference, _ = gradient(op.values, b, 1.0)
    for scale in RHS_SCALES:
        g, jitted = gradient(op.values, b, scale)
        for scaled in (solve(op, b * scale, solver), jitted):
            np.testing.assert_allclose(scaled.x / scale, sol.x, rtol=1e-10,
                                       err_msg=f"x at scale {scale:g}")
            assert (int(scaled.status), int(scaled.iterations)) == \
                (int(sol.status), int(sol.iterations)), scale
        np.testing.assert_allclose(g, reference, rtol=1e-8,
                                   atol=1e-12 * abs(reference).max(),
                                   err_msg=f"gradient at scale {scale:g}")


def test_a_tolerance_not_met_is_reported_at_any_scale(small_problem):
    """At 1e-300 rtol ||b|| flushed to 0 under jit: the loop ran to stagnation and a solve
    cut short by max_iterations reported success."""
    disc, kappa, f = small_problem
    system = disc.system
    b = system.rhs(jnp.asarray(kappa), jnp.asarray(f))
    op = system.operator(jnp.asarray(kappa))
    short = jax.jit(lambda b: solve(op, b, ConvergedCG(rtol=1e-10, max_iterations=10)))
    for scale in (1.0, 2.0 ** -997, 2.0 ** 997):
        assert int(short(b * scale).status) == pf.Status.NOT_CONVERGED, scale


def test_preconditioner_and_counts_are_validated():
    with pytest.raises(pf.SolverConfigError, match="a plain function is not a pytree"):
        TruncatedCG(5, preconditioner=lambda r: r)
    with pytest.raises(pf.SolverConfigError, match=r"iterations=.*-3.*expected an integer >= 0"):
        TruncatedCG(np.int64(-3))
    with pytest.raises(pf.SolverConfigError, match=r"max_iterations=.*-1"):
        ConvergedCG(max_iterations=np.int64(-1))
    assert TruncatedCG(np.int64(4)).iterations == 4
    assert TruncatedCG(np.array(4), gradient="implicit").iterations == 4


def test_custom_preconditioner_pytree_in_both_modes(small_problem):
    disc, kappa, f = small_problem
    op = disc.system.operator(jnp.asarray(kappa))
    custom = pf.linalg.JacobiPreconditioner(1.0 / pf.linalg.diagonal(op))
    b = disc.system.rhs(jnp.asarray(kappa), jnp.asarray(f))
    for mode in ("unrolled", "implicit"):
        a = solve(op, b, TruncatedCG(9, preconditioner=custom, gradient=mode)).x
        ref = solve(op, b, TruncatedCG(9, preconditioner="jacobi", gradient=mode)).x
        np.testing.assert_allclose(a, ref, rtol=1e-12)


def test_taylor_test_accepts_exact_gradient_of_a_linear_map(small_problem):
    disc, kappa, _ = small_problem
    system = disc.system
    op = system.operator(jnp.asarray(kappa))

    def linear_in_f(f):  # x = A^{-1} S f is linear in f (no Dirichlet lifting in the loss)
        return jnp.sum(solve(op, system.rhs(kappa, f) - system.rhs(kappa),
                             TruncatedCG(400, gradient="implicit")).x)

    # the gradient jitted: one program (a grad of the jitted function compiled two)
    result = pf.taylor_test(jax.jit(linear_in_f), jnp.ones(disc.n_dofs),
                            gradient=jax.jit(jax.grad(linear_in_f))(jnp.ones(disc.n_dofs)))
    assert result.passed()
    assert not pf.taylor_test(jax.jit(linear_in_f), jnp.ones(disc.n_dofs),
                              gradient=jnp.zeros(disc.n_dofs)).passed()


# ------------------------------------------------------------------------------------------
# Jacobi runs as CG on S A S (S = M^1/2): the same map as PCG with z = M r
# ------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _DiagonalAsGeneral:
    """``z = M r`` with a diagonal ``M``, but not a JacobiPreconditioner: the general PCG path."""

    inverse_diagonal: jax.Array

    def __call__(self, r):
        return self.inverse_diagonal * r


@pytest.mark.parametrize("mode", ["unrolled", "implicit"])
def test_scaled_jacobi_equals_pcg_with_z_equal_M_r(small_problem, mode):
    disc, kappa, f = small_problem
    system = disc.system
    inverse_diagonal = pf.linalg.jacobi(system.operator(jnp.asarray(kappa))).inverse_diagonal
    b = system.rhs(jnp.asarray(kappa), jnp.asarray(f))

    # K traced (below a scan length in unrolled mode, the static scan's map: the scan-length
    # tests check that): one program per preconditioner serves both counts
    scan_length = 16 if mode == "unrolled" else None

    def loss(values, preconditioner, K):
        op = system.operator(jnp.asarray(kappa)).with_values(values)
        x = solve(op, b, TruncatedCG(K, preconditioner, gradient=mode,
                                     scan_length=scan_length)).x
        return jnp.sum(x * jnp.cos(jnp.arange(x.size)))

    values = system.operator(jnp.asarray(kappa)).values
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    scaled, general = pf.linalg.JacobiPreconditioner(inverse_diagonal), \
        _DiagonalAsGeneral(inverse_diagonal)
    for K in (1, 12):
        (value, grad), (reference, reference_grad) = (value_and_grad(values, scaled, K),
                                                      value_and_grad(values, general, K))
        np.testing.assert_allclose(value, reference, rtol=1e-12)
        np.testing.assert_allclose(grad, reference_grad, rtol=1e-9, atol=1e-13)


# ------------------------------------------------------------------------------------------
# with a preconditioner to apply, the while loops precondition at the top of an iteration
# ------------------------------------------------------------------------------------------


# K = 4 with the slow cases: K = 1 and 17 bracket it; AMG at K = 1 and 17 too: the diagonal
# cases keep those counts through the same loop, and AMG's past case runs every iteration of it
@pytest.mark.parametrize(("k", "preconditioner"), [
    (0, "diagonal"), (0, "amg"), (1, "diagonal"), pytest.param(1, "amg", marks=pytest.mark.slow),
    pytest.param(4, "diagonal", marks=pytest.mark.slow),
    pytest.param(4, "amg", marks=pytest.mark.slow),
    (17, "diagonal"), pytest.param(17, "amg", marks=pytest.mark.slow),
    ("past", "diagonal"), ("past", "amg")])
def test_preconditioned_while_loops_take_the_scans_iterations(small_problem, preconditioner,
                                                              k):
    # implicit mode's loop preconditions the residual it starts from; the unrolled scan
    # preconditions the residual it ends with: the same iterates, iterations and freeze
    disc, kappa, f = small_problem
    op = disc.system.operator(jnp.asarray(kappa))
    b = disc.system.rhs(jnp.asarray(kappa), jnp.asarray(f))
    precond = _DiagonalAsGeneral(1.0 / pf.linalg.diagonal(op)) if preconditioner == "diagonal" \
        else pf.amg_preconditioner(op)
    k = 10 * disc.n_free if k == "past" else k
    unrolled, implicit = (solve(op, b, TruncatedCG(k, precond, gradient=mode))
                          for mode in ("unrolled", "implicit"))
    scale = float(jnp.abs(unrolled.x).max())
    np.testing.assert_allclose(implicit.x, unrolled.x, rtol=1e-13, atol=1e-15 * scale)
    assert int(implicit.iterations) == int(unrolled.iterations)
    if k > disc.n_free:  # frozen after convergence, in both, at the same iteration
        assert int(implicit.iterations) < disc.n_free
        np.testing.assert_allclose(implicit.x, exact(disc, kappa, f), rtol=1e-12,
                                   atol=1e-12 * scale)


def test_a_truncated_solve_applies_the_preconditioner_once_per_iteration(small_problem):
    # K iterations need z_0 .. z_{K-1}: a solve that also formed z_K (or z_0 before its loop)
    # ran one V-cycle more, and its program held one more inlined copy of it
    disc, kappa, f = small_problem
    op = disc.system.operator(jnp.asarray(kappa))
    b = disc.system.rhs(jnp.asarray(kappa), jnp.asarray(f))
    applications, traces = [], []

    @jax.tree_util.register_dataclass
    @dataclasses.dataclass(frozen=True)
    class Counted:
        inverse_diagonal: jax.Array

        def __call__(self, r):
            traces.append(1)
            jax.debug.callback(lambda: applications.append(1), ordered=True)
            return self.inverse_diagonal * r

    precond = Counted(1.0 / pf.linalg.diagonal(op))
    for K in (1, 7):
        applications.clear()
        sol = solve(op, b, TruncatedCG(K, precond, gradient="implicit"))
        assert int(sol.iterations) == K
        jax.effects_barrier()  # debug callbacks may outlast the result being ready
        assert len(applications) == K
    assert len(traces) == 1  # one program for both K, the preconditioner once in its loop
    reference = solve(op, b, TruncatedCG(7, _DiagonalAsGeneral(precond.inverse_diagonal)))
    np.testing.assert_allclose(sol.x, reference.x, rtol=1e-13)
