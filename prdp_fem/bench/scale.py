"""Figures at scale (``prdp-fem bench scale``): an inversion from 250k state dofs up, and the
sharded PCG iteration over 1, 2 and 4 devices.

``inversion_at_scale`` runs the main job's physics on a big mesh: recover log kappa from the
noisy full state (1 % noise), ``-div(e^m grad u) = 1``, ``u = 0`` on the boundary, P1 state
and coefficient, H1 regulariser (alpha = 1e-5), the truth of the ``cube_kappa`` scene (its
z terms dropped in 2-D), L-BFGS with a Polyak first step, AMG-PCG (one V-cycle, the
hierarchy built at the initial kappa; its setup counts as run time). Meshes: ``square:N``
(``unit_square(N)``, ``(N - 1)^2`` free dofs) or ``cube:N`` (``unit_cube(N)``,
``(N - 1)^3``). The converged run (CG to ``rtol`` 1e-10) and the PRDP run (``K0 = 4``,
``dK = 2``, as the main job) run ``steps`` steps each. The saving compares each run's own
time to the converged run's final error with the converged run's own time to it (the first
step from which it stays in the 1 % band, as :mod:`prdp_fem.inverse.comparison` reads it).
PRDP's arrival is read two ways: inside the band (``prdp_to_target_s``), and at or below
its top (``prdp_at_or_below_s``: an error that ends lower than the converged run's counts,
as ``study.reached = "at_or_below"`` reads it). Each mesh runs in a fresh process
(``python -m prdp_fem.bench.scale``), so ``peak_rss_gb`` (the process's high-water mark:
mesh, assembly, reference solve, compiled programs, both runs) is its own.

``sharded_iteration`` times one Jacobi-PCG iteration of a 2-D P1 operator on one device
(the plain ELL kernel) and spread over 1, 2 and 4 devices of a ``jax.sharding.Mesh``
(:mod:`prdp_fem.linalg.sharding`), in one process started with as many forced host devices;
the configurations alternate ``repeats`` times (medians) and each ratio is against the
one-device time of the same repeat. On a CPU the forced devices share the machine's cores:
these figures are the overhead of the halo exchange and the cross-device reductions, not a
speed-up.
"""

from __future__ import annotations

import json
import math
import os
import resource
import statistics
import subprocess
import sys
import time
from typing import NamedTuple

import numpy as np

from ..errors import SolverConfigError
from .cg import this_package_first

__all__ = ["InversionAtScale", "ShardedIteration", "inversion_at_scale", "parse_mesh",
           "scale_problem", "sharded_iteration"]

ALPHA = 1e-5
NOISE = 0.01
# the cube_kappa scene's truth; in 2-D its z terms are dropped
TRUTH_2D = ("log(2 + 1.5*exp(-20*((x - 0.4)**2 + (y - 0.6)**2))"
            " - exp(-20*((x - 0.7)**2 + (y - 0.3)**2)))")
TRUTH_3D = ("log(2 + 1.5*exp(-20*((x - 0.4)**2 + (y - 0.6)**2 + (z - 0.5)**2))"
            " - exp(-20*((x - 0.7)**2 + (y - 0.3)**2 + (z - 0.4)**2)))")


class InversionAtScale(NamedTuple):
    mesh: str
    dofs: int                   # free state dofs
    parameters: int
    steps: int
    setup_s: float              # mesh, assembly, reference solve, data
    converged_step_s: float     # median time of one optimiser step, compilation excluded
    prdp_step_s: float
    converged_to_target_s: float  # each run's own time to the converged run's final error
    prdp_to_target_s: float
    time_saving: float          # 1 - prdp / converged, both to the target
    iteration_saving: float
    prdp_at_or_below_s: float   # PRDP's time to stay at or below (1 + 1 %) the target
    at_or_below_saving: float   # 1 - that / the converged run's own time to the target
    converged_reached_step: int  # where the converged run entered its final band for good
    converged_error: float      # final relative parameter errors
    prdp_error: float
    final_K: int
    compile_s: float            # both runs' programs
    peak_rss_gb: float          # the process's high-water mark


