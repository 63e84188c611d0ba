"""Coefficient recovery (hIPPYlib's elliptic problem), converged vs fixed K vs PRDP.

    min_m  1/2 ||u - d||^2 + gamma/2 ||grad m||^2   s.t.  -div(e^m grad u) = 1,  u = 0 on bdry

on the unit square, u in P2, m in P1, true m = log(8 - 4 [|x - (0.5, 0.5)| < 0.2]), data = the true
state on all dofs plus 5 % Gaussian noise (sigma = 0.05 max|u|), L2 misfit, H1 regularisation with
gamma = 1e-8 (hIPPYlib's value; the discrepancy principle lands close to it here, see
prdp_fem.inverse.parameter_choice.morozov). A second scene inverts on the shipped unstructured mesh
meshes/plate_hole.msh from 60 point sensors, u = 0 on the outer sides and a unit source.

    python examples/coefficient_recovery.py [n] [steps]
"""

import sys
from pathlib import Path

import numpy as np

import prdp_fem as pf
from prdp_fem.fem import full_field, point_sensors, with_noise
from prdp_fem.inverse import compare, converged, fixed, format_table, inverse_problem, prdp

GAMMA = 1e-8
NOISE = 0.05
MESH = Path(__file__).resolve().parent.parent / "meshes" / "plate_hole.msh"


def inclusion(x, centre=(0.5, 0.5), radius=0.2):
    r2 = (x[0] - centre[0]) ** 2 + (x[1] - centre[1]) ** 2
    return np.log(8.0 - 4.0 * (r2 < radius ** 2))


def true_state(disc, m_true, f):
    kappa = np.exp(m_true)
    return disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f)).x)


def build(n: int = 64, seed: int = 1):
    """hIPPYlib's problem on an n x n unit square."""
    disc = pf.discretize(pf.unit_square(n, "triangle"), element="P2", kappa_space="P1",
                         dirichlet=0.0)
    m_true = disc.interpolate_kappa(inclusion)
    f = np.ones(disc.n_dofs)
    data = with_noise(full_field(disc, u_true=true_state(disc, m_true, f)), NOISE, seed)
    return disc, inverse_problem(disc, data, unknown="log_kappa", alpha=GAMMA,
                                 regularization="h1", known=f, truth=m_true)


def build_mesh_file(n_sensors: int = 60, seed: int = 1, alpha: float = 1e-7):
    """The same physics on the shipped plate-with-hole mesh, observed at point sensors."""
    mesh = pf.load_mesh(MESH)
    disc = pf.discretize(mesh, element="P1", kappa_space="P1",
                         dirichlet={"left": 0.0, "right": 0.0, "bottom": 0.0, "top": 0.0})
    lo, hi = mesh.p.min(axis=1), mesh.p.max(axis=1)
    centre = 0.5 * (lo + hi)
    m_true = disc.interpolate_kappa(
        lambda x: inclusion(x, centre=(centre[0] + 0.25 * (hi[0] - lo[0]), centre[1]),
                            radius=0.15 * (hi[1] - lo[1])))
    f = np.ones(disc.n_dofs)
    interior = np.setdiff1d(np.arange(mesh.p.shape[1]), mesh.boundary_nodes())
    picked = np.random.default_rng(seed).choice(interior, n_sensors, replace=False)
    sensors = mesh.p[:, picked].T  # sensors at interior mesh vertices
    data = with_noise(point_sensors(disc, sensors, u_true=true_state(disc, m_true, f)),
                      0.01, seed)
    return disc, inverse_problem(disc, data, unknown="log_kappa", alpha=alpha,
                                 regularization="h1", known=f, truth=m_true)


RUNS = {
    "converged": dict(refinement=converged(1e-10)),
    "fixed K=20": dict(refinement=fixed(20)),
    "prdp": dict(refinement=prdp(K0=10, dK=10, restart=True)),
}


def run(n: int = 64, steps: int = 100):
    _, problem = build(n)
    return compare(problem, RUNS, steps=steps)


def run_mesh_file(steps: int = 100):
    _, problem = build_mesh_file()
    return compare(problem, RUNS, steps=steps)


def main(argv=()):
    n = int(argv[0]) if argv else 64
    steps = int(argv[1]) if len(argv) > 1 else 100
    print(f"coefficient recovery, unit square n = {n} (P2/P1), 5 % noise, gamma = {GAMMA:g}, "
          f"L-BFGS, {steps} steps")
    rows = run(n, steps)
    print(format_table(rows))
    print(f"\nplate with hole ({MESH.name}), 60 point sensors, 1 % noise, {steps} steps")
    mesh_rows = run_mesh_file(steps)
    print(format_table(mesh_rows))
    return rows, mesh_rows


if __name__ == "__main__":
    main(sys.argv[1:])
