"""AMG preconditioner (prdp_fem.linalg.amg): construction, the map M, PCG against pyamg, then
grouped
by transformation (jit, vmap, jvp, vjp in both gradient modes), the rebuild policy, the command."""

import functools
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.sparse as sp

import prdp_fem as pf
from prdp_fem.bench import cg as pf_bench_cg
from prdp_fem.cli.main import main
from prdp_fem.inverse import fixed
from prdp_fem.linalg import AMGCycle, PyamgCycle, amg_hierarchy, amg_preconditioner, rebuild_policy

IMPLEMENTATIONS = ["jax", "callback"]
SMOOTHER = {"jax": "jacobi", "callback": "gauss_seidel"}  # the cycle each implementation runs


class Problem:
    """P1 Poisson on the free dofs: the discretisation, kappa, source, operator and rhs."""

    def __init__(self, mesh, kappa_fn=lambda x: 1.0 + 0.0 * x[0]):
        self.disc = pf.discretize(mesh, element="P1", kappa_space="P0")
        self.kappa = jnp.asarray(self.disc.interpolate_kappa(kappa_fn))
        self.f = jnp.asarray(self.disc.interpolate(lambda x: np.sin(3 * x[0]) + x[1]))
        self.operator = self.disc.system.operator(self.kappa)
        self.b = self.disc.system.rhs(self.kappa, self.f)
        self._built = {}
        self.losses = {}

    def built(self, implementation):
        """``(ml, M)``: the pyamg hierarchy and our preconditioner on it (cached)."""
        if implementation not in self._built:
            ml = amg_hierarchy(self.operator, smoother=SMOOTHER[implementation])
            cls = AMGCycle if implementation == "jax" else PyamgCycle
            self._built[implementation] = ml, cls.from_pyamg(ml)
        return self._built[implementation]


def inclusion(x):
    """kappa = 1e4 in a disc, 1 outside: a high-contrast coefficient."""
    return np.where((x[0] - 0.4) ** 2 + (x[1] - 0.6) ** 2 < 0.09, 1e4, 1.0)


@pytest.fixture(scope="module")
def problems():
    return {"square": Problem(pf.unit_square(24)), "cube": Problem(pf.unit_cube(8)),
            "contrast": Problem(pf.unit_square(24), inclusion)}


@pytest.fixture(scope="module")
def small():
    """A 10 x 10 square with a varying kappa, for the derivative tests (fast compiles)."""
    return Problem(pf.unit_square(10), lambda x: 1.0 + x[0] + 0.5 * np.sin(3 * x[1]))


@jax.jit
def converged(matrix, b, precond):
    return pf.solve(matrix, b, pf.ConvergedCG(rtol=1e-10, preconditioner=precond))


def pyamg_iterations(ml, b):
    residuals = []
    ml.solve(np.asarray(b), tol=1e-10, accel="cg", residuals=residuals)
    return len(residuals) - 1


# ------------------------------------------------------------------------------------------
# construction: typed errors at the edge
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("options", "message"), [
    ({"kind": "gmg"}, r"kind='gmg': expected one of \('sa', 'rs'\)"),
    ({"implementation": "cuda"}, r"implementation='cuda': expected one of \('jax', 'callback'\)"),
    ({"smoother": "sor"}, r"smoother='sor': expected one of"),
    ({"implementation": "jax", "smoother": "gauss_seidel"}, r"implements 'jacobi' only"),
    ({"omega": 1.95}, r"omega=1.95: expected a number in \(0, 1.9\] \(the Jacobi damping"),
    ({"omega": 0}, r"omega=0: expected a number in \(0, 1.9\]"),
    ({"sweeps": 0}, r"sweeps=0: expected an integer >= 1"),
    ({"max_coarse": 1.5}, r"max_coarse=1.5: expected an integer >= 1"),
])
def test_bad_options_name_the_argument(problems, options, message):
    with pytest.raises(pf.SolverConfigError, match=message):
        amg_preconditioner(problems["square"].operator, **options)


def test_bad_matrices_raise_typed_errors(problems):
    laplacian = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(20, 20), format="csr")
    broken = laplacian.copy()
    broken.data[3] = np.nan
    with pytest.raises(pf.DataError, match=r"matrix: 1 stored value\(s\) are NaN/Inf"):
        amg_preconditioner(broken)
    with pytest.raises(pf.SolverConfigError, match=r"matrix: not symmetric"):
        amg_preconditioner(laplacian + sp.eye(20, k=2, format="csr"))
    with pytest.raises(pf.SolverConfigError, match=r"a diagonal entry is <= 0"):
        amg_preconditioner(-laplacian)
    with pytest.raises(pf.ShapeError, match=r"matrix: shape \(20, 19\)"):
        amg_preconditioner(laplacian[:, :19])
    with pytest.raises(pf.SolverConfigError, match=r"expected a prdp_fem.SparseMatrix"):
        amg_preconditioner(laplacian.toarray())
    operator = problems["square"].operator
    with pytest.raises(pf.SolverConfigError, match=r"values are traced.*outside the "
                       r"transformation and pass it as an argument"):
        jax.jit(lambda v: amg_preconditioner(operator.with_values(v)))(operator.values)


