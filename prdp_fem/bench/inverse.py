r"""Inverse-problem benchmarks (``prdp-fem bench mother``, ``prdp-fem bench prdp``).

Mother problem against the peer
-------------------------------
dolfin-adjoint's Poisson "mother problem" on the unit square, P1 state and P1 control on an
``n x n`` mesh:

.. math::

    \min_f\; \tfrac12 \|u - d\|_{L^2}^2 + \tfrac\alpha2 \|f\|_{L^2}^2, \quad
    -\Delta u = f,\; u|_{\partial\Omega} = 0, \quad
    d = \frac{\sin\pi x \sin\pi y}{2\pi^2}, \quad
    f^* = \frac{\sin\pi x \sin\pi y}{1 + 4\alpha\pi^4}, \quad \alpha = 10^{-6}.

The objective is quadratic in ``f``. The race's solver (``solver="kkt"``) is
:func:`~prdp_fem.inverse.kkt.kkt_solve`: MINRES on the KKT system of state, source and
adjoint, with the Pearson-Wathen block preconditioner (an AMG V-cycle pair per iteration,
mesh-independent iteration counts). ``solver="reduced"`` is
:func:`~prdp_fem.inverse.reduced.reduced_cg`: CG on the reduced Hessian, preconditioned by the
L2 Riesz map, whose Hessian products are the toolkit's implicit gradients through truncated
PCG state and adjoint solves (``K`` from a PRDP controller, or converged to ``inner_rtol``).
Either stops at the first iterate whose distance to the *discrete optimum*
(:func:`mother_optimum_field`) is within 1 % of that optimum's relative L2 error against
``f*`` (``||f - f*||_M / ||f*||_M`` with the P1 mass matrix and the nodal interpolant of
``f*``, as the study and the example measure it): the same discrete problem solved to the
same accuracy. The peer,
dolfin-adjoint's L-BFGS-B on legacy FEniCS (:mod:`prdp_fem.bench.dolfin_adjoint_mother`),
runs with its tutorial's settings in its own fresh processes, alternated with the project's,
where its Python is given (``peer_python``); it is judged on its own final error, reported
beside its time. Every run is a fresh Python process
(:func:`mother_whole_process`): interpreter start, imports, mesh, assembly, compilation and the
optimisation are all inside the wall time. By default no persistent compilation cache is used
(``cache="cold"``; ``"warm"`` times processes that load the program from a cache one untimed
process filled); the package's bytecode is written first (:func:`compile_package_bytecode`),
as installing it does.

PRDP saving
-----------
:func:`prdp_saving` runs a scene's converged reference and its PRDP configurations through
:func:`~prdp_fem.studies.runner.run_study` and reads the saving from the study's own summary
(BENCHMARKS.md): run time and cumulative primal + adjoint CG iterations of a PRDP run up to the
step from which its parameter error stays within 1 % of the converged run's final error,
divided by the converged run's totals (same scene, optimiser and steps; compilation excluded).

One study follows one trajectory of a truncated optimisation, and a controller setting that
moves a refinement by a step or two moves where that trajectory goes: the saving of one
problem instance is one sample. :func:`seed_variants` gives the same scene with other noise
and sensor draws (``inverse.seed``), and :func:`seed_summary` counts, per run, the instances
that meet the goal and the medians over them (``prdp-fem bench prdp --seeds 1 2 3``).
"""

from __future__ import annotations

import compileall
import contextlib
import dataclasses
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any, NamedTuple

import numpy as np

from ..compilation_cache import ENVIRONMENT_VARIABLE as CACHE_VARIABLE
from ..compilation_cache import enable_compilation_cache
from ..errors import SceneError, SolverConfigError
from ..fem.discretization import discretize
from ..fem.observations import full_field
from ..inverse.driver import InverseProblem, inverse_problem
from ..inverse.kkt import kkt_solve
from ..inverse.reduced import reduced_cg
from ..inverse.refinement import converged, prdp
from ..mesh.generators import unit_square
from .cg import this_package_first

__all__ = [
    "ALPHA",
    "CACHES",
    "GOALS",
    "RACE_INNER_RTOL",
    "SOLVERS",
    "TARGET_FACTOR",
    "MotherBench",
    "MotherSolve",
    "PeerFigure",
    "SavingRow",
    "SeedSummary",
    "compile_package_bytecode",
    "median_row",
    "mother_optimum",
    "mother_optimum_field",
    "mother_problem",
    "mother_whole_process",
    "prdp_saving",
    "saving_rows",
    "seed_summary",
    "seed_variants",
    "solve_mother",
]

