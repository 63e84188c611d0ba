"""The stability suite: its fast subset (the full suite is `prdp-fem stability`), its verdict
logic and the `prdp-fem stability` command (tables, exit codes)."""

import csv
import functools
import math

import numpy as np
import pytest

from prdp_fem.cli.main import main
from prdp_fem.studies import stability
from prdp_fem.studies.stability import CaseResult, format_markdown, run_case, suite_passed
from prdp_fem.studies.stability_cases import CASES, case_named

FAST = [case for case in CASES if case.fast]


def test_catalogue_covers_every_group_and_builds_lazily():
    groups = {case.group for case in CASES}
    assert groups == {"contrast", "anisotropy", "mesh", "scale", "neumann", "precision",
                      "element"}
    assert len({case.name for case in CASES}) == len(CASES)
    assert {"contrast_1", "inclusion_1e10", "checkerboard_1e10", "lognormal_s5",
            "anisotropy_1e-6", "aspect_1e4", "graded_1e3", "scale_1e-6", "scale_1e6",
            "neumann_balanced", "neumann_unbalanced", "float32_contrast_1"} <= {
                case.name for case in CASES}
    with pytest.raises(ValueError, match="case 'nope': expected one of"):
        case_named("nope")


@pytest.fixture(scope="session")
def fast_results():
    """``fast_results(name)``: the case's result, run once per process on first use (under
    pytest-xdist each worker runs only the cases its tests ask for)."""
    return functools.cache(lambda name: run_case(case_named(name)))


#: fast cases whose stiffness other default tests cover (tests/test_extreme.py: tensor
#: coefficients, pure Neumann, float32): opt-in here, in every `prdp-fem stability` run
_COVERED_ELSEWHERE = {"anisotropy_1e-6", "aspect_1e4", "neumann_balanced", "float32_contrast_1"}


@pytest.mark.parametrize("name", [
    pytest.param(case.name, marks=pytest.mark.slow) if case.name in _COVERED_ELSEWHERE
    else case.name for case in FAST])
def test_fast_case_is_finite_and_not_failed(fast_results, name):
    """Every fast case: finite, monotone, not failed; a float64 case with a direct-solve
    reference agrees with it within its condition-scaled tolerance."""
    result = fast_results(name)
    assert result.nonfinite == 0
    assert result.gradients_finite and result.monotone
    assert result.verdict in ("ok", "flagged"), result.note
    if result.dtype == "float64" and not math.isnan(result.error):
        assert result.error <= result.tolerance, result
        assert result.verdict == "ok", result.note
        assert result.its_jacobi > 0


def test_high_contrast_is_conditioned_as_expected(fast_results):
    """Contrast 1e10 raises cond(A) by ~1e10 over kappa = 1; Jacobi takes back a factor ~2."""
    base, stiff = fast_results("contrast_1"), fast_results("inclusion_1e10")
    assert 1e9 < stiff.cond_A / base.cond_A < 1e11
    assert stiff.cond_jacobi < stiff.cond_A
    assert stiff.its_jacobi < stiff.its_identity
    assert stiff.error < 1e-4  # far below its tolerance (cond * eps ~ 1e-4)


def test_float32_states_its_limits(fast_results):
    single, double = fast_results("float32_contrast_1"), fast_results("contrast_1")
    assert single.verdict == "flagged" and "below float32 round-off" in single.note
    assert single.its_jacobi == -1  # rtol 1e-8 cannot be reached in float32
    assert 1e-8 < single.error < single.tolerance  # ~cond * eps32, not float64 accuracy
    assert double.error < 1e-12


def test_unbalanced_neumann_is_refused(fast_results):
    result = fast_results("neumann_unbalanced")
    assert result.verdict == "ok" and "IncompatibleDataError" in result.note


def row(**changes):
    base = CaseResult("c", "g", 10, "float64", 1.0, 1.0, 1, 1, 1, 0.0, 1.0, 0, True, True,
                      "ok", "", 0.0)
    return base._replace(**changes)


def test_verdicts_flag_limits_and_fail_the_rest():
    assert stability._verdict([], 0, 1e-12) == ("ok", "")
    assert stability._verdict([("miss", True)], 0, 1.0)[0] == "flagged"
    assert stability._verdict([("miss", True), ("bug", False)], 0, 1.0)[0] == "FAIL"
    assert stability._verdict([], 3, 1e-12)[0] == "FAIL"  # NaN/Inf is never excused
    assert suite_passed([row(), row(verdict="flagged")])
    assert not suite_passed([row(), row(verdict="FAIL")])
    assert not suite_passed([row(nonfinite=1, verdict="flagged")])


def test_monotone_check_allows_round_off_only():
    errors = np.array([1.0, 0.5, 0.1, 1e-14, 2e-14])
    assert stability._monotone(errors, floor=1e-13)
    assert not stability._monotone(np.array([1.0, 0.5, 0.6]), floor=1e-13)


# ------------------------------------------------------------------------------------------
# the command
# ------------------------------------------------------------------------------------------


def test_command_writes_markdown_and_csv(tmp_path, capsys, monkeypatch, fast_results):
    # the cases' own results are tested above: reuse this worker's (no second run of each)
    monkeypatch.setattr(stability, "run_case", lambda case: fast_results(case.name))
    code = main(["stability", "--case", "contrast_1", "neumann_unbalanced",
                 "--out", str(tmp_path)])
    assert code == 0
    with open(tmp_path / "stability.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [r["case"] for r in rows] == ["contrast_1", "neumann_unbalanced"]
    assert float(rows[0]["error"]) < float(rows[0]["tolerance"])
    assert int(rows[0]["its_jacobi"]) > 0 and rows[0]["verdict"] == "ok"
    markdown = (tmp_path / "stability.md").read_text()
    assert markdown.startswith("| case | dofs |") and "| contrast_1 | 361 |" in markdown
    assert "2 cases: 2 ok, 0 flagged, 0 failed in" in capsys.readouterr().out


def test_command_exits_nonzero_on_a_failure(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(stability, "run_case", lambda case: row(case=case.name, verdict="FAIL",
                                                                note="energy error grew"))
    assert main(["stability", "--case", "contrast_1", "--out", str(tmp_path)]) == 1
    assert "1 failed (contrast_1)" in capsys.readouterr().out
    monkeypatch.setattr(stability, "run_case", lambda case: row(case=case.name, nonfinite=2,
                                                                verdict="flagged"))
    assert main(["stability", "--case", "contrast_1", "--out", str(tmp_path)]) == 1


def test_command_refuses_unknown_cases(tmp_path, capsys):
    assert main(["stability", "--case", "nope", "--out", str(tmp_path)]) == 2
    assert "case 'nope': expected one of" in capsys.readouterr().err


def test_markdown_marks_missing_values():
    text = format_markdown([row(its_pyamg=-1, cond_A=math.nan)])
    assert "| c | 10 | float64 | - | 1.0e+00 | 1 | 1 | - |" in text
