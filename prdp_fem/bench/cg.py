"""Benchmarks, measured side by side in one process (never timed assertions in tests).

``cg_iteration_cost``: time of one Jacobi-PCG iteration inside the jitted loop divided by the
time of one SciPy CSR SpMV of the same matrix (an iteration can never cost less than its SpMV
on one core). Each repeat interleaves ``[SciPy: m SpMVs] [JAX: K iterations] [JAX: 0
iterations]`` for three programs: the ELL kernel compiled as the package compiles its own
programs (:mod:`prdp_fem._xla_options`), the same compiled with XLA's own fusion emitters forced
(what a user's ``jax.jit`` gets where ``XLA_FLAGS`` are silent), and the COO segment-sum kernel
the ELL kernel replaced (the package's options). An iteration's time is ``(t_K - t_0) / K``
so that call overhead cancels; ratios are medians over repeats. ``scaling_slope`` fits
``log t = slope log n + c`` over a size sweep (linear: 1).

>>> costs = [CGIterationCost(n, 5 * n, 1e-9 * n, 2e-9 * n, 2.0, 2e-9 * n, 2.0, 3e-9 * n, 3.0,
...                          0.1) for n in (1000, 8000)]
>>> round(scaling_slope(costs), 6)
1.0
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import skfem
from skfem.models.poisson import laplace

from .._xla_options import FUSION_EMITTERS, compiler_options
from ..errors import SolverConfigError
from ..linalg.cg import TruncatedCG, solve
from ..linalg.operator import KERNELS, SparseMatrix, default_kernel, prepare
from ..mesh.generators import unit_cube, unit_square

__all__ = ["CGIterationCost", "DeviceIterationCost", "cg_iteration_cost",
           "device_iteration_cost", "poisson_operator", "scaling_slope", "this_package_first"]


def this_package_first(environ: Mapping[str, str] = os.environ) -> dict[str, str]:
    """A copy of ``environ`` whose ``PYTHONPATH`` starts with this package's parent directory,
    so that a benchmark's child process imports this very package, whichever is installed.

    >>> env = this_package_first({"PYTHONPATH": "/elsewhere", "HOME": "/h"})
    >>> env["PYTHONPATH"].split(os.pathsep)[1:], env["HOME"]
    (['/elsewhere'], '/h')
    """
    package_parent = str(Path(__file__).resolve().parent.parent)
    path = os.pathsep.join(filter(None, [package_parent, environ.get("PYTHONPATH")]))
    return {**environ, "PYTHONPATH": path}


class CGIterationCost(NamedTuple):
    n_dofs: int
    nnz: int
    spmv_s: float  # median SciPy CSR SpMV
    iteration_s: float  # median JAX PCG iteration, ELL kernel (the default), package's options
    ratio: float  # median of the per-repeat ratios iteration / SpMV
    xla_iteration_s: float  # the same program compiled with XLA's own fusion emitters
    xla_ratio: float
    coo_iteration_s: float  # the COO segment-sum kernel (no layout), package's options
    coo_ratio: float
    compile_s: float  # trace, lower and compile of the first program (ELL, package's options)


def poisson_operator(n_side: int, dim: int = 2) -> tuple[SparseMatrix, np.ndarray]:
    """The P1 Laplacian on the free dofs of an ``n_side^dim`` unit square/cube and a smooth
    right-hand side (assembled by scikit-fem directly: no coefficient map is needed here)."""
    if dim not in (2, 3):
        raise SolverConfigError(f"dim={dim!r}: expected 2 or 3")
    mesh = unit_square(n_side) if dim == 2 else unit_cube(n_side)
    basis = skfem.Basis(mesh, skfem.ElementTriP1() if dim == 2 else skfem.ElementTetP1())
    free = basis.complement_dofs(basis.get_dofs())
    A = laplace.assemble(basis).tocsr()[free][:, free]
    b = np.sin(np.pi * mesh.p[0, free]) * mesh.p[1, free]
    return SparseMatrix.from_scipy(A), b


def _check_counts(**counts: int) -> None:
    for name, value in counts.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise SolverConfigError(f"{name}={value!r}: expected an integer >= 1")


def cg_iteration_cost(n_side: int, *, dim: int = 2, iterations: int = 100,
                      repeats: int = 7) -> CGIterationCost:
    """P1 Laplacian on ``n_side^dim`` cells ((n_side - 1)^dim free dofs)."""
    _check_counts(n_side=n_side, iterations=iterations, repeats=repeats)
    ell, b = poisson_operator(n_side, dim)
    coo = SparseMatrix(ell.rows, ell.cols, ell.values, ell.shape)  # no layout: COO kernel
    csr = ell.to_scipy()
    b = jnp.asarray(b)

    def run(op, b, k):
        return solve(op, b, TruncatedCG(k, gradient="implicit")).x

    def compiled(op, options=None):
        """``run`` for ``op`` (``K`` traced): with ``options``, else the package's choice."""
        traced = jax.jit(run).trace(op, b, iterations)
        chosen = compiler_options(traced.jaxpr) if options is None else dict(options)
        return traced.lower().compile(compiler_options=chosen)

    tic = time.perf_counter()
    programs = {"ell": compiled(ell)}
    compile_s = time.perf_counter() - tic
    programs |= {"xla": compiled(ell, FUSION_EMITTERS), "coo": compiled(coo)}

    operands = {"ell": ell, "xla": ell, "coo": coo}

    def timed(name: str, k: int) -> float:
        tic = time.perf_counter()
        jax.block_until_ready(programs[name](operands[name], b, k))
        return time.perf_counter() - tic

    x = np.asarray(b)
    spmv, per_iteration = [], {name: [] for name in programs}
    for _ in range(repeats):
        tic = time.perf_counter()
        for _ in range(iterations):
            csr @ x
        spmv.append((time.perf_counter() - tic) / iterations)
        for name, times in per_iteration.items():
            times.append(max(timed(name, iterations) - timed(name, 0), 0.0) / iterations)
    median = lambda values: float(np.median(values))  # noqa: E731

    def ratio(name: str) -> float:
        return median([t / s for t, s in zip(per_iteration[name], spmv, strict=True)])

    return CGIterationCost(csr.shape[0], csr.nnz, median(spmv), median(per_iteration["ell"]),
                           ratio("ell"), median(per_iteration["xla"]), ratio("xla"),
                           median(per_iteration["coo"]), ratio("coo"), compile_s)