ALPHA = 1e-6


class PeerFigure(NamedTuple):
    """dolfin-adjoint (L-BFGS-B), run here: median whole-process seconds, final error."""

    seconds: float
    error: float
    goal_ratio: float  # prdp_fem time / peer time to beat (NaN: no goal at this size)
    evaluations: int = 0


#: prdp_fem's whole-process time over the peer's to beat, by size (the issue's goal)
GOALS: Mapping[int, float] = MappingProxyType({512: 0.25, 1024: 0.15})
#: the race's target: this factor times the discrete optimum's error (within 1 %)
TARGET_FACTOR = 1.01
# the inner PCG's preconditioner by name (a fresh process gets a name, not a pytree): each
# builds what solve() takes from the problem, once, inside the timed setup; an AMG cycle
# (a pytree built from problem.system.operator(problem.known)) slots in here
def _amg_cycle(problem: InverseProblem):
    from ..linalg.amg import amg_preconditioner  # pyamg's setup: only where it is asked for

    return amg_preconditioner(problem.system.operator(problem.known).to_scipy())


INNER_PRECONDITIONERS: Mapping[str, Callable[[InverseProblem], Any]] = MappingProxyType({
    "jacobi": lambda problem: "jacobi",
    "identity": lambda problem: "identity",
    "amg": _amg_cycle,  # smoothed aggregation, built in the timed setup
})
#: the inner solves of the race: converged to this relative residual (PRDP-truncated inner
#: solves with K0 = dK = 5 or 20 did not reach the discrete optimum within 100 outer steps)
RACE_INNER_RTOL = 1e-8
DEFAULT_K = 5  # K0 = dK of the inner solves: the mother scene's PRDP settings
#: the project's solvers of the race: all-at-once MINRES on the KKT system (the race's), or
#: CG on the reduced Hessian through inner PCG solves
SOLVERS = ("kkt", "reduced")
SAVING_GOAL, ERROR_BAND = 0.8, 0.01  # BENCHMARKS.md: >= 80 % saving, final error within 1 %


# --------------------------------------------------------------------------------------
# the mother problem, solved in this process
# --------------------------------------------------------------------------------------


def _mode(x: np.ndarray) -> np.ndarray:
    return np.sin(np.pi * x[0]) * np.sin(np.pi * x[1])


def mother_problem(n: int, alpha: float = ALPHA) -> InverseProblem:
    """The mother problem on an ``n x n`` unit square as an :class:`InverseProblem`.

    The misfit is against the L2 projection of ``d`` (the same minimiser as against ``d``
    itself, which dolfin-adjoint integrates); the truth is the nodal interpolant of ``f*``.
    """
    disc = discretize(unit_square(n, "triangle"), element="P1", kappa_space="P0",
                      dirichlet=0.0)
    data = disc.project(lambda x: _mode(x) / (2 * np.pi ** 2))
    truth = disc.interpolate(_mode) / (1 + 4 * alpha * np.pi ** 4)
    return inverse_problem(disc, full_field(disc, data=data), unknown="source", alpha=alpha,
                           regularization="l2", truth=truth)


class MotherSolve(NamedTuple):
    """One mother-problem solve in this process, phases timed (seconds)."""

    n: int
    dofs: int                 # nodal unknowns of f (the control)
    error: float              # relative L2 error of f against f* where the run stopped
    target: float
    outer_iterations: int     # MINRES iterations (kkt) or reduced-Hessian CG iterations
    inner_iterations: int     # AMG V-cycles (kkt) or primal + adjoint state-solve PCG its
    riesz_iterations: int     # mass-matrix PCG iterations of the Riesz map (reduced)
    final_K: int              # the inner solves' last K (reduced; 0 for kkt)
    assembly_s: float         # mesh, assembly, data, the inverse problem, the preconditioner
    compile_s: float          # 0 for kkt: nothing is compiled
    solve_s: float            # the optimisation, compilation excluded
    solver: str = "kkt"


