"""Checkpointed unrolled CG: the same K-iteration map in segments, its memory bound, and the
``bench memory`` command (structure and the checkpointed < plain ordering; never timings)."""

import os
import resource
import sys
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prdp_fem as pf
from prdp_fem.bench import memory as bench_memory
from prdp_fem.bench.memory import (
    REUSE_ENVIRONMENT,
    _gradient_problem,
    child_environment,
    memory_cost,
)
from prdp_fem.cli.main import main
from prdp_fem.linalg import TruncatedCG, solve
from prdp_fem.linalg.cg import _scan_iterations, segment_length

# ------------------------------------------------------------------------------------------
# the segmented scan is the plain scan
# ------------------------------------------------------------------------------------------


def _toy_body(theta):
    """A nonlinear scan body closed over a differentiated parameter, as CG's is over A."""

    def body(carry, _):
        x, s = carry
        x_new = jnp.tanh(theta * x[::-1] + 0.3 * s) + 0.1 * x
        return (x_new, 0.9 * s + jnp.sum(x_new)), (x_new[0] > 0, jnp.sum(x_new ** 2))

    return body


def _toy_run(theta, x0, iterations, segment):
    """``(final x, per-iteration outputs)`` and a scalar that depends on all of them."""
    (x, s), (flags, squares) = _scan_iterations(_toy_body(theta), (x0, jnp.zeros(())),
                                                iterations, segment)
    return jnp.sum(x) + s + jnp.vdot(jnp.cos(jnp.arange(iterations)), squares), (x, flags)


# 5 with the slow cases: 9 too has segments that divide it and segments that leave a rest
@pytest.mark.parametrize("iterations", [0, 1, pytest.param(5, marks=pytest.mark.slow), 9])
def test_segmented_scan_is_the_plain_scan_for_any_segment_length(iterations):
    theta, x0 = jnp.linspace(0.5, 1.5, 4), jnp.asarray([0.3, -0.2, 0.1, 0.4])
    direction = jnp.asarray([1.0, -0.5, 0.25, 2.0])

    @partial(jax.jit, static_argnums=0)
    def derivatives(segment):
        value_and_grad = jax.value_and_grad(_toy_run, argnums=(0, 1), has_aux=True)
        (value, (x, flags)), grads = value_and_grad(theta, x0, iterations, segment)
        _, slope = jax.jvp(lambda t: _toy_run(t, x0, iterations, segment)[0], (theta,),
                           (direction,))
        return value, x, flags, grads, slope

    value, x, flags, grads, slope = derivatives(None)
    assert flags.shape == (iterations,)
    for segment in sorted({1, 2, 3, 4, max(iterations, 1), iterations + 1}):
        s_value, s_x, s_flags, s_grads, s_slope = derivatives(segment)
        np.testing.assert_array_equal(s_x, x)
        np.testing.assert_array_equal(s_flags, flags)
        assert float(s_value) == float(value)
        for s_grad, grad in zip(s_grads, grads, strict=True):
            np.testing.assert_allclose(s_grad, grad, rtol=1e-13, atol=1e-15)
        assert float(s_slope) == pytest.approx(float(slope), rel=1e-13, abs=1e-15)


def _weights(disc):
    return jnp.asarray(np.cos(np.arange(disc.n_free)))


def _loss(small_problem, iterations, checkpoint):
    """``kappa -> (J, Solution)`` with ``J = w . x_K``."""
    disc, _, f = small_problem
    system, w = disc.system, _weights(disc)

    def loss(kappa):
        sol = solve(system.operator(kappa), system.rhs(kappa, f),
                    TruncatedCG(iterations, checkpoint=checkpoint))
        return w @ sol.x, sol

    return loss


# K = 7 with the sqrt rule: s = 3, two segments and one iteration left over; K = 12 with s = 5:
# two segments and two left over (with the slow cases: a segment length given as a number is
# the sqrt rule's scan with another length, which the toy scan above checks for every length)
@pytest.mark.parametrize(("iterations", "checkpoint"), [
    (7, True), pytest.param(12, 5, marks=pytest.mark.slow)])
def test_checkpointed_solve_gives_the_plain_x_history_and_gradient(small_problem, iterations,
                                                                   checkpoint):
    kappa = jnp.asarray(small_problem[1])

    def run(checkpoint):
        loss = _loss(small_problem, iterations, checkpoint)
        return jax.jit(jax.value_and_grad(loss, has_aux=True))(kappa)

    (_, plain), plain_grad = run(False)
    (_, sol), grad = run(checkpoint)
    # the same operations in the same order, but XLA may fuse the nested loops differently
    # (a last-bit difference in a product): equal to round-off
    np.testing.assert_allclose(sol.x, plain.x, rtol=1e-13)
    np.testing.assert_allclose(sol.residual_history, plain.residual_history, rtol=1e-13)
    assert int(sol.iterations) == int(plain.iterations) == iterations
    assert int(sol.status) == int(plain.status)
    # the backward pass sums in another order: round-off only
    np.testing.assert_allclose(grad, plain_grad, rtol=1e-12,
                               atol=1e-14 * float(np.max(np.abs(plain_grad))))


