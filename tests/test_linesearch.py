"""The zoom line search that gives up on a contradicted gradient (prdp_fem.optim.linesearch).

Where the gradient is right it must take optax's steps exactly; where the values rise against
the gradient's slope it must stop after three trials with a failure optax's state reports.
"""
from __future__ import annotations

import collections
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optax.tree_utils as otu
import pytest

import prdp_fem as pf
from prdp_fem.inverse.steps import step_failed
from prdp_fem.optim import Contradiction, ZoomSearchState
from prdp_fem.optim.linesearch import _nothing_seen, _watch


def _rosenbrock(z):
    return jnp.sum(100.0 * (z[1:] - z[:-1] ** 2) ** 2 + (1.0 - z[:-1]) ** 2)


def _narrow_valley(z):
    # the unit first trial overshoots by far: the search sees rising trials and zooms in
    return jnp.sum(jnp.cosh(100.0 * z))


def _badly_scaled(z):
    # the unit first trial is far too short: the search doubles it, 20 times
    return 1e-8 * jnp.sum(jnp.arange(1.0, z.size + 1) * (z - 3.0) ** 2)


def _run(optimizer, fn, z, steps):
    @jax.jit
    def step(z, state):
        value, grad = jax.value_and_grad(fn)(z)
        updates, state = optimizer.update(grad, state, z, value=value, grad=grad, value_fn=fn)
        return optax.apply_updates(z, updates), state

    state, path, searches = optimizer.init(z), [], []
    for _ in range(steps):
        z, state = step(z, state)
        path.append(np.asarray(z))
        searches.append(int(otu.tree_get(state, "num_linesearch_steps")))
    return np.array(path), searches


@pytest.mark.parametrize("fn, start, longest_search", [
    (_rosenbrock, np.array([-3.0, 4.0, -2.0, 3.0]), 2),
    pytest.param(_narrow_valley, np.array([0.05, -0.02, 0.01]), 6, marks=pytest.mark.slow),
    pytest.param(_badly_scaled, np.zeros(3), 20, marks=pytest.mark.slow),
])
def test_a_right_gradient_gets_optax_steps_exactly(fn, start, longest_search):
    z = jnp.asarray(start)
    ours, our_searches = _run(pf.lbfgs(), fn, z, 15)
    theirs, their_searches = _run(optax.lbfgs(), fn, z, 15)
    np.testing.assert_array_equal(ours, theirs)
    assert our_searches == their_searches
    # the cases reach the regimes the rule must leave alone: long searches, rising trials
    assert max(their_searches) >= longest_search


def _paraboloid_with_gradient_times(factor):
    """``sum((z - 1)^2)`` whose derivative is ``factor`` times the true one: a stand-in for a
    truncated gradient that does not match its loss."""
    @jax.custom_jvp
    def paraboloid(z):
        return jnp.sum((z - 1.0) ** 2)

    @paraboloid.defjvp
    def paraboloid_jvp(primals, tangents):
        (z,), (dz,) = primals, tangents
        return paraboloid(z), factor * jnp.sum(2.0 * (z - 1.0) * dz)

    return paraboloid


_wrong_sign = _paraboloid_with_gradient_times(-1.0)
# the right direction, ten times too steep: the unit trial (scaled by 1/|g|) lands far past
# the minimum along the line
_too_steep = _paraboloid_with_gradient_times(10.0)


def _search(optimizer, fn, z):
    value, grad = jax.value_and_grad(fn)(z)
    updates, state = optimizer.update(grad, optimizer.init(z), z, value=value, grad=grad,
                                      value_fn=fn)
    return value, grad, updates, state


@functools.cache
def _search_program(optimizer, fn):
    """:func:`_search` as one program, kept per transformation and objective (op by op,
    every search compiled its loops anew)."""
    return jax.jit(functools.partial(_search, optimizer, fn))


def _one_search(optimizer, fn, z):
    return _search_program(optimizer, fn)(z)


# the transformations as module constants: tests that search one objective with one of them
# share its compiled search (optax's transformations are pure)
_OURS, _OPTAX, _POLYAK = pf.lbfgs(), optax.lbfgs(), pf.lbfgs(first_step="polyak")