def check_mother_options(sizes, *, repeats: int = 1, target: float | None = None,
                         K: int = DEFAULT_K, inner_rtol: float | None = None,
                         preconditioner: str = "jacobi", cache: str = "cold",
                         solver: str = "kkt") -> None:
    """Refuse bad benchmark settings up front (SolverConfigError naming the option)."""
    if solver not in SOLVERS:
        raise SolverConfigError(f"--solver {solver!r}: expected one of {list(SOLVERS)}")
    if any(isinstance(n, bool) or not isinstance(n, int) or n < 2 for n in sizes) or not sizes:
        raise SolverConfigError(f"--sizes {' '.join(map(str, sizes))}: expected integers >= 2")
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise SolverConfigError(f"--repeats {repeats!r}: expected an integer >= 1")
    if isinstance(K, bool) or not isinstance(K, int) or K < 1:
        raise SolverConfigError(f"--iterations {K!r}: expected an integer >= 1")
    if inner_rtol is not None and not (isinstance(inner_rtol, float | int)
                                       and 0 < inner_rtol < 1):
        raise SolverConfigError(f"--inner-rtol {inner_rtol!r}: expected a number in (0, 1)")
    if preconditioner not in INNER_PRECONDITIONERS:
        raise SolverConfigError(f"--preconditioner {preconditioner!r}: expected one of "
                                f"{list(INNER_PRECONDITIONERS)}")
    if cache not in CACHES:
        raise SolverConfigError(f"--cache {cache!r}: expected one of {list(CACHES)}")
    if target is not None:
        _target(sizes[0], target)


def _inner_refinement(K: int, inner_rtol: float | None):
    """PRDP on the inner ``K`` (``K0 = dK = K``), or every inner solve to ``inner_rtol``."""
    return prdp(K0=K, dK=K, restart=True) if inner_rtol is None else converged(inner_rtol)


def solve_mother(n: int, *, target: float | None = None, K: int = DEFAULT_K,
                 inner_rtol: float | None = None, preconditioner: str = "jacobi",
                 max_iterations: int = 100, optimum_file: str | None = None,
                 solver: str = "kkt") -> MotherSolve:
    """Set up and solve the mother problem to within 1 % of the discrete optimum's error.

    It stops at the first iterate ``f`` with ``||f - f_opt||_M <= 0.01 ||f_opt - f*||_M``
    (then its error is within 1 % of the optimum's, and it is that optimum, not an iterate
    passing the error on its way), ``f_opt`` the discrete optimum (:func:`mother_optimum`,
    read from ``optimum_file`` where given: a child process is handed the parent's). With
    ``target``, instead, at the first iterate whose error reaches it. ``solver="kkt"``:
    :func:`~prdp_fem.inverse.kkt.kkt_solve` (``K``, ``inner_rtol`` and ``preconditioner`` do
    not apply). ``solver="reduced"``: :func:`~prdp_fem.inverse.reduced.reduced_cg`, its
    inner state and adjoint solves ``K`` PCG iterations under PRDP (``K0 = dK = K``), or to
    the relative residual ``inner_rtol`` when given; ``preconditioner`` is the inner PCG's.
    At most ``max_iterations`` outer iterations (MINRES: ten times as many).
    """
    check_mother_options([n], target=target, K=K, inner_rtol=inner_rtol,
                         preconditioner=preconditioner, solver=solver)
    stop = None
    if target is None:
        f_opt = np.load(optimum_file) if optimum_file else mother_optimum_field(n)
    start = time.perf_counter()
    problem = mother_problem(n)
    inner_preconditioner = None if solver == "kkt" else \
        INNER_PRECONDITIONERS[preconditioner](problem)
    if target is None:
        stop, target = _near_optimum(problem, f_opt)
    assembly = time.perf_counter() - start
    if solver == "kkt":
        def error(field) -> float:
            return float(problem.parameter_error(field))

        result = kkt_solve(problem, rtol=0.0, iterations=10 * max_iterations,
                           callback=(lambda k, field: error(field) <= target)
                           if stop is None else (lambda k, field: stop(None, field)))
        return MotherSolve(
            n=n, dofs=problem.n_parameters, error=error(result.field), target=target,
            outer_iterations=result.iterations, inner_iterations=result.vcycles,
            riesz_iterations=0, final_K=0, assembly_s=assembly + result.setup_time,
            compile_s=0.0, solve_s=result.solve_time, solver=solver)
    result = reduced_cg(problem, refinement=_inner_refinement(K, inner_rtol),
                        iterations=max_iterations, preconditioner=inner_preconditioner,
                        callback=(lambda record, field: record.parameter_error <= target)
                        if stop is None else stop)
    last = result.history[-1]
    return MotherSolve(
        n=n, dofs=problem.n_parameters, error=last.parameter_error, target=target,
        outer_iterations=last.step,
        inner_iterations=last.primal_iterations + last.adjoint_iterations_total,
        riesz_iterations=result.riesz_iterations, final_K=last.iterations,
        assembly_s=assembly, compile_s=last.compile_time, solve_s=last.time, solver=solver)


