"""The step machinery every training loop through the solver shares.

:func:`~prdp_fem.inverse.invert`, the learned inverse (:mod:`prdp_fem.learning.learned`), the
heat hybrid (:mod:`prdp_fem.learning.heat`) and the reduced-Hessian CG
(:mod:`prdp_fem.inverse.reduced`) build the solver of a step from the refinement's current
``(K, K_adj, rtol)``, run one optimiser update from the value and gradient its line search
stored, read whether the update failed, and key their compiled programs by preconditioner.
These are the functions that do it, one definition for all of them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optax.tree_utils as otu

from ..errors import SolverConfigError
from ..linalg.amg import AMGCycle
from ..linalg.cg import ConvergedCG, TruncatedCG, unrolled_length
from ..optim.linesearch import evaluation, has_search_state, search_warm_start

__all__ = [
    "check_training_refinement",
    "cycle_argument",
    "device_settings",
    "keeps_program",
    "preconditioner_key",
    "step_failed",
    "step_scan_length",
    "step_solver",
    "uses_stored_value",
    "value_grad_and_update",
    "with_stale_value",
]


def step_solver(gradient: str, tolerance_mode: bool, K, K_adj, rtol, preconditioner,
            scan_length: int = 0):
    """The solver of one step; ``scan_length`` (unrolled mode, when ``> 0``): ``K`` is traced
    below it (see :func:`step_scan_length`)."""
    if tolerance_mode:
        return ConvergedCG(rtol=rtol, max_iterations=K, preconditioner=preconditioner)
    if gradient == "unrolled":
        return TruncatedCG(K, preconditioner, gradient="unrolled",
                           scan_length=scan_length or None)
    return TruncatedCG(K, preconditioner, gradient="implicit", adjoint_iterations=K_adj)


def step_scan_length(gradient: str, K) -> int:
    """A step program's static argument: in unrolled mode the scan length for ``K``
    (:func:`~prdp_fem.linalg.cg.unrolled_length`: one program per power of two, not one per
    ``K``), else 0 (``K`` is traced anyway)."""
    return unrolled_length(int(K)) if gradient == "unrolled" else 0


def uses_stored_value(opt_state) -> bool:
    return otu.tree_get(opt_state, "value") is not None


def _stored_or_evaluated(evaluate, z, opt_state):
    """:func:`optax.value_and_grad_from_state`: the value and gradient the line search stored
    (no counts), unless that value is not finite (none yet, or :func:`invert` marked it
    stale), through ``evaluate`` (:func:`~prdp_fem.optim.linesearch.evaluation`)."""
    value, grad = otu.tree_get(opt_state, "value"), otu.tree_get(opt_state, "grad")
    counts = jax.eval_shape(evaluate, z).counts
    return jax.lax.cond(jnp.isfinite(value),
                        lambda: (value, grad, jnp.zeros(counts.shape, counts.dtype)),
                        lambda: evaluate(z)[:3])


def _search_counts(opt_state, like: jax.Array) -> jax.Array:
    """The counts a :class:`~prdp_fem.optim.linesearch.ZoomSearchState` in ``opt_state`` holds
    of its last update's evaluations; zeros without one."""
    counts = otu.tree_get(opt_state, "counts")
    return jnp.zeros_like(like) if counts is None else counts


def _refreshes(opt_state) -> bool:
    """Whether the optimiser's line search evaluates a stale stored value itself
    (:class:`~prdp_fem.optim.linesearch.ZoomSearchState`, :func:`prdp_fem.lbfgs`'s search)."""
    return has_search_state(opt_state)


def value_grad_and_update(optimizer, opt_state, z, value_fn):
    """``(J(z), grad J(z), updates, new_state, counts, warm_start)``: one optimiser update at
    ``z``, from the value and gradient its line search stored where it stores them (evaluated
    first where they are stale), else from a fresh evaluation.

    ``counts``: the iterations the update's evaluations ran where ``value_fn`` returns them
    (its ``evaluate``, :func:`~prdp_fem.optim.linesearch.evaluation`;
    ``[primal, adjoint, primal_solves, adjoint_solves]``), zeros where it counts them
    otherwise. Evaluations inside other optimisers' own searches (optax's) and their
    products (Newton-CG's) count only in ``value_fn``'s own counter. ``warm_start``: the
    last evaluation's (:class:`~prdp_fem.optim.linesearch.Evaluation`), what the next step's
    solves start from; ``None`` where the objective keeps none or the evaluation is inside
    another optimiser's search.

    With :func:`prdp_fem.lbfgs`'s search, the update runs in a loop of one trip, or two where
    the stored value is stale: the first trip hands the search the stale value, and the search
    evaluates ``J`` and its gradient at ``z`` in its own trial and returns them (see
    :mod:`prdp_fem.optim.linesearch`); the second trip is the update proper, from them and from
    ``opt_state`` as given. So the program holds the objective once, where an evaluation
    before the update held it twice: a CG solve and its adjoint, each compiled anew. Other
    optimisers with a stored value: :func:`optax.value_and_grad_from_state`'s evaluation,
    then the update.
    """
    evaluate = evaluation(value_fn)
    warm_start = None
    if not uses_stored_value(opt_state):
        value, grad, counts, warm_start = evaluate(z)
    elif not _refreshes(opt_state):
        value, grad, counts = _stored_or_evaluated(evaluate, z, opt_state)
    else:
        return _refreshed_update(optimizer, opt_state, z, value_fn)
    updates, new_state = optimizer.update(grad, opt_state, z, value=value, grad=grad,
                                          value_fn=value_fn)
    return value, grad, updates, new_state, counts + _search_counts(new_state, counts), \
        warm_start