class ShardedIteration(NamedTuple):
    devices: int                # 0: one device, no partition (the plain kernel)
    dofs: int
    halo: int                   # values a device receives per product (largest)
    iteration_ms: float         # median time of one PCG iteration
    ratio: float                # median of the per-repeat ratios to the one-device time


def parse_mesh(spec: str) -> tuple[str, int]:
    """``"square:N"`` or ``"cube:N"`` -> ``(kind, N)`` (a SolverConfigError otherwise)."""
    kind, _, size = spec.partition(":")
    if kind not in ("square", "cube") or not size.isdigit() or int(size) < 3:
        raise SolverConfigError(f"mesh {spec!r}: expected square:N or cube:N with N >= 3 "
                                "cells per side (e.g. square:1001, about 1M dofs)")
    return kind, int(size)


def scale_problem(kind: str, n: int, seed: int = 1):
    """The inverse problem on ``unit_square(n)`` / ``unit_cube(n)`` (see the module)."""
    from ..fem.discretization import discretize
    from ..fem.observations import full_field, with_noise
    from ..fem.reference import amg_solve
    from ..inverse.driver import inverse_problem
    from ..mesh.generators import unit_cube, unit_square
    from ..scene.expressions import compile_field

    mesh = unit_square(n) if kind == "square" else unit_cube(n)
    disc = discretize(mesh, element="P1", kappa_space="P1", dirichlet=0.0)
    truth = compile_field(TRUTH_2D if kind == "square" else TRUTH_3D, where="truth")
    m_true = disc.interpolate_kappa(truth)
    f = np.ones(disc.n_dofs)
    kappa = np.exp(m_true)
    u = disc.expand(amg_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f), rtol=1e-12).x)
    data = with_noise(full_field(disc, u_true=u), NOISE, seed)
    return inverse_problem(disc, data, unknown="log_kappa", alpha=ALPHA,
                           regularization="h1", known=f, truth=m_true)


def inversion_at_scale(meshes: list[str], steps: int = 100) -> list[InversionAtScale]:
    """One row per mesh spec, each measured in a fresh process."""
    for spec in meshes:
        parse_mesh(spec)
    return [_in_child(["inversion", spec, str(steps)], InversionAtScale)[0] for spec in meshes]


def sharded_iteration(n: int = 501, devices: tuple[int, ...] = (1, 2, 4), iterations: int = 50,
                      repeats: int = 5) -> list[ShardedIteration]:
    """Rows for one device (``devices = 0``) and each count in ``devices`` (one process)."""
    if n < 3 or iterations < 1 or repeats < 1 or not devices or min(devices) < 1:
        raise SolverConfigError("sharded_iteration: expected n >= 3, iterations >= 1, "
                                "repeats >= 1 and device counts >= 1")
    return _in_child(["sharded", str(n), ",".join(map(str, devices)), str(iterations),
                      str(repeats)], ShardedIteration, devices=max(devices))


def _in_child(argv: list[str], row: type, devices: int | None = None) -> list:
    """The rows ``python -m prdp_fem.bench.scale ARGV`` prints, in a fresh process (with
    ``devices`` forced host devices)."""
    env = this_package_first(dict(os.environ))
    if devices is not None:
        env["XLA_FLAGS"] = (f"{env.get('XLA_FLAGS', '')} "
                            f"--xla_force_host_platform_device_count={devices}")
    done = subprocess.run([sys.executable, "-m", "prdp_fem.bench.scale", *argv], env=env,
                          capture_output=True, text=True)
    if done.returncode:
        raise RuntimeError(f"bench scale {' '.join(argv)} failed: {done.stderr[-2000:]}")
    return [row(**json.loads(line)) for line in done.stdout.splitlines()
            if line.startswith("{")]


