"""Executables with the tally's host calls, stored across processes (prdp_fem.program_store):
a later process loads what an earlier one compiled, with the same results and tallies; any
other host callback, a bad file and a full store are handled."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import json_from_a_process
from jax._src import compiler as jax_compiler

from prdp_fem import executables, program_store, tally
from prdp_fem.cg import IterationCounter
from prdp_fem.executables import SharedCompile


@pytest.fixture
def store(tmp_path, monkeypatch):
    """A store of its own, storing every compilation, and the compilations of programs with
    host callbacks through SharedCompile (what loading from the store saves)."""
    directory = tmp_path / "tally"
    monkeypatch.setattr(program_store, "store_directory", lambda: directory)
    previous = jax.config.jax_persistent_cache_min_compile_time_secs
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    compiled = []
    original = jax_compiler.backend_compile_and_load

    def counting(backend, module, devices, options, host_callbacks):
        if host_callbacks and _through_shared_compile(module):
            compiled.append(module)
        return original(backend, module, devices, options, host_callbacks)

    monkeypatch.setattr(jax_compiler, "backend_compile_and_load", counting)
    monkeypatch.setattr(executables, "_EXECUTABLES", executables.OrderedDict())
    yield directory, compiled
    jax.config.update("jax_persistent_cache_min_compile_time_secs", previous)


def _through_shared_compile(module) -> bool:
    # not the once-per-process probes of the tally and the direct call
    return "jit_flat" in str(module.operation.attributes["sym_name"])


def _tapped(counter, x, k):
    tally.tap(counter, "primal", k, x)
    return jnp.sin(x) * k


def _run_fresh_lowering(function=_tapped):
    """Compile ``function`` as an inversion does (:class:`SharedCompile`), with the
    process's table of executables emptied first, and run it: (result, tally)."""
    executables._EXECUTABLES.clear()
    counter, x, k = IterationCounter(), jnp.linspace(0.0, 1.0, 7), jnp.int32(3)
    result = SharedCompile(function)(counter, x, k)
    jax.effects_barrier()
    return np.asarray(result), counter.snapshot()


def test_a_tally_program_is_stored_once_and_loaded_after(store):
    directory, compiled = store
    first, first_tally = _run_fresh_lowering()
    assert len(compiled) == 1 and len(list(directory.glob("*.xla"))) == 1
    second, second_tally = _run_fresh_lowering()
    assert len(compiled) == 1  # loaded, not compiled
    assert np.array_equal(first, second) and first_tally == second_tally == (3, 0)


def test_a_file_that_does_not_load_is_compiled_again_and_replaced(store):
    directory, compiled = store
    _run_fresh_lowering()
    (stored,) = directory.glob("*.xla")
    stored.write_bytes(b"not an executable")
    result, counts = _run_fresh_lowering()
    assert len(compiled) == 2 and counts == (3, 0)
    assert np.array_equal(result, np.sin(np.linspace(0.0, 1.0, 7)) * 3)
    _run_fresh_lowering()
    assert len(compiled) == 2  # the replaced file loads


def test_a_file_written_for_another_count_of_host_calls_is_not_loaded(store):
    # loading an executable with other host calls than it was built with would be unsafe
    directory, compiled = store
    _run_fresh_lowering()
    (stored,) = directory.glob("*.xla")
    data = stored.read_bytes()
    header = program_store._MAGIC + (1).to_bytes(4, "little")
    assert data.startswith(header)  # one host call: the tap
    stored.write_bytes(program_store._MAGIC + (2).to_bytes(4, "little") + data[len(header):])
    assert _run_fresh_lowering()[1] == (3, 0)
    assert len(compiled) == 2 and stored.read_bytes().startswith(header)  # compiled, rewritten


def test_a_program_with_another_host_callback_is_never_stored(store):
    directory, compiled = store
    seen = []

    def logging(counter, x, k):
        jax.debug.callback(seen.append, x)
        return _tapped(counter, x, k)

    _run_fresh_lowering(logging)
    _run_fresh_lowering(logging)
    assert len(compiled) == 2 and not directory.exists()
    jax.effects_barrier()  # the debug callbacks may still be running
    assert len(seen) == 2


def test_a_program_without_host_callbacks_is_left_to_jax(store):
    directory, _ = store
    lowered = jax.jit(lambda x: jnp.cos(x) * 2).lower(jnp.ones(3))
    assert np.allclose(program_store.compile_lowered(lowered)(jnp.zeros(3)), 2.0)
    assert not directory.exists()


def test_the_store_keeps_the_most_recently_used(store, monkeypatch):
    directory, _ = store
    monkeypatch.setattr(program_store, "CAPACITY", 2)
    for scale in (1.0, 2.0, 3.0):  # three programs (the constant is in the text)
        _run_fresh_lowering(lambda counter, x, k, scale=scale: _tapped(counter, x, k) * scale)
    assert len(list(directory.glob("*.xla"))) == 2
    assert not list(directory.glob("*.tmp"))


def test_the_store_follows_jax_s_cache_directory():
    assert program_store._tally_directory("/some/cache", True) == Path("/some/cache/tally")
    assert program_store._tally_directory("/some/cache", False) is None  # cache disabled
    assert program_store._tally_directory("", True) is None              # no directory
    assert program_store._tally_directory("gs://bucket/cache", True) is None  # remote: JAX's
    assert program_store.store_directory() == Path(
        jax.config.jax_compilation_cache_dir) / "tally"  # the session's (tests/conftest.py)


