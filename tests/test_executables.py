"""Executables shared within a process: equal programs compile once, and nothing else is
shared (results, constants and iteration tallies stay each caller's own)."""

import os
import subprocess
import sys
from collections import OrderedDict
from types import SimpleNamespace
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import prdp_fem as pf
from prdp_fem import executables, inverse, tally
from prdp_fem.cg import IterationCounter, TruncatedCG, solve
from prdp_fem.executables import SharedCompile
from prdp_fem.inverse import Validation, inverse_problem, invert
from prdp_fem.observations import full_field
from prdp_fem.prdp import fixed, prdp


@pytest.fixture(scope="module")
def source_problem():
    disc = pf.discretize(pf.unit_square(10), element="P1", dirichlet=0.0)
    data = disc.project(lambda x: np.sin(np.pi * x[0]) * np.sin(np.pi * x[1]) / 20)
    return inverse_problem(disc, full_field(disc, data=data), unknown="source", alpha=1e-4,
                           regularization="l2")


def test_equal_programs_share_and_different_ones_do_not():
    scale = SharedCompile(lambda x, n: x * n, static_argnum=1)
    again = SharedCompile(lambda x, n: x * n, static_argnum=1)
    shifted = SharedCompile(lambda x, n: x + n, static_argnum=1)
    x = jnp.arange(3.0)
    assert np.array_equal(scale(x, 2), [0.0, 2.0, 4.0])
    assert np.array_equal(again(x + 1, 2), [2.0, 4.0, 6.0]) and again.shared == 1
    assert np.array_equal(again(x, 3), [0.0, 3.0, 6.0]) and again.shared == 1  # new K: own
    assert np.array_equal(shifted(x, 2), [2.0, 3.0, 4.0]) and shifted.shared == 0
    assert np.array_equal(scale(jnp.arange(4.0), 2), [0.0, 2.0, 4.0, 6.0])  # new shape: own


def test_a_shared_compile_keeps_its_most_recent_executables_only():
    scale = SharedCompile(lambda x: x * 2.0)
    for size in range(1, executables._ENTRY_LIMIT + 4):   # a sweep of shapes
        assert np.array_equal(scale(jnp.ones(size)), np.full(size, 2.0))
    assert len(scale._cache) == executables._ENTRY_LIMIT
    assert np.array_equal(scale(jnp.ones(1)), [2.0])      # dropped, compiled again
    assert len(scale._cache) == executables._ENTRY_LIMIT


def test_functions_reading_different_arguments_are_different_programs():
    first = SharedCompile(lambda a, b: a * 2)
    second = SharedCompile(lambda a, b: b * 2)
    one, five = jnp.ones(3), jnp.full(3, 5.0)
    assert np.array_equal(first(one, five), [2.0] * 3)
    assert np.array_equal(second(one, five), [10.0] * 3) and second.shared == 0


def test_programs_with_other_host_callbacks_are_never_shared():
    """A callback holds Python state the text does not show (here: which list it fills)."""
    seen_first, seen_second = [], []

    def logging_to(seen):
        return SharedCompile(lambda x: jax.debug.callback(seen.append, x) or x * 2)

    first, second = logging_to(seen_first), logging_to(seen_second)
    jax.block_until_ready(first(jnp.float64(1.0)))
    jax.block_until_ready(second(jnp.float64(2.0)))
    jax.effects_barrier()
    assert [float(v) for v in seen_first] == [1.0] and [float(v) for v in seen_second] == [2.0]
    assert second.shared == 0


def test_primal_and_adjoint_taps_are_different_programs():
    def tapping(kind):
        return SharedCompile(lambda counter, k: tally.tap(counter, kind, k, jnp.ones(2)) or k)

    primal, adjoint = IterationCounter(), IterationCounter()
    jax.block_until_ready(tapping("primal")(primal, jnp.int32(5)))
    jax.block_until_ready(tapping("adjoint")(adjoint, jnp.int32(5)))
    jax.effects_barrier()
    assert primal.snapshot() == (5, 0) and adjoint.snapshot() == (0, 5)


def test_constants_are_part_of_the_program():
    first = SharedCompile(lambda x: x * np.array([1.0, 2.0]))
    second = SharedCompile(lambda x: x * jnp.array([3.0, 5.0]))
    assert np.array_equal(first(jnp.ones(2)), [1.0, 2.0])
    assert np.array_equal(second(jnp.ones(2)), [3.0, 5.0]) and second.shared == 0


