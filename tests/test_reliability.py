"""One writer per output directory, outputs inside the directory the user chose, shapes
checked at the system's entry (issue: reliability)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SMALL_STUDY

import prdp_fem as pf
from prdp_fem._atomic import atomic_path
from prdp_fem._lock import directory_lock
from prdp_fem.errors import OutputLockedError, SceneError, ShapeError
from prdp_fem.scene import parse_scene

ROOT = Path(__file__).resolve().parent.parent


def cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-c", "from prdp_fem.cli.main import run; run()",
                           *map(str, args)], capture_output=True, text=True, timeout=300,
                          cwd=cwd, env={**os.environ, "PYTHONPATH": str(ROOT)})


def test_a_second_writer_is_refused_with_the_holders_pid(tmp_path, capsys):
    """This process holds the directory; a study in another process exits 2 at once, in one
    line naming the directory and this pid, and writes nothing there. (flock locks belong to
    open files, not processes: the same command run in this process is refused alike.)"""
    from prdp_fem.cli.main import main
    scene = tmp_path / "small.toml"  # a one-solve forward study: the lock is the same for all
    scene.write_text('name = "small"\n[mesh]\nn = 4\n[solver]\niterations = [1]\n')
    out = tmp_path / "out"
    out.mkdir()
    # a bench prdp run to resume there, with the options the command below gives
    (out / "bench.json").write_text(json.dumps({"scene": ["mother"], "steps": None,
                                                "repeats": 1, "seeds": None}))
    with directory_lock(out):
        done = cli("study", scene, "--out", out)
        assert done.returncode == 2, done.stderr
        assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
        assert f"(pid {os.getpid()})" in done.stderr and str(out) in done.stderr
        for args in (("study", scene, "--out", out, "--resume"),
                     ("bench", "prdp", "--scene", "mother", "--out", out, "--resume")):
            assert main([str(a) for a in args]) == 2
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and f"(pid {os.getpid()})" in err, err
        assert sorted(p.name for p in out.iterdir()) == [".prdp-fem.lock", "bench.json"]
    (out / "bench.json").unlink()
    # released with the block (and by the kernel when a holder dies): the study runs now
    assert main(["study", str(scene), "--out", str(out)]) == 0
    assert (out / "summary.csv").exists()


def test_the_lock_is_released_when_its_holder_is_killed(tmp_path):
    # the lock's module alone: a bare package, not the __init__ that imports JAX (seconds)
    package = str(ROOT / "prdp_fem")
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time, types\n"
         "sys.modules['prdp_fem'] = types.ModuleType('prdp_fem')\n"
         f"sys.modules['prdp_fem'].__path__ = [{package!r}]\n"
         "from prdp_fem._lock import directory_lock\n"
         f"with directory_lock({str(tmp_path)!r}):\n print('held', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(OutputLockedError, match=f"pid {holder.pid}"), \
                directory_lock(tmp_path):
            pass
    finally:
        holder.kill()
        holder.wait()
    with directory_lock(tmp_path):  # kill -9 left no stale lock
        pass


def test_temporary_files_are_unique_per_writer(tmp_path):
    target = tmp_path / "summary.csv"
    with atomic_path(target) as first, atomic_path(target) as second:
        assert first != second and first.parent == second.parent == tmp_path
        first.write_text("a")
        second.write_text("b")
    assert target.read_text() == "a" and sorted(p.name for p in tmp_path.iterdir()) == [
        "summary.csv"]


@pytest.mark.parametrize("name", ["../../../x", "a/b", "..", ".", "a\\b", "x\0y"])
def test_a_scene_name_cannot_leave_the_working_directory(name):
    with pytest.raises(SceneError, match=r"name = .*usable as a file name"):
        parse_scene({"name": name})


def test_the_cli_writes_nothing_outside_for_an_escaping_name(tmp_path, monkeypatch, capsys):
    from prdp_fem.cli.main import main

    work = tmp_path / "deep" / "work"
    work.mkdir(parents=True)
    (work / "evil.toml").write_text('name = "../../escaped"\n[mesh]\nn = 4\n')
    monkeypatch.chdir(work)  # the command's main in this process, as run from there
    for command in ("invert", "solve"):
        assert main([command, "evil.toml"]) == 2
        assert "usable as a file name" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["deep", "evil.toml", "work"]


@pytest.mark.parametrize("frozen", [False, True])
def test_rhs_refuses_a_source_of_the_wrong_length(small_problem, frozen):
    disc, kappa, f = small_problem
    system = disc.system_at(kappa) if frozen else disc.system
    k = jnp.ones(1) if frozen else jnp.asarray(kappa)
    for bad in (f[:-1], np.concatenate([f, [0.0]]), np.ones((2, f.size))):
        with pytest.raises(ShapeError, match=rf"f: a nodal source of {f.size} values"):
            system.rhs(k, bad)
        with pytest.raises(ShapeError):  # under jit too: the shape is static
            jax.jit(system.rhs)(k, jnp.asarray(bad))
    # the right length still gives the host assembly's right-hand side
    np.testing.assert_allclose(system.rhs(k, f), disc.rhs(kappa, f), rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------------------
# no tracebacks: formulas bounded at the parser, one line for anything unexpected
# --------------------------------------------------------------------------------------


def test_formula_depth_is_bounded_exactly_at_the_documented_limit():
    import numpy as np

    from prdp_fem.scene.expressions import MAX_FORMULA_DEPTH, FormulaTooLargeError, compile_field

    deepest = "+" * MAX_FORMULA_DEPTH + "x"
    assert compile_field(deepest, where="t: f")(np.full((2, 3), 2.0)).tolist() == [2.0] * 3
    terms = "+".join(["x"] * (MAX_FORMULA_DEPTH + 1))  # a sum nests one level per '+'
    assert compile_field(terms, where="t: f")(np.ones((2, 1))).tolist() == [201.0]
    for text in ("+" * (MAX_FORMULA_DEPTH + 1) + "x", terms + "+x"):
        with pytest.raises(FormulaTooLargeError, match=r"t: f = .*: nested more than 200 "
                           "levels deep"):
            compile_field(text, where="t: f")


@pytest.mark.parametrize(("text", "found"), [
    ("+".join(["x"] * 200_000), "399999 characters"),  # RecursionError in the parser before
    ("+" * 100_000 + "x", "100001 characters"),        # MemoryError in the parser before
    ("+" * 9_000 + "x", "nested too deeply for the parser"),
    ("(" * 300 + "x" + ")" * 300, "too many nested parentheses")])
def test_huge_formulas_raise_a_typed_error_not_recursion_or_memory(text, found):
    from prdp_fem.errors import ResourceLimitError
    from prdp_fem.scene.expressions import ExpressionError

    with pytest.raises(ResourceLimitError) as caught:
        parse_scene({"pde": {"source": text}}, source="s.toml")
    assert isinstance(caught.value, SceneError | ExpressionError)
    message = str(caught.value)
    assert message.startswith("s.toml: pde.source = ") and found in message
    assert len(message) < 400  # the formula is quoted by its ends, not whole


def test_an_unexpected_error_is_one_line_exit_2_and_debug_shows_it(monkeypatch, capsys):
    from prdp_fem.cli import main as cli

    def broken(args):
        raise RecursionError("maximum recursion depth exceeded\nsecond line")

    monkeypatch.setitem(cli.COMMANDS, "scenes", broken)
    assert cli.main(["scenes"]) == 2
    err = capsys.readouterr().err
    assert err == ("prdp-fem: internal error: RecursionError: maximum recursion depth exceeded "
                   "| second line; rerun with --debug for the traceback\n")
    for argv in (["--debug", "scenes"], ["scenes", "--debug"]):
        with pytest.raises(RecursionError):
            cli.main(argv)
    monkeypatch.setitem(cli.COMMANDS, "scenes", lambda args: (_ for _ in ()).throw(
        SceneError("a.toml: mesh.n = 0: expected an integer >= 1")))
    assert cli.main(["scenes"]) == 2
    assert capsys.readouterr().err == ("prdp-fem: error: a.toml: mesh.n = 0: expected an "
                                       "integer >= 1\n")
    with pytest.raises(SceneError):
        cli.main(["--debug", "scenes"])


# --------------------------------------------------------------------------------------
# resource limits: a mesh file's refinements, estimated on the file before refining
# --------------------------------------------------------------------------------------


def test_a_mesh_files_refinement_is_estimated_on_the_file_before_refining(tmp_path,
                                                                         monkeypatch):
    import prdp_fem as pf
    from prdp_fem.errors import ResourceLimitError
    from prdp_fem.scene import load_scene
    from prdp_fem.scene.build import build_mesh
    from prdp_fem.scene.spec import max_dofs

    pf.save_mesh(pf.unit_square(2), tmp_path / "m.msh")  # 9 vertices
    (tmp_path / "s.toml").write_text('[mesh]\nfile = "m.msh"\nrefine = 4\n')
    monkeypatch.setenv("PRDP_FEM_MAX_DOFS", "1000")
    assert max_dofs() == 1000
    scene = load_scene(tmp_path / "s.toml")  # one cell refined 4 times: 153 vertices, fine
    with pytest.raises(ResourceLimitError, match=r"s\.toml: mesh\.refine = 4: the 9-vertex "
                       r"mesh m\.msh refined 4 times would carry about 2\.3e\+03 degrees of "
                       r"freedom; expected at most 1000"):
        build_mesh(scene)
    monkeypatch.setenv("PRDP_FEM_MAX_DOFS", "3000")
    assert build_mesh(scene).nvertices == 33 ** 2  # refined as asked under the limit
    monkeypatch.setenv("PRDP_FEM_MAX_DOFS", "lots")
    with pytest.raises(SceneError, match="PRDP_FEM_MAX_DOFS='lots': expected a positive"):
        max_dofs()


def test_second_order_elements_count_in_the_estimate(monkeypatch):
    from prdp_fem.scene.spec import SceneResourceLimitError

    monkeypatch.setenv("PRDP_FEM_MAX_DOFS", "500")
    parse_scene({"mesh": {"n": 20}})  # 441 vertices, P1
    with pytest.raises(SceneResourceLimitError, match=r"mesh\.n = 20: .*about 1\.76e\+03"):
        parse_scene({"mesh": {"n": 20}, "pde": {"element": "P2"}})
    with pytest.raises(SceneResourceLimitError, match=r"\(run 'fine'\): mesh\.n = 40"):
        parse_scene({"mesh": {"n": 8}, "inverse": {"truth": 1.0},
                     "study": {"runs": [{"name": "fine", "mesh": {"n": 40}}]}})


# --------------------------------------------------------------------------------------
# the smaller ones: outputs, the pyamg reference, typed errors for odd values
# --------------------------------------------------------------------------------------


def test_a_failed_write_names_the_file_and_leaves_no_temporary(tmp_path):
    import errno

    from prdp_fem.errors import OutputError

    target = tmp_path / "summary.csv"
    with pytest.raises(OutputError, match=rf"^{target}: could not be written \(No space left "
                       r"on device\); expected a writable path"), atomic_path(target) as tmp:
        tmp.write_text("partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp))
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_in_the_results_log_names_it(tmp_path, monkeypatch):
    import builtins
    import errno

    from prdp_fem.errors import OutputError
    from prdp_fem.studies.runner import ResultsLog

    log = ResultsLog(tmp_path / "results.jsonl")
    log.append({"type": "step", "run": "a"})

    class Full:
        def __init__(self, stream):
            self.stream = stream

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.stream.close()

        def tell(self):
            return self.stream.tell()

        def write(self, data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    real_open = builtins.open
    monkeypatch.setattr(builtins, "open", lambda path, mode="r", *a, **k: Full(
        real_open(path, mode, *a, **k)) if mode == "ab" else real_open(path, mode, *a, **k))
    with pytest.raises(OutputError, match=r"results\.jsonl: could not be written \(No space "
                       r"left on device\)"):
        log.append({"type": "step", "run": "b"})


def test_a_failed_pyamg_reference_is_reported_as_such(tmp_path, monkeypatch, capsys):
    import numpy as np

    from prdp_fem.cli import main as cli
    from prdp_fem.fem import ReferenceSolution
    from prdp_fem.scene import build

    (tmp_path / "s.toml").write_text('name = "s"\n[mesh]\nn = 4\n')
    monkeypatch.chdir(tmp_path)
    real = build.amg_solve
    monkeypatch.setattr(build, "amg_solve", lambda A, b, rtol: ReferenceSolution(
        np.zeros_like(b), 500, float(np.linalg.norm(b))))  # pyamg stuck at x = 0
    assert cli.main(["solve", "s.toml", "--reference"]) == 0
    out = capsys.readouterr().out
    assert ("reference: pyamg did not converge (relative residual 1 after 500 iterations; "
            "asked 1e-12, accepted up to 1e-08); no error against it to report") in out
    assert "relative l2 error" not in out
    monkeypatch.setattr(build, "amg_solve", real)
    assert cli.main(["solve", "s.toml", "--reference"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if "relative l2" in x)
    assert float(line.split()[-1]) < 1e-8


def test_a_rejected_scene_leaves_no_output_directory(tmp_path, capsys):
    from prdp_fem.cli import main as cli

    (tmp_path / "bad.toml").write_text(SMALL_STUDY.replace("STEPS", "2").replace(
        "[mesh]", '[pde]\ndirichlet = { nowhere = 0.0 }\n[mesh]'))
    out = tmp_path / "out"
    assert cli.main(["study", str(tmp_path / "bad.toml"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nowhere" in err and "bad.toml" in err
    assert not out.exists()
    out.mkdir()  # an empty directory the user made stays, empty
    assert cli.main(["study", str(tmp_path / "bad.toml"), "--out", str(out)]) == 2
    assert list(out.iterdir()) == []


@pytest.mark.parametrize("bad", [
    np.ones(8) * (1 + 1e-3j), "1.0", np.array(["1.0"] * 8), [None] * 8, [[1.0], [1.0, 2.0]]])
def test_kappa_that_is_not_real_numbers_is_refused_not_truncated(bad):
    import prdp_fem as pf
    from prdp_fem.errors import CoefficientError

    disc = pf.discretize(pf.unit_square(2))
    assert disc.n_kappa == 8
    for entry in (disc.system.operator, disc.check_kappa,
                  lambda k: disc.system.solve(k, None, pf.ConvergedCG())):
        with pytest.raises(CoefficientError, match=r"^kappa: .*expected real numbers"):
            entry(bad)


def test_a_complex_jax_kappa_is_refused_under_jit_too():
    import prdp_fem as pf
    from prdp_fem.errors import CoefficientError

    disc = pf.discretize(pf.unit_square(2))
    with pytest.raises(CoefficientError, match=r"kappa: complex values \(dtype complex64\)"):
        jax.jit(disc.system.operator)(jnp.ones(8, dtype=jnp.complex64))


def test_load_mesh_of_a_number_is_a_typed_error():
    import prdp_fem as pf

    with pytest.raises(pf.MeshFileError, match=r"^42: a int given as the mesh path; expected "
                       "a file path"):
        pf.load_mesh(42)


def test_tracers_where_host_values_are_needed_raise_a_typed_error():
    import prdp_fem as pf
    from prdp_fem.errors import TracerError
    from prdp_fem.fem import full_field
    from prdp_fem.inverse import inverse_problem, invert

    disc = pf.discretize(pf.unit_square(3))
    for method in (disc.interpolate, disc.interpolate_kappa, disc.project):
        with pytest.raises(TracerError, match=r"fn\(x\): a JAX tracer .*expected concrete"):
            jax.jit(lambda c, m=method: m(lambda x: c * x[0]))(2.0)
    obs = full_field(disc, u_true=disc.interpolate(lambda x: x[0] * (1 - x[0])))
    problem = inverse_problem(disc, obs, unknown="source", alpha=1e-6)
    with pytest.raises(TracerError, match=r"^init \(initial source field\): a JAX tracer"):
        jax.jit(lambda z: invert(problem, steps=1, init=z).field)(jnp.zeros(disc.n_dofs))


def test_coordinates_too_large_for_cell_measures_are_named(tmp_path):
    import warnings

    import prdp_fem as pf
    from prdp_fem.mesh.io import MAX_COORDINATE

    points = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    cells = np.array([[0, 1, 2], [0, 2, 3]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow warnings leak out
        with pytest.raises(pf.errors.CoordinateRangeError, match=r"<array mesh>: 3 node\(s\) have "
                           r"coordinates beyond \+-1e\+50 \(first: node 1 at \[1e\+300, "
                           r"0\.0\]\).*rescale the mesh"):
            pf.mesh_from_arrays(points * 1e300, cells, "triangle")
    mesh = pf.mesh_from_arrays(points * MAX_COORDINATE, cells, "triangle")  # at the bound
    assert pf.mesh_quality(mesh).total_measure == pytest.approx(MAX_COORDINATE ** 2)


def test_max_dofs_holds_for_the_command_and_leaves_the_callers_environment(monkeypatch,
                                                                          tmp_path, capsys):
    from prdp_fem.cli.main import main
    monkeypatch.setenv("PRDP_FEM_MAX_DOFS", "777")
    scene = tmp_path / "big.toml"
    scene.write_text("[mesh]\nn = 40\n")  # about 1.7e3 dofs
    assert main(["solve", str(scene), "--max-dofs", "100"]) == 2
    assert "expected at most 100" in capsys.readouterr().err
    assert os.environ["PRDP_FEM_MAX_DOFS"] == "777"
    monkeypatch.delenv("PRDP_FEM_MAX_DOFS")
    assert main(["solve", str(scene), "--max-dofs", "100"]) == 2
    assert "PRDP_FEM_MAX_DOFS" not in os.environ


@pytest.mark.parametrize("method", ["interpolate", "interpolate_kappa"])
def test_a_field_function_of_the_wrong_shape_is_a_shape_error(method):
    disc = pf.discretize(pf.unit_square(4), element="P1", kappa_space="P1", dirichlet=0.0)
    with pytest.raises(ShapeError, match=rf"{method}: fn\(x\): shape \(3,\)"):
        getattr(disc, method)(lambda x: np.ones(3))
    assert getattr(disc, method)(lambda x: 2.0).shape == (25,)
