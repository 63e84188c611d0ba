"""Step programs compiled ahead of time, their compile time counted apart from their runs.

An inversion, a training and a heat calibration each call one step function many times; the
history reports the run time without compilation and the compilation time apart. So a step
is a :class:`SharedCompile`: ``jax.jit(fn).trace(...).lower().compile()`` once per value of
its static argument and per argument structure, shapes and dtypes, timed, then called as the
compiled program (:class:`jax.stages.Compiled`). Every inversion builds its own step
function, so :func:`kept_programs` keeps the step per settings for the process: runs that
differ only in ``K``, ``K_adj``, ``rtol`` and their counters (arguments of the program) share
one executable.

Each program is compiled with the XLA options chosen for it (:mod:`prdp_fem._xla_options`).

>>> import jax.numpy as jnp
>>> double = SharedCompile(lambda x, n: x * n, static_argnum=1)
>>> float(double(jnp.float64(3.0), 2)), float(double(jnp.float64(4.0), 2))
(6.0, 8.0)
>>> len(double._cache)  # one executable for both calls
1
"""

from __future__ import annotations

import functools
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import jax

from ._xla_options import compile_lowered, compiler_options

__all__ = ["SharedCompile", "kept_programs"]

#: Executables one SharedCompile keeps (per static value and argument types).
_ENTRY_LIMIT = 8


class SharedCompile:
    """``fn`` compiled once per value of its static argument (``static_argnum``, an int such
    as an unrolled ``K``) and per argument structure, shapes and dtypes.

    Every array argument is taken as strongly typed (``jax.jit`` would let a weakly typed
    scalar take the dtype of what it meets), so one executable fits every call with its key.
    ``seconds`` is the time spent tracing, lowering and compiling, so that callers can time
    runs apart from it. The :data:`_ENTRY_LIMIT` most recently used executables are kept (a
    sweep of shapes or of unrolled ``K``).
    """

    def __init__(self, fn: Callable, static_argnum: int | None = None):
        self._fn, self._static_argnum = fn, static_argnum
        self._cache: OrderedDict[tuple, Any] = OrderedDict()  # the most recent last
        self.seconds = 0.0

    def __call__(self, *args):
        static, dynamic = self._split(args)
        leaves, treedef = jax.tree_util.tree_flatten(dynamic)
        key = (static, treedef, tuple(map(_argument_type, leaves)))
        compiled = self._cache.get(key)
        if compiled is None:
            start = time.perf_counter()
            compiled = self._cache[key] = self._compile(static, treedef, leaves)
            self.seconds += time.perf_counter() - start
            while len(self._cache) > _ENTRY_LIMIT:
                self._cache.popitem(last=False)
        elif len(self._cache) > 1:
            self._cache.move_to_end(key)
        try:
            return compiled(*leaves)
        except Exception as error:
            reported = _floating_point_error(error, self._fn)
            if reported is None:
                raise
            raise reported from error

    def _split(self, args: tuple) -> tuple[int | None, tuple]:
        n = self._static_argnum
        if n is None:
            return None, args
        return int(args[n]), args[:n] + args[n + 1:]

    def _compile(self, static, treedef, leaves: list):
        """The executable of ``fn`` taking the flattened dynamic arguments (a pytree
        flattened and built again may be another type, as a counter is: its leaves are what
        is passed)."""
        n = self._static_argnum

        def flat(*flat_leaves):
            args = list(jax.tree_util.tree_unflatten(treedef, flat_leaves))
            if static is not None:
                args.insert(n, static)
            return self._fn(*args)

        traced = jax.jit(flat).trace(*map(_strong, leaves))
        return compile_lowered(traced.lower(), compiler_options(traced.jaxpr))


def kept_programs(build: Callable[..., SharedCompile],
                  size: int = 8) -> Callable[..., SharedCompile]:
    """``build(*settings)``, kept for the process per settings (the last ``size``).

    A driver (:func:`prdp_fem.inverse.driver.invert`, the trainings) builds a new step function on
    every call, so equal settings would trace, lower and compile their step again. Called with
    ``keep=False`` (a preconditioner object: a pytree of arrays, which a key would keep alive)
    or with settings that cannot be hashed, it builds a program of its own. ``cache_clear()``
    forgets the kept ones.
    """
    kept = functools.lru_cache(maxsize=size)(build)

    def program(*settings, keep: bool = True) -> SharedCompile:
        try:
            hash(settings)
        except TypeError:  # an optimizer (or other setting) that is not a key
            keep = False
        return kept(*settings) if keep else build(*settings)

    program.cache_clear = kept.cache_clear
    return program


def _floating_point_error(error: Exception, fn) -> FloatingPointError | None:
    """JAX's report of a NaN/Inf output (``jax_debug_nans``/``jax_debug_infs``) from a
    compiled program, where it is not a ``FloatingPointError`` already, as the one
    ``jax.jit`` raises; ``None`` for any other error."""
    if type(error).__name__ != "InternalFloatingPointError":
        return None
    name = getattr(fn, "__qualname__", type(fn).__name__)
    return FloatingPointError(f"invalid value ({getattr(error, 'ty', 'nan')}) encountered in "
                              f"{name}; run it under jax.disable_jit() to find the operation")


def _argument_type(leaf):
    """Shape, dtype and placement over devices (a Python scalar: its type)."""
    shape = getattr(leaf, "shape", None)
    return type(leaf) if shape is None else (shape, leaf.dtype, _spread(leaf))


def _strong(leaf):
    """An array leaf as a strongly typed abstract value (a Python scalar stays itself),
    with its sharding where it is spread over several devices (a sharded system's arrays:
    the program is compiled for them; any other argument is placed by the compiler)."""
    shape = getattr(leaf, "shape", None)
    if shape is None:
        return leaf
    return jax.ShapeDtypeStruct(shape, leaf.dtype, sharding=_spread(leaf))


def _spread(leaf):
    """The sharding of an array on more than one device, else ``None``."""
    sharding = getattr(leaf, "sharding", None)
    if sharding is None or len(sharding.device_set) < 2:
        return None
    return sharding
