"""Bad input anywhere in the public API and the CLI: a typed error that names what was wrong.

Grouped by layer: mesh files, discretisation inputs, observations, inverse problems, solver
options, scenes, and the ``prdp-fem`` command. Every case asks for the *specific* error type and
a message naming the field (and the file where there is one), so each test fails if the check
is removed or a more generic type is raised.
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import meshio
import numpy as np
import pytest

import prdp_fem as pf
from prdp_fem import errors
from prdp_fem.bench.cg import cg_iteration_cost
from prdp_fem.fem import (
    Parameterization,
    boundary_values,
    full_field,
    point_sensors,
    regularizer,
    with_noise,
)
from prdp_fem.inverse import (
    History,
    Validation,
    fixed,
    inverse_problem,
    invert,
    l_curve,
    morozov,
    prdp,
)
from prdp_fem.mesh import write_vtu
from prdp_fem.scene import SceneError, build, load_scene
from prdp_fem.scene.expressions import ExpressionError, compile_field
from prdp_fem.scene.spec import (
    SceneCoefficientError,
    SceneDataError,
    SceneDiscretizationError,
    SceneSensorError,
    SceneSolverConfigError,
)
from prdp_fem.studies.forward import build_scene, forward_convergence

ROOT = Path(__file__).resolve().parent.parent
NAN, INF = float("nan"), float("inf")


@pytest.fixture(scope="module")
def disc():
    return pf.discretize(pf.unit_square(4), element="P1", kappa_space="P0", dirichlet=0.0)


@pytest.fixture(scope="module")
def obs(disc):
    return full_field(disc, u_true=disc.interpolate(lambda x: x[0] * (1 - x[0])))


# --------------------------------------------------------------------------------------
# mesh files that lie about their contents
# --------------------------------------------------------------------------------------


def _checkout_env() -> dict:
    """Subprocesses import this checkout's package, whatever is installed (and whatever cwd)."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}


def _saved(tmp_path, name, **kwargs) -> Path:
    path = tmp_path / name
    pf.save_mesh(pf.unit_square(4), path, **kwargs)
    return path