@pytest.mark.parametrize("builder, options", [("_smoothed_aggregation", {}),
                                               ("_pyamg_solver", {"kind": "rs"})])
def test_a_hierarchy_with_a_non_finite_cycle_is_refused_at_build(problems, monkeypatch, builder,
                                                                 options):
    build = getattr(pf.linalg.amg, builder)

    def broken(*args, **kwargs):  # as Ruge-Stueben can break down on 3-D tetrahedra
        built = build(*args, **kwargs)
        ml = built[0] if isinstance(built, tuple) else built
        ml.levels[-1].A = ml.levels[-1].A * np.nan
        return built

    monkeypatch.setattr(pf.linalg.amg, builder, broken)
    kind = options.get("kind", "sa")
    with pytest.raises(pf.SolverConfigError, match=rf"kind='{kind}': the V-cycle of this "
                       r"hierarchy is not finite and positive"):
        amg_preconditioner(problems["square"].operator, **options)


def test_amg_by_name_in_a_solver_points_to_amg_preconditioner():
    with pytest.raises(pf.SolverConfigError, match=r"preconditioner='amg'.*amg_preconditioner"):
        pf.TruncatedCG(5, preconditioner="amg")


def test_jax_cycle_refuses_a_hierarchy_it_does_not_implement(problems):
    ml, _ = problems["square"].built("callback")  # Gauss-Seidel smoothing
    with pytest.raises(pf.SolverConfigError, match=r"level 0 smooths with gauss_seidel; "
                       r"expected damped Jacobi"):
        AMGCycle.from_pyamg(ml)


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_vector_of_the_wrong_length_is_a_shape_error(problems, implementation):
    _, M = problems["square"].built(implementation)
    with pytest.raises(pf.ShapeError, match=r"r\(3,\): expected a vector of length 529"):
        M(jnp.ones(3))


# ------------------------------------------------------------------------------------------
# the Jacobi smoother's spectral radius (Lanczos)
# ------------------------------------------------------------------------------------------


def _exact_rho_jacobi(matrix) -> float:
    dense = sp.csr_matrix(matrix).toarray()
    scale = 1.0 / np.sqrt(np.diag(dense))
    return float(np.linalg.eigvalsh(dense * scale[:, None] * scale[None, :])[-1])


def _random_spd(n, seed):
    """A sparse SPD matrix with rows of very different scales (a diagonal congruence)."""
    rng = np.random.default_rng(seed)
    a = sp.random(n, n, density=0.05, random_state=seed)
    a = a + a.T + sp.diags(np.abs(a + a.T).sum(axis=1).A1 + 0.1)
    d = sp.diags(10.0 ** rng.uniform(-3, 3, n))
    return sp.csr_matrix(d @ a @ d)


@pytest.mark.parametrize("name", ["square", "cube", "contrast", "levels", "random"])
def test_the_smoothers_spectral_radius_is_within_a_percent_below_the_exact_one(problems, name):
    from prdp_fem.linalg.amg import _rho_jacobi
    if name == "levels":  # every level of a hierarchy, coarse ones included
        matrices = [level.A for level in amg_hierarchy(problems["contrast"].operator).levels]
    elif name == "random":
        matrices = [_random_spd(n, seed) for seed, n in enumerate((300, 40, 3))]
    else:
        matrices = [problems[name].operator.to_scipy()]
    for matrix in matrices:
        exact = _exact_rho_jacobi(matrix)
        estimate = _rho_jacobi(matrix)
        # Ritz values lie below the largest eigenvalue; 4/3 / estimate keeps omega rho < 2
        assert 0.99 * exact <= estimate <= exact * (1 + 1e-12), (matrix.shape, estimate, exact)


def test_the_smoothers_spectral_radius_is_deterministic_and_exact_on_an_invariant_subspace():
    from prdp_fem.linalg.amg import _rho_jacobi
    matrix = _random_spd(200, 7)
    np.random.seed(1)  # noqa: NPY002 (the estimate must not read the global generator)
    first = _rho_jacobi(matrix)
    np.random.seed(2)  # noqa: NPY002
    assert _rho_jacobi(matrix) == first
    # D^-1 A = I: the first Lanczos step spans an invariant subspace, the estimate is exact
    assert _rho_jacobi(sp.diags(np.linspace(1.0, 5.0, 50))) == pytest.approx(1.0, abs=1e-15)


