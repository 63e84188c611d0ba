"""AMG preconditioning while the coefficient moves: built once, rebuilt, or Jacobi.

A log-kappa inversion of a high-contrast inclusion (kappa = 1000 in a disk of radius 0.2, 1
outside) from the full noisy state, P1 on an n x n unit square, L-BFGS with converged inner
solves (rtol 1e-8), so that the CG iterations measure the preconditioner alone:

* ``jacobi``: Jacobi-PCG;
* ``amg once``: a smoothed-aggregation hierarchy built at the initial guess (kappa = 1) and
  kept, as ``preconditioner=pf.amg_preconditioner(A)`` does;
* ``amg every 10``: :class:`prdp_fem.RebuiltAMG` rebuilt every 10 steps;
* ``amg factor 3``: rebuilt once kappa has moved by more than a factor 3 somewhere.

Times exclude compilation; a rebuild's pyamg setup is run time, and its new step program is
compile time.

    python examples/amg_rebuild.py [n] [steps]
"""

import sys

import jax.numpy as jnp
import numpy as np

import prdp_fem as pf
from prdp_fem.inverse import converged

CONTRAST = 1e3
NOISE = 0.01
ALPHA = 1e-8


def inclusion(x):
    return np.where((x[0] - 0.5) ** 2 + (x[1] - 0.5) ** 2 < 0.04, np.log(CONTRAST), 0.0)


def build(n: int) -> pf.InverseProblem:
    disc = pf.discretize(pf.unit_square(n), element="P1", kappa_space="P0", dirichlet=0.0)
    m_true = disc.interpolate_kappa(inclusion)
    f = np.ones(disc.n_dofs)
    kappa = np.exp(m_true)
    u = disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f)).x)
    observation = pf.with_noise(pf.full_field(disc, u_true=u), NOISE, seed=1)
    return pf.inverse_problem(disc, observation, unknown="log_kappa", alpha=ALPHA, known=f,
                              truth=m_true)


def preconditioners(problem: pf.InverseProblem) -> dict:
    at_start = problem.system.operator(jnp.ones(problem.n_parameters))
    return {
        "jacobi": "jacobi",
        "amg once": pf.amg_preconditioner(at_start),
        "amg every 10": pf.RebuiltAMG(pf.rebuild_policy(every=10)),
        "amg factor 3": pf.RebuiltAMG(pf.rebuild_policy(factor=3.0)),
    }


def run(n: int = 128, steps: int = 40) -> dict[str, pf.History]:
    problem = build(n)
    return {name: pf.invert(problem, refinement=converged(1e-8), steps=steps,
                            preconditioner=preconditioner).history
            for name, preconditioner in preconditioners(problem).items()}


def main(argv=()):
    n = int(argv[0]) if argv else 128
    steps = int(argv[1]) if len(argv) > 1 else 40
    histories = run(n, steps)
    print(f"log-kappa inclusion (contrast {CONTRAST:g}), P1 on unit_square({n}), "
          f"{(n + 1) ** 2} nodes, L-BFGS, {steps} steps, converged solves (rtol 1e-8)")
    print(f"{'preconditioner':<16}{'final err':>11}{'CG its':>9}{'rebuilds':>10}"
          f"{'time s':>9}{'compile s':>11}")
    for name, history in histories.items():
        last = history[-1]
        print(f"{name:<16}{last.parameter_error:>11.4e}{last.total_iterations:>9d}"
              f"{last.rebuilds:>10d}{last.time:>9.2f}{last.compile_time:>11.2f}")


if __name__ == "__main__":
    main(sys.argv[1:])