@pytest.mark.parametrize("binary", [False, True], ids=["ascii", "binary"])
def test_truncated_msh_is_named_as_truncated(tmp_path, binary):
    data = _saved(tmp_path, "full.msh", binary=binary).read_bytes()
    half = tmp_path / "half.msh"
    half.write_bytes(data[: len(data) // 2])
    with pytest.raises(pf.MeshFileError, match=r"half\.msh: could not be read as a mesh: the "
                       r"Gmsh file ends with .* instead of an \$End\.\.\. section line, so it "
                       "is truncated"):
        pf.load_mesh(half)


@pytest.mark.parametrize(("name", "kwargs"), [("m.msh", {}), ("m.msh", {"binary": True}),
                                              ("m.vtu", {}), ("m.mesh", {})],
                         ids=["msh", "msh-binary", "vtu", "medit"])
def test_every_truncation_raises_a_mesh_error_or_loads_everything(tmp_path, name, kwargs):
    """Cut a small file at every byte: it loads in full (only an end marker was lost) or fails
    with a MeshError naming the file; it never loads in part or fails with another type."""
    full_path = tmp_path / name
    pf.save_mesh(pf.unit_square(1), full_path, **kwargs)
    data, full = full_path.read_bytes(), pf.load_mesh(full_path)
    cut_path = tmp_path / f"cut{full_path.suffix}"
    for cut in range(1, len(data)):
        cut_path.write_bytes(data[:cut])
        try:
            mesh = pf.load_mesh(cut_path)
        except pf.MeshError as error:
            assert str(cut_path) in str(error), (cut, error)
            continue
        assert mesh.t.shape == full.t.shape, cut
        assert sorted(mesh.boundaries) == sorted(full.boundaries), cut


def test_truncated_vtu_and_medit_are_named_as_truncated(tmp_path):
    for name, marker in (("m.vtu", "</VTKFile>"), ("m.mesh", "End")):
        data = _saved(tmp_path, name).read_bytes()
        cut = tmp_path / f"cut-{name}"
        cut.write_bytes(data[: int(0.8 * len(data))])
        with pytest.raises(pf.MeshFileError, match=rf"cut-{name}: .* instead of {marker}, so it "
                           "is truncated"):
            pf.load_mesh(cut)


@pytest.mark.parametrize(("saved", "renamed", "content"), [
    ("m.vtu", "renamed.msh", "VTK XML"), ("m.msh", "renamed.vtu", "Gmsh"),
    ("m.msh", "renamed.xdmf", "Gmsh"), ("m.vtu", "renamed.txt", "VTK XML")])
def test_file_with_the_wrong_extension(tmp_path, saved, renamed, content):
    path = tmp_path / renamed
    path.write_bytes(_saved(tmp_path, saved).read_bytes())
    right = "renamed" + Path(saved).suffix
    with pytest.raises(pf.MeshFileError, match=rf"{renamed}: could not be read as a mesh: its "
                       rf"content is a {content} file but its suffix is '\.\w+'; expected the "
                       rf"suffix to match the content \(rename it to {right}\)"):
        pf.load_mesh(path)


@pytest.mark.parametrize(("name", "content", "message"), [
    ("junk.msh", b"hello world\nthis is not a mesh\n",
     r"junk\.msh: could not be read as a mesh: it does not start with \$MeshFormat \(first "
     r"line 'hello world'\)"),
    ("junk.vtu", b"hello world\n", r"junk\.vtu: could not be read as a mesh \(no valid \.vtu "
     r"content\)"),
    ("junk.vtk", b"hello world\n", r"junk\.vtk: could not be read as a mesh \(Illegal VTK"),
    ("junk.xdmf", b"hello world\n", r"junk\.xdmf: could not be read as a mesh \(ParseError"),
    ("noise.vtu", bytes(range(256)) * 8, r"noise\.vtu: could not be read as a mesh"),
    ("noise.msh", bytes(range(256)) * 8, r"noise\.msh: .*does not start with \$MeshFormat "
     r"\(first line binary data\)"),
])
def test_garbage_with_a_known_extension(tmp_path, capfd, name, content, message):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(pf.MeshFileError, match=message):
        pf.load_mesh(path)
    out, err = capfd.readouterr()
    assert out == "" and err == ""  # meshio's own prints are not passed on: one error, one line


@pytest.mark.parametrize(("name", "cells", "found"), [
    ("lines.msh", [("line", np.array([[0, 1], [1, 2], [2, 3]]))], "'line'"),
    ("points.vtu", [("vertex", np.array([[0], [1], [2], [3]]))], "'vertex'"),
    ("both.vtu", [("line", np.array([[0, 1]])), ("vertex", np.array([[2], [3]]))],
     "'line', 'vertex'"),
])
def test_mesh_without_supported_cells(tmp_path, name, cells, found):
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    path = tmp_path / name
    meshio.write(path, meshio.Mesh(points, cells),
                 **({"file_format": "gmsh22", "binary": False} if name.endswith(".msh") else {}))
    with pytest.raises(errors.UnsupportedCellsError, match=rf"{name}: holds \[{found}\]; expected "
                       "triangle, quad, tetra or hexahedron cells"):
        pf.load_mesh(path)


# --------------------------------------------------------------------------------------
# discretisation inputs
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("value", [NAN, INF, lambda x: np.where(x[1] > 0.5, NAN, 0.0)])
def test_non_finite_boundary_data(value):
    mesh = pf.unit_square(4)
    with pytest.raises(pf.DataError, match=r"dirichlet\[None\]: boundary data is NaN/Inf"):
        pf.discretize(mesh, dirichlet=value)
    with pytest.raises(pf.DataError, match=r"neumann\['right'\]: boundary data is NaN/Inf"):
        pf.discretize(mesh, dirichlet={"left": 0.0}, neumann={"right": value})


@pytest.mark.parametrize(("kappa", "message"), [
    (-1.0, r"kappa: 32 value\(s\) <= 0"), (0.0, r"kappa: 32 value\(s\) <= 0"),
    (NAN, r"kappa: 32 value\(s\) are NaN/Inf"), (np.ones(5), r"kappa: expected a vector of 32"),
])
def test_bad_kappa_in_the_discretisation(disc, kappa, message):
    error = pf.ShapeError if np.ndim(kappa) else pf.CoefficientError
    with pytest.raises(error, match=message):
        disc.stiffness_matrix(kappa)


def test_non_finite_source_in_the_discretisation(disc):
    with pytest.raises(pf.DataError, match=r"f: 1 value\(s\) are NaN/Inf \(first: index 3"):
        disc.rhs(np.ones(disc.n_kappa), np.where(np.arange(disc.n_dofs) == 3, INF, 0.0))


# --------------------------------------------------------------------------------------
# observations
# --------------------------------------------------------------------------------------


def test_bad_observed_values(disc):
    n = disc.n_dofs
    with pytest.raises(pf.DataError, match=r"u_true .*: 1 value\(s\) are NaN/Inf"):
        full_field(disc, u_true=np.where(np.arange(n) == 0, NAN, 1.0))
    with pytest.raises(pf.ShapeError, match=rf"u_true .*: expected a vector of {n} values, got "
                       r"shape \(3,\)"):
        full_field(disc, u_true=np.ones(3))
    with pytest.raises(pf.DataError, match=r"data \(observed values\): 1 value\(s\) are NaN/Inf"):
        full_field(disc, data=np.where(np.arange(n) == 0, -INF, 1.0))
    with pytest.raises(pf.ShapeError, match=r"data \(observed values\): expected a vector of"):
        full_field(disc, data=np.ones(n + 1))
    with pytest.raises(pf.DataError, match="expected exactly one of u_true="):
        full_field(disc)
    with pytest.raises(pf.SolverConfigError, match="norm='h1'"):
        full_field(disc, data=np.ones(n), norm="h1")


def test_bad_sensor_points(disc):
    u = np.ones(disc.n_dofs)
    with pytest.raises(errors.SensorError, match=r"points: an empty sensor set \(shape \(0, 2\)\)"):
        point_sensors(disc, np.empty((0, 2)), u_true=u)
    with pytest.raises(pf.ShapeError, match=r"points: expected coordinates of shape \(n_sensors, "
                       r"2\), got \(3, 3\)"):
        point_sensors(disc, np.full((3, 3), 0.5), u_true=u)
    with pytest.raises(pf.ShapeError, match=r"points: .*got \(2, 2, 1\)"):
        point_sensors(disc, np.full((2, 2, 1), 0.5), u_true=u)
    with pytest.raises(errors.SensorError, match=r"points: 1 sensor\(s\) have NaN/Inf coordinates "
                       r"\(first: sensor 1 at \[nan, 0\.5\]\)"):
        point_sensors(disc, [[0.5, 0.5], [NAN, 0.5]], u_true=u)
    with pytest.raises(errors.SensorError, match=r"points: 2 sensor\(s\) lie outside the mesh "
                       r"\(first: sensor 1 at \[1\.5, 0\.5\]\)"):
        point_sensors(disc, [[0.5, 0.5], [1.5, 0.5], [0.5, -2.0]], u_true=u)
    with pytest.raises(pf.ShapeError, match=r"data \(observed values\): expected a vector of 1 "):
        point_sensors(disc, [[0.5, 0.5]], data=[1.0, 2.0])


def test_bad_observed_boundaries():
    natural = pf.discretize(pf.unit_square(4), dirichlet={"left": 0.0})
    u = np.ones(natural.n_dofs)
    with pytest.raises(errors.SensorError, match=r"boundaries=\[\]: an empty sensor set"):
        boundary_values(natural, [], u_true=u)
    with pytest.raises(errors.SensorError, match=r"unknown 'inlet'; expected names among"):
        boundary_values(natural, ["right", "inlet"], u_true=u)
    with pytest.raises(errors.SensorError, match=r"boundaries='right': expected a list"):
        boundary_values(natural, "right", u_true=u)
    with pytest.raises(errors.SensorError, match="every observed dof carries Dirichlet data"):
        boundary_values(natural, ["left"], u_true=u)


@pytest.mark.parametrize("level", [NAN, INF, -0.1, "1%", np.ones(2)])
def test_bad_noise_level(obs, level):
    with pytest.raises(pf.DataError, match=r"noise level=.*: expected a finite number >= 0"):
        with_noise(obs, level)


def test_bad_noise_seed(obs):
    with pytest.raises(pf.DataError, match=r"noise seed=-1: expected an integer >= 0"):
        with_noise(obs, 0.01, seed=-1)


# --------------------------------------------------------------------------------------
# inverse problems
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(("known", "error", "message"), [
    (-1.0, pf.CoefficientError, r"known \(kappa of a source inversion\): 32 value\(s\) <= 0"),
    (0.0, pf.CoefficientError, r"known \(kappa of a source inversion\): 32 value\(s\) <= 0"),
    (NAN, pf.CoefficientError, r"known \(kappa of a source inversion\): .* NaN/Inf"),
    (np.ones(7), pf.ShapeError, r"known \(kappa of a source inversion\): expected a vector of "
     r"32 values, got shape \(7,\)"),
])
def test_bad_known_kappa_of_a_source_inversion(disc, obs, known, error, message):
    with pytest.raises(error, match=message):
        inverse_problem(disc, obs, unknown="source", alpha=1e-3, known=known)


def test_bad_known_source_of_a_log_kappa_inversion(disc, obs):
    f = np.ones(disc.n_dofs)
    f[4] = INF
    with pytest.raises(pf.DataError, match=r"known \(nodal source f of a log_kappa inversion\): "
                       r"1 value\(s\) are NaN/Inf \(first: index 4"):
        inverse_problem(disc, obs, unknown="log_kappa", alpha=1e-3, known=f)
    with pytest.raises(pf.ShapeError, match=r"known \(nodal source f .*expected a vector of 25"):
        inverse_problem(disc, obs, unknown="log_kappa", alpha=1e-3, known=np.ones(3))


def test_truth_of_log_kappa_may_be_negative_but_not_nan(disc, obs):
    negative = -np.ones(disc.n_kappa)
    problem = inverse_problem(disc, obs, unknown="log_kappa", alpha=1e-3, truth=negative)
    assert float(problem.parameter_error(problem.parameterization.from_field(negative))) == 0
    with pytest.raises(pf.CoefficientError, match=r"truth \(log_kappa field\): 1 value\(s\) are "
                       "NaN/Inf"):
        inverse_problem(disc, obs, unknown="log_kappa", alpha=1e-3,
                        truth=np.where(np.arange(disc.n_kappa) == 0, NAN, 0.0))
    with pytest.raises(pf.ShapeError, match=r"truth \(log_kappa field\): expected a vector of 32"):
        inverse_problem(disc, obs, unknown="log_kappa", alpha=1e-3, truth=np.ones(25))
    with pytest.raises(pf.DataError, match=r"truth \(source field\): .*NaN/Inf"):
        inverse_problem(disc, obs, unknown="source", alpha=1e-3, truth=np.full(25, NAN))


@pytest.mark.parametrize("bounds", [(NAN, 1.0), (1.0, 0.0), (0.0, 0.0), (-INF, 0.0), (1.0,),
                                    "ab", (1.0, 2.0, 3.0)])
def test_bounds_must_be_finite_and_ordered(disc, obs, bounds):
    with pytest.raises(pf.CoefficientError, match=r"bounds=.* on the log_kappa field: expected "
                       r"finite \(lower, upper\) with lower < upper"):
        inverse_problem(disc, obs, unknown="log_kappa", alpha=1e-3, bounds=bounds)
    with pytest.raises(pf.DataError, match=r"bounds=.* on the source field"):
        Parameterization("source", bounds)


@pytest.mark.parametrize("alpha", [NAN, -1.0, INF, "big", None])
def test_bad_alpha(disc, obs, alpha):
    with pytest.raises(pf.SolverConfigError, match=r"alpha=.*: expected a finite number >= 0"):
        inverse_problem(disc, obs, unknown="source", alpha=alpha)


def test_bad_problem_options(disc, obs):
    with pytest.raises(pf.SolverConfigError, match=r"unknown='kappa': expected one of"):
        inverse_problem(disc, obs, unknown="kappa", alpha=1.0)
    with pytest.raises(pf.SolverConfigError, match=r"regularizer='h2': expected one of"):
        inverse_problem(disc, obs, unknown="source", alpha=1.0, regularization="h2")
    with pytest.raises(pf.SolverConfigError, match=r"regularization=3: expected"):
        inverse_problem(disc, obs, unknown="source", alpha=1.0, regularization=3)
    other = pf.discretize(pf.unit_square(3))
    with pytest.raises(pf.ShapeError, match=r"regularization: built for 16 parameters, expected "
                       "25"):
        inverse_problem(disc, obs, unknown="source", alpha=1.0,
                        regularization=regularizer(other, "source"))
    with pytest.raises(pf.ShapeError, match=r"observation: operator acts on 25 dofs, expected 16"):
        inverse_problem(other, obs, unknown="source", alpha=1.0)


def test_bad_regularizer_settings(disc):
    with pytest.raises(pf.SolverConfigError, match=r"epsilon=0\.0: expected a finite number > 0"):
        regularizer(disc, "source", "tv", epsilon=0.0)
    with pytest.raises(pf.DataError, match=r"reference \(m_0 of the source field\): .*NaN/Inf"):
        regularizer(disc, "source", "l2", reference=np.full(disc.n_dofs, NAN))
    with pytest.raises(pf.ShapeError, match=r"reference \(m_0 of the log_kappa field\): expected "
                       "a vector of 32"):
        regularizer(disc, "log_kappa", "h1", reference=np.ones(3))
    with pytest.raises(pf.SolverConfigError, match=r"unknown='f'"):
        regularizer(disc, "f")


def test_tensor_kappa_in_inverse_problems():
    tensor = pf.discretize(pf.unit_square(4), kappa_kind="tensor", dirichlet=0.0)
    obs = full_field(tensor, u_true=tensor.interpolate(lambda x: x[0] * (1 - x[0])))
    with pytest.raises(errors.DiscretizationError,
                       match=r"unknown='log_kappa' .*kappa_kind='tensor'"):
        inverse_problem(tensor, obs, unknown="log_kappa", alpha=1.0)
    problem = inverse_problem(tensor, obs, unknown="source", alpha=1.0)  # default: identity
    # the system is frozen at kappa: its operator is the Laplacian's free block
    free = tensor.free_dofs
    laplace = tensor.laplace_matrix[free][:, free].toarray()
    frozen = problem.system.operator(jnp.asarray(problem.known)).todense()
    np.testing.assert_allclose(frozen, laplace, rtol=0, atol=1e-14 * np.abs(laplace).max())
    singular = tensor.interpolate_kappa(lambda x: np.ones((2, 2)))
    with pytest.raises(pf.CoefficientError, match=r"known \(kappa of a source inversion\): the "
                       "tensor at 32 point"):
        inverse_problem(tensor, obs, unknown="source", alpha=1.0, known=singular)


def test_bad_alpha_choice_settings(disc, obs):
    problem = inverse_problem(disc, obs, unknown="source", alpha=1e-3)
    with pytest.raises(pf.DataError, match="morozov: the observation has no noise level"):
        morozov(problem)
    noisy = inverse_problem(disc, with_noise(obs, 0.01), unknown="source", alpha=1e-3)
    for kwargs, message in (({"alpha0": -1.0}, "alpha0=-1.0"), ({"tau": NAN}, "tau=nan"),
                            ({"rtol": 0.0}, "rtol=0.0"),
                            ({"max_inversions": 0}, "max_inversions=0")):
        with pytest.raises(pf.SolverConfigError, match=f"morozov: {message}"):
            morozov(noisy, **kwargs)
    for alphas in ([1e-3, 1e-2], [1e-3, 1e-3, 1e-3], [0.0, 1e-3, 1e-2], [NAN, 1.0, 2.0, 3.0],
                   ["a", 1.0, 2.0]):
        with pytest.raises(pf.SolverConfigError, match=r"alphas=.*: expected at least 3 "
                           "distinct finite positive values"):
            l_curve(problem, alphas)


def test_bad_vtu_fields_and_history_files(tmp_path):
    mesh = pf.unit_square(4)
    with pytest.raises(pf.ShapeError, match=r"field 'k': expected 32 cell values, got \(3,\)"):
        write_vtu(mesh, tmp_path / "k.vtu", {"k": ("P0", np.ones(3))})
    with pytest.raises(errors.DiscretizationError, match=r"field 'k': space 'P3'"):
        write_vtu(mesh, tmp_path / "k.vtu", {"k": ("P3", np.ones(32))})
    path = tmp_path / "history.jsonl"
    path.write_text('{"step": 1}\nnot json\n')
    with pytest.raises(pf.DataError, match=r"history\.jsonl: line 1 is not a step record"):
        History.from_jsonl(path)
    with pytest.raises(KeyError, match="'error': expected one of"):
        History().first_reaching(0.1, "error")


# --------------------------------------------------------------------------------------
# solver options (and the initial guess) of invert
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def source_problem(disc, obs):
    return inverse_problem(disc, obs, unknown="source", alpha=1e-3)


def test_bad_initial_guess(disc, obs, source_problem):
    n = disc.n_dofs
    with pytest.raises(pf.DataError, match=r"init \(initial source field\): 1 value\(s\) are "
                       r"NaN/Inf \(first: index 2"):
        invert(source_problem, steps=1, init=np.where(np.arange(n) == 2, NAN, 0.0))
    with pytest.raises(pf.ShapeError, match=r"init \(initial source field\): expected a vector of "
                       r"25 values, got shape \(3,\)"):
        invert(source_problem, steps=1, init=np.ones(3))
    bounded = inverse_problem(disc, obs, unknown="log_kappa", alpha=1e-3, bounds=(-1.0, 1.0))
    with pytest.raises(pf.DataError, match=r"init \(initial log_kappa field\): 32 value\(s\) "
                       r"outside bounds=\(-1\.0, 1\.0\)"):
        invert(bounded, steps=1, init=2.0)


@pytest.mark.parametrize(("make", "message"), [
    (lambda: fixed(-1), r"schedule=.*K0=-1.*expected integers 0 <= K0 <= K_max"),
    (lambda: fixed(3, -2), r"adjoint=.*K0=-2"),
    (lambda: prdp(K0=-5), r"schedule=.*K0=-5"),
    (lambda: prdp(adjoint=(-1, 1, 10, 1.0)), r"adjoint=.*K0=-1"),
])
def test_negative_iteration_counts(make, message):
    with pytest.raises(pf.SolverConfigError, match=message):
        make()


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"gradient": "adjoint"}, r"gradient='adjoint': expected 'implicit' or 'unrolled'"),
    ({"preconditioner": "ilu"}, r"preconditioner='ilu': expected one of \('identity', 'jacobi'\)"),
    ({"preconditioner": lambda r: r}, r"preconditioner=.*a plain function is not a pytree"),
    ({"steps": -1}, r"steps=-1: expected an integer >= 0"),
    ({"steps": 2.5}, r"steps=2\.5: expected an integer >= 0"),
    ({"steps": True}, r"steps=True: expected an integer >= 0"),
    ({"reference_every": -1}, r"reference_every=-1: expected an integer >= 0"),
    ({"monitor": "misfit"}, r"monitor='misfit': expected 'loss', 'gradient' or a Validation"),
    ({"refinement": "prdp"}, r"refinement='prdp': expected a controller"),
    ({"callback": 3}, r"callback=3: expected a callable"),
])
def test_bad_invert_options(source_problem, kwargs, message):
    with pytest.raises(pf.SolverConfigError, match=message):
        invert(source_problem, steps=kwargs.pop("steps", 1), **kwargs)


