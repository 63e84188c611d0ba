"""Step programs compiled ahead of time: one executable per static value and argument types,
its compile time counted apart, and nothing shared between callers but the executable
(results, constants and iteration tallies stay each caller's own)."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import prdp_fem as pf
from prdp_fem import _executables as executables
from prdp_fem._executables import SharedCompile, kept_programs
from prdp_fem.fem import full_field
from prdp_fem.inverse import Validation, fixed, inverse_problem, invert, prdp
from prdp_fem.inverse import driver as inverse
from prdp_fem.linalg import IterationCounter, TruncatedCG, solve
from prdp_fem.linalg import _tally as tally


@pytest.fixture(scope="module")
def source_problem():
    disc = pf.discretize(pf.unit_square(10), element="P1", dirichlet=0.0)
    data = disc.project(lambda x: np.sin(np.pi * x[0]) * np.sin(np.pi * x[1]) / 20)
    return inverse_problem(disc, full_field(disc, data=data), unknown="source", alpha=1e-4,
                           regularization="l2")


def test_one_executable_per_static_value_and_shape_and_the_compile_time_counted():
    scale = SharedCompile(lambda x, n: x * n, static_argnum=1)
    x = jnp.arange(3.0)
    assert scale.seconds == 0.0
    assert np.array_equal(scale(x, 2), [0.0, 2.0, 4.0])
    compiled = scale.seconds
    assert compiled > 0.0
    assert np.array_equal(scale(x + 1, 2), [2.0, 4.0, 6.0]) and len(scale._cache) == 1
    assert scale.seconds == compiled  # a run adds no compile time
    assert np.array_equal(scale(x, 3), [0.0, 3.0, 6.0]) and len(scale._cache) == 2  # new K
    assert np.array_equal(scale(jnp.arange(4.0), 2), [0.0, 2.0, 4.0, 6.0])  # new shape
    assert len(scale._cache) == 3 and scale.seconds > compiled


def test_a_weakly_typed_scalar_takes_the_executable_of_its_strong_type():
    add = SharedCompile(lambda x, y: x + y)
    assert float(add(jnp.float64(1.0), jnp.float64(2.0))) == 3.0
    assert float(add(jnp.asarray(1.0), jnp.float64(4.0))) == 5.0  # weak: the same program
    assert len(add._cache) == 1


def test_a_shared_compile_keeps_its_most_recent_executables_only():
    scale = SharedCompile(lambda x: x * 2.0)
    for size in range(1, executables._ENTRY_LIMIT + 4):   # a sweep of shapes
        assert np.array_equal(scale(jnp.ones(size)), np.full(size, 2.0))
    assert len(scale._cache) == executables._ENTRY_LIMIT
    assert np.array_equal(scale(jnp.ones(1)), [2.0])      # dropped, compiled again
    assert len(scale._cache) == executables._ENTRY_LIMIT


def test_programs_with_other_host_callbacks_keep_their_own_state():
    seen_first, seen_second = [], []

    def logging_to(seen):
        return SharedCompile(lambda x: jax.debug.callback(seen.append, x) or x * 2)

    first, second = logging_to(seen_first), logging_to(seen_second)
    jax.block_until_ready(first(jnp.float64(1.0)))
    jax.block_until_ready(second(jnp.float64(2.0)))
    jax.effects_barrier()
    assert [float(v) for v in seen_first] == [1.0] and [float(v) for v in seen_second] == [2.0]


def test_primal_and_adjoint_taps_count_apart():
    def tapping(kind):
        return SharedCompile(lambda counter, k: (tally.tap(counter, kind, k, jnp.ones(2)), k)[1])

    primal, adjoint = IterationCounter(), IterationCounter()
    jax.block_until_ready(tapping("primal")(primal, jnp.int32(5)))
    jax.block_until_ready(tapping("adjoint")(adjoint, jnp.int32(5)))
    jax.effects_barrier()
    assert primal.snapshot() == (5, 0) and adjoint.snapshot() == (0, 5)


def test_a_solve_counts_into_each_callers_counter():
    disc = pf.discretize(pf.unit_square(6), element="P1", dirichlet=0.0)
    A, b = disc.system.operator(jnp.ones(disc.n_kappa)), jnp.ones(disc.n_free)
    program = SharedCompile(lambda counter, b: solve(A, b, TruncatedCG(3), counter=counter).x)
    one, two = IterationCounter(), IterationCounter()
    jax.block_until_ready(program(one, b))
    jax.block_until_ready(program(two, b))
    jax.block_until_ready(program(two, 2 * b))
    jax.effects_barrier()
    assert len(program._cache) == 1  # the counter is an argument: one executable
    assert one.snapshot() == (3, 0) and two.snapshot() == (6, 0)


def test_empty_and_unread_arguments_and_python_scalars_pass():
    def program(x, empty, unread, k):
        return x * k, empty * 2.0, empty.sum() + x[0]

    compiled = SharedCompile(program)
    x = jnp.arange(3.0)
    scaled, doubled, first_entry = compiled(x, jnp.zeros((0, 4)), jnp.ones(5), 2)
    assert np.array_equal(scaled, [0.0, 2.0, 4.0]) and float(first_entry) == 0.0
    assert doubled.shape == (0, 4) and doubled.dtype == jnp.float64
    assert np.array_equal(compiled(x, jnp.zeros((0, 4)), jnp.zeros(5), 3)[0], [0.0, 3.0, 6.0])
    assert len(compiled._cache) == 1


def test_a_nan_check_reports_as_jax_jit_does():
    counter = IterationCounter()

    def tapped_log(counter, x):
        tally.tap(counter, "primal", jnp.int32(1), x)
        return jnp.log(x)

    for program in (SharedCompile(tapped_log), SharedCompile(lambda c, x: jnp.log(x))):
        program(counter, jnp.ones(2))
        with jax.debug_nans(True), pytest.raises(FloatingPointError):
            program(counter, -jnp.ones(2))


def _tallies(inversion):
    return [(r.primal_iterations, r.adjoint_iterations_total, r.evaluations,
             r.validation_iterations) for r in inversion.history]


@pytest.mark.parametrize("monitor", ["loss", pytest.param(Validation(every=2, rtol=1e-10),
                                                   marks=pytest.mark.slow)])
def test_inversions_of_one_program_compile_once_and_keep_their_own_tallies(
        source_problem, monitor, backend_compiles):
    def run(refinement):
        return invert(source_problem, refinement=refinement, steps=4, monitor=monitor)

    inverse._step_program.cache_clear()  # no step kept from an earlier test
    inverse._validation_program.cache_clear()
    first = run(fixed(4))
    compiled = len(backend_compiles)
    assert compiled >= 1
    second, third = run(prdp(K0=4, dK=4)), run(fixed(6))
    # K is an argument: the same step for every controller and K
    assert len(backend_compiles) == compiled, backend_compiles[compiled:]
    assert second.history[-1].compile_time == 0.0 and first.history[-1].compile_time > 0.0
    assert _tallies(first) == _tallies(second)  # prdp does not refine in 4 steps
    inverse._step_program.cache_clear()
    inverse._validation_program.cache_clear()
    alone = run(fixed(6))  # compiled for itself
    assert _tallies(third) == _tallies(alone)
    np.testing.assert_array_equal(third.params, alone.params)
    assert _tallies(third)[-1][0] > _tallies(first)[-1][0] > 0
    if isinstance(monitor, Validation):
        assert first.history[-1].validation_iterations > 0


def test_a_typed_prng_key_in_the_state_passes(source_problem):
    """optax.noisy_sgd keeps a typed PRNG key in its state."""
    def keyed(counter, x, key):
        tally.tap(counter, "primal", jnp.int32(2), x)
        return x + jax.random.uniform(key, x.shape)

    program, counter, x = SharedCompile(keyed), IterationCounter(), jnp.zeros(3)
    key = jax.random.key(7)
    np.testing.assert_array_equal(program(counter, x, key), jax.random.uniform(key, (3,)))
    jax.effects_barrier()
    assert counter.primal == 2
    noisy = invert(source_problem, optimizer=optax.noisy_sgd(1e-2, key=0), refinement=fixed(4),
                   steps=3)
    assert _tallies(noisy)[-1][2] == 3


def test_kept_programs_keep_one_program_per_hashable_setting():
    built = []

    def build(*settings):
        built.append(settings)
        return SharedCompile(lambda x: x)

    program = kept_programs(build, size=2)
    first = program("adam", "implicit")
    assert program("adam", "implicit") is first and len(built) == 1
    assert program("adam", "implicit", keep=False) is not first  # e.g. a preconditioner object
    assert program(["not", "hashable"], "implicit") is not program(["not", "hashable"], "implicit")
    program("b", 1), program("c", 2)  # the oldest falls out beyond size
    assert program("adam", "implicit") is not first
    program.cache_clear()
    assert len(built) == 7
