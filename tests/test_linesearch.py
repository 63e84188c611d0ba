"""The zoom line search that gives up on a contradicted gradient (prdp_fem.linesearch).

Where the gradient is right it must take optax's steps exactly; where the values rise against
the gradient's slope it must stop after three trials with a failure optax's state reports.
"""
from __future__ import annotations

import collections

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optax.tree_utils as otu
import pytest

import prdp_fem as pf
from prdp_fem.inverse import _step_failed
from prdp_fem.linesearch import Contradiction, _nothing_seen, _watch


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
    (_narrow_valley, np.array([0.05, -0.02, 0.01]), 6),
    (_badly_scaled, np.zeros(3), 20),
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


def _one_search(optimizer, fn, z):
    value, grad = jax.value_and_grad(fn)(z)
    updates, state = optimizer.update(grad, optimizer.init(z), z, value=value, grad=grad,
                                      value_fn=fn)
    return value, grad, updates, state


def test_a_gradient_of_the_wrong_sign_ends_the_search_after_three_trials():
    z = jnp.array([0.2, -0.4, 0.7])
    value, grad, updates, state = _one_search(pf.lbfgs(), _wrong_sign, z)
    assert int(otu.tree_get(state, "num_linesearch_steps")) == 3
    np.testing.assert_array_equal(updates, np.zeros(3))          # no step: every trial rose
    assert float(otu.tree_get(state, "value")) == float(value)   # the start's value and
    np.testing.assert_array_equal(otu.tree_get(state, "grad"), grad)  # gradient are kept
    assert bool(_step_failed(state))                              # invert counts a failure

    *_, optax_state = _one_search(optax.lbfgs(), _wrong_sign, z)
    assert int(otu.tree_get(optax_state, "num_linesearch_steps")) == 20
    assert bool(_step_failed(optax_state))


def test_a_too_steep_gradient_is_not_a_contradiction():
    # the values fall for small steps, so the search can succeed: the rule must not fire
    z = jnp.array([0.2, -0.4, 0.7])
    *_, ours = _one_search(pf.lbfgs(), _too_steep, z)
    *_, theirs = _one_search(optax.lbfgs(), _too_steep, z)
    for name in ("num_linesearch_steps", "learning_rate", "decrease_error", "curvature_error"):
        assert float(otu.tree_get(ours, name)) == float(otu.tree_get(theirs, name)), name


class _Trial:
    """The fields of optax's zoom state that the watch reads."""

    def __init__(self, t, value, *, slope=-1.0, slope_init=-1.0, curvature_error=1.0):
        self.stepsize, self.value, self.value_init = (jnp.asarray(t), jnp.asarray(value),
                                                      jnp.asarray(0.0))
        self.slope, self.slope_init = jnp.asarray(slope), jnp.asarray(slope_init)
        self.curvature_error = jnp.asarray(curvature_error)


def _watched(trials) -> Contradiction:
    seen = _nothing_seen(jnp.float64)
    for trial in trials:
        seen = _watch(seen, trial)
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
def test_a_contradiction_needs_a_gradient_that_still_says_down_too_steeply(trial_kwargs, why):
    rising = [_Trial(t, 0.3 * t + 2.0 * t * t) for t in (1.0, 0.4)]
    last = _Trial(0.1, 0.3 * 0.1 + 2.0 * 0.01, **trial_kwargs)
    assert not bool(_watched([*rising, last]).found), why


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
        pf.scale_by_zoom_linesearch(**kwargs)


def _quadratic_line(minimum):
    """``J(z) = minimum + |z - 3|^2 / 2`` (``J(0) = minimum + 9/2`` in 1-D): along the first
    direction it is quadratic with the given minimum."""
    def objective(z):
        return minimum + 0.5 * jnp.sum((z - 3.0) ** 2)
    return objective


def test_a_polyak_first_step_ends_the_first_search_after_one_evaluation():
    """On a badly scaled least-squares objective the unit first trial doubles 20 times; the
    trial J / |s_0| is accepted at once, and it is that step exactly."""
    z = jnp.zeros(3)
    value, grad, updates, state = _one_search(pf.lbfgs(first_step="polyak"), _badly_scaled, z)
    assert int(otu.tree_get(state, "num_linesearch_steps")) == 1
    direction = -grad  # L-BFGS's first direction: the bare gradient
    slope = float(jnp.vdot(direction, grad))
    np.testing.assert_allclose(updates, float(value) / -slope * direction, rtol=1e-13)
    *_, unit = _one_search(pf.lbfgs(), _badly_scaled, z)
    assert int(otu.tree_get(unit, "num_linesearch_steps")) == 20


@pytest.mark.parametrize("share, one_evaluation", [(0.0, True), (0.5, True), (0.72, True),
                                                   (0.76, False), (0.9, False)])
def test_the_polyak_trial_meets_the_wolfe_conditions_up_to_the_stated_minimum(share,
                                                                             one_evaluation):
    """The docstring's claim: on a quadratic line with minimum m, one evaluation whenever
    m <= 0.73 J(z_0)."""
    minimum = share * 4.5 / (1.0 - share)  # m = share * J(0), J(0) = m + 4.5
    *_, state = _one_search(pf.lbfgs(first_step="polyak"), _quadratic_line(minimum),
                            jnp.zeros(1))
    assert (int(otu.tree_get(state, "num_linesearch_steps")) == 1) == one_evaluation


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


@pytest.mark.parametrize("break_it", ["no internals", "other arguments", "other state"])
def test_an_optax_without_the_expected_internals_gets_optax_search_and_a_warning(
        monkeypatch, break_it):
    """prdp_fem drives optax's private zoom functions; where an optax moved, renamed or
    reshaped them, `pf.lbfgs()` runs optax's own search (its steps exactly) and says so,
    instead of failing at import or inside a step."""
    from prdp_fem import linesearch

    def other_arguments(**kwargs):
        raise TypeError("zoom_linesearch() got an unexpected keyword argument 'tol'")

    zoom = linesearch._optax_zoom

    def other_state(**kwargs):  # a state without one of the fields read
        init, step, stop = zoom(**kwargs)
        fields = [name for name in init(jnp.ones(1), jnp.zeros(1), value=jnp.ones(()),
                                        grad=jnp.ones(1))._fields if name != "safe_grad"]
        reduced = collections.namedtuple("ZoomLinesearchState", fields)

        def reduced_init(*args, **kw):
            return reduced(*(getattr(init(*args, **kw), name) for name in fields))
        return reduced_init, step, stop

    monkeypatch.setattr(linesearch, "_optax_zoom", {"no internals": None,
                                                    "other arguments": other_arguments,
                                                    "other state": other_state}[break_it])
    z = jnp.array([-3.0, 4.0, -2.0, 3.0])
    with pytest.warns(RuntimeWarning, match="does not stop on a contradicted gradient; "
                      "first_step='polyak' is ignored"):
        ours, our_searches = _run(pf.lbfgs(first_step="polyak"), _rosenbrock, z, 6)
    theirs, their_searches = _run(optax.lbfgs(), _rosenbrock, z, 6)
    np.testing.assert_array_equal(ours, theirs)
    assert our_searches == their_searches