def test_bad_validation_forward_and_bench_options():
    with pytest.raises(pf.SolverConfigError, match=r"Validation\(every=0"):
        Validation(every=0)
    scene = build_scene("square", n=4)
    with pytest.raises(pf.SolverConfigError, match=r"preconditioner='ilu'"):
        forward_convergence(scene, [1], preconditioner="ilu")
    with pytest.raises(pf.SolverConfigError, match=r"iterations=\[1, -1\]: expected integers >= "
                       r"0 \(first bad: -1\)"):
        forward_convergence(scene, [1, -1])
    with pytest.raises(pf.SceneError, match=r"scene 'torus': expected one of"):
        build_scene("torus")
    with pytest.raises(pf.SolverConfigError, match=r"repeats=0: expected an integer >= 1"):
        cg_iteration_cost(4, iterations=1, repeats=0)


# --------------------------------------------------------------------------------------
# scenes
# --------------------------------------------------------------------------------------


def _scene(tmp_path, text, name="bad.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize(("kappa", "found"), [('"x - 0.5"', "min -0.417"),
                                              ('"0.25 - x*y"', "min -0.514")])
def test_scene_kappa_that_is_not_positive_on_the_mesh(tmp_path, kappa, found):
    scene = load_scene(_scene(tmp_path, f"[mesh]\nn = 4\n[pde]\nkappa = {kappa}\n"))
    with pytest.raises(SceneCoefficientError, match=rf"bad\.toml: pde\.kappa = .*: expected "
                       rf"values > 0 on the mesh, found {found}") as info:
        build.forward_solve(scene)
    assert isinstance(info.value, pf.CoefficientError) and isinstance(info.value, SceneError)


