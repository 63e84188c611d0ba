"""Memory of a gradient through truncated PCG: unrolled, unrolled with checkpoints, implicit.

``memory_cost`` measures, for each gradient mode and ``K``, the peak resident memory and the
time of one jitted ``jax.grad`` of ``J(kappa) = w . x_K(kappa)``, where ``x_K`` is ``K``
Jacobi-PCG iterations on the P1 Poisson problem ``-div(kappa grad u) = f`` on
``unit_square(side)`` (P0 kappa, zero Dirichlet data; ``side = 257``: 65536 dofs).

What the modes should store in reverse mode, in n-vectors (``R``: what one iteration saves,
``c``: the CG state kept per checkpoint; both a few):

* ``unrolled``: every iteration's intermediates, ``K R``;
* ``checkpointed``: one state per segment of ``s`` iterations and one segment's
  intermediates, ``(K / s) c + s R`` (``s = ceil(sqrt(K))`` unless given): ``O(sqrt(K))``;
* ``implicit``: the solution and the adjoint solve's state, independent of ``K``.

Method. Peaks of different configurations must not mix and a process's high-water mark never
goes down, so every configuration runs in a fresh ``python -m prdp_fem.bench.memory``. There
it builds the problem, compiles the gradient, and takes as its *baseline* the resident set
right before the first gradient evaluation (problem built, nothing differentiated yet); on
Linux it then resets the kernel's high-water mark to that (``/proc/self/clear_refs``), so
that the compiler's own transient peak, which can exceed a small gradient's, does not hide
it. ``peak_mb`` is the high-water mark after one gradient evaluation minus the baseline. Where
the mark cannot be reset, ``ru_maxrss`` is used and ``hwm_reset`` is ``False``: small peaks
then read as 0. XLA's own estimate of the gradient's scratch memory
(``Compiled.memory_analysis``) is reported next to it, and a configuration whose estimate
exceeds ``max_mb`` is compiled but not run (so one huge ``K`` cannot exhaust the machine).

The allocator. XLA's CPU runtime takes a gradient's scratch as one block per evaluation
(``posix_memalign`` from a worker thread) and frees it after. glibc serves a block that large
with a fresh ``mmap`` (a thread's arena holds at most 64 MB, and above 32 MB the main arena
maps too), so every evaluation faults its scratch in page by page. With
``allocator="reuse"`` the child runs under :data:`REUSE_ENVIRONMENT` (one arena, no
``mmap``, no trimming), so the block comes back from the heap already mapped;
``faults_per_call`` (minor page faults per evaluation after the first) shows which happened.
``"default"`` runs without those three variables. A reused heap also holds what compiling
freed, so under ``"reuse"`` ``peak_mb`` counts only memory beyond it. glibc only (Linux);
elsewhere the variables are ignored.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import NamedTuple

import numpy as np

from ..errors import SolverConfigError
from .cg import this_package_first

__all__ = ["ALLOCATORS", "MODES", "REUSE_ENVIRONMENT", "MemoryCost", "child_environment",
           "memory_cost"]

MODES = ("unrolled", "checkpointed", "implicit")
ALLOCATORS = ("default", "reuse")
#: glibc's allocator, told to keep freed memory mapped: every thread in the main arena (a
#: thread's own arena cannot hold a block above 64 MB and maps it), no ``mmap`` for large
#: blocks, and no trimming of the heap's top after a free (below 4 GiB)
REUSE_ENVIRONMENT: Mapping[str, str] = MappingProxyType({
    "MALLOC_ARENA_MAX": "1", "MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": str(2**32)})
MB = 1e6  # bytes; the table is in decimal megabytes
HIGH_WATER_RESET = "5"  # written to /proc/self/clear_refs: VmHWM := VmRSS (Linux >= 4.0)


class MemoryCost(NamedTuple):
    """One configuration's row; ``peak_mb`` and ``gradient_s`` are NaN when it was not run."""

    mode: str
    iterations: int
    segment: int | None  # iterations per checkpointed segment (checkpointed mode only)
    n_dofs: int
    vector_mb: float  # one float64 n-vector, for scale
    peak_mb: float  # peak resident memory of one gradient evaluation above the baseline
    baseline_mb: float  # resident memory before it: the problem built, the gradient compiled
    xla_temp_mb: float  # XLA's scratch-buffer estimate for the compiled gradient
    gradient_s: float  # median wall time of one gradient evaluation
    hwm_reset: bool  # the high-water mark was reset to the baseline before the run
    ran: bool  # False: xla_temp_mb exceeded max_mb, the gradient was only compiled
    allocator: str = "default"  # "default" (glibc's settings) or "reuse" (REUSE_ENVIRONMENT)
    faults_per_call: float = float("nan")  # minor page faults per evaluation after the first
    # the fewest of those in one evaluation: 0 where the scratch was reused even once (its
    # release may still be on its way when the next evaluation allocates, which then faults)
    fewest_faults: float = float("nan")


