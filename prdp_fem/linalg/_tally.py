"""Counting the CG iterations that ran, from inside jitted code.

A solve knows how many iterations it ran only as a traced value, and the inverse driver's
solves run inside optax's line searches, which call the objective an unknown number of times
and return nothing but its value. So the count leaves through a side door: every solve *taps*
an :class:`IterationCounter`, a host call that adds the count to plain Python integers.

The host call is :func:`jax.experimental.io_callback` (unordered: the counts are sums, so
the order of the calls does not matter, and an unordered callback may go inside loops, ``vmap``
and custom derivative rules). Its effect keeps the call from being pruned from a program
whose outputs do not depend on it.

>>> import jax, jax.numpy as jnp
>>> counter = IterationCounter()
>>> @jax.jit
... def run(k):
...     tap(counter, "primal", k, jnp.zeros(3))
...     return k
>>> _ = jax.block_until_ready(run(jnp.int32(7))); jax.effects_barrier()
>>> counter.snapshot(), counter.primal_solves
((7, 0), 1)

A host call has a price: JAX dispatches a program that holds one through its Python path,
argument by argument, and the host calls run inside the program. Where every evaluation is
differentiated in reverse mode (a line search's value-and-gradient trials), the counts need
no host at all: a :class:`ReverseTally` makes them the gradient with respect to a dummy
input, ``seed``. Every solve leaves an identity on its result whose transpose adds the solve's
count to the seed's cotangent; an implicit-mode adjoint solve, which runs only in the
backward pass, adds its own count as the seed's part of its transpose solve's result.

>>> import jax.numpy as jnp
>>> def J(z, seed):
...     x = tap(ReverseTally(seed), "primal", jnp.int32(7), 2.0 * z)
...     return jnp.sum(x ** 2)
>>> value, (grad, counts) = jax.value_and_grad(J, argnums=(0, 1))(jnp.ones(2), zero_counts())
>>> read_counts(counts)
{'primal': 7, 'adjoint': 0, 'primal_solves': 1, 'adjoint_solves': 0}
"""

from __future__ import annotations

import itertools
import threading
import weakref
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jax.experimental import io_callback

__all__ = ["COUNTS", "IterationCounter", "ReverseTally", "counted_linear_solve", "live_tangent",
           "read_counts", "tap", "zero_counts"]


@jax.tree_util.register_pytree_node_class
class IterationCounter:
    """Host-side tally of the CG iterations that actually ran, primal and adjoint.

    Pass one to :func:`prdp_fem.linalg.cg.solve` (``counter=``): every forward solve adds its
    iterations to ``primal`` and every backward (adjoint) solve -- the truncated adjoint PCG
    in implicit mode, the reversed scan in unrolled mode -- adds its own to ``adjoint``; so
    does every forward-mode tangent solve of implicit mode (a Hessian-vector product adds
    two). The tally is exact even inside jitted line searches that evaluate the objective an
    unknown number of times. Read it after the results are ready (``jax.block_until_ready``).
    Under ``vmap`` every batch member counts, in one host call per batched solve (see
    :func:`tap`). Known gap: an implicit-mode transpose solve under *two* nested ``vmap`` s
    (e.g. ``vmap`` over samples of a ``jacrev``) counts the inner batch only; map the outer
    axis with ``lax.map`` (as :class:`prdp_fem.learning.learned.BatchObjective` does) to keep the
    tally exact.

    A counter is a pytree whose one leaf is its ``slot``, the key under which the host finds
    it (a weak table of live counters). Passed to a jitted function as an *argument*, the
    slot is traced, so the compiled program does not depend on which counter it counts into:
    runs that differ only in their counters share one executable (see
    :mod:`prdp_fem._executables`). Closed over, the slot is a constant of the program. A
    pytree map over a counter (``tree_map``, ``device_put``) therefore gives back a
    reference to its slot, not a counter, and a copy (``copy.copy``) shares the original's
    slot, so the original receives the copy's counts.
    """

    def __init__(self):
        self.primal = 0
        self.adjoint = 0
        self.primal_solves = 0
        self.adjoint_solves = 0
        self._lock = threading.Lock()
        self.slot = np.int32(next(_SLOTS))
        _LIVE[int(self.slot)] = self

    def snapshot(self) -> tuple[int, int]:
        """``(primal, adjoint)`` iterations so far."""
        return self.primal, self.adjoint

    def _add(self, kind: str, iterations, solves) -> None:
        with self._lock:  # unordered host calls may run on several XLA threads at once
            if kind == "primal":
                self.primal += int(iterations)
                self.primal_solves += int(solves)
            else:
                self.adjoint += int(iterations)
                self.adjoint_solves += int(solves)

    def tree_flatten(self):
        return (self.slot,), None

    @classmethod
    def tree_unflatten(cls, aux, children) -> _CounterRef:
        del aux
        return _CounterRef(children[0])


