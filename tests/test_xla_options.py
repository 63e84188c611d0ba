"""The XLA options of the package's own programs: XLA's classic CPU fusion emitters unless the
program applies an AMG cycle or the caller's XLA_FLAGS choose the emitters.

The suite itself compiles with the classic emitters (tests/conftest.py sets XLA_FLAGS), so the
in-process tests clear that choice from the environment the decision reads; the test of what
XLA builds runs in fresh processes."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import prdp_fem as pf
from prdp_fem import _executables as executables
from prdp_fem._xla_options import (
    CLASSIC_EMITTERS,
    applies_amg_cycle,
    compiler_options,
    solver_options,
)
from prdp_fem.bench.inverse import mother_problem
from prdp_fem.inverse import fixed, invert, reduced
from prdp_fem.linalg import cg


@pytest.fixture
def emitters_left_to_the_package(monkeypatch):
    """XLA_FLAGS as a user's environment usually has it: silent on the emitters."""
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")


@pytest.fixture(scope="module")
def poisson():
    disc = pf.discretize(pf.unit_square(8), element="P1", dirichlet=0.0)
    kappa = jnp.ones(disc.n_kappa)
    return disc, kappa, disc.system.operator(kappa), jnp.ones(disc.n_free)


def _gradient_jaxpr(disc, kappa, solver):
    def loss(kappa):
        return jnp.sum(disc.system.solve(kappa, jnp.ones(disc.n_dofs), solver).x ** 2)
    return jax.jit(jax.grad(loss)).trace(kappa).jaxpr


def test_only_programs_that_apply_an_amg_cycle_keep_xla_s_emitters(
        poisson, emitters_left_to_the_package):
    disc, kappa, operator, b = poisson
    for mode in ("implicit", "unrolled"):
        jacobi = _gradient_jaxpr(disc, kappa, pf.TruncatedCG(5, "jacobi", gradient=mode))
        assert not applies_amg_cycle(jacobi)
        assert compiler_options(jacobi) == {"xla_cpu_use_fusion_emitters": False}
    for implementation in ("jax", "callback"):
        cycle = pf.amg_preconditioner(operator, implementation=implementation)
        for mode in ("implicit", "unrolled"):  # the cycle sits in a loop's body, forward and back
            gradient = _gradient_jaxpr(disc, kappa, pf.TruncatedCG(5, cycle, gradient=mode))
            assert applies_amg_cycle(gradient) and compiler_options(gradient) == {}
    batched = jax.jit(jax.vmap(lambda b: pf.solve(operator, b, pf.ConvergedCG(
        preconditioner=pf.amg_preconditioner(operator)))))
    assert applies_amg_cycle(batched.trace(jnp.stack([b, 2 * b])).jaxpr)


def test_the_caller_s_xla_flags_choose_the_emitters_for_every_program(poisson, monkeypatch):
    disc, kappa, operator, _ = poisson
    jacobi = _gradient_jaxpr(disc, kappa, pf.TruncatedCG(5, "jacobi"))
    for flags in ("--xla_cpu_use_fusion_emitters=true",
                  "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"):
        monkeypatch.setenv("XLA_FLAGS", flags)
        assert compiler_options(jacobi) == {} and solver_options("jacobi") == {}
    monkeypatch.delenv("XLA_FLAGS")
    assert compiler_options(jacobi) == dict(CLASSIC_EMITTERS)
    # before tracing, a solve's program is judged by its preconditioner: a name, or a pytree
    # that may be a cycle (a Jacobi pytree too: not looked into)
    assert solver_options("identity") == solver_options("jacobi") == dict(CLASSIC_EMITTERS)
    assert solver_options(pf.amg_preconditioner(operator)) == {}
    assert solver_options(pf.linalg.jacobi(operator)) == {}


def test_an_xla_without_the_option_keeps_its_own_emitters(poisson, monkeypatch,
                                                          emitters_left_to_the_package):
    from prdp_fem import _xla_options as xla_options

    disc, kappa, _, _ = poisson
    jacobi = _gradient_jaxpr(disc, kappa, pf.TruncatedCG(5, "jacobi"))
    assert xla_options._option_known()  # this XLA has it
    monkeypatch.setattr(xla_options, "_option_known", lambda: False)
    assert compiler_options(jacobi) == {} and solver_options("jacobi") == {}


def _recorded(monkeypatch, module) -> list:
    """The options each ``module.compile_lowered`` call passes."""
    passed, compile_lowered = [], module.compile_lowered

    def recording(lowered, options=None):
        passed.append(options)
        return compile_lowered(lowered, options)

    monkeypatch.setattr(module, "compile_lowered", recording)
    return passed


