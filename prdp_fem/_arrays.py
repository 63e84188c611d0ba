"""NumPy or ``jax.numpy``, picked by the arguments, for rules that run both on the host and in jit.

The refinement controllers and the AMG rebuild rule update small states once per optimiser
step: from host values on the Python driver (no dispatch, no device round trip) and from
tracers inside a jitted step. Each update asks :func:`array_module` which namespace to use.
"""

import jax.numpy as jnp
import numpy as np

__all__ = ["array_module"]

_HOST_TYPES = (np.ndarray, np.generic, float, int, bool)


def array_module(*values):
    """NumPy when every argument is a host value, else ``jnp`` (a JAX array or a tracer)."""
    return np if all(isinstance(v, _HOST_TYPES) for v in values) else jnp