def test_a_search_step_holds_the_evaluation_once_and_runs_it_once_per_trial():
    """optax's step evaluates inside both branches of a ``cond``; ours has the evaluation
    (a CG solve and its adjoint in an inversion) once in the program, which XLA compiles
    once instead of twice, and runs it once per trial. Counted by tracing (optax's own
    search traces it twice) and by a host call at run time (one per trial)."""
    traced, ran = collections.Counter(), collections.Counter()

    def counted(z):
        traced["value_fn"] += 1
        jax.debug.callback(lambda: ran.update(["value_fn"]))
        return _badly_scaled(z)  # its unit first trial doubles 20 times

    z = jnp.array([-3.0, 4.0, -2.0, 3.0])
    value, grad = jax.value_and_grad(_badly_scaled)(z)
    for name, optimizer in (("ours", pf.lbfgs()), ("optax", optax.lbfgs())):
        traced.clear()
        ran.clear()
        _, state = jax.jit(lambda z, state, opt=optimizer: opt.update(
            grad, state, z, value=value, grad=grad, value_fn=counted))(z, optimizer.init(z))
        jax.effects_barrier()
        trials = int(otu.tree_get(state, "num_linesearch_steps"))
        assert trials == 20, name
        assert traced["value_fn"] == (1 if name == "ours" else 2), name
        assert ran["value_fn"] == trials, name


@pytest.mark.parametrize("stale", [jnp.inf, jnp.nan])
def test_a_non_finite_value_gets_the_value_and_gradient_at_params_from_one_trial(stale):
    """No value to search from: the search evaluates at ``params`` once, through its own
    trial, returns a zero update and stores the value and gradient there; the rest of the
    state (the step size of the last search, its info) is kept. ``invert`` then updates from
    them, so its step holds the objective once."""
    ran = collections.Counter()

    def counted(z):
        jax.debug.callback(lambda: ran.update(["value_fn"]))
        return _badly_scaled(z)

    optimizer = _OURS
    z = jnp.array([-3.0, 4.0, -2.0, 3.0])
    *_, searched = _one_search(optimizer, _badly_scaled, z)  # a state with a search behind it
    moved = z + 0.1
    updates, state = jax.jit(lambda z, state: optimizer.update(
        jnp.zeros(4), state, z, value=stale, grad=jnp.zeros(4), value_fn=counted))(
        moved, searched)
    jax.effects_barrier()
    assert ran["value_fn"] == 1
    np.testing.assert_array_equal(updates, np.zeros(4))
    expected_value, expected_grad = jax.value_and_grad(_badly_scaled)(moved)
    assert float(otu.tree_get(state, "value")) == pytest.approx(float(expected_value),
                                                                 rel=1e-15)
    np.testing.assert_allclose(otu.tree_get(state, "grad"), expected_grad, rtol=1e-15)
    for name in ("learning_rate", "num_linesearch_steps", "decrease_error"):
        assert float(otu.tree_get(state, name)) == float(otu.tree_get(searched, name)), name
    assert isinstance(state[-1], ZoomSearchState)


def test_a_gradient_of_the_wrong_sign_ends_the_search_after_three_trials():
    z = jnp.array([0.2, -0.4, 0.7])
    value, grad, updates, state = _one_search(_OURS, _wrong_sign, z)
    assert int(otu.tree_get(state, "num_linesearch_steps")) == 3
    np.testing.assert_array_equal(updates, np.zeros(3))          # no step: every trial rose
    assert float(otu.tree_get(state, "value")) == float(value)   # the start's value and
    np.testing.assert_array_equal(otu.tree_get(state, "grad"), grad)  # gradient are kept
    assert bool(step_failed(state))                              # invert counts a failure

    *_, optax_state = _one_search(_OPTAX, _wrong_sign, z)
    assert int(otu.tree_get(optax_state, "num_linesearch_steps")) == 20
    assert bool(step_failed(optax_state))


def test_a_too_steep_gradient_is_not_a_contradiction():
    # the values fall for small steps, so the search can succeed: the rule must not fire
    z = jnp.array([0.2, -0.4, 0.7])
    *_, ours = _one_search(_OURS, _too_steep, z)
    *_, theirs = _one_search(_OPTAX, _too_steep, z)
    for name in ("num_linesearch_steps", "learning_rate", "decrease_error", "curvature_error"):
        assert float(otu.tree_get(ours, name)) == float(otu.tree_get(theirs, name)), name