def _near_optimum(problem: InverseProblem, f_opt: np.ndarray):
    """``(stop, error)``: the callback that stops within 1 % of the optimum's error of the
    optimum itself (see :func:`solve_mother`), and the optimum's relative error."""
    mass, truth = problem.parameter_mass.to_scipy(), np.asarray(problem.truth)
    scale = float(np.sqrt(truth @ (mass @ truth)))
    gap = f_opt - truth
    error = float(np.sqrt(gap @ (mass @ gap))) / scale

    def stop(record, field) -> bool:
        distance = np.asarray(field) - f_opt
        return float(np.sqrt(distance @ (mass @ distance))) / scale <= (TARGET_FACTOR - 1) * error

    return stop, TARGET_FACTOR * error


_OPTIMA: dict[int, np.ndarray] = {}  # mother_optimum_field's results in this process


def mother_optimum_field(n: int) -> np.ndarray:
    """The mother problem's discrete optimum ``f`` at size ``n``: the reduced-Hessian CG run
    to convergence (outer ``rtol = 1e-12``), every inner solve by AMG-PCG to ``rtol =
    1e-13`` (a test checks it against a sparse LU of the KKT system)."""
    if n not in _OPTIMA:
        problem = mother_problem(n)
        cycle = _amg_cycle(problem)
        result = reduced_cg(problem, refinement=converged(1e-13), iterations=300, rtol=1e-12,
                            preconditioner=cycle, riesz_rtol=1e-14)
        _OPTIMA[n] = np.asarray(result.field)
    return _OPTIMA[n]


def mother_optimum(n: int) -> float:
    """The relative L2 error of ``f`` against ``f*`` at the discrete optimum at size ``n``."""
    return _near_optimum(mother_problem(n), mother_optimum_field(n))[1] / TARGET_FACTOR


def _target(n: int, target: float | None) -> float:
    """``target``, or 1 % above the discrete optimum's error (computed once per size)."""
    if target is None:
        return TARGET_FACTOR * mother_optimum(n)
    if not (isinstance(target, float | int) and 0 < target < 1):
        raise SolverConfigError(f"--target {target!r}: expected a relative error in (0, 1)")
    return float(target)


# --------------------------------------------------------------------------------------
# the mother problem, one fresh process per run
# --------------------------------------------------------------------------------------

# the child times its own imports from its first statement; the parent times the whole process
_CHILD = (
    "import time; start = time.perf_counter()\n"
    "import sys\n"
    "from prdp_fem.bench.inverse import _mother_child\n"
    "_mother_child(start, sys.argv[1])\n"
)


def _mother_child(start: float, arguments: str) -> None:
    """Solve in this (fresh) process and print the phases as one JSON line, with the wall
    clock at the print (the parent times the exit from it)."""
    imported = time.perf_counter() - start
    enable_compilation_cache()  # as a user's script does for a warm second run
    solve = solve_mother(**json.loads(arguments))
    print(json.dumps({**solve._asdict(), "import_s": imported, "printed_at": time.time()}),
          flush=True)


class MotherBench(NamedTuple):
    """Medians over fresh-process runs at one size (seconds); the last run's solver figures."""

    n: int
    dofs: int
    target: float
    error: float
    outer_iterations: int
    inner_iterations: int
    riesz_iterations: int
    start_s: float      # interpreter start, and anything else outside the phases and the exit
    import_s: float
    assembly_s: float
    compile_s: float
    solve_s: float
    exit_s: float       # from the child's last print to its end, as the parent saw it
    whole_s: float      # wall time of the whole process, measured by the parent
    runs: int
    peer: PeerFigure | None
    cache: str = "cold"  # "cold": compiled in the process; "warm": loaded from a primed cache
    solver: str = "kkt"

    @property
    def ratio(self) -> float:
        """Whole-process time / the peer's (NaN where the peer's time is unknown)."""
        return self.whole_s / self.peer.seconds if self.peer else math.nan

    @property
    def goal_met(self) -> bool | None:
        """Time ratio and error both at the goal (None where there is no goal: no peer figure,
        or a warm cache, since the goal's time includes the compilation)."""
        if self.peer is None or math.isnan(self.peer.goal_ratio) or self.cache != "cold":
            return None
        return self.ratio <= self.peer.goal_ratio and self.error <= self.target


