"""Throughput of batched inversion (``prdp-fem bench batch``).

``batch_throughput`` solves ``members`` inverse problems that differ in their data -- the
mother problem's state observed in full with 1 % noise, one noise seed per member -- three
ways, alternated ``repeats`` times: one :func:`~prdp_fem.inverse.batch.invert_batch` call
in each of its modes (``vmap``: the members together; ``map``: in turn inside the one
program), and a Python loop of :func:`~prdp_fem.inverse.driver.invert` calls (each reusing
the one compiled step, as a script looping over data sets does). All run the same optimiser,
controller and number of steps, each member under its own PRDP controller; all are timed
warm (their programs compiled by an untimed run first, the batched program's compile time
reported apart). Reported per mode: the medians of the batch's and the loop's wall time,
problems per second, the median of the per-repeat ratios loop / batch, and the largest
difference between a member's result and its single run's.
"""

from __future__ import annotations

import statistics
import time
from functools import partial
from typing import NamedTuple

import numpy as np

from ..errors import SolverConfigError
from ..fem.discretization import discretize
from ..fem.observations import full_field, with_noise
from ..fem.reference import direct_solve
from ..inverse.batch import MODES, invert_batch
from ..inverse.driver import InverseProblem, inverse_problem, invert
from ..inverse.refinement import Refinement, prdp
from ..mesh.generators import unit_square

__all__ = ["BatchThroughput", "batch_throughput", "noise_batch"]


class BatchThroughput(NamedTuple):
    members: int
    mode: str               # invert_batch's mode: "vmap" or "map"
    dofs: int
    batch_s: float          # median wall time of one invert_batch call
    loop_s: float           # median wall time of the loop of invert calls
    speedup: float          # median of the per-repeat ratios loop / batch
    compile_s: float        # the batched program's compilation (untimed run)
    max_difference: float   # max over members of |z_batch - z_single| / |z_single| (inf norm)
    largest_K: int          # the largest K any member reached

    @property
    def batch_rate(self) -> float:
        """Problems per second, batched."""
        return self.members / self.batch_s

    @property
    def loop_rate(self) -> float:
        return self.members / self.loop_s


def noise_batch(n: int, members: int, *, noise: float = 0.01,
                alpha: float = 1e-6) -> list[InverseProblem]:
    """``members`` source problems on the ``n x n`` unit square: the state of the source
    ``sin(pi x) sin(pi y)`` observed in full with ``noise`` relative noise, seed ``i`` for
    member ``i``; an L2 regulariser, P1 state and source."""
    disc = discretize(unit_square(n, "triangle"), element="P1", kappa_space="P0",
                      dirichlet=0.0)
    truth = disc.interpolate(lambda x: np.sin(np.pi * x[0]) * np.sin(np.pi * x[1]))
    kappa = np.ones(disc.n_kappa)
    state = disc.expand(direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, truth)).x)
    clean = full_field(disc, u_true=state)
    return [inverse_problem(disc, with_noise(clean, noise, seed=seed), unknown="source",
                            alpha=alpha, regularization="l2", truth=truth)
            for seed in range(members)]


def _check(sizes, n, steps, repeats) -> None:
    for option, values, minimum in (("--sizes", sizes, 1), ("--n", [n], 2),
                                    ("--steps", [steps], 1), ("--repeats", [repeats], 1)):
        if not values or any(isinstance(v, bool) or not isinstance(v, int) or v < minimum
                             for v in values):
            shown = " ".join(map(str, values))
            raise SolverConfigError(f"{option} {shown}: expected integers >= {minimum}")


def batch_throughput(sizes=(1, 8, 32, 128), *, n: int = 32, steps: int = 20,
                     repeats: int = 5, refinement: Refinement | None = None
                     ) -> list[BatchThroughput]:
    """Rows per batch size and mode (see the module's text)."""
    _check(list(sizes), n, steps, repeats)
    refinement = prdp() if refinement is None else refinement
    return [row for members in sizes
            for row in _throughput(noise_batch(n, members), steps, repeats, refinement)]


def _throughput(problems: list[InverseProblem], steps: int, repeats: int,
                refinement: Refinement) -> list[BatchThroughput]:
    calls = {mode: partial(invert_batch, problems, refinement=refinement, steps=steps,
                           mode=mode) for mode in MODES}
    calls["loop"] = lambda: [invert(problem, refinement=refinement, steps=steps)
                             for problem in problems]
    warm = {name: call() for name, call in calls.items()}  # compiles each (untimed)
    times = {name: [] for name in calls}
    for _ in range(repeats):  # alternated: a slow spell of the machine hits every side
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - start)
    rows = []
    for mode in MODES:
        batch = warm[mode]
        difference = max(_relative_difference(batch.params[i], single.params)
                         for i, single in enumerate(warm["loop"]))
        rows.append(BatchThroughput(
            len(problems), mode, problems[0].system.n_free, statistics.median(times[mode]),
            statistics.median(times["loop"]),
            statistics.median(loop / batch for loop, batch in zip(times["loop"], times[mode],
                                                                   strict=True)),
            batch.compile_time, difference,
            max(record.iterations for history in batch.histories for record in history)))
    return rows


def _relative_difference(params, reference) -> float:
    """``max |params - reference| / max |reference|``."""
    reference = np.asarray(reference)
    scale = max(float(np.max(np.abs(reference))), np.finfo(float).tiny)
    return float(np.max(np.abs(np.asarray(params) - reference))) / scale