class _Trial:
    """The fields of optax's zoom state that the watch reads."""

    def __init__(self, t, rise, *, slope=-1.0, slope_init=-1.0, curvature_error=1.0,
                 value_init=0.0):
        self.stepsize, self.value, self.value_init = (jnp.asarray(t),
                                                      jnp.asarray(value_init + rise),
                                                      jnp.asarray(value_init))
        self.slope, self.slope_init = jnp.asarray(slope), jnp.asarray(slope_init)
        self.curvature_error = jnp.asarray(curvature_error)


def _watched(trials, approx_dec_rtol=1e-6) -> Contradiction:
    seen = _nothing_seen(jnp.float64)
    for trial in trials:
        seen = _watch(seen, trial, approx_dec_rtol)
    return seen


def test_the_extrapolated_slope_is_a_parabola_s_slope_at_zero():
    # J(t) - J(0) = a t + b t^2: every pair of trials gives a exactly
    a, b = 0.3, 2.0
    seen = _watched(_Trial(t, a * t + b * t * t) for t in (1.0, 0.4, 0.1))
    np.testing.assert_allclose(float(seen.extrapolated_slope), a, rtol=1e-12)
    assert bool(seen.found)
    # a right gradient on a parabola (a < 0) never gives a positive slope, however the
    # trials rise
    seen = _watched(_Trial(t, -0.3 * t + 2.0 * t * t) for t in (1.0, 0.4, 0.2))
    np.testing.assert_allclose(float(seen.extrapolated_slope), -0.3, rtol=1e-12)
    assert not bool(seen.found)


@pytest.mark.parametrize("trial_kwargs, why", [
    (dict(curvature_error=0.0), "the curvature condition holds at the last trial"),
    (dict(slope=+0.5), "the gradient's slope has turned: a smaller step may meet curvature"),
])
def test_a_rise_within_the_approximate_tolerance_needs_a_steep_gradient(trial_kwargs, why):
    # J(0) = 1e6: the last rise, 0.05, is within optax's approximate decrease (1e-6 J(0)),
    # which a step below t_3 may meet with the curvature condition
    rising = [_Trial(t, 0.3 * t + 2.0 * t * t, value_init=1e6) for t in (1.0, 0.4)]
    last = _Trial(0.1, 0.3 * 0.1 + 2.0 * 0.01, value_init=1e6, **trial_kwargs)
    assert not bool(_watched([*rising, last]).found), why
    # the same trials with a steep gradient at t_3: optax's search would fail as well
    steep = _Trial(0.1, 0.3 * 0.1 + 2.0 * 0.01, value_init=1e6)
    assert bool(_watched([*rising, steep]).found)


# at t_3 = 0.1 the rise is 0.05: the secant slope m_3 = 0.5
@pytest.mark.parametrize("trial_kwargs", [dict(curvature_error=0.0), dict(slope=+0.4)])
@pytest.mark.parametrize("value_init, approx_dec_rtol, found", [
    (1e3, 1e-6, True),    # rise 0.05 > 1e-3: what optax might still accept raises J
    (1e5, 1e-6, False),   # rise 0.05 < 0.1: within the tolerance
    (1e5, None, True),    # no approximate decrease: no tolerance
])
def test_a_rise_beyond_the_approximate_tolerance_is_a_contradiction(
        trial_kwargs, value_init, approx_dec_rtol, found):
    trials = [_Trial(t, 0.3 * t + 2.0 * t * t, value_init=value_init) for t in (1.0, 0.4)]
    trials.append(_Trial(0.1, 0.3 * 0.1 + 2.0 * 0.01, value_init=value_init, **trial_kwargs))
    assert bool(_watched(trials, approx_dec_rtol).found) == found


def test_a_gradient_slope_above_the_secant_is_no_contradiction_however_high_the_rise():
    # J'(t_3) >= m_3, as for any J convex on [0, t_3] with its true gradient
    trials = [_Trial(t, 0.3 * t + 2.0 * t * t) for t in (1.0, 0.4)]
    trials.append(_Trial(0.1, 0.3 * 0.1 + 2.0 * 0.01, slope=+0.6, curvature_error=0.0))
    assert not bool(_watched(trials, None).found)


def _smoothed_kink(z):
    # convex, right gradient: J = 10 - t + (sqrt(1 + (100 t)^2) - 1) along z; the secant
    # slope is concave and the values rise from far below the unit trial down to t ~ 1e-2
    return jnp.sum(10.0 - z + jnp.sqrt(1.0 + (100.0 * z) ** 2) - 1.0)