class _CounterRef(NamedTuple):
    """What a jitted function sees of a counter passed as an argument: its (traced) slot."""

    slot: Any


#: Live counters by slot: the host calls carry a slot, not the counter (see IterationCounter).
_LIVE: weakref.WeakValueDictionary[int, IterationCounter] = weakref.WeakValueDictionary()
_SLOTS = itertools.count()
_KINDS = ("primal", "adjoint")


def _tally(kind, slot, iterations, solves) -> tuple:
    """The host side of every tap: add to the counter in ``slot`` (gone: nothing to add to).

    Everything it needs arrives as operands (``kind`` as its index in :data:`_KINDS`), so one
    module-level function serves every program.
    """
    counter = _LIVE.get(int(slot))
    if counter is not None:
        counter._add(_KINDS[int(kind)], iterations, solves)
    return ()


class ReverseTally(NamedTuple):
    """Counts that leave an evaluation differentiated in reverse mode as the gradient with
    respect to ``seed`` (a float vector of :data:`COUNTS`, zero: :func:`zero_counts`).

    Pass ``ReverseTally(seed)`` as a solve's ``counter`` inside a function of ``seed`` and take
    the gradient with respect to it too (``jax.value_and_grad(f, argnums=(0, 1))``): the
    seed's gradient is ``[primal, adjoint, primal_solves, adjoint_solves]`` of that
    evaluation, read by :func:`read_counts`. No host call, so the program keeps JAX's fast
    dispatch and its persistent compilation cache.

    What it counts: every solve whose result reaches the differentiated value, and every
    adjoint solve of the backward pass, exactly as an :class:`IterationCounter` would in the
    same evaluation. What it does not: an evaluation run without a reverse pass (a value
    alone, a forward-mode product) counts nothing -- use an :class:`IterationCounter` there.
    First order only: a gradient that is differentiated again with the seed differentiated
    inside (forward over reverse) is refused by ``jax.lax.custom_linear_solve``; with the seed
    held constant it differentiates as the plain gradient (and counts nothing).

    ``adjoint_start`` (optional, a vector of the system's size): the initial guess of an
    implicit-mode adjoint solve (:class:`~prdp_fem.linalg.TruncatedCG` with
    ``gradient="implicit"``, :class:`~prdp_fem.linalg.ConvergedCG`), and the way its
    solution leaves: the gradient with respect to ``adjoint_start`` is the adjoint solve's
    result -- the warm start of the next evaluation's adjoint solve. Meant for an evaluation
    with one such solve (the gradients of several would add up); solvers without an adjoint
    solve of their own (unrolled mode, the stationary solver) ignore it, and its gradient is
    then zero, a cold start.
    """

    seed: jax.Array
    adjoint_start: jax.Array | None = None


#: The order of the counts in a :class:`ReverseTally`'s seed.
COUNTS = ("primal", "adjoint", "primal_solves", "adjoint_solves")


