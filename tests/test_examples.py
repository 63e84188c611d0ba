"""The example scripts, imported and pinned to their numbers."""

import importlib.util
import itertools
from pathlib import Path

import numpy as np
import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def load(name):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_forward_convergence_example():
    result = load("forward_convergence").main()
    errors = result["errors"]
    assert result["n_free"] == 1823
    values = [errors[k] for k in sorted(errors)]
    assert all(a > b for a, b in itertools.pairwise(values))
    assert errors[80] == pytest.approx(8.27e-3, rel=2e-2)
    assert errors[160] < 1e-6
    assert 5 <= result["amg_iterations"] <= 30


def test_gradient_check_example():
    result = load("gradient_check").main()
    unrolled, implicit = result["unrolled"], result["implicit"]
    assert unrolled["value"] == pytest.approx(implicit["value"], rel=1e-12)
    # unrolled differentiates the truncated map exactly: second-order Taylor remainder
    assert np.median(unrolled["rates"]) == pytest.approx(2.0, abs=0.1)
    # implicit at K = 30 approximates the converged gradient, not the truncated map's
    assert np.median(implicit["rates"]) < 1.5
    difference = np.linalg.norm(unrolled["gradient"] - implicit["gradient"])
    assert difference > 1e-3 * np.linalg.norm(unrolled["gradient"])
