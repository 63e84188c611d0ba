"""Counting the CG iterations that ran, from inside jitted code.

A solve knows how many iterations it ran only as a traced value, and the inverse driver's
solves run inside optax's line searches, which call the objective an unknown number of times
and return nothing but its value. So the count leaves through a side door: every solve *taps*
an :class:`IterationCounter`, a host call that adds the count to plain Python integers.

Why a primitive of its own
--------------------------
``jax.experimental.io_callback`` hands its host function ``jax.Array`` s: every call
device-puts its operands and the host function converts them back. Inside a busy objective
on a 2-core CPU that cost about 0.3 ms per call, and an implicit-mode evaluation taps twice
(primal and adjoint): a quarter of a ``K = 10`` evaluation of the ``inclusion`` scene
(3.05 ms against 2.30 ms without a counter). The ``iteration_tap`` primitive lowers to the
same XLA host call, but its host function receives the NumPy scalars as they come: about
0.06 ms per call (2.58 ms per evaluation). It is built from two pieces of JAX that are public
in practice but not promised: ``jax.interpreters.mlir.emit_python_callback``, and
``io_callback``'s own effect, which keeps the tap from being pruned and lets it into loops and
custom derivative rules exactly where ``io_callback`` may go. A probe at first use lowers and
runs one tap; where either piece is missing or does not work, every tap goes through
``io_callback`` instead (the same counts, slower).

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

import functools
import itertools
import logging
import threading
import weakref
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import io_callback

__all__ = ["IterationCounter", "is_tally_host_call", "tap"]

_LOG = logging.getLogger(__name__)


@jax.tree_util.register_pytree_node_class
class IterationCounter:
    """Host-side tally of the CG iterations that actually ran, primal and adjoint.

    Pass one to :func:`prdp_fem.cg.solve` (``counter=``): every forward solve adds its
    iterations to ``primal`` and every backward (adjoint) solve -- the truncated adjoint PCG
    in implicit mode, the reversed scan in unrolled mode -- adds its own to ``adjoint``; so
    does every forward-mode tangent solve of implicit mode (a Hessian-vector product adds
    two). The tally is exact even inside jitted line searches that evaluate the objective an
    unknown number of times. Read it after the results are ready (``jax.block_until_ready``).
    Under ``vmap`` every batch member counts, in one host call per batched solve (see
    :func:`tap`). Known gap: an implicit-mode transpose solve under *two* nested ``vmap`` s
    (e.g. ``vmap`` over samples of a ``jacrev``) counts the inner batch only; map the outer
    axis with ``lax.map`` (as :class:`prdp_fem.learned.BatchObjective` does) to keep the
    tally exact.

    A counter is a pytree whose one leaf is its ``slot``, the key under which the host finds
    it (a weak table of live counters). Passed to a jitted function as an *argument*, the
    slot is traced, so the compiled program does not depend on which counter it counts into:
    runs that differ only in their counters share one executable (see
    :mod:`prdp_fem.executables`). Closed over, the slot is a constant of the program. A
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
    module-level function serves every program, and a program's text says all that its host
    calls do (:func:`is_tally_host_call`, :mod:`prdp_fem.executables`).
    """
    counter = _LIVE.get(int(slot))
    if counter is not None:
        counter._add(_KINDS[int(kind)], iterations, solves)
    return ()


def is_tally_host_call(callback) -> bool:
    """Whether a program's host callback (as JAX wraps it) is a tap of this module."""
    return any(getattr(cell, "cell_contents", None) is _tally
               for cell in getattr(callback, "__closure__", None) or ())


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
    if _primitive_works():
        _TAP_PRIMITIVE.bind(kind, slot, iterations, solves)
    else:
        _io_callback_tap(kind, slot, iterations, solves)


def _io_callback_tap(kind, slot, iterations, solves) -> None:
    io_callback(_tally, None, kind, slot, iterations, solves, ordered=False)


# --------------------------------------------------------------------------------------
# the iteration_tap primitive: io_callback's host call without its device_put
# --------------------------------------------------------------------------------------


def _tap_primitive():
    """``iteration_tap(kind, slot, iterations, solves)``: no outputs, :func:`_tally` called
    on the host with NumPy scalars; ``None`` where this JAX lacks the pieces."""
    try:
        from jax._src.callback import _IOEffect
        from jax.extend.core import Primitive
        from jax.interpreters import mlir
        emit = mlir.emit_python_callback
    except (ImportError, AttributeError):
        return None
    primitive = Primitive("iteration_tap")
    primitive.multiple_results = True
    primitive.def_effectful_abstract_eval(lambda *avals: ([], {_IOEffect}))
    primitive.def_impl(lambda *operands: _tally(*operands) and [])

    def lowering(ctx, *operands):
        emit(ctx, _tally, None, list(operands), ctx.avals_in, [], has_side_effect=True)
        return []

    mlir.register_lowering(primitive, lowering, cacheable=False)
    return primitive


_TAP_PRIMITIVE = _tap_primitive()


@functools.cache
def _primitive_works() -> bool:
    """Whether one tap through the primitive lowers, runs and arrives (once per process)."""
    if _TAP_PRIMITIVE is None:
        return False
    probe = IterationCounter()
    try:
        with jax.ensure_compile_time_eval():  # a probe that runs, also mid-trace
            # NumPy constants: a jnp constructor would compile a program of its own here
            jax.jit(lambda slot, k: _TAP_PRIMITIVE.bind(np.int32(1), slot, k,
                                                        np.int32(1)))(probe.slot, 3)
            jax.effects_barrier()
    except Exception as error:  # any failure means: use io_callback
        _LOG.debug("iteration_tap does not work here (%r); the tally uses io_callback", error)
        return False
    works = (probe.adjoint, probe.adjoint_solves, probe.primal) == (3, 1, 0)
    if not works:
        _LOG.debug("iteration_tap lost its count here; the tally uses io_callback")
    return works