@pytest.mark.parametrize("name, theta", [("square", 0.0), ("cube", 0.0), ("contrast", 0.0),
                                         ("contrast", 0.25)])
def test_smoothed_aggregation_step_by_step_is_pyamgs_given_the_same_radii(problems, name, theta,
                                                                         monkeypatch):
    import pyamg.aggregation.smooth

    from prdp_fem.linalg.amg import _smoothed_aggregation, seeded_numpy_random

    def exact_radius(matrix):  # of D^-1 A, pyamg's prolongation smoother's operator
        return float(np.max(np.abs(np.linalg.eigvals(sp.csr_matrix(matrix).toarray()))))

    csr = problems[name].operator.to_scipy()
    monkeypatch.setattr(pyamg.aggregation.smooth, "approximate_spectral_radius",
                        lambda matrix, **_: exact_radius(matrix))
    monkeypatch.setattr(pf.linalg.amg, "_rho_jacobi", _exact_rho_jacobi)  # the same radii in ours
    with seeded_numpy_random():
        theirs = pyamg.smoothed_aggregation_solver(
            csr.copy(), symmetry="symmetric", strength=("symmetric", {"theta": theta}),
            max_coarse=10, presmoother=None, postsmoother=None)
    ours, radii = _smoothed_aggregation(csr.copy(), 10, theta)
    assert len(ours.levels) == len(theirs.levels) >= 3 and len(radii) == len(ours.levels) - 1
    for depth, (mine, pyamgs) in enumerate(zip(ours.levels, theirs.levels, strict=True)):
        for matrix in ("A", "P", "R") if depth < len(radii) else ("A",):
            a, b = sp.csr_matrix(getattr(mine, matrix)), sp.csr_matrix(getattr(pyamgs, matrix))
            assert a.shape == b.shape and a.format == b.format, (depth, matrix)
            assert abs(a - b).max() <= 1e-13 * abs(b).max(), (depth, matrix)


def test_the_smoothers_radius_is_the_prolongators_one_estimate(problems, monkeypatch):
    estimates = []
    rho_jacobi = pf.linalg.amg._rho_jacobi

    def counted(matrix):
        estimates.append(rho_jacobi(matrix))
        return estimates[-1]

    monkeypatch.setattr(pf.linalg.amg, "_rho_jacobi", counted)
    ml = amg_hierarchy(problems["contrast"].operator, omega=1.2)
    assert len(estimates) == len(ml.levels) - 1  # one per level, shared
    omegas = [level.presmoother.keywords["omega"] for level in ml.levels[:-1]]
    np.testing.assert_allclose(omegas, 1.2 / np.array(estimates), rtol=1e-15)


@pytest.mark.parametrize("spelling", ["symmetric", ("symmetric", {}),
                                      ("symmetric", {"theta": 0.0})])
def test_the_default_strength_spelt_out_builds_the_same_hierarchy(problems, spelling):
    default = amg_hierarchy(problems["contrast"].operator)
    spelt = amg_hierarchy(problems["contrast"].operator, strength=spelling)
    assert len(spelt.levels) == len(default.levels)
    for ours, reference in zip(spelt.levels, default.levels, strict=True):
        assert (sp.csr_matrix(ours.A) != sp.csr_matrix(reference.A)).nnz == 0
    assert [level.presmoother.keywords["omega"] for level in spelt.levels[:-1]] == \
        [level.presmoother.keywords["omega"] for level in default.levels[:-1]]


def test_a_level_with_a_non_finite_diagonal_gets_a_nan_radius():
    from prdp_fem.linalg.amg import _rho_jacobi
    assert np.isnan(_rho_jacobi(sp.diags([1.0, np.nan, 2.0])))
    assert np.isnan(_rho_jacobi(sp.diags([1.0, np.inf, 2.0])))


def test_a_level_without_a_positive_diagonal_gets_pyamgs_estimate():
    from pyamg.relaxation.smoothing import rho_D_inv_A

    from prdp_fem.linalg.amg import _rho_jacobi, seeded_numpy_random
    matrix = sp.csr_matrix(np.array([[2.0, 1.0, 0.0], [1.0, -1.0, 0.5], [0.0, 0.5, 3.0]]))
    with seeded_numpy_random():
        expected = float(rho_D_inv_A(matrix.copy()))
    with seeded_numpy_random():
        assert _rho_jacobi(matrix) == expected


