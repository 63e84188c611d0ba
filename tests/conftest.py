"""Shared fixtures: manufactured solutions and small discretisations."""

import atexit
import importlib.util
import logging
import os
import shutil
import tempfile
from pathlib import Path

# OpenBLAS (NumPy's and SciPy's) runs a thread per core, and its threads spin while they wait
# for each other: wherever the cores are shared -- pytest-xdist's workers, one per core, or
# any other busy process -- a descheduled thread stalls the rest. The suite's dense matrices
# are small (AMG radii, condition numbers, direct references: up to a few thousand rows), so
# each process keeps to one BLAS thread unless the caller chose (test_amg.py's eigen-solves:
# 1 s on one thread, 28 s on two beside a busy process). OpenBLAS reads it when it loads,
# so it is set before NumPy's import; the CLI processes the tests start inherit it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import pytest
from hypothesis import settings

# hermetic: the session (and the CLI subprocesses it starts) share one throwaway compilation
# cache instead of the user's; set before prdp_fem is imported, which switches the cache on
if "PRDP_FEM_COMPILATION_CACHE" not in os.environ:
    _CACHE = tempfile.mkdtemp(prefix="prdp-fem-test-cache-")
    os.environ["PRDP_FEM_COMPILATION_CACHE"] = _CACHE
    atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)

# Compiling was two thirds of the suite's time: the tests build thousands of programs on
# meshes of tens to thousands of unknowns and run each a few times. XLA compiles them about
# three times faster with LLVM's optimisation off and the classic CPU fusion emitters. The
# programs are the same HLO in IEEE arithmetic (no fast-math), so only the order of some sums
# can change, as on another CPU (a batched program is compared to its unbatched one to
# round-off); tests that read a compiled program's text ask for the shipped emitters.
# `XLA_FLAGS` set by the caller wins: `XLA_FLAGS= python -m pytest ...` compiles as users do.
if "XLA_FLAGS" not in os.environ:  # read when JAX starts its backend, after this import
    os.environ["XLA_FLAGS"] = ("--xla_backend_optimization_level=0"
                               " --xla_cpu_use_fusion_emitters=false")

import prdp_fem as pf

# Property tests draw the same examples in every run (derived from each test's source), so CI
# passes or fails on the code, not on a new draw. `--hypothesis-profile=explore` draws fresh
# ones; a failure prints its arguments either way.
settings.register_profile("reproducible", derandomize=True, database=None, deadline=None)
settings.register_profile("explore", database=None, deadline=None)
settings.load_profile("reproducible")

MESH_DIR = Path(__file__).resolve().parent.parent / "meshes"
EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
SHIPPED_MESHES = sorted(MESH_DIR.glob("*.msh"))

# a three-configuration study of the mother problem on an 8 x 8 mesh (STEPS: optimiser steps)
SMALL_STUDY = """
name = "small"
[mesh]
n = 8
[inverse]
unknown = "source"
data = "sin(pi*x)*sin(pi*y)/(2*pi**2)"
truth = "sin(pi*x)*sin(pi*y)/(1 + 4e-6*pi**4)"
alpha = 1e-6
regularization = "l2"
[refinement]
kind = "prdp"
K0 = 2
dK = 2
[optimizer]
steps = STEPS
[[study.runs]]
name = "converged"
refinement = { kind = "converged" }
[[study.runs]]
name = "fixed K=3"
refinement = { kind = "fixed", K = 3 }
[[study.runs]]
name = "prdp"
"""

# scikit-fem logs a warning whenever refined() drops named boundaries; the rate tests refine
logging.getLogger("skfem").setLevel(logging.ERROR)


class Manufactured:
    """u = exp(c.x) with kappa = 1 + a.x (exactly P1), f = -div(kappa grad u)."""

    def __init__(self, dim: int):
        self.c = np.array([0.7, 0.5, 0.3])[:dim]
        self.a = np.array([0.5, 0.25, 0.125])[:dim]

    def u(self, x):
        return np.exp(np.einsum("d,d...->...", self.c, x))

    def grad_u(self, x):
        return np.stack([ci * self.u(x) for ci in self.c])

    def kappa(self, x):
        return 1.0 + np.einsum("d,d...->...", self.a, x)

    def f(self, x):
        # -div(kappa grad u) = -(grad kappa . grad u + kappa lap u)
        return -(self.a @ self.c + self.kappa(x) * (self.c @ self.c)) * self.u(x)


@pytest.fixture
def manufactured_2d():
    return Manufactured(2)


@pytest.fixture
def manufactured_3d():
    return Manufactured(3)


