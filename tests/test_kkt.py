"""MINRES, the Chebyshev mass inverse and the all-at-once KKT solve of source problems."""

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import prdp_fem as pf
from prdp_fem.bench.inverse import mother_optimum_field, mother_problem
from prdp_fem.errors import SolverBreakdownError, SolverConfigError
from prdp_fem.inverse import converged, reduced_cg
from prdp_fem.inverse.kkt import kkt_solve, kkt_system
from prdp_fem.linalg.host_minres import chebyshev_inverse, minres
from prdp_fem.linalg.operator import FixedMatrix


def _indefinite_system(n=40, seed=1):
    rng = np.random.default_rng(seed)
    q = rng.standard_normal((n, n))
    a = q + q.T  # symmetric, indefinite
    lower = rng.standard_normal((n, n))
    preconditioner = lower @ lower.T + n * np.eye(n)
    return a, rng.standard_normal(n), np.linalg.inv(preconditioner)


def test_minres_iterates_are_scipys_and_its_residual_norm_is_the_true_one():
    a, b, p_inverse = _indefinite_system()
    theirs = []
    spla.minres(a, b, M=p_inverse, rtol=1e-15, maxiter=25,
                callback=lambda x: theirs.append(x.copy()))
    ours = []
    solution = minres(lambda v: a @ v, b, lambda v: p_inverse @ v, rtol=1e-15,
                      max_iterations=25, callback=lambda k, x: ours.append(x.copy()))
    assert solution.result == "max_iterations" and solution.iterations == 25 == len(ours)
    for mine, scipys in zip(ours, theirs, strict=True):
        np.testing.assert_allclose(mine, scipys, rtol=1e-7, atol=1e-9 * np.abs(scipys).max())
    residual = b - a @ solution.x
    assert solution.residual_norm == pytest.approx(np.sqrt(residual @ p_inverse @ residual),
                                                   rel=1e-8)
    assert np.all(np.diff(solution.residual_history) <= 1e-12)  # MINRES never goes up


def test_minres_converges_stops_and_says_why():
    a, b, p_inverse = _indefinite_system()
    solved = minres(lambda v: a @ v, b, lambda v: p_inverse @ v, rtol=1e-10)
    assert solved.result in ("converged", "exhausted")
    np.testing.assert_allclose(a @ solved.x, b, atol=1e-7 * np.linalg.norm(b))
    stopped = minres(lambda v: a @ v, b, lambda v: p_inverse @ v,
                     callback=lambda k, x: k == 3)
    assert (stopped.result, stopped.iterations) == ("stopped", 3)
    zero = minres(lambda v: a @ v, np.zeros(len(b)), lambda v: v)
    assert zero.result == "converged" and zero.iterations == 0 and not zero.x.any()


def test_minres_refuses_an_indefinite_preconditioner_and_nonfinite_operands():
    a, b, _ = _indefinite_system()
    with pytest.raises(SolverBreakdownError, match="positive definite preconditioner"):
        minres(lambda v: a @ v, b, lambda v: -v)
    with pytest.raises(SolverBreakdownError, match="finite"):
        minres(lambda v: a @ v * np.nan, b, lambda v: v)
    with pytest.raises(SolverConfigError, match="rtol=2"):
        minres(lambda v: a @ v, b, lambda v: v, rtol=2)


def test_chebyshev_inverse_of_a_mass_matrix_is_spd_and_converges_with_steps():
    disc = pf.discretize(pf.unit_square(8, "triangle"), element="P1", kappa_space="P0")
    mass = disc.mass_matrix.tocsr()
    dense = mass.toarray()
    errors = []
    for steps in (1, 3, 6):
        apply = chebyshev_inverse(mass, steps)
        inverse = np.column_stack([apply(e) for e in np.eye(mass.shape[0])])
        np.testing.assert_allclose(inverse, inverse.T, atol=1e-12 * np.abs(inverse).max())
        assert np.linalg.eigvalsh((inverse + inverse.T) / 2).min() > 0
        errors.append(np.linalg.norm(np.eye(len(dense)) - inverse @ dense, 2))
    # D^-1 M in [1/2, 2] on triangles: the Chebyshev rate (sqrt(4) - 1) / (sqrt(4) + 1) = 1/3
    assert errors[0] < 1 and errors[1] < errors[0] / 5 and errors[2] < errors[1] / 10
    with pytest.raises(SolverConfigError, match="steps=0"):
        chebyshev_inverse(mass, 0)
    with pytest.raises(SolverConfigError, match="non-positive"):
        chebyshev_inverse(sp.diags([1.0, 0.0]), 2)


@pytest.fixture(scope="module")
def mother16():
    return mother_problem(16), mother_optimum_field(16)


def _relative(problem, f, reference):
    mass = problem.parameter_mass.to_scipy()
    gap = f - reference
    return float(np.sqrt(gap @ mass @ gap / (reference @ mass @ reference)))


def test_the_kkt_solve_is_the_discrete_optimum_of_the_mother_problem(mother16):
    """MINRES on the KKT system reaches the optimum the reduced-space CG converges to (itself
    checked against a sparse LU in test_bench_inverse), with the state and adjoint of it."""
    problem, optimum = mother16
    solution = kkt_solve(problem, rtol=1e-12)
    assert solution.result == "converged"
    assert _relative(problem, solution.field, optimum) < 1e-9
    blocks = kkt_system(problem)
    state = spla.spsolve(blocks.stiffness.tocsc(), blocks.source @ solution.field)
    np.testing.assert_allclose(solution.state, state, rtol=1e-8, atol=1e-12)
    # stationarity in f: alpha R f = S^T lam
    np.testing.assert_allclose(blocks.alpha * (blocks.regularization @ solution.field),
                               blocks.source.T @ solution.adjoint, atol=1e-16)
    assert solution.vcycles == 2 * (solution.iterations + 1)