def test_a_lowering_with_hidden_constants_or_of_an_unknown_shape_is_never_shared():
    """JAX may pass large constants as arguments apart from the text (its simplified-constants
    mode): the text no longer says everything, so such a program gets its own executable."""
    hidden = SimpleNamespace(_lowering=SimpleNamespace(const_args=[np.ones(3)]))
    assert executables._program_key(hidden, [], {}) is None
    assert executables._program_key(SimpleNamespace(), [], {}) is None  # a JAX that does not say
    lowered = jax.jit(lambda x: 2 * x).lower(jnp.ones(2))
    assert executables._program_key(lowered, [jnp.ones(2)], {}) is not None
    # the same text compiled with other XLA options is another executable
    classic = {"xla_cpu_use_fusion_emitters": False}
    assert executables._program_key(lowered, [jnp.ones(2)], classic) != \
        executables._program_key(lowered, [jnp.ones(2)], {})


def test_a_shared_solve_counts_into_each_callers_counter():
    disc = pf.discretize(pf.unit_square(6), element="P1", dirichlet=0.0)
    A, b = disc.system.operator(jnp.ones(disc.n_kappa)), jnp.ones(disc.n_free)

    def make():
        return SharedCompile(lambda counter, b: solve(A, b, TruncatedCG(3), counter=counter).x)

    first, second = make(), make()
    one, two = IterationCounter(), IterationCounter()
    jax.block_until_ready(first(one, b))
    jax.block_until_ready(second(two, b))
    jax.block_until_ready(second(two, 2 * b))
    jax.effects_barrier()
    assert second.shared == 1
    assert one.snapshot() == (3, 0) and two.snapshot() == (6, 0)


def _tallies(inversion):
    return [(r.primal_iterations, r.adjoint_iterations_total, r.evaluations,
             r.validation_iterations) for r in inversion.history]


@pytest.mark.parametrize("monitor", ["loss", Validation(every=2, rtol=1e-10)])
def test_inversions_of_one_program_compile_once_and_keep_their_own_tallies(
        source_problem, monitor, monkeypatch):
    def run(refinement):
        return invert(source_problem, refinement=refinement, steps=4, monitor=monitor)

    # the step (and the validation misfit); the controller updates on the host
    programs = 1 if monitor == "loss" else 2
    inverse._step_program.cache_clear()  # no step kept from an earlier test
    monkeypatch.setattr(executables, "_EXECUTABLES", OrderedDict())
    first = run(fixed(4))
    assert len(executables._EXECUTABLES) == programs
    second, third = run(prdp(K0=4, dK=4)), run(fixed(6))
    # K is an argument: the same step for every controller and K
    assert len(executables._EXECUTABLES) == programs
    assert _tallies(first) == _tallies(second)  # prdp does not refine in 4 steps
    monkeypatch.setattr(executables, "_EXECUTABLES", OrderedDict())
    inverse._step_program.cache_clear()
    alone = run(fixed(6))  # compiled for itself
    assert _tallies(third) == _tallies(alone)
    assert _tallies(third)[-1][0] > _tallies(first)[-1][0] > 0
    if isinstance(monitor, Validation):
        assert first.history[-1].validation_iterations > 0


def test_empty_arrays_are_made_by_the_program_not_passed():
    """A program with host calls pays per argument: empty arrays (a kernel's missing tail)
    stay out of the call, and the results and sharing are as if they were passed."""
    def program(x, empty, y):
        return x + y, empty * 2.0, empty.sum() + x[0]

    first, second = SharedCompile(program), SharedCompile(program)
    x, y = jnp.arange(3.0), jnp.ones(3)
    total, doubled, first_entry = first(x, jnp.zeros((0, 4)), y)
    assert np.array_equal(total, [1.0, 2.0, 3.0]) and float(first_entry) == 0.0
    assert doubled.shape == (0, 4) and doubled.dtype == jnp.float64
    [entry] = first._cache.values()
    assert len(jax.tree_util.tree_leaves(entry.executable.args_info)) == 2
    assert np.array_equal(second(y, jnp.zeros((0, 4)), y)[0], [2.0] * 3)
    assert second.shared == 1
    other = second(x, jnp.zeros((0, 5)), y)  # another empty shape: its own executable
    assert other[1].shape == (0, 5) and second.shared == 1


