"""Host data onto the accelerator as JAX arrays, without compiling anything.

``jnp.asarray`` of a NumPy array or a Python number can run a small compiled program per new
shape and dtype, which adds up over a setup that converts many arrays. :func:`as_jax` converts
on the host and copies with ``jax.device_put``, which compiles nothing.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

__all__ = ["as_jax"]


def as_jax(value: Any, dtype: Any = None) -> jax.Array:
    """``value`` (array-like or number, on the host) as a JAX array of ``dtype``.

    Numbers give strongly typed scalars (``jnp.asarray(1.0)`` is weakly typed). Inside a
    traced function the result is a tracer, as with any JAX operation: keep constants built
    under ``jax.ensure_compile_time_eval`` where they are cached.

    >>> as_jax([1, 2], np.int32)
    Array([1, 2], dtype=int32)
    """
    return jax.device_put(np.asarray(value, dtype=dtype))