#: How a child finds its compiled program: compiled in the process, or loaded from a cache
#: that one untimed run filled (what a user's script gets from its second run on).
CACHES = ("cold", "warm")


def _child_environment(cache_directory: str | None = None) -> dict[str, str]:
    """This package first on the path; the package's persistent compilation cache in
    ``cache_directory``, or none at all (a cold start: the package's own cache, on by default,
    is switched off too, not only JAX's)."""
    environment = {**this_package_first(), CACHE_VARIABLE: cache_directory or "0"}
    return {key: value for key, value in environment.items()
            if key != "JAX_COMPILATION_CACHE_DIR"}


def compile_package_bytecode() -> bool:
    """Write the bytecode of this package's modules next to them, as ``pip install`` does for
    an installed package, whatever ``PYTHONDONTWRITEBYTECODE`` says; False where some module
    could not be written (a read-only tree).

    A process reads bytecode that exists even where it may not write any
    (``PYTHONDONTWRITEBYTECODE``, common in containers); without it every child of the
    mother benchmark compiled the 40 modules of the package it imports from source, 0.13 s of
    its import (median paired difference) that a user's process does not spend.
    The dependencies' bytecode came with their install.
    """
    return compileall.compile_dir(Path(__file__).resolve().parents[1], quiet=2)


def _run_child(arguments: dict, timeout: float, environment: dict[str, str]
               ) -> tuple[dict, float, float]:
    """The child's phases, its whole wall time and its exit: the interpreter's shutdown, whose
    garbage collections over JAX's objects took 0.27-0.35 s (a process that only imports
    JAX: 0.19 s; on 2 CPU cores)."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(arguments)],
                          capture_output=True, text=True, timeout=timeout, env=environment)
    whole, ended = time.perf_counter() - start, time.time()
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"mother benchmark process failed ({done.returncode}): {last}")
    phases = json.loads(done.stdout.strip().splitlines()[-1])
    # wall clocks of two processes on one machine; clamped in case the clock was stepped
    return phases, whole, min(max(ended - phases["printed_at"], 0.0), whole)


def mother_whole_process(n: int, *, repeats: int = 3, target: float | None = None,
                         K: int = DEFAULT_K, inner_rtol: float | None = None,
                         preconditioner: str = "jacobi", cache: str = "cold",
                         timeout: float = 600.0, peer_python: str | None = None,
                         solver: str = "kkt") -> MotherBench:
    """Median whole-process figures over ``repeats`` fresh processes solving at size ``n``.

    The settings are those of :func:`solve_mother`. ``cache="warm"``: the processes share a
    compilation cache of their own (a temporary directory), filled by one untimed process
    first, so they load the program a cold process compiles. ``peer_python``: the peer's
    interpreter (see :mod:`prdp_fem.bench.dolfin_adjoint_mother`); each of the project's
    processes is followed by one of the peer's, with its form compiler's cache cold or warm
    alike.
    """
    check_mother_options([n], repeats=repeats, target=target, K=K, inner_rtol=inner_rtol,
                         preconditioner=preconditioner, cache=cache, solver=solver)
    arguments = {"n": n, "target": target, "K": K, "inner_rtol": inner_rtol,
                 "preconditioner": preconditioner, "solver": solver}
    holder = tempfile.TemporaryDirectory(prefix="prdp-fem-optimum-")
    if target is None:  # the children stop near the optimum the parent computes once
        arguments["optimum_file"] = str(Path(holder.name) / "optimum.npy")
        np.save(arguments["optimum_file"], mother_optimum_field(n))
    target = _target(n, target)
    if not compile_package_bytecode():
        warnings.warn(f"the bytecode of {Path(__file__).parents[1]} could not be written: each "
                      "process compiles the package's modules (about 0.1 s more import)",
                      RuntimeWarning, stacklevel=2)
    warm = cache == "warm"
    own_cache = tempfile.TemporaryDirectory(prefix="prdp-fem-mother-cache-") if warm \
        else contextlib.nullcontext()
    peer_runs = []
    with holder, own_cache as directory, \
            tempfile.TemporaryDirectory(prefix="prdp-fem-peer-") as peer:
        environment = _child_environment(directory)
        if warm:
            _run_child(arguments, timeout, environment)  # fills the cache
            if peer_python:
                _run_peer(peer_python, n, timeout, str(Path(peer) / "warm"))
        runs = []
        for repeat in range(repeats):  # alternated: a slow spell of the machine hits both
            runs.append(_run_child(arguments, timeout, environment))
            if peer_python:
                peer_cache = Path(peer) / ("warm" if warm else f"cold-{repeat}")
                peer_runs.append(_run_peer(peer_python, n, timeout, str(peer_cache)))
    phases = ("import_s", "assembly_s", "compile_s", "solve_s")

    def median(values) -> float:
        return float(statistics.median(values))

    last = runs[-1][0]
    outside = [whole - shutdown - sum(run[p] for p in phases) for run, whole, shutdown in runs]
    return MotherBench(
        n=n, dofs=last["dofs"], target=target, error=last["error"],
        outer_iterations=last["outer_iterations"], inner_iterations=last["inner_iterations"],
        riesz_iterations=last["riesz_iterations"], start_s=median(outside),
        **{p: median([run[p] for run, _, _ in runs]) for p in phases},
        exit_s=median([shutdown for _, _, shutdown in runs]),
        whole_s=median([whole for _, whole, _ in runs]), runs=repeats,
        peer=None if not peer_runs else PeerFigure(
            median([whole for _, whole in peer_runs]), peer_runs[-1][0]["error"],
            GOALS.get(n, math.nan), peer_runs[-1][0]["evaluations"]),
        cache=cache, solver=solver)


#: the peer's script, run by the peer's Python from its path (it imports no prdp_fem)
PEER_SCRIPT = Path(__file__).with_name("dolfin_adjoint_mother.py")


def _run_peer(python: str, n: int, timeout: float, form_cache: str) -> tuple[dict, float]:
    """One fresh peer process at size ``n``: its printed figures and its whole wall time.
    ``form_cache``: its form compiler's (dijitso's) cache directory -- a new one is a cold
    start, as the project's processes compile their program."""
    environment = {**os.environ, "DIJITSO_CACHE_DIR": form_cache}
    start = time.perf_counter()
    done = subprocess.run([python, str(PEER_SCRIPT), str(n)], capture_output=True, text=True,
                          timeout=timeout, env=environment)
    whole = time.perf_counter() - start
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise SolverConfigError(f"the peer ({python}) failed at n = {n} ({done.returncode}): "
                                f"{last}; to install it: {PEER_INSTALL}")
    return json.loads(done.stdout.strip().splitlines()[-1]), whole


