"""Stiff and singular inputs to the solver: status codes, pure Neumann nullspace, tensor
coefficients, condition estimates and extreme meshes, grouped by what they check."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

import prdp_fem as pf
from prdp_fem.linalg import ConvergedCG, Status, TruncatedCG, solve
from prdp_fem.studies.conditioning import condition_estimate

MODES = ("unrolled", "implicit")
# the unrolled twin of a slow case runs with -m slow; the implicit one in the default suite
SLOW_UNROLLED = (pytest.param("unrolled", marks=pytest.mark.slow), "implicit")


def square(n=8, **options):
    return pf.discretize(pf.unit_square(n), **options)


# ------------------------------------------------------------------------------------------
# status: eager calls raise typed errors, jitted calls report them
# ------------------------------------------------------------------------------------------


def test_negative_kappa_breaks_down_eagerly_and_is_flagged_under_jit():
    disc = square()
    system, f = disc.system, np.ones(disc.n_dofs)
    with pytest.raises(pf.errors.SolverBreakdownError, match="not positive definite"):
        system.solve(-np.ones(disc.n_kappa), f, ConvergedCG())
    solvers = (ConvergedCG(), TruncatedCG(20), TruncatedCG(20, gradient="implicit"))
    # the three solves in one program (one compile, not three)
    sols = jax.jit(lambda k: [system.solve(k, f, s) for s in solvers])(-jnp.ones(disc.n_kappa))
    for sol in sols:
        assert int(sol.status) == Status.BREAKDOWN
        assert np.isfinite(sol.x).all()


def test_nan_inputs_are_refused_eagerly_and_flagged_under_jit():
    disc = square()
    system = disc.system
    A = system.operator(jnp.ones(disc.n_kappa))
    b = np.ones(disc.n_free)
    bad_b = b.copy()
    bad_b[3] = np.nan
    with pytest.raises(pf.DataError, match=r"b: 1 of \d+ entries are NaN/Inf \(first: index 3\)"):
        solve(A, bad_b, TruncatedCG(5))
    with pytest.raises(pf.DataError, match=r"x0: .*NaN/Inf"):
        solve(A, b, TruncatedCG(5), x0=bad_b)
    bad_kappa = np.ones(disc.n_kappa)
    bad_kappa[40] = np.inf
    with pytest.raises(pf.CoefficientError, match="kappa: 1 value"):
        system.solve(bad_kappa, np.ones(disc.n_dofs), TruncatedCG(5))
    with pytest.raises(pf.DataError, match="operator values"):
        solve(system.operator(jnp.asarray(bad_kappa)), b, TruncatedCG(5))
    solvers = (ConvergedCG(), TruncatedCG(5), TruncatedCG(5, gradient="implicit"))
    # the three solves in one program (one compile, not three)
    sols = jax.jit(lambda b: [solve(A, b, s) for s in solvers])(jnp.asarray(bad_b))
    for sol in sols:
        assert int(sol.status) == Status.NONFINITE


def test_converged_cg_out_of_iterations_says_so():
    disc = square()
    kappa, f = np.ones(disc.n_kappa), np.ones(disc.n_dofs)
    short = disc.system.solve(kappa, f, ConvergedCG(rtol=1e-12, max_iterations=2))
    assert int(short.status) == Status.NOT_CONVERGED
    assert int(disc.system.solve(kappa, f, ConvergedCG(rtol=1e-12)).status) == Status.SUCCESS
    # a truncated solve stops at K by design: that is success
    assert int(disc.system.solve(kappa, f, TruncatedCG(2)).status) == Status.SUCCESS


# ------------------------------------------------------------------------------------------
# pure Neumann: nullspace handled, unbalanced data refused
# ------------------------------------------------------------------------------------------


def neumann_problem(n=12):
    disc = pf.discretize(pf.unit_square(n), dirichlet=None)
    f = disc.balance_source(disc.interpolate(lambda x: np.cos(np.pi * x[0]) + x[1] ** 2))
    return disc, np.ones(disc.n_kappa), f


def test_balance_source_makes_the_discrete_data_sum_to_zero():
    disc, kappa, f = neumann_problem()
    b = disc.rhs(kappa, f)
    assert abs(b.sum()) < 1e-14 * np.abs(b).sum()
    assert disc.nullspace is not None and square().nullspace is None


@pytest.mark.parametrize("mode", MODES)
def test_pure_neumann_matches_the_bordered_direct_solve(mode):
    disc, kappa, f = neumann_problem()
    reference = pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f),
                                nullspace=disc.nullspace).x
    sol = disc.system.solve(kappa, f, TruncatedCG(10 * disc.n_free, gradient=mode))
    assert int(sol.status) == Status.SUCCESS
    np.testing.assert_allclose(sol.x, reference, atol=1e-11 * abs(reference).max())
    assert abs(np.sum(sol.x)) < 1e-10 * abs(reference).max()  # the mean-free solution


@pytest.mark.parametrize("scale", [1e-170, 1e200])
def test_pure_neumann_data_of_extreme_scale_is_compatible(scale):
    """The compatibility test compares v.b with ||b||: at 1e-170 b.b underflowed to 0, and
    every balanced b was refused as incompatible; at 1e200 it overflowed."""
    disc, kappa, f = neumann_problem()
    A, b = disc.stiffness_matrix(kappa), disc.rhs(kappa, f)
    reference = pf.direct_solve(A, b, nullspace=disc.nullspace).x
    sol = solve(pf.SparseMatrix.from_scipy(A), b * scale, ConvergedCG(rtol=1e-12),
                nullspace=disc.nullspace)
    assert int(sol.status) == Status.SUCCESS
    np.testing.assert_allclose(sol.x / scale, reference, atol=1e-10 * abs(reference).max())


def test_l2_projection_of_data_of_extreme_scale_scales_exactly():
    """The projection's host CG (mass matrix) runs on data scaled by a power of two: at
    2^-600 (1e-181) r.r underflowed to 0 and the projection returned 0; at 2^600, inf."""
    disc = square(8)

    def field(x):
        return np.sin(np.pi * x[0]) * np.cos(x[1]) + 0.3

    reference = disc.project(field)
    for scale in (2.0 ** -600, 2.0 ** 600):
        np.testing.assert_array_equal(disc.project(lambda x, s=scale: s * field(x)) / scale,
                                      reference)


def test_pure_neumann_converges_to_the_manufactured_solution():
    """u = cos(pi x) cos(pi y) / (2 pi^2) solves -lap u = cos cos with du/dn = 0: rate 2."""
    errors = []
    # 8 -> 16 measures 1.94 (16 -> 32: 1.98): the asymptotic rate already, one compile of a
    # 1089-dof solve fewer
    for n in (8, 16):
        disc = pf.discretize(pf.unit_square(n), dirichlet=None)
        f = disc.balance_source(disc.interpolate(
            lambda x: np.cos(np.pi * x[0]) * np.cos(np.pi * x[1])))
        u = disc.system.solve(np.ones(disc.n_kappa), f, ConvergedCG(rtol=1e-12)).x
        errors.append(pf.fem.l2_error(disc, np.asarray(u), lambda x: np.cos(np.pi * x[0])
                                  * np.cos(np.pi * x[1]) / (2 * np.pi ** 2)))
    rates = np.log2(np.array(errors[:-1]) / errors[1:])
    assert rates[-1] == pytest.approx(2.0, abs=0.1)


@pytest.mark.parametrize("mode", SLOW_UNROLLED)
def test_pure_neumann_gradient_passes_taylor_test(mode):
    disc, _, f = neumann_problem(6)
    solver = TruncatedCG(10 * disc.n_free, gradient=mode)
    weights = jnp.asarray(np.random.default_rng(0).standard_normal(disc.n_free))

    def loss(log_kappa):
        x = disc.system.solve(jnp.exp(log_kappa), f, solver).x
        return jnp.vdot(weights, x) + 0.5 * jnp.sum(x ** 2)

    # the values and the gradient from one program: one compile, not op by op
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    zero = jnp.zeros(disc.n_kappa)
    result = pf.taylor_test(lambda k: value_and_grad(k)[0], zero,
                            gradient=value_and_grad(zero)[1])
    assert result.passed(), result.rates


def test_unbalanced_neumann_data_are_refused_and_flagged():
    disc, kappa, f = neumann_problem()
    with pytest.raises(pf.errors.IncompatibleDataError, match="balance_source"):
        disc.system.solve(kappa, f + 1.0, TruncatedCG(10))
    sol = jax.jit(lambda f: disc.system.solve(kappa, f, ConvergedCG()))(jnp.asarray(f + 1.0))
    assert int(sol.status) == Status.INCOMPATIBLE
    assert np.isfinite(sol.x).all()


def test_disconnected_meshes_need_dirichlet_data_on_every_part():
    left = pf.unit_square(2)
    points = np.vstack([left.p.T, left.p.T + np.array([2.0, 0.0])])
    cells = np.vstack([left.t.T, left.t.T + left.p.shape[1]])
    mesh = pf.mesh_from_arrays(points, cells, "triangle")
    with pytest.raises(pf.errors.DiscretizationError, match="2 disconnected parts"):
        pf.discretize(mesh, dirichlet=None)
    pinned_left = mesh.with_boundaries({"left": lambda x: np.abs(x[0]) < 1e-12})
    with pytest.raises(pf.errors.DiscretizationError, match="1 of the mesh's 2 disconnected parts"):
        pf.discretize(pinned_left, dirichlet={"left": 0.0})


# ------------------------------------------------------------------------------------------
# tensor coefficient
# ------------------------------------------------------------------------------------------


def test_isotropic_tensor_equals_the_scalar_coefficient():
    for space in ("P0", "P1"):
        scalar = square(kappa_space=space)
        tensor = square(kappa_space=space, kappa_kind="tensor")
        k = scalar.interpolate_kappa(lambda x: 1.0 + x[0] ** 2)
        kt = tensor.interpolate_kappa(
            lambda x: np.eye(2)[:, :, None] * (1.0 + x[0] ** 2))
        assert tensor.n_kappa == 3 * scalar.n_kappa
        diff = scalar.stiffness_matrix(k) - tensor.stiffness_matrix(kt)
        assert abs(diff).max() < 1e-14


def test_full_tensor_converges_at_rate_two():
    """K = [[a, c], [c, b]], u = sin(pi x) sin(pi y): f = pi^2 (a + b) u - 2 c pi^2 cos cos."""
    a, b, c = 2.0, 0.5, 0.7
    tensor = np.array([[a, c], [c, b]])

    def exact(x):
        return np.sin(np.pi * x[0]) * np.sin(np.pi * x[1])

    def source(x):
        return (np.pi ** 2 * (a + b) * exact(x)
                - 2 * c * np.pi ** 2 * np.cos(np.pi * x[0]) * np.cos(np.pi * x[1]))

    errors = []
    for n in (8, 16, 32):
        disc = square(n, kappa_kind="tensor")
        kappa = disc.interpolate_kappa(lambda x: tensor)
        u = pf.direct_solve(disc.stiffness_matrix(kappa),
                            disc.load_vector(source) + disc.rhs(kappa)).x
        errors.append(pf.fem.l2_error(disc, disc.expand(u), exact))
    rates = np.log2(np.array(errors[:-1]) / errors[1:])
    assert rates[-1] == pytest.approx(2.0, abs=0.1)
    assert errors[-1] < 2e-3


@pytest.mark.parametrize("mode", SLOW_UNROLLED)
def test_gradient_with_respect_to_tensor_components_passes_taylor_test(mode):
    disc = square(6, kappa_kind="tensor")
    kappa = jnp.asarray(disc.interpolate_kappa(lambda x: np.array([[1.0, 0.3], [0.3, 0.5]])))
    f = jnp.ones(disc.n_dofs)
    solver = TruncatedCG(10 * disc.n_free, gradient=mode)
    # the values and the gradient from one program: one compile, not op by op
    value_and_grad = jax.jit(jax.value_and_grad(
        lambda k: jnp.sum(disc.system.solve(k, f, solver).x ** 2)))
    result = pf.taylor_test(lambda k: value_and_grad(k)[0], kappa,
                            gradient=value_and_grad(kappa)[1])
    assert result.passed(), result.rates


def test_tensor_coefficients_are_checked():
    disc = square(4, kappa_kind="tensor")
    n = disc.kappa_basis.N
    indefinite = np.concatenate([np.ones(n), np.ones(n), 2.0 * np.ones(n)])  # c^2 > ab
    with pytest.raises(pf.CoefficientError, match=r"not positive definite.*smallest eigenvalue"):
        disc.stiffness_matrix(indefinite)
    with pytest.raises(pf.CoefficientError, match="a single number for a tensor"):
        disc.stiffness_matrix(1.0)
    with pytest.raises(pf.ShapeError, match=f"expected a vector of {3 * n} values"):
        disc.stiffness_matrix(np.ones(n))
    with pytest.raises(pf.CoefficientError, match="not symmetric"):
        disc.interpolate_kappa(lambda x: np.array([[1.0, 0.1], [0.2, 1.0]]))
    with pytest.raises(pf.errors.DiscretizationError, match="kappa_kind='matrix'"):
        pf.discretize(pf.unit_square(2), kappa_kind="matrix")


def test_scalar_coefficients_are_checked():
    disc = square(4)
    for bad, message in ((0.0, r"<= 0 \(first: index 0, value 0.0\)"),
                         (-1.0, "<= 0"), (np.nan, "NaN/Inf")):
        with pytest.raises(pf.CoefficientError, match=message):
            disc.stiffness_matrix(np.full(disc.n_kappa, bad))


# ------------------------------------------------------------------------------------------
# condition estimates from CG's Lanczos coefficients
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("preconditioner", ["identity", "jacobi"])
def test_condition_estimate_matches_dense_eigenvalues(preconditioner):
    disc = square(10)
    rng = np.random.default_rng(1)
    kappa = np.exp(3.0 * rng.standard_normal(disc.n_kappa))
    A = disc.stiffness_matrix(kappa)
    dense = A.toarray()
    if preconditioner == "jacobi":
        scale = 1.0 / np.sqrt(np.diag(dense))
        dense = scale[:, None] * dense * scale[None, :]
    eigenvalues = np.linalg.eigvalsh(dense)
    estimate = condition_estimate(A, preconditioner=preconditioner)
    assert estimate.condition == pytest.approx(eigenvalues[-1] / eigenvalues[0], rel=1e-6)
    assert estimate.largest == pytest.approx(eigenvalues[-1], rel=1e-8)


def test_condition_estimate_on_the_complement_of_a_nullspace():
    disc, kappa, _ = neumann_problem(8)
    A = disc.stiffness_matrix(kappa)
    eigenvalues = np.linalg.eigvalsh(A.toarray())  # eigenvalue 0 first: the constants
    estimate = condition_estimate(A, preconditioner="identity", nullspace=disc.nullspace)
    assert estimate.condition == pytest.approx(eigenvalues[-1] / eigenvalues[1], rel=1e-6)
    singular = condition_estimate(A, preconditioner="identity")
    assert singular.condition > 1e6 * estimate.condition or not np.isfinite(singular.condition)


def test_direct_solve_with_nullspace_is_orthogonal_to_it():
    A = sp.csr_matrix(np.array([[1.0, -1.0], [-1.0, 1.0]]))
    x = pf.direct_solve(A, np.array([1.0, -1.0]), nullspace=np.ones(2)).x
    np.testing.assert_allclose(x, [0.5, -0.5], atol=1e-15)


# ------------------------------------------------------------------------------------------
# extreme meshes and scales: generators and a solve on each
# ------------------------------------------------------------------------------------------


def test_geometric_spacing_and_tensor_mesh():
    x = pf.mesh.geometric_spacing(20, 1e3)
    h = np.diff(x)
    assert h.max() / h.min() == pytest.approx(1e3)
    assert x[0] == 0.0 and x[-1] == pytest.approx(1.0)
    mesh = pf.mesh.tensor_mesh(x * 1e6, np.linspace(0.0, 1.0, 5))
    assert len(mesh.boundaries["left"]) == 4 and len(mesh.boundaries["top"]) == 20
    with pytest.raises(pf.errors.DiscretizationError, match="strictly increasing"):
        pf.mesh.tensor_mesh(np.array([0.0, 1.0, 1.0]), np.linspace(0, 1, 3))


@pytest.mark.parametrize("length", [1e-6, 1e6])
def test_scaled_domains_keep_the_solution_scaling_as_length_squared(length):
    """-lap u = 1 on [0, L]^2: u(L x) = L^2 u_1(x), to round-off, in both modes."""
    unit = pf.discretize(pf.unit_square(8))
    u_unit = np.asarray(unit.system.solve(np.ones(unit.n_kappa), np.ones(unit.n_dofs),
                                          ConvergedCG()).x)
    scaled = pf.discretize(pf.mesh.tensor_mesh(*[np.linspace(0.0, length, 9)] * 2))
    for mode in MODES:
        u = scaled.system.solve(np.ones(scaled.n_kappa), np.ones(scaled.n_dofs),
                                TruncatedCG(10 * scaled.n_free, gradient=mode)).x
        np.testing.assert_allclose(np.asarray(u) / length ** 2, u_unit, rtol=1e-10)


@pytest.mark.parametrize("preconditioner", [pytest.param("identity", marks=pytest.mark.slow),
                                            "jacobi"])
def test_unrolled_gradient_far_past_convergence_is_the_exact_one(preconditioner):
    """Frozen at round-off, the K-iteration map is the solution map: its gradient (and JVP)
    must be the exact one, not the lagging derivative of the last Krylov iterate (~1e-2 off)."""
    disc = square(6)
    f = disc.interpolate(lambda x: np.cos(np.pi * x[0]) + x[1] ** 2)
    weights = jnp.asarray(np.random.default_rng(0).standard_normal(disc.n_free))

    def loss(log_kappa, solver):
        return jnp.vdot(weights, disc.system.solve(jnp.exp(log_kappa), f, solver).x)

    zero = jnp.zeros(disc.n_kappa)
    exact_solver = ConvergedCG(rtol=1e-14, preconditioner=preconditioner)
    unrolled = TruncatedCG(10 * disc.n_free, preconditioner)

    # second order: the derivative of the implicit tangent sees the implicit tangent of x
    def hessian_vector(solver, d):
        squared = lambda z: loss(z, solver) ** 2  # noqa: E731 (a loss with curvature in x)
        return jax.jvp(jax.grad(squared), (zero,), (d,))[1]

    # every derivative in one program (op by op they compiled some 150 small ones, jitted
    # apart five)
    @jax.jit
    def derivatives(d):
        return (jax.grad(loss)(zero, exact_solver), jax.grad(loss)(zero, unrolled),
                jax.jvp(lambda z: loss(z, unrolled), (zero,), (d,))[1],
                hessian_vector(exact_solver, d), hessian_vector(unrolled, d))

    direction = jnp.asarray(np.random.default_rng(1).standard_normal(disc.n_kappa))
    exact, gradient, tangent, reference, second = derivatives(direction)
    np.testing.assert_allclose(gradient, exact, rtol=1e-8, atol=1e-10 * abs(exact).max())
    assert float(tangent) == pytest.approx(float(jnp.vdot(exact, direction)), rel=1e-8)
    np.testing.assert_allclose(second, reference, rtol=1e-7, atol=1e-9 * abs(reference).max())


def test_a_frozen_unrolled_solve_runs_no_second_solve():
    """Frozen before K, the unrolled solve returns the scan's iterate, differentiated as the
    solution map: its forward program holds no loop but the scan, and its gradient one loop
    more (the adjoint solve) than the scan's two sweeps. Solving again in the forward sweep
    compiled a second PCG loop into every unrolled step (0.6 s of a 2 s gradient compile on
    the inclusion scene)."""
    disc = square(6)
    f = jnp.asarray(disc.interpolate(lambda x: 1.0 + x[0]))
    solver = TruncatedCG(10 * disc.n_free, "jacobi")

    def x(log_kappa):
        return disc.system.solve(jnp.exp(log_kappa), f, solver).x

    def loops(fn) -> int:  # in the lowered program: what XLA compiles
        return jax.jit(fn).lower(zero).as_text().count("stablehlo.while")

    zero = jnp.zeros(disc.n_kappa)
    assert loops(x) == 1
    assert loops(jax.grad(lambda z: jnp.sum(x(z)))) == 3
    reference = disc.system.solve(jnp.ones(disc.n_kappa), f, ConvergedCG(rtol=1e-14)).x
    np.testing.assert_allclose(x(zero), reference, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("mode", SLOW_UNROLLED)
def test_float32_solves_run_in_float32_to_its_stated_accuracy(mode):
    disc = square(12)
    kappa, f = jnp.ones(disc.n_kappa), jnp.ones(disc.n_dofs)
    reference = pf.direct_solve(disc.stiffness_matrix(np.ones(disc.n_kappa)),
                                disc.rhs(np.ones(disc.n_kappa), np.ones(disc.n_dofs))).x
    A = disc.system.operator(kappa).astype(jnp.float32)
    sol = solve(A, disc.system.rhs(kappa, f), TruncatedCG(10 * disc.n_free, gradient=mode))
    assert sol.x.dtype == jnp.float32 and int(sol.status) == Status.SUCCESS
    error = np.linalg.norm(np.asarray(sol.x, float) - reference) / np.linalg.norm(reference)
    cond = condition_estimate(disc.stiffness_matrix(np.ones(disc.n_kappa))).condition
    assert 1e-9 < error < 10 * cond * np.finfo(np.float32).eps  # float32, not float64, digits

    def loss(k):
        x = solve(disc.system.operator(k).astype(jnp.float32), disc.system.rhs(k, f),
                  TruncatedCG(10 * disc.n_free, gradient=mode)).x
        return jnp.sum(x.astype(jnp.float64) ** 2)

    # the gradients jitted, in one program (the solve above is the eager one)
    gradient, exact = jax.jit(lambda k: (jax.grad(loss)(k), jax.grad(
        lambda k: jnp.sum(disc.system.solve(k, f, ConvergedCG()).x ** 2))(k)))(kappa)
    assert np.isfinite(gradient).all()
    np.testing.assert_allclose(gradient, exact, rtol=1e-3, atol=1e-4 * abs(exact).max())


def test_interpolation_of_non_finite_functions_is_refused():
    disc = square(4)
    with np.errstate(divide="ignore", invalid="ignore"), \
            pytest.raises(pf.DataError, match=r"interpolate: fn\(x\).*NaN/Inf"):
        disc.interpolate(lambda x: np.log(x[0]))  # log 0 = -inf on the left side
    with np.errstate(invalid="ignore"), pytest.raises(pf.CoefficientError,
                                                      match="interpolate_kappa"):
        disc.interpolate_kappa(lambda x: np.sqrt(x[0] - 0.5))
    with pytest.raises(pf.DataError, match="project"):
        disc.project(lambda x: np.nan * x[0])
    with pytest.raises(pf.ShapeError, match="nullspace"):
        solve(disc.system.operator(jnp.ones(disc.n_kappa)), np.ones(disc.n_free),
              TruncatedCG(2), nullspace=np.ones(3))