def memory_cost(side: int = 257, iterations: tuple[int, ...] = (10, 100, 1000), *,
                modes: tuple[str, ...] = MODES, segment: int | None = None, repeats: int = 3,
                max_mb: float = 4000.0, allocators: tuple[str, ...] = ("default",),
                on_row=None) -> list[MemoryCost]:
    """One :class:`MemoryCost` per ``(mode, K, allocator)``, each in a fresh subprocess.

    ``segment`` sets the checkpointed segment length (default ``ceil(sqrt(K))``);
    ``repeats`` gradient evaluations are timed (the first is the one whose memory is
    measured); a configuration whose XLA scratch estimate exceeds ``max_mb`` is not run.
    ``allocators`` (some of :data:`ALLOCATORS`) run one after the other for each
    configuration, so that a comparison is interleaved. ``on_row`` is called with each row as
    it lands.
    """
    _check_options(side, iterations, modes, segment, repeats, max_mb, allocators)
    rows = []
    for mode in modes:
        for k in iterations:
            for allocator in allocators:
                row = _measure_in_subprocess(
                    dict(side=side, iterations=k, mode=mode, segment=segment, repeats=repeats,
                         max_mb=max_mb), allocator)
                rows.append(row)
                if on_row is not None:
                    on_row(row)
    return rows


def _check_options(side, iterations, modes, segment, repeats, max_mb, allocators) -> None:
    def is_int(value) -> bool:
        return isinstance(value, int | np.integer) and not isinstance(value, bool)

    if not is_int(side) or side < 2:
        raise SolverConfigError(f"side={side!r}: expected an integer >= 2")
    if not iterations or not all(is_int(k) and k >= 0 for k in iterations):
        raise SolverConfigError(f"iterations={list(iterations)!r}: expected integers >= 0")
    bad_modes = [m for m in modes if m not in MODES]
    if not modes or bad_modes:
        raise SolverConfigError(f"modes={list(modes)!r}: expected some of {list(MODES)}")
    if segment is not None and not (is_int(segment) and segment >= 1):
        raise SolverConfigError(f"segment={segment!r}: expected an integer >= 1 or None "
                                "(ceil(sqrt(K)))")
    if not is_int(repeats) or repeats < 1:
        raise SolverConfigError(f"repeats={repeats!r}: expected an integer >= 1")
    if isinstance(max_mb, bool) or not isinstance(max_mb, int | float) or not max_mb > 0:
        raise SolverConfigError(f"max_mb={max_mb!r}: expected a number > 0")
    bad_allocators = [a for a in allocators if a not in ALLOCATORS]
    if not allocators or bad_allocators:
        raise SolverConfigError(f"allocators={list(allocators)!r}: expected some of "
                                f"{list(ALLOCATORS)}")


def child_environment(allocator: str, environ: Mapping[str, str] = os.environ) -> dict:
    """The child's environment: this package first on the path and the allocator's settings.

    >>> env = child_environment("default", {"MALLOC_ARENA_MAX": "2", "HOME": "/h"})
    >>> "MALLOC_ARENA_MAX" in env, env["HOME"]
    (False, '/h')
    >>> child_environment("reuse", {})["MALLOC_MMAP_MAX_"]
    '0'
    """
    env = {key: value for key, value in this_package_first(environ).items()
           if key not in REUSE_ENVIRONMENT}
    return {**env, **REUSE_ENVIRONMENT} if allocator == "reuse" else env


