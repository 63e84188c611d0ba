"""Property: scene and mesh files generated to be malformed never escape as a traceback or an
internal error. ``prdp-fem`` either runs (exit 0) or exits 2 with one line
``prdp-fem: error: ...``."""

import contextlib
import io
import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prdp_fem.cli.main import main

BASE_SCENE = {
    "name": "p",
    "mesh": {"generator": "unit_square", "n": 4},
    "pde": {"element": "P1", "kappa": "1 + x", "source": 1.0, "dirichlet": 0.0},
    "solver": {"preconditioner": "jacobi", "gradient": "implicit"},
    "inverse": {"unknown": "source", "truth": "sin(x)", "observations": "full_field",
                "noise": 0.01, "seed": 1, "alpha": 1e-4, "regularization": "h1"},
    "refinement": {"kind": "prdp", "K0": 5, "dK": 5},
    "optimizer": {"name": "lbfgs", "steps": 3},
}
KEYS = [(section, key) for section, table in BASE_SCENE.items() if isinstance(table, dict)
        for key in table] + [("mesh", "refine"), ("mesh", "file"), ("pde", "neumann"),
                             ("inverse", "sensors"), ("study", "kind"), ("nonsense", "x")]

junk = st.one_of(
    st.integers(-2**63, 2**63 - 1), st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12), st.booleans(), st.lists(st.integers(-5, 5), max_size=3),
    st.sampled_from(["P2", "Q1", "tetra", "log_kappa", "amg", "unrolled", "converged",
                     "sensors", "1/0", "x**1e9", "exp(exp(exp(x)))", "../x", ""]),
    st.dictionaries(st.sampled_from(["left", "a", "", "K"]), st.integers(-3, 3), max_size=2))


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return ("nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")) \
            if not math.isfinite(value) else repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(v)}" for k, v in value.items()) \
        + "}"


def _toml(scene: dict) -> str:
    lines = [f"{key} = {_toml_value(value)}" for key, value in scene.items()
             if not isinstance(value, dict)]
    for section, table in scene.items():
        if isinstance(table, dict):
            lines.append(f"[{section}]")
            lines += [f"{json.dumps(k)} = {_toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


mutation = st.tuples(st.sampled_from(KEYS), st.booleans(), junk)


def _run(argv: list[str]) -> tuple[int, str]:
    """``main(argv)`` in this process: its exit code and what it wrote to stderr."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(argv)
    return code, err.getvalue()


def _assert_one_line_or_success(code: int, err: str) -> None:
    assert code in (0, 2), (code, err)
    if code == 2:
        assert err.count("\n") == 1 and err.startswith("prdp-fem: error: "), err
    assert "Traceback" not in err


# slow: tests/test_bad_input.py checks malformed scenes key by key in the default suite
@pytest.mark.slow
@settings(max_examples=40)
@given(mutations=st.lists(mutation, min_size=1, max_size=3))
def test_a_malformed_scene_is_one_line_and_exit_2(tmp_path_factory, mutations):
    scene = json.loads(json.dumps(BASE_SCENE))
    for (section, key), delete, value in mutations:
        table = scene.setdefault(section, {})
        if delete:
            table.pop(key, None)
        else:
            table[key] = value
    folder = tmp_path_factory.mktemp("scene")
    path = folder / "scene.toml"
    path.write_text(_toml(scene))
    _assert_one_line_or_success(*_run(["solve", str(path), "--max-dofs", "5000", "--out",
                                       str(folder / "u.vtu")]))


MESH = """$MeshFormat
2.2 0 8
$EndMeshFormat
$PhysicalNames
2
1 1 "left"
2 2 "plate"
$EndPhysicalNames
$Nodes
5
1 0 0 0
2 1 0 0
3 1 1 0
4 0 1 0
5 0.5 0.5 0
$EndNodes
$Elements
5
1 1 2 1 1 4 1
2 2 2 2 1 1 2 5
3 2 2 2 1 2 3 5
4 2 2 2 1 3 4 5
5 2 2 2 1 4 1 5
$EndElements
"""
TOKENS = ["nan", "inf", "-1", "0", "7", "99999999999", "1e400", "x", "2.5", "$Nodes", "",
          "1 2", "-0"]


@settings(max_examples=60)
@given(edits=st.lists(st.tuples(st.integers(0, 200), st.integers(0, 10),
                                 st.sampled_from(["token", "drop", "repeat", "cut"]),
                                 st.sampled_from(TOKENS)), min_size=1, max_size=3))
def test_a_malformed_mesh_file_is_one_line_and_exit_2(tmp_path_factory, edits):
    lines = MESH.splitlines()
    for line_at, token_at, action, token in edits:
        i = line_at % len(lines)
        if action == "token":
            words = lines[i].split(" ")
            words[token_at % len(words)] = token
            lines[i] = " ".join(words)
        elif action == "drop" and len(lines) > 1:
            del lines[i]
        elif action == "repeat":
            lines.insert(i, lines[i])
        elif action == "cut":
            lines = lines[:i + 1]
    path = tmp_path_factory.mktemp("mesh") / "m.msh"
    path.write_text("\n".join(lines) + "\n")
    _assert_one_line_or_success(*_run(["mesh-info", str(path)]))