# the toy scan's test above differentiates the segments in forward mode, and the test above
# checks the solve's segments
@pytest.mark.slow
def test_checkpointed_solve_jvp_matches_the_plain_one(small_problem):
    disc, kappa, _ = small_problem
    direction = jnp.asarray(np.random.default_rng(3).normal(size=disc.n_kappa))

    def tangent(checkpoint):  # K = 10, sqrt rule: s = 4, two segments and two left over
        loss = _loss(small_problem, 10, checkpoint)
        return jax.jit(lambda k, v: jax.jvp(lambda k: loss(k)[0], (k,), (v,)))(
            jnp.asarray(kappa), direction)

    (value, slope), (plain_value, plain_slope) = tangent(True), tangent(False)
    assert float(value) == float(plain_value)
    assert float(slope) == pytest.approx(float(plain_slope), rel=1e-12)


# ------------------------------------------------------------------------------------------
# the option
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("iterations", "checkpoint", "segment"), [
    (0, True, 1), (1, True, 1), (2, True, 2), (10, True, 4), (16, True, 4), (17, True, 5),
    (1000, True, 32), (1000, False, None), (1000, 7, 7), (3, 7, 7)])
def test_segment_length(iterations, checkpoint, segment):
    assert segment_length(iterations, checkpoint) == segment


@pytest.mark.parametrize("checkpoint", [0, -2, 2.5, "yes", None, np.array([3]), 1.0])
def test_bad_checkpoint_is_refused_at_construction(checkpoint):
    with pytest.raises(pf.SolverConfigError, match=r"checkpoint=.*: expected True \(segments "
                       r"of ceil\(sqrt\(K\)\) iterations\), False or a segment length >= 1"):
        TruncatedCG(10, checkpoint=checkpoint)


@pytest.mark.parametrize(("checkpoint", "stored"), [
    (True, True), (False, False), (np.True_, True), (4, 4), (np.int64(4), 4)])
def test_checkpoint_is_stored_as_a_python_value(checkpoint, stored):
    solver = TruncatedCG(10, checkpoint=checkpoint)
    assert solver.checkpoint == stored and type(solver.checkpoint) is type(stored)


# ------------------------------------------------------------------------------------------
# the memory bound, read from XLA's buffer assignment (deterministic, no process measured)
# ------------------------------------------------------------------------------------------


SIDE = 33
N_VECTOR_MB = (SIDE - 1) ** 2 * 8 / 1e6  # one vector of the P1 problem's free dofs


def _scratch_mb(mode: str, iterations: int, side: int = SIDE) -> float:
    gradient, kappa, n_free, _ = _gradient_problem(side, iterations, mode, None)
    assert n_free * 8 / 1e6 == N_VECTOR_MB
    analysis = gradient.lower(kappa).compile().memory_analysis()
    # the CPU backend (CI's) reports it; a backend that does not must fail here, not pass
    assert analysis is not None, "no memory analysis from this backend"
    return analysis.temp_size_in_bytes / 1e6


@pytest.mark.slow  # a process per mode and K
def test_checkpointed_memory_grows_like_sqrt_k_and_implicit_not_at_all():
    scratch = {(mode, k): _scratch_mb(mode, k) for mode, k in (
        ("unrolled", 100), ("unrolled", 400), ("checkpointed", 100), ("checkpointed", 400),
        ("implicit", 100), ("implicit", 400))}
    # plain unrolled keeps p, q and r of every iteration: the symmetric product's transpose
    # gathers the values' cotangent from p (JAX's own rules kept every ELL slot's gather: 7)
    per_iteration = (scratch["unrolled", 400] - scratch["unrolled", 100]) / 300 / N_VECTOR_MB
    assert 2.5 < per_iteration < 3.5
    # checkpointed: K/s stored states + s recomputed iterations with s = sqrt(K), so 4x the
    # iterations is about 2x the memory (plain: every iteration's intermediates, 4x)
    assert scratch["checkpointed", 400] < 2.2 * scratch["checkpointed", 100]
    assert scratch["checkpointed", 400] < scratch["unrolled", 400] / 5
    assert scratch["implicit", 400] == scratch["implicit", 100]


