"""bench cg: the operator it times, the table it prints (numbers' structure, never timings)."""

import math

import numpy as np
import pytest
import scipy.sparse.linalg as spla

import prdp_fem as pf
from prdp_fem import linalg
from prdp_fem.bench import cg as bench_module
from prdp_fem.bench.cg import (
    CGIterationCost,
    device_iteration_cost,
    poisson_operator,
    scaling_slope,
)
from prdp_fem.cli.main import main


def test_poisson_operator_is_the_discretised_laplacian():
    """Against the package's own discretisation with kappa = 1: the same free-dof matrix, and
    its solution of -lap u = 2 pi^2 sin sin converges to the analytic one."""
    A, b = poisson_operator(16)
    disc = pf.discretize(pf.unit_square(16), element="P1", kappa_space="P0")
    reference = disc.stiffness_matrix(np.ones(disc.n_kappa))
    assert A.shape == reference.shape == (225, 225) and b.shape == (225,)
    assert abs(A.to_scipy() - reference).max() < 1e-12
    A3, _ = poisson_operator(4, dim=3)
    assert A3.shape == (27, 27) and np.allclose(A3.to_scipy().toarray(),
                                                A3.to_scipy().toarray().T)
    assert np.all(spla.eigsh(A3.to_scipy(), k=1, which="SA")[0] > 0)


def test_the_scaling_slope():
    """(The fields of a measured cost: the bench cg test below, on the command's costs.)"""
    line = [CGIterationCost(n, 5 * n, 0.0, 3e-9 * n ** 1.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            for n in (100, 1000, 10000)]
    assert abs(scaling_slope(line) - 1.5) < 1e-12
    assert math.isnan(scaling_slope(line[:1]))
    # a time differenced to zero is left out, not a log of zero
    unmeasured = line[0]._replace(iteration_s=0.0)
    assert abs(scaling_slope([unmeasured, *line[1:]]) - 1.5) < 1e-12
    assert math.isnan(scaling_slope([unmeasured, line[1]]))


def bench_cg(*args: str, capsys) -> str:
    """What ``prdp-fem bench cg ARGS`` prints (its main, in this process)."""
    capsys.readouterr()
    assert main(["bench", "cg", *args]) == 0
    return capsys.readouterr().out


def measured(monkeypatch, name: str) -> list:
    """The costs ``prdp_fem.bench.cg.<name>`` returns from now on (the command's own, checked
    as they are: no second measurement compiled for the test)."""
    costs, measure = [], getattr(bench_module, name)
    monkeypatch.setattr(bench_module, name, lambda *a, **k: costs.append(measure(*a, **k))
                        or costs[-1])
    return costs


def test_bench_cg_prints_one_row_per_size_and_the_slope(capsys, monkeypatch):
    costs = measured(monkeypatch, "cg_iteration_cost")
    out = bench_cg("--sides", "8", "12", "--iterations", "2", "--repeats", "1", capsys=capsys)
    rows = [line.split() for line in out.splitlines() if line.strip()[:1].isdigit()]
    # the operator: interior dofs and the five-point pattern of P1 on right triangles
    assert [(int(row[0]), int(row[1])) for row in rows] == [(n * n, n * n + 4 * n * (n - 1))
                                                            for n in (7, 11)]
    # dofs, nnz, SpMV, iteration, ratio, XLA iteration and ratio, COO iteration and ratio,
    # compile
    assert all(len(row) == 10 and all(math.isfinite(float(v)) for v in row) for row in rows)
    assert "log-log slope" in out.splitlines()[-1]
    # the costs behind the rows: the operator's counts, times and ratios >= 0
    assert [(cost.n_dofs, cost.nnz) for cost in costs] == [
        (n * n, poisson_operator(n + 1)[0].nnz) for n in (7, 11)]
    assert all(value >= 0 and math.isfinite(value) for cost in costs for value in cost[2:])


@pytest.mark.slow  # the device bench test below checks these fields on the command's cost
def test_device_cost_times_every_kernel_against_the_csr_spmv():
    """The accelerator table's numbers (run here on the host backend): one time per kernel,
    the ratio is the default kernel's time over the reference SpMV's."""
    cost = device_iteration_cost(9, iterations=3, repeats=1)
    assert cost.n_dofs == 64 and set(cost.kernel_s) == set(linalg.KERNELS)
    assert cost.iteration_s == cost.kernel_s[linalg.default_kernel()]
    # at 64 dofs a loaded machine can time the SpMV loop at 0 (t_K - t_0 clamped): the
    # ratio's denominator is then the guard, not a division by zero
    assert math.isclose(cost.ratio, cost.iteration_s / max(cost.spmv_s, 1e-30),
                        rel_tol=1e-12)
    assert all(t >= 0 and math.isfinite(t) for t in (*cost.kernel_s.values(), cost.spmv_s))


def test_bench_cg_device_reference_prints_one_column_per_kernel(capsys, monkeypatch):
    """The accelerator table (run here on the host backend), and the cost behind its row: one
    time per kernel, the ratio is the default kernel's time over the reference SpMV's."""
    costs = measured(monkeypatch, "device_iteration_cost")
    out = bench_cg("--sides", "8", "--iterations", "2", "--repeats", "1", "--reference",
                   "device", capsys=capsys)
    header = next(line for line in out.splitlines() if line.split()[:1] == ["dofs"])
    assert [f"{k}" for k in linalg.KERNELS] == [w for w in header.split() if w in linalg.KERNELS]
    rows = [line.split() for line in out.splitlines() if line.strip()[:1].isdigit()]
    assert len(rows) == 1 and int(rows[0][0]) == 49
    assert len(rows[0]) == 3 + len(linalg.KERNELS) + 2
    assert all(math.isfinite(float(v)) for v in rows[0])
    [cost] = costs
    assert cost.n_dofs == 49 and set(cost.kernel_s) == set(linalg.KERNELS)
    assert cost.iteration_s == cost.kernel_s[linalg.default_kernel()]
    # at 49 dofs a loaded machine can time the SpMV loop at 0 (t_K - t_0 clamped): the
    # ratio's denominator is then the guard, not a division by zero
    assert math.isclose(cost.ratio, cost.iteration_s / max(cost.spmv_s, 1e-30),
                        rel_tol=1e-12)
    assert all(t >= 0 and math.isfinite(t) for t in (*cost.kernel_s.values(), cost.spmv_s))
