"""Refinement controllers on synthetic error curves: exact K sequences.

A literal transcription of the reference rule (``_reference_refines``: NumPy EMA over the whole
history, checkpoint as an explicit variable) is the oracle; a few sequences are also written out
by hand so that the oracle itself is pinned.
"""

import itertools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from prdp_fem.errors import SolverConfigError
from prdp_fem.inverse import Schedule, converged, fixed, prdp, state_from_dict, state_to_dict


def _ema(values, window):
    a = 2.0 / (window + 1.0)
    out = [values[0]]
    for v in values[1:]:
        out.append(a * v + (1 - a) * out[-1])
    return np.array(out)


def _reference_sequence(errors, K0=25, dK=10, K_max=600, tau_step=0.98, tau_stop=0.9,
                        window=6, delta=3):
    """The reference controller, written the plain way: K after each value."""
    K, checkpoint, history, ks = K0, errors[0], [], []
    for e in errors:
        history.append(e)
        if len(history) > delta:
            s = _ema(history, window)
            if s[-1] / s[-delta] > tau_step:
                rc = s[-1] / checkpoint
                if rc < tau_stop or rc > 1:
                    checkpoint = s[-1]
                    K = min(K + dK, K_max)
        ks.append(K)
    return ks


def _run(controller, errors, field="iterations"):
    state = controller.init()
    out = []
    for e in errors:
        state = controller.update(state, e)
        out.append(int(getattr(state, field)) if field != "rtol" else float(state.rtol))
    return out, state


def _plateaus(levels, length):
    return [lvl for lvl in levels for _ in range(length)]


CURVES = {
    "steady": [0.9 ** t for t in range(40)],
    "plateaus": _plateaus([1.0, 0.5, 0.25, 0.2, 0.19, 0.1], 15),
    "noisy": list(np.exp(-0.02 * np.arange(60)) * (1 + 0.05 * np.random.default_rng(0)
                                                   .standard_normal(60))),
    "diverging": [1.0, 0.8, 0.7, 0.65] + [0.65 * 1.05 ** t for t in range(30)],
    "flat": [1.0] * 30,
}


@pytest.mark.parametrize("name", sorted(CURVES))
def test_prdp_matches_the_reference_rule(name):
    errors = CURVES[name]
    got, _ = _run(prdp(), errors)
    assert got == _reference_sequence(errors)


def test_hand_checked_sequences():
    # steady 10 % decrease per step: never stalls
    assert _run(prdp(), CURVES["steady"])[0] == [25] * 40
    # flat from the start: stalls at t = 4 with no gain over e_1: "enough", never refines
    ks, state = _run(prdp(), CURVES["flat"])
    assert ks == [25] * 30 and bool(state.stopped)
    # one drop to half: stall at the first level (no gain: keep), refine once on the second
    errors = [1.0] * 4 + [0.5] * 12
    assert _run(prdp(K0=10, dK=10, K_max=40), errors)[0] == [10] * 15 + [20]
    # divergence (s above the checkpoint) refines on every stalled step, up to K_max
    ks, _ = _run(prdp(K0=10, dK=10, K_max=60), CURVES["diverging"])
    assert ks[-1] == 60 and all(b - a in (0, 10) for a, b in itertools.pairwise(ks))


def test_plateau_sequence_exact():
    ks, _state = _run(prdp(), CURVES["plateaus"])
    refinement_steps = [t + 1 for t in range(1, len(ks)) if ks[t] > ks[t - 1]]
    # each plateau >= 10 % below the previous checkpoint refines once it has stalled; the
    # 0.2 -> 0.19 step (5 %) does not, 0.19 -> 0.1 does again (not latched)
    assert ks[-1] == 25 + 10 * len(refinement_steps)
    level_of = {t: CURVES["plateaus"][t - 1] for t in refinement_steps}
    assert sorted(set(level_of.values()), reverse=True) == [0.5, 0.25, 0.2, 0.1]
    assert ks == _reference_sequence(CURVES["plateaus"])