def test_the_kkt_iterations_do_not_grow_with_the_mesh():
    """The Pearson-Wathen preconditioner is mesh-independent: the same residual reduction
    in about the same number of MINRES iterations from 8 x 8 to 64 x 64."""
    counts = [kkt_solve(mother_problem(n), rtol=1e-10).iterations for n in (8, 16, 32, 64)]
    assert max(counts) <= 40 and max(counts) - min(counts) <= 6


def _general_source_problem(dim=2):
    mesh = pf.unit_square(6) if dim == 2 else pf.unit_cube(3)
    disc = pf.discretize(mesh, element="P1", kappa_space="P0",
                         dirichlet={"left": 1.0, "bottom": lambda x: x[0]},
                         neumann={"top": 0.5} if dim == 2 else None)
    state = disc.expand(pf.direct_solve(disc.stiffness_matrix(np.ones(disc.n_kappa)),
                                        disc.rhs(np.ones(disc.n_kappa))).x)
    observation = pf.with_noise(pf.full_field(disc, u_true=state), 0.05, seed=3)
    reference = disc.interpolate(lambda x: 1 + x[1])
    regularization = pf.regularizer(disc, "source", "l2", reference=reference)
    return pf.inverse_problem(disc, observation, unknown="source", alpha=1e-3,
                              regularization=regularization,
                              known=disc.interpolate_kappa(lambda x: 1 + x[0]))


# (2, "sa") with the slow cases: (2, "rs") and (3, "sa") cover both AMG kinds and dimensions
@pytest.mark.parametrize(("dim", "amg"), [(2, "rs"),
                                          pytest.param(2, "sa", marks=pytest.mark.slow),
                                          (3, "sa")])
def test_the_kkt_solve_carries_dirichlet_neumann_data_and_a_reference(dim, amg):
    """Every affine term (Dirichlet and Neumann data, a variable kappa, the regulariser's
    reference, noisy data) as the reduced-space CG sees them through the JAX losses."""
    problem = _general_source_problem(dim)
    expected = reduced_cg(problem, refinement=converged(1e-13), iterations=200, rtol=1e-12,
                          riesz_rtol=1e-14).field
    solution = kkt_solve(problem, rtol=1e-13, amg=amg)
    np.testing.assert_allclose(solution.field, expected, rtol=1e-7,
                               atol=1e-8 * np.abs(expected).max())


def test_a_weighted_misfit_changes_the_iterations_little(mother16):
    """Matched for the mother problem's ``H = M``, the preconditioner stays effective for a
    misfit weighted by 1e-4 to 1e4 (the effective alpha moves by eight decades)."""
    problem, _ = mother16
    observation = problem.observation
    counts = []
    for weight in (1e-4, 1.0, 1e4):
        weighted = dataclasses.replace(problem, observation=dataclasses.replace(
            observation, weight=FixedMatrix.symmetric(weight * observation.weight.to_scipy())))
        solution = kkt_solve(weighted, rtol=1e-10)
        assert solution.result == "converged"
        counts.append(solution.iterations)
    assert max(counts) <= 30


def test_the_kkt_solve_stops_at_the_callback_with_the_current_field(mother16):
    problem, optimum = mother16
    seen = []
    solution = kkt_solve(problem, callback=lambda k, field: seen.append(field.copy()) or k == 5)
    assert (solution.result, solution.iterations, len(seen)) == ("stopped", 5, 5)
    np.testing.assert_array_equal(seen[-1], solution.field)
    assert _relative(problem, seen[0], optimum) > _relative(problem, seen[-1], optimum)


@pytest.mark.parametrize(("settings", "message"), [
    (dict(unknown="log_kappa"), "unknown='log_kappa'"),
    (dict(unknown="source", bounds=(0.0, 1.0)), r"bounds=\(0.0, 1.0\)"),
    (dict(unknown="source", regularization="h1"), "regularization='h1'; expected 'l2'"),
    (dict(unknown="source", regularization="l2", alpha=0.0), "alpha=0.0; expected alpha > 0"),
])
def test_the_kkt_solve_refuses_problems_it_does_not_solve(settings, message):
    disc = pf.discretize(pf.unit_square(4), element="P1", kappa_space="P1", dirichlet=0.0)
    observation = pf.full_field(disc, data=np.zeros(disc.n_dofs))
    problem = pf.inverse_problem(disc, observation, **{"alpha": 1e-6, **settings})
    with pytest.raises(SolverConfigError, match=message):
        kkt_solve(problem)


def test_the_kkt_solve_refuses_sparse_sensors_and_bad_options(mother16):
    disc = pf.discretize(pf.unit_square(4), element="P1", kappa_space="P0", dirichlet=0.0)
    sensors = pf.point_sensors(disc, np.array([[0.5, 0.5], [0.25, 0.75]]),
                               data=np.zeros(2))
    problem = pf.inverse_problem(disc, sensors, unknown="source", alpha=1e-6,
                                 regularization="l2")
    with pytest.raises(SolverConfigError, match=r"carry no misfit weight .* use reduced_cg"):
        kkt_solve(problem)
    with pytest.raises(SolverConfigError, match="amg='gmg'"):
        kkt_solve(mother16[0], amg="gmg")