#: how to install the peer (printed where it is not given or fails)
PEER_INSTALL = ("apt-get install python3-dolfin python3-scipy; python3 -m venv "
                "--system-site-packages PEER_VENV; PEER_VENV/bin/pip install --no-deps "
                "dolfin-adjoint==2023.0.0 pyadjoint-ad==2023.0.0; then --peer-python "
                "PEER_VENV/bin/python")


# --------------------------------------------------------------------------------------
# PRDP saving on the built-in scenes, through the study
# --------------------------------------------------------------------------------------

SAVING_SCENES = ("mother", "inclusion", "plate_hole", "cube")


class SavingRow(NamedTuple):
    """One PRDP configuration against the scene's converged reference.

    Same target, both sides: the run reaches the converged run's final error ``e*`` at the
    first step from which its error stays within ``+-1 %`` of it (``reached_step``), and the
    savings are ``1 -`` its cost there / the converged run's cost to its *own* such step
    (wall time without compilation; CG iterations, validation solves included). A run that
    ends below the band has not reached it: ``ends_at_or_below`` says so apart, never as a
    saving.
    """

    scene: str
    run: str
    converged_s: float          # whole run
    converged_iterations: int
    prdp_s: float               # whole run
    prdp_iterations: int
    reached_step: int | None    # the study's: in the +-1 % band from here on (None: never)
    time_saving: float          # NaN when never reached
    iteration_saving: float
    ends_at_or_below: bool      # the final error is at most 1.01 e* (not a saving)
    converged_error: float
    prdp_error: float
    repeats: int = 1            # studies whose medians these are (see median_row)
    time_saving_low: float = math.nan   # the lowest and highest time_saving among them
    time_saving_high: float = math.nan
    seed: int | None = None     # the scene's inverse.seed, where it draws the data (_seeded)

    @property
    def error_difference(self) -> float:
        """(PRDP final error - converged final error) / converged final error."""
        return (self.prdp_error - self.converged_error) / self.converged_error

    @property
    def goal_met(self) -> bool:
        """BENCHMARKS.md read strictly: >= 80 % time saving, final error within +-1 %."""
        return self.time_saving >= SAVING_GOAL and abs(self.error_difference) <= ERROR_BAND