# ------------------------------------------------------------------------------------------
# the map M: pyamg's cycle, symmetric positive definite
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
@pytest.mark.parametrize("name", ["square", "cube"])
def test_cycle_is_pyamgs_cycle_on_the_same_hierarchy(problems, name, implementation):
    ml, M = problems[name].built(implementation)
    r = np.random.default_rng(1).standard_normal(M.n)
    expected = ml.aspreconditioner(cycle="V") @ r
    np.testing.assert_allclose(M(r), expected, rtol=1e-12, atol=1e-12 * abs(expected).max())


@pytest.mark.parametrize(("fraction", "rows", "sparse_levels"), [
    (0.0, 0, "all but the coarsest"),  # the cycle level by level, A_L^+ alone dense
    (0.0, 64, "above 64 rows"),
    (0.0, 10**6, "none"),  # the whole cycle one dense matrix
])
def test_the_dense_tail_of_the_jax_cycle_is_pyamgs_cycle(monkeypatch, fraction, rows,
                                                        sparse_levels):
    monkeypatch.setattr(pf.linalg.amg, "_DENSE_FRACTION", fraction)
    monkeypatch.setattr(pf.linalg.amg, "_DENSE_ROWS", rows)
    problem = Problem(pf.unit_square(40))
    ml = amg_hierarchy(problem.operator)
    sizes = [level.A.shape[0] for level in ml.levels]
    expected_sparse = {"all but the coarsest": len(sizes) - 1, "none": 0,
                       "above 64 rows": sum(n > 64 for n in sizes)}[sparse_levels]
    assert 0 < sum(n > 64 for n in sizes) < len(sizes) - 1  # each case cuts elsewhere
    M = AMGCycle.from_pyamg(ml)
    assert len(M.levels) == expected_sparse
    assert M.coarse_map.shape == (sizes[expected_sparse],) * 2
    r = np.random.default_rng(3).standard_normal((3, M.n))
    expected = np.stack([ml.aspreconditioner(cycle="V") @ row for row in r])
    np.testing.assert_allclose(jax.vmap(M)(r), expected, rtol=1e-12,
                               atol=1e-12 * abs(expected).max())


def test_the_dense_tail_starts_at_the_first_level_small_enough():
    """A level goes dense once its dense matrix holds at most half the finest
    matrix's entries (or it has at most 64 rows): on 2-D P1 at 65k dofs (324105 entries),
    from 136 rows (18496 entries; the level above has 1224 rows, 1.5M entries)."""
    operator, _ = pf_bench_cg.poisson_operator(256)
    ml = amg_hierarchy(operator)
    sizes = [level.A.shape[0] for level in ml.levels]
    assert sizes[:4] == [65025, 10943, 1224, 136] and len(sizes) > 4
    assert pf.linalg.amg._first_dense_level(ml) == 3
    assert len(AMGCycle.from_pyamg(ml).levels) == 3


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
@pytest.mark.parametrize("name", ["square", "cube", "contrast"])
def test_preconditioner_is_symmetric_positive_definite(problems, name, implementation):
    _, M = problems[name].built(implementation)
    u, v = np.random.default_rng(2).standard_normal((2, 6, M.n))
    mu, mv = jax.vmap(M)(u), jax.vmap(M)(v)
    uMv, vMu = np.einsum("ki,ki->k", u, mv), np.einsum("ki,ki->k", v, mu)
    np.testing.assert_allclose(uMv, vMu, rtol=1e-11, atol=1e-12 * np.abs(uMv).max())
    assert np.all(np.einsum("ki,ki->k", u, mu) > 0)


# ------------------------------------------------------------------------------------------
# PCG + AMG: iterations equal pyamg's own CG, solution equals a direct solve
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
@pytest.mark.parametrize("name", ["square", "cube", "contrast"])
def test_iterations_equal_pyamgs_cg_on_the_same_hierarchy(problems, name, implementation):
    problem = problems[name]
    ml, M = problem.built(implementation)
    sol = converged(problem.operator, problem.b, M)
    assert pf.Status(int(sol.status)) == pf.Status.SUCCESS
    assert abs(int(sol.iterations) - pyamg_iterations(ml, problem.b)) <= 1
    assert int(sol.iterations) < 25  # AMG, not Jacobi (which needs ~70 here)


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
@pytest.mark.parametrize("name", ["square", "cube", "contrast"])
def test_solution_equals_a_direct_solve(problems, name, implementation):
    problem = problems[name]
    _, M = problem.built(implementation)
    x = converged(problem.operator, problem.b, M).x
    x_direct = pf.direct_solve(problem.operator.to_scipy(), np.asarray(problem.b)).x
    np.testing.assert_allclose(x, x_direct, rtol=0, atol=1e-8 * abs(x_direct).max())


