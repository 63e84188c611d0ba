"""PRDP's stall judged per unit learning rate (``prdp(per_learning_rate=True)``): the rule on
synthetic curves against a plain transcription, the trainers' epoch scales against the
schedule's closed form, and the run loops that refuse it."""

import math

import jax
import numpy as np
import optax
import pytest
from conftest import learning_rate_spy, small_heat_case

import prdp_fem as pf
from prdp_fem.errors import SolverConfigError
from prdp_fem.fem import full_field
from prdp_fem.inverse import inverse_problem, invert, prdp
from prdp_fem.learning import heat, learned
from prdp_fem.scene import SceneError, parse_scene
from prdp_fem.scene.build import build_heat, controller, heat_train_options


def _plain_rtols(errors, scales, rtol=3e-3, factor=0.1, tau_step=0.98, tau_stop=0.9,
                 window=6, delta=3):
    """The rule written the plain way (whole-history EMA, explicit checkpoint): a stall is a
    fall of the moving average over ``delta - 1`` values below ``(1 - tau_step)`` times the
    learning-rate scale; rtol after each value."""
    a = 2.0 / (window + 1.0)
    s, checkpoint, out = [], errors[0], []
    for e, scale in zip(errors, scales, strict=True):
        s.append(e if not s else a * e + (1 - a) * s[-1])
        if len(s) > delta and 1 - s[-1] / s[-delta] < (1 - tau_step) * scale:
            gain = s[-1] / checkpoint
            if gain < tau_stop or gain > 1:
                checkpoint, rtol = s[-1], rtol * factor
        out.append(rtol)
    return out


def _feed(control, errors, scales):
    state, out = control.init(), []
    for e, scale in zip(errors, scales, strict=True):
        state = control.update(state, e, learning_rate_scale=scale)
        out.append(float(state.rtol))
    return out


EPOCHS = 100
#: a cosine-decayed learning rate, mean of each epoch over the first step's
COSINE = [0.5 * (1 + math.cos(math.pi * (t - 0.5) / EPOCHS)) for t in range(1, EPOCHS + 1)]
#: an error that falls in proportion to the learning rate of the steps: the schedule's
#: slowdown, not the solves', ends its fall
SCHEDULED = [math.exp(-0.06 * sum(COSINE[:t])) for t in range(1, EPOCHS + 1)]
#: noisy training curves
NOISY = list(np.exp(-0.03 * np.arange(EPOCHS)) * (
    1 + 0.02 * np.random.default_rng(1).standard_normal(EPOCHS)))


def test_a_decaying_learning_rate_is_not_a_stall_but_a_constant_one_is_the_reference():
    """On an error that slows with a cosine schedule, the reference rule refines (reading
    the slowdown as a paying stall); per unit learning rate it holds its level. At a
    constant rate (scale 1) the two rules are the same on every curve."""
    scaled = prdp(rtol=3e-3, restart=False, per_learning_rate=True)
    reference = prdp(rtol=3e-3, restart=False)
    held = _feed(scaled, SCHEDULED, COSINE)
    assert held == _plain_rtols(SCHEDULED, COSINE)
    assert held[-1] == 3e-3
    refined = _feed(reference, SCHEDULED, [1.0] * EPOCHS)
    assert refined == _plain_rtols(SCHEDULED, [1.0] * EPOCHS)
    assert refined[-1] < 3e-3
    for curve in (SCHEDULED, NOISY, [1.0] * 30):
        ones = [1.0] * len(curve)
        assert _feed(scaled, curve, ones) == _feed(reference, curve, ones)


def test_a_plateau_stalls_at_any_learning_rate_and_noise_follows_the_transcription():
    """A level the solves cannot get below (the error stops falling) is a stall however small
    the steps are; a noisy curve under the schedule makes the transcription's decisions."""
    floor = [max(0.95 ** t, 0.5) for t in range(60)]
    scales = [0.3] * 60
    got = _feed(prdp(rtol=3e-3, restart=False, per_learning_rate=True), floor, scales)
    assert got == _plain_rtols(floor, scales) and got[-1] < 3e-3
    got = _feed(prdp(rtol=3e-3, restart=False, per_learning_rate=True), NOISY, COSINE)
    assert got == _plain_rtols(NOISY, COSINE)


def test_the_scaled_update_jits_with_a_traced_scale():
    control = prdp(rtol=3e-3, restart=False, per_learning_rate=True)
    jitted = jax.jit(control.update)
    host = device = control.init()
    for e, scale in zip(NOISY, COSINE, strict=True):
        host = control.update(host, e, learning_rate_scale=scale)
        device = jitted(device, e, learning_rate_scale=scale)
        assert float(host.rtol) == float(device.rtol)
        np.testing.assert_allclose(host.ema, device.ema, rtol=1e-14)