def test_a_program_with_host_calls_skips_the_checked_call_and_its_unread_arguments():
    """JAX's checked Python call costs a few microseconds per argument; a tally program takes
    the executable's unchecked call, with only the arguments it reads. A program without
    host calls keeps JAX's own (C++) call."""
    def counted(counter, x, unread, k):
        tally.tap(counter, "primal", k, x)
        return x * 2.0

    tallied, plain = SharedCompile(counted), SharedCompile(lambda x, unread: x * 3.0)
    counter, x = IterationCounter(), jnp.arange(3.0)
    doubled = tallied(counter, x, jnp.ones(5), jnp.int32(4))
    tripled = plain(x, jnp.ones(5))
    jax.effects_barrier()
    assert np.array_equal(doubled, [0.0, 2.0, 4.0]) and np.array_equal(tripled, [0.0, 3.0, 6.0])
    assert counter.snapshot() == (4, 0)
    [with_calls], [without] = tallied._cache.values(), plain._cache.values()
    assert with_calls.run is not with_calls.executable and without.run is without.executable
    assert with_calls.executable._executable._kept_var_idx == {0, 1, 3}  # not `unread`
    assert np.array_equal(tallied(counter, x + 1, jnp.zeros(5), jnp.int32(2)), [2.0, 4.0, 6.0])
    jax.effects_barrier()
    assert counter.snapshot() == (6, 0)


def _tapped_sine(counter, x, k):
    tally.tap(counter, "primal", k, x)
    return jnp.sin(x) * k


def _without_direct_calls(monkeypatch):
    monkeypatch.setattr(executables._DirectCall, "of", classmethod(lambda cls, unchecked: None))


def test_a_program_with_host_calls_runs_directly_with_jax_results_and_tallies(monkeypatch):
    """The direct call skips JAX's per-call work: the same results and counts as JAX's path,
    for arrays, a NumPy scalar (placed once) and a Python int, and `effects_barrier` still
    waits for the taps."""
    direct, counter = SharedCompile(_tapped_sine), IterationCounter()
    calls = [(jnp.linspace(0.0, 1.0, 5), jnp.int32(4)), (jnp.linspace(1.0, 2.0, 5), np.int32(3)),
             (jnp.linspace(2.0, 3.0, 5), 2)]
    results = [direct(counter, x, k) for x, k in calls]
    jax.effects_barrier()
    assert counter.snapshot() == (9, 0) and counter.primal_solves == 3
    assert all(isinstance(entry.run, executables._DirectCall) for entry in direct._cache.values())

    _without_direct_calls(monkeypatch)
    through_jax, reference = SharedCompile(_tapped_sine), IterationCounter()
    expected = [through_jax(reference, x, k) for x, k in calls]
    jax.effects_barrier()
    assert reference.snapshot() == counter.snapshot()
    assert not any(isinstance(entry.run, executables._DirectCall)
                   for entry in through_jax._cache.values())
    for got, want in zip(results, expected, strict=True):
        assert got.dtype == want.dtype and np.array_equal(got, want)


def test_a_direct_call_leaves_nan_checks_and_foreign_arguments_to_jax():
    """With NaN checking on, JAX's path checks the outputs; an argument the executable
    refuses (another device's) is handed to JAX's path, which moves it, from then on; any
    other error of the run is the caller's."""
    program, counter, x = SharedCompile(_tapped_sine), IterationCounter(), jnp.ones(3)
    program(counter, x, jnp.int32(1))
    [entry] = program._cache.values()
    run = entry.run
    with jax.debug_nans(True), pytest.raises(FloatingPointError, match=r"invalid value \(nan\)"):
        program(counter, jnp.full(3, jnp.inf), jnp.int32(1))
    plain = SharedCompile(jnp.log)  # no host calls: JAX's C++ path, the same report
    plain(jnp.ones(2))
    with jax.debug_nans(True), pytest.raises(FloatingPointError, match="encountered in log"):
        plain(-jnp.ones(2))

    def refusing(message):
        def execute_sharded(arguments, with_tokens):
            raise jax.errors.JaxRuntimeError(message)
        return SimpleNamespace(execute_sharded=execute_sharded)

    run._executable = refusing("INTERNAL: the program failed")
    with pytest.raises(jax.errors.JaxRuntimeError, match="program failed"):
        program(counter, x, jnp.int32(1))
    run._executable = refusing("INVALID_ARGUMENT: Buffer passed to Execute() as argument 1 "
                               "to replica 0 is on device cpu:1, but replica is assigned to "
                               "device cpu:0.")
    before = counter.primal
    assert np.array_equal(program(counter, x, jnp.int32(2)), jnp.sin(x) * 2)
    assert np.array_equal(program(counter, x, jnp.int32(2)), jnp.sin(x) * 2)  # JAX's path now
    jax.effects_barrier()
    assert counter.primal == before + 4