class DeviceIterationCost(NamedTuple):
    """One size on an accelerator: each kernel's PCG iteration against the vendor SpMV."""

    n_dofs: int
    nnz: int
    spmv_s: float  # median device SpMV through the CSR kernel (cuSPARSE on NVIDIA GPUs)
    iteration_s: float  # median PCG iteration, the backend's default kernel
    ratio: float  # iteration_s / spmv_s
    kernel_s: dict  # kernel name -> median PCG iteration time
    compile_s: float  # as in CGIterationCost, default kernel


def device_iteration_cost(n_side: int, *, dim: int = 2, iterations: int = 100,
                          repeats: int = 7) -> DeviceIterationCost:
    """:func:`cg_iteration_cost` for an accelerator (JAX's default backend), where SciPy's
    host SpMV is no reference: the reference is the device's own CSR SpMV (``csr_matvec``,
    cuSPARSE on NVIDIA GPUs) in a jitted loop, and every kernel of :data:`KERNELS` runs the
    same Jacobi-PCG. Times are ``(t_K - t_0) / K`` medians over interleaved repeats."""
    _check_counts(n_side=n_side, iterations=iterations, repeats=repeats)
    base, b = poisson_operator(n_side, dim)
    b = jnp.asarray(b)
    csr = prepare(base.with_kernel("csr"))
    # y <- A y / ||A||_inf stays bounded (no overflow, no denormals over K products)
    shrink = 1.0 / float(np.abs(base.to_scipy()).sum(axis=1).max())

    @jax.jit
    def spmv_loop(kernel, y, k):
        return jax.lax.fori_loop(0, k, lambda _, y: kernel(y) * shrink, y)

    @jax.jit
    def run(op, b, k):
        return solve(op, b, TruncatedCG(k, gradient="implicit")).x

    def timed(call, *args) -> float:
        tic = time.perf_counter()
        jax.block_until_ready(call(*args))
        return time.perf_counter() - tic

    def per_iteration(call, operand) -> float:
        return max(timed(call, operand, b, iterations) - timed(call, operand, b, 0), 0.0) \
            / iterations

    chosen = default_kernel()
    matrices = {name: base.with_kernel(name) for name in KERNELS}
    first = timed(run, matrices[chosen], b, iterations)
    for name in KERNELS:
        timed(run, matrices[name], b, iterations)  # compile
    timed(spmv_loop, csr, b, iterations)
    spmv, kernel_s, steady = [], {name: [] for name in KERNELS}, []
    for _ in range(repeats):
        spmv.append(per_iteration(spmv_loop, csr))
        for name in KERNELS:
            kernel_s[name].append(per_iteration(run, matrices[name]))
        steady.append(timed(run, matrices[chosen], b, iterations))
    median = lambda values: float(np.median(values))  # noqa: E731
    medians = {name: median(values) for name, values in kernel_s.items()}
    return DeviceIterationCost(base.shape[0], base.nnz, median(spmv), medians[chosen],
                               medians[chosen] / max(median(spmv), 1e-30), medians,
                               max(first - median(steady), 0.0))


def scaling_slope(costs: list[CGIterationCost]) -> float:
    """Least-squares slope of ``log(iteration time)`` against ``log(dofs)``, over the sizes
    whose time was measurable: a time differenced to zero (a few iterations of a tiny problem
    vanish in the timer's noise) has no logarithm."""
    costs = [c for c in costs if c.iteration_s > 0]
    if len({c.n_dofs for c in costs}) < 2:
        return float("nan")  # no slope from one size
    n = np.log([c.n_dofs for c in costs])
    t = np.log([c.iteration_s for c in costs])
    return float(np.polyfit(n, t, 1)[0])
