"""Truncated (damped) Jacobi sweeps: the converged value against SciPy, the unrolled derivative
against the K-sweep map's own (written out in NumPy), the implicit one against the truncated
adjoint formula, Taylor remainders, traced counts, and the statuses of bad sweeps."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spl

import prdp_fem as pf
from prdp_fem.errors import DataError, SolverBreakdownError, SolverConfigError
from prdp_fem.linalg import SparseMatrix, Status, TruncatedJacobi, solve

N = 12


def laplacian(n=N, shift=0.0):
    return sp.diags([-np.ones(n - 1), (2.0 + shift) * np.ones(n), -np.ones(n - 1)],
                    [-1, 0, 1]).tocsr()


def nonsymmetric(n=N):
    """Diagonally dominant, not symmetric (advection-like off-diagonals)."""
    return sp.diags([-1.3 * np.ones(n - 1), 3.0 + np.linspace(0, 1, n), -0.6 * np.ones(n - 1)],
                    [-1, 0, 1]).tocsr()


def with_values(matrix: SparseMatrix, values) -> SparseMatrix:
    return SparseMatrix(matrix.rows, matrix.cols, values, matrix.shape, matrix.layout,
                        matrix.kernel)


def rhs(n=N):
    return np.sin(1.0 + np.arange(n)) + 0.5


def sweep_map(M, K, omega=1.0):
    """``(S, T)`` with ``x_K = S b + T x0`` for ``K`` sweeps, by the textbook recursion."""
    dense = M.toarray()
    step = omega / np.diag(dense)
    G = np.eye(len(dense)) - step[:, None] * dense
    S, T = np.zeros_like(dense), np.eye(len(dense))
    for _ in range(K):
        S = G @ S + np.diag(step)
        T = G @ T
    return S, T


# ------------------------------------------------------------------------------------------
# forward
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("gradient", ["unrolled", "implicit"])
@pytest.mark.parametrize("kind", ["symmetric", "nonsymmetric"])
def test_converged_sweeps_match_spsolve(gradient, kind):
    M = laplacian(shift=0.3) if kind == "symmetric" else nonsymmetric()
    x0 = np.linspace(-1.0, 2.0, N)
    sol = solve(SparseMatrix.from_scipy(M), rhs(), TruncatedJacobi(
        300, omega=0.9, gradient=gradient), x0=x0)
    np.testing.assert_allclose(sol.x, spl.spsolve(M.tocsc(), rhs()), rtol=0, atol=1e-12)
    assert Status(int(sol.status)) == Status.SUCCESS and int(sol.iterations) == 300
    np.testing.assert_allclose(float(sol.residual_norm), np.linalg.norm(rhs() - M @ sol.x),
                               rtol=1e-6, atol=1e-15)
    np.testing.assert_allclose(float(sol.initial_residual_norm),
                               np.linalg.norm(rhs() - M @ x0), rtol=1e-14)


@pytest.mark.parametrize("gradient", ["unrolled", "implicit"])
def test_truncated_sweeps_are_the_k_sweep_map(gradient):
    M = nonsymmetric()
    x0 = np.cos(np.arange(N))
    S, T = sweep_map(M, 7, omega=0.8)
    sol = solve(SparseMatrix.from_scipy(M), rhs(), TruncatedJacobi(7, omega=0.8,
                                                                   gradient=gradient), x0=x0)
    np.testing.assert_allclose(sol.x, S @ rhs() + T @ x0, rtol=1e-13, atol=1e-14)
    # K = 0 returns x0
    zero = solve(SparseMatrix.from_scipy(M), rhs(), TruncatedJacobi(0, gradient=gradient), x0=x0)
    np.testing.assert_array_equal(zero.x, x0)


def test_undamped_sweep_is_the_splitting_form():
    """omega = 1: x <- D^{-1} (b - (L + U) x), the reference code's update, to round-off."""
    M = laplacian()
    dense = M.toarray()
    off, d = dense - np.diag(np.diag(dense)), np.diag(dense)
    x = np.zeros(N)
    for _ in range(40):
        x = (rhs() - off @ x) / d
    sol = solve(SparseMatrix.from_scipy(M), rhs(), TruncatedJacobi(40))
    np.testing.assert_allclose(sol.x, x, rtol=1e-13)
    # the history is ||b - A x_k|| for k = 0..K
    assert sol.residual_history.shape == (41,)
    np.testing.assert_allclose(sol.residual_history[0], np.linalg.norm(rhs()), rtol=1e-14)
    np.testing.assert_allclose(sol.residual_history[-1], float(sol.residual_norm), rtol=1e-14)


