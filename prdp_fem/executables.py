"""Compiled programs shared within a process, keyed by the program they run.

JAX's persistent compilation cache does not store an executable that contains host callbacks,
and the iteration tally (:mod:`prdp_fem.tally`) is one; ``jax.jit`` caches per function
object, and every inversion builds its own step function. So a study of six configurations
compiled six optimiser steps although five of them are the same program: they differ only in
``K``, ``K_adj`` and their counters, which are arguments. :class:`SharedCompile` lowers its
function and looks the lowered program up in a small process-wide table before compiling:
equal programs compile once, and a later process loads what an earlier one compiled
(:mod:`prdp_fem.program_store`).

What makes two lowerings the same program: the same text (constants are in it), the same
arguments read (unread ones are left out of the text, so which ones it takes is part of the
key), the same argument shapes and dtypes, the same backend and device count, and host
callbacks that do nothing but what the text says. The tally's host calls qualify (one
module-level function; which counter and which tally arrive as operands); any other host
callback -- a ``jax.debug.callback``, pyamg's cycle behind a callable preconditioner --
holds Python state the text does not show, so such a program is compiled for itself, as is a
lowering that passes constants apart from its text or whose compile arguments this JAX does
not expose.

>>> import jax.numpy as jnp
>>> double = SharedCompile(lambda x, n: x * n, static_argnum=1)
>>> twice = SharedCompile(lambda x, n: x * n, static_argnum=1)  # another function, same program
>>> float(double(jnp.float64(3.0), 2)), float(twice(jnp.float64(4.0), 2))
(6.0, 8.0)
>>> twice.shared
1
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import operator
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .program_store import compile_lowered
from .tally import is_tally_host_call
from .xla_options import compiler_options

__all__ = ["SharedCompile", "kept_programs"]

#: Executables by program; the least recently used is dropped beyond the limit.
_EXECUTABLES: OrderedDict[tuple, Any] = OrderedDict()
_LIMIT = 32
#: Executables one SharedCompile keeps (per static value and argument types).
_ENTRY_LIMIT = 8
_TABLE_LOCK = threading.Lock()


#: Arrays of a packed argument up to this many elements travel in their dtype's buffer;
#: larger ones stay arguments of their own: their work outweighs a dispatch, and a loop that
#: reads a slice of a buffer may copy it first.
_PACK_LIMIT = 1 << 16


class _Entry(NamedTuple):
    treedef: tuple        # the arguments' structure it was compiled for (per _Segments)
    executable: Any       # a jax.stages.Compiled
    run: Callable         # its call (see _runner)
    out_tree: list        # [the result's structure], filled when the function is traced
    passed: Callable      # leaves -> those passed one by one (not empty, not packed)
    packing: _Packing     # leaves -> the buffers of the packed ones


class _Packing:
    """The small arrays of an entry's packed arguments, one flat buffer per dtype.

    The buffers are built on the host once, and again only when a call brings other arrays
    than the last one did (compared by identity: a ``jax.Array`` is immutable, so the same
    object holds the same values). Inside the program each array is a static slice of its
    buffer.
    """

    def __init__(self, groups: list[list[int]], leaves: list):
        self.layout = [[(i, leaves[i].shape, leaves[i].size) for i in group]
                       for group in groups]   # (leaf index, shape, size) per buffer, in order
        self._dtypes = [np.dtype(leaves[group[0]].dtype) for group in groups]
        self.indices = [i for group in groups for i in group]
        self._take = _selector(self.indices)
        # (the arrays, their buffers), replaced as one: a call on another thread sees a pair
        self._last: tuple[tuple, tuple] = ((), ())

    def buffer_types(self) -> list[jax.ShapeDtypeStruct]:
        return [jax.ShapeDtypeStruct((sum(size for _, _, size in layout),), dtype)
                for layout, dtype in zip(self.layout, self._dtypes, strict=True)]

    def buffers(self, leaves: list) -> tuple:
        if not self.indices:
            return ()
        sources = self._take(leaves)
        last_sources, last_buffers = self._last
        if len(sources) == len(last_sources) and \
                all(a is b for a, b in zip(sources, last_sources, strict=True)):
            return last_buffers
        by_index = dict(zip(self.indices, sources, strict=True))
        buffers = tuple(jax.device_put(np.concatenate([np.ravel(np.asarray(by_index[i]))
                                                       for i, _, _ in layout]))
                        for layout in self.layout)
        self._last = (sources, buffers)
        return buffers

    def forget(self) -> None:
        """Drop the last arrays and their buffers (the caller is done with them)."""
        self._last = ((), ())

    def unpack(self, buffers) -> dict[int, jax.Array]:
        """Inside the program: leaf index -> its slice of its buffer."""
        leaves = {}
        for buffer, layout in zip(buffers, self.layout, strict=True):
            offset = 0
            for i, shape, size in layout:
                leaves[i] = jax.lax.slice(buffer, (offset,), (offset + size,)).reshape(shape)
                offset += size
        return leaves


class _Flat(NamedTuple):
    """One segment of the arguments, flattened."""

    source: Any        # what was flattened (a packed argument: kept to recognise it)
    leaves: list
    treedef: Any
    types: tuple       # _argument_type of each leaf


def _flat(source) -> _Flat:
    leaves, treedef = jax.tree_util.tree_flatten(source)
    return _Flat(source, leaves, treedef, tuple(map(_argument_type, leaves)))


class _Segments:
    """The dynamic arguments flattened in segments: each packed argument alone, and the runs
    of other arguments between them; the leaves come out in the order of flattening them all.

    A packed argument's flattening is remembered by identity: the same object holds the same
    leaves (a frozen pytree of immutable arrays, as the problems are) unless it is a ``dict``
    or a ``list``, which may be changed in place and are flattened every call. Flattening a
    ``plate_hole`` problem (99 leaves) and reading its leaves' types took about 18 us of each
    0.5 ms step; a repeated problem now costs an identity check."""

    def __init__(self, n_arguments: int, packed: list[int]):
        self.n_arguments = n_arguments
        packed = [i for i in packed if i < n_arguments]
        bounds = sorted({0, n_arguments} | set(packed) | {i + 1 for i in packed})
        self._slices = [(start, stop, start in packed)
                        for start, stop in itertools.pairwise(bounds)]
        self._remembered: dict[int, _Flat] = {}  # packed position -> its last flattening

    def flatten(self, arguments: tuple) -> tuple[list, tuple, tuple]:
        """``(leaves, treedefs, types)``: ``treedefs`` one per segment."""
        leaves, treedefs, types = [], [], ()
        for start, stop, packed in self._slices:
            if not packed:
                flat = _flat(arguments[start:stop])
            elif isinstance(arguments[start], dict | list):
                flat = _flat(arguments[start])
            else:
                flat = self._remembered.get(start)
                if flat is None or flat.source is not arguments[start]:
                    flat = self._remembered[start] = _flat(arguments[start])
            leaves += flat.leaves
            treedefs.append(flat.treedef)
            types += flat.types
        return leaves, tuple(treedefs), types

    def whole(self, treedefs: tuple):
        """The structure of the argument tuple from the segments' structures."""
        children = []
        for (_, _, packed), treedef in zip(self._slices, treedefs, strict=True):
            children += [treedef] if packed else treedef.children()
        return jax.tree_util.treedef_tuple(children)

    def forget(self) -> None:
        self._remembered.clear()


