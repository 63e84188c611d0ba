"""The package's layout: imports run one way between subpackages, and no module imports
another module's private name. Read from the source (ast), so an import inside a function
counts too."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "prdp_fem"
SOURCES = sorted(PACKAGE.rglob("*.py"))
#: Each subpackage may import its own modules and those of the subpackages before it;
#: the top-level modules (errors, the private helpers) are below all of them.
LAYERS = ["mesh", "linalg", "fem", "optim", "inverse", "learning", "scene", "studies", "bench",
          "cli"]


def _module_name(path: Path) -> list[str]:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return parts[:-1] if parts[-1] == "__init__" else parts


def _imports(path: Path) -> list[tuple[list[str], list[str]]]:
    """(the imported module's dotted parts, the names imported from it) of every import of
    the package's own modules in ``path``."""
    here = _module_name(path)
    package = here if path.name == "__init__.py" else here[:-1]
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                target = base + (node.module.split(".") if node.module else [])
            elif node.module and node.module.split(".")[0] == "prdp_fem":
                target = node.module.split(".")
            else:
                continue
            found.append((target, [alias.name for alias in node.names]))
        elif isinstance(node, ast.Import):
            found += [(alias.name.split("."), []) for alias in node.names
                      if alias.name.split(".")[0] == "prdp_fem"]
    return found


def _layer(parts: list[str]) -> int:
    """-1 for the top-level modules, else the subpackage's place in LAYERS."""
    return LAYERS.index(parts[1]) if len(parts) > 1 and parts[1] in LAYERS else -1


def test_every_subpackage_has_a_layer():
    subpackages = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()}
    assert subpackages == set(LAYERS)


@pytest.mark.parametrize("path", SOURCES, ids=lambda path: str(path.relative_to(PACKAGE)))
def test_imports_run_one_way_and_take_no_private_names(path):
    here = _module_name(path)
    for target, names in _imports(path):
        if here == ["prdp_fem"] or here[1:2] == ["__main__"]:
            continue  # the package's own namespace gathers from everywhere
        assert _layer(target) <= _layer(here), f"{'.'.join(here)} imports {'.'.join(target)}"
        private = [n for n in names if n.startswith("_") and n != "__version__"]
        assert not private, f"{'.'.join(here)} imports {private} from {'.'.join(target)}"


def test_the_layer_check_sees_an_upward_import(tmp_path):
    assert _layer(["prdp_fem", "cli", "main"]) > _layer(["prdp_fem", "linalg", "cg"])
    assert _layer(["prdp_fem", "errors"]) < _layer(["prdp_fem", "mesh", "io"])