@pytest.mark.parametrize("approx_dec_rtol", [1e-6, None])
def test_a_convex_kink_with_its_true_gradient_gets_optax_s_search(approx_dec_rtol):
    """The values seem to rise from t = 0 (a smoothed total variation's kink), but the
    gradient's slope stays above the secant's: optax's search, which finds the step."""
    z = jnp.zeros(1)
    value, grad = jax.value_and_grad(_smoothed_kink)(z)
    results = []
    for search in (pf.optim.scale_by_zoom_linesearch(approx_dec_rtol=approx_dec_rtol),
                   optax.scale_by_zoom_linesearch(20, approx_dec_rtol=approx_dec_rtol)):
        updates, state = search.update(-grad, search.init(z), z, value=value, grad=grad,
                                       value_fn=_smoothed_kink)
        results.append((np.asarray(updates), int(otu.tree_get(state, "num_linesearch_steps")),
                        bool(step_failed(state))))
    (ours, our_count, we_failed), (theirs, their_count, they_failed) = results
    np.testing.assert_array_equal(ours, theirs)
    assert our_count == their_count > 3 and not we_failed and not they_failed
    assert float(_smoothed_kink(z + ours)) < float(value)


def test_two_rising_trials_or_disagreeing_slopes_are_not_enough():
    assert not bool(_watched(_Trial(t, 0.3 * t + 2.0 * t * t) for t in (1.0, 0.4)).found)
    # the extrapolated slopes 0.3 and 3.0 disagree by more than a factor two
    trials = [_Trial(1.0, 0.3 + 2.0), _Trial(0.4, 0.3 * 0.4 + 2.0 * 0.16),
              _Trial(0.1, 3.0 * 0.1 + 0.05)]
    assert not bool(_watched(trials).found)


@pytest.mark.parametrize("kwargs", [dict(max_linesearch_steps=0),
                                    dict(max_linesearch_steps=2.5),
                                    dict(initial_guess_strategy="guess")])