# ------------------------------------------------------------------------------------------
# the benchmark and its command
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"side": 1}, r"side=1: expected an integer >= 2"),
    ({"iterations": (3, -1)}, r"iterations=\[3, -1\]: expected integers >= 0"),
    ({"iterations": ()}, r"iterations=\[\]: expected integers >= 0"),
    ({"modes": ("adjoint",)}, r"modes=\['adjoint'\]: expected some of \['unrolled', "),
    ({"segment": 0}, r"segment=0: expected an integer >= 1 or None"),
    ({"repeats": 0}, r"repeats=0: expected an integer >= 1"),
    ({"max_mb": 0}, r"max_mb=0: expected a number > 0"),
])
def test_bad_memory_cost_options(kwargs, message):
    with pytest.raises(pf.SolverConfigError, match=message):
        memory_cost(**{"side": 8, "iterations": (1,), **kwargs})


@pytest.mark.slow  # spawns a process per mode; the sqrt(K) memory test stays
def test_bench_memory_table_and_checkpointed_peak_below_plain(capsys):
    # 4096 dofs, K = 400: plain stores ~120 MB, checkpointed ~10 MB, far apart from the few MB
    # by which a resident-set reading can wander (implicit mode: tested on XLA's figures above)
    assert main(["bench", "memory", "--side", "65", "--iterations", "400", "--modes",
                 "unrolled", "checkpointed", "--repeats", "1"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("P1 Poisson on unit_square(65): 4096 dofs, one n-vector = ")
    assert lines[2].split() == ["mode", "K", "segment", "allocator", "peak", "MB", "n-vectors",
                                "XLA", "temp", "MB", "grad", "[s]", "faults/call", "ratio"]
    rows = [line.split() for line in lines[3:]]
    assert [row[:4] for row in rows] == [["unrolled", "400", "-", "default"],
                                         ["checkpointed", "400", "20", "default"]]
    peak = {row[0]: float(row[4]) for row in rows}
    for row in rows:
        assert all(float(cell) >= 0 for cell in row[4:8])
        assert row[8:] == ["-", "-"]  # one evaluation: no faults after the first; no pair
    assert peak["checkpointed"] < peak["unrolled"] / 4


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator settings")
@pytest.mark.slow  # spawns processes per allocator setting
def test_the_reuse_allocator_keeps_an_unrolled_gradient_s_scratch_mapped(capsys, monkeypatch):
    # 4096 dofs, K = 800: one 81 MB scratch block per evaluation, above what glibc keeps in
    # a thread's arena (64 MB); under glibc's defaults each evaluation maps it afresh and
    # faults it in (about 20 000 pages here), kept mapped it is reused
    # faults it in (about 20 000 pages here), kept mapped it is reused. Under load the
    # scratch's release can still be on its way when the next evaluation allocates, which
    # then maps a block of its own (the average over 4 evaluations once read 3 of them), so
    # "reused" is read as: at least one evaluation after the first faults almost nothing.
    measured = []

    def measuring(*args, **kwargs):
        measured.extend(memory_cost(*args, **kwargs))
        return measured

    monkeypatch.setattr(bench_memory, "memory_cost", measuring)
    assert main(["bench", "memory", "--side", "65", "--iterations", "800", "--modes",
                 "unrolled", "--repeats", "5", "--allocator", "both"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.strip().splitlines()[3:]]
    assert [row[3] for row in rows] == ["default", "reuse"] == [m.allocator for m in measured]
    default, reuse = measured
    scratch_pages = default.xla_temp_mb / (resource.getpagesize() / 1e6)
    assert default.xla_temp_mb > 64
    assert default.fewest_faults > 0.5 * scratch_pages  # every evaluation maps it afresh
    assert reuse.fewest_faults < 0.05 * scratch_pages   # kept mapped and reused
    assert reuse.faults_per_call <= default.faults_per_call
    assert [float(row[8]) for row in rows] == [round(m.faults_per_call) for m in measured]
    assert rows[0][9] == "-"
    assert float(rows[1][9]) == pytest.approx(reuse.gradient_s / default.gradient_s, abs=0.01)


def test_a_child_runs_with_the_allocator_s_settings_and_only_then():
    user = {"MALLOC_ARENA_MAX": "4", "MALLOC_TRIM_THRESHOLD_": "1", "PYTHONPATH": "/elsewhere"}
    default, reuse = (child_environment(a, user) for a in ("default", "reuse"))
    assert not set(REUSE_ENVIRONMENT) & set(default)  # glibc's own defaults, not the user's
    assert {k: reuse[k] for k in REUSE_ENVIRONMENT} == dict(REUSE_ENVIRONMENT)
    for env in (default, reuse):
        assert env["PYTHONPATH"].split(os.pathsep)[1:] == ["/elsewhere"]
    with pytest.raises(pf.SolverConfigError, match=r"allocators=\['tcmalloc'\]: expected some"):
        memory_cost(side=8, iterations=(1,), allocators=("tcmalloc",))
