"""Benchmarks, measured side by side in one process (never timed assertions in tests).

``cg_iteration_cost``: time of one Jacobi-PCG iteration inside the jitted loop divided by the
time of one SciPy CSR SpMV of the same matrix. Each repeat interleaves
``[SciPy: m SpMVs] [JAX: K iterations] [JAX: 0 iterations]``; the iteration time is
``(t_K - t_0) / K`` so that call overhead cancels; the ratio is the median over repeats.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .cg import TruncatedCG, solve
from .discretization import discretize
from .errors import SolverConfigError
from .generators import unit_square

__all__ = ["CGIterationCost", "cg_iteration_cost"]


class CGIterationCost(NamedTuple):
    n_dofs: int
    nnz: int
    spmv_s: float  # median SciPy CSR SpMV
    iteration_s: float  # median JAX PCG iteration
    ratio: float  # median of the per-repeat ratios
    compile_s: float  # first call of the jitted solve, compile included, minus a steady call


def _poisson_operator(n_side: int):
    disc = discretize(unit_square(n_side), element="P1", kappa_space="P0")
    kappa = np.ones(disc.n_kappa)
    return disc.system.operator(jnp.asarray(kappa)), disc.rhs(kappa, disc.interpolate(
        lambda x: np.sin(np.pi * x[0]) * x[1]))


def cg_iteration_cost(n_side: int, *, iterations: int = 100, repeats: int = 7) -> CGIterationCost:
    """P1 Laplacian on an ``n_side x n_side`` square ((n_side - 1)^2 free dofs)."""
    for name, value in (("iterations", iterations), ("repeats", repeats)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise SolverConfigError(f"{name}={value!r}: expected an integer >= 1")
    op, b = _poisson_operator(n_side)
    csr = op.to_scipy()
    b = jnp.asarray(b)

    @jax.jit
    def run(op, b, k):
        return solve(op, b, TruncatedCG(k, gradient="implicit")).x

    tic = time.perf_counter()
    jax.block_until_ready(run(op, b, iterations))
    first = time.perf_counter() - tic
    x = np.asarray(b)
    spmv, per_iteration, ratios, steady = [], [], [], []
    for _ in range(repeats):
        tic = time.perf_counter()
        for _ in range(iterations):
            y = csr @ x
        t_spmv = (time.perf_counter() - tic) / iterations
        del y
        tic = time.perf_counter()
        jax.block_until_ready(run(op, b, iterations))
        t_k = time.perf_counter() - tic
        tic = time.perf_counter()
        jax.block_until_ready(run(op, b, 0))
        t_0 = time.perf_counter() - tic
        t_it = max(t_k - t_0, 0.0) / iterations
        spmv.append(t_spmv)
        per_iteration.append(t_it)
        ratios.append(t_it / t_spmv)
        steady.append(t_k)
    return CGIterationCost(csr.shape[0], csr.nnz, float(np.median(spmv)),
                           float(np.median(per_iteration)), float(np.median(ratios)),
                           max(first - float(np.median(steady)), 0.0))