def saving_configurations(scene) -> list[str]:
    """The reference and the PRDP runs comparable with it (the order of the scene)."""
    if scene.study.kind != "inverse":
        raise SceneError(f"{scene.source}: study.kind = {scene.study.kind!r}; expected an "
                         "inverse study (the PRDP saving compares inversions)")
    runs = dict(scene.runs())
    reference = runs.get(scene.study.reference)
    if reference is None:
        raise SceneError(f"{scene.source}: study.reference = {scene.study.reference!r} is not "
                         f"one of its runs {list(runs)}; expected the converged baseline")
    compared = [name for name, variant in runs.items()
                if variant.refinement.kind in ("prdp", "adaptive")
                and variant.same_problem(reference)]
    if not compared:
        raise SceneError(f"{scene.source}: no PRDP run comparable with the reference "
                         f"{scene.study.reference!r}; expected a run with refinement.kind = "
                         "'prdp' on the same mesh, PDE, data and optimiser")
    # each run's own reference too: the converged run of its preconditioner
    references = {scene.study.reference} | {scene.reference_of(name) for name in compared}
    return [name for name in runs if name in references or name in compared]


def _restricted(scene, names: list[str]):
    """The scene with only the named runs (a scene without [[study.runs]] gets them spelled)."""
    runs = scene.study.runs or (("converged", json.dumps(
        {"refinement": {"kind": "converged"}})), (scene.name, "{}"))
    kept = tuple((name, overrides) for name, overrides in runs if name in names)
    return dataclasses.replace(scene, study=dataclasses.replace(scene.study, runs=kept))


def prdp_saving(scene, *, repeats: int = 1, out: str | Path | None = None,
                resume: bool = False, progress=None, client=None) -> list[SavingRow]:
    """The PRDP saving of every comparable PRDP run of ``scene`` (a loaded Scene).

    Runs the reference and those runs with :func:`~prdp_fem.studies.runner.run_study` into ``out``
    (a
    temporary directory when ``None``) and reads the figures from its summary and records.
    ``repeats > 1`` runs the study that many times (into ``out/repeat-<i>``), so the reference
    and the PRDP runs alternate, and returns each run's :func:`median_row`: on a shared 2-core
    machine one study's time saving moved by 10 points from run to run. ``resume``: the
    studies already in ``out`` keep their finished runs (read back, with the times measured
    when they ran) and run only the rest. ``client``: a ``dask.distributed.Client`` to run
    each study's configurations on (:func:`~prdp_fem.studies.runner.run_study`); runs that
    share a machine's cores slow each other, so their time savings compare contended runs.
    """
    from ..studies.runner import run_study  # here: they import matplotlib

    if not (isinstance(repeats, int) and not isinstance(repeats, bool) and repeats >= 1):
        raise SolverConfigError(f"repeats={repeats!r}: expected an integer >= 1")
    restricted = _restricted(scene, saving_configurations(scene))
    per_study = []
    with tempfile.TemporaryDirectory(prefix="prdp-saving-") as scratch:
        root = Path(out) if out is not None else Path(scratch)
        for index in range(repeats):
            directory = root if repeats == 1 else root / f"repeat-{index + 1}"
            result = run_study(restricted, directory, resume=resume, progress=progress,
                               client=client)
            per_study.append(saving_rows(scene.name, scene.study.reference, result.summary))
    seed = scene.inverse.seed if _seeded(scene) else None
    return [median_row([row._replace(seed=seed) for row in rows])
            for rows in zip(*per_study, strict=True)]


def median_row(rows) -> SavingRow:
    """One run's :class:`SavingRow` s from repeated studies as one: every figure's median.

    A step or iteration count that is ``None`` (never reached) in any study is ``None``, and
    a NaN saving makes the median NaN: a run counts as reaching ``e*`` only if it always did.
    ``time_saving_low`` / ``_high`` keep the spread of the time saving.
    """
    first = rows[0]
    if any((row.scene, row.run, row.seed) != (first.scene, first.run, first.seed)
           for row in rows):
        raise ValueError("median_row: rows of different runs")

    def count(values):
        if any(value is None for value in values):
            return None
        return round(statistics.median(values))

    def number(values):
        return float(np.median(np.asarray(values, dtype=float)))

    fields = dict(zip(SavingRow._fields, zip(*rows, strict=True), strict=True))
    merged = {name: count(values) if name in _COUNT_FIELDS
              else all(values) if name == "ends_at_or_below" else number(values)
              for name, values in fields.items() if name in _MEDIAN_FIELDS}
    savings = np.asarray(fields["time_saving"], dtype=float)
    return SavingRow(first.scene, first.run, **merged, repeats=len(rows),
                     time_saving_low=float(np.min(savings)),
                     time_saving_high=float(np.max(savings)), seed=first.seed)