def test_refinement_resumes_after_lower_plateau_unless_latched():
    errors = [1.0] * 20 + [0.5] * 40
    free, _ = _run(prdp(K0=5, dK=5), errors)
    latched, state = _run(prdp(K0=5, dK=5, latch=True), errors)
    assert free[19] == 5 and free[-1] == 10          # stop at 1.0, resume at 0.5
    assert latched[-1] == 5 and bool(state.stopped)  # the stop at 1.0 is final


def test_multiplicative_growth_and_cap():
    errors = _plateaus([1.0, 0.5, 0.25, 0.1, 0.05, 0.02], 20)
    ks, _ = _run(prdp(K0=4, dK=0, factor=2.0, K_max=40), errors)
    assert sorted(set(ks)) == [4, 8, 16, 32, 40]


def test_separate_adjoint_schedule():
    errors = _plateaus([1.0, 0.5, 0.25], 20)
    controller = prdp(K0=10, dK=10, adjoint=Schedule(K0=5, dK=2, K_max=8))
    ks, _ = _run(controller, errors)
    kadj, _ = _run(controller, errors, "adjoint_iterations")
    n_ref = len(set(ks)) - 1
    assert n_ref == 2 and sorted(set(kadj)) == [5, 7, 8]
    shared, _ = _run(prdp(K0=10, dK=10), errors, "adjoint_iterations")
    assert shared == ks


def test_tolerance_mode_divides_rtol():
    errors = _plateaus([1.0, 0.5, 0.25], 20)
    rt, state = _run(prdp(K_max=500, rtol=1e-2, rtol_factor=0.1, rtol_min=1e-3), errors, "rtol")
    assert sorted(set(rt), reverse=True) == pytest.approx([1e-2, 1e-3])
    assert int(state.iterations) == 500 and int(state.refinements) == 2  # second hits rtol_min


def test_non_finite_value_refines_and_stays_out_of_the_average():
    errors = [1.0, 0.9, float("nan"), 0.8]
    ks, state = _run(prdp(K0=10, dK=10), errors)
    assert ks == [10, 10, 20, 20]
    assert int(state.count) == 3 and np.isfinite(np.asarray(state.ema)).all()


def _run_with_failures(controller, errors, failed):
    state, ks = controller.init(), []
    for e, f in zip(errors, failed, strict=True):
        state = controller.update(state, e, failed=f)
        ks.append(int(state.iterations))
    return ks, state


def test_a_failed_step_is_a_stall_at_once():
    # a steady 10 % decrease never stalls the average; a failure reported after the sixth
    # value refines at once (the error fell > 10 % since e_1); the reference rule ignores it
    errors, failed = CURVES["steady"][:12], [t == 5 for t in range(12)]
    assert _run_with_failures(prdp(K0=10, dK=10, stall_on_failure=True), errors,
                              failed)[0] == [10] * 5 + [20] * 7
    reference = prdp(K0=10, dK=10)  # the default: the reference rule
    assert _run_with_failures(reference, errors, failed)[0] == [10] * 12


def test_failures_refine_at_the_starting_K_but_do_not_cascade():
    # a flat loss that fails every step: the first step's failure is exempt (its line search
    # starts from an arbitrary step size), the second refines (nothing judged yet at K0);
    # after that the refinement bought nothing, so the gain test says "enough"
    ks, state = _run_with_failures(prdp(K0=10, dK=10, stall_on_failure=True), [1.0] * 10,
                                   [True] * 10)
    assert ks == [10] + [20] * 9 and bool(state.stopped) and int(state.refinements) == 1
    # a loss that keeps dropping > 10 % per refinement while failing refines every step
    ks, _ = _run_with_failures(prdp(K0=10, dK=10, K_max=50, stall_on_failure=True),
                               [0.5 ** t for t in range(6)],
                               [True] * 6)
    assert ks == [10, 20, 30, 40, 50, 50]
    # a loss that moves up after the refinement (a truncated loss changes level with K) is
    # no divergence for a failure: no second refinement until the moving average stalls
    ks, state = _run_with_failures(prdp(K0=10, dK=10, restart=True, stall_on_failure=True),
                                   [1.0, 1.0, 2.0, 2.0, 2.0],
                                   [True] * 5)
    assert ks == [10, 20, 20, 20, 20] and bool(state.stopped)


