"""Reference solves: converged, and the same for the same system whatever the caller's NumPy
random state (pyamg draws its spectral-radius estimates from NumPy's global generator)."""

import numpy as np

import prdp_fem as pf


def test_amg_solve_is_reproducible_and_leaves_the_global_generator_alone():
    disc = pf.discretize(pf.unit_square(24), element="P2", dirichlet=0.0)
    kappa = disc.interpolate_kappa(lambda x: 1.0 + 100.0 * (x[0] > 0.5))
    A, b = disc.stiffness_matrix(kappa), disc.rhs(kappa, np.ones(disc.n_dofs))
    solutions = []
    for seed in (1, 2):
        np.random.seed(seed)  # noqa: NPY002 (the legacy generator pyamg draws from)
        before = np.random.get_state()[1].copy()  # noqa: NPY002
        solutions.append(pf.amg_solve(A, b, rtol=1e-8))
        assert np.array_equal(np.random.get_state()[1], before)  # noqa: NPY002
    first, second = solutions
    assert np.array_equal(first.x, second.x) and first.iterations == second.iterations
    assert first.residual_norm <= 1e-8 * np.linalg.norm(b)
