"""Scene files: parsing, defaults, errors naming file/key/expectation, lazy building."""

import json
from pathlib import Path

import jax
import numpy as np
import optax
import pytest

import prdp_fem as pf
from prdp_fem.scene import (
    BUILTIN_SCENES,
    SceneError,
    build,
    builtin_scene_path,
    load_scene,
    parse_scene,
)
from prdp_fem.scene.expressions import ExpressionError, compile_field
from prdp_fem.scene.spec import mesh_scene, with_overrides

ROOT = Path(__file__).resolve().parent.parent


def write(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


# -- built-in scenes and their copies ----------------------------------------------------


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_builtin_scenes_parse_and_match_their_example_copies(name):
    scene = load_scene(name)
    assert scene.name == name and scene.description
    # one copy: the example is a link to the packaged scene, not a duplicate kept in sync
    example = ROOT / "examples" / "scenes" / f"{name}.toml"
    assert example.is_symlink() and example.resolve() == builtin_scene_path(name).resolve()
    copy = load_scene(ROOT / "examples" / "scenes" / f"{name}.toml")
    assert copy.fingerprint == scene.fingerprint or scene.mesh.file is None or \
        scene.mesh.file.startswith("@meshes/")


@pytest.mark.parametrize("mesh", ["plate_hole.msh", "cube_tet.msh"])
def test_packaged_meshes_are_the_shipped_ones(mesh):
    shipped = ROOT / "meshes" / mesh  # one copy: a link to the package's
    assert shipped.is_symlink()
    assert shipped.resolve() == (ROOT / "prdp_fem" / "data" / "meshes" / mesh).resolve()
    assert pf.load_mesh(shipped).p.shape[1] > 0


def test_defaults_are_documented_values():
    scene = parse_scene({})
    assert (scene.mesh.generator, scene.mesh.n, scene.pde.element, scene.pde.kappa_space) == \
        ("unit_square", 32, "P1", "P0")
    assert (scene.solver.preconditioner, scene.solver.gradient) == ("jacobi", "implicit")
    assert (scene.refinement.kind, scene.refinement.K0, scene.refinement.dK) == ("prdp", 25, 10)
    assert not scene.refinement.stall_on_failure and scene.refinement.restart
    assert (scene.optimizer.name, scene.optimizer.steps) == ("lbfgs", 100)
    assert scene.inverse is None and scene.study.kind == "forward"


def test_first_step_reaches_the_line_search():
    """`[optimizer] first_step = "polyak"` builds L-BFGS whose first search takes J / |s_0|
    in one evaluation; the scene reader knows the same choices as the line search."""
    from prdp_fem.optim import FIRST_STEPS
    from prdp_fem.scene.spec import _FIRST_STEPS
    assert _FIRST_STEPS == FIRST_STEPS

    def fn(z):
        return 1e-8 * jax.numpy.sum((z - 3.0) ** 2)

    def first_update(optimizer):  # jitted: the eager line search dispatched op by op
        z = jax.numpy.zeros(2)
        value, grad = jax.value_and_grad(fn)(z)
        _, state = optimizer.update(grad, optimizer.init(z), z, value=value, grad=grad,
                                    value_fn=fn)
        return optax.tree_utils.tree_get(state, "num_linesearch_steps")

    searches = {}
    for first_step in FIRST_STEPS:
        optimizer = build.optimizer(parse_scene({"optimizer": {"first_step": first_step}}))
        searches[first_step] = int(jax.jit(first_update, static_argnums=0)(optimizer))
    assert searches["polyak"] == 1 and searches["unit"] > 10


def test_equal_lbfgs_settings_build_one_optimizer_object():
    """A study's runs then share one compiled step (`invert` keys its steps by the object)."""
    first = build.optimizer(parse_scene({"optimizer": {"first_step": "unit"}}))
    again = build.optimizer(parse_scene({"optimizer": {"first_step": "unit"}}))
    other = build.optimizer(parse_scene({"optimizer": {"first_step": "polyak"}}))
    assert first is again and other is not first
    adam = {"optimizer": {"name": "adam", "learning_rate": 1e-3, "decay": "cosine"}}
    assert build.optimizer(parse_scene(adam), 50) is build.optimizer(parse_scene(adam), 50)
    assert build.optimizer(parse_scene(adam), 60) is not build.optimizer(parse_scene(adam), 50)


def test_stall_on_failure_reaches_the_controller():
    for flag, expected in ((True, 20), (False, 10)):
        spec = parse_scene({"refinement": {"K0": 10, "stall_on_failure": flag}})
        controller = build.controller(spec)
        state = controller.update(controller.init(), 1.0)  # the first step is exempt
        assert int(controller.update(state, 0.5, failed=True).iterations) == expected


def _refinement_step(controller, values):
    """The first update after which ``controller`` has refined (None: never)."""
    state = controller.init()
    for step, value in enumerate(values, 1):
        state = controller.update(state, value)
        if int(state.refinements):
            return step
    return None


INVERSE = {"inverse": {"truth": "x"}}


@pytest.mark.parametrize("table, window", [
    (INVERSE, 2),                                                    # L-BFGS watching its loss
    ({**INVERSE, "optimizer": {"name": "newton_cg"}}, 2),
    ({**INVERSE, "optimizer": {"name": "gauss_newton"}}, 2),
    ({**INVERSE, "refinement": {"monitor": "gradient"}}, 6),         # not monotone
    ({**INVERSE, "refinement": {"monitor": "validation"}}, 6),
    ({**INVERSE, "optimizer": {"name": "adam"}}, 6),                 # no line search
    ({**INVERSE, "optimizer": {"name": "hig"}}, 6),
    ({**INVERSE, "refinement": {"ema_window": 6}}, 6),               # given: kept
    ({**INVERSE, "optimizer": {"name": "adam"}, "refinement": {"ema_window": 2}}, 2),
    ({}, 6),                                                         # a forward study
])
def test_ema_window_default_follows_the_monitored_signal(table, window):
    """An inversion's loss under a line-search optimiser falls monotonically between
    refinements: the moving average defaults to a window of 2 there, to the reference's 6
    elsewhere; the built controller uses it (a window of 2 calls the stall sooner)."""
    scene = parse_scene(table)
    assert scene.refinement.ema_window == window
    plateau = [1.0, 0.5, 0.25, 0.125] + [0.125] * 20
    built = _refinement_step(build.controller(scene), plateau)
    spec = scene.refinement
    reference = _refinement_step(pf.inverse.prdp(spec.K0, spec.dK, restart=spec.restart,
                                              ema_window=window), plateau)
    assert built == reference
    assert (built, _refinement_step(pf.inverse.prdp(spec.K0, spec.dK, restart=spec.restart),
                                    plateau)) == ((10, 19) if window == 2 else (19, 19))


def test_ema_window_default_per_study_run():
    """Each run resolves its own default: mother's loss-monitored PRDP runs take 2, its
    gradient-monitored run 6, and every run of a learned study 6 (its controller watches a
    validation misfit epoch by epoch, whatever the optimiser). Other kinds have no window."""
    mother = dict(load_scene("mother").runs())
    assert mother["prdp"].refinement.ema_window == 2
    assert mother["prdp K_adj0=20"].refinement.ema_window == 2
    assert mother["prdp monitor=gradient"].refinement.ema_window == 6
    learned = load_scene(ROOT / "examples" / "scenes" / "learned.toml").runs()
    assert {run.optimizer.name for _, run in learned} >= {"adam", "lbfgs", "newton_cg"}
    assert {run.refinement.ema_window for _, run in learned
            if run.refinement.kind == "prdp"} == {6}
    heat = load_scene(ROOT / "examples" / "scenes" / "heat.toml").runs()
    assert {run.refinement.ema_window for _, run in heat if run.refinement.kind == "prdp"} == {6}
    assert not any(hasattr(run.refinement, "ema_window") for _, run in heat
                   if run.refinement.kind != "prdp")


def test_runs_merge_sections_and_replace_refinement():
    scene = parse_scene({
        "mesh": {"generator": "unit_square", "n": 16, "cell": "quad"},
        "pde": {"element": "Q1"},
        "inverse": {"truth": "x"},
        "refinement": {"kind": "prdp", "K0": 7},
        "study": {"runs": [{"name": "coarse", "mesh": {"n": 4}},
                           {"name": "fixed", "refinement": {"kind": "fixed", "K": 3}}]}})
    (_, coarse), (_, fixed) = scene.runs()
    assert (coarse.mesh.n, coarse.mesh.cell, coarse.refinement.K0) == (4, "quad", 7)
    assert (fixed.refinement.kind, fixed.refinement.K, fixed.mesh.n) == ("fixed", 3, 16)


def test_inverse_scene_without_runs_adds_the_converged_baseline():
    scene = parse_scene({"inverse": {"truth": "x"}, "refinement": {"kind": "fixed", "K": 4}},
                        default_name="mine")
    names = [(n, s.refinement.kind) for n, s in scene.runs()]
    assert names == [("converged", "converged"), ("mine", "fixed")]


def test_fingerprint_follows_settings_not_names():
    scene = parse_scene({"name": "a", "description": "x", "mesh": {"n": 4}})
    renamed = parse_scene({"name": "b", "description": "y", "mesh": {"n": 4}})
    assert scene.fingerprint == renamed.fingerprint
    assert with_overrides(scene, {"mesh": {"n": 5}}).fingerprint != scene.fingerprint


def _table_only_fingerprint(scene) -> str:
    """The fingerprint as it was before the window's default changed: table and directory."""
    import hashlib
    table = json.loads(scene.raw)
    for key in ("name", "description"):
        table.pop(key, None)
    text = json.dumps([table, scene.directory], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def test_a_study_begun_under_the_old_window_does_not_resume_into_the_new_one(tmp_path):
    """Runs whose unset window became 2 change the fingerprint (a study directory written
    before, its finished runs with 6, is refused on --resume); studies whose runs all keep
    the reference's 6 keep theirs and resume."""
    changed = load_scene("plate_hole")             # L-BFGS watching its loss: now 2
    assert changed.fingerprint != _table_only_fingerprint(changed)
    for kept in (load_scene("poisson_h"),          # an h-study: no inversion
                 parse_scene({**INVERSE, "refinement": {"monitor": "gradient"}}),
                 parse_scene({**INVERSE, "refinement": {"ema_window": 2}}),  # spelled
                 parse_scene({**INVERSE, "optimizer": {"name": "adam"}})):
        assert kept.fingerprint == _table_only_fingerprint(kept)
    # the study refuses a directory whose manifest has the old fingerprint
    from prdp_fem.studies import runner as study
    small = parse_scene({**INVERSE, "mesh": {"n": 4}, "optimizer": {"steps": 1},
                         "refinement": {"K0": 2, "dK": 2}})
    out = tmp_path / "study"
    out.mkdir()
    manifest = study._manifest(small)
    (out / "study.json").write_text(json.dumps(
        {**manifest, "fingerprint": _table_only_fingerprint(small)}))
    with pytest.raises(study.StudyError, match="fingerprint"):
        study.run_study(small, out, resume=True)


def test_a_refinement_spec_built_by_hand_gets_the_default_window():
    """``build.controller`` resolves a window left unset outside ``parse_scene``."""
    import dataclasses
    scene = parse_scene(INVERSE)
    by_hand = dataclasses.replace(scene, refinement=dataclasses.replace(
        scene.refinement, ema_window=None))
    plateau = [1.0, 0.5, 0.25, 0.125] + [0.125] * 20
    assert _refinement_step(build.controller(by_hand), plateau) == \
        _refinement_step(build.controller(scene), plateau) == 10


# -- errors ------------------------------------------------------------------------------


@pytest.mark.parametrize(("text", "message"), [
    ("colour = 1", "unknown key 'colour'"),
    ("[pde]\nelemnt = 'P1'", "unknown key 'pde.elemnt'; allowed in [pde]: ["),
    ("[pde]\nelement = 'P7'", "pde.element = 'P7': expected one of ['P1', 'P2', 'Q1', 'Q2']"),
    ("[mesh]\nn = 0", "mesh.n = 0: expected an integer >= 1"),
    ("[mesh]\nn = 2.5", "mesh.n = 2.5: expected an integer >= 1"),
    ("[mesh]\nfile = 'a.msh'\ngenerator = 'unit_square'", "both given"),
    ("[pde]\nsource = 'sin(q)'", "unknown name 'q'"),
    ("[pde]\nsource = '__import__(\"os\")'", "only the functions"),
    ("[pde]\nsource = 'x.real'", "Attribute is not allowed"),
    ("[pde]\nsource = 'sin(x'", "not a formula"),
    ("[pde]\nsource = 'abc'", "unknown name 'abc'"),
    ("[pde]\nsource = true", "expected a number or a formula"),
    ("[inverse]\nunknown = 'source'", "needs 'truth' (synthetic data) or 'data'"),
    ("[inverse]\ntruth = 'x'\nobservations = 'boundary'", "inverse.boundaries"),
    ("[inverse]\ntruth = 'x'\nnoise = -1", "inverse.noise = -1: expected a finite number"),
    ("[refinement]\nkind = 'fixed'\nK0 = 3", "unknown key 'refinement.K0'"),
    ("[refinement]\nK0 = 700", "refinement.K0 = 700 exceeds K_max = 600"),
    ("[refinement]\nmonitor = 'misfit'", "refinement.monitor = 'misfit'"),
    ("[refinement]\nstall_on_failure = 1", "refinement.stall_on_failure = 1"),
    ("[optimizer]\nname = 'newton'", "optimizer.name = 'newton'"),
    ("[optimizer]\nfirst_step = 'half'", "optimizer.first_step = 'half'"),
    ("[optimizer]\nname = 'adam'\nfirst_step = 'polyak'", "a first step only for 'lbfgs'"),
    ("[study]\nkind = 'inverse'", "needs an [inverse] section"),
    ("[study]\nlevels = [8, 4]", "study.levels = [8, 4]: expected an increasing list"),
    ("[[study.runs]]\nname = 'a'\nsolver = {gradient = 'magic'}", "solver.gradient = 'magic'"),
    ("[solver]\nrebuild_every = 5", "solver.rebuild_every = 5: expected no value unless "
     "solver.preconditioner = 'amg' (it is 'jacobi')"),
    ("[solver]\npreconditioner = 'amg'\nrebuild_every = -1",
     "solver.rebuild_every = -1: expected an integer >= 0"),
    ("[solver]\npreconditioner = 'amg'\nrebuild_factor = 1",
     "solver.rebuild_factor = 1: expected 0 (never) or a finite number > 1"),
    ("[solver]\npreconditioner = 'amg'\namg_kind = 'ml'", "solver.amg_kind = 'ml': expected one "
     "of ['sa', 'rs']"),
    ("[inverse]\nunknown = 'source'\n[learned]\n[solver]\npreconditioner = 'amg'\n"
     "rebuild_factor = 2", "solver.rebuild_every / rebuild_factor with study.kind = 'learned'"),
    ("[solver]\npreconditioner = 'amg'\nrebuild_every = 5",
     "solver.rebuild_every / rebuild_factor with study.kind = 'forward': expected 0"),
    ("[solver]\npreconditioner = 'amg'\nrebuild_factor = 3\n[study]\nkind = 'h'",
     "solver.rebuild_every / rebuild_factor with study.kind = 'h': expected 0"),
    ("[[study.runs]]\nname = 'a'\n[[study.runs]]\nname = 'a'", "must be unique"),
    ("[[study.runs]]\nname = 'a'\ncolour = 1", "unknown key 'study.runs[0].colour'"),
    ("[study]\nreference = 'nope'\n[[study.runs]]\nname = 'a'", "expected one of the run names"),
    ("mesh = 3", "mesh = 3: expected a [mesh] table"),
    ("[inverse]\nunknown = 'source'\n[learned]\ncolour = 1", "unknown key 'learned.colour'"),
    ("[inverse]\nunknown = 'source'\n[learned]\nsamples = 4\nbatch_size = 8",
     "learned.batch_size = 8: expected an integer from 1 to learned.samples = 4"),
    ("[inverse]\nunknown = 'source'\n[learned]\nhidden = [0]",
     "learned.hidden = [0]: expected a list of hidden layer sizes"),
    ("[inverse]\nunknown = 'source'\n[learned]\nnoise = -0.1",
     "learned.noise = -0.1: expected a finite number >= 0"),
    ("[inverse]\nunknown = 'log_kappa'\n[learned]\n", "inverse.unknown = 'log_kappa': "
     "expected 'source' for a learned inverse"),
    ("[inverse]\nunknown = 'source'\n[learned]\nsamples = 8\nbatch_size = 4\n"
     "[optimizer]\nname = 'lbfgs'", "expected a full batch"),
    ("[learned]\nsamples = 4", "study.kind = 'learned' needs an [inverse] section"),
    ("[inverse]\ntruth = 'x'\n[learned]\n[study]\nkind = 'inverse'",
     "a [learned] section with study.kind = 'inverse'"),
    ("[inverse]\nunknown = 'source'\n[learned]\n[[study.runs]]\nname = 'a'\n"
     "learned = {epochs = 0}", "learned.epochs = 0: expected an integer >= 1"),
])
def test_bad_scene_names_file_key_and_expectation(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(SceneError, match=None) as info:
        load_scene(path)
    assert str(path) in str(info.value)
    assert message in str(info.value)


def test_bad_toml_and_missing_file(tmp_path):
    with pytest.raises(SceneError, match="not valid TOML"):
        load_scene(write(tmp_path, "[mesh\nn = 3"))
    with pytest.raises(SceneError, match="scene file does not exist"):
        load_scene(tmp_path / "nope.toml")
    with pytest.raises(SceneError, match=r"expected a \.toml file or a built-in scene"):
        load_scene("torus")


def test_a_directory_named_like_a_builtin_scene_does_not_hide_it(tmp_path, monkeypatch):
    """``prdp-fem study mother --out mother`` leaves a directory ``mother`` behind: the next
    ``prdp-fem evaluate mother`` still means the built-in scene."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mother").mkdir()
    assert load_scene("mother").fingerprint == load_scene(builtin_scene_path("mother")).fingerprint
    (tmp_path / "torus").mkdir()
    with pytest.raises(SceneError, match="torus"):  # not a built-in name: the path is meant
        load_scene("torus")


def test_relative_mesh_file_resolves_against_the_scene(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "m.msh").write_bytes((ROOT / "meshes" / "square_tri.msh").read_bytes())
    scene = load_scene(write(tmp_path, "[mesh]\nfile = 'sub/m.msh'"))
    assert scene.mesh_path() == tmp_path / "sub" / "m.msh"
    assert build.build_mesh(scene).p.shape[1] > 10
    missing = load_scene(write(tmp_path, "[mesh]\nfile = 'gone.msh'", "b.toml"))
    with pytest.raises(pf.MeshFileError, match=r"gone\.msh: file does not exist"):
        build.build_mesh(missing)


def test_non_positive_kappa_is_caught_at_build():
    scene = parse_scene({"mesh": {"n": 4}, "pde": {"kappa": "x - 0.5"}}, source="k.toml")
    with pytest.raises(pf.PrdpFemError, match=r"k.toml: pde.kappa = 'x - 0.5': expected values "
                       r"> 0 on the mesh"):
        build.forward_solve(scene)
    # positive at every cell centre (P0), not at every quadrature point, where it is evaluated
    between = parse_scene({"mesh": {"n": 4}, "pde": {"kappa": "x - 0.05"}}, source="k.toml")
    with pytest.raises(pf.scene.spec.SceneCoefficientError,
                       match=r"k.toml: pde.kappa\(x\) is <= 0 at 8 quadrature point\(s\)"):
        build.forward_solve(between)


def test_non_finite_formula_values_are_caught():
    scene = parse_scene({"mesh": {"n": 4}, "pde": {"source": "log(x - 0.5)"}}, source="s.toml")
    with pytest.raises(ExpressionError, match=r"s.toml: pde.source = 'log\(x - 0.5\)': non-finite"):
        build.forward_solve(scene)


def test_expressions_evaluate_like_numpy():
    x = np.random.default_rng(0).random((2, 7))
    f = compile_field("where(x > 0.5, exp(-y), hypot(x, y)) + pi", where="t")
    expected = np.where(x[0] > 0.5, np.exp(-x[1]), np.hypot(x[0], x[1])) + np.pi
    np.testing.assert_allclose(f(x), expected, rtol=1e-15)
    np.testing.assert_array_equal(compile_field(3, where="t")(x), np.full(7, 3.0))
    with pytest.raises(ExpressionError, match="unknown name 'z'"):
        compile_field("z", where="t", dim=2)


# -- building only what the scene uses ---------------------------------------------------


@pytest.fixture
def no_amg(monkeypatch):
    """pyamg's hierarchy setup (used by every reference solve) raises if called."""
    import pyamg

    def forbidden(*args, **kwargs):
        raise AssertionError("an AMG hierarchy was built")

    monkeypatch.setattr(pyamg, "smoothed_aggregation_solver", forbidden)


def test_forward_solve_builds_no_mass_matrix_or_amg_reference(no_amg):
    scene = parse_scene({"mesh": {"n": 12}, "pde": {"kappa": "1 + x", "source": "sin(pi*y)"}})
    result = build.forward_solve(scene)
    disc = result.disc
    for lazy in ("mass_matrix", "source_matrix", "system", "laplace_matrix"):
        assert lazy not in disc.__dict__, lazy
    assert np.isnan(result.relative_error)  # no reference solve asked for, none run
    # and the solve is right: the direct solve of the same (exact-load) system
    kappa = disc.interpolate_kappa(lambda x: 1 + x[0])
    b = disc.rhs(kappa) + disc.load_vector(lambda x: np.sin(np.pi * x[1]))
    reference = pf.direct_solve(disc.stiffness_matrix(kappa), b).x
    np.testing.assert_allclose(result.u[disc.free_dofs], reference, rtol=1e-8, atol=1e-12)


@pytest.fixture
def no_kappa_map(monkeypatch):
    """Building the map kappa -> A (Discretization.system, stiffness_matrix) raises."""
    from prdp_fem.fem import discretization

    def forbidden(*args, **kwargs):
        raise AssertionError("the map kappa -> A was built")

    monkeypatch.setattr(discretization, "_assembly_maps", forbidden)


def test_scenes_with_a_fixed_kappa_build_no_kappa_map(no_kappa_map):
    """Source inversions (data synthetic from the truth, or given), learned inverses, the heat
    problem and forward solves never change kappa: they assemble at it and never build G
    (an inversion reads only its problem). Forward and h-studies: test_study's forward and
    built-in h-study tests run under the same guard."""
    from prdp_fem.learning import heat_problem, learned_inverse

    source = {"mesh": {"n": 6}, "pde": {"kappa": "1 + x"},
              "inverse": {"truth": "sin(pi*x)*sin(pi*y)", "alpha": 1e-4,
                          "observations": "sensors", "sensors": 12}}
    for inverse in (source["inverse"], {"data": "x*y", "alpha": 1e-4}):
        setup = build.build_inverse(parse_scene({**source, "inverse": inverse}))
        assert setup.problem.system.n_kappa == 1
    disc = pf.discretize(pf.unit_square(4))
    learned = learned_inverse(disc, pf.full_field(disc, data=np.zeros(disc.n_dofs)),
                              kappa=2.0)
    assert learned.system.n_kappa == 1
    heat_problem(disc, 0.1, kappa=2.0, source=np.ones(disc.n_dofs))
    scene = parse_scene({"mesh": {"n": 8}, "pde": {"kappa": "1 + x"}})
    assert np.isfinite(build.forward_solve(scene).u).all()


def test_forward_solve_reference_uses_pyamg_only_when_asked():
    scene = parse_scene({"mesh": {"n": 12}, "solver": {"iterations": [3]}})
    truncated = build.forward_solve(scene, reference=True)
    assert int(truncated.solution.iterations) == 3
    assert 1e-3 < truncated.relative_error < 1


@pytest.mark.slow  # test_study's inverse study of Jacobi runs checks it builds no AMG
def test_inverse_study_with_jacobi_builds_no_amg(no_amg, tmp_path):
    from prdp_fem.studies import run_study

    scene = parse_scene({
        "mesh": {"n": 6}, "inverse": {"truth": "sin(pi*x)*sin(pi*y)", "alpha": 1e-4},
        "refinement": {"kind": "fixed", "K": 4}, "optimizer": {"steps": 3}})
    result = run_study(scene, tmp_path / "s")
    assert [row["run"] for row in result.summary] == ["converged", "scene"]


def test_an_amg_scene_solves_forward_and_rebuilds_during_an_inversion(tmp_path):
    from prdp_fem.studies import run_study
    from prdp_fem.studies.runner import ResultsLog

    table = {"mesh": {"n": 8},
             "inverse": {"unknown": "log_kappa", "truth": "0.5*sin(pi*x)*y", "alpha": 1e-6},
             "solver": {"preconditioner": "amg", "rebuild_every": 2},
             "refinement": {"kind": "fixed", "K": 4},
             "optimizer": {"name": "adam", "learning_rate": 0.1, "steps": 5}}
    # a forward solve with the hierarchy of its operator: converged, it is Jacobi's solution
    amg, jacobi = (build.forward_solve(parse_scene({**table, "mesh": {"n": 16},
                                                    "solver": solver}))
                   for solver in ({"preconditioner": "amg", "rtol": 1e-12}, {"rtol": 1e-12}))
    np.testing.assert_allclose(amg.u, jacobi.u, rtol=1e-9, atol=1e-12)
    assert int(amg.solution.iterations) < int(jacobi.solution.iterations)
    # a study's run rebuilds every 2 steps; a run that switches rebuilding off keeps the
    # hierarchy it starts with (the two share one compiled step: the cycle is an argument)
    scene = parse_scene({**table, "study": {"reference": "rebuilt", "runs": [
        {"name": "rebuilt"}, {"name": "kept", "solver": {"rebuild_every": 0}}]}})
    run_study(scene, tmp_path / "s")
    steps = [r for r in ResultsLog(tmp_path / "s" / "results.jsonl").records()
             if r["type"] == "step"]
    assert [r["rebuilds"] for r in steps if r["run"] == "rebuilt"] == [0, 0, 1, 1, 2]
    assert [r["rebuilds"] for r in steps if r["run"] == "kept"] == [0] * 5
    # a run that leaves the AMG leaves its settings (setting them with Jacobi is refused)
    jacobi = parse_scene({**table, "study": {"runs": [
        {"name": "jacobi", "solver": {"preconditioner": "jacobi"}}]}})
    solver = dict(jacobi.runs())["jacobi"].solver
    assert (solver.preconditioner, solver.rebuild_every) == ("jacobi", 0)
    with pytest.raises(SceneError, match=r"solver\.rebuild_every = 3: expected no value unless"):
        parse_scene({**table, "study": {"runs": [
            {"name": "j", "solver": {"preconditioner": "jacobi", "rebuild_every": 3}}]}})


def test_mesh_scene_is_the_default_problem_on_a_file():
    scene = mesh_scene(ROOT / "meshes" / "plate_hole.msh")
    result = build.forward_solve(scene)
    assert scene.pde.source == 1.0 and scene.pde.dirichlet == 0.0
    u = result.u
    assert u.min() >= -1e-12 and u.max() > 0  # -lap u = 1 >= 0 with u = 0: u >= 0
    assert json.loads(scene.raw)["mesh"]["file"].endswith("plate_hole.msh")


def test_observing_only_dirichlet_dofs_is_refused():
    scene = parse_scene({"mesh": {"n": 4}, "inverse": {
        "truth": "x", "observations": "boundary", "boundaries": ["left"]}}, source="o.toml")
    with pytest.raises(pf.PrdpFemError, match="every observed dof carries Dirichlet data"):
        build.build_inverse(scene)
    natural = parse_scene({"mesh": {"n": 4}, "pde": {"dirichlet": {"right": 0.0}}, "inverse": {
        "truth": "x", "observations": "boundary", "boundaries": ["left"]}})
    setup = build.build_inverse(natural)
    assert setup.problem.observation.operator.shape[0] == 5  # the 5 nodes of the left side


def test_learned_scene_reads_its_table_and_runs_merge_it():
    scene = load_scene(ROOT / "examples" / "scenes" / "learned.toml")
    assert scene.study.kind == "learned" and scene.learned.hidden == (8,)
    runs = dict(scene.runs())
    assert runs["converged"].refinement.kind == "converged"
    assert runs["prdp"].learned.batch_size == 8 < runs["lbfgs prdp"].learned.batch_size == 32
    assert runs["lbfgs prdp"].learned.samples == 32 and runs["lbfgs prdp"].learned.epochs == 30
    assert runs["hig prdp"].optimizer.name == "hig" and runs["hig prdp"].study.kind == "learned"


def test_a_scene_pins_its_state_at_a_vertex():
    """pde.pins: a pure Neumann scene (dirichlet = {}) pinned at the centre solves forward;
    a malformed list or a point that is no vertex is an error naming the key."""
    table = {"mesh": {"n": 4}, "pde": {
        "source": 0.0, "dirichlet": {}, "pins": [[0.5, 0.5, 1.5]],
        "neumann": {side: "(x - 0.5)*y*(y - 1)" for side in ("left", "right", "bottom", "top")}}}
    result = build.forward_solve(parse_scene(table, source="p.toml"), reference=True)
    centre = int(result.disc.dirichlet_dofs[0])
    assert result.u[centre] == 1.5 and result.relative_error < 1e-8
    bad = {**table, "pde": {**table["pde"], "pins": [[0.5, 0.5]]}}
    with pytest.raises(pf.SceneError, match=r"p.toml: pde.pins"):
        parse_scene(bad, source="p.toml")
    off = {**table, "pde": {**table["pde"], "pins": [[0.55, 0.5, 0.0]]}}
    with pytest.raises(pf.SceneError, match=r"pins\[0\]: point \[0.55, 0.5\] is not a node"):
        build.forward_solve(parse_scene(off, source="p.toml"))