@pytest.mark.parametrize("kappa", ["-1", "0", "-0.5"])
def test_scene_constant_kappa_not_positive_is_refused_at_load(tmp_path, kappa):
    with pytest.raises(SceneCoefficientError, match=rf"bad\.toml: pde\.kappa = "
                       rf"{re.escape(kappa)}: expected a coefficient > 0"):
        load_scene(_scene(tmp_path, f"[pde]\nkappa = {kappa}\n"))


def test_scene_non_finite_formulas_name_file_and_key(tmp_path):
    cases = [("[pde]\nkappa = 'sqrt(x - 2)'", build.forward_solve, r"pde\.kappa = 'sqrt\(x - "
              r"2\)': non-finite value at x = \["),
             ("[pde]\nkappa = nan", None, r"pde\.kappa = nan: expected a finite number"),
             ("[pde]\nsource = '1/(x - x)'", build.forward_solve, r"pde\.source = .*non-finite"),
             ("[pde]\ndirichlet = {left = 0.0}\nneumann = {right = 'log(x - 2)'}",
              build.forward_solve, r"pde\.neumann\.right = 'log\(x - 2\)': non-finite"),
             ("[pde]\nsource = 'log(x - 2)'\n[inverse]\nunknown = 'log_kappa'\ntruth = 'x'",
              build.build_inverse, r"pde\.source = 'log\(x - 2\)': non-finite"),
             ("[pde]\nsource = '2**100000'", build.forward_solve,
              r"pde\.source = '2\*\*100000': could not be evaluated \(OverflowError")]
    for text, run, message in cases:
        path = _scene(tmp_path, "[mesh]\nn = 4\n" + text)
        with pytest.raises(ExpressionError, match=rf"bad\.toml: {message}"):
            run(load_scene(path))


