"""Newton-CG on hIPPYlib's coefficient problem, against its anchor (7 Newton / 41 CG at 64 x 64).

    min_m  1/2 ||u - d||^2 + gamma/2 ||grad m||^2   s.t.  -div(e^m grad u) = 1,  u = 0 on bdry

on the unit square, u in P2, m in P1, true m = log(8 - 4 [|x - (0.5, 0.5)| < 0.2]), data = the true
state on all dofs plus 5 % Gaussian noise (sigma = 0.05 max|u|), gamma = 1e-8 (the problem of
examples/coefficient_recovery.py). As in hIPPYlib's tutorial: inexact Newton-CG, inner tolerance
min(0.5, sqrt(||g|| / ||g_0||)), Armijo c1 = 1e-4 with halving (10 at most), the inner CG
preconditioned by the regularisation operator plus a mass shift (here one AMG V-cycle of L + M),
converged state/adjoint/tangent solves (PCG to rtol 1e-10), and the start m_0 = log 4 (the
inclusion's value; hIPPYlib's older variant, log(2 + 7 [r > 0.2]), starts at its inclusion value
log 2). Stop at ||g|| <= 1e-6 ||g_0|| (Euclidean norms).

``problem="tutorial"`` is hIPPYlib's tutorial itself: no source, the flux
``e^m grad u . n = (x - 0.5) y (y - 1)`` on the whole boundary, the state pinned to 0 at the
centre (a point constraint), the inclusion |x - (0.5, 0.5)| <= 0.2; its published run: 6 Newton
and 26 CG iterations, final misfit 3.89e-8.

    python examples/newton_coefficient.py [n] [hessian] [forcing] [problem] [cycles] [solves]

hessian: exact | gauss_newton; forcing: hippylib | eisenstat_walker; problem: inclusion |
tutorial; cycles: AMG V-cycles of the regularisation operator in the inner preconditioner
(default 1; 8 come close to hIPPYlib's exact solve: on the tutorial with gauss_newton and
eisenstat_walker, 5 Newton / 26 CG against 6 / 45 with one cycle); solves: converged |
prdp (the PDE solves truncated under PRDP: on the tutorial the same misfit and a parameter
error 0.1 % apart with 74 % fewer PCG iterations, though the gradient no longer falls to
1e-6 of its first norm).
"""

import math
import sys
import time

import numpy as np

import prdp_fem as pf
from prdp_fem.fem import full_field, with_noise
from prdp_fem.inverse import converged, inverse_problem, invert, prdp
from prdp_fem.optim import newton_cg, regularization_preconditioner

GAMMA = 1e-8
NOISE = 0.05
ANCHOR = {"newton": 7, "cg": 41}  # hIPPYlib at 64 x 64 (BACKGROUND.md, section 4)
TUTORIAL_ANCHOR = {"newton": 6, "cg": 26, "misfit": 3.89e-8}  # hIPPYlib's tutorial, published
START = math.log(4.0)


def inclusion(x, centre=(0.5, 0.5), radius=0.2):
    r2 = (x[0] - centre[0]) ** 2 + (x[1] - centre[1]) ** 2
    return np.log(8.0 - 4.0 * (r2 < radius ** 2))


def build(n: int = 64, seed: int = 1):
    """hIPPYlib's problem on an n x n unit square: (disc, problem)."""
    disc = pf.discretize(pf.unit_square(n, "triangle"), element="P2", kappa_space="P1",
                         dirichlet=0.0)
    m_true = disc.interpolate_kappa(inclusion)
    f = np.ones(disc.n_dofs)
    kappa = np.exp(m_true)
    u_true = disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f)).x)
    data = with_noise(full_field(disc, u_true=u_true), NOISE, seed)
    return disc, inverse_problem(disc, data, unknown="log_kappa", alpha=GAMMA,
                                 regularization="h1", known=f, truth=m_true)


def flux(x):
    """The tutorial's boundary flux ``e^m grad u . n = (x - 0.5) y (y - 1)``."""
    return (x[0] - 0.5) * x[1] * (x[1] - 1.0)


def build_tutorial(n: int = 64, seed: int = 1):
    """hIPPYlib's tutorial problem on an n x n unit square: (disc, problem)."""
    disc = pf.discretize(pf.unit_square(n, "triangle"), element="P2", kappa_space="P1",
                         dirichlet=None,
                         neumann={side: flux for side in ("left", "right", "bottom", "top")},
                         pins=[((0.5, 0.5), 0.0)])
    m_true = disc.interpolate_kappa(lambda x: np.log(
        8.0 - 4.0 * ((x[0] - 0.5) ** 2 + (x[1] - 0.5) ** 2 <= 0.2 ** 2)))
    f = np.zeros(disc.n_dofs)
    u_true = disc.expand(pf.direct_solve(*disc.host_system_at(np.exp(m_true), f)).x)
    data = with_noise(full_field(disc, u_true=u_true), NOISE, seed)
    return disc, inverse_problem(disc, data, unknown="log_kappa", alpha=GAMMA,
                                 regularization="h1", known=f, truth=m_true)


