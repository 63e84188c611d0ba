"""Compiled programs shared within a process, keyed by the program they run.

JAX's persistent compilation cache does not store an executable that contains host callbacks,
and the iteration tally (:mod:`prdp_fem.tally`) is one; ``jax.jit`` caches per function
object, and every inversion builds its own step function. So a study of six configurations
compiled six optimiser steps although five of them are the same program: they differ only in
``K``, ``K_adj`` and their counters, which are arguments. :class:`SharedCompile` lowers its
function and looks the lowered program text up in a small process-wide table before
compiling: equal programs compile once.

Sharing is sound because the text is the whole program: constants are in it, and the tally's
host calls route by the counter slot they receive as an operand (not by a Python object the
executable holds). A lowering that hands JAX constants as hidden arguments (JAX's
``jax_use_simplified_jaxpr_constants`` mode) is compiled for itself, never shared.

>>> import jax.numpy as jnp
>>> double = SharedCompile(lambda x, n: x * n, static_argnum=1)
>>> twice = SharedCompile(lambda x, n: x * n, static_argnum=1)  # another function, same program
>>> float(double(jnp.float64(3.0), 2)), float(twice(jnp.float64(4.0), 2))
(6.0, 8.0)
>>> twice.shared
1
"""

from __future__ import annotations

import hashlib
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import jax

__all__ = ["SharedCompile"]

#: Executables by program; the least recently used is dropped beyond the limit.
_EXECUTABLES: OrderedDict[tuple, Any] = OrderedDict()
_LIMIT = 32


class SharedCompile:
    """``fn`` compiled once per value of its static argument (``static_argnum``, an int such
    as an unrolled ``K``) and per argument types, reusing an executable of the same program
    compiled earlier in the process. The other arguments' pytree structure must stay the same
    between calls (as an inversion's do).

    ``seconds`` is the time spent lowering and compiling (so callers can time runs apart
    from it); ``shared`` counts the compilations saved by reusing an executable.
    """

    def __init__(self, fn: Callable, static_argnum: int | None = None):
        self._fn, self._static_argnum = fn, static_argnum
        self._cache: dict[tuple, tuple[Any, list]] = {}
        self.seconds, self.shared = 0.0, 0

    def __call__(self, *args):
        static, dynamic = self._split(args)
        leaves, treedef = jax.tree_util.tree_flatten(dynamic)
        key = (static, tuple(map(_argument_type, leaves)))
        if key not in self._cache:
            start = time.perf_counter()
            self._cache[key] = self._compile(static, treedef, leaves)
            self.seconds += time.perf_counter() - start
        executable, out_tree = self._cache[key]
        return jax.tree_util.tree_unflatten(out_tree[0], executable(*leaves))

    def _split(self, args: tuple) -> tuple[int | None, tuple]:
        n = self._static_argnum
        if n is None:
            return None, args
        return int(args[n]), args[:n] + args[n + 1:]

    def _compile(self, static, treedef, leaves) -> tuple[Any, list]:
        out_tree: list = []  # filled when the flat function is traced

        def flat(*leaves):
            args = list(jax.tree_util.tree_unflatten(treedef, leaves))
            if static is not None:
                args.insert(self._static_argnum, static)
            out_leaves, tree = jax.tree_util.tree_flatten(self._fn(*args))
            out_tree.append(tree)
            return out_leaves

        lowered = jax.jit(flat).lower(*leaves)
        key = _program_key(lowered, leaves)
        if key is None:
            return lowered.compile(), out_tree
        if key in _EXECUTABLES:
            _EXECUTABLES.move_to_end(key)
            self.shared += 1
        else:
            _EXECUTABLES[key] = lowered.compile()
            while len(_EXECUTABLES) > _LIMIT:
                _EXECUTABLES.popitem(last=False)
        return _EXECUTABLES[key], out_tree


def _program_key(lowered, leaves) -> tuple | None:
    """The program text's digest and the argument types; ``None``: do not share."""
    constants = getattr(getattr(lowered, "_lowering", None), "const_args", None)
    if constants is None or len(constants):
        return None  # constants passed apart from the text, or a JAX that does not say
    digest = hashlib.sha256(lowered.as_text().encode()).hexdigest()
    return digest, tuple(map(_argument_type, leaves))


def _argument_type(leaf):
    """Shape and dtype (a Python scalar: its type). Not the weak type: it steers tracing,
    not the compiled program, and an optimiser state comes back from its first update with
    other weak types than ``init`` gave it (keying on it compiled every run's step twice).
    Read as attributes: this runs for every leaf of every call."""
    shape = getattr(leaf, "shape", None)
    return type(leaf) if shape is None else (shape, leaf.dtype)