@pytest.mark.parametrize(("formula", "message"), [
    ("sin(x, y)", r"sin\(\) called with 2 argument\(s\); expected 1"),  # would write into y
    ("hypot(x)", r"hypot\(\) called with 1 argument\(s\); expected 2"),
    ("where(x > 0.5)", r"where\(\) called with 1 argument\(s\); expected 3"),
])
def test_formula_with_the_wrong_number_of_arguments_is_refused_at_load(tmp_path, formula,
                                                                        message):
    with pytest.raises(ExpressionError, match=rf"bad\.toml: pde\.source = .*: {message}"):
        load_scene(_scene(tmp_path, f"[pde]\nsource = '{formula}'\n"))
    x = np.array([[0.1, 0.2], [0.3, 0.4]])
    if formula == "sin(x, y)":  # and the coordinates are never written into
        with pytest.raises(ExpressionError):
            compile_field(formula, where="f")(x)
        np.testing.assert_array_equal(x, [[0.1, 0.2], [0.3, 0.4]])


def _bare_packages(*names: str) -> str:
    """Source that makes ``names`` bare packages of this checkout in a child process: it
    imports the one module it needs without their ``__init__`` (which imports JAX and the
    finite-element stack, seconds of a child's run)."""
    lines = ["import sys, types"]
    for name in names:
        path = str(ROOT.joinpath(*name.split(".")))
        lines += [f"sys.modules[{name!r}] = types.ModuleType({name!r})",
                  f"sys.modules[{name!r}].__path__ = [{path!r}]"]
    return "\n".join(lines) + "\n"