def zero_counts(dtype=jnp.float64) -> jax.Array:
    """A :class:`ReverseTally`'s seed: zeros, one per entry of :data:`COUNTS`."""
    return jnp.zeros(len(COUNTS), dtype)


def read_counts(counts) -> dict[str, int]:
    """A seed's gradient (or a sum of them) as ``{name: count}`` (exact below ``2**53``)."""
    return dict(zip(COUNTS, (round(value) for value in np.asarray(counts).tolist()),
                    strict=True))


def _count_vector(kind: str, iterations, dtype) -> jax.Array:
    """The counts one ``kind`` solve of ``iterations`` adds, in :data:`COUNTS` order."""
    index = _KINDS.index(kind)
    iterations = jax.lax.stop_gradient(jnp.asarray(iterations)).astype(dtype)
    return zero_counts(dtype).at[index].set(iterations).at[index + 2].set(1)


def tap(counter: IterationCounter | _CounterRef | ReverseTally | None, kind: str,
        iterations: jax.Array, anchor: jax.Array) -> jax.Array:
    """Count one solve of ``iterations`` as ``kind`` (``"primal"`` or ``"adjoint"``) in
    ``counter``; returns ``anchor``, the solve's result, to be used in its place.

    An :class:`IterationCounter` adds on the host now, and ``anchor`` comes back unchanged;
    a :class:`ReverseTally` adds when the reverse pass transposes the returned identity on
    ``anchor``; ``None`` counts nothing.

    For a host counter ``anchor`` carries the batching: under ``vmap`` a batched solve is a
    batch of solves even when the iteration count is not (a fixed ``K``). The batching rule
    (:func:`jax.custom_batching.custom_vmap`) adds the sum over the batch in *one* host call,
    so a batch of ``B`` solves costs one call, not ``B``.
    """
    if counter is None:
        return anchor
    if isinstance(counter, ReverseTally):
        return _count_on_reverse(anchor, counter.seed,
                                 _count_vector(kind, iterations, counter.seed.dtype))
    scalar = jax.lax.stop_gradient(jnp.sum(jnp.ravel(anchor)[:1]))
    _batched_tap(jnp.int32(_KINDS.index(kind)), jnp.asarray(counter.slot, jnp.int32),
                 jax.lax.stop_gradient(iterations), jnp.ones((), jnp.int32), scalar)
    return anchor


def _is_zero(tangent) -> bool:
    return isinstance(tangent, SymbolicZero)


@jax.custom_jvp
def _count_on_reverse(x, seed, counts):
    """``x``; its transpose adds ``counts`` to the cotangent of ``seed``."""
    del seed, counts
    return x


def _count_on_reverse_jvp(primals, tangents):
    x, seed, counts = primals
    x_dot, seed_dot, _ = tangents
    out = _count_on_reverse(x, seed, counts)
    if _is_zero(x_dot):  # nothing of x is differentiated: no reverse pass reaches it
        return out, jnp.zeros_like(x)
    if _is_zero(seed_dot):  # the seed is not differentiated: nowhere to count
        return out, x_dot
    counts = jax.lax.stop_gradient(counts)
    # The tangent is the identity, written as a linear solve over (x, seed) so that its
    # transpose can add to the seed's cotangent: forward, nothing is counted.
    tangent, _ = jax.lax.custom_linear_solve(
        lambda v: v, (x_dot, seed_dot), lambda _, right: right,
        lambda _, right: (right[0], counts))
    return out, tangent


_count_on_reverse.defjvp(_count_on_reverse_jvp, symbolic_zeros=True)


