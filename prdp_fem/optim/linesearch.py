r"""A zoom line search that gives up once the values contradict the gradient.

optax's zoom line search (strong Wolfe conditions, Nocedal and Wright's algorithms 3.5 and
3.6) assumes that the gradient ``g`` is the derivative of the value ``J``. A *truncated*
adjoint gradient is not: at a small ``K`` the slope ``s_0 = g.d`` along the search direction
``d`` can say "down" where ``J(z + t d)`` goes up. No step then meets the conditions, and
the search spends all its ``max_linesearch_steps`` evaluations (20 in :func:`optax.lbfgs`)
shrinking ``t`` towards zero. For PRDP such a failure is the signal to refine ``K``
(``stall_on_failure``), so those evaluations buy nothing.

:func:`scale_by_zoom_linesearch` runs optax's own search steps (its zoom search's init and
step functions, which optax's public transform runs inside its loop: a vendored copy in
:mod:`prdp_fem.optim._zoom`) and stops once the values
slope *up* at ``t = 0``: three successive trials ``t_1 > t_2 > t_3`` all raise the value,
the slope at ``t = 0`` of the parabola through ``J(0)`` and two successive trials,

.. math::

    \hat s_i = \frac{m_{i+1} t_i - m_i t_{i+1}}{t_i - t_{i+1}},
    \qquad m_i = \frac{J(t_i) - J(0)}{t_i},

is positive for both pairs and agrees within a factor two, and at ``t_3`` either

- the gradient's slope has the sign of ``s_0 < 0`` and fails the curvature condition
  ``|g(t_3).d| <= c_2 |s_0|``: then no smaller step meets the sufficient decrease (the values
  rise) nor, with the gradient's slope running from ``s_0`` to ``g(t_3).d``, the curvature
  condition, which optax's approximate (Hager-Zhang) decrease would otherwise let through;
  optax's search would fail too, after more evaluations; or
- the value has risen by more than the approximate decrease's tolerance,
  ``J(t_3) - J(0) > \epsilon |J(0)|`` (``approx_dec_rtol``), and the gradient's slope there
  lies below the values' secant slope, ``g(t_3).d < m_3``: the gradient contradicts the
  values at ``t_3`` as well as at ``0``. What optax's search may still accept below ``t_3``
  (the values slope up there) is a step that raises ``J`` by up to ``\epsilon |J(0)|``, no
  progress and, for PRDP, the failure it is.

For a correct gradient the first cannot happen where the secant slope ``m(t)`` is convex on
``[0, t_1]`` (a quadratic ``J`` included): the linear extrapolation of ``m`` to ``t = 0`` then
stays below ``m(0) = s_0 < 0``. The second cannot happen where ``J`` is convex on
``[0, t_3]``, since then ``J'(t_3) >= m_3``: a kink of size ``1/100`` such as a smoothed
total variation's makes the secant slope concave and the values seem to rise from ``t = 0``,
but its gradient's slope at ``t_3`` stays above the secant's. The converged reference runs of
the built-in scenes take the same steps with it as with optax's search, to round-off (the
mother problem's run amplifies it: 88 evaluations instead of 90, the same error).

The search then ends the way optax's own failure does, minus the wasted evaluations: with
the best trial that met the sufficient decrease if there is one, else a zero step (the
value and gradient at the start), and a positive decrease or curvature error, so that
:func:`prdp_fem.inverse.driver.invert` counts the step as failed.

Each evaluation is an :class:`Evaluation`: the value, the gradient, the solver iterations it
ran and, where the objective keeps one, its *warm start* -- what the next evaluation's solves
start from (:class:`prdp_fem.inverse.WarmStart`: the state and adjoint solutions). The search
keeps the last trial's in its state (``ZoomSearchState.warm_start``), for the next step.

One more departure, only in the first search after the objective changed (the stored value
is ``inf`` although a search has run: :func:`prdp_fem.inverse.driver.invert` does that when PRDP
refines ``K``): L-BFGS's direction then comes from another objective's curvature pairs and
can be thousands of times too long. Where the first trial ``t`` overshoots so far that the
minimiser of the quadratic through ``J(0)``, ``s_0`` and ``J(t)``,

.. math::

    t_q = \frac{-s_0 t^2}{2 (J(t) - J(0) - s_0 t)},

lies below ``t / 10`` (where optax's zoom discards it and bisects, one halving per
evaluation), the search starts afresh at ``max(t_q, 10^{-3} t)``; where ``J(t)`` is not
finite (the trial left the domain, e.g. an overflowing coefficient), at ``t / 10``, again
while it stays so. All trials count against ``max_linesearch_steps``. Everywhere else,
every step, value and gradient is optax's.

One more entry: handed a non-finite ``value`` (none yet, or marked stale), the search
evaluates ``J`` and its gradient at ``params`` instead of searching, and returns a zero update
with a :class:`ZoomSearchState` that stores them. :func:`prdp_fem.inverse.driver.invert` then calls
the same update again with them (``prdp_fem.inverse.steps.value_grad_and_update``): the
step's program holds the objective once, in the search's loop, instead of once more for the
value at the start.

A gradient with the wrong sign: optax's search spends its 20 evaluations, this one three.

>>> import jax, jax.numpy as jnp, optax, optax.tree_utils as otu
>>> @jax.custom_jvp
... def J(z):
...     return jnp.sum((z - 1.0) ** 2)
>>> @J.defjvp
... def J_jvp(primals, tangents):
...     (z,), (dz,) = primals, tangents
...     return J(z), -jnp.sum(2.0 * (z - 1.0) * dz)
>>> def evaluations_and_step(opt):
...     z = jnp.zeros(2); value, grad = jax.value_and_grad(J)(z)
...     updates, state = opt.update(grad, opt.init(z), z, value=value, grad=grad,
...                                 value_fn=J)
...     return int(otu.tree_get(state, "num_linesearch_steps")), float(jnp.abs(updates).max())
>>> evaluations_and_step(optax.lbfgs())[0]
20
>>> evaluations_and_step(lbfgs())
(3, 0.0)
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

# the search's init/step/stop functions: optax's transform hides them in its loop, so they
# are a vendored copy of optax's (see prdp_fem.optim._zoom)
from ..linalg.cg import zero_counts
from ._zoom import zoom_linesearch as _optax_zoom

__all__ = ["FIRST_STEPS", "Contradiction", "Evaluation", "ZoomSearchState", "evaluation",
           "has_search_state", "lbfgs", "scale_by_zoom_linesearch", "search_warm_start",
           "with_warm_start_slot"]

#: The first line search's initial trial: optax's unit step, or ``J(z_0) / |s_0|``.
FIRST_STEPS = ("unit", "polyak")


class ZoomSearchState(NamedTuple):
    """optax's zoom-search state (:class:`optax.ScaleByZoomLinesearchState`'s fields, read the
    same way: :func:`optax.value_and_grad_from_state`, ``tree_get``) and ``counts``. Its type
    says that the search refreshes a non-finite ``value``: it evaluates ``J`` and its
    gradient at ``params``, stores them here and returns a zero update (see the module's
    docstring).

    ``counts``: the solver iterations the last update's evaluations ran, where ``value_fn``
    reports them (an ``evaluate`` method, as :class:`prdp_fem.inverse.driver.Objective` has:
    ``[primal, adjoint, primal_solves, adjoint_solves]``, see
    :class:`prdp_fem.linalg.ReverseTally`); zeros otherwise.

    ``warm_start``: the last evaluation's warm start (:class:`Evaluation`), ``None`` where the
    objective keeps none. Its slot must have the evaluations' type before the first update
    (:func:`with_warm_start_slot`): a loop carries the state, and a compiled step takes it.
    """

    learning_rate: jax.Array
    value: jax.Array
    grad: Any
    info: optax.ZoomLinesearchInfo
    counts: jax.Array
    warm_start: Any = None


class Evaluation(NamedTuple):
    """One evaluation of the objective: what a line search's trial computes.

    ``counts``: the solver iterations it ran (zeros where the objective counts them
    elsewhere); ``warm_start``: where the objective's next evaluation should start its solves
    from (``None`` for an objective that keeps none).
    """

    value: jax.Array
    grad: Any
    counts: jax.Array
    warm_start: Any = None


class Contradiction(NamedTuple):
    """What the search has seen of the values against the gradient.

    ``stepsizes``/``rises``: the last two trial steps and ``J(t) - J(0)`` there (oldest
    first; zero before any trial); ``extrapolated_slope``: the last parabola's slope at
    ``t = 0`` (NaN unless the last two trials both rose and shrank); ``found``: the values
    slope up where the gradient says down (the search stops).
    """

    stepsizes: jax.Array
    rises: jax.Array
    extrapolated_slope: jax.Array
    found: jax.Array


def _nothing_seen(dtype) -> Contradiction:
    return Contradiction(stepsizes=jnp.zeros(2, dtype), rises=jnp.zeros(2, dtype),
                         extrapolated_slope=jnp.asarray(jnp.nan, dtype),
                         found=jnp.asarray(False))


def _watch(seen: Contradiction, state, approx_dec_rtol: float | None = 1e-6) -> Contradiction:
    """``seen`` updated with the trial the search has just made (optax's state);
    ``approx_dec_rtol`` is the search's (``None``: no approximate decrease)."""
    t, rise = state.stepsize, state.value - state.value_init
    t_last, rise_last = seen.stepsizes[1], seen.rises[1]
    both_rising = (t > 0) & (t < t_last) & (rise > 0) & (rise_last > 0)
    slope = (rise * t_last / t - rise_last * t / t_last) / jnp.where(both_rising,
                                                                     t_last - t, 1.0)
    slope = jnp.where(both_rising, slope, jnp.nan)
    previous = seen.extrapolated_slope
    uphill = (slope > 0) & (previous > 0) & (slope <= 2 * previous) & (previous <= 2 * slope)
    # the gradient still says down, too steeply for the curvature condition
    steep = (state.slope * state.slope_init > 0) & (state.curvature_error > 0)
    # a rise no approximate decrease forgives, with a gradient's slope below the secant's:
    # for a correct gradient and a J convex on [0, t], J'(t) >= (J(t) - J(0)) / t
    tolerance = 0.0 if approx_dec_rtol is None else approx_dec_rtol * jnp.abs(state.value_init)
    below_secant = (t > 0) & (state.slope * t < rise)
    return Contradiction(stepsizes=jnp.stack([t_last, t]), rises=jnp.stack([rise_last, rise]),
                         extrapolated_slope=slope,
                         found=uphill & (steep | ((rise > tolerance) & below_secant)))


def _give_up(state, curv_rtol: float):
    """End a contradicted search: its best trial with sufficient decrease, else no step.

    The errors reported are the returned step's: at the safe trial the decrease error is zero
    and the curvature error positive (else the search would have stopped there, done); with
    no safe trial, the last trial's, one of them positive (the search was not done).
    """
    safe = state.safe_stepsize > 0
    slope_safe = optax.tree.real(optax.tree.vdot(state.updates, state.safe_grad))
    curvature_safe = jnp.maximum(jnp.abs(slope_safe) - curv_rtol * jnp.abs(state.slope_init),
                                 0.0)
    ended = state._replace(stepsize=jnp.where(safe, state.safe_stepsize, 0.0),
                           value=state.safe_value, grad=state.safe_grad,
                           decrease_error=jnp.where(safe, 0.0, state.decrease_error),
                           curvature_error=jnp.where(safe, curvature_safe,
                                                     state.curvature_error),
                           failed=jnp.asarray(True))
    return optax.tree.cast_like(ended, other_tree=state)  # float32 parameters stay float32


def scale_by_zoom_linesearch(max_linesearch_steps: int = 20, *,
                             max_learning_rate: float | None = None,
                             slope_rtol: float = 1e-4, curv_rtol: float = 0.9,
                             increase_factor: float = 2.0,
                             approx_dec_rtol: float | None = 1e-6,
                             stepsize_precision: float = 1e-5,
                             initial_guess_strategy: str = "one",
                             first_step: str = "unit",
                             ) -> optax.GradientTransformationExtraArgs:
    r"""optax's :func:`optax.scale_by_zoom_linesearch` that stops on a contradiction and,
    after the objective changed, restarts a far overshoot (see the module's docstring).

    The arguments are optax's (the defaults are those :func:`optax.lbfgs` uses; extra update
    arguments go on to ``value_fn`` as keywords); the state is a :class:`ZoomSearchState`,
    with the fields of :class:`optax.ScaleByZoomLinesearchState`, so
    :func:`optax.value_and_grad_from_state` and the failure test of
    :func:`prdp_fem.inverse.driver.invert` read it as they read optax's. A
    non-finite ``value`` asks for ``J`` and its gradient at ``params`` instead of a search
    (see the module's docstring).

    ``first_step`` picks the first search's initial trial: ``"unit"`` (optax's: ``t = 1``)
    or ``"polyak"``, where the linear model of a nonnegative objective reaches zero,

    .. math::

        t_0 = \frac{J(z_0)}{|s_0|}, \qquad s_0 = g_0 \cdot d_0 < 0

    (``"unit"`` where ``J(z_0) <= 0`` or ``s_0 >= 0``). L-BFGS's first direction is the bare
    gradient, whose length has nothing to do with the step; from ``t = 1`` the search doubles
    ``t`` once per evaluation (20 evaluations, the cap, on the ``inclusion`` and ``mother``
    scenes). Where ``J`` is quadratic along the line with minimum ``m``, ``t_0`` meets both
    strong Wolfe conditions (optax's constants) whenever ``m <= 0.73 J(z_0)``, so the first
    search ends after one evaluation; for a least-squares objective, ``t_0`` is half the step
    to a zero-residual minimum. Later searches are unchanged.
    """
    if not (isinstance(max_linesearch_steps, int) and max_linesearch_steps >= 1):
        raise ValueError(f"max_linesearch_steps={max_linesearch_steps!r}: expected an "
                         "integer >= 1")
    if initial_guess_strategy not in ("one", "keep"):
        raise ValueError(f"initial_guess_strategy={initial_guess_strategy!r}: expected "
                         "'one' or 'keep'")
    if first_step not in FIRST_STEPS:
        raise ValueError(f"first_step={first_step!r}: expected one of {FIRST_STEPS}")
    # optax's own search, with the same settings: the state, and so its init, are its own
    optax_search = optax.scale_by_zoom_linesearch(
        max_linesearch_steps, max_learning_rate=max_learning_rate, increase_factor=increase_factor,
        slope_rtol=slope_rtol, curv_rtol=curv_rtol, approx_dec_rtol=approx_dec_rtol,
        stepsize_precision=stepsize_precision, initial_guess_strategy=initial_guess_strategy)
    init_search, step_search, searching = _optax_zoom(
        max_linesearch_steps=max_linesearch_steps, max_stepsize=max_learning_rate,
        tol=0.0, increase_factor=increase_factor, slope_rtol=slope_rtol,
        curv_rtol=curv_rtol, approx_dec_rtol=approx_dec_rtol,
        interval_threshold=stepsize_precision, verbose=False)

    def init(params):
        return ZoomSearchState(*optax_search.init(params), counts=zero_counts(), warm_start=None)

    def update(updates, state, params, *, value, grad,
               value_fn: Callable[..., Any], **value_fn_kwargs):
        evaluate = _evaluation(value_fn, value_fn_kwargs)
        # no value to search from: evaluate at params, through the trial below (one copy of
        # the objective in the program), and return it (see the module's docstring)
        value = jnp.asarray(value)
        refresh = ~jnp.isfinite(value)
        guess = jnp.asarray(1.0) if initial_guess_strategy == "one" else state.learning_rate
        if first_step == "polyak":
            guess = _polyak_first_guess(state, updates, value, grad, guess)
        def start_at(stepsize):
            return init_search(updates, params, value=value, grad=grad,
                               prev_stepsize=stepsize, initial_guess_strategy="keep")

        start = start_at(guess)
        # invert stores inf when PRDP changed the objective (see the module's docstring)
        objective_changed = ~jnp.isfinite(state.value) & \
            (state.info.num_linesearch_steps > 0)

        def going_on(carry):
            search, seen, spent, _, _ = carry
            searches_on = searching(search) & ~seen.found & \
                (spent + search.count < max_linesearch_steps)
            return jnp.where(refresh, search.count < 1, searches_on)

        def trial(carry):
            search, seen, spent, _, counts = carry
            search, evaluated = _step_with_one_evaluation(step_search, search, evaluate,
                                                          value_fn_kwargs, at_start=refresh)
            counts = counts + evaluated[2]
            seen = _watch(seen, search, approx_dec_rtol)
            overshot, restart_at = _overshoot(search)
            restart = objective_changed & overshot & ~seen.found & ~refresh & \
                (spent + search.count < max_linesearch_steps)
            spent = spent + jnp.where(restart, search.count, 0)
            search = jax.lax.cond(
                restart, lambda s: optax.tree.cast_like(start_at(restart_at), other_tree=s),
                lambda s: s, search)
            return search, seen, spent, evaluated, counts

        dtype = jnp.result_type(start.value_init)
        not_yet = _filled_evaluation(evaluate, params, jnp.nan)
        final, seen, spent, (value_there, grad_there, _, warm_there), counts = jax.lax.while_loop(
            going_on, trial, (start, _nothing_seen(dtype), jnp.zeros_like(start.count),
                              not_yet, zero_counts()))
        final = jax.lax.cond(seen.found & ~refresh,
                             functools.partial(_give_up, curv_rtol=curv_rtol),
                             lambda s: s, final)
        # only the cap on all trials stops a search that is still going (after restarts)
        final = jax.lax.cond(searching(final) & ~seen.found & ~refresh, _out_of_trials,
                             lambda s: s, final)
        info = optax.ZoomLinesearchInfo(num_linesearch_steps=spent + final.count,
                                        decrease_error=final.decrease_error,
                                        curvature_error=final.curvature_error)
        # the last trial's warm start: the accepted step's, or close to it (a search that
        # gives up returns an earlier trial)
        searched = ZoomSearchState(learning_rate=final.stepsize, value=final.value,
                                   grad=final.grad, info=info, counts=counts,
                                   warm_start=warm_there)
        refreshed = state._replace(value=value_there, grad=grad_there, counts=counts,
                                   warm_start=warm_there)
        new_state = optax.tree.where(refresh, optax.tree.cast_like(refreshed, other_tree=state),
                                     optax.tree.cast_like(searched, other_tree=state))
        step = optax.tree.where(refresh, optax.tree.zeros_like(updates),
                                optax.tree.scale(final.stepsize, updates))
        return step, new_state

    return optax.GradientTransformationExtraArgs(init, update)


#: optax's zoom discards an interpolated step within this share of the interval from an end
#: and bisects instead (its ``quad_chk``)
_ZOOM_MARGIN = 0.1
#: the most a restart shrinks the first trial: a non-quadratic rise can put t_q far too low
_LEAST_RESTART = 1e-3
#: a first trial with a non-finite value restarts this much shorter (and again, while the
#: values stay non-finite): a tenth per evaluation where the zoom bisects, a half
_OUTSIDE_SHRINK = 0.1


def evaluation(value_fn, value_fn_kwargs=None) -> Callable:
    """``point -> Evaluation``: the one ``value_fn`` carries as its ``evaluate``
    (:class:`prdp_fem.inverse.driver.Objective`: the counts of its solves as outputs, its warm
    start, and one nested program for every place that evaluates, traced once), else its
    ``value_and_grad`` or ``jax.value_and_grad(value_fn)``, with zero counts (the solves
    count wherever ``value_fn`` counts them, such as an
    :class:`~prdp_fem.linalg.IterationCounter`) and no warm start."""
    value_fn_kwargs = value_fn_kwargs or {}
    own = getattr(value_fn, "evaluate", None)
    if callable(own) and not value_fn_kwargs:
        return own
    value_and_grad = getattr(value_fn, "value_and_grad", None)
    if not callable(value_and_grad) or value_fn_kwargs:
        value_and_grad = jax.value_and_grad(value_fn)

    def uncounted(point, **kwargs):
        return Evaluation(*value_and_grad(point, **kwargs), zero_counts())

    return uncounted


def search_warm_start(opt_state) -> Any:
    """The warm start of the last evaluation a :class:`ZoomSearchState` in ``opt_state`` holds
    (``None`` without one)."""
    for node in _search_states(opt_state):
        return node.warm_start
    return None


def with_warm_start_slot(opt_state, warm_start):
    """``opt_state`` with the :class:`ZoomSearchState` 's ``warm_start`` set to ``warm_start``
    (an initial guess with the evaluations' type: zeros are a cold start)."""
    def replace(node):
        return node._replace(warm_start=warm_start) if isinstance(node, ZoomSearchState) \
            else node
    return jax.tree_util.tree_map(replace, opt_state, is_leaf=_is_search_state)


def has_search_state(opt_state) -> bool:
    """Whether ``opt_state`` holds a :class:`ZoomSearchState` (:func:`lbfgs` 's search)."""
    return bool(_search_states(opt_state))


def _is_search_state(node) -> bool:
    return isinstance(node, ZoomSearchState)


def _search_states(opt_state) -> list:
    return [node for node in jax.tree_util.tree_leaves(opt_state, is_leaf=_is_search_state)
            if isinstance(node, ZoomSearchState)]


def _evaluation(value_fn, fn_kwargs) -> Callable:
    """``point -> Evaluation`` (:func:`evaluation`), jitted once per search so that its
    trace for the placeholders' types (:func:`_filled_evaluation`: exactly as the evaluation
    returns them, no cast) is the one the search's loop calls."""
    evaluate = evaluation(value_fn, fn_kwargs)
    return jax.jit(lambda point: evaluate(point, **fn_kwargs))


def _filled_evaluation(evaluate: Callable, params, value: float) -> Evaluation:
    """An :class:`Evaluation` 's types at ``params``, filled with ``J = value``, ``g = 0``,
    no counts and a zero warm start (nothing is computed)."""
    shapes = jax.eval_shape(evaluate, params)

    def zeros(tree):
        return jax.tree_util.tree_map(lambda leaf: jnp.zeros(leaf.shape, leaf.dtype), tree)

    return Evaluation(jnp.full(shapes.value.shape, value, shapes.value.dtype),
                      zeros(shapes.grad), zeros(shapes.counts), zeros(shapes.warm_start))


def _step_with_one_evaluation(step_search, search, evaluate, fn_kwargs,
                              at_start: jax.Array | bool = False):
    """optax's search step ``step_search(search, ...)``, with the objective's evaluation
    ``evaluate`` (:func:`_evaluation`) in the program once instead of once in each branch of
    the step's ``cond`` (bracket or zoom).

    Each branch picks its trial step ``t`` from the state alone, then evaluates at
    ``z + t d``. So the step runs twice in a loop: first with a stand-in evaluation,
    ``J = -inf`` and ``g = 0``, which meets both Wolfe conditions, so that the search neither
    fails nor falls back to its safe step and the result's ``stepsize`` is the trial ``t``;
    ``evaluate`` runs there, once; then with that value and gradient, the same
    arithmetic on the same state, so the same ``t``. For float64 parameters these are
    optax's trial steps exactly (its values to round-off: the objective is compiled in
    another place of the program). Float32 parameters are evaluated at a float32 point,
    where optax's zoom forms ``z + t d`` with a float64 ``t``.

    The stand-in cannot meet the conditions where ``J(0)`` is NaN or ``-inf`` or the slope
    ``s_0`` (or ``t s_0``) is not finite; a search then stops at its last trial or at its safe
    step, so the evaluation may land there instead of at ``t``. Such a search is lost anyway
    (and :func:`prdp_fem.inverse.driver.invert` stops on a non-finite value or gradient).

    Returns the stepped state and the :class:`Evaluation`. ``at_start`` (traced): evaluate
    at the search's ``params`` instead of the trial point (a refresh; the state's step is then
    meaningless).

    Why: XLA inlines every call of the evaluation, a CG solve and its adjoint solve (an AMG
    cycle inside each), and compiles each of its kernels separately. One copy instead of
    two took 7 % off the backend compile of an L-BFGS step with Jacobi-PCG and 18 % with AMG;
    the step logic written out twice instead of the loop lost on Jacobi (see the
    performance log).
    """
    stand_in = _filled_evaluation(evaluate, search.params, -jnp.inf)

    def run(carry):
        trip, values, _ = carry
        stepped = step_search(search, value_and_grad_fn=lambda *_, **__: values[:2],
                              fn_kwargs=fn_kwargs)
        trial = optax.tree.where(
            at_start, search.params,
            optax.tree.add_scale(search.params, stepped.stepsize, search.updates))
        values = jax.lax.cond(trip == 0, lambda: evaluate(trial), lambda: values)
        return trip + 1, values, stepped

    _, values, stepped = jax.lax.while_loop(lambda c: c[0] < 2, run,
                                            (jnp.zeros((), jnp.int32), stand_in, search))
    return stepped, values


def _overshoot(search):
    """Whether the search's first trial overshot beyond its zoom's reach, and the step to
    start afresh from: ``max(t_q, 1e-3 t)``, ``t_q`` the minimiser of the quadratic through
    ``J(0)``, ``s_0`` and ``J(t)`` (see the module's docstring); ``t / 10`` where ``J(t)`` is
    not finite (no quadratic to fit: the zoom would halve, ten evaluations per 1000x)."""
    t, s0 = search.stepsize, search.slope_init
    rise = search.value - search.value_init
    excess = rise - s0 * t  # the quadratic's c t^2: positive where t failed the decrease
    quadratic = -s0 * t * t / (2.0 * jnp.where(excess > 0, excess, 1.0))
    first = (search.count == 1) & ~search.done & ~search.failed & (s0 < 0)
    finite = jnp.isfinite(rise)
    far = search.interval_found & (search.decrease_error > 0) & finite & (excess > 0) & \
        (quadratic < _ZOOM_MARGIN * t)
    outside = ~finite & jnp.isfinite(search.value_init)  # the trial left the domain
    restart_at = jnp.where(finite, jnp.maximum(quadratic, _LEAST_RESTART * t),
                           _OUTSIDE_SHRINK * t)
    return first & (far | outside), restart_at


def _out_of_trials(state):
    """End a search that spent all its trials as optax's does (its ``_try_safe_step``): at
    the best trial with sufficient decrease, or where the last trial left the domain, else
    at the last trial; failed."""
    use_safe = (state.safe_stepsize > 0) | jnp.isinf(state.decrease_error)
    stepsize, value, grad = optax.tree.where(
        use_safe, [state.safe_stepsize, state.safe_value, state.safe_grad],
        [state.stepsize, state.value, state.grad])
    ended = state._replace(stepsize=stepsize, value=value, grad=grad,
                           failed=jnp.asarray(True))
    return optax.tree.cast_like(ended, other_tree=state)


def lbfgs(memory_size: int = 10, *, max_linesearch_steps: int = 20,
          first_step: str = "unit") -> optax.GradientTransformationExtraArgs:
    """:func:`optax.lbfgs` with :func:`scale_by_zoom_linesearch` as its line search.

    optax's defaults otherwise (unit initial step, ``scale_init_precond``): on a problem
    whose gradients match its values it takes optax's steps exactly, unless the objective
    changes under it (a far overshoot of the first search after that restarts; see
    :func:`scale_by_zoom_linesearch`). ``first_step="polyak"``
    starts the first line search at ``J(z_0) / |s_0|`` instead (see
    :func:`scale_by_zoom_linesearch`): one evaluation instead of 10-20 for the first step
    of the built-in scenes, and a different path from there on.
    """
    return optax.lbfgs(memory_size=memory_size, linesearch=scale_by_zoom_linesearch(
        max_linesearch_steps, initial_guess_strategy="one", first_step=first_step))


def _polyak_first_guess(state, updates, value, grad, guess):
    """``J / |s_0|`` at the first search (no search has run yet), else ``guess``."""
    slope = optax.tree.real(optax.tree.vdot(updates, grad))
    polyak = value / jnp.where(slope < 0, -slope, 1.0)
    usable = (state.info.num_linesearch_steps == 0) & (slope < 0) & (value > 0) & \
        jnp.isfinite(polyak)
    return jnp.where(usable, polyak, guess)

