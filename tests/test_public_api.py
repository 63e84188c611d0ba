"""The public API: a curated top level, subpackages that export what they document, and a
deprecated alias (with a warning) for each name the top level held before the subpackages."""

import importlib
import inspect
import warnings

import pytest

import prdp_fem as pf

SUBPACKAGES = ["mesh", "fem", "linalg", "inverse", "optim", "learning"]


def test_the_top_level_is_curated():
    names = [n for n in pf.__all__ if n != "__version__" and not inspect.ismodule(getattr(pf, n))]
    assert 45 <= len(names) <= 65
    assert len(set(pf.__all__)) == len(pf.__all__)
    assert not [n for n in names if "bench" in getattr(pf, n).__module__]


@pytest.mark.parametrize("package", ["prdp_fem", *(f"prdp_fem.{s}" for s in SUBPACKAGES)])
def test_every_exported_name_exists_and_is_documented(package):
    module = importlib.import_module(package)
    for name in module.__all__:
        value = getattr(module, name)
        if name == "__version__" or not (inspect.isclass(value) or inspect.isfunction(value)):
            continue
        assert inspect.getdoc(value), f"{package}.{name} has no docstring"


def test_the_top_level_names_are_the_subpackages_objects():
    assert pf.prdp is pf.inverse.prdp and pf.invert is pf.inverse.invert
    assert pf.TruncatedCG is pf.linalg.TruncatedCG and pf.load_mesh is pf.mesh.load_mesh
    assert inspect.isfunction(pf.prdp)  # the controller, no longer shadowed by its module


def test_a_moved_name_warns_and_is_the_moved_object():
    for name, where in [("jacobi_solve", "prdp_fem.linalg"), ("AMGCost", "prdp_fem.bench.amg"),
                        ("InversionError", "prdp_fem.inverse"),
                        ("UnusedNodeError", "prdp_fem.errors")]:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            value = getattr(pf, name)
        assert value is getattr(importlib.import_module(where), name)
        assert [w.category for w in caught] == [DeprecationWarning]
        assert f"moved to {where}.{name}" in str(caught[0].message)
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        pf.no_such_name  # noqa: B018
