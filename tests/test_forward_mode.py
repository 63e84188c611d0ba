"""Forward mode through the implicit solves: J v, its adjoint identity, and Hessian products."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prdp_fem as pf
from prdp_fem.fem import full_field, with_noise
from prdp_fem.inverse import inverse_problem
from prdp_fem.linalg import ConvergedCG, IterationCounter, TruncatedCG, solve


@pytest.fixture(scope="module")
def problem():
    """P1 state, P1 kappa, Dirichlet data on two sides, a source: (disc, kappa, f)."""
    disc = pf.discretize(pf.unit_square(8), element="P1", kappa_space="P1",
                         dirichlet={"left": 1.0, "right": 0.0})
    kappa = jnp.asarray(disc.interpolate_kappa(lambda x: 1.0 + 3 * x[0] * x[1]))
    f = jnp.asarray(disc.interpolate(lambda x: np.sin(2 * x[1])))
    return disc, kappa, f


def state_map(disc, solver, counter=None):
    """``(kappa, f) -> x`` through ``solve``."""
    system = disc.system

    def x_of(kappa, f):
        return solve(system.operator(kappa), system.rhs(kappa, f), solver, counter=counter).x

    return x_of


def directions(disc, seed=3):
    rng = np.random.default_rng(seed)
    return (jnp.asarray(rng.normal(size=disc.n_kappa)), jnp.asarray(rng.normal(size=disc.n_dofs)),
            jnp.asarray(rng.normal(size=disc.n_free)))


CONVERGED = {
    "converged": ConvergedCG(rtol=1e-13),
    "truncated K=10n": TruncatedCG(10 * 81, gradient="implicit"),
}


# truncated with the slow cases: the converged solve's tangent is the same rule's, and
# test_truncated_jvp_is_the_truncated_tangent_solve pins the truncated one to its solve
@pytest.mark.parametrize("name", [name if name == "converged" else
                                  pytest.param(name, marks=pytest.mark.slow)
                                  for name in CONVERGED])
def test_jvp_matches_central_differences(problem, name):
    disc, kappa, f = problem
    x_of = state_map(disc, CONVERGED[name])
    dkappa, df, _ = directions(disc)
    # jitted: one program for the tangent and one for the map (op by op, some 90 small ones)
    _, tangent = jax.jit(lambda *a: jax.jvp(x_of, a[:2], a[2:]))(kappa, f, dkappa, df)
    h = 1e-4  # central differences: O(h^2) ~ 1e-8 relative
    x_of = jax.jit(x_of)
    difference = (x_of(kappa + h * dkappa, f + h * df)
                  - x_of(kappa - h * dkappa, f - h * df)) / (2 * h)
    assert np.linalg.norm(tangent - difference) < 1e-7 * np.linalg.norm(difference)


# truncated with the slow cases: test_truncated_sweeps_are_adjoint_only_as_they_converge holds
# its K = K_adj = 10 n sweeps to the same identity
@pytest.mark.parametrize("name", [name if name == "converged" else
                                  pytest.param(name, marks=pytest.mark.slow)
                                  for name in CONVERGED])
def test_jvp_and_vjp_are_adjoint(problem, name):
    disc, kappa, f = problem
    x_of = state_map(disc, CONVERGED[name])
    dkappa, df, w = directions(disc)

    @jax.jit  # one program (op by op, the assembly's derivatives compiled some 110 small ones)
    def products(kappa, f, dkappa, df, w):
        _, tangent = jax.jvp(x_of, (kappa, f), (dkappa, df))
        kappa_bar, f_bar = jax.vjp(x_of, kappa, f)[1](w)
        return w @ tangent, kappa_bar @ dkappa + f_bar @ df

    forward, reverse = (float(v) for v in products(kappa, f, dkappa, df, w))
    assert forward == pytest.approx(reverse, rel=1e-10)


def test_truncated_jvp_is_the_truncated_tangent_solve(problem):
    """K = 5, K_adj = 7: J v is 7 PCG iterations on A dx = db - dA x_5, nothing else."""
    disc, kappa, f = problem
    system = disc.system
    dkappa, df, _ = directions(disc)
    counter = IterationCounter()
    solver = TruncatedCG(5, gradient="implicit", adjoint_iterations=7)
    x_of = state_map(disc, solver, counter)
    # jitted: one program each (op by op, the assembly's tangents compile many small ones)
    x, tangent = jax.jit(lambda *a: jax.jvp(x_of, a[:2], a[2:]))(kappa, f, dkappa, df)
    jax.effects_barrier()
    assert counter.snapshot() == (5, 7)  # the tangent solve is tallied as an adjoint one

    @jax.jit
    def tangent_solve(kappa, dkappa, df, x):
        # db - dA x: b and A are affine / linear in (kappa, f), so db = b(dkappa, df) - h
        rhs = system.rhs(dkappa, df) - system.neumann \
            - pf.linalg.matvec(system.operator(dkappa), x)
        return solve(system.operator(kappa), rhs, TruncatedCG(7, gradient="implicit")).x

    reference = tangent_solve(kappa, dkappa, df, x)
    np.testing.assert_allclose(tangent, reference, rtol=1e-12, atol=1e-12 * abs(reference).max())


def test_truncated_sweeps_are_adjoint_only_as_they_converge(problem):
    """A truncated CG sweep is not linear in its right-hand side: <J v, w> = <v, J^T w> holds
    to round-off only once K_adj converges, and the gap closes as K_adj grows."""
    disc, kappa, f = problem
    dkappa, df, w = directions(disc)

    @jax.jit  # K_adj traced: one program for the three counts
    def gap(k_adj):
        x_of = state_map(disc, TruncatedCG(10 * disc.n_free, gradient="implicit",
                                           adjoint_iterations=k_adj))
        _, tangent = jax.jvp(x_of, (kappa, f), (dkappa, df))
        kappa_bar, f_bar = jax.vjp(x_of, kappa, f)[1](w)
        forward, reverse = w @ tangent, kappa_bar @ dkappa + f_bar @ df
        return jnp.abs(forward - reverse) / jnp.abs(reverse)

    gaps = [float(gap(k_adj)) for k_adj in (3, 20, 10 * disc.n_free)]
    # measured 0.35, 2.3e-4, 3e-15 (63 free dofs)
    assert gaps[0] > 0.1 and 1e-5 < gaps[1] < 1e-3 and gaps[2] < 1e-12


def test_jvp_through_a_singular_system():
    """Pure Neumann (nullspace = constants): the tangent stays orthogonal to the constants."""
    disc = pf.discretize(pf.unit_square(8), element="P1", kappa_space="P1", dirichlet=None)
    system = disc.system
    kappa = jnp.asarray(disc.interpolate_kappa(lambda x: 1.0 + x[0]))
    f = jnp.asarray(disc.balance_source(disc.interpolate(lambda x: np.cos(np.pi * x[0]))))

    def x_of(kappa):
        return solve(system.operator(kappa), system.rhs(kappa, f), ConvergedCG(rtol=1e-13),
                     nullspace=system.nullspace).x

    dkappa, _, w = directions(disc)
    # jitted: one program each way (op by op, some 80 small ones)
    _, tangent = jax.jit(lambda k, d: jax.jvp(x_of, (k,), (d,)))(kappa, dkappa)
    assert abs(float(jnp.sum(tangent))) < 1e-10 * float(jnp.linalg.norm(tangent))
    reverse = float(jax.jit(lambda k, w: jax.vjp(x_of, k)[1](w)[0])(kappa, w) @ dkappa)
    assert float(w @ tangent) == pytest.approx(reverse, rel=1e-9)


def test_jvp_with_an_amg_preconditioner(problem):
    disc, kappa, f = problem
    amg = pf.amg_preconditioner(disc.system.operator(kappa), max_coarse=5)
    dkappa, df, _ = directions(disc)

    def tangent_of(solver):  # jitted: one program (op by op, the assembly's many small ones)
        return jax.jit(lambda *a: jax.jvp(state_map(disc, solver), a[:2], a[2:])[1])(
            kappa, f, dkappa, df)

    tangent = tangent_of(ConvergedCG(rtol=1e-13, preconditioner=amg))
    reference = tangent_of(ConvergedCG(rtol=1e-13))
    np.testing.assert_allclose(tangent, reference, rtol=1e-9, atol=1e-11)


# ------------------------------------------------------------------------------------------
# Hessian-vector products through InverseProblem.loss
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def log_kappa_problem():
    disc = pf.discretize(pf.unit_square(6), element="P2", kappa_space="P1", dirichlet=0.0)
    m_true = disc.interpolate_kappa(lambda x: np.log(2.0 + x[0] * x[1]))
    f = np.ones(disc.n_dofs)
    kappa = np.exp(m_true)
    u = disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f)).x)
    data = with_noise(full_field(disc, u_true=u), 0.02, 0)
    problem = inverse_problem(disc, data, unknown="log_kappa", alpha=1e-4, known=f)
    return disc, problem


# converged with the slow cases: K = 400 is converged here too, through the same jvp rule
@pytest.mark.parametrize("solver", [pytest.param(ConvergedCG(rtol=1e-13), marks=pytest.mark.slow),
                                    TruncatedCG(400, gradient="implicit")],
                         ids=["converged", "truncated"])
def test_hessian_vector_product_passes_the_taylor_test(log_kappa_problem, solver):
    """grad J(z + h v) - grad J(z) - h H v = O(h^2): the remainder falls 4x per halving."""
    disc, problem = log_kappa_problem
    z = jnp.asarray(disc.interpolate_kappa(lambda x: 0.5 + 0.3 * x[0]))
    grad = jax.grad(lambda z: problem.loss(z, solver)[0])
    # (grad J(z), H v): one program serves the products and the gradients below
    hvp = jax.jit(lambda z, v: jax.jvp(grad, (z,), (v,)))
    rng = np.random.default_rng(0)
    v, w = (jnp.asarray(rng.normal(size=z.shape)) for _ in range(2))
    (_, Hv), (_, Hw) = hvp(z, v), hvp(z, w)
    # symmetric (forward over reverse through the tangent and second-order adjoint solves)
    assert float(w @ Hv) == pytest.approx(float(v @ Hw), rel=1e-9)
    # the Taylor test of z -> <grad J(z), w>, whose gradient is H w
    result = pf.taylor_test(lambda z: hvp(z, w)[0] @ w, z, v, gradient=Hw, h0=1e-1, n_steps=5)
    assert result.passed(), result.rates
    assert np.all(np.abs(result.rates - 2.0) < 0.2), result.rates


def test_unrolled_solves_with_a_counter_take_jvp_and_count_only_the_backward_sweep(problem):
    disc, kappa, f = problem
    counter = IterationCounter()
    x_of = state_map(disc, TruncatedCG(6), counter)
    dkappa, df, w = directions(disc)
    _, tangent = jax.jit(lambda *a: jax.jvp(x_of, a[:2], a[2:]))(kappa, f, dkappa, df)
    assert counter.snapshot() == (6, 0)  # forward mode runs along the scan: no extra sweep
    kappa_bar, f_bar = jax.jit(lambda k, f, w: jax.vjp(x_of, k, f)[1](w))(kappa, f, w)
    assert counter.snapshot() == (12, 6)  # the reversed scan is tallied once
    # the unrolled map is differentiated exactly both ways: the adjoint identity holds
    assert float(w @ tangent) == pytest.approx(float(kappa_bar @ dkappa + f_bar @ df),
                                               rel=1e-12)
