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
"""

from __future__ import annotations

import itertools
import threading
import weakref
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import io_callback

__all__ = ["IterationCounter", "tap"]


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


def tap(counter: IterationCounter | _CounterRef | None, kind: str, iterations: jax.Array,
        anchor: jax.Array) -> None:
    """Add ``iterations`` (one solve's) to ``counter``'s ``kind`` (``"primal"`` or
    ``"adjoint"``) on the host; nothing when ``counter`` is ``None``.

    ``anchor`` (a vector of the solve, its gradient stopped) carries the batching: under
    ``vmap`` a batched solve is a batch of solves even when the iteration count is not (a
    fixed ``K``). The batching rule (:func:`jax.custom_batching.custom_vmap`) adds the sum
    over the batch in *one* host call, so a batch of ``B`` solves costs one call, not ``B``.
    """
    if counter is None:
        return
    anchor = jax.lax.stop_gradient(jnp.sum(jnp.ravel(anchor)[:1]))
    _batched_tap(jnp.int32(_KINDS.index(kind)), jnp.asarray(counter.slot, jnp.int32),
                 jax.lax.stop_gradient(iterations), jnp.ones((), jnp.int32), anchor)


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