def _measure_inversion(spec: str, steps: int) -> InversionAtScale:
    from ..inverse.comparison import settled
    from ..inverse.driver import invert
    from ..inverse.refinement import converged, prdp
    from ..linalg.amg import RebuiltAMG
    from ..optim.linesearch import lbfgs

    start = time.perf_counter()
    problem = scale_problem(*parse_mesh(spec))
    setup = time.perf_counter() - start
    shared = dict(preconditioner=RebuiltAMG(None), optimizer=lbfgs(first_step="polyak"),
                  steps=steps)
    conv = invert(problem, refinement=converged(1e-10), **shared).history
    fast = invert(problem, refinement=prdp(K0=4, dK=2, stall_on_failure=True),
                  **shared).history
    target = conv[-1].parameter_error
    base = settled(conv, target)  # the converged run's own arrival: inside its band

    def reach(at_or_below: bool) -> tuple[float, float, float]:
        hit = settled(fast, target, at_or_below=at_or_below)
        if hit is None or base is None:
            return math.nan, math.nan, math.nan
        return (hit.time, 1 - hit.time / base.time,
                1 - hit.total_iterations / base.total_iterations)

    (band_s, band_saving, band_its), (below_s, below_saving, _) = reach(False), reach(True)
    return InversionAtScale(
        mesh=spec, dofs=problem.system.n_free, parameters=problem.n_parameters, steps=steps,
        setup_s=setup, converged_step_s=conv[-1].time / steps, prdp_step_s=fast[-1].time / steps,
        converged_to_target_s=base.time if base else math.nan, prdp_to_target_s=band_s,
        time_saving=band_saving, iteration_saving=band_its, prdp_at_or_below_s=below_s,
        at_or_below_saving=below_saving, converged_reached_step=base.step if base else -1,
        converged_error=target, prdp_error=fast[-1].parameter_error,
        final_K=fast[-1].iterations,
        compile_s=conv[-1].compile_time + fast[-1].compile_time, peak_rss_gb=_peak_rss_gb())


def _peak_rss_gb() -> float:
    kilobytes = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kB on Linux
    return kilobytes / 2 ** 20


def _measure_sharded(n: int, devices: tuple[int, ...], iterations: int,
                     repeats: int) -> list[ShardedIteration]:
    import jax
    import jax.numpy as jnp
    from jax.sharding import Mesh

    from ..fem.discretization import discretize
    from ..linalg.cg import TruncatedCG, solve
    from ..linalg.sharding import shard
    from ..mesh.generators import unit_square

    disc = discretize(unit_square(n), element="P1", kappa_space="P1", dirichlet=0.0)
    kappa = jnp.asarray(np.exp(disc.interpolate_kappa(lambda x: np.sin(3 * x[0]) * x[1])))
    matrix = disc.system.operator(kappa)
    b = disc.system.rhs(kappa, jnp.ones(disc.n_dofs))
    solver = TruncatedCG(iterations)
    program = jax.jit(lambda A, b: solve(A, b, solver).x)
    operators = {0: matrix}
    for count in devices:
        operators[count] = shard(matrix, Mesh(np.array(jax.devices()[:count]), ("dofs",)))
    for A in operators.values():
        program(A, b).block_until_ready()  # compiles (untimed)
    seconds = {count: [] for count in operators}
    for _ in range(repeats):
        for count, A in operators.items():
            start = time.perf_counter()
            program(A, b).block_until_ready()
            seconds[count].append(time.perf_counter() - start)
    rows = []
    for count, A in operators.items():
        halo = 0 if count == 0 else sum(s.shape[0] for s in A.layout.halo.sends) // count
        ratios = [t / t0 for t, t0 in zip(seconds[count], seconds[0], strict=True)]
        rows.append(ShardedIteration(count, matrix.shape[0], halo,
                                     1e3 * statistics.median(seconds[count]) / iterations,
                                     statistics.median(ratios)))
    return rows


def _main(argv: list[str]) -> int:
    if argv[0] == "inversion":
        rows = [_measure_inversion(argv[1], int(argv[2]))]
    else:
        devices = tuple(int(d) for d in argv[2].split(","))
        rows = _measure_sharded(int(argv[1]), devices, int(argv[3]), int(argv[4]))
    for row in rows:
        print(json.dumps(row._asdict()))
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
