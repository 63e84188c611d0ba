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