def counted_linear_solve(matvec, rhs, solve, transpose_solve, counter, seed_dot=None, *,
                         symmetric: bool = False, start_dot=None):
    """``jax.lax.custom_linear_solve(matvec, rhs, ...)`` whose two solves count as adjoint
    solves: ``solve(right)`` and ``transpose_solve(right)`` return ``(x, iterations)``.

    A host counter (``counter``, or ``None``) is tapped by both. ``seed_dot`` -- the tangent of a
    :class:`ReverseTally`'s seed, where the enclosing derivative rule has one -- makes the
    transpose solve (the backward pass's adjoint solve) add its count to the seed's
    cotangent: the system is solved over ``(x, seed)``, the seed's part passed through
    forward and replaced by the count in the transpose. A forward (tangent) solve counts
    nothing then, as a reverse tally counts only what a reverse pass runs. ``start_dot`` --
    the tangent of a tally's ``adjoint_start`` -- is a further part of the same kind, replaced
    by the transpose solve's result: the adjoint solution leaves as the start's cotangent.
    ``symmetric`` (``transpose_solve`` is ``solve``) is passed on where neither is.
    """
    if seed_dot is None and start_dot is None:
        def counted(fn):
            def run(_, right):
                x, iterations = fn(right)
                return tap(counter, "adjoint", iterations, x)
            return run

        if symmetric:
            return jax.lax.custom_linear_solve(matvec, rhs, counted(solve), symmetric=True)
        return jax.lax.custom_linear_solve(matvec, rhs, counted(solve), counted(transpose_solve))

    parts = tuple(part for part in (seed_dot, start_dot) if part is not None)

    def forward(_, right):
        return (solve(right[0])[0], *right[1:])

    def transpose(_, right):
        x, iterations = transpose_solve(right[0])
        reports = []
        if seed_dot is not None:
            reports.append(_count_vector("adjoint", iterations, right[1].dtype))
        if start_dot is not None:
            reports.append(x)
        return (x, *reports)

    return jax.lax.custom_linear_solve(lambda v: (matvec(v[0]), *v[1:]), (rhs, *parts),
                                       forward, transpose)[0]


def live_tangent(tangent):
    """``tangent``, or ``None`` where it is absent or symbolically zero (a derivative rule
    declared with ``symbolic_zeros=True`` is handed :class:`jax.custom_derivatives.SymbolicZero`
    for an input that is not differentiated)."""
    return None if tangent is None or _is_zero(tangent) else tangent


@jax.custom_batching.custom_vmap
def _batched_tap(kind, slot, iterations, solves, anchor):
    _host_call(kind, slot, iterations, solves)
    return anchor


@_batched_tap.def_vmap
def _batched_tap_rule(axis_size, in_batched, kind, slot, iterations, solves, anchor):
    def total(value, batched):
        return jnp.sum(value) if batched else value * axis_size

    def member(value, batched, i):
        return value[i] if batched else value

    if in_batched[1]:  # a batch of counters (vmap over a stack of them): one tap each
        for i in range(axis_size):
            _batched_tap(member(kind, in_batched[0], i), slot[i],
                         member(iterations, in_batched[2], i), member(solves, in_batched[3], i),
                         member(anchor, in_batched[4], i))
        return anchor, in_batched[4]
    # one unbatched tally: an enclosing vmap level (if any) multiplies again
    _batched_tap(member(kind, in_batched[0], 0), slot,
                 total(iterations, in_batched[2]).astype(iterations.dtype),
                 total(solves, in_batched[3]).astype(jnp.int32),
                 jnp.sum(anchor) if in_batched[4] else anchor)
    return anchor, in_batched[4]


def _host_call(kind, slot, iterations, solves) -> None:
    # one operand, not four: io_callback transfers each to the host (0.14 against 0.24 ms
    # per call in a loop)
    operands = jnp.stack([jnp.asarray(value, jnp.int32)
                          for value in (kind, slot, iterations, solves)])
    io_callback(_tally_packed, None, operands, ordered=False)


def _tally_packed(operands) -> tuple:
    """:func:`_tally` of ``[kind, slot, iterations, solves]``."""
    return _tally(*np.asarray(operands).tolist())