def test_ruge_stueben_in_2d(problems):
    problem = problems["square"]
    for implementation, cls in (("jax", AMGCycle), ("callback", PyamgCycle)):
        ml = amg_hierarchy(problem.operator, kind="rs", smoother=SMOOTHER[implementation])
        sol = converged(problem.operator, problem.b, cls.from_pyamg(ml))
        assert abs(int(sol.iterations) - pyamg_iterations(ml, problem.b)) <= 1


# ------------------------------------------------------------------------------------------
# jit and vmap
# ------------------------------------------------------------------------------------------


def test_jit_takes_the_preconditioner_as_an_argument_and_a_rebuild_reuses_the_compile(
        problems):
    problem = problems["square"]
    traces = []

    @jax.jit
    def apply(precond, r):
        traces.append(1)
        return precond(r)

    _, first = problem.built("jax")
    np.testing.assert_allclose(apply(first, problem.b), first(problem.b), rtol=1e-14)
    rebuilt = amg_preconditioner(problem.operator.with_values(2.0 * problem.operator.values),
                                 implementation="jax")
    np.testing.assert_allclose(apply(rebuilt, problem.b), rebuilt(problem.b), rtol=1e-14)
    assert len(traces) == 1  # same level sizes: the same compiled function


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_vmap_over_right_hand_sides(problems, implementation):
    problem = problems["square"]
    _, M = problem.built(implementation)
    rhs = jnp.stack([problem.b, jnp.flip(problem.b), jnp.ones_like(problem.b)])
    batched = jax.vmap(lambda b: converged(problem.operator, b, M).x)(rhs)
    for b, x in zip(rhs, batched, strict=True):
        np.testing.assert_allclose(x, converged(problem.operator, b, M).x, rtol=1e-12,
                                   atol=1e-14)
    # a batch axis other than the first reaches the cycle as one batched call
    np.testing.assert_allclose(jax.vmap(M, in_axes=1, out_axes=1)(rhs.T),
                               jax.vmap(M)(rhs).T, rtol=1e-13)


def test_vmap_over_stacked_hierarchies(problems):
    problem = problems["square"]
    _, first = problem.built("jax")
    second = amg_preconditioner(problem.operator.with_values(2.0 * problem.operator.values))
    # stacked on the host and applied jitted: one program (op by op, some 35 small ones)
    stacked = jax.tree_util.tree_map(lambda a, c: np.stack([a, c]), first, second)
    applied = jax.jit(jax.vmap(lambda M, r: M(r), in_axes=(0, None)))(stacked, problem.b)
    # to round-off, not bit for bit: how XLA fuses the batched gathers is its own choice
    np.testing.assert_allclose(applied, jnp.stack([first(problem.b), second(problem.b)]),
                               rtol=1e-14)


# ------------------------------------------------------------------------------------------
# derivatives of M itself: linear, tangent M dr, transpose M
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_linear_rules_of_the_cycle(problems, implementation):
    _, M = problems["square"].built(implementation)
    r, dr = np.random.default_rng(3).standard_normal((2, M.n))
    z, tangent = jax.jvp(M, (jnp.asarray(r),), (jnp.asarray(dr),))
    np.testing.assert_allclose(tangent, M(dr), rtol=1e-14)
    _, pullback = jax.vjp(M, jnp.asarray(r))
    np.testing.assert_allclose(pullback(jnp.asarray(dr))[0], M(dr), rtol=1e-14)
    (transposed,) = jax.linear_transpose(M, jnp.asarray(r))(jnp.asarray(dr))
    np.testing.assert_allclose(transposed, M(dr), rtol=1e-14)
    # grad(r.Mr / 2) = M r (symmetric), under jit and vmap too
    grad = jax.jit(jax.vmap(jax.grad(lambda v: 0.5 * jnp.vdot(v, M(v)))))
    np.testing.assert_allclose(grad(jnp.stack([r, dr]))[0], z, rtol=1e-12,
                               atol=1e-14 * np.abs(z).max())


# ------------------------------------------------------------------------------------------
# derivatives of solve(...).x: Taylor tests, both gradient modes
# ------------------------------------------------------------------------------------------

SOLVERS = {
    # truncated well before convergence: the derivative of the 4-iteration map
    "unrolled": lambda M: pf.TruncatedCG(4, preconditioner=M),
    # converged to round-off by 40 AMG iterations: implicit gradients are exact
    "implicit": lambda M: pf.TruncatedCG(40, preconditioner=M, gradient="implicit"),
    "converged": lambda M: pf.ConvergedCG(rtol=1e-13, preconditioner=M),
}


def loss(problem, mode):
    """``J((kappa, f), M) = w . x(kappa, f)``, jitted, ``M`` passed as an argument (one function
    per mode, shared by the tests: each compiles once per implementation)."""
    if mode not in problem.losses:
        problem.losses[mode] = _loss(problem, mode)
    return problem.losses[mode]