def _packed_groups(treedef, leaves: list, positions: list[int]) -> list[list[int]]:
    """The leaves that travel packed: the non-empty ``jax.Array`` s of the arguments at
    ``positions`` up to :data:`_PACK_LIMIT` elements, grouped by dtype (groups of two or
    more: one array gains nothing). A position past the call's arguments (a trailing
    argument left out) packs nothing."""
    children = treedef.children()
    starts = np.cumsum([0] + [child.num_leaves for child in children])
    groups: dict[np.dtype, list[int]] = {}
    for position in (p for p in positions if p < len(children)):
        for i in range(int(starts[position]), int(starts[position + 1])):
            leaf = leaves[i]
            if isinstance(leaf, jax.Array) and 0 < leaf.size <= _PACK_LIMIT:
                groups.setdefault(np.dtype(leaf.dtype), []).append(i)
    return [group for group in groups.values() if len(group) > 1]


class SharedCompile:
    """``fn`` compiled once per value of its static argument (``static_argnum``, an int such
    as an unrolled ``K``) and per argument structure, shapes and dtypes, reusing an
    executable of the same program compiled earlier in the process.

    Every array argument is taken as strongly typed (``jax.jit`` would let a weakly typed
    scalar take the dtype of what it meets), so one executable fits every call with its key.
    ``seconds`` is the time spent lowering and compiling (so callers can time runs apart from
    it); ``shared`` counts the compilations saved by reusing an executable.

    A program with host callbacks (the iteration tally) cannot take JAX's C++ dispatch; its
    Python dispatch cost about 4 us per argument, and an inversion step had 123 arrays. So
    it is given only what it reads: empty arrays (a kernel's missing COO tail, a layout
    without repeated diagonals; 45 of them) are made by the program from the shape it was
    compiled for, arrays it does not read (the COO form of a matrix applied through its ELL
    layout; 19) are dropped, and JAX's per-call work is skipped (see :func:`_runner`).

    ``packed_argnums`` names arguments that stay the same from call to call (an inverse
    problem: 60-75 non-empty arrays): their arrays of up to :data:`_PACK_LIMIT` elements are
    passed as one flat buffer per dtype, built when the arrays change (see :class:`_Packing`),
    and sliced back inside the program. Through JAX's Python dispatch they cost about 2.4 us
    each on a 2-core CPU, a fifth of a small inversion step (``plate_hole``: 0.53 -> 0.42 ms).
    The direct call (:class:`_DirectCall`) passes arrays for a fraction of that, and there
    packing measured neutral; it stays for the JAX versions that do not allow that call.
    """

    def __init__(self, fn: Callable, static_argnum: int | None = None,
                 packed_argnums: tuple[int, ...] = ()):
        self._fn, self._static_argnum = fn, static_argnum
        if static_argnum in packed_argnums:
            raise ValueError(f"argument {static_argnum} cannot be both static and packed")
        self._packed_argnums = tuple(packed_argnums)
        self._segments = None  # how the dynamic arguments are flattened (first call)
        self._cache: OrderedDict[tuple, _Entry] = OrderedDict()  # the most recent last
        self.seconds, self.shared = 0.0, 0

    def __call__(self, *args):
        static, dynamic = self._split(args)
        if self._segments is None or self._segments.n_arguments != len(dynamic):
            self._segments = _Segments(len(dynamic), self._packed_positions())
        leaves, treedef, types = self._segments.flatten(dynamic)
        key = (static, types)
        entry = self._cache.get(key)
        if entry is None or entry.treedef != treedef:
            start = time.perf_counter()
            entry = self._cache[key] = self._compile(static, treedef, leaves)
            self.seconds += time.perf_counter() - start
            while len(self._cache) > _ENTRY_LIMIT:  # a long sweep of shapes or unrolled K
                self._cache.popitem(last=False)
        elif len(self._cache) > 1:
            self._cache.move_to_end(key)
        buffers = entry.packing.buffers(leaves)
        try:
            outputs = entry.run(*buffers, *entry.passed(leaves))
        except Exception as error:
            reported = _floating_point_error(error, self._fn)
            if reported is None:
                raise
            raise reported from error
        return jax.tree_util.tree_unflatten(entry.out_tree[0], outputs)

    def release(self) -> None:
        """Let go of the arrays the last calls packed (the executables stay): a program kept
        for later callers should not keep a finished caller's problem alive."""
        for entry in self._cache.values():
            entry.packing.forget()
        if self._segments is not None:
            self._segments.forget()

    def _split(self, args: tuple) -> tuple[int | None, tuple]:
        n = self._static_argnum
        if n is None:
            return None, args
        return int(args[n]), args[:n] + args[n + 1:]

    def _compile(self, static, treedefs, leaves) -> _Entry:
        treedef = self._segments.whole(treedefs)
        out_tree: list = []  # filled when the flat function is traced
        empty = {i: (leaf.shape, leaf.dtype) for i, leaf in enumerate(leaves) if _is_empty(leaf)}
        packing = _Packing(_packed_groups(treedef, leaves, self._packed_positions()), leaves)
        packed = set(packing.indices)
        kept = [i for i in range(len(leaves)) if i not in empty and i not in packed]
        n_buffers = len(packing.layout)

        def flat(*arguments):
            unpacked = packing.unpack(arguments[:n_buffers])
            given = iter(arguments[n_buffers:])
            all_leaves = [jnp.zeros(*empty[i]) if i in empty else
                          unpacked[i] if i in packed else next(given)
                          for i in range(len(leaves))]
            args = list(jax.tree_util.tree_unflatten(treedef, all_leaves))
            if static is not None:
                args.insert(self._static_argnum, static)
            out_leaves, tree = jax.tree_util.tree_flatten(self._fn(*args))
            out_tree.append(tree)
            return out_leaves

        arguments = packing.buffer_types() + [_strong(leaves[i]) for i in kept]
        traced = jax.jit(flat).trace(*arguments)
        executable = self._executable(traced.lower(), arguments,
                                      compiler_options(traced.jaxpr))
        return _Entry(treedefs, executable, _runner(executable), out_tree, _selector(kept),
                      packing)

    def _packed_positions(self) -> list[int]:
        """``packed_argnums`` as positions among the dynamic (non-static) arguments."""
        static = self._static_argnum
        return [n - (static is not None and n > static) for n in self._packed_argnums]

    def _executable(self, lowered, leaves, options: dict):
        """An executable of the same program compiled earlier in the process, else a new one
        (compiled with the XLA ``options``)."""
        key = _program_key(lowered, leaves, options)
        if key is None:
            return compile_lowered(lowered, options)
        with _TABLE_LOCK:
            executable = _EXECUTABLES.get(key)
            if executable is not None:
                _EXECUTABLES.move_to_end(key)
                self.shared += 1
                return executable
        executable = compile_lowered(lowered, options)
        with _TABLE_LOCK:
            _EXECUTABLES[key] = executable
            while len(_EXECUTABLES) > _LIMIT:
                _EXECUTABLES.popitem(last=False)
        return executable