def test_a_direct_call_passes_what_it_cannot_pass_itself_to_jax(source_problem, monkeypatch):
    """A typed PRNG key (optax.noisy_sgd keeps one in its state) goes through JAX's path; a
    deleted argument gets JAX's error; a transfer guard holds as on JAX's path."""
    def keyed(counter, x, key):
        tally.tap(counter, "primal", jnp.int32(2), x)
        return x + jax.random.uniform(key, x.shape)

    program, counter, x = SharedCompile(keyed), IterationCounter(), jnp.zeros(3)
    key = jax.random.key(7)
    np.testing.assert_array_equal(program(counter, x, key), jax.random.uniform(key, (3,)))
    jax.effects_barrier()
    assert counter.primal == 2

    def noisy_run():
        return invert(source_problem, optimizer=optax.noisy_sgd(1e-2, key=0),
                      refinement=fixed(4), steps=3)

    direct = noisy_run()
    gone = jnp.ones(3)
    gone.delete()
    with pytest.raises(RuntimeError, match="deleted"):
        program(counter, gone, key)
    with jax.transfer_guard("disallow"), pytest.raises(Exception, match="Disallowed"):
        program(IterationCounter(), x, key)  # a new counter's slot must be transferred

    _without_direct_calls(monkeypatch)
    through_jax = noisy_run()
    np.testing.assert_array_equal(direct.params, through_jax.params)
    assert _tallies(direct) == _tallies(through_jax) and _tallies(direct)[-1][2] == 3


def test_several_devices_take_jax_path():
    """With several devices the direct call could be handed another device's array: it is
    not used there (a fresh process with two CPU devices)."""
    script = ("import jax, jax.numpy as jnp\n"
              "from prdp_fem import executables, tally\n"
              "from prdp_fem.cg import IterationCounter\n"
              "p = executables.SharedCompile(lambda c, x: tally.tap(c, 'primal', jnp.int32(1), x)"
              " or x)\n"
              "x = jax.device_put(jnp.ones(2), jax.devices()[1])\n"
              "print(len(jax.devices()), float(p(IterationCounter(), x).sum()),\n"
              "      type(next(iter(p._cache.values())).run).__name__)\n")
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out[:2] == ["2", "2.0"] and out[2] != "_DirectCall"


def _constants(scale=1.0):
    """A stand-in for an inverse problem: many small arrays of two dtypes and a large one."""
    return {"values": [jnp.full(k + 1, scale * (k + 1)) for k in range(6)],
            "columns": [jnp.arange(k + 2, dtype=jnp.int32) for k in range(4)],
            "single": jnp.full((2, 3), 7.0 * scale, jnp.float32),  # alone in its dtype
            "large": jnp.full(40, scale)}


def _reads_constants(x, constants, k):
    total = sum(jnp.sum(v) for v in constants["values"]) + jnp.sum(constants["large"])
    offsets = sum(jnp.sum(c) for c in constants["columns"]).astype(x.dtype)
    return x * k + total + offsets + jnp.sum(constants["single"]).astype(x.dtype)