def _loss(problem, mode):
    system = problem.disc.system
    w = jnp.asarray(np.random.default_rng(4).standard_normal(problem.disc.n_free))

    @jax.jit
    def fn(kappa_and_f, precond):
        kappa, f = kappa_and_f
        return w @ pf.solve(system.operator(kappa), system.rhs(kappa, f), SOLVERS[mode](precond)).x

    return fn


# unrolled: the slow twin; converged too (ConvergedCG differentiates on the implicit path)
@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
@pytest.mark.parametrize("mode", [pytest.param(m, marks=pytest.mark.slow) if m != "implicit"
                                  else m for m in SOLVERS])
def test_vjp_passes_the_taylor_test(small, mode, implementation):
    _, M = small.built(implementation)
    fn = loss(small, mode)
    x = (small.kappa, small.f)
    # steps small enough for the asymptotic regime of the (strongly contracting) AMG-CG map
    result = pf.taylor_test(lambda v: fn(v, M), x, gradient=jax.jit(jax.grad(fn))(x, M),
                            h0=2e-3)  # the gradient jitted: one program (grad of a jit: two)
    assert result.passed(), (result.rates, result.first_order)


# callback: the slow twin (test_linear_rules_of_the_cycle[callback] checks its cycle's tangent)
@pytest.mark.parametrize("implementation", [
    "jax", pytest.param("callback", marks=pytest.mark.slow)])
def test_unrolled_jvp_passes_the_taylor_test(small, implementation):
    _, M = small.built(implementation)
    fn = loss(small, "unrolled")
    x = (small.kappa, small.f)
    direction = (jnp.asarray(np.cos(np.arange(small.kappa.size))),
                 jnp.asarray(np.sin(np.arange(small.f.size))))
    _, slope = jax.jvp(lambda v: fn(v, M), (x,), (direction,))
    # a "gradient" whose inner product with the direction is the jvp: the Taylor remainder
    # with it shrinks at second order only if the jvp is the directional derivative
    norm2 = sum(jnp.vdot(d, d) for d in direction)
    as_gradient = tuple(slope * d / norm2 for d in direction)
    result = pf.taylor_test(lambda v: fn(v, M), x, direction, gradient=as_gradient, h0=2e-3)
    assert result.passed(), result.rates


# ------------------------------------------------------------------------------------------
# when to rebuild
# ------------------------------------------------------------------------------------------


def test_rebuild_every_n_steps():
    policy = rebuild_policy(every=3)
    state = policy.init(jnp.ones(2))
    decisions = []
    for _ in range(7):
        rebuild, state = policy.update(state, jnp.ones(2))
        decisions.append(bool(rebuild))
    assert decisions == [False, False, True, False, False, True, False]


def test_rebuild_when_values_move_by_more_than_the_factor():
    policy = rebuild_policy(factor=2.0)
    reference = jnp.array([1.0, -4.0, 0.0])
    state = policy.init(reference)
    update = jax.jit(policy.update)
    cases = [([1.9, -4.0, 0.0], False), ([1.0, -2.1, 0.0], False), ([2.1, -4.0, 0.0], True),
             ([0.49, -4.0, 0.0], True), ([1.0, 4.0, 0.0], True), ([1.0, -4.0, 1e-3], True),
             ([np.nan, -4.0, 0.0], True)]
    for values, expected in cases:
        rebuild, _ = update(state, jnp.asarray(values))
        assert bool(rebuild) == expected, values
    # a rebuild resets the reference: the same values no longer count as moved
    rebuild, state = update(state, jnp.asarray([3.0, -4.0, 0.0]))
    assert bool(rebuild) and int(state.steps_since_build) == 0
    assert not bool(update(state, jnp.asarray([3.0, -4.0, 0.0]))[0])
    # without a rebuild the state ages and keeps its reference
    _, older = update(state, jnp.asarray([3.5, -4.0, 0.0]))
    assert int(older.steps_since_build) == 1
    np.testing.assert_array_equal(older.reference_values, [3.0, -4.0, 0.0])


def test_the_host_update_is_numpy_and_decides_as_the_jitted_one():
    policy = rebuild_policy(every=4, factor=2.0)
    host, device = policy.init(np.array([1.0, -4.0, 0.0])), policy.init(jnp.array([1.0, -4.0,
                                                                                 0.0]))
    assert all(isinstance(leaf, np.ndarray) for leaf in host)
    update = jax.jit(policy.update)
    for values in ([1.9, -4.0, 0.0], [2.1, -4.0, 0.0], [2.1, -4.0, 0.0], [np.nan, 1.0, 0.0],
                   [0.0, 0.0, 0.0], [0.0, 0.0, 1e-3], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0],
                   [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]):
        rebuild, host = policy.update(host, np.array(values))
        expected, device = update(device, jnp.array(values))
        assert isinstance(rebuild, np.ndarray | np.bool_) and bool(rebuild) == bool(expected)
        for mine, theirs in zip(host, device, strict=True):
            np.testing.assert_array_equal(mine, np.asarray(theirs))