@pytest.mark.slow  # a fresh process per program kind
def test_inversion_steps_and_the_reduced_gradient_compile_with_the_chosen_options(
        poisson, monkeypatch, emitters_left_to_the_package):
    disc, _, operator, _ = poisson
    passed = _recorded(monkeypatch, executables)
    problem = pf.inverse_problem(disc, pf.full_field(disc, data=disc.project(
        lambda x: np.sin(np.pi * x[0]) / 20)), unknown="source", alpha=1e-4,
        regularization="l2")
    sgd = optax.sgd(1e-3)  # a small step program
    jacobi = invert(problem, optimizer=sgd, refinement=fixed(3), steps=2)
    assert passed and all(options == dict(CLASSIC_EMITTERS) for options in passed)
    passed.clear()
    amg = invert(problem, optimizer=sgd, refinement=fixed(3), steps=2,
                 preconditioner=pf.amg_preconditioner(operator))
    assert passed and {} in passed  # the step; a program beside it may take the classic ones
    for run in (jacobi, amg):
        assert np.all(np.isfinite(run.history.column("loss")))
    passed = _recorded(monkeypatch, reduced)
    result = reduced.reduced_cg(mother_problem(8), iterations=3)
    assert passed == [dict(CLASSIC_EMITTERS)] and np.isfinite(result.history[-1].loss)


def test_an_eager_solve_takes_the_classic_program_for_a_named_preconditioner(
        poisson, emitters_left_to_the_package):
    _, _, operator, b = poisson
    assert cg._compiled_program("jacobi") is cg._COMPILED_SOLVE_CLASSIC
    cycle = pf.amg_preconditioner(operator)
    assert cg._compiled_program(cycle) is cg._COMPILED_SOLVE  # a pytree may be a cycle
    x = pf.solve(operator, b, pf.ConvergedCG(rtol=1e-12, preconditioner="jacobi")).x
    reference = np.linalg.solve(operator.todense(), np.asarray(b))
    np.testing.assert_allclose(x, reference, rtol=1e-10)


# what XLA builds: the classic emitters expand a scatter into a loop (tests/test_products.py)
_BUILT = """
import json, jax, jax.numpy as jnp
import numpy as np
import prdp_fem as pf
from prdp_fem.linalg import cg
from prdp_fem import _executables as executables
index = np.array([0, 2, 2, 1])
step = executables.SharedCompile(jax.grad(lambda x: jnp.sum(x[index] ** 2)))
gradient = step(jnp.arange(3.0))
compiled = list(step._cache.values())[-1]
# the eager solve's two programs: the classic one must carry its option into XLA
disc = pf.discretize(pf.unit_square(4), element="P1", dirichlet=0.0)
A, b = disc.system.operator(jnp.ones(disc.n_kappa)), jnp.ones(disc.n_free)
dynamic, static = cg._split_solver(pf.ConvergedCG(), A.shape[0])
texts = [program.lower(A, b, None, None, cg._typed(dynamic), static=static).compile().as_text()
         for program in (cg._COMPILED_SOLVE_CLASSIC, cg._COMPILED_SOLVE)]
print(json.dumps({"scatters": compiled.as_text().count(" scatter("),
                  "gradient": [float(g) for g in gradient],
                  "eager classic": cg._compiled_program("jacobi") is cg._COMPILED_SOLVE_CLASSIC,
                  "eager programs differ": texts[0] != texts[1]}))
"""


@pytest.mark.parametrize("flags, chosen", [
    ("", True), pytest.param("--xla_cpu_use_fusion_emitters=true", False,
                             marks=pytest.mark.slow)])
def test_programs_compiled_in_a_fresh_process_have_the_emitters_chosen(flags, chosen):
    """With XLA_FLAGS silent a step is compiled with the classic emitters (no scatter left) and
    an eager Jacobi solve takes its classic program; a user who asks for XLA's emitters gets
    them (the scatter stays, the other program). The classic program is another program."""
    environment = {**os.environ, "XLA_FLAGS": flags}
    done = subprocess.run([sys.executable, "-c", _BUILT], capture_output=True, text=True,
                          env=environment, timeout=300, check=True)
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["gradient"] == [0.0, 2.0, 8.0]
    assert (out["scatters"] == 0) == chosen and out["eager classic"] == chosen
    assert out["eager programs differ"]