def test_jitted_update_takes_a_traced_failure_flag():
    controller = prdp(K0=10, dK=10, stall_on_failure=True)
    update = jax.jit(controller.update)
    state = update(controller.init(), 1.0, jnp.asarray(True))  # the first step: exempt
    assert int(state.iterations) == 10
    assert int(update(state, 1.0, jnp.asarray(True)).iterations) == 20
    assert int(update(state, 1.0, jnp.asarray(False)).iterations) == 10


def test_fixed_and_converged_never_change():
    ks, state = _run(fixed(30, 12), CURVES["diverging"])
    assert ks == [30] * len(CURVES["diverging"]) and int(state.adjoint_iterations) == 12
    failing, _ = _run_with_failures(fixed(30), CURVES["flat"], [True] * 30)
    assert failing == [30] * 30  # a failed step does not move a fixed K
    controller = converged(1e-9)
    ks, state = _run(controller, CURVES["flat"], "rtol")
    assert controller.tolerance_mode and ks == [1e-9] * 30


def test_update_jits_and_scans():
    controller = prdp()
    errors = np.array(CURVES["plateaus"])

    def body(state, e):
        state = controller.update(state, e)
        return state, state.iterations
    _, ks = jax.jit(lambda s, e: jax.lax.scan(body, s, e))(controller.init(), errors)
    assert list(np.asarray(ks)) == _reference_sequence(list(errors))


CONTROLLERS = {
    "reference": prdp(),
    "restart, failures": prdp(K0=10, dK=10, restart=True, stall_on_failure=True),
    "latched, multiplicative, adjoint": prdp(K0=4, dK=0, factor=2.0, K_max=64, latch=True,
                                             adjoint=Schedule(8, 4, 30)),
    "tolerance": prdp(K0=10, rtol=1e-2, rtol_factor=0.1, rtol_min=1e-8),
    "fixed": fixed(30, 12),
    "converged": converged(1e-9),
}


@pytest.mark.parametrize("name", sorted(CONTROLLERS))
def test_host_update_is_numpy_and_equals_the_jitted_update(name):
    """The run loops update a host state with NumPy (no program dispatch); under ``jit`` the
    same function computes with ``jnp``. Both make the same decisions and carry the same
    averages (to rounding: XLA may fuse ``a e + (1 - a) s`` into one multiply-add) on curves
    with NaN, infinities, zeros (0/0 ratios) and failed steps."""
    controller = CONTROLLERS[name]
    errors = [*CURVES["plateaus"][:40], float("nan"), 0.0, 0.0, float("inf"),
              *CURVES["noisy"][:30], *CURVES["diverging"][:20]]
    jitted = jax.jit(controller.update)
    host = device = controller.init()
    for t, e in enumerate(errors):
        failed = t % 7 == 3
        host = controller.update(host, e, failed)
        device = jitted(device, e, failed)
        for field, a, b in zip(host._fields, host, device, strict=True):
            assert not isinstance(a, jax.Array), field
            assert np.asarray(a).dtype == np.asarray(b).dtype, field
            if np.asarray(a).dtype.kind == "f":
                np.testing.assert_allclose(a, b, rtol=1e-14, err_msg=f"step {t}: {field}")
            else:
                np.testing.assert_array_equal(a, b, err_msg=f"step {t}: {field}")


def test_state_round_trips_through_json():
    controller = prdp()
    _, state = _run(controller, CURVES["plateaus"][:25])
    restored = state_from_dict(json.loads(json.dumps(state_to_dict(state))))
    rest = CURVES["plateaus"][25:]
    a = [int((state := controller.update(state, e)).iterations) for e in rest]
    b = [int((restored := controller.update(restored, e)).iterations) for e in rest]
    assert a == b and a == _reference_sequence(CURVES["plateaus"])[25:]
    fresh = state_to_dict(controller.init())  # NaN placeholders survive JSON as null
    assert json.loads(json.dumps(fresh))["checkpoint"] is None


@pytest.mark.parametrize("kwargs", [dict(K0=-1), dict(K0=10, K_max=5), dict(dK=0),
                                    dict(factor=0.5), dict(tau_stop=1.5), dict(delta=1),
                                    dict(rtol=2.0)])
def test_bad_configuration_is_rejected(kwargs):
    with pytest.raises(SolverConfigError):
        prdp(**kwargs)
