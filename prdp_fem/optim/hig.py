r"""Half-inverse gradients (Schnell, Holl & Thuerey, ICLR 2022) and their relatives.

For a loss ``L(theta) = 1/2 ||r(theta)||^2`` with residual ``r`` (stacked over a batch for a
network) and Jacobian ``J = dr/dtheta`` with thin SVD ``J = U S V^T``,

.. math::

    \Delta\theta = -\eta\, V S_\tau^{p}\, U^\top r, \qquad
    (S_\tau^p)_{ii} = \begin{cases} s_i^p & s_i \ge \tau s_{\max} \\ 0 & \text{else,}
    \end{cases}

* ``p = +1``: ``V S U^T r = J^T r = grad L``: gradient descent;
* ``p = -1``: ``V S^{-1} U^T r = J^+ r``: the Gauss-Newton (pseudo-inverse) step; with
  ``eta = 1`` it lands on the minimiser of a linear least-squares problem;
* ``p = -1/2`` (default): the half-inverse, which evens out the scale distortions a physics
  solver puts between the directions of parameter space without the noise amplification of a
  full inverse.

Singular values below ``tau s_max`` are *dropped* (their directions get no update), not
clamped: with ``p < 0`` a clamped tiny ``s`` would still dominate the step. When every singular
value is dropped (``J = 0``, ``s_max = 0``) the update is exactly zero, and the state says so
(``rank = 0``).

Two ways to the SVD:

* ``rank=None``: the explicit Jacobian (``m x n``) and a dense thin SVD, for small problems.
  Each block of the residual takes forward mode (``n`` Jacobian-vector products) when it has
  more rows than there are parameters and the function supports it, reverse mode (``m``
  vector-Jacobian products) otherwise (:func:`residual_jacobian`);
* ``rank=k``: a matrix-free randomised truncated SVD (Halko, Martinsson & Tropp 2011, with
  power iterations) from ``J v`` (``jax.linearize``) and ``J^T u`` (``jax.vjp``) products only:
  ``(1 + q)(k + oversample)`` of each. Exact when ``rank(J) <= k``. It needs forward mode
  through the residual, which both PCG gradient modes support (an implicit solve's tangent is
  a truncated tangent solve, :mod:`prdp_fem.linalg.cg`).

:func:`hig` is an optax ``GradientTransformationExtraArgs`` that takes ``residual_fn=``, or
a ``value_fn`` with ``residual_blocks()`` (:func:`prdp_fem.inverse.driver.invert`'s objective) and,
for a batch, ``residual_jacobian(params, mode)`` giving ``(r, J)`` with ``J`` stacked over the
samples, each sample's block taken on its own (:class:`prdp_fem.learning.learned.BatchObjective`,
what :func:`prdp_fem.learning.learned.train` passes); :func:`hig_update` is the plain function for a
training loop that already holds the (batch-stacked) Jacobian.

>>> import jax.numpy as jnp
>>> A, b = jnp.array([[2.0, 0.0], [0.0, 0.5], [0.0, 0.0]]), jnp.array([1.0, 1.0, 1.0])
>>> theta = jnp.zeros(2)          # r = A theta - b; Gauss-Newton lands on the minimiser
>>> step, info = hig_update(A, A @ theta - b, learning_rate=1.0, exponent=-1.0)
>>> (theta + step).tolist(), int(info.rank)
([0.5, 2.0], 2)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

from ..errors import SolverConfigError

__all__ = [
    "JACOBIAN_MODES",
    "HigInfo",
    "HigState",
    "hig",
    "hig_direction",
    "hig_update",
    "randomized_svd",
    "residual_jacobian",
]

JACOBIAN_MODES = ("auto", "forward", "reverse")


class HigInfo(NamedTuple):
    """What one step kept: ``rank`` singular values (of those computed) and ``s_max``."""

    rank: jax.Array
    s_max: jax.Array


class HigState(NamedTuple):
    """State of :func:`hig`: steps taken, the sketch's PRNG key and the last step's SVD facts."""

    count: jax.Array   # int32, for learning-rate schedules
    key: jax.Array     # PRNG key of the randomised SVD (unused with rank=None)
    rank: jax.Array    # int32, singular values kept at the last step (0 before the first)
    s_max: jax.Array   # largest singular value at the last step


# --------------------------------------------------------------------------------------
# the update from an SVD
# --------------------------------------------------------------------------------------


def hig_direction(u: jax.Array, s: jax.Array, vt: jax.Array, residual: jax.Array,
                  exponent: float = -0.5, tau: float = 1e-6) -> tuple[jax.Array, HigInfo]:
    r"""``V S_tau^p U^T r`` from a (thin or truncated) SVD ``u, s, vt`` of ``J``.

    Kept: ``s_i >= tau s_max`` and ``s_i > 0``. The power is taken of the kept values only
    (a dropped zero never meets a negative exponent, in either direction of autodiff).

    >>> import jax.numpy as jnp
    >>> d, info = hig_direction(jnp.eye(2), jnp.array([4.0, 1e-9]), jnp.eye(2),
    ...                         jnp.array([2.0, 1.0]), exponent=-0.5)
    >>> d.tolist(), int(info.rank)        # 4^-1/2 * 2; the 1e-9 direction is dropped
    ([1.0, 0.0], 1)
    """
    s_max = jnp.max(s, initial=0.0)
    keep = (s >= tau * s_max) & (s > 0)
    powered = jnp.where(keep, jnp.where(keep, s, 1.0) ** exponent, 0.0)
    direction = vt.T @ (powered * (u.T @ residual))
    return direction, HigInfo(jnp.sum(keep).astype(jnp.int32), s_max)


def hig_update(jacobian: Any, residual: jax.Array, *, learning_rate: float = 1.0,
               exponent: float = -0.5, tau: float = 1e-6) -> tuple[Any, HigInfo]:
    r"""``-eta V S_tau^p U^T r`` for an explicit Jacobian: the step for a training loop.

    ``residual`` may have any shape (e.g. ``(batch, outputs)``: it is flattened, so the batch
    is stacked); ``jacobian`` is then ``jax.jacrev(residual_fn)(params)``: an array of shape
    ``residual.shape + params.shape``, or a pytree of such leaves for pytree parameters. The
    update has the structure of the parameters (apply it with ``optax.apply_updates``).

    A non-finite Jacobian or residual gives a non-finite update (the SVD does not hide it):
    check the loss, as :func:`~prdp_fem.inverse.driver.invert` does. Raises
    :class:`~prdp_fem.errors.SolverConfigError` for bad options or shapes.
    """
    _check_exponent_tau(exponent, tau)
    if callable(learning_rate):
        raise SolverConfigError(f"learning_rate={learning_rate!r}: expected a number > 0 "
                                "(hig_update takes no schedule: evaluate it at the step)")
    _check_learning_rate(learning_rate)
    residual = jnp.asarray(residual)
    m = residual.size
    leaves = jax.tree_util.tree_leaves(jacobian)
    if not leaves or any(jnp.shape(leaf)[:residual.ndim] != residual.shape for leaf in leaves):
        raise SolverConfigError(
            f"jacobian: leaves of shapes {[jnp.shape(x) for x in leaves]}; expected arrays of "
            f"shape residual.shape + parameter shape, residual.shape = {residual.shape}")
    template = jax.tree_util.tree_map(lambda x: jnp.zeros(jnp.shape(x)[residual.ndim:],
                                                          jnp.result_type(x)), jacobian)
    _, unravel = ravel_pytree(template)
    matrix = jnp.concatenate([jnp.reshape(x, (m, -1)) for x in leaves], axis=1)
    u, s, vt = jnp.linalg.svd(matrix, full_matrices=False)
    direction, info = hig_direction(u, s, vt, residual.ravel(), exponent, tau)
    return unravel(-learning_rate * direction), info


# --------------------------------------------------------------------------------------
# Jacobians and SVDs of a residual function
# --------------------------------------------------------------------------------------


def _blocks(residual_fn: Callable | Sequence[Callable]) -> list[Callable]:
    """One flat function per block: ``residual_fn`` is a function or a sequence of them."""
    fns = list(residual_fn) if isinstance(residual_fn, tuple | list) else [residual_fn]
    if not fns or not all(callable(fn) for fn in fns):
        raise SolverConfigError(f"residual_fn={residual_fn!r}: expected a function of the "
                                "parameters, or a tuple of such functions (blocks of r)")
    return [lambda y, fn=fn: jnp.ravel(fn(y)) for fn in fns]


def _forward_unsupported(exc: Exception) -> bool:
    return isinstance(exc, TypeError) and "forward-mode" in str(exc)


def _jacobian_block(fn: Callable, x: jax.Array, mode: str) -> tuple[jax.Array, jax.Array]:
    n, m = x.size, jax.eval_shape(fn, x).size
    if mode == "forward" or (mode == "auto" and m > n):
        try:
            r, jvp = jax.linearize(fn, x)
            return r, jax.vmap(jvp, out_axes=1)(jnp.eye(n, dtype=x.dtype))
        except TypeError as exc:
            if not _forward_unsupported(exc):
                raise
            if mode == "forward":
                raise SolverConfigError(_NO_FORWARD) from exc
    r, pullback = jax.vjp(fn, x)
    return r, jax.vmap(lambda e: pullback(e)[0])(jnp.eye(m, dtype=r.dtype))


_NO_FORWARD = (
    "jacobian='forward' (or a matrix-free rank): the residual does not support forward mode "
    "(jax.jvp), e.g. it has a jax.custom_vjp rule. Expected jacobian='reverse'/'auto' with "
    "rank=None, or a residual with forward-mode rules (PCG solves of both gradient modes "
    "have them)")


def residual_jacobian(residual_fn: Callable | Sequence[Callable], x: jax.Array,
                      mode: str = "auto") -> tuple[jax.Array, jax.Array]:
    """``(r, J)`` of ``residual_fn`` at a flat ``x``: ``r`` flat (blocks concatenated).

    ``residual_fn`` is a function (its output, of any shape, is flattened) or a tuple of
    functions whose outputs are blocks of ``r``. Each block's Jacobian is taken on its own, so
    a block that does not pass through the solver (a regulariser) costs no solves. ``mode``:
    ``"reverse"`` (one VJP per row), ``"forward"`` (one JVP per parameter) or ``"auto"``
    (forward for a block with more rows than parameters, falling back to reverse where
    forward mode is not supported).

    >>> import jax.numpy as jnp
    >>> r, J = residual_jacobian((lambda x: x ** 2, lambda x: 3.0 * x[:1]),
    ...                          jnp.array([1.0, 2.0]))
    >>> r.tolist(), J.tolist()
    ([1.0, 4.0, 3.0], [[2.0, 0.0], [0.0, 4.0], [3.0, 0.0]])
    """
    if mode not in JACOBIAN_MODES:
        raise SolverConfigError(f"jacobian={mode!r}: expected one of {JACOBIAN_MODES}")
    parts = [_jacobian_block(fn, x, mode) for fn in _blocks(residual_fn)]
    return (jnp.concatenate([p[0] for p in parts]),
            jnp.concatenate([p[1] for p in parts], axis=0))


def randomized_svd(matvec: Callable, rmatvec: Callable, shape: tuple[int, int], rank: int,
                   key: jax.Array, *, oversample: int = 10,
                   power_iterations: int = 2) -> tuple[jax.Array, jax.Array, jax.Array]:
    r"""Rank-``k`` SVD ``(U, s, V^T)`` of an ``m x n`` operator from products alone.

    Halko, Martinsson & Tropp (2011), algorithms 4.4 and 5.1: with ``l = k + oversample``
    (at most ``min(m, n)``) Gaussian test vectors ``Omega``, ``Q = orth(J Omega)``, refined by
    ``q`` power iterations ``Q = orth(J orth(J^T Q))`` (which sharpen a slowly decaying
    spectrum), then the SVD of the small ``B = Q^T J = (J^T Q)^T``. ``matvec(v) = J v`` and
    ``rmatvec(u) = J^T u`` take single vectors (they are vmapped here). Exact, to round-off,
    when ``rank(J) <= l``.
    """
    m, n = shape
    k = min(rank, m, n)
    width = min(k + oversample, m, n)
    apply = jax.vmap(matvec, in_axes=1, out_axes=1)
    apply_t = jax.vmap(rmatvec, in_axes=1, out_axes=1)
    q, _ = jnp.linalg.qr(apply(jax.random.normal(key, (n, width))))
    for _ in range(power_iterations):
        z, _ = jnp.linalg.qr(apply_t(q))
        q, _ = jnp.linalg.qr(apply(z))
    u_small, s, vt = jnp.linalg.svd(apply_t(q).T, full_matrices=False)
    return (q @ u_small)[:, :k], s[:k], vt[:k]


def _matrix_free_svd(residual_fn: Callable | Sequence[Callable], x: jax.Array, rank: int,
                     key: jax.Array, oversample: int, power_iterations: int):
    blocks = _blocks(residual_fn)

    def flat(y):
        return jnp.concatenate([fn(y) for fn in blocks])

    _, pullback = jax.vjp(flat, x)
    try:  # JAX may report a missing forward rule at linearize or only once it is applied
        r, jvp = jax.linearize(flat, x)
        u, s, vt = randomized_svd(jvp, lambda e: pullback(e)[0], (r.size, x.size), rank, key,
                                  oversample=oversample, power_iterations=power_iterations)
    except TypeError as exc:
        if _forward_unsupported(exc):
            raise SolverConfigError(_NO_FORWARD) from exc
        raise
    return r, u, s, vt


# --------------------------------------------------------------------------------------
# the optax transformation
# --------------------------------------------------------------------------------------


def hig(learning_rate: optax.ScalarOrSchedule, exponent: float = -0.5, tau: float = 1e-6,
        rank: int | None = None, *, relative: bool = False, jacobian: str = "auto",
        oversample: int = 10, power_iterations: int = 2,
        seed: int = 0) -> optax.GradientTransformationExtraArgs:
    r"""Half-inverse gradient steps ``-eta V S_tau^p U^T r`` as an optax transformation.

    ``update(grads, state, params, *, residual_fn)`` ignores ``grads`` and differentiates
    ``residual_fn(params)``: the residual ``r`` with ``loss = 1/2 ||r||^2`` (or a tuple of
    functions giving blocks of it, see :func:`residual_jacobian`).
    :func:`prdp_fem.inverse.driver.invert` passes it (build the problem with
    ``inverse_problem(..., residual=True)``).

    Parameters
    ----------
    learning_rate
        ``eta > 0`` or an optax schedule of the step count.
    exponent
        ``p``: ``-0.5`` half-inverse, ``-1`` Gauss-Newton, ``+1`` gradient descent.
    tau
        Relative cut-off in ``[0, 1)``: singular values below ``tau s_max`` are dropped.
    rank
        ``None``: explicit Jacobian and a full thin SVD. An integer ``k >= 1``: matrix-free
        randomised SVD of rank ``k`` (needs forward mode through the residual).
    relative
        Scale the step by ``s_max^{-(1 + p)}`` (``eta_eff = eta s_max^{-(1+p)}``): then
        ``eta = 1`` takes the full Gauss-Newton step along the top singular direction for
        every ``p``, and direction ``i`` moves by ``(s_i / s_max)^{1+p}`` of its Gauss-Newton
        step. For ``p = 1`` this is gradient descent with step ``1 / L``, ``L = s_max^2``
        the Lipschitz constant of a linear least-squares gradient. It makes one ``eta``
        grid fit every exponent and problem scaling; off by default (``eta`` as in the paper).
    jacobian
        Explicit path only: ``"auto"``, ``"forward"`` or ``"reverse"``
        (:func:`residual_jacobian`).
    oversample, power_iterations, seed
        Matrix-free path: extra test vectors, power iterations, and the PRNG seed (the key is
        split every step and kept in the state).
    """
    _check_learning_rate(learning_rate)
    _check_exponent_tau(exponent, tau)
    if rank is not None and not (_is_int(rank) and rank >= 1):
        raise SolverConfigError(f"rank={rank!r}: expected None (explicit Jacobian) or an "
                                "integer >= 1 (matrix-free truncated SVD)")
    if jacobian not in JACOBIAN_MODES:
        raise SolverConfigError(f"jacobian={jacobian!r}: expected one of {JACOBIAN_MODES}")
    if not isinstance(relative, bool):
        raise SolverConfigError(f"relative={relative!r}: expected True or False")
    for name, value in (("oversample", oversample), ("power_iterations", power_iterations),
                        ("seed", seed)):
        if not (_is_int(value) and value >= 0):
            raise SolverConfigError(f"{name}={value!r}: expected an integer >= 0")

    def init_fn(params) -> HigState:
        dtype = ravel_pytree(params)[0].dtype
        return HigState(jnp.zeros((), jnp.int32), jax.random.PRNGKey(seed),
                        jnp.zeros((), jnp.int32), jnp.zeros((), dtype))

    def update_fn(updates, state: HigState, params=None, *, residual_fn=None, value_fn=None,
                  **extra_args):
        del updates, extra_args  # the step comes from the residual, not from the gradient
        stacked = residual_fn is None and rank is None and hasattr(value_fn,
                                                                  "residual_jacobian")
        if residual_fn is None and hasattr(value_fn, "residual_blocks"):
            residual_fn = value_fn.residual_blocks()  # invert's Objective, train's BatchObjective
        if params is None or residual_fn is None:
            raise SolverConfigError(
                "hig: update needs params and residual_fn= (the residual vector r with "
                "loss = 1/2 ||r||^2), or a value_fn with residual_blocks() as "
                "prdp_fem.inverse.driver.invert passes for a problem built with "
                "inverse_problem(..., residual=True)")
        x, unravel = ravel_pytree(params)
        flat_fn = [lambda y, fn=fn: fn(unravel(y)) for fn in _blocks(residual_fn)]

        key = state.key
        if stacked:  # a batch: the value_fn stacks per-sample Jacobians (learned.BatchObjective)
            r, matrix = value_fn.residual_jacobian(params, jacobian)
            u, s, vt = jnp.linalg.svd(matrix, full_matrices=False)
        elif rank is None:
            r, matrix = residual_jacobian(flat_fn, x, jacobian)
            u, s, vt = jnp.linalg.svd(matrix, full_matrices=False)
        else:
            key, sketch = jax.random.split(key)
            r, u, s, vt = _matrix_free_svd(flat_fn, x, rank, sketch, oversample,
                                           power_iterations)
        direction, info = hig_direction(u, s, vt, r, exponent, tau)
        eta = learning_rate(state.count) if callable(learning_rate) else learning_rate
        if relative:  # all dropped (s_max = 0): the direction is zero, keep eta finite
            eta = eta * jnp.where(info.s_max > 0, info.s_max, 1.0) ** -(1.0 + exponent)
        step = unravel((-eta * direction).astype(x.dtype))
        return step, HigState(state.count + 1, key, info.rank, info.s_max.astype(x.dtype))

    return optax.GradientTransformationExtraArgs(init_fn, update_fn)


# --------------------------------------------------------------------------------------
# option checks
# --------------------------------------------------------------------------------------


def _is_int(value) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def _is_finite_number(value) -> bool:
    """A real scalar (Python, NumPy or a 0-d array) that is finite; a tracer passes (jit)."""
    if isinstance(value, jax.core.Tracer):
        return True
    if isinstance(value, bool) or np.ndim(value) != 0:
        return False
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


def _concrete(value) -> bool:
    return not isinstance(value, jax.core.Tracer)


def _check_learning_rate(learning_rate) -> None:
    if callable(learning_rate):
        return
    if not (_is_finite_number(learning_rate)
            and (not _concrete(learning_rate) or float(learning_rate) > 0)):
        raise SolverConfigError(f"learning_rate={learning_rate!r}: expected a finite number "
                                "> 0 or an optax schedule")


def _check_exponent_tau(exponent, tau) -> None:
    if not _is_finite_number(exponent):
        raise SolverConfigError(f"exponent={exponent!r}: expected a finite number (-0.5 "
                                "half-inverse, -1 Gauss-Newton, +1 gradient descent)")
    if not (_is_finite_number(tau) and (not _concrete(tau) or 0 <= float(tau) < 1)):
        raise SolverConfigError(f"tau={tau!r}: expected a number in [0, 1) (singular values "
                                "below tau * s_max are dropped)")
