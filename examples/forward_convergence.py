"""Truncated PCG on a user-style problem: error against K, checked against pyamg.

Run as a script (``python examples/forward_convergence.py``); the tests import ``main`` and pin
its numbers.
"""

import numpy as np

import prdp_fem as pf


def main(n: int = 32, iterations=(0, 10, 20, 40, 80, 160)) -> dict:
    mesh = pf.rectangle_with_hole(n)
    disc = pf.discretize(mesh, element="P1", kappa_space="P1",
                         dirichlet={"left": 0.0, "hole": 1.0})
    kappa = disc.interpolate_kappa(lambda x: 1.0 + x[0])
    f = disc.interpolate(lambda x: np.sin(np.pi * x[1]))
    system = disc.system_at(kappa)  # kappa never changes: no map kappa -> A is built
    scale = np.ones(1)  # the frozen system's one coefficient
    op, b = system.operator(scale), system.rhs(scale, f)
    reference = pf.amg_solve(*disc.host_system_at(kappa, f), rtol=1e-12)
    u_ref = disc.expand(reference.x)
    errors = {}
    for k in iterations:
        sol = pf.solve(op, b, pf.TruncatedCG(k, gradient="implicit"))
        errors[k] = pf.relative_l2_error(disc, disc.expand(np.asarray(sol.x)), u_ref)
        print(f"K = {k:4d}: relative L2 error {errors[k]:.3e}, residual {sol.residual_norm:.2e}")
    return {"n_free": disc.n_free, "amg_iterations": reference.iterations, "errors": errors}


if __name__ == "__main__":
    main()
