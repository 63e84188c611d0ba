"""One source of defaults: a scene's refinement keys default to the controllers' own
arguments, except where a difference is deliberate and named here."""

import dataclasses
import inspect

from prdp_fem.inverse import adaptive_tolerance, converged, fixed, prdp, truncation_gap
from prdp_fem.scene.spec import (
    REFINEMENT_SPECS,
    AdaptiveSpec,
    ConvergedSpec,
    FixedSpec,
    GapSpec,
    PrdpSpec,
    RefinementSpec,
)

#: scene key -> (the API's argument, why the scene differs; None: it must not)
PRDP_KEYS = {
    "K0": "K0", "dK": "dK", "K_max": "K_max", "factor": "factor", "tau_step": "tau_step",
    "tau_stop": "tau_stop", "delta": "delta", "latch": "latch",
    "stall_on_failure": "stall_on_failure", "rtol_factor": "rtol_factor",
    "rtol_min": "rtol_min",
}
#: deliberate: an inversion's loss moves when K does (restart, see prdp()'s docstring), and
#: the window depends on what is watched (scene.default_ema_window)
DIFFERENT = {"restart": (True, False), "ema_window": (None, 6)}


def _defaults(function) -> dict:
    return {name: p.default for name, p in inspect.signature(function).parameters.items()
            if p.default is not inspect.Parameter.empty}


def test_scene_prdp_defaults_are_the_controller_s():
    spec, api = PrdpSpec(), _defaults(prdp)
    for key, argument in PRDP_KEYS.items():
        assert getattr(spec, key) == api[argument], key
    for key, (scene_value, api_value) in DIFFERENT.items():
        assert (getattr(spec, key), api[key]) == (scene_value, api_value), key


def test_scene_adaptive_defaults_are_the_controller_s():
    spec, api = AdaptiveSpec(), _defaults(adaptive_tolerance)
    assert (spec.rtol0, spec.power, spec.failure_factor, spec.rtol_min) == (
        api["rtol0"], api["power"], api["failure_factor"], api["rtol_min"])


def test_scene_gap_defaults_are_the_controller_s():
    spec, api = GapSpec(), _defaults(truncation_gap)
    assert (spec.rtol, spec.max_gap, spec.rtol_factor, spec.rtol_min, spec.redo) == (
        api["rtol"], api["max_gap"], api["rtol_factor"], api["rtol_min"], api["redo"])


def test_scene_converged_and_fixed_defaults_are_the_controllers_():
    assert _defaults(converged)["rtol"] == ConvergedSpec().rtol == RefinementSpec().validation_rtol
    assert _defaults(fixed)["K_adj"] is FixedSpec().K_adj


def test_one_spec_per_refinement_kind_holds_only_its_controller_s_settings():
    """Each kind's spec has its own fields and no other kind's (a fixed run has no K0)."""
    own = {kind: {f.name for f in dataclasses.fields(spec)} for kind, spec in
           REFINEMENT_SPECS.items()}
    assert {kind: spec().kind for kind, spec in REFINEMENT_SPECS.items()} == {
        kind: kind for kind in REFINEMENT_SPECS}
    assert "K0" in own["prdp"] and "K0" not in own["fixed"] | own["converged"] | own["adaptive"]
    assert "K" in own["fixed"] and "K" not in own["prdp"]
    assert own["converged"] - {f.name for f in dataclasses.fields(RefinementSpec)} == {"rtol"}
