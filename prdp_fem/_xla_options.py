"""The XLA options this package compiles its own programs with, chosen per program.

On the CPU, XLA's classic fusion emitters (``xla_cpu_use_fusion_emitters=False``) compile this
package's programs faster than its default emitters and run their PCG iterations faster at
tens of thousands of unknowns and more (measured in ``docs/performance-log.md``, "XLA's
classic CPU fusion emitters, per program"). The arithmetic is the same IEEE arithmetic, but
a fusion may order a sum differently, as another CPU would: results agree to round-off, and
a run that amplifies round-off (unpreconditioned PRDP on an ill-conditioned scene) may take
another path.

One kind of program must not get them: the classic emitters fuse a chain of gathers into one
loop that recomputes every coarser level per fine entry, which makes a JAX AMG V-cycle many
times slower. Options are per executable (``Lowered.compile``'s
``compiler_options``, ``jax.jit``'s), so each program is compiled with the classic emitters
unless

* it applies an AMG cycle (the primitive :data:`AMG_CYCLE`, found by walking its jaxpr),
* it compiles for another backend than the CPU, or
* the caller's ``XLA_FLAGS`` name the emitters: that choice wins, for every program
  (``XLA_FLAGS=--xla_cpu_use_fusion_emitters=true`` restores XLA's default everywhere). XLA
  reads the variable once, when JAX starts its backend, and this module when it compiles a
  program: set it before the first JAX computation (a ``--flagfile`` is not looked into).

Chosen here: inversion and training steps (:class:`~prdp_fem._executables.SharedCompile`) and
the reduced-space CG's gradient from their jaxprs (:func:`compiler_options`, compiled by
:func:`compile_lowered`); an eager
:func:`~prdp_fem.linalg.cg.solve` and the timed solves of forward, h- and scene studies from their
preconditioner (:func:`solver_options`: a preconditioner pytree may be a cycle, so it keeps
XLA's emitters without looking). Every other program keeps JAX's options: a ``jax.jit`` of
the user's own around this package's functions, and the package's smaller jitted helpers
(validation passes, assembly). A program with pyamg's callback cycle keeps XLA's emitters too
(the primitive is the same), although it has no chain of gathers.

>>> import jax, jax.numpy as jnp
>>> traced = jax.jit(lambda x: jnp.sin(x) @ x).trace(jnp.ones(3))
>>> applies_amg_cycle(traced.jaxpr)
False
"""

from __future__ import annotations

import functools
import os
from collections.abc import Iterator
from types import MappingProxyType
from typing import Any

import jax
import numpy as np
from jax.extend.core import ClosedJaxpr, Jaxpr

__all__ = ["AMG_CYCLE", "CLASSIC_EMITTERS", "FUSION_EMITTERS", "applies_amg_cycle",
           "classic_emitters_apply", "compile_lowered", "compiler_options", "solver_options"]

#: The name of the primitive that applies an AMG V-cycle (:mod:`prdp_fem.linalg.amg` binds it).
AMG_CYCLE = "amg_v_cycle"
_EMITTERS_FLAG = "xla_cpu_use_fusion_emitters"
#: The options of a program that applies no AMG cycle, on the CPU.
CLASSIC_EMITTERS = MappingProxyType({_EMITTERS_FLAG: False})
#: XLA's own fusion emitters, forced (a benchmark's side-by-side column; a caller's flags lose).
FUSION_EMITTERS = MappingProxyType({_EMITTERS_FLAG: True})


def classic_emitters_apply() -> bool:
    """Whether programs compile for the CPU and the caller's ``XLA_FLAGS`` (read now; XLA
    read them when its backend started) leave the fusion emitters to this package, and this
    XLA knows the option."""
    return jax.default_backend() == "cpu" and \
        _EMITTERS_FLAG not in os.environ.get("XLA_FLAGS", "") and _option_known()


@functools.cache
def _option_known() -> bool:
    """Whether this XLA compiles a program with :data:`CLASSIC_EMITTERS` (once per process)."""
    try:
        jax.jit(lambda x: x + 1).lower(np.float64(0.0)).compile(
            compiler_options=dict(CLASSIC_EMITTERS))
    except Exception:  # "No such compile option": the classic emitters are gone
        return False
    return True


def compile_lowered(lowered, options: dict[str, Any] | None = None):
    """``lowered.compile(compiler_options=options)``."""
    return lowered.compile(compiler_options=dict(options) if options else None)


def solver_options(preconditioner: Any) -> dict[str, Any]:
    """The options of a solve's program known before tracing it: the classic emitters for a
    named preconditioner (``"identity"``, ``"jacobi"``: no AMG cycle) where they apply; a
    preconditioner pytree may be a cycle, so it keeps XLA's emitters without looking.

    >>> solver_options(object())
    {}
    """
    if isinstance(preconditioner, str) and classic_emitters_apply():
        return dict(CLASSIC_EMITTERS)
    return {}


def compiler_options(jaxpr: ClosedJaxpr | Jaxpr) -> dict[str, Any]:
    """The options to compile the program of ``jaxpr`` with (see the module docstring)."""
    if not classic_emitters_apply() or applies_amg_cycle(jaxpr):
        return {}
    return dict(CLASSIC_EMITTERS)


def applies_amg_cycle(jaxpr: ClosedJaxpr | Jaxpr) -> bool:
    """Whether ``jaxpr`` or any jaxpr nested in it (loop bodies, branches, custom rules' calls)
    binds :data:`AMG_CYCLE`."""
    pending = list(_jaxprs_in(jaxpr))
    seen: set[int] = set()
    while pending:
        inner = pending.pop()
        if id(inner) in seen:
            continue
        seen.add(id(inner))
        for equation in inner.eqns:
            if equation.primitive.name == AMG_CYCLE:
                return True
            for parameter in equation.params.values():
                pending.extend(_jaxprs_in(parameter))
    return False


def _jaxprs_in(value) -> Iterator[Jaxpr]:
    if isinstance(value, ClosedJaxpr):
        yield value.jaxpr
    elif isinstance(value, Jaxpr):
        yield value
    elif isinstance(value, tuple | list):
        for item in value:
            yield from _jaxprs_in(item)