@pytest.mark.parametrize(("options", "message"), [
    ({}, r"expected at least one rebuild criterion"),
    ({"every": 0}, r"every=0: expected an integer >= 1"),
    ({"factor": 1.0}, r"factor=1.0: expected a finite number > 1"),
    ({"every": 2, "factor": float("inf")}, r"factor=inf"),
])
def test_bad_rebuild_policies(options, message):
    with pytest.raises(pf.SolverConfigError, match=message):
        rebuild_policy(**options)


#: one optimizer object for the inversions below: a step program is kept per optimizer object
#: (and AMG hierarchies of equal shapes are its argument), so their runs share one compile
SGD = optax.sgd(10.0)


@functools.cache  # one problem for the tests below (each builds its own runs from it)
def _coefficient_inversion(n=6):
    """A log-kappa inversion from a full noiseless field (the preconditioner's operator moves
    with every step)."""
    disc = pf.discretize(pf.unit_square(n), element="P1", kappa_space="P0", dirichlet=0.0)
    m_true = disc.interpolate_kappa(lambda x: 0.5 * np.sin(np.pi * x[0]) * x[1])
    f = np.ones(disc.n_dofs)
    kappa = np.exp(m_true)
    u = disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f)).x)
    observation = pf.full_field(disc, u_true=u)
    return pf.inverse_problem(disc, observation, unknown="log_kappa", alpha=1e-6, known=f,
                              truth=m_true)


def test_invert_rebuilds_the_hierarchy_at_the_current_kappa_when_the_policy_says_so(
        monkeypatch):
    problem = _coefficient_inversion()
    built = []  # the matrices the hierarchies were built from
    build = pf.RebuiltAMG.build
    monkeypatch.setattr(pf.RebuiltAMG, "build",
                        lambda self, matrix: built.append(matrix.to_scipy()) or
                        build(self, matrix))
    params = []
    run = pf.invert(problem, refinement=fixed(4), steps=6, optimizer=SGD,
                    preconditioner=pf.RebuiltAMG(rebuild_policy(every=2)),
                    callback=lambda record, z: params.append(np.asarray(z)))
    # the policy fires after steps 2, 4 and 6; steps 3 and 5 start with a new hierarchy, and
    # none is built after the last step
    assert [record.rebuilds for record in run.history] == [0, 0, 1, 1, 2, 2]
    starts = [np.zeros(problem.n_parameters), params[1], params[3]]
    assert len(built) == 3
    for matrix, z in zip(built, starts, strict=True):
        kappa = problem.parameterization.coefficients(jnp.asarray(z), problem.known)[0]
        expected = problem.system.operator(kappa).to_scipy()
        assert abs(matrix - expected).max() == 0.0
    assert len({float(abs(m).sum()) for m in built}) == 3  # kappa moved between the builds
    # a policy that never fires runs exactly as the hierarchy built at the start, passed in
    never = pf.invert(problem, refinement=fixed(4), steps=3, optimizer=SGD,
                      preconditioner=pf.RebuiltAMG(rebuild_policy(every=100)))
    fixed_amg = pf.invert(problem, refinement=fixed(4), steps=3, optimizer=SGD,
                          preconditioner=amg_preconditioner(
                              problem.system.operator(jnp.ones(problem.n_parameters))))
    np.testing.assert_array_equal(never.history.column("loss"),
                                  fixed_amg.history.column("loss"))
    assert [record.rebuilds for record in never.history] == [0, 0, 0]


def test_the_first_hierarchy_build_is_run_time(monkeypatch):
    """The AMG setup is part of the method's cost: the build before the first step counts in
    that step's time (left out, it would flatter an AMG run's saving against a Jacobi one).
    The build is made to take a known extra time: the first step's time holds it, and the
    run is the same."""
    problem = _coefficient_inversion()
    extra = 0.4
    build = pf.RebuiltAMG.build

    def slow_build(self, matrix):
        time.sleep(extra)
        return build(self, matrix)

    preconditioner = pf.RebuiltAMG()
    pf.invert(problem, refinement=fixed(4), steps=2, optimizer=SGD,
              preconditioner=preconditioner)  # compiled here: the next run's times are steps
    fast = pf.invert(problem, refinement=fixed(4), steps=2, optimizer=SGD,
                     preconditioner=preconditioner)
    monkeypatch.setattr(pf.RebuiltAMG, "build", slow_build)
    slow = pf.invert(problem, refinement=fixed(4), steps=2, optimizer=SGD,
                     preconditioner=preconditioner)
    assert slow.history[0].time >= extra
    np.testing.assert_array_equal(slow.history.column("loss"), fast.history.column("loss"))