def _refreshed_update(optimizer, opt_state, z, value_fn):
    """:func:`value_grad_and_update` where the line search refreshes a stale value."""
    stored_value, stored_grad = otu.tree_get(opt_state, "value"), otu.tree_get(opt_state, "grad")
    stale = ~jnp.isfinite(stored_value)

    def trip(carry):
        count, value, grad, _, _, counts = carry
        updates, new_state = optimizer.update(grad, opt_state, z, value=value, grad=grad,
                                              value_fn=value_fn)
        refreshed = ~jnp.isfinite(value)  # the search evaluated at z: its state holds them
        value = jnp.where(refreshed, otu.tree_get(new_state, "value"), value)
        grad = optax.tree.where(refreshed, otu.tree_get(new_state, "grad"), grad)
        # each trip's search counted its own evaluations (the refresh, then the search)
        return count + 1, value, grad, updates, new_state, \
            counts + otu.tree_get(new_state, "counts")

    _, value, grad, updates, new_state, counts = jax.lax.while_loop(
        lambda carry: (carry[0] == 0) | ((carry[0] == 1) & stale), trip,
        (jnp.zeros((), jnp.int32), stored_value, stored_grad, optax.tree.zeros_like(z),
         opt_state, jnp.zeros_like(otu.tree_get(opt_state, "counts"))))
    return value, grad, updates, new_state, counts, search_warm_start(new_state)


def step_failed(opt_state) -> jax.Array:
    """Whether the optimiser reports its last update as failed.

    optax's line searches keep their errors in the state (a positive sufficient-decrease or,
    for the zoom search, curvature error: the search ended without meeting its conditions);
    :func:`prdp_fem.optim.newton.newton_cg` keeps ``line_search_failed``. Other optimisers report
    nothing: ``False``.
    """
    failed = jnp.asarray(False)
    for name in ("decrease_error", "curvature_error"):
        error = otu.tree_get(opt_state, name)
        if error is not None:
            failed = failed | (error > 0)
    flag = otu.tree_get(opt_state, "line_search_failed")
    return failed if flag is None else failed | flag


def device_settings(settings: tuple[int, int, float]) -> tuple[jax.Array, ...]:
    """The step's ``(K, K_adj, rtol)`` arguments: transferred once per refinement, not per
    step (the controller's state lives on the host)."""
    K, K_adj, rtol = settings
    return tuple(jax.device_put((np.int32(K), np.int32(K_adj), np.float64(rtol))))


def preconditioner_key(preconditioner):
    """What a step program is built for: a name, the class :class:`~prdp_fem.linalg.amg.AMGCycle`
    for any such cycle (its arrays are then an argument of the program: hierarchies of
    equal shapes, such as an AMG rebuilt at another kappa or the runs of a sweep, share one
    compiled step), or the object itself (closed over: pyamg's callback cycle, a callable)."""
    return AMGCycle if isinstance(preconditioner, AMGCycle) else preconditioner


def keeps_program(key) -> bool:
    """Whether a program built for ``key`` (:func:`preconditioner_key`) is kept for the
    process: a name or the class; a closed-over object is a pytree of arrays or a host
    cycle, no key to keep it under."""
    return isinstance(key, str) or key is AMGCycle


def with_stale_value(opt_state):
    """``opt_state`` with its stored value marked stale (``inf``): the next step evaluates
    ``J`` and its gradient afresh, with that step's solver."""
    return otu.tree_set(opt_state, value=jnp.asarray(jnp.inf))


def cycle_argument(preconditioner) -> tuple:
    """The programs' trailing argument: an :class:`~prdp_fem.linalg.amg.AMGCycle`, else none."""
    return (preconditioner,) if isinstance(preconditioner, AMGCycle) else ()


def check_training_refinement(refinement, gradient: str) -> None:
    """Refuse a controller a training loop cannot feed: one that watches an inversion step's
    gradient (training feeds a validation error, or the truncation gap of
    :func:`~prdp_fem.inverse.refinement.truncation_gap`), or a tolerance-mode controller with
    unrolled gradients (a loop of unknown length)."""
    if getattr(refinement, "monitor", None) not in (None, "truncation_gap"):
        raise SolverConfigError(
            f"refinement: this controller is fed the {refinement.monitor!r} norm of an "
            "inversion step; training feeds its controller a validation error (expected "
            "prdp(), fixed(K), converged(rtol) or truncation_gap())")
    if refinement.tolerance_mode and gradient == "unrolled":
        raise SolverConfigError("a tolerance-mode controller needs gradient='implicit'")
