"""Differentiate a truncated solve with respect to the coefficient, both ways, and Taylor-test it.

J(kappa) = 1/2 ||u_K(kappa) - d||^2 on the shipped plate-with-hole mesh.
"""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import prdp_fem as pf

MESH = Path(__file__).resolve().parent.parent / "meshes" / "plate_hole.msh"


def main(k: int = 30) -> dict:
    disc = pf.discretize(pf.load_mesh(MESH), element="P1", kappa_space="P0",
                         dirichlet={"left": 1.0, "right": 0.0})
    system = disc.system
    kappa = jnp.asarray(disc.interpolate_kappa(lambda x: 1.0 + 0.5 * x[1]))
    data = jnp.asarray(np.linspace(0.0, 1.0, disc.n_free))

    def objective(kappa, solver):
        u = pf.solve(system.operator(kappa), system.rhs(kappa), solver).x
        return 0.5 * jnp.sum((u - data) ** 2)

    results = {}
    for mode in ("unrolled", "implicit"):
        solver = pf.TruncatedCG(k, gradient=mode)
        fn = jax.jit(lambda kappa, solver=solver: objective(kappa, solver))
        taylor = pf.taylor_test(fn, kappa)
        results[mode] = {"value": float(fn(kappa)), "rates": taylor.rates,
                         "gradient": np.asarray(jax.grad(fn)(kappa))}
        print(f"{mode:>9}: J = {results[mode]['value']:.6e}, Taylor rates {taylor.rates[:4]}")
    return results


if __name__ == "__main__":
    main()
