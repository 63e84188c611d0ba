"""The documentation for users: a README within its budget, links that resolve, an API
reference that names every public module and a gallery that shows every example. (The
build itself, warnings as errors, is `python -m sphinx -W -b html docs docs/_build/html`,
run by CI.)"""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md"))]


def anchors(page: Path) -> set[str]:
    """GitHub's heading anchors of a Markdown page (outside code blocks)."""
    found, fenced = set(), False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and line.startswith("#"):
            text = re.sub(r"[^\w\- ]", "", line.lstrip("#").strip().lower())
            found.add(text.replace(" ", "-"))
    return found


def test_readme_is_for_users():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 250
    text = "\n".join(lines)
    for paper in ("Bhatia", "List", "Schnell"):  # the three papers the toolkit builds on
        assert paper in text
    assert "pip install -e . && prdp-fem study" in text
    assert "python -m pytest -q -n auto" in text


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_resolve(page):
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+://", target):
            continue
        path, _, anchor = target.partition("#")
        linked = (page.parent / path).resolve() if path else page
        if not linked.exists():
            broken.append(target)
        elif anchor and linked.suffix == ".md" and anchor not in anchors(linked):
            broken.append(target)
    assert not broken, f"{page.name}: {broken}"


def test_readme_scripts_run(monkeypatch, capsys):
    """The README's scripts, as a user pastes them: the Taylor rates print at second order and
    the inversion lowers its loss."""
    import numpy as np

    import prdp_fem as pf

    monkeypatch.chdir(ROOT)
    # the Taylor test the README prints, kept as it runs (not run a second time here)
    taylor_tests, taylor_test = [], pf.taylor_test
    monkeypatch.setattr(pf, "taylor_test", lambda *a, **k: taylor_tests.append(
        taylor_test(*a, **k)) or taylor_tests[-1])
    code = "\n".join(re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(),
                                re.S))
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    [taylor] = taylor_tests
    rates = np.asarray(taylor.rates)
    rates = rates[np.isfinite(rates)]
    assert rates.size and np.all(np.abs(rates - 2.0) < 0.25)
    history = namespace["result"].history
    assert history[-1].loss < history[0].loss


def test_module_docstrings_carry_no_timings_machines_or_dates():
    """Docstrings are for users: figures belong in docs/benchmarks.md and the performance
    log (benchmark modules describe their procedure, and are skipped)."""
    import ast
    import re
    from pathlib import Path

    pattern = re.compile(r"\b\d+(?:\.\d+)?\s?(?:ms|us|µs)\b|\bCPU cores?\b|Xeon|EPYC|H100|H200|"
                         r"\b20\d\d-\d\d-\d\d\b")
    package = Path(__file__).resolve().parent.parent / "prdp_fem"
    found = []
    for path in sorted(package.glob("*.py")):
        if path.name.startswith("bench"):
            continue
        doc = ast.get_docstring(ast.parse(path.read_text())) or ""
        found += [f"{path.name}: {m.group(0)}" for m in pattern.finditer(doc)]
    assert not found, found


PACKAGE = ROOT / "prdp_fem"


def _public_modules() -> set[str]:
    found = set()
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if any(part.startswith("_") for part in parts) or parts[1:2] in (("bench",), ("cli",)):
            continue  # private modules, __init__/__main__, benchmarks and the command line
        found.add(".".join(parts))
    return found


def test_the_api_reference_documents_every_public_module():
    documented = set(re.findall(r"^\.\. automodule:: ([\w.]+)$",
                                (ROOT / "docs" / "api.rst").read_text(), re.M))
    assert _public_modules() - documented == set()
    assert documented - _public_modules() <= {"prdp_fem"}


def test_the_gallery_shows_every_example_and_scene():
    gallery = (ROOT / "docs" / "examples.md").read_text()
    for script in (ROOT / "examples").glob("*.py"):
        assert f"../examples/{script.name}" in gallery, script.name
    for scene in (ROOT / "examples" / "scenes").glob("*.toml"):
        assert f"`{scene.name}`" in gallery, scene.name
