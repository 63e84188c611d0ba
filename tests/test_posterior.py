"""Gaussian priors and the Laplace posterior, against dense computations of the same posterior."""

import jax
import jax.numpy as jnp
import meshio
import numpy as np
import pytest

import prdp_fem as pf
from prdp_fem.errors import SolverConfigError
from prdp_fem.fem import bilaplacian_prior, full_field, with_noise
from prdp_fem.inverse import converged, inverse_problem, laplace_posterior

SIGMA2 = 1e-4


@pytest.fixture(scope="module")
def setting():
    """``(disc, prior, problem, z, dense_posterior_covariance)`` on a 6 x 6 square (49
    parameters); ``z`` is a point near the truth (the identity holds at any point)."""
    disc = pf.discretize(pf.unit_square(6), element="P1", kappa_space="P1", dirichlet=0.0)
    m_true = disc.interpolate_kappa(lambda x: 0.5 * np.sin(np.pi * x[0]) * x[1])
    f = np.ones(disc.n_dofs)
    kappa = np.exp(m_true)
    u = disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f)).x)
    data = with_noise(full_field(disc, u_true=u), 0.01, seed=3)
    prior = bilaplacian_prior(disc, "log_kappa", gamma=0.05, delta=0.5, mean=0.1)
    problem = inverse_problem(disc, data, unknown="log_kappa", alpha=SIGMA2,
                              regularization=prior.regularizer(), known=f, truth=m_true)
    z = jnp.asarray(0.9 * m_true + 0.02)
    return disc, prior, problem, z, _dense_posterior(problem, prior, z)


def _dense_posterior(problem, prior, z) -> np.ndarray:
    """``(J^T W J / sigma^2 + R)^{-1}`` with ``J`` the exact Jacobian of the observed state
    through dense direct solves (no CG, no custom derivative rules)."""
    def observed(params):
        kappa, f = problem.parameterization.coefficients(params, problem.known)
        matrix = problem.system.operator(kappa).todense()
        u = jnp.linalg.solve(matrix, problem.system.rhs(kappa, f))
        return problem.observation.operator(problem.system.expand(u))

    jacobian = np.asarray(jax.jit(jax.jacfwd(observed))(z))  # one program, not op by op
    weight = problem.observation.weight.to_scipy().toarray()
    hessian = jacobian.T @ weight @ jacobian / SIGMA2
    return np.linalg.inv(hessian + prior.precision.toarray())


def _relative(a, b) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


# --- the prior -----------------------------------------------------------------------------


def test_the_prior_covariance_inverts_its_precision_and_its_square_root_factors_it(setting):
    _, prior, _, _, _ = setting
    n = prior.size
    identity = np.eye(n)
    assert _relative(prior.covariance_product(prior.precision @ identity), identity) < 1e-10
    root = prior.sqrt_covariance_product(identity)
    dense = np.linalg.inv(prior.precision.toarray())
    assert _relative(root @ root.T, dense) < 1e-10
    assert np.allclose(prior.pointwise_variance(), np.diag(dense), rtol=1e-10)
    estimate = prior.pointwise_variance("randomized", probes=4000, seed=1)
    # the estimator's error falls as probes^-1/2; the prior's strong correlations make it ~5 %
    assert np.mean(np.abs(estimate / np.diag(dense) - 1)) < 0.1


def test_the_prior_is_the_bilaplacian_of_the_fem_matrices(setting):
    """``R = A M_L^{-1} A`` with ``A = gamma K + delta M``: on a constant field ``K`` vanishes
    and ``R 1 = delta^2 M M_L^{-1} M 1 = delta^2 M 1`` (lumped rows are ``M 1``)."""
    disc, prior, _, _, _ = setting
    ones = np.ones(prior.size)
    mass = pf.fem.parameter_mass(disc, "log_kappa")
    assert np.allclose(prior.precision @ ones, prior.delta ** 2 * (mass @ ones), rtol=1e-12)
    regularizer = prior.regularizer()
    m = np.linspace(0.0, 1.0, prior.size)
    expected = 0.5 * (m - prior.mean) @ (prior.precision @ (m - prior.mean))
    assert float(regularizer(jnp.asarray(m))) == pytest.approx(expected, rel=1e-12)


# --- the Laplace posterior -------------------------------------------------------------------


def test_every_eigenpair_kept_gives_the_dense_posterior(setting):
    _, prior, problem, z, dense = setting
    posterior = laplace_posterior(problem, z, prior, rank=prior.size)
    assert _relative(posterior.covariance(), dense) < 1e-8
    assert np.allclose(posterior.pointwise_variance(), np.diag(dense), rtol=1e-8)
    root = posterior.sqrt_covariance_product(np.eye(prior.size))
    assert _relative(root @ root.T, dense) < 1e-8  # samples have the posterior covariance
    assert np.all(posterior.eigenvalues[:-1] >= posterior.eigenvalues[1:])


def test_the_low_rank_posterior_converges_as_eigenpairs_are_added(setting):
    _, prior, problem, z, dense = setting
    # rank + oversampling fixed: one compiled block of Hessian products for the three
    errors = [_relative(laplace_posterior(problem, z, prior, rank=r, oversampling=24 - r)
                        .covariance(), dense) for r in (4, 8, 16)]
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 1e-3


