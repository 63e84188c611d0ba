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
goes down, so every configuration runs in a fresh ``python -m prdp_fem.bench_memory``. There
it builds the problem, compiles the gradient, and takes as its *baseline* the resident set
right before the first gradient evaluation (problem built, nothing differentiated yet); on
Linux it then resets the kernel's high-water mark to that (``/proc/self/clear_refs``), so
that the compiler's own transient peak, which can exceed a small gradient's, does not hide
it. ``peak_mb`` is the high-water mark after one gradient evaluation minus the baseline. Where
the mark cannot be reset, ``ru_maxrss`` is used and ``hwm_reset`` is ``False``: small peaks
then read as 0. XLA's own estimate of the gradient's scratch memory
(``Compiled.memory_analysis``) is reported next to it, and a configuration whose estimate
exceeds ``max_mb`` is compiled but not run (so one huge ``K`` cannot exhaust the machine).
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .errors import SolverConfigError

__all__ = ["MODES", "MemoryCost", "memory_cost"]

MODES = ("unrolled", "checkpointed", "implicit")
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


def memory_cost(side: int = 257, iterations: tuple[int, ...] = (10, 100, 1000), *,
                modes: tuple[str, ...] = MODES, segment: int | None = None, repeats: int = 3,
                max_mb: float = 4000.0, on_row=None) -> list[MemoryCost]:
    """One :class:`MemoryCost` per ``(mode, K)``, each measured in a fresh subprocess.

    ``segment`` sets the checkpointed segment length (default ``ceil(sqrt(K))``);
    ``repeats`` gradient evaluations are timed (the first is the one whose memory is
    measured); a configuration whose XLA scratch estimate exceeds ``max_mb`` is not run.
    ``on_row`` is called with each row as it lands.
    """
    _check_options(side, iterations, modes, segment, repeats, max_mb)
    rows = []
    for mode in modes:
        for k in iterations:
            row = _measure_in_subprocess(dict(side=side, iterations=k, mode=mode,
                                              segment=segment, repeats=repeats, max_mb=max_mb))
            rows.append(row)
            if on_row is not None:
                on_row(row)
    return rows


def _check_options(side, iterations, modes, segment, repeats, max_mb) -> None:
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


def _measure_in_subprocess(config: dict) -> MemoryCost:
    # the child imports this very package, whichever one is installed
    package_parent = str(Path(__file__).resolve().parent.parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [package_parent, *filter(None, [os.environ.get("PYTHONPATH")])])}
    done = subprocess.run([sys.executable, "-m", "prdp_fem.bench_memory", json.dumps(config)],
                          capture_output=True, text=True, env=env, check=False)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise RuntimeError(f"memory measurement {config} failed with exit status "
                           f"{done.returncode}: {last}")
    return MemoryCost(**json.loads(done.stdout.strip().splitlines()[-1]))


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

    from .cg import TruncatedCG, segment_length, solve
    from .discretization import discretize
    from .generators import unit_square

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
    peak_mb = gradient_s = float("nan")
    if ran:
        times = []
        for _ in range(repeats):
            tic = time.perf_counter()
            jax.block_until_ready(compiled(kappa))
            times.append(time.perf_counter() - tic)
            if len(times) == 1:  # the timed repeats reuse the same buffers: read it once
                peak_mb = max(_resident_mb()[1] - baseline_mb, 0.0)
        gradient_s = float(np.median(times))
    return MemoryCost(mode, iterations, used_segment, n_dofs, 8 * n_dofs / MB, peak_mb,
                      baseline_mb, xla_temp_mb, gradient_s, hwm_reset, ran)


def _main(argv: list[str]) -> int:
    config = json.loads(argv[0])
    print(json.dumps(measure(**config)._asdict()))
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