def test_bad_flags_and_run_loops_that_cannot_feed_a_rate_are_refused(small_problem):
    with pytest.raises(SolverConfigError, match="per_learning_rate"):
        prdp(per_learning_rate="yes")
    disc, kappa, f = small_problem
    u = disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f)).x)
    problem = inverse_problem(disc, full_field(disc, u_true=u), unknown="source", alpha=1e-4,
                              known=kappa)
    with pytest.raises(SolverConfigError, match="an inversion does not feed it"):
        invert(problem, refinement=prdp(per_learning_rate=True), steps=1)


@pytest.fixture(scope="module")
def small():
    return small_heat_case()


def test_heat_training_feeds_each_epoch_s_mean_rate_and_refuses_an_unknown_one(small):
    """12 trajectories x 5 windows (unroll 2) in batches of 12: 5 steps an epoch under a cosine
    schedule over 3 epochs; the controller sees each epoch's mean rate over the first step's
    (closed form ``(1 + cos(pi k / 15)) / 2``). With an optimiser of the caller's and no
    ``learning_rate`` the training refuses to guess it."""
    _, problem, trajectories, validation = small
    spy, fed = learning_rate_spy(prdp(K0=2, dK=1, per_learning_rate=True))
    schedule = optax.cosine_decay_schedule(1e-3, 15)
    network = learned.mlp_init(jax.random.PRNGKey(0), [problem.n_free, 8, problem.n_free],
                               output_scale=0.05)
    heat.train(problem, network, trajectories, validation, unroll=2, refinement=spy,
               optimizer=optax.adam(schedule), learning_rate=schedule, epochs=3,
               batch_size=12)
    expected = [np.mean([(1 + math.cos(math.pi * k / 15)) / 2 for k in range(5 * e, 5 * e + 5)])
                for e in range(3)]
    np.testing.assert_allclose(fed, expected, rtol=1e-6)  # the schedule computes in float32
    with pytest.raises(SolverConfigError, match="learning_rate="):
        heat.train(problem, network, trajectories, validation, unroll=2, refinement=spy,
                   optimizer=optax.adam(schedule), epochs=1, batch_size=12)
    with pytest.raises(SolverConfigError, match="learning_rate"):
        heat.train(problem, network, trajectories, validation, unroll=2, refinement=spy,
                   optimizer=optax.adam(schedule), learning_rate=lambda count: 0.0 * count,
                   epochs=1, batch_size=12)


def test_a_scene_key_builds_the_controller_and_hands_the_trainer_its_schedule():
    scene = parse_scene({"heat": {"epochs": 4, "trajectories": 16, "batch_size": 8},
                         "refinement": {"kind": "prdp", "rtol": 3e-3,
                                        "per_learning_rate": True},
                         "optimizer": {"name": "adam", "learning_rate": 2e-3,
                                       "decay": "cosine"}})
    assert controller(scene).scaled_by_learning_rate
    options = heat_train_options(scene, build_heat(scene).problem)
    updates = 4 * (scene.heat.windows // 8)
    rate = options["learning_rate"]
    np.testing.assert_allclose([float(rate(0)), float(rate(updates // 2)),
                                float(rate(updates))], [2e-3, 1e-3, 0.0], atol=1e-12)
    plain = parse_scene({"heat": {}, "refinement": {"kind": "prdp", "rtol": 3e-3}})
    assert not controller(plain).scaled_by_learning_rate


@pytest.mark.parametrize(("table", "match"), [
    ({}, r"bad.toml: refinement.per_learning_rate = true with study.kind = 'forward': "
         r"expected a learned or heat study"),
    ({"inverse": {"unknown": "source"}, "optimizer": {"name": "lbfgs"},
      "learned": {"samples": 8, "validation_samples": 4, "test_samples": 4, "batch_size": 8}},
     r"bad.toml: refinement.per_learning_rate = true with optimizer.name = 'lbfgs': "
     r"expected an optimiser with a learning rate"),
    ({"heat": {}, "refinement": {"kind": "gap", "per_learning_rate": True}},
     r"per_learning_rate"),
])
def test_scenes_that_cannot_feed_a_learning_rate_are_refused_at_parse(table, match):
    with pytest.raises(SceneError, match=match):
        parse_scene({"name": "bad", "refinement": {"kind": "prdp", "per_learning_rate": True},
                     **table}, source="bad.toml")