_COUNT_FIELDS = frozenset({"converged_iterations", "prdp_iterations", "reached_step"})
# the measured figures: every field after the run's name up to the repeat bookkeeping
_MEDIAN_FIELDS = frozenset(SavingRow._fields[2:SavingRow._fields.index("repeats")])


def saving_rows(scene_name: str, reference: str, summary: list[dict]) -> list[SavingRow]:
    """:class:`SavingRow` s of every run but the converged references, each against its own
    (the summary's ``reference``: the converged run of its preconditioner, else
    ``reference``), from a study's summary rows (as ``run_study`` returns them): the
    study's own figures, read, not recomputed. The error columns compare with ``reference``
    (the target)."""
    rows = {row["run"]: row for row in summary}
    target = rows[reference]
    references = {reference} | {row.get("reference", reference) for row in summary}
    return [SavingRow(
        scene_name, name, base["time_s"], base["cg_iterations"], row["time_s"],
        row["cg_iterations"], row["reached_step"] if row["reached_step"] != "" else None,
        row["time_saving"], row["iteration_saving"], bool(row["ends_at_or_below"]),
        target["final_error"], row["final_error"])
        for name, row in rows.items() if name not in references
        for base in (rows[row.get("reference", reference)],)]


def _seeded(scene) -> bool:
    """Whether ``inverse.seed`` draws anything: the noise, or the random sensor vertices."""
    spec = scene.inverse
    random_sensors = spec.observations == "sensors" and isinstance(spec.sensors, int)
    return spec.data is None and (spec.noise > 0 or random_sensors)


def seed_variants(scene, seeds) -> list[tuple[int | None, Any]]:
    """``(seed, scene)`` for every seed in ``seeds``: the scene with ``inverse.seed = seed``
    (other noise, other random sensors; everything else as the scene's file says: the
    variants are parsed again from its table, so a scene edited in Python with
    ``dataclasses.replace`` loses those edits).

    One ``(None, scene)`` where the scene's data do not depend on the seed (no noise and no
    random sensors: every seed would give the same study) or where ``seeds`` is empty.
    """
    from ..scene.spec import with_overrides

    seeds = [] if seeds is None else list(seeds)
    if any(not isinstance(seed, int | np.integer) or isinstance(seed, bool) or seed < 0
           for seed in seeds):
        raise SolverConfigError(f"seeds={seeds!r}: expected integers >= 0")
    seeds = [int(seed) for seed in seeds]
    if len(set(seeds)) != len(seeds):
        raise SolverConfigError(f"seeds={seeds!r}: expected distinct seeds")
    if scene.inverse is None:
        raise SceneError(f"{scene.source}: no [inverse] section; expected an inverse scene")
    if not seeds or not _seeded(scene):
        return [(None, scene)]
    return [(seed, with_overrides(scene, {"inverse": {"seed": seed}})) for seed in seeds]


class SeedSummary(NamedTuple):
    """One run of one scene over the problem instances of :func:`seed_variants`."""

    scene: str
    run: str
    instances: int
    met: int                    # instances meeting the goal (SavingRow.goal_met)
    reached: int                # instances that reach the +-1 % band at all
    ends_below: int             # instances whose final error is at most 1.01 e* (not a saving)
    time_saving: float          # medians over the instances that reach the band (NaN: none)
    iteration_saving: float
    error_difference: float     # median over all instances


def seed_summary(rows) -> list[SeedSummary]:
    """Per ``(scene, run)``, in the order of ``rows``: how many instances meet the goal, and
    the medians of their savings (over the instances that reach ``e*``) and final errors."""
    groups: dict[tuple[str, str], list[SavingRow]] = {}
    for row in rows:
        groups.setdefault((row.scene, row.run), []).append(row)

    def median(values) -> float:
        finite = [v for v in values if not math.isnan(v)]
        return float(np.median(finite)) if finite else math.nan

    return [SeedSummary(
        scene, run, len(group), sum(r.goal_met for r in group),
        sum(r.reached_step is not None for r in group),
        sum(bool(r.ends_at_or_below) for r in group),
        median([r.time_saving for r in group]), median([r.iteration_saving for r in group]),
        median([r.error_difference for r in group]))
        for (scene, run), group in groups.items()]
