"""The iteration tally counts what ran, under every transformation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prdp_fem as pf
from prdp_fem.linalg import (
    ConvergedCG,
    IterationCounter,
    ReverseTally,
    TruncatedCG,
    TruncatedJacobi,
    read_counts,
    solve,
    zero_counts,
)
from prdp_fem.linalg import _tally as tally


@pytest.fixture(scope="module")
def system():
    """(A, b, B): a small P1 system and three right-hand sides."""
    disc = pf.discretize(pf.unit_square(10), element="P1", dirichlet=0.0)
    kappa = jnp.asarray(disc.interpolate_kappa(lambda x: 1.0 + x[0]))
    f = jnp.asarray(disc.interpolate(lambda x: np.sin(3 * x[0]) + x[1]))
    b = disc.system.rhs(kappa, f)
    B = jnp.stack([b, 2 * b + 0.1, jnp.cos(jnp.arange(b.size, dtype=b.dtype))])
    return disc.system.operator(kappa), b, B


def _counted(counter):
    jax.effects_barrier()
    return counter.snapshot(), counter.primal_solves, counter.adjoint_solves


# --- eager, jit, loops ------------------------------------------------------------------


def test_eager_solve_counts_what_ran(system):
    A, b, _ = system
    counter = IterationCounter()
    sol = solve(A, b, ConvergedCG(rtol=1e-10), counter=counter)
    assert _counted(counter) == ((int(sol.iterations), 0), 1, 0)
    assert int(sol.iterations) > 5


def test_a_loop_of_unknown_length_counts_every_trip(system):
    A, b, _ = system
    counter = IterationCounter()

    @jax.jit
    def trips(n):
        return jax.lax.fori_loop(
            0, n, lambda i, x: solve(A, b + x[0], TruncatedCG(4), counter=counter).x,
            jnp.zeros_like(b))

    jax.block_until_ready(trips(jnp.int32(5)))
    assert _counted(counter) == ((20, 0), 5, 0)


# --- grad (implicit and unrolled) -------------------------------------------------------


@pytest.mark.parametrize("solver, adjoint", [
    (TruncatedCG(7, gradient="implicit", adjoint_iterations=3), 3),
    (TruncatedCG(5, gradient="unrolled"), 5),
])
def test_grad_counts_the_primal_and_the_backward_solve(system, solver, adjoint):
    A, b, _ = system
    counter = IterationCounter()
    loss = jax.jit(jax.grad(lambda b: jnp.sum(solve(A, b, solver, counter=counter).x ** 2)))
    jax.block_until_ready(loss(b))
    assert _counted(counter) == ((solver.iterations, adjoint), 1, 1)


# --- vmap -------------------------------------------------------------------------------


def test_vmap_counts_every_member_in_one_host_call(system):
    A, _, B = system
    counter = IterationCounter()
    solver = ConvergedCG(rtol=1e-10)
    sols = jax.jit(jax.vmap(lambda b: solve(A, b, solver, counter=counter)))(B)
    assert _counted(counter) == ((int(jnp.sum(sols.iterations)), 0), 3, 0)
    nested = IterationCounter()
    twice = jax.jit(jax.vmap(jax.vmap(lambda b: solve(A, b, TruncatedCG(2), counter=nested).x)))
    jax.block_until_ready(twice(jnp.stack([B, B])))
    assert _counted(nested) == ((12, 0), 6, 0)


# --- a counter as an argument -----------------------------------------------------------


def test_counters_passed_as_arguments_share_one_program_and_keep_their_tallies(system):
    A, b, _ = system
    run = jax.jit(lambda counter, b: solve(A, b, TruncatedCG(4), counter=counter).x)
    one, two = IterationCounter(), IterationCounter()
    jax.block_until_ready(run(one, b))
    jax.block_until_ready(run(two, b))
    jax.block_until_ready(run(two, 2 * b))
    assert run._cache_size() == 1  # the slot is traced: one program for every counter
    assert _counted(one) == ((4, 0), 1, 0) and _counted(two) == ((8, 0), 2, 0)


def test_a_tap_for_a_counter_that_is_gone_adds_nowhere():
    counter = IterationCounter()
    slot = int(counter.slot)
    del counter
    tally._tally("primal", slot, 5, 1)  # no error: nothing left to add to
    assert slot not in tally._LIVE


def test_a_vmap_over_a_stack_of_counters_counts_into_each(system):
    A, _, B = system
    counters = [IterationCounter() for _ in range(2)]
    stacked = jax.tree_util.tree_map(lambda *slots: jnp.stack(slots), *counters)
    run = jax.jit(jax.vmap(lambda counter, b: solve(A, b, TruncatedCG(3), counter=counter).x))
    jax.block_until_ready(run(stacked, B[:2]))
    assert [_counted(c) for c in counters] == [((3, 0), 1, 0)] * 2


# --- counts as outputs: a reverse tally ---------------------------------------------------

_SOLVERS = [
    TruncatedCG(7, "jacobi", gradient="implicit", adjoint_iterations=5),
    TruncatedCG(7, "jacobi", gradient="unrolled"),
    ConvergedCG(rtol=1e-10, preconditioner="jacobi"),
    TruncatedJacobi(6, gradient="implicit", adjoint_iterations=4),
    TruncatedJacobi(6, gradient="unrolled"),
]


def _objective(system, solver):
    """``J(theta, counter)``: a solve whose operator and right-hand side depend on theta."""
    A, b, _ = system

    def J(theta, counter):
        sol = solve(A.with_values(A.values * jnp.exp(theta)), b * (1 + theta), solver,
                    counter=counter)
        return jnp.sum(sol.x ** 2)

    return J


# ConvergedCG with the slow cases: it taps the counts on TruncatedCG's implicit path
@pytest.mark.parametrize("solver", [pytest.param(s, marks=pytest.mark.slow)
                                    if isinstance(s, ConvergedCG) else s for s in _SOLVERS],
                         ids=lambda s: f"{type(s).__name__}-{getattr(s, 'gradient', 'converged')}")
def test_a_reverse_tally_returns_what_the_host_counter_hears(system, solver):
    """The same value, gradient and counts (primal, adjoint, solves) as outputs, no host
    call in the program."""
    J = _objective(system, solver)
    host = IterationCounter()
    value, grad = jax.jit(jax.value_and_grad(lambda t: J(t, host)))(0.3)
    counted = jax.jit(jax.value_and_grad(lambda t, seed: J(t, ReverseTally(seed)),
                                         argnums=(0, 1)))
    value_r, (grad_r, counts) = counted(0.3, zero_counts())
    assert float(value_r) == float(value) and float(grad_r) == float(grad)
    (primal, adjoint), primal_solves, adjoint_solves = _counted(host)
    assert read_counts(counts) == dict(primal=primal, adjoint=adjoint,
                                       primal_solves=primal_solves,
                                       adjoint_solves=adjoint_solves)
    assert primal > 0 and adjoint > 0 and primal_solves == adjoint_solves == 1
    program = counted.lower(0.3, zero_counts()).compile().as_text()
    assert "custom-call(" not in program  # no host callback: JAX's fast dispatch


def test_a_reverse_tally_counts_every_member_under_vmap(system):
    J = _objective(system, _SOLVERS[0])
    host = IterationCounter()
    thetas = jnp.asarray([0.1, 0.2, 0.3])
    jax.jit(jax.vmap(jax.grad(lambda t: J(t, host))))(thetas)
    _, (_, counts) = jax.jit(jax.vmap(
        jax.value_and_grad(lambda t, seed: J(t, ReverseTally(seed)), argnums=(0, 1)),
        (0, None)))(thetas, zero_counts())
    (primal, adjoint), primal_solves, adjoint_solves = _counted(host)
    assert read_counts(counts.sum(axis=0)) == dict(
        primal=primal, adjoint=adjoint, primal_solves=primal_solves,
        adjoint_solves=adjoint_solves)
    assert primal_solves == 3


@pytest.mark.parametrize("solver", [
    _SOLVERS[0],
    # 5 s (a second-order scan); the primal tap's identity is the same in every mode
    pytest.param(_SOLVERS[1], marks=pytest.mark.slow),
    pytest.param(_SOLVERS[2], marks=pytest.mark.slow)], ids=["implicit", "unrolled", "converged"])
def test_a_reverse_tally_whose_seed_is_held_constant_differentiates_as_none(system, solver):
    """Differentiated in theta alone (the seed a constant), first and second order (forward
    over reverse) give the derivatives without a tally."""
    J = _objective(system, solver)

    @jax.jit
    def derivatives(theta, counter):
        first = jax.grad(lambda t: J(t, counter))
        return first(theta), jax.jvp(first, (theta,), (1.0,))[1]

    tallied = derivatives(0.3, ReverseTally(zero_counts()))
    assert [float(v) for v in tallied] == [float(v) for v in derivatives(0.3, None)]
    assert float(tallied[1]) != 0.0