# ------------------------------------------------------------------------------------------
# derivatives
# ------------------------------------------------------------------------------------------


def test_unrolled_derivative_is_that_of_the_k_sweep_map():
    M = nonsymmetric()
    A = SparseMatrix.from_scipy(M)
    x0 = np.cos(np.arange(N))
    S, T = sweep_map(M, 9, omega=0.7)
    solver = TruncatedJacobi(9, omega=0.7)
    # the derivatives jitted: one program each (op by op, some 90 small ones)
    jac_b = jax.jit(jax.jacrev(lambda b: solve(A, b, solver, x0=x0).x))(jnp.asarray(rhs()))
    jac_x0 = jax.jit(jax.jacfwd(lambda x: solve(A, rhs(), solver, x0=x).x))(jnp.asarray(x0))
    np.testing.assert_allclose(jac_b, S, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(jac_x0, T, rtol=1e-12, atol=1e-15)

    # in the operator's values (the diagonal included): the map's own derivative, by a
    # central difference of the NumPy map
    def numpy_map(values):
        matrix = sp.csr_matrix((values, (np.asarray(A.rows), np.asarray(A.cols))), M.shape)
        S, T = sweep_map(matrix, 9, omega=0.7)
        return S @ rhs() + T @ x0

    direction = np.sin(np.arange(A.values.shape[0]) * 0.7)
    h = 1e-6
    expected = (numpy_map(np.asarray(A.values) + h * direction)
                - numpy_map(np.asarray(A.values) - h * direction)) / (2 * h)
    _, got = jax.jit(lambda d: jax.jvp(lambda v: solve(with_values(A, v), rhs(), solver,
                                                       x0=x0).x, (A.values,), (d,)))(
        jnp.asarray(direction))
    np.testing.assert_allclose(got, expected, rtol=1e-7, atol=1e-9)


def test_implicit_gradient_is_the_truncated_adjoint_formula():
    """b_bar = lambda, values_bar[k] = -lambda[row_k] x[col_k], with lambda = K_adj sweeps on
    A^T c from zero: not the K-sweep map's derivative (K_adj != K, a non-zero x0)."""
    M = nonsymmetric()
    A = SparseMatrix.from_scipy(M)
    x0 = np.cos(np.arange(N))
    c = np.linspace(1.0, -1.0, N)
    solver = TruncatedJacobi(6, omega=0.9, gradient="implicit", adjoint_iterations=4)

    def loss(values, b):
        return jnp.vdot(c, solve(with_values(A, values), b, solver, x0=x0).x)

    # the derivatives jitted: one program each (op by op, some 80 small ones)
    g_values, g_b = jax.jit(jax.grad(loss, argnums=(0, 1)))(A.values, jnp.asarray(rhs()))
    S, T = sweep_map(M, 6, omega=0.9)
    x = S @ rhs() + T @ x0
    S_adj, _ = sweep_map(M.T.tocsr(), 4, omega=0.9)
    lam = S_adj @ c
    np.testing.assert_allclose(g_b, lam, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(g_values, -lam[np.asarray(A.rows)] * x[np.asarray(A.cols)],
                               rtol=1e-12, atol=1e-15)
    # forward mode: the tangent system db - dA x by K_adj sweeps on A
    db, dv = np.sin(np.arange(N)), np.cos(np.arange(A.values.shape[0]))
    _, tangent = jax.jit(lambda dv, db: jax.jvp(
        lambda v, b: solve(with_values(A, v), b, solver, x0=x0).x,
        (A.values, jnp.asarray(rhs())), (dv, db)))(jnp.asarray(dv), jnp.asarray(db))
    dA = sp.csr_matrix((dv, (np.asarray(A.rows), np.asarray(A.cols))), M.shape)
    S4, _ = sweep_map(M, 4, omega=0.9)
    np.testing.assert_allclose(tangent, S4 @ (db - dA @ x), rtol=1e-12, atol=1e-14)
    # x0 gets no derivative in implicit mode
    g_x0 = jax.jit(jax.grad(lambda x: jnp.vdot(c, solve(A, rhs(), solver, x0=x).x)))(
        jnp.asarray(x0))
    np.testing.assert_array_equal(g_x0, 0.0)


def test_symmetric_implicit_and_unrolled_agree_from_zero():
    """The reference's setting: A symmetric, x0 = 0, K_adj = K: the same derivative in b."""
    A = SparseMatrix.from_scipy(laplacian())
    c = np.linspace(1.0, -1.0, N)
    # jitted: one program each (op by op, some 75 small ones)
    grads = [jax.jit(jax.grad(lambda b, g=g: jnp.vdot(c, solve(A, b, TruncatedJacobi(
        25, gradient=g)).x)))(jnp.asarray(rhs())) for g in ("unrolled", "implicit")]
    np.testing.assert_allclose(grads[0], grads[1], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("gradient,K", [("unrolled", 8), ("implicit", 600)])
def test_taylor_remainders_are_second_order(gradient, K):
    """Unrolled at K = 8: the gradient of the truncated loss. Implicit at K = 600 (converged):
    the gradient of the solution map's loss. Along values and b together."""
    M = laplacian(shift=0.2)
    A = SparseMatrix.from_scipy(M)
    target = np.linspace(0.0, 1.0, N)
    solver = TruncatedJacobi(K, gradient=gradient)

    def loss(params):
        x = solve(with_values(A, params[0]), params[1], solver).x
        return 0.5 * jnp.sum((x - target) ** 2) + jnp.sum(x ** 3) / 3.0

    params = (A.values, jnp.asarray(rhs()))
    direction = (jnp.asarray(np.cos(np.arange(A.values.shape[0]))) * 0.1,
                 jnp.asarray(np.sin(np.arange(N))))
    # jitted: a program for the loss and one for its gradient (op by op, some 40 small ones)
    loss = jax.jit(loss)
    result = pf.taylor_test(loss, params, direction, gradient=jax.jit(jax.grad(loss))(params),
                            h0=1e-2, n_steps=5)
    assert result.passed(), result.rates
    np.testing.assert_allclose(np.median(result.rates[np.isfinite(result.rates)]), 2.0, atol=0.1)


# ------------------------------------------------------------------------------------------
# traced counts, jit
# ------------------------------------------------------------------------------------------


def test_traced_counts_give_the_static_results():
    A = SparseMatrix.from_scipy(nonsymmetric())
    b = jnp.asarray(rhs())
    c = jnp.linspace(1.0, -1.0, N)

    @jax.jit
    def implicit(values, K, K_adj, omega):
        def loss(v):
            return jnp.vdot(c, solve(with_values(A, v), b, TruncatedJacobi(
                K, omega=omega, gradient="implicit", adjoint_iterations=K_adj)).x)
        return loss(values), jax.grad(loss)(values)

    @jax.jit
    def unrolled(values, K):
        def loss(v):
            return jnp.vdot(c, solve(with_values(A, v), b,
                                     TruncatedJacobi(K, scan_length=16)).x)
        return loss(values), jax.grad(loss)(values)

    for K in (3, 11):
        value, grad = implicit(A.values, K, K - 1, 0.75)
        static = TruncatedJacobi(K, omega=0.75, gradient="implicit", adjoint_iterations=K - 1)
        # the references jitted too: one program each (op by op, many small ones)
        expected = jax.jit(jax.grad(lambda v, s=static: jnp.vdot(c, solve(with_values(A, v), b,
                                                                           s).x)))
        np.testing.assert_allclose(grad, expected(A.values), rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(value, jnp.vdot(c, solve(A, b, static).x), rtol=1e-13)
        value, grad = unrolled(A.values, K)
        expected = jax.jit(jax.grad(lambda v, K=K: jnp.vdot(c, solve(with_values(A, v), b,
                                                                     TruncatedJacobi(K)).x)))
        np.testing.assert_allclose(grad, expected(A.values), rtol=1e-12, atol=1e-15)
        sol = solve(A, b, TruncatedJacobi(K, scan_length=16))
        assert int(sol.iterations) == K and sol.residual_history.shape == (17,)


# ------------------------------------------------------------------------------------------
# bad sweeps and bad options
# ------------------------------------------------------------------------------------------


def _dense(matrix):
    return SparseMatrix.from_scipy(sp.csr_matrix(matrix))


def test_divergent_sweep_gets_a_status_and_stays_finite():
    """rho(G) = 1.8 on a positive definite matrix far from diagonal dominance."""
    A = _dense(np.full((3, 3), 0.9) + 0.1 * np.eye(3))

    @jax.jit
    def run(values, b):
        sol = solve(with_values(A, values), b, TruncatedJacobi(500))
        grad = jax.grad(lambda v: jnp.sum(solve(with_values(A, v), b,
                                                TruncatedJacobi(500)).x))(values)
        implicit = solve(with_values(A, values), b, TruncatedJacobi(500, gradient="implicit"))
        return sol, grad, implicit

    sol, grad, implicit = run(A.values, jnp.ones(3))
    for s in (sol, implicit):
        assert Status(int(s.status)) == Status.DIVERGED
        assert np.all(np.isfinite(s.x)) and 0 < int(s.iterations) < 500
    assert np.all(np.isfinite(grad))
    with pytest.raises(SolverBreakdownError, match="spectral radius"):
        solve(A, np.ones(3), TruncatedJacobi(500))
    # omega small enough converges on the same matrix: rho(I - omega A) < 1 for omega < 2/2.8
    ok = solve(A, np.ones(3), TruncatedJacobi(400, omega=0.5))
    np.testing.assert_allclose(ok.x, np.linalg.solve(np.asarray(A.todense()), np.ones(3)),
                               rtol=1e-12)


def test_convergent_sweeps_are_never_flagged_from_an_exact_start():
    """Round-off around an exact x0 is not growth."""
    M = laplacian()
    x = spl.spsolve(M.tocsc(), rhs())
    sol = solve(SparseMatrix.from_scipy(M), rhs(), TruncatedJacobi(50), x0=x)
    assert Status(int(sol.status)) == Status.SUCCESS


def test_zero_diagonal_is_a_breakdown():
    A = _dense(np.array([[0.0, 1.0], [1.0, 2.0]]))
    sol = jax.jit(lambda v: solve(with_values(A, v), jnp.ones(2), TruncatedJacobi(5)))(A.values)
    assert Status(int(sol.status)) == Status.BREAKDOWN
    np.testing.assert_array_equal(sol.x, 0.0)
    with pytest.raises(SolverBreakdownError, match="diagonal"):
        solve(A, np.ones(2), TruncatedJacobi(5, gradient="implicit"))


def test_nonfinite_data_raises_eagerly_and_flags_under_jit():
    A = SparseMatrix.from_scipy(laplacian())
    b = rhs()
    b[3] = np.nan
    with pytest.raises(DataError, match="NaN"):
        solve(A, b, TruncatedJacobi(5))
    sol = jax.jit(lambda b: solve(A, b, TruncatedJacobi(5)))(b)
    assert Status(int(sol.status)) == Status.NONFINITE


@pytest.mark.parametrize("options,match", [
    (dict(iterations=3, omega=0.0), "omega"),
    (dict(iterations=3, omega=2.0), "omega"),
    (dict(iterations=3, omega=float("nan")), "omega"),
    (dict(iterations=-1), "iterations"),
    (dict(iterations=3, gradient="adjoint"), "gradient"),
    (dict(iterations=20, scan_length=16), "scan_length"),
    (dict(iterations=3, gradient="implicit", scan_length=16), "scan_length"),
])
def test_bad_options_are_refused(options, match):
    with pytest.raises(SolverConfigError, match=match):
        TruncatedJacobi(**options)


def test_traced_count_needs_a_scan_length_unrolled():
    with pytest.raises(SolverConfigError, match="scan_length"):
        jax.jit(lambda K: TruncatedJacobi(K).iterations)(3)


def test_no_nullspace():
    A = SparseMatrix.from_scipy(laplacian())
    with pytest.raises(SolverConfigError, match="nullspace"):
        solve(A, rhs(), TruncatedJacobi(3), nullspace=np.ones(N))


@pytest.mark.parametrize("gradient,adjoint", [("unrolled", 9), ("implicit", 4)])
def test_counter_tallies_sweeps(gradient, adjoint):
    A = SparseMatrix.from_scipy(laplacian())
    counter = pf.IterationCounter()
    solver = TruncatedJacobi(9, gradient=gradient,
                             adjoint_iterations=4 if gradient == "implicit" else None)
    # jitted: one program (op by op, some dozen small ones)
    jax.jit(jax.grad(lambda b: jnp.sum(solve(A, b, solver, counter=counter).x)))(
        jnp.asarray(rhs()))
    jax.effects_barrier()
    assert counter.snapshot() == (9, adjoint)


def test_bad_shapes():
    A = SparseMatrix.from_scipy(laplacian())
    with pytest.raises(pf.ShapeError):
        solve(A, np.ones(N + 1), TruncatedJacobi(3))


def test_exported():
    assert "TruncatedJacobi" in pf.__all__ and pf.TruncatedJacobi is TruncatedJacobi
    assert pf.linalg.jacobi_solve is pf.linalg.stationary.jacobi_solve