def test_packed_arguments_travel_as_one_buffer_per_dtype_and_follow_new_arrays(monkeypatch):
    """An inversion step's problem is ~60 arrays, each costing a dispatch: packed, its small
    arrays arrive in one buffer per dtype. The results are those of the unpacked program, and
    a call with other arrays (another problem of the same shapes) repacks them."""
    monkeypatch.setattr(executables, "_PACK_LIMIT", 10)  # `large` (40 entries) stays apart
    counter = IterationCounter()

    def program(k, x, constants, counter):
        tally.tap(counter, "primal", jnp.int32(1), x)
        return _reads_constants(x, constants, k)

    packed = SharedCompile(program, static_argnum=0, packed_argnums=(2,))
    plain = SharedCompile(program, static_argnum=0)
    x, one, two = jnp.arange(3.0), _constants(), _constants(2.0)
    for constants in (one, one, two, one):
        assert np.array_equal(packed(3, x, constants, counter), plain(3, x, constants, counter))
        assert np.array_equal(packed(3, x, constants, counter),
                              _reads_constants(x, constants, 3))
    [entry] = packed._cache.values()
    [unpacked] = plain._cache.values()
    # 6 float64 + 4 int32 small arrays -> 2 buffers; `single` and `large` stay apart
    assert len(entry.executable.args_info[0]) == 2 + 4  # buffers, x, single, large, counter
    assert len(unpacked.executable.args_info[0]) == 14
    buffers = entry.packing.buffers(jax.tree_util.tree_leaves((x, one, counter)))
    assert sorted((b.dtype.name, b.shape) for b in buffers) == [("float64", (21,)),
                                                               ("int32", (14,))]
    jax.effects_barrier()
    assert counter.primal == 12  # every call taps once: 8 packed, 4 plain


class _Frozen(NamedTuple):
    constants: dict  # immutable at the top, as a problem (a frozen dataclass) is


def test_a_packed_argument_is_flattened_once_per_object(monkeypatch):
    """A frozen packed argument passed again (the same object) is not flattened again; another
    object, or a dict changed in place, is, and the results follow its values."""
    original, flattened = executables._flat, []

    def counting(source):
        flattened.append(type(source).__name__)
        return original(source)

    monkeypatch.setattr(executables, "_flat", counting)
    program = SharedCompile(lambda k, x, frozen, y: _reads_constants(x, frozen.constants, k) + y,
                            static_argnum=0, packed_argnums=(2,))
    x, y = jnp.arange(3.0), jnp.float64(1.0)
    one, two = _Frozen(_constants()), _Frozen(_constants(2.0))
    for frozen in (one, one, two, two, one):
        np.testing.assert_array_equal(program(3, x, frozen, y),
                                      _reads_constants(x, frozen.constants, 3) + y)
    # (x,) and (y,) every call; the packed argument when another object comes
    assert flattened.count("_Frozen") == 3 and flattened.count("tuple") == 10
    program.release()  # lets go of the last problem
    assert not program._segments._remembered

    # another number of arguments is another structure: segmented and compiled anew
    def varargs(k, x, frozen, *more):
        return _reads_constants(x, frozen.constants, k) + sum(more)

    flexible = SharedCompile(varargs, static_argnum=0, packed_argnums=(2,))
    np.testing.assert_array_equal(flexible(3, x, one), _reads_constants(x, one.constants, 3))
    np.testing.assert_array_equal(flexible(3, x, one, y, y),
                                  _reads_constants(x, one.constants, 3) + 2 * y)

    in_place = SharedCompile(lambda k, x, constants: _reads_constants(x, constants, k),
                             static_argnum=0, packed_argnums=(2,))
    changing = _constants()
    in_place(3, x, changing)
    changing["large"] = changing["large"] + 1.0
    np.testing.assert_array_equal(in_place(3, x, changing), _reads_constants(x, changing, 3))


def test_an_argument_cannot_be_both_static_and_packed():
    with pytest.raises(ValueError, match="both static and packed"):
        SharedCompile(lambda k, x: x * k, static_argnum=0, packed_argnums=(0,))


def test_an_inversion_step_takes_its_problem_packed(source_problem, monkeypatch):
    """The step of `invert` gets the problem's arrays in a few buffers, not one by one, and
    runs its executable directly."""
    made = []
    original = SharedCompile.__init__

    def recording(self, *args, **kwargs):
        original(self, *args, **kwargs)
        made.append(self)

    monkeypatch.setattr(SharedCompile, "__init__", recording)
    inverse._step_program.cache_clear()  # build the step here
    invert(source_problem, refinement=fixed(4), steps=2)
    problem_arrays = [leaf for leaf in jax.tree_util.tree_leaves(source_problem) if leaf.size]
    [step] = [compiled for compiled in made if compiled._packed_argnums == (0, 8)]
    [entry] = step._cache.values()
    taken = len(jax.tree_util.tree_leaves(entry.executable.args_info))
    assert len(problem_arrays) > 40 and taken < 25
    assert isinstance(entry.run, executables._DirectCall)  # and skips JAX's per-call work


def test_kept_programs_keep_one_program_per_hashable_setting():
    from prdp_fem.executables import kept_programs

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
