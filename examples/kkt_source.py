"""The mother problem's optimum by MINRES on its KKT system, against the reduced-Hessian CG.

dolfin-adjoint's Poisson mother problem (P1 state and control on the n x n unit square,
alpha = 1e-6, see source_recovery.py) solved to its discrete optimum two ways: `kkt_solve`
(MINRES on the coupled state-source-adjoint system, Pearson-Wathen preconditioner: one
Ruge-Stueben V-cycle pair per iteration) and `reduced_cg` (CG on the reduced Hessian, every
product a forward and an adjoint AMG-PCG solve). Both to a relative residual of 1e-10.

    python examples/kkt_source.py [n ...]
"""

import sys
import time

import numpy as np

from prdp_fem.bench.inverse import mother_problem
from prdp_fem.inverse import converged, kkt_solve, reduced_cg
from prdp_fem.linalg import amg_preconditioner


def solve(n: int) -> dict:
    problem = mother_problem(n)
    start = time.perf_counter()
    kkt = kkt_solve(problem, rtol=1e-10)
    kkt_seconds = time.perf_counter() - start
    start = time.perf_counter()
    cycle = amg_preconditioner(problem.system.operator(problem.known).to_scipy())
    reduced = reduced_cg(problem, refinement=converged(1e-12), iterations=200, rtol=1e-10,
                         preconditioner=cycle, riesz_rtol=1e-13)
    reduced_seconds = time.perf_counter() - start
    mass = problem.parameter_mass.to_scipy()
    gap = kkt.field - reduced.field
    last = reduced.history[-1]
    return {"n": n, "kkt_iterations": kkt.iterations, "vcycles": kkt.vcycles,
            "kkt_seconds": kkt_seconds, "reduced_iterations": last.step,
            "pcg_iterations": last.primal_iterations + last.adjoint_iterations_total,
            "reduced_seconds": reduced_seconds,
            "difference": float(np.sqrt(gap @ mass @ gap / (reduced.field @ mass
                                                            @ reduced.field))),
            "error": float(problem.parameter_error(kkt.field))}


def main(argv=()):
    sizes = [int(a) for a in argv] or [32, 64, 128]
    print(f"{'n':>5} {'MINRES':>6} {'V-cycles':>8} {'[s]':>6} {'CG':>4} {'PCG its':>7} "
          f"{'[s]':>6} {'difference':>10} {'error':>9}")
    rows = [solve(n) for n in sizes]
    for r in rows:
        print(f"{r['n']:>5} {r['kkt_iterations']:>6} {r['vcycles']:>8} {r['kkt_seconds']:>6.2f} "
              f"{r['reduced_iterations']:>4} {r['pcg_iterations']:>7} "
              f"{r['reduced_seconds']:>6.2f} {r['difference']:>10.1e} {r['error']:>9.3e}")
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