def test_after_a_rebuild_l_bfgs_evaluates_with_the_new_hierarchy():
    """A truncated J depends on the preconditioner: the value L-BFGS stored with the old
    hierarchy is recomputed, so the step after a rebuild reports J(z) at the new one."""
    problem = _coefficient_inversion()
    params = []
    run = pf.invert(problem, refinement=fixed(3), steps=3,
                    preconditioner=pf.RebuiltAMG(rebuild_policy(every=2)),
                    callback=lambda record, z: params.append(np.asarray(z)))
    assert [record.rebuilds for record in run.history] == [0, 0, 1]
    z = jnp.asarray(params[1])
    kappa = problem.parameterization.coefficients(z, problem.known)[0]
    new = amg_preconditioner(problem.system.operator(kappa))
    old = amg_preconditioner(problem.system.operator(jnp.ones(problem.n_parameters)))
    # jitted, the cycle an argument (op by op, the loss compiled some 20 small programs)
    loss = jax.jit(lambda z, cycle: problem.loss(z, pf.TruncatedCG(3, cycle))[0])
    at_new, at_old = (float(loss(z, cycle)) for cycle in (new, old))
    assert abs(at_new - at_old) > 1e-6 * abs(at_new)  # the test can tell them apart
    assert run.history[2].loss == pytest.approx(at_new, rel=1e-10)


def test_a_validation_monitor_with_rebuilds_compiles_its_programs_once(monkeypatch):
    from conftest import shared_compiles_made

    from prdp_fem.inverse import driver as inverse

    inverse._step_program.cache_clear()
    inverse._validation_program.cache_clear()
    made = shared_compiles_made(monkeypatch)
    problem = _coefficient_inversion()
    run = pf.invert(problem, refinement=fixed(4), steps=5, optimizer=SGD,
                    preconditioner=pf.RebuiltAMG(rebuild_policy(every=1)),
                    monitor=pf.inverse.Validation(every=1))
    assert [record.rebuilds for record in run.history] == [0, 1, 2, 3, 4]
    assert len(made) == 2 and all(len(program._cache) == 1 for program in made)


@pytest.mark.parametrize(("arguments", "message"), [
    ({"policy": "every 10"}, r"policy='every 10': expected None or a RebuildPolicy"),
    ({"kind": "ml"}, r"kind='ml': expected one of"),
    ({"implementation": "jax", "smoother": "gauss_seidel"}, r"implements 'jacobi' only"),
    ({"sweeps": 0}, r"sweeps=0: expected an integer >= 1"),
])
def test_a_rebuilt_amg_checks_its_options_at_construction(arguments, message):
    arguments = {"policy": rebuild_policy(every=5), **arguments}
    with pytest.raises(pf.SolverConfigError, match=message):
        pf.RebuiltAMG(**arguments)


# ------------------------------------------------------------------------------------------
# prdp-fem bench amg
# ------------------------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(
    [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}


def test_bench_amg_reports_iterations_and_ratios(capsys):
    assert main(["bench", "amg", "--sides", "12", "--cube-sides", "--implementations", "jax",
                 "--repeats", "1"]) == 0
    row = capsys.readouterr().out.strip().splitlines()[-1].split()
    assert row[:3] == ["2", str(11 * 11), "jax"] and row[5] == "yes"  # iterations equal
    assert len(row) == 13 and all(float(v) >= 0 for v in row[6:])


def test_bench_amg_bad_option_is_one_line_and_exit_2(tmp_path):
    done = subprocess.run([sys.executable, "-m", "prdp_fem.cli.main", "bench", "amg", "--repeats",
                           "0"], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env=ENV)
    assert done.returncode == 2, done.stderr
    assert done.stderr == "prdp-fem: error: --repeats 0: expected integers >= 1\n"


@pytest.mark.parametrize(("args", "message"), [
    (["--sides", "1"], r"--sides 1: expected integers >= 2"),
    (["--sides", "--cube-sides"], r"--sides, --cube-sides: both empty"),
    (["--implementations", "gpu"], r"--implementations gpu: expected some of jax callback"),
])
def test_bench_amg_bad_options(capsys, args, message):
    assert main(["bench", "amg", *args]) == 2
    error = capsys.readouterr().err
    assert error.startswith("prdp-fem: error: ") and error.count("\n") == 1
    assert re.search(message, error), error
