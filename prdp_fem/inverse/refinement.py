r"""Refinement controllers: how many CG iterations the next optimisation step gets.

Optax style: a controller is a pair of pure functions over a small NamedTuple state,

    state = controller.init()
    state = controller.update(state, monitored_value)   # once per step or epoch
    state = controller.update(state, monitored_value, failed=True)  # the step failed
    state.iterations, state.adjoint_iterations, state.rtol

jittable (no Python branching on values) and serialisable (:func:`state_to_dict` /
:func:`state_from_dict`, plain JSON types). ``init`` returns host (NumPy) arrays and ``update``
computes with the array module of its arguments: NumPy in a run loop (no dispatch, no
program to compile), ``jnp`` under ``jax.jit`` or on device arrays.

PRDP (Bhatia, Koehler, Thuerey, ICLR 2025) watches a monitored error ``e_1, e_2, ...`` through
an exponential moving average ``s`` (``a = 2 / (window + 1)``, ``s_1 = e_1``,
``s_t = a e_t + (1 - a) s_{t-1}``) and after each value decides

.. math::

    r_t = s_t / s_{t-\delta+1}, \qquad
    \text{refine} \iff t > \delta \;\wedge\; r_t > \tau_\text{step} \;\wedge\;
    \left(s_t / c < \tau_\text{stop} \;\vee\; s_t / c > 1\right),

where the checkpoint ``c`` (initially ``e_1``, or ``initial_checkpoint``) becomes ``s_t`` at every
refinement: refine when
the error has stalled *and* the last refinement bought at least ``1 - tau_stop`` (or things got
worse); a stall without that gain means "K is enough" (``stopped``). As in the reference code
the stop is not latched unless ``latch=True``: a later plateau ``>= 10 %`` lower refines again.

One addition to that rule, opt-in (``stall_on_failure=True``): a *failed optimiser step*
(``update(state, value, failed=True)``: a line search that ended without meeting its
conditions) counts as a stall at once, without waiting for the moving average. With a
truncated solve, the implicit gradient does not match the truncated value; the line search
then fails, and keeps failing at the same ``K``, long before a moving average started orders
of magnitude higher sees the plateau (on the ``inclusion`` scene L-BFGS spent 20 evaluations
per step for 30 steps at ``K = 10``). Such a stall refines when ``s_t / c < tau_stop`` (a
real gain since the last refinement) or while ``K`` is still ``K0`` (nothing judged yet), and
means "enough" otherwise; ``s_t / c > 1`` does not count here, because a truncated loss moves
to another level when ``K`` changes (counting it sent unpreconditioned CG to ``K_max``). The
run's first step is exempt: its line search starts from an arbitrary step size.

Beyond the reference: separate primal and adjoint :class:`Schedule` s, multiplicative growth,
``K_max`` caps, a latched stop, a *tolerance mode* in which refinement divides a relative
residual tolerance instead of raising ``K``, and (opt-in, ``per_learning_rate=True``) a stall
judged per unit learning rate, ``r_t > 1 - (1 - \tau_\text{step})\,\eta_t / \eta_1`` for
the learning rate ``\eta_t`` of the steps behind ``e_t``. A non-finite monitored value counts
as divergence (refine) and is kept out of the moving average.

>>> controller = prdp(K0=10, dK=10, K_max=40)
>>> state = controller.init()
>>> for error in [1.0] * 4 + [0.5] * 12:     # a plateau, then one 50 % lower
...     state = controller.update(state, error)
>>> int(state.iterations), int(state.refinements)
(20, 1)
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
from jax.typing import ArrayLike

from .._arrays import array_module
from ..errors import SolverConfigError

__all__ = [
    "Refinement",
    "RefinementState",
    "Schedule",
    "adaptive_tolerance",
    "converged",
    "fixed",
    "prdp",
    "state_from_dict",
    "state_to_dict",
    "truncation_gap",
]


class Schedule(NamedTuple):
    """An iteration count and how refinement raises it: ``K <- min(ceil(factor K) + dK, K_max)``.

    Additive (the reference): ``factor = 1``. Multiplicative: ``factor > 1``, ``dK = 0``.
    """

    K0: int
    dK: int = 10
    K_max: int = 600
    factor: float = 1.0


class RefinementState(NamedTuple):
    """Everything a controller knows; all fields are arrays (NumPy on the host, ``jnp`` under
    ``jit``; serialisable)."""

    iterations: ArrayLike          # K for the next primal solves
    adjoint_iterations: ArrayLike  # K_adj for the next adjoint solves
    rtol: ArrayLike                # tolerance mode: relative residual tolerance (else 0)
    count: ArrayLike               # finite monitored values seen (t; since the last
    #                                refinement with restart=True)
    ema: ArrayLike                 # the last `delta` moving-average values, oldest first
    checkpoint: ArrayLike          # moving average at the last refinement (e_1 at first)
    refinements: ArrayLike         # refinements so far
    stopped: ArrayLike             # the last stall was judged "K is enough"

    def settings(self) -> tuple[int, int, float]:
        """``(K, K_adj, rtol)`` as Python numbers: the solver of the next step."""
        return int(self.iterations), int(self.adjoint_iterations), float(self.rtol)


class Refinement(NamedTuple):
    """A controller: ``init() -> state`` and ``update(state, value, failed=False) -> state``.

    ``failed`` reports that the optimiser step which produced ``value`` failed (its line
    search ended without meeting its conditions); :func:`prdp` counts it as a stall.

    ``tolerance_mode`` tells the solve loop to read ``state.rtol`` (a converged solve capped at
    ``state.iterations``) instead of a fixed ``K``.

    ``redo`` asks the trainers to discard an epoch whose ``update`` tightened the solves and
    to train it again at the new setting, from the parameters, optimiser state and batch
    order it started with (the discarded work stays counted). A refinement then never leaves
    behind an epoch trained at a level the controller found too coarse.

    The run loops (:func:`~prdp_fem.inverse.driver.invert`, the trainers, ``reduced_cg``) call
    ``update`` eagerly on the host with the state ``init`` returned and a Python float. A
    controller of your own written with ``jnp`` works there too, one JAX operation at a time;
    written with the array module of its arguments, as :func:`prdp` is, it runs as NumPy.
    """

    init: Any
    update: Any
    tolerance_mode: bool = False
    #: what the controller must be fed (``"gradient"``: the norm of the step's gradient), or
    #: ``None``: whatever the run loop's ``monitor`` says
    monitor: str | None = None
    redo: bool = False
    #: feed ``update`` the learning rate of the optimiser steps behind each value relative to
    #: the run's first (``update(state, value, learning_rate_scale=...)``; :func:`prdp` with
    #: ``per_learning_rate=True``): the trainers compute it from their ``learning_rate``
    scaled_by_learning_rate: bool = False
    #: a :func:`truncation_gap` controller's reference: where the trainer runs a reference
    #: pass of its own (a mixed heat run), to ``rtol * reference_factor`` (never tighter than
    #: the validation's tolerance); ``None``: to the validation's tolerance
    reference_factor: float | None = None


def _check_schedule(schedule: Schedule, name: str) -> Schedule:
    K0, dK, K_max, factor = schedule
    ints = all(isinstance(v, int | np.integer) and not isinstance(v, bool) for v in (K0, dK, K_max))
    if not ints or K0 < 0 or dK < 0 or K_max < K0:
        raise SolverConfigError(
            f"{name}={schedule!r}: expected integers 0 <= K0 <= K_max and dK >= 0")
    if not (math.isfinite(factor) and factor >= 1.0):
        raise SolverConfigError(f"{name}.factor={factor!r}: expected a finite number >= 1")
    if dK == 0 and factor == 1.0 and K_max > K0:
        raise SolverConfigError(f"{name}={schedule!r}: dK = 0 and factor = 1 never refine")
    return Schedule(int(K0), int(dK), int(K_max), float(factor))


#: What a host state and value are made of (checked by exact classes: an ABC check of
#: ``jax.Array`` per field costs more than a third of a host update).
def _grow(xp, K, schedule: Schedule):
    grown = xp.ceil(schedule.factor * K.astype(np.float64)).astype(K.dtype) + schedule.dK
    return xp.minimum(grown, schedule.K_max).astype(K.dtype)


def _initial_state(K: int, K_adj: int, rtol: float, delta: int) -> RefinementState:
    return RefinementState(
        iterations=np.asarray(K, np.int32),
        adjoint_iterations=np.asarray(K_adj, np.int32),
        rtol=np.asarray(rtol, np.float64),
        count=np.asarray(0, np.int32),
        ema=np.full(delta, np.nan, np.float64),
        checkpoint=np.asarray(np.nan, np.float64),
        refinements=np.asarray(0, np.int32),
        stopped=np.asarray(False),
    )


def prdp(K0: int = 25, dK: int = 10, K_max: int = 600, *, factor: float = 1.0,
         adjoint: Schedule | None = None, tau_step: float = 0.98, tau_stop: float = 0.9,
         ema_window: int = 6, delta: int = 3, latch: bool = False, restart: bool = False,
         stall_on_failure: bool = False, rtol: float | None = None, rtol_factor: float = 0.1,
         rtol_min: float = 1e-12, initial_checkpoint: float | None = None,
         per_learning_rate: bool = False) -> Refinement:
    """The PRDP controller (reference defaults; see the module docstring for the rule).

    Parameters
    ----------
    K0, dK, K_max, factor
        The primal :class:`Schedule`.
    adjoint
        Its own schedule for ``K_adj`` (refined at the same moments); ``None``: ``K_adj = K``.
    tau_step, tau_stop, ema_window, delta
        Stall threshold, minimum gain per refinement, EMA window, look-back window. The
        reference's window of 6 smooths the noise of stochastic training. The loss of a
        line-search optimiser (L-BFGS, Newton-CG) on one inverse problem falls monotonically
        between refinements: there ``ema_window=2`` calls its stall some ten steps sooner,
        and scene files default to it (:func:`prdp_fem.scene.spec.default_ema_window`; measured
        over noise seeds in the README's "PRDP saving on the built-in scenes").
    latch
        Once a stall is judged "K is enough", never refine again.
    restart
        After each refinement, restart the moving average from the next value, so the next
        decision needs ``delta + 1`` values taken at the new ``K``. Use it when the monitored
        value is the *training loss*, whose level moves when ``K`` does (a truncated solve
        changes the objective): without it, a loss that jumps up after a refinement reads as
        divergence and refines again at once, cascading to ``K_max``. The checkpoint stays the
        average at the refinement: measuring the gain from the first value at the new ``K``
        instead was tried and refined too late (the mother scene's saving fell from 98 % to
        87 %, inclusion's implicit run stalled at ``K = 50``).
    stall_on_failure
        Count a step reported as failed (``update(..., failed=True)``) as a stall at once.
        Off by default (the reference rule, which only reads the moving average): it saves
        much where the line search keeps failing at small K (inclusion scene: 536 -> 211
        evaluations) but refines on isolated failures too (the source example at n = 32:
        2.5x the CG iterations for no gain).
    rtol, rtol_factor, rtol_min
        Tolerance mode when ``rtol`` is given: solves run to ``||r|| <= rtol ||b||`` (capped at
        ``K_max`` iterations) and refinement multiplies ``rtol`` by ``rtol_factor`` down to
        ``rtol_min``.
    initial_checkpoint
        The checkpoint ``c`` before the first refinement. ``None`` (default): the first
        monitored value ``e_1``, so the first stall refines only if the error fell by at least
        ``1 - tau_stop`` since the start (or rose above it). The reference notebooks differ
        here: the 1-D Poisson and Navier-Stokes ones start from ``c = 100``, above any error
        they watch, so their first stall always refines; the 2-D heat one from the first
        error. ``initial_checkpoint=100.0`` with ``ema_window=1, delta=2, tau_step=0.92``
        is the 1-D Poisson notebook's rule (``examples/reference_1d.py``).
    """
    primal = _check_schedule(Schedule(K0, dK, K_max, factor), "schedule")
    dual = None if adjoint is None else _check_schedule(Schedule(*adjoint), "adjoint")
    if not (0 < tau_step and 0 < tau_stop <= 1):
        raise SolverConfigError(
            f"tau_step={tau_step!r}, tau_stop={tau_stop!r}: expected tau_step > 0 and "
            "0 < tau_stop <= 1")
    if not (isinstance(ema_window, int) and ema_window >= 1 and isinstance(delta, int)
            and delta >= 2):
        raise SolverConfigError(
            f"ema_window={ema_window!r}, delta={delta!r}: expected integers >= 1 and >= 2")
    tolerance_mode = rtol is not None
    if tolerance_mode and not (0 < rtol_min <= rtol < 1 and 0 < rtol_factor < 1):
        raise SolverConfigError(
            f"rtol={rtol!r}, rtol_factor={rtol_factor!r}, rtol_min={rtol_min!r}: expected "
            "0 < rtol_min <= rtol < 1 and 0 < rtol_factor < 1")
    if initial_checkpoint is not None and not (
            isinstance(initial_checkpoint, int | float) and not isinstance(initial_checkpoint, bool)
            and math.isfinite(initial_checkpoint) and initial_checkpoint > 0):
        raise SolverConfigError(
            f"initial_checkpoint={initial_checkpoint!r}: expected None or a finite number > 0")
    if not isinstance(per_learning_rate, bool):
        raise SolverConfigError(f"per_learning_rate={per_learning_rate!r}: expected True or "
                                "False")
    checkpoint0 = math.nan if initial_checkpoint is None else float(initial_checkpoint)
    a = 2.0 / (ema_window + 1.0)

    def init() -> RefinementState:
        if tolerance_mode:  # K and K_adj are caps; the tolerance decides
            state = _initial_state(primal.K_max, primal.K_max, rtol, delta)
        else:
            state = _initial_state(primal.K0, primal.K0 if dual is None else dual.K0, 0.0, delta)
        return state._replace(checkpoint=np.asarray(checkpoint0, np.float64))

    def update(state: RefinementState, value, failed=False,
               learning_rate_scale=1.0) -> RefinementState:
        xp = array_module(*state, value, failed, learning_rate_scale)
        if per_learning_rate:
            # the fall a step must keep up shrinks with its size (a scale of 0: only a
            # rising error stalls)
            threshold = 1.0 - (1.0 - tau_step) * xp.maximum(
                xp.asarray(learning_rate_scale, np.float64), 0.0)
        else:
            threshold = tau_step
        with np.errstate(divide="ignore", invalid="ignore"):  # NaN/inf ratios are decided on
            return _decide(xp, state, xp.asarray(value, np.float64), failed, threshold)

    def _decide(xp, state, value, failed, threshold) -> RefinementState:
        finite = xp.isfinite(value)
        first = state.count == 0  # (re)seed the moving average with this value
        previous = state.ema[-1]
        smoothed = xp.where(first, value, a * value + (1.0 - a) * previous)
        shifted = xp.concatenate([state.ema[1:], xp.reshape(smoothed, (1,))])
        ema = xp.where(finite, xp.where(first, value, shifted), state.ema)
        count = state.count + finite.astype(state.count.dtype)
        checkpoint = xp.where(finite & xp.isnan(state.checkpoint), value, state.checkpoint)
        s = ema[-1]
        averaged_stall = (count > delta) & (s / ema[0] > threshold)
        gain = s / checkpoint
        worth_it = (gain < tau_stop) | (gain > 1.0)
        stalled = averaged_stall
        if stall_on_failure:
            # the first step's failure says nothing about K (its line search starts from an
            # arbitrary step size); a later one refines after a real gain, or at K0, where no
            # refinement has been judged yet. Not on gain > 1: after a refinement a truncated
            # loss moves to another level, which is not divergence.
            seen = ~xp.isnan(state.checkpoint) if initial_checkpoint is None else (
                (state.count > 0) | (state.refinements > 0))
            failed = xp.asarray(failed, bool) & seen
            stalled = stalled | failed
            failure_pays = (gain < tau_stop) | (state.refinements == 0)
            worth_it = xp.where(averaged_stall, worth_it, failure_pays)
        may_refine = ~(state.stopped & latch)
        refine = may_refine & ((finite & stalled & worth_it) | ~finite)
        enough = finite & stalled & ~worth_it
        if restart:
            count = xp.where(refine, 0, count).astype(state.count.dtype)
        return _refined(xp, state, refine, enough, ema, count,
                        xp.where(refine & finite, s, checkpoint))

    def _refined(xp, state, refine, enough, ema, count, checkpoint) -> RefinementState:
        K, K_adj, tolerance = state.iterations, state.adjoint_iterations, state.rtol
        if tolerance_mode:
            tolerance = xp.where(refine, xp.maximum(tolerance * rtol_factor, rtol_min),
                                 tolerance)
        else:
            K = xp.where(refine, _grow(xp, K, primal), K)
            K_adj = K if dual is None else xp.where(refine, _grow(xp, K_adj, dual), K_adj)
        stopped = state.stopped | enough if latch else xp.where(
            refine, False, state.stopped | enough)
        return RefinementState(
            iterations=K, adjoint_iterations=K_adj, rtol=tolerance, count=count, ema=ema,
            checkpoint=checkpoint,
            refinements=state.refinements + refine.astype(state.refinements.dtype),
            stopped=stopped)

    return Refinement(init, update, tolerance_mode, scaled_by_learning_rate=per_learning_rate)


def fixed(K: int, K_adj: int | None = None) -> Refinement:
    """A fixed iteration count (``K_adj = K`` unless given); ``update`` only counts values."""
    _check_schedule(Schedule(K, 0, K), "schedule")
    K_adj = K if K_adj is None else K_adj
    _check_schedule(Schedule(K_adj, 0, K_adj), "adjoint")
    return Refinement(lambda: _initial_state(K, K_adj, 0.0, 2), _count_only)


def converged(rtol: float = 1e-10, max_iterations: int = 100_000) -> Refinement:
    """Every solve (primal and adjoint) to ``||r|| <= rtol ||b||``; the reference baseline."""
    if not (0 < rtol < 1) or not (isinstance(max_iterations, int) and max_iterations > 0):
        raise SolverConfigError(
            f"rtol={rtol!r}, max_iterations={max_iterations!r}: expected 0 < rtol < 1 and a "
            "positive integer cap")
    return Refinement(lambda: _initial_state(max_iterations, max_iterations, rtol, 2),
                      _count_only, tolerance_mode=True)


def adaptive_tolerance(rtol0: float = 1e-2, *, power: float = 1.0, rtol_min: float = 1e-10,
                       failure_factor: float = 0.1, max_iterations: int = 100_000
                       ) -> Refinement:
    r"""A residual-aware controller: every solve runs to a relative tolerance that follows the
    gradient, so that the truncation error stays small against the gradient it perturbs.

    Inexact-gradient theory: a gradient with error ``e`` still descends while
    ``||e|| < ||g||``, and the error of an adjoint gradient is bounded by the primal and
    adjoint residuals. So the tolerance of the next step's primal and adjoint solves is

    .. math::

        \text{rtol}_{k+1} = \min\left(\text{rtol}_k,\;
        \max\left(\text{rtol}_\min,\; \text{rtol}_0 \left(\|g_k\| / \|g_1\|\right)^p\right)\right),

    never loosened. A step whose line search failed (``update(..., failed=True)``) tightens it
    by ``failure_factor`` at once: its gradient was not good enough. Unlike :func:`prdp` with a
    fixed ``K``, the solves converge as the optimisation does, so a run ends at the converged
    problem's optimum rather than at a nearby stationary point of the truncated one.

    It must be fed the norm of the step's gradient (``monitor = "gradient"``, which
    :func:`~prdp_fem.inverse.driver.invert` picks for it). ``state.iterations`` is the cap
    ``max_iterations``; ``state.rtol`` the tolerance; ``state.checkpoint`` the first gradient
    norm.

    >>> controller = adaptive_tolerance(1e-2, rtol_min=1e-8)
    >>> state = controller.init()
    >>> for gradient_norm in [1.0, 0.1, 0.2, 1e-4]:
    ...     state = controller.update(state, gradient_norm)
    ...     print(f"{float(state.rtol):.0e}")
    1e-02
    1e-03
    1e-03
    1e-06
    """
    if not (0 < rtol_min <= rtol0 < 1 and 0 < failure_factor < 1 and math.isfinite(power)
            and power > 0):
        raise SolverConfigError(
            f"rtol0={rtol0!r}, rtol_min={rtol_min!r}, failure_factor={failure_factor!r}, "
            f"power={power!r}: expected 0 < rtol_min <= rtol0 < 1, 0 < failure_factor < 1 "
            "and power > 0")
    _check_cap(max_iterations)

    def init() -> RefinementState:
        return _initial_state(max_iterations, max_iterations, rtol0, 2)

    def update(state: RefinementState, value, failed=False) -> RefinementState:
        xp = array_module(*state, value, failed)
        value = xp.asarray(value, np.float64)
        finite = xp.isfinite(value) & (value > 0)
        checkpoint = xp.where(finite & xp.isnan(state.checkpoint), value, state.checkpoint)
        with np.errstate(divide="ignore", invalid="ignore"):
            followed = rtol0 * (value / checkpoint) ** power
        target = xp.where(finite, xp.clip(followed, rtol_min, rtol0), state.rtol)
        # a failed line search (after the first step, whose search starts from an arbitrary
        # step size) or a non-finite gradient: the solves were not accurate enough
        failed = (xp.asarray(failed, bool) & ~xp.isnan(state.checkpoint)) | \
            ~xp.isfinite(value)
        target = xp.where(failed, xp.minimum(target, state.rtol * failure_factor), target)
        rtol = xp.maximum(xp.minimum(state.rtol, target), rtol_min)
        tightened = rtol < state.rtol
        return state._replace(
            rtol=rtol, checkpoint=checkpoint,
            count=state.count + finite.astype(state.count.dtype),
            refinements=state.refinements + tightened.astype(state.refinements.dtype))

    return Refinement(init, update, tolerance_mode=True, monitor="gradient")


def truncation_gap(rtol: float = 1e-2, *, max_gap: float = 0.01, rtol_factor: float = 0.1,
                   rtol_min: float = 1e-10, max_iterations: int = 100_000,
                   redo: bool = True, reference_factor: float | None = 1e-2) -> Refinement:
    r"""Refine a training's solves while they still change what is measured: every solve
    runs to ``rtol``, and after each epoch the trainer feeds the *truncation gap*

    .. math::

        \gamma = \left| e_\text{rtol} / e_\text{converged} - 1 \right|,

    the relative change of the validation error when the validation rollouts (or solves) run
    at the training's ``rtol`` instead of converged (a mixed heat run, whose rollouts run no
    solver: the bound :func:`~prdp_fem.learning.heat.chain_gap` on that change for its
    training chain over the validation windows). ``rtol`` is multiplied by ``rtol_factor``
    (down to ``rtol_min``) each time ``gamma > max_gap``, and never loosened.

    Why not :func:`prdp`'s rule: PRDP refines at a stall of the validation error when the
    last refinement bought ``1 - tau_stop`` of it. Under a decaying learning rate the error
    keeps falling whatever the solves, so every stall reads as a paying refinement and the
    solves are driven to near convergence long after truncation stopped mattering. The gap
    measures the truncation itself: early on, a coarse solve's error is small beside the
    network's; as the network improves the same truncation becomes visible and the solves
    tighten; once a level changes the validation error by less than ``max_gap`` they stay.

    ``redo`` (default): an epoch whose gap tightened the solves is trained again at the new
    level (:class:`Refinement`'s ``redo``). The gap grows fastest in the first epoch -- an
    untrained network cannot see a level it sees one epoch later -- and an epoch trained at
    a level the network can see leaves the trained network off the converged run's, so the
    first level finds itself at the cost of the discarded epoch. ``redo=False`` keeps the
    epoch and refines from the next.

    It must be fed the gap (``monitor = "truncation_gap"``): the trainers of
    :mod:`prdp_fem.learning` (``heat.train``, ``learned.train``) compute it from one extra
    validation pass at the training's tolerance, counted with the validation solves; an
    inversion (:func:`~prdp_fem.inverse.driver.invert`) refuses it. ``state.rtol`` is the
    tolerance, ``state.iterations`` the cap ``max_iterations``, ``state.checkpoint`` the last
    gap fed.

    ``reference_factor``: where the trainer has no converged validation to compare with (a
    mixed heat run validates an emulator that runs no solver, so both of its chain passes are
    extra), the reference chain runs to ``rtol * reference_factor`` (never tighter than the
    validation's tolerance) instead of converged. CG's error falls about in proportion to its
    tolerance, so the gap measured is the converged reference's to within about
    ``reference_factor`` of itself (1 % at the default) for a fraction of the iterations;
    ``None`` compares with converged chains. Where the validation runs the solver the
    reference is the converged validation itself, free, and this is not used.

    >>> controller = truncation_gap(1e-2, max_gap=0.01)
    >>> state = controller.init()
    >>> for gap in [0.002, 0.03, 0.004, 0.02]:
    ...     state = controller.update(state, gap)
    ...     print(f"{float(state.rtol):.0e}")
    1e-02
    1e-03
    1e-03
    1e-04
    """
    if not (0 < rtol_min <= rtol < 1 and 0 < rtol_factor < 1):
        raise SolverConfigError(
            f"rtol={rtol!r}, rtol_factor={rtol_factor!r}, rtol_min={rtol_min!r}: expected "
            "0 < rtol_min <= rtol < 1 and 0 < rtol_factor < 1")
    if isinstance(max_gap, bool) or not isinstance(max_gap, int | float) or not (
            math.isfinite(max_gap) and max_gap > 0):
        raise SolverConfigError(f"max_gap={max_gap!r}: expected a finite number > 0 (the "
                                "relative change of the validation error truncation may make)")
    _check_cap(max_iterations)
    if not isinstance(redo, bool):
        raise SolverConfigError(f"redo={redo!r}: expected True or False")
    if reference_factor is not None and (
            isinstance(reference_factor, bool) or not isinstance(reference_factor, int | float)
            or not 0 < reference_factor < 1):
        raise SolverConfigError(f"reference_factor={reference_factor!r}: expected None (a "
                                "converged reference) or a number in (0, 1)")

    def init() -> RefinementState:
        return _initial_state(max_iterations, max_iterations, rtol, 2)

    def update(state: RefinementState, value, failed=False) -> RefinementState:
        del failed  # the gap, not the optimiser's step, decides
        xp = array_module(*state, value)
        value = xp.asarray(value, np.float64)
        finite = xp.isfinite(value)
        # a non-finite gap (a truncated rollout that blew up) is the largest gap there is
        refine = ~finite | (value > max_gap)
        tightened = xp.where(refine, xp.maximum(state.rtol * rtol_factor, rtol_min),
                             state.rtol)
        refined = tightened < state.rtol
        return state._replace(
            rtol=tightened, checkpoint=value,
            count=state.count + finite.astype(state.count.dtype),
            refinements=state.refinements + refined.astype(state.refinements.dtype),
            stopped=~refine)

    return Refinement(init, update, tolerance_mode=True, monitor="truncation_gap", redo=redo,
                      reference_factor=None if reference_factor is None
                      else float(reference_factor))


def refuse_learning_rate_scaling(refinement: Refinement, run: str) -> None:
    """Refuse a controller that judges stalls per unit learning rate in a run loop that does
    not feed it one (``run`` names the loop): fed nothing, it would silently run the
    reference rule."""
    if getattr(refinement, "scaled_by_learning_rate", False):
        raise SolverConfigError(
            f"refinement: prdp(per_learning_rate=True) is fed the learning rate of a "
            f"training's epochs (prdp_fem.learning's trainers); {run} does not feed it "
            "(expected per_learning_rate=False)")


def _is_count(value) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def _check_cap(max_iterations) -> None:
    """A tolerance-mode controller's iteration cap: a positive integer."""
    if not (_is_count(max_iterations) and max_iterations > 0):
        raise SolverConfigError(
            f"max_iterations={max_iterations!r}: expected a positive integer cap")


def _count_only(state: RefinementState, value, failed=False) -> RefinementState:
    del failed  # a fixed K or tolerance does not react to the optimiser
    xp = array_module(*state, value)
    finite = xp.isfinite(xp.asarray(value, np.float64))
    return state._replace(count=state.count + finite.astype(state.count.dtype))


def state_to_dict(state: RefinementState) -> dict:
    """JSON-ready dict of a state (lists and Python scalars; NaN as ``None``)."""
    def plain(x):
        x = np.asarray(x)
        if x.dtype.kind == "f":
            x = np.where(np.isfinite(x), x, np.nan)
            return [None if np.isnan(v) else float(v) for v in x.ravel()] if x.ndim else (
                None if np.isnan(x) else float(x))
        return x.tolist()
    return {name: plain(value) for name, value in state._asdict().items()}


def state_from_dict(data: dict) -> RefinementState:
    """Inverse of :func:`state_to_dict`."""
    missing = set(RefinementState._fields) - set(data)
    if missing:
        raise SolverConfigError(
            f"refinement state: missing fields {sorted(missing)}; expected "
            f"{list(RefinementState._fields)}")
    dtypes = {"iterations": np.int32, "adjoint_iterations": np.int32, "count": np.int32,
              "refinements": np.int32, "stopped": np.bool_}

    def array(name):
        value = data[name]
        if name in dtypes:
            return np.asarray(value, dtypes[name])
        return np.asarray([np.nan if v is None else v for v in value] if isinstance(
            value, list) else (np.nan if value is None else value), dtype=np.float64)
    return RefinementState(**{name: array(name) for name in RefinementState._fields})