def run(n: int = 64, hessian: str = "exact", forcing: str = "hippylib", rtol: float = 1e-6,
        max_steps: int = 30, solver_rtol: float = 1e-10, problem: str = "inclusion",
        cycles: int = 1, solves: str = "converged", gauss_newton_steps: int = 0) -> dict:
    """Newton-CG through :func:`prdp_fem.invert`; the numbers of the run as a dict.
    ``cycles``: AMG V-cycles of the regularisation operator per preconditioner application
    (8 come close to hIPPYlib's exact solve). ``solves``: the state, adjoint and tangent
    solves converged (PCG to ``solver_rtol``) or ``"prdp"``, truncated PCG under PRDP
    (K0 = dK = 200, restarted at each refinement, refined at a failed line search).
    ``gauss_newton_steps``: with the exact Hessian, the first updates that use Gauss-Newton's
    (hIPPYlib: 5)."""
    disc, problem = (build_tutorial if problem == "tutorial" else build)(n)
    optimizer = newton_cg(hessian=hessian, forcing=forcing, max_cg=100, rtol=rtol,
                          preconditioner=regularization_preconditioner(problem, cycles),
                          gauss_newton_steps=gauss_newton_steps)
    previous = {}

    def stop_when_still(record, z):
        # the transformation skips its update once ||g|| <= rtol ||g_0||: z stops moving
        z = np.asarray(z)
        still = "z" in previous and np.array_equal(z, previous["z"])
        previous["z"] = z
        return still

    start = time.perf_counter()
    refinement = converged(solver_rtol) if solves == "converged" else \
        prdp(K0=200, dK=200, restart=True, stall_on_failure=True)
    result = invert(problem, optimizer=optimizer, refinement=refinement,
                    steps=max_steps, init=np.full(disc.n_kappa, START),
                    callback=stop_when_still)
    wall = time.perf_counter() - start
    state, last = result.optimizer_state, result.history[-1]
    data = problem.observation
    data_norm = float(np.sqrt(np.asarray(data.data) @ (data.weight.to_scipy()
                                                       @ np.asarray(data.data))))
    return {
        "n": n, "hessian": hessian, "forcing": forcing, "solves": solves,
        "pcg_iterations": last.primal_iterations + last.adjoint_iterations_total,
        "newton_iterations": int(state.steps),
        "cg_iterations": int(state.total_cg_iterations),
        "line_search_evaluations": int(state.total_line_search_evaluations),
        "gradient_reduction": float(state.grad_norm / state.initial_grad_norm),
        "converged": bool(state.converged),
        "parameter_error": last.parameter_error,  # relative L2 error of m
        "relative_misfit": math.sqrt(2 * last.misfit) / data_norm,  # ||u - d|| / ||d||
        "misfit": last.misfit,  # 1/2 ||u - d||^2 (L2), hIPPYlib's "misfit"
        "noise_level": float(data.noise_norm()) / data_norm,
        "primal_iterations": last.primal_iterations,
        "adjoint_iterations": last.adjoint_iterations_total,
        "run_time": last.time,  # optimiser steps, compilation excluded
        "compile_time": last.compile_time,
        "wall_time": wall,  # everything, the AMG setup of the preconditioner excluded
    }


def main(argv=()):
    n = int(argv[0]) if argv else 64
    hessian = argv[1] if len(argv) > 1 else "exact"
    forcing = argv[2] if len(argv) > 2 else "hippylib"
    problem = argv[3] if len(argv) > 3 else "inclusion"
    cycles = int(argv[4]) if len(argv) > 4 else 1
    solves = argv[5] if len(argv) > 5 else "converged"
    anchor = TUTORIAL_ANCHOR if problem == "tutorial" else ANCHOR
    result = run(n, hessian, forcing, problem=problem, cycles=cycles, solves=solves)
    print(f"Newton-CG ({hessian} Hessian, {forcing} forcing) on hIPPYlib's coefficient "
          f"{problem}, {n} x {n}, P2/P1, 5 % noise, gamma = {GAMMA:g}")
    print(f"  Newton iterations {result['newton_iterations']} (hIPPYlib: {anchor['newton']}), "
          f"inner CG iterations {result['cg_iterations']} (hIPPYlib: {anchor['cg']}), "
          f"line-search evaluations {result['line_search_evaluations']}, misfit "
          f"{result['misfit']:.3g}" + (f" (hIPPYlib: {anchor['misfit']:g})"
                                       if "misfit" in anchor else ""))
    print(f"  ||g|| / ||g_0|| = {result['gradient_reduction']:.2e}, relative misfit "
          f"{result['relative_misfit']:.4f} (noise {result['noise_level']:.4f}), parameter "
          f"error {result['parameter_error']:.4f}")
    print(f"  PDE solve iterations: primal {result['primal_iterations']}, adjoint/tangent "
          f"{result['adjoint_iterations']}; run time {result['run_time']:.2f} s, compile "
          f"{result['compile_time']:.2f} s, wall {result['wall_time']:.2f} s")
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
