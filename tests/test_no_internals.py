"""The package uses its dependencies' public API only: no module imports a private module or
name of another package (JAX's or optax's private source package, ``from scipy.x import
_y``) or reads a private attribute of one (``np._core``). Read from the source (ast), so a
reach hidden in a function body or a ``try`` counts too. The examples below spell the
private package's name in pieces, so that no text search of this suite finds a reach."""

import ast
from pathlib import Path

import pytest

SRC = "_" + "src"  # the private source package of jax and optax
PACKAGE = Path(__file__).resolve().parent.parent / "prdp_fem"
SOURCES = sorted(PACKAGE.rglob("*.py"))


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def reaches(source: str) -> list[str]:
    """The private imports and attribute reads into other packages in ``source``."""
    tree = ast.parse(source)
    found, dependency_names = [], set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if any(map(_private, parts[1:])) or _private(parts[0]):
                    found.append(f"import {alias.name}")
                dependency_names.add(alias.asname or parts[0])
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and \
                node.module != "__future__":
            parts = node.module.split(".")
            if any(map(_private, parts)):
                found.append(f"from {node.module} import ...")
            for alias in node.names:
                if _private(alias.name):
                    found.append(f"from {node.module} import {alias.name}")
                else:
                    dependency_names.add(alias.asname or alias.name)
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr):
            root = node.value
            while isinstance(root, ast.Attribute):
                root = root.value
            if isinstance(root, ast.Name) and root.id in dependency_names:
                found.append(ast.unparse(node))
    return found


@pytest.mark.parametrize("path", SOURCES, ids=lambda path: str(path.relative_to(PACKAGE)))
def test_no_module_reaches_into_a_dependency_s_internals(path):
    assert reaches(path.read_text(encoding="utf-8")) == []


@pytest.mark.parametrize("source", [
    f"from jax.{SRC} import compiler",
    f"import optax.{SRC}.linesearch",
    f"import jax.{SRC}.dispatch as dispatch",
    "from scipy.sparse import _sparsetools",
    "import numpy as np\nnp._core.multiarray",
    "import jax\njax.interpreters.mlir._emit",
    f"def f():\n    try:\n        from jax.{SRC}.callback import _IOEffect\n"
    "    except ImportError:\n        pass",
])
def test_the_scan_sees_each_kind_of_reach(source):
    assert reaches(source)


def test_the_scan_leaves_public_names_and_the_package_s_own_private_modules_alone():
    assert reaches("from __future__ import annotations\nimport jax\nfrom . import _zoom\n"
                   "from ._zoom import zoom_linesearch\nimport optax.tree_utils as otu\n"
                   "jax.__version__\nfrom .tally import _tally\n") == []


def private_writes(source: str) -> list[str]:
    """Private attributes written on objects that are not the class's own instance: another
    package's cached state (a scikit-fem mesh's facets, say) set from outside."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store | ast.Del) \
                and _private(node.attr):
            if not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                found.append(ast.unparse(node))
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and \
                node.func.id in ("setattr", "delattr") and len(node.args) >= 2:
            name = node.args[1]
            if not (isinstance(name, ast.Constant) and isinstance(name.value, str)
                    and not _private(name.value)):
                found.append(ast.unparse(node))
    return found


@pytest.mark.parametrize("path", SOURCES, ids=lambda path: str(path.relative_to(PACKAGE)))
def test_no_module_writes_another_object_s_private_state(path):
    assert private_writes(path.read_text(encoding="utf-8")) == []


@pytest.mark.parametrize("source", [
    "mesh._facets = facets", "setattr(mesh, '_t2f', t2f)", "setattr(mesh, name, value)",
    "del mesh._f2t"])
def test_the_write_scan_sees_each_kind_of_write(source):
    assert private_writes(source)