def _measure_in_subprocess(config: dict, allocator: str = "default") -> MemoryCost:
    env = child_environment(allocator)
    done = subprocess.run([sys.executable, "-m", "prdp_fem.bench.memory", json.dumps(config)],
                          capture_output=True, text=True, env=env, check=False)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise RuntimeError(f"memory measurement {config} failed with exit status "
                           f"{done.returncode}: {last}")
    return MemoryCost(**{**json.loads(done.stdout.strip().splitlines()[-1]),
                         "allocator": allocator})


# --------------------------------------------------------------------------------------
# the child: one configuration in this process
# --------------------------------------------------------------------------------------


def _resident_mb() -> tuple[float, float]:
    """``(current, peak)`` resident set in MB: VmRSS and VmHWM, else ``ru_maxrss`` twice."""
    try:
        fields = dict(line.split(":", 1) for line in
                      Path("/proc/self/status").read_text().splitlines() if ":" in line)
        return (int(fields["VmRSS"].split()[0]) * 1024 / MB,
                int(fields["VmHWM"].split()[0]) * 1024 / MB)
    except (OSError, KeyError, ValueError):
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        peak_mb = peak / MB if sys.platform == "darwin" else peak * 1024 / MB  # bytes / KiB
        return peak_mb, peak_mb


def _reset_high_water_mark() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text(HIGH_WATER_RESET)
    except OSError:
        return False
    return True


def _gradient_problem(side: int, iterations: int, mode: str, segment: int | None):
    """``(jitted grad of J, kappa, n_dofs, segment used)`` on the P1 Poisson problem."""
    import jax
    import jax.numpy as jnp

    from ..fem.discretization import discretize
    from ..linalg.cg import TruncatedCG, segment_length, solve
    from ..mesh.generators import unit_square

    disc = discretize(unit_square(side), element="P1", kappa_space="P0")
    system = disc.system  # built here, outside the trace
    kappa = jnp.ones(disc.n_kappa)
    b = jnp.asarray(disc.rhs(np.ones(disc.n_kappa), disc.interpolate(
        lambda x: np.sin(np.pi * x[0]) * x[1])))
    weights = jnp.asarray(np.cos(np.arange(disc.n_free)))  # J = w . x_K, a fixed functional
    checkpoint = False if mode != "checkpointed" else (True if segment is None else segment)
    solver = TruncatedCG(iterations, gradient="implicit" if mode == "implicit" else "unrolled",
                         checkpoint=checkpoint)

    def loss(kappa):
        return weights @ solve(system.operator(kappa), b, solver).x

    gradient = jax.jit(jax.grad(loss))
    return gradient, kappa, disc.n_free, segment_length(iterations, checkpoint)


def measure(side: int, iterations: int, mode: str, segment: int | None, repeats: int,
            max_mb: float) -> MemoryCost:
    """One configuration in *this* process (meant for a fresh one: see the module docstring)."""
    import jax

    gradient, kappa, n_dofs, used_segment = _gradient_problem(side, iterations, mode, segment)
    compiled = gradient.lower(kappa).compile()
    analysis = compiled.memory_analysis()
    xla_temp_mb = float("nan") if analysis is None else analysis.temp_size_in_bytes / MB
    baseline_mb, _ = _resident_mb()
    hwm_reset = _reset_high_water_mark()
    ran = not xla_temp_mb > max_mb
    peak_mb = gradient_s = faults_per_call = fewest_faults = float("nan")
    if ran:
        times, faults = [], []
        for _ in range(repeats):
            faults_before, tic = _minor_faults(), time.perf_counter()
            jax.block_until_ready(compiled(kappa))
            times.append(time.perf_counter() - tic)
            faults.append(_minor_faults() - faults_before)
            if len(times) == 1:  # the timed repeats reuse the same buffers: read it once
                peak_mb = max(_resident_mb()[1] - baseline_mb, 0.0)
        if repeats > 1:
            faults_per_call, fewest_faults = float(np.mean(faults[1:])), float(min(faults[1:]))
        gradient_s = float(np.median(times))
    return MemoryCost(mode, iterations, used_segment, n_dofs, 8 * n_dofs / MB, peak_mb,
                      baseline_mb, xla_temp_mb, gradient_s, hwm_reset, ran,
                      faults_per_call=faults_per_call, fewest_faults=fewest_faults)


def _minor_faults() -> int:
    """Minor page faults of this process so far, all threads (first touches of fresh pages)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def _main(argv: list[str]) -> int:
    config = json.loads(argv[0])
    print(json.dumps(measure(**config)._asdict()))
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