# in the default suite: the prior scene's test below (a posterior tighter than the prior at
# its run's result) and test_inverse's (invert reaches the discrete optimum)
@pytest.mark.slow
def test_the_map_point_through_the_driver_is_stationary_and_tighter_than_the_prior(setting):
    _, prior, problem, _, _ = setting
    run = pf.invert(problem, refinement=converged(1e-12), steps=60,
                    init=np.full(prior.size, 0.1))
    gradient = jax.jit(jax.grad(lambda p: problem.loss(p, pf.ConvergedCG(rtol=1e-12))[0]))
    start_norm = float(jnp.linalg.norm(gradient(jnp.full(prior.size, 0.1))))
    assert float(jnp.linalg.norm(gradient(run.params))) < 1e-5 * start_norm
    posterior = laplace_posterior(problem, run.params, prior, rank=14)  # 24 directions
    assert np.all(posterior.pointwise_variance() < prior.pointwise_variance())


def test_the_posterior_is_written_to_vtu(setting, tmp_path):
    disc, prior, problem, z, _ = setting
    posterior = laplace_posterior(problem, z, prior, rank=14)
    path = posterior.write_vtu(tmp_path / "posterior.vtu", disc, samples=2, seed=4)
    written = meshio.read(path).point_data
    assert sorted(written) == ["map", "prior_variance", "sample_1", "sample_2", "variance"]
    assert np.allclose(written["map"], np.asarray(z))
    assert np.allclose(written["variance"], posterior.pointwise_variance())
    draws = posterior.sample(np.random.default_rng(4), 2)
    assert np.allclose(written["sample_2"], draws[1])


# --- bad input -------------------------------------------------------------------------------


@pytest.mark.parametrize("key, value", [("gamma", 0.0), ("delta", float("nan")),
                                        ("gamma", "0.1"), ("delta", -1.0)])
def test_a_prior_with_a_non_positive_parameter_is_refused_by_name(setting, key, value):
    disc = setting[0]
    settings = dict(gamma=0.1, delta=0.5) | {key: value}
    with pytest.raises(SolverConfigError, match=key):
        bilaplacian_prior(disc, "log_kappa", **settings)


def test_a_posterior_of_a_problem_without_the_prior_or_with_bad_counts_is_refused(setting):
    disc, prior, problem, z, _ = setting
    with pytest.raises(SolverConfigError, match="rank"):
        laplace_posterior(problem, z, prior, rank=0)
    other = bilaplacian_prior(disc, "log_kappa", gamma=0.05, delta=0.5, mean=0.2)
    with pytest.raises(SolverConfigError, match="regularization"):
        laplace_posterior(problem, z, other, rank=4)
    with pytest.raises(SolverConfigError, match="alpha"):
        laplace_posterior(problem.with_alpha(0.0), z, prior, rank=4)


# --- scenes ------------------------------------------------------------------------------------


_PRIOR_SCENE = {
    "name": "bayes", "mesh": {"generator": "unit_square", "n": 6},
    "pde": {"element": "P1", "kappa_space": "P1", "source": 1.0, "dirichlet": 0.0},
    "inverse": {"unknown": "log_kappa", "truth": "0.5*sin(pi*x)*y", "observations": "full_field",
                "noise": 0.01, "seed": 3, "alpha": SIGMA2, "regularization": "bilaplacian",
                "prior_gamma": 0.05, "prior_delta": 0.5, "prior_mean": 0.1,
                "posterior_rank": 14, "posterior_samples": 2},
    "refinement": {"kind": "converged", "rtol": 1e-10},
    "optimizer": {"name": "lbfgs", "steps": 5},
}


def test_a_scene_with_a_gaussian_prior_writes_each_run_s_posterior(setting, tmp_path):
    """regularization = "bilaplacian": the scene's prior is the fixture's, and the study writes
    the Laplace posterior at each run's result beside its fields."""
    from prdp_fem.scene import parse_scene
    from prdp_fem.scene.build import build_inverse
    from prdp_fem.studies import run_study

    _, prior, _, _, _ = setting
    scene = parse_scene(_PRIOR_SCENE)
    built = build_inverse(scene)
    assert (built.prior.precision != prior.precision).nnz == 0
    assert np.array_equal(built.prior.mean, prior.mean)
    run_study(scene, tmp_path / "out")
    written = meshio.read(tmp_path / "out" / "fields" / "bayes_posterior.vtu").point_data
    assert {"map", "variance", "prior_variance", "sample_1", "sample_2"} <= set(written)
    assert np.all(written["variance"] < written["prior_variance"])


@pytest.mark.parametrize("keys, message", [
    ({"prior_gamma": 0.0}, r"inverse.prior_gamma"),
    ({"prior_delta": -1.0}, r"inverse.prior_delta"),
    ({"posterior_rank": -1}, r"inverse.posterior_rank"),
    ({"regularization": "h1"}, r"unknown key 'inverse.p(rior|osterior)_"),
])
def test_a_scene_names_a_bad_prior(keys, message):
    from prdp_fem.scene import parse_scene

    table = {**_PRIOR_SCENE, "inverse": {**_PRIOR_SCENE["inverse"], **keys}}
    with pytest.raises(pf.SceneError, match=message):
        parse_scene(table, source="b.toml")
