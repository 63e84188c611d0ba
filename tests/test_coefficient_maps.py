"""Coefficient maps: the unknown field mapped to kappa by log (exp), a SIMP power law, or a
user's JAX function. Each map's gradient passes the Taylor test; bad maps and bounds are
refused by name; the built-in SIMP scene recovers its density."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prdp_fem as pf
from prdp_fem.fem import Parameterization, Simp, full_field, simp
from prdp_fem.inverse import inverse_problem
from prdp_fem.linalg import ConvergedCG
from prdp_fem.scene import load_scene, parse_scene
from prdp_fem.scene.build import build_inverse
from prdp_fem.scene.spec import SceneCoefficientError


def _softplus_map(field):
    return 0.1 + jax.nn.softplus(field)


def _problem(unknown, coefficient_map=None, kappa_space="P0", cell="triangle"):
    disc = pf.discretize(pf.unit_square(6, cell), element="P1", kappa_space=kappa_space,
                         dirichlet={"bottom": 0.0}, neumann={"top": 1.0})
    field = disc.interpolate_kappa(lambda x: 0.3 + 0.4 * (x[0] > 0.5))
    kappa = np.asarray(Parameterization(unknown, coefficient_map=coefficient_map).kappa(field))
    u = disc.expand(pf.direct_solve(*disc.host_system_at(kappa)).x)
    return inverse_problem(disc, full_field(disc, u_true=u), unknown=unknown, alpha=1e-3,
                           coefficient_map=coefficient_map, truth=field)


@pytest.mark.parametrize("unknown, coefficient_map, kappa_space", [
    ("log_kappa", None, "P1"),
    ("density", None, "P0"),
    pytest.param("density", simp(0.05, 2.0, 2.0), "P1", marks=pytest.mark.slow),
    ("coefficient", _softplus_map, "P0"),
])
def test_every_map_s_gradient_passes_the_taylor_test(unknown, coefficient_map, kappa_space):
    problem = _problem(unknown, coefficient_map, kappa_space)
    rng = np.random.default_rng(4)
    z = problem.parameterization.from_field(0.4 + 0.2 * rng.uniform(size=problem.n_parameters))
    # one program for the values and the gradient (one compile, not two)
    value_and_grad = jax.jit(jax.value_and_grad(
        lambda p: problem.loss(p, ConvergedCG(rtol=1e-13))[0]))
    result = pf.taylor_test(lambda p: value_and_grad(p)[0], z, gradient=value_and_grad(z)[1])
    assert result.passed(), result


def test_the_maps_give_the_coefficients_they_name():
    field = jnp.array([0.0, 0.25, 1.0])
    np.testing.assert_allclose(Parameterization("log_kappa").kappa(field), np.exp(field))
    law = Parameterization("density", coefficient_map=simp(0.01, 2.0, 3.0))
    np.testing.assert_allclose(law.kappa(field), 0.01 + 1.99 * np.asarray(field) ** 3)
    assert law.bounds == (0.0, 1.0) and Parameterization("density").coefficient_map == Simp()
    user = Parameterization("coefficient", coefficient_map=_softplus_map)
    np.testing.assert_allclose(user.kappa(field), 0.1 + np.log1p(np.exp(field)))
    kappa, f = user.coefficients(field, jnp.ones(2))
    np.testing.assert_allclose(kappa, user.kappa(field))
    np.testing.assert_allclose(f, 1.0)


@pytest.mark.parametrize("make, error, message", [
    (lambda: Simp(k_min=0.0), pf.CoefficientError, "expected finite 0 < k_min < k_max"),
    (lambda: Simp(k_min=2.0, k_max=1.0), pf.CoefficientError, "0 < k_min < k_max"),
    (lambda: Simp(penalty=0.5), pf.CoefficientError, "penalty >= 1"),
    (lambda: Parameterization("density", bounds=(-0.5, 1.0)), pf.CoefficientError,
     "0 <= lower < upper <= 1"),
    (lambda: Parameterization("density", coefficient_map=jnp.exp), pf.SolverConfigError,
     "expected a Simp law"),
    (lambda: Parameterization("coefficient"), pf.SolverConfigError,
     "expected a JAX function field -> kappa"),
    (lambda: Parameterization("log_kappa", coefficient_map=jnp.exp), pf.SolverConfigError,
     "expected none"),
])
def test_bad_maps_and_bounds_are_refused_by_name(make, error, message):
    with pytest.raises(error, match=message):
        make()


def test_a_scene_names_a_bad_density_law():
    base = {"mesh": {"n": 4}, "inverse": {"unknown": "density", "truth": 0.5}}
    for keys, message in [({"k_min": 2.0, "k_max": 1.0}, "k_min = 2.0 and k_max = 1.0"),
                          ({"bounds": [0.0, 2.0]}, r"0 <= lower < upper <= 1"),
                          ({"penalty": 0.5}, r"inverse.penalty = 0.5")]:
        table = {**base, "inverse": {**base["inverse"], **keys}}
        with pytest.raises(SceneCoefficientError, match=message):
            parse_scene(table, source="d.toml")
    with pytest.raises(pf.SceneError, match=r"unknown key 'inverse.k_min'"):
        parse_scene({"inverse": {"unknown": "log_kappa", "truth": 0.0, "k_min": 0.1}})


def test_the_simp_scene_builds_its_law_and_recovers_the_density():
    """simp_slab: the density's SIMP law from the scene, P0 on the hexahedra of the slab's
    mesh file; 40 L-BFGS steps with converged solves take the density error from the uniform
    start's down by a third, and every value stays within [0, 1]."""
    scene = load_scene("simp_slab")
    setup = build_inverse(scene)
    law = setup.problem.parameterization
    assert law.unknown == "density" and law.coefficient_map == Simp(0.01, 1.0, 3.0)
    assert setup.disc.kappa_space == "P0" and setup.disc.mesh.t.shape == (8, 16 * 4 * 16)
    assert np.ptp(setup.disc.mesh.p, axis=1).tolist() == [1.0, 0.25, 1.0]  # a slab
    result = pf.invert(setup.problem, refinement=pf.converged(1e-10), steps=40)
    errors = result.history.column("parameter_error")
    assert errors[-1] < 0.67 * errors[0]
    field = np.asarray(result.field)
    assert field.min() >= 0.0 and field.max() <= 1.0
