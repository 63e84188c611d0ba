"""Source recovery: the dolfin-adjoint Poisson "mother problem", converged vs fixed K vs PRDP.

    min_f  1/2 ||u - d||^2 + alpha/2 ||f||^2   s.t.  -lap u = f in (0,1)^2,  u = 0 on the boundary

with d = sin(pi x) sin(pi y) / (2 pi^2), alpha = 1e-6, P1 state and P1 control on the unit square
(n x n cells, two triangles each). The optimum is analytic: f* = sin(pi x) sin(pi y) / (1 + 4 alpha
pi^4). The misfit is against the function d itself (through its L2 projection, which has the same
minimiser), as dolfin-adjoint assembles it. Peer figures (dolfin-adjoint, L-BFGS-B): relative L2
error of f 6.4e-4 at n = 128 and 2.2e-4 at n = 256.

    python examples/source_recovery.py [n] [steps]
"""

import sys

import numpy as np

import prdp_fem as pf
from prdp_fem.fem import full_field
from prdp_fem.inverse import compare, converged, fixed, format_table, inverse_problem, prdp

ALPHA = 1e-6
PEER_ERROR = {128: 6.4e-4, 256: 2.2e-4, 512: 7.5e-5}


def mode(x):
    return np.sin(np.pi * x[0]) * np.sin(np.pi * x[1])


def build(n: int):
    """The discretisation and the inverse problem on an n x n unit square."""
    disc = pf.discretize(pf.unit_square(n, "triangle"), element="P1", kappa_space="P0",
                         dirichlet=0.0)
    data = disc.project(lambda x: mode(x) / (2 * np.pi ** 2))
    truth = disc.interpolate(mode) / (1 + 4 * ALPHA * np.pi ** 4)
    problem = inverse_problem(disc, full_field(disc, data=data), unknown="source",
                              alpha=ALPHA, regularization="l2", truth=truth)
    return disc, problem


RUNS = {
    "converged": dict(refinement=converged(1e-10)),
    "fixed K=5": dict(refinement=fixed(5)),
    "prdp": dict(refinement=prdp(K0=5, dK=5, restart=True)),
}


def run(n: int = 128, steps: int = 60):
    _, problem = build(n)
    return compare(problem, RUNS, steps=steps)


def main(argv=()):
    n = int(argv[0]) if argv else 128
    steps = int(argv[1]) if len(argv) > 1 else 60
    rows = run(n, steps)
    print(f"source recovery, n = {n}, alpha = {ALPHA:g}, L-BFGS, {steps} steps "
          f"(peer error {PEER_ERROR.get(n, float('nan')):.1e})")
    print(format_table(rows))
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