def kept_programs(build: Callable[..., SharedCompile],
                  size: int = 8) -> Callable[..., SharedCompile]:
    """``build(*settings)``, kept for the process per settings (the last ``size``).

    A driver (:func:`prdp_fem.inverse.invert`, the trainings) builds a new step function on
    every call, so equal settings traced and lowered their step again (0.4-1 s) before
    finding the shared executable. Called with ``keep=False`` (a preconditioner object: a
    pytree of arrays, which a key would keep alive) or with settings that cannot be hashed,
    it builds a program of its own. ``cache_clear()`` forgets the kept ones.
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


def _program_key(lowered, leaves, options: dict) -> tuple | None:
    """What identifies the program (see the module docstring); ``None``: do not share."""
    lowering = getattr(lowered, "_lowering", None)
    constants = getattr(lowering, "const_args", None)
    compile_args = getattr(lowering, "compile_args", None)
    if constants is None or len(constants) or not isinstance(compile_args, dict):
        return None  # constants apart from the text, or a JAX that does not say
    callbacks = compile_args.get("host_callbacks")
    backend = compile_args.get("backend")
    read = compile_args.get("kept_var_idx")
    if callbacks is None or backend is None or not all(map(is_tally_host_call, callbacks)):
        return None  # host calls holding state the text does not show
    if read is None:
        return None  # which arguments the text's parameters are: unknown
    digest = hashlib.sha256(lowered.as_text().encode()).hexdigest()
    return (digest, tuple(sorted(read)), tuple(map(_argument_type, leaves)), backend.platform,
            compile_args.get("num_devices"), tuple(sorted(options.items())))


def _runner(compiled) -> Callable:
    """How to call ``compiled``: its own call, or, for a program with host callbacks, a call
    that skips JAX's per-call work.

    A program with host callbacks (the iteration tally) cannot take JAX's C++ dispatch path;
    its Python path checks every argument's type and placement (about 1.3 us each on a 2-core
    CPU), places them (about 1.5 us each) and handles the runtime tokens. The checks repeat
    what the key of :class:`SharedCompile` has already established (shapes, dtypes, the
    structure), so they are skipped where this JAX exposes the call behind them
    (``unsafe_call``), and where it exposes the executable behind that, so is the rest (see
    :class:`_DirectCall`). Unread arguments are dropped there too: the program is lowered
    without them (JAX's ``keep_unused=False``), and those calls pass only the read ones on.
    """
    executable = getattr(compiled, "_executable", None)
    unchecked = getattr(executable, "unsafe_call", None)
    if getattr(unchecked, "has_host_callbacks", False) and \
            getattr(executable, "_kept_var_idx", None) is not None:
        return _DirectCall.of(unchecked) or unchecked
    return compiled


class _DirectCall:
    """A single-device program with host callbacks, run by its XLA executable directly.

    What JAX's Python path does per call besides running the program: argument checks and
    placement (about 2.4 us per argument), a runtime-token dance and a profiler annotation:
    about 60 us of a 0.45 ms ``plate_hole`` inversion step with 19 arguments. Here the
    arguments are ``jax.Array`` s of the program's one device already (the key checked their
    shapes and dtypes; the device is the backend's only one), a NumPy or Python scalar (a
    counter's slot) is placed once and kept, and the output token is handed to JAX as its own
    path does, so that :func:`jax.effects_barrier` still waits for the host calls.

    Falls back to JAX's path (``unsafe_call``) when NaN/Inf checking is on (it wraps the
    outputs), for an argument it does not pass itself (a typed PRNG key, as in
    ``optax.noisy_sgd``'s state) or a deleted one (JAX's path says which), and for good when
    an argument lives on another device (the executable refuses it before running
    anything). Built only where this JAX has every piece and a probe program gives the same
    result and tally both ways (:func:`_direct_calls_work`).
    """

    def __init__(self, unchecked, parts):
        self._unchecked = unchecked
        self._executable, self._handlers, self._device, self._token_set, \
            self._check_special, self._array_type = parts
        self._take = _selector(sorted(unchecked.kept_var_idx))
        self._placed: dict[int, tuple] = {}  # id -> (scalar, its device array)
        self._foreign = False  # an argument came from another device: JAX's path from now on

    @classmethod
    def of(cls, unchecked) -> _DirectCall | None:
        parts = _direct_parts(unchecked)
        if parts is None or not _direct_calls_work():
            return None
        return cls(unchecked, parts)

    def __call__(self, *args):
        if self._foreign or self._check_special():
            return self._unchecked(*args)
        arguments = list(self._take(args))
        for i, argument in enumerate(arguments):
            if type(argument) is not self._array_type:
                placed = self._place(argument)
                if placed is None:  # a key array, ...: JAX's path knows how to pass it
                    return self._unchecked(*args)
                arguments[i] = placed
        try:
            results = self._executable.execute_sharded(arguments, with_tokens=True)
        except RuntimeError as error:  # JAX's JaxRuntimeError
            if any(argument.is_deleted() for argument in arguments):
                return self._unchecked(*args)  # refused before running: JAX's path says why
            if "Buffer passed to Execute()" not in str(error):
                raise  # the program ran and failed: not ours to retry
            self._foreign = True
            return self._unchecked(*args)
        self._token_set(self._device, results.consume_token().get_token(0))
        return results.consume_with_handlers(self._handlers)

    def _place(self, value):
        """``value`` (NumPy or Python) as an array of the device, transferred the way JAX's
        path does (implicitly: a transfer guard applies); a scalar once, then kept (an array
        is mutable: every call). ``None`` for anything else."""
        if isinstance(value, np.ndarray):
            return self._transferred(value)
        if not isinstance(value, np.generic | int | float | bool):
            return None
        kept = self._placed.get(id(value))
        if kept is None or kept[0] is not value:
            if len(self._placed) > 16:
                self._placed.clear()
            kept = self._placed[id(value)] = (value, self._transferred(value))
        return kept[1]

    def _transferred(self, value):
        with jax.default_device(self._device):
            placed = jnp.asarray(value)
        return placed if type(placed) is self._array_type else None


def _direct_parts(unchecked) -> tuple | None:
    """What :class:`_DirectCall` needs of JAX's internals; ``None`` where any is missing or
    the program is beyond it (ordered effects, mutable arrays, several devices, a
    profile-guided build)."""
    try:
        from jax._src import dispatch
        from jax._src.array import ArrayImpl
        devices = unchecked._local_devices
        parts = (unchecked.xla_executable, unchecked.out_handler.handlers, devices[0],
                 dispatch.runtime_tokens.set_output_runtime_token,
                 dispatch.needs_check_special, ArrayImpl)
        plain = not (unchecked.ordered_effects or unchecked.mut or unchecked.pgle_profiler)
        local = len(devices) == 1 and len(devices[0].client.local_devices()) == 1
    except (ImportError, AttributeError, IndexError, TypeError):
        return None
    return parts if plain and local else None


@functools.cache
def _direct_calls_work() -> bool:
    """Whether a probe program (a tally tap and a result) gives the same result and tally
    run directly as through JAX (once per process)."""
    from .tally import IterationCounter, tap

    def probe(counter, x):
        tap(counter, "primal", jnp.int32(3), x)
        return 2.0 * x

    try:
        counter = IterationCounter()
        x = jax.device_put(np.arange(3.0))
        compiled = jax.jit(probe).lower(counter, x).compile()
        unchecked = compiled._executable.unsafe_call
        parts = _direct_parts(unchecked)
        if parts is None:
            return False
        [result] = _DirectCall(unchecked, parts)(counter.slot, x)
        jax.effects_barrier()
        return bool(np.array_equal(np.asarray(result), [0.0, 2.0, 4.0])) and \
            (counter.primal, counter.primal_solves) == (3, 1)
    except Exception:  # any failure: JAX's own path
        return False


def _floating_point_error(error: Exception, fn) -> FloatingPointError | None:
    """JAX's internal report of a NaN/Inf output (``jax_debug_nans``/``jax_debug_infs``) as
    the ``FloatingPointError`` that ``jax.jit`` raises; ``None`` for any other error."""
    if type(error).__name__ != "InternalFloatingPointError":
        return None
    name = getattr(fn, "__qualname__", type(fn).__name__)
    return FloatingPointError(f"invalid value ({getattr(error, 'ty', 'nan')}) encountered in "
                              f"{name}; run it under jax.disable_jit() to find the operation")


def _is_empty(leaf) -> bool:
    return getattr(leaf, "size", None) == 0


def _selector(kept: list[int]) -> Callable[[list], tuple]:
    """``leaves -> tuple(leaves[i] for i in kept)``, by ``operator.itemgetter`` (in C: this
    runs for every call)."""
    if not kept:
        return lambda leaves: ()
    if len(kept) == 1:
        index = kept[0]
        return lambda leaves: (leaves[index],)
    return operator.itemgetter(*kept)


def _argument_type(leaf):
    """Shape and dtype (a Python scalar: its type), read as attributes: this runs for every
    leaf of every call."""
    shape = getattr(leaf, "shape", None)
    return type(leaf) if shape is None else (shape, leaf.dtype)


def _strong(leaf):
    """An array leaf as a strongly typed abstract value (a Python scalar stays itself)."""
    shape = getattr(leaf, "shape", None)
    return leaf if shape is None else jax.ShapeDtypeStruct(shape, leaf.dtype)