def test_with_the_cache_off_nothing_is_stored(store, monkeypatch):
    directory, compiled = store
    monkeypatch.setattr(program_store, "store_directory", lambda: None)
    _run_fresh_lowering()
    _run_fresh_lowering()
    assert len(compiled) == 2 and not directory.exists()


def test_concurrent_compiles_leave_jax_s_function_in_place_and_others_programs_alone(store):
    """While one thread compiles through the store (JAX's function swapped), another
    thread's tally program compiled by plain `jax.jit` is not stored, a second
    `compile_lowered` waits, and JAX's function is JAX's again afterwards."""
    import threading

    directory, _ = store
    jax_function = jax_compiler.compile_or_get_cached
    holding, release = threading.Event(), threading.Event()

    class Waiting:  # a lowering whose compile waits until released
        def compile(self, compiler_options=None):
            holding.set()
            release.wait(timeout=60)
            return "compiled"

    class Quick:
        def compile(self, compiler_options=None):
            return "quick"

    results = {}
    first = threading.Thread(target=lambda: results.update(
        first=program_store.compile_lowered(Waiting())))
    first.start()
    assert holding.wait(timeout=60)
    assert jax_compiler.compile_or_get_cached is not jax_function  # swapped, for `first`
    second = threading.Thread(target=lambda: results.update(
        second=program_store.compile_lowered(Quick())))
    second.start()
    counter = IterationCounter()
    jax.jit(_tapped)(counter, jnp.ones(3), jnp.int32(2))  # this thread: not the owner
    jax.effects_barrier()
    assert counter.snapshot() == (2, 0) and not directory.exists()
    release.set()
    first.join(timeout=60)
    second.join(timeout=60)
    assert results == {"first": "compiled", "second": "quick"}
    assert jax_compiler.compile_or_get_cached is jax_function


SCRIPT = """
import json, jax, numpy as np
from jax._src import compiler
compiled = []
original = compiler.backend_compile_and_load
def counting(backend, module, devices, options, host_callbacks):
    name = str(module.operation.attributes["sym_name"])
    if host_callbacks and "jit_flat" in name:  # SharedCompile's (not the probes)
        compiled.append(name)
    return original(backend, module, devices, options, host_callbacks)
compiler.backend_compile_and_load = counting
import prdp_fem as pf
pf.enable_compilation_cache()
from prdp_fem.inverse import inverse_problem, invert
from prdp_fem.observations import full_field
from prdp_fem.prdp import prdp
disc = pf.discretize(pf.unit_square(8), element="P1", dirichlet=0.0)
data = disc.project(lambda x: np.sin(np.pi * x[0]) * np.sin(np.pi * x[1]) / 20)
problem = inverse_problem(disc, full_field(disc, data=data), unknown="source", alpha=1e-4,
                          regularization="l2")
history = invert(problem, refinement=prdp(K0=3, dK=3), steps=6).history
print(json.dumps({"compiled": compiled,
                  "tallies": [[r.primal_iterations, r.adjoint_iterations_total,
                               r.evaluations] for r in history],
                  "losses": [r.loss.hex() for r in history]}))
"""


def _inversion_in_a_process(cache: Path) -> dict:
    return json_from_a_process(SCRIPT, str(cache))


def test_a_second_process_loads_the_inversion_step_with_its_own_tallies(tmp_path):
    first = _inversion_in_a_process(tmp_path)
    assert first["compiled"] and list((tmp_path / "tally").glob("*.xla"))
    second = _inversion_in_a_process(tmp_path)
    assert second["compiled"] == []  # the step (and the controller's update) loaded
    assert second["tallies"] == first["tallies"] and second["losses"] == first["losses"]
    assert second["tallies"][-1][0] > 0


def test_the_reduced_hessian_cg_loads_its_gradient_and_counts_into_its_own_counter(
        store, monkeypatch):
    """reduced_cg's gradient holds the tally's host calls, which JAX's cache refuses: a
    second run (here in the same process, with the store's file) loads it instead of
    compiling, and its solves count into the second run's counter."""
    from prdp_fem.bench_inverse import mother_problem
    from prdp_fem.prdp import fixed
    from prdp_fem.reduced import reduced_cg

    directory, _ = store
    compiled = []
    original = jax_compiler.backend_compile_and_load

    def counting(backend, module, devices, options, host_callbacks):
        if "jit_gradient" in str(module.operation.attributes["sym_name"]):
            compiled.append(module)
        return original(backend, module, devices, options, host_callbacks)

    monkeypatch.setattr(jax_compiler, "backend_compile_and_load", counting)
    problem = mother_problem(8)
    first, second = (reduced_cg(problem, refinement=fixed(7), iterations=3) for _ in range(2))
    assert len(compiled) == 1 and len(list(directory.glob("*.xla"))) == 1
    np.testing.assert_array_equal(first.field, second.field)
    counts = [[(r.primal_iterations, r.adjoint_iterations_total) for r in run.history]
              for run in (first, second)]
    assert counts[0] == counts[1] and counts[0][-1] == (3 * 7, 4 * 7)