def small_heat_case(dt: float = 0.02):
    """6x6 P1 (25 free dofs), 12 training and 4 validation trajectories of 6 steps of the
    heat equation: (disc, problem, train_set, validation_set)."""
    from prdp_fem.learning import heat

    disc = pf.discretize(pf.unit_square(6), dirichlet=0.0)
    problem = heat.heat_problem(disc, dt)
    initial = heat.random_initial_states(disc, 16, seed=0, width=0.2)
    trajectories = heat.reference_trajectories(disc, initial, dt=dt, steps=6)
    return disc, problem, trajectories.take(np.arange(12)), trajectories.take(np.arange(12, 16))


def learning_rate_spy(control):
    """``(spy, fed)``: ``control`` with an ``update`` that records the learning-rate scale
    each call is fed into the list ``fed``."""
    fed = []

    def update(state, value, failed=False, learning_rate_scale=1.0):
        fed.append(learning_rate_scale)
        return control.update(state, value, failed, learning_rate_scale)

    return control._replace(update=update), fed


@pytest.fixture
def small_problem():
    """P1 on an 8x8 square, P0 kappa, non-zero Dirichlet data, a source: (disc, kappa, f)."""
    disc = pf.discretize(pf.unit_square(8), element="P1", kappa_space="P0",
                         dirichlet=lambda x: 0.5 * x[0])
    kappa = disc.interpolate_kappa(lambda x: 1.0 + x[0] + 0.5 * np.sin(3 * x[1]))
    f = disc.interpolate(lambda x: np.cos(2 * x[0]) + x[1])
    return disc, kappa, f


@pytest.fixture(scope="session")
def load_example():
    """``load_example(name)`` imports ``examples/<name>.py`` (plain scripts, not a package)."""

    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


def resume_after_losing_done(scene, out: Path, run: str, runner: str, monkeypatch):
    """Drop ``run``'s ``done`` record from the study in ``out``, resume it, and check that
    only ``run`` ran again (through ``prdp_fem.studies.runner.<runner>``); the resumed
    StudyOutput."""
    import json

    from prdp_fem.studies import runner as study

    records = study.ResultsLog(out / study.RESULTS).records()
    kept = [r for r in records if not (r["type"] == "done" and r["run"] == run)]
    (out / study.RESULTS).write_text("".join(json.dumps(r) + "\n" for r in kept))
    calls = []
    original = getattr(study, runner)
    monkeypatch.setattr(study, runner, lambda name, *a: (calls.append(name), original(name, *a)))
    resumed = study.run_study(scene, out, resume=True)
    assert calls == [run] and resumed.ran == [run]
    return resumed


def json_from_a_process(script: str, cache_setting: str) -> dict:
    """Run ``script`` in a fresh Python process (this checkout importable) with
    ``PRDP_FEM_COMPILATION_CACHE=cache_setting``; the JSON of its last printed line."""
    import json
    import subprocess
    import sys

    root = str(Path(__file__).resolve().parent.parent)
    env = {**os.environ, "PRDP_FEM_COMPILATION_CACHE": cache_setting,
           "PYTHONPATH": os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])])}
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                         text=True, check=True, timeout=300)
    return json.loads(out.stdout.strip().splitlines()[-1])


def shared_compiles_made(monkeypatch) -> list:
    """The ``SharedCompile`` programs built from now on (the test's ``monkeypatch`` undoes
    the recording)."""
    from prdp_fem._executables import SharedCompile

    made, original = [], SharedCompile.__init__

    def recording(self, *args, **kwargs):
        original(self, *args, **kwargs)
        made.append(self)

    monkeypatch.setattr(SharedCompile, "__init__", recording)
    return made


@pytest.fixture
def backend_compiles():
    """The names of the XLA compilations from here on (``jit(name)``; the persistent cache
    off, so none is loaded), as JAX's monitoring events report them."""
    import jax

    from prdp_fem._xla_options import classic_emitters_apply

    classic_emitters_apply()  # its one-off check of XLA's options compiles before, not here
    compiled = []

    def listener(event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            compiled.append(kwargs.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(listener)
    previous = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    yield compiled
    jax.config.update("jax_enable_compilation_cache", previous)
    jax.monitoring.unregister_event_duration_listener(listener)


def count_primitives(fn, arg, name: str) -> int:
    """How many ``name`` equations the jaxpr of ``fn(arg)`` holds, nested ones included."""
    import jax
    import jax.extend.core

    def count(jaxpr) -> int:
        return sum((eqn.primitive.name == name)
                   + sum(count(sub.jaxpr if hasattr(sub, "jaxpr") else sub)
                         for sub in jax.extend.core.jaxprs_in_params(eqn.params))
                   for eqn in jaxpr.eqns)
    return count(jax.make_jaxpr(fn)(arg).jaxpr)