def test_huge_integer_powers_are_evaluated_as_floats_not_for_ever():
    # in a child process, which a hang cannot outlive
    code = (_bare_packages("prdp_fem", "prdp_fem.scene") +
            "from prdp_fem.scene.expressions import ExpressionError, compile_field\n"
            "import numpy as np\n"
            "try:\n"
            "    compile_field('10**10**10 + x', where='f')(np.zeros((2, 3)))\n"
            "except ExpressionError as error:\n"
            "    print(error)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env=_checkout_env())
    assert "f = '10**10**10 + x': could not be evaluated (OverflowError" in done.stdout, done


INVERSE = "[mesh]\nn = 4\n[inverse]\ntruth = 'x'\n"


@pytest.mark.parametrize(("text", "message"), [
    ("observations = 'sensors'\nsensors = 0", r"inverse\.sensors = 0: expected a positive count"),
    ("observations = 'sensors'\nsensors = []", r"inverse\.sensors = \[\]: expected a positive"),
    ("observations = 'sensors'\nsensors = [[0.5, 0.5], [0.5, 0.5, 0.5]]",
     r"inverse\.sensors = .*: expected a positive count or a non-empty list"),
    ("observations = 'boundary'", r"inverse\.boundaries: expected a non-empty list"),
])
def test_scene_without_sensors_is_refused_at_load(tmp_path, text, message):
    with pytest.raises(SceneSensorError, match=rf"bad\.toml: {message}") as info:
        load_scene(_scene(tmp_path, INVERSE + text))
    assert isinstance(info.value, errors.SensorError)


@pytest.mark.parametrize(("text", "message"), [
    ("observations = 'sensors'\nsensors = [[0.5, 0.5], [2.0, 2.0]]",
     r"inverse\.sensors: points: 1 sensor\(s\) lie outside the mesh \(first: sensor 1 at "
     r"\[2\.0, 2\.0\]\)"),
    ("observations = 'sensors'\nsensors = [[0.5, 0.5, 0.5]]",
     r"inverse\.sensors: points: expected coordinates of shape \(n_sensors, 2\)"),
    ("observations = 'sensors'\nsensors = 50",
     r"inverse\.sensors = 50: the mesh has only 9 interior vertices"),
    ("observations = 'boundary'\nboundaries = ['inlet']",
     r"inverse\.boundaries: boundaries=\['inlet'\]: unknown 'inlet'"),
])
def test_scene_sensors_that_do_not_fit_the_mesh(tmp_path, text, message):
    scene = load_scene(_scene(tmp_path, INVERSE + text))
    with pytest.raises(SceneSensorError, match=rf"bad\.toml: {message}") as info:
        build.build_inverse(scene)
    assert isinstance(info.value, errors.SensorError)


@pytest.mark.parametrize(("text", "message"), [
    ("[solver]\niterations = [10, -1]", r"solver\.iterations = \[10, -1\]: expected a list of "
     "integers >= 0"),
    ("[solver]\npreconditioner = 'ilu'", r"solver\.preconditioner = 'ilu': expected one of "
     r"\['jacobi', 'identity', 'amg'\]"),
    ("[solver]\ngradient = 'adjoint'", r"solver\.gradient = 'adjoint': expected one of"),
    ("[refinement]\nkind = 'fixed'\nK = -1", r"refinement\.K = -1: expected an integer >= 0"),
    ("[refinement]\nK0 = -3", r"refinement\.K0 = -3: expected an integer >= 1"),
    ("[refinement]\nK0 = 700", r"refinement\.K0 = 700 exceeds K_max = 600"),
    ("[optimizer]\nsteps = -1", r"optimizer\.steps = -1: expected an integer >= 0"),
    ("[inverse]\ntruth = 'x'\nalpha = -1e-3", r"inverse\.alpha = -0\.001: expected a finite"),
])
def test_scene_solver_settings(tmp_path, text, message):
    with pytest.raises(SceneSolverConfigError, match=rf"bad\.toml: {message}") as info:
        load_scene(_scene(tmp_path, text))
    assert isinstance(info.value, pf.SolverConfigError)


def test_scene_data_bounds_and_init(tmp_path):
    with pytest.raises(SceneDataError, match=r"bad\.toml: inverse\.noise = nan: expected a "
                       "finite number >= 0"):
        load_scene(_scene(tmp_path, "[inverse]\ntruth = 'x'\nnoise = nan"))
    with pytest.raises(SceneCoefficientError, match=r"bad\.toml: inverse\.bounds = \[1\.0, "
                       r"0\.0\]: expected \[lower, upper\] with finite lower < upper"):
        load_scene(_scene(tmp_path, "[inverse]\nunknown = 'log_kappa'\ntruth = 'x'\n"
                          "bounds = [1.0, 0.0]"))
    with pytest.raises(SceneDataError, match=r"inverse\.bounds = \[0\.0, inf\]"):
        load_scene(_scene(tmp_path, "[inverse]\ntruth = 'x'\nbounds = [0.0, inf]"))
    scene = load_scene(_scene(tmp_path, INVERSE + "unknown = 'log_kappa'\n"
                              "bounds = [-1.0, 1.0]\ninit = '3*x'"))
    with pytest.raises(SceneCoefficientError, match=r"bad\.toml: inverse\.init = '3\*x': values "
                       r"from .* to .* on the mesh; expected values within inverse\.bounds"):
        build.invert_options(scene, build.build_discretization(scene))


def test_scene_pde_that_does_not_fit_the_mesh(tmp_path):
    scene = load_scene(_scene(tmp_path, "[mesh]\nn = 4\n[pde]\ndirichlet = {inlet = 0.0}"))
    with pytest.raises(SceneDiscretizationError, match=r"bad\.toml: \[pde\] dirichlet: unknown "
                       r"boundary 'inlet'; this mesh has \['bottom', 'left', 'right', 'top'\]"):
        build.forward_solve(scene)
    scene = load_scene(_scene(tmp_path, "[mesh]\nn = 4\n[pde]\nelement = 'Q1'"))
    with pytest.raises(SceneDiscretizationError, match=r"bad\.toml: \[pde\] element='Q1' on a "
                       "MeshTri1 mesh"):
        build.forward_solve(scene)


def test_scene_with_a_truncated_mesh_file_names_the_mesh(tmp_path):
    data = _saved(tmp_path, "full.msh").read_bytes()
    (tmp_path / "cut.msh").write_bytes(data[: len(data) // 2])
    scene = load_scene(_scene(tmp_path, "[mesh]\nfile = 'cut.msh'"))
    with pytest.raises(pf.MeshFileError, match=rf"{tmp_path / 'cut.msh'}: .*so it is truncated"):
        build.forward_solve(scene)


# --------------------------------------------------------------------------------------
# the prdp-fem command (its main, in this process): one line on stderr, exit status 2
# --------------------------------------------------------------------------------------


def run_main(args, cwd, monkeypatch, capsys) -> tuple[int, str]:
    """``main(args)`` in this process, run in ``cwd``: its exit code and stderr (the program
    only exits with that code; tests/test_cli_commands.py runs a bad input through it)."""
    from prdp_fem.cli.main import main

    monkeypatch.chdir(cwd)
    capsys.readouterr()
    try:
        code = main([str(a) for a in args])
    except SystemExit as exit:  # an option argparse refuses
        code = exit.code
    return code, capsys.readouterr().err


@pytest.mark.parametrize(("args", "message"), [
    (["solve", "KAPPA"], r"kappa\.toml: pde\.kappa = 'x - 0\.5': expected values > 0 on the "
     "mesh"),
    (["study", "ITERATIONS"], r"iterations\.toml: solver\.iterations = \[-1\]: expected a list "
     "of integers >= 0"),
    (["mesh-info", "HALF"], r"half\.msh: could not be read as a mesh: the Gmsh file ends with "
     r".*so it is truncated"),
    (["mesh-info", "RENAMED"], r"renamed\.msh: could not be read as a mesh: its content is a "
     r"VTK XML file but its suffix is '\.msh'"),
    (["invert", "SENSORS"], r"sensors\.toml \(run 'sensors'\): inverse\.sensors: points: 1 "
     r"sensor\(s\) lie outside the mesh"),
    (["bench", "cg", "--sides", "4", "--repeats", "0"], r"--repeats 0: expected integers >= 1"),
    (["bench", "memory", "--modes", "adjoint"], r"--modes adjoint: expected some of "
     r"\['unrolled', 'checkpointed', 'implicit'\]"),
])
def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys, args, message):
    (tmp_path / "kappa.toml").write_text("[mesh]\nn = 4\n[pde]\nkappa = 'x - 0.5'\n")
    (tmp_path / "iterations.toml").write_text("[mesh]\nn = 4\n[solver]\niterations = [-1]\n")
    (tmp_path / "sensors.toml").write_text(
        INVERSE + "observations = 'sensors'\nsensors = [[0.5, 0.5], [1.5, 0.5]]\n")
    data = _saved(tmp_path, "full.msh").read_bytes()
    (tmp_path / "half.msh").write_bytes(data[: len(data) // 2])
    (tmp_path / "renamed.msh").write_bytes(_saved(tmp_path, "m.vtu").read_bytes())
    names = {"KAPPA": "kappa.toml", "ITERATIONS": "iterations.toml", "HALF": "half.msh",
             "RENAMED": "renamed.msh", "SENSORS": "sensors.toml"}
    code, err = run_main([names.get(a, a) for a in args], tmp_path, monkeypatch, capsys)
    assert code == 2, err
    assert err.startswith("prdp-fem: error: "), err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert re.search(message, err), err