def test_bad_settings_are_refused_at_construction(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        pf.optim.scale_by_zoom_linesearch(**kwargs)


def _quadratic_line(minimum):
    """``J(z) = minimum + |z - 3|^2 / 2`` (``J(0) = minimum + 9/2`` in 1-D): along the first
    direction it is quadratic with the given minimum."""
    def objective(z):
        return minimum + 0.5 * jnp.sum((z - 3.0) ** 2)
    return objective


def test_a_polyak_first_step_ends_the_first_search_after_one_evaluation():
    """On a badly scaled least-squares objective the unit first trial doubles 20 times; the
    trial J / |s_0| is accepted at once, and it is that step exactly."""
    z = jnp.array([-3.0, 4.0, -2.0, 3.0])  # the start above: its compiled unit search serves
    value, grad, updates, state = _one_search(_POLYAK, _badly_scaled, z)
    assert int(otu.tree_get(state, "num_linesearch_steps")) == 1
    direction = -grad  # L-BFGS's first direction: the bare gradient
    slope = float(jnp.vdot(direction, grad))
    np.testing.assert_allclose(updates, float(value) / -slope * direction, rtol=1e-13)
    *_, unit = _one_search(_OURS, _badly_scaled, z)
    assert int(otu.tree_get(unit, "num_linesearch_steps")) == 20


@pytest.mark.parametrize("share, one_evaluation", [(0.0, True), (0.5, True), (0.72, True),
                                                   (0.76, False), (0.9, False)])
def test_the_polyak_trial_meets_the_wolfe_conditions_up_to_the_stated_minimum(share,
                                                                             one_evaluation):
    """The docstring's claim: on a quadratic line with minimum m, one evaluation whenever
    m <= 0.73 J(z_0)."""
    minimum = share * 4.5 / (1.0 - share)  # m = share * J(0), J(0) = m + 4.5
    state = _polyak_search_on_a_quadratic_line(minimum)
    assert (int(otu.tree_get(state, "num_linesearch_steps")) == 1) == one_evaluation


@jax.jit
def _polyak_search_on_a_quadratic_line(minimum):
    """The state after one Polyak-first search from 0 on ``_quadratic_line(minimum)``: the
    minimum an argument, so that every case runs one compiled search."""
    *_, state = _search(_POLYAK, _quadratic_line(minimum), jnp.zeros(1))
    return state


def test_a_polyak_first_step_needs_a_positive_value_and_a_descent_slope():
    """Where J(z_0) <= 0 the guess means nothing: the first trial is optax's unit step, and
    later searches are optax's in any case."""
    negative = _quadratic_line(-20.0)  # J(z_0) = -8.875
    z = jnp.array([0.5, -1.0])
    ours, our_searches = _run(pf.lbfgs(first_step="polyak"), negative, z, 4)
    theirs, their_searches = _run(pf.lbfgs(), negative, z, 4)
    np.testing.assert_array_equal(ours, theirs)
    assert our_searches == their_searches
    with pytest.raises(ValueError, match="first_step='half'"):
        pf.lbfgs(first_step="half")


# --- the first search after the objective changed ----------------------------------------


def _half_squared_distance_to_one(z):
    return 0.5 * jnp.sum((z - 1.0) ** 2)


def _search_along(direction_scale, *, changed, max_linesearch_steps=20):
    """One search of `pf.optim.scale_by_zoom_linesearch` along ``direction_scale`` times the
    steepest descent direction of a quadratic, whose line minimum is at
    ``t* = 1 / direction_scale``; ``changed``: the state says the objective changed since the
    last search (the value invert stores when PRDP refines), else a finite stored value."""
    return _search_along_program(direction_scale, changed, max_linesearch_steps)


def _search_along_op_by_op(direction_scale, changed, max_linesearch_steps):
    fn, z = _half_squared_distance_to_one, jnp.array([0.2, -0.4, 0.7])
    value, grad = jax.value_and_grad(fn)(z)
    search = pf.optim.scale_by_zoom_linesearch(max_linesearch_steps)
    state = search.init(z)
    state = state._replace(value=jnp.where(changed, jnp.inf, value), grad=grad,
                           info=state.info._replace(num_linesearch_steps=jnp.asarray(3)))
    direction = -direction_scale * grad
    updates, state = search.update(direction, state, z, value=value, grad=grad, value_fn=fn)
    return direction, updates, state


# the scale and the flag are arguments: one compiled search per trial budget
_search_along_program = jax.jit(_search_along_op_by_op, static_argnums=2)


def test_an_overshoot_after_the_objective_changed_restarts_at_the_quadratic_step():
    # the direction is 1000 times too long: optax's zoom halves the unit trial (the quadratic
    # step 1e-3 lies within 10 % of the interval's end) where the restart lands on t* at once
    direction, updates, state = _search_along(1000.0, changed=True)
    assert int(otu.tree_get(state, "num_linesearch_steps")) == 2
    np.testing.assert_allclose(updates, 1e-3 * direction, rtol=1e-12)
    assert not bool(step_failed(state))
    # the same search with the objective unchanged is optax's, many halvings long (both op
    # by op: compiled apart, the two programs may round a last bit differently)
    _, our_updates, ours = _search_along_op_by_op(1000.0, False, 20)
    fn, z = _half_squared_distance_to_one, jnp.array([0.2, -0.4, 0.7])
    value, grad = jax.value_and_grad(fn)(z)
    theirs = optax.scale_by_zoom_linesearch(20)
    their_updates, theirs = theirs.update(-1000.0 * grad, theirs.init(z), z, value=value,
                                          grad=grad, value_fn=fn)
    np.testing.assert_array_equal(our_updates, their_updates)
    assert int(otu.tree_get(ours, "num_linesearch_steps")) == \
        int(otu.tree_get(theirs, "num_linesearch_steps")) > 5


def test_a_restart_shrinks_the_trial_by_at_most_a_thousand_and_repeats():
    # t* = 1e-8: restarts at 1e-3 (the floor), 1e-6 (the floor) and 1e-8 (t_q), then done
    direction, updates, state = _search_along(1e8, changed=True)
    assert int(otu.tree_get(state, "num_linesearch_steps")) == 4
    np.testing.assert_allclose(updates, 1e-8 * direction, rtol=1e-9)
    assert not bool(step_failed(state))


def test_restarts_count_against_the_search_s_trials():
    # three trials allowed: 1, 1e-3, 1e-6 all overshoot; the search ends there, failed,
    # at its last trial as optax's ends without a step that met the sufficient decrease
    direction, updates, state = _search_along(1e8, changed=True, max_linesearch_steps=3)
    assert int(otu.tree_get(state, "num_linesearch_steps")) == 3
    assert bool(step_failed(state))
    np.testing.assert_allclose(updates, 1e-6 * direction, rtol=1e-12)
    z = jnp.array([0.2, -0.4, 0.7])
    np.testing.assert_allclose(float(otu.tree_get(state, "value")),
                               float(_half_squared_distance_to_one(z + updates)), rtol=1e-12)


@pytest.mark.parametrize("direction_scale", [5.0, 1.0])
def test_a_first_trial_within_the_zoom_s_reach_is_not_restarted(direction_scale):
    # t* = 0.2 (the zoom's quadratic step is usable) and t* = 1 (the unit trial is right):
    # optax's search exactly, objective changed or not
    _, changed_updates, changed = _search_along(direction_scale, changed=True)
    _, kept_updates, kept = _search_along(direction_scale, changed=False)
    np.testing.assert_array_equal(changed_updates, kept_updates)
    assert int(otu.tree_get(changed, "num_linesearch_steps")) == \
        int(otu.tree_get(kept, "num_linesearch_steps"))


def test_a_first_trial_outside_the_domain_restarts_a_tenth_shorter_until_finite():
    # the quadratic is NaN where |z| >= 5 (an overflowing coefficient, say); t* = 1e-3. The
    # trials 1, 0.1 and 0.01 leave the domain, each restarting ten times shorter, and 1e-3
    # is the minimum: four evaluations. optax's zoom halves instead (ten and more).
    def fn(z):
        return jnp.where(jnp.max(jnp.abs(z)) < 5.0, _half_squared_distance_to_one(z), jnp.nan)

    z = jnp.array([0.2, -0.4, 0.7])
    value, grad = jax.value_and_grad(fn)(z)

    @jax.jit  # one program for both searches (the flag an argument)
    def search(changed):
        line = pf.optim.scale_by_zoom_linesearch(20)
        state = line.init(z)
        state = state._replace(value=jnp.where(changed, jnp.inf, value), grad=grad,
                               info=state.info._replace(num_linesearch_steps=jnp.asarray(3)))
        return line.update(-1000.0 * grad, state, z, value=value, grad=grad, value_fn=fn)

    updates, state = search(changed=True)
    assert int(otu.tree_get(state, "num_linesearch_steps")) == 4
    np.testing.assert_allclose(z + updates, jnp.ones(3), rtol=1e-12)
    assert not bool(step_failed(state))
    _, unchanged = search(changed=False)  # optax's search: no restart
    assert int(otu.tree_get(unchanged, "num_linesearch_steps")) >= 10


def test_a_search_out_of_trials_after_a_restart_ends_at_its_safe_step_as_optax_s_does():
    # along the line: slope -1000 up to a wall at t = 1.5e-3. The unit trial overshoots, the
    # restart at 1e-3 meets the decrease (not the curvature), the doubled 2e-3 hits the
    # wall; with three trials the search ends there, failed, at the safe 1e-3
    updates, state = _three_trials_against_a_wall(jnp.zeros(1))
    assert int(otu.tree_get(state, "num_linesearch_steps")) == 3
    np.testing.assert_allclose(updates, [1.0], rtol=1e-12)
    assert float(otu.tree_get(state, "value")) == pytest.approx(float(_walled(jnp.ones(1))))
    assert bool(step_failed(state))


def _walled(z):
    return jnp.sum(-z + 1e6 * jnp.maximum(z - 1.5, 0.0) ** 2)


@jax.jit
def _three_trials_against_a_wall(z):
    """The search above, from ``z`` in its dtype: (updates, state)."""
    value, grad = jax.value_and_grad(_walled)(z)
    search = pf.optim.scale_by_zoom_linesearch(3)
    state = search.init(z)
    state = state._replace(info=state.info._replace(num_linesearch_steps=jnp.asarray(1)))
    return search.update(jnp.array([1000.0], z.dtype), state, z, value=value, grad=grad,
                         value_fn=_walled)


def test_float32_parameters_keep_their_dtype_when_a_search_gives_up_or_runs_out():
    # the give-up and out-of-trials branches must return the state's float32 types
    z = jnp.array([0.2, -0.4, 0.7], dtype=jnp.float32)
    _, _, updates, state = _one_search(_OURS, _wrong_sign, z)
    assert updates.dtype == jnp.float32 and int(otu.tree_get(state, "num_linesearch_steps")) == 3
    np.testing.assert_array_equal(updates, np.zeros(3, np.float32))
    updates, state = _three_trials_against_a_wall(jnp.zeros(1, jnp.float32))
    assert updates.dtype == jnp.float32 and bool(step_failed(state))
    np.testing.assert_allclose(updates, [1.0], rtol=1e-6)
