r"""The models the trainers take: any JAX function of trainable parameters and an input.

:func:`~prdp_fem.learning.learned.train` and :func:`~prdp_fem.learning.heat.train` train a
*model*: an object with

* ``params``, the trainable pytree (what the optimiser sees),
* ``predict(params, inputs)``, the output at other parameters (differentiated through),
* ``replace_params(params)``, the model with new ones (what training returns), and
* ``model(inputs)``, the output at its own parameters.

:class:`Model` wraps any ``apply(params, inputs)`` -- a plain JAX function, an Equinox
module (:func:`equinox_model`) or a Flax module with its variables (:func:`flax_model`) -- and
the built-in MLP (:class:`~prdp_fem.learning.learned.Network`) is one too. A model maps one
input vector to one output vector; the trainers batch it with ``vmap``. Equinox and Flax are
optional (``pip install 'prdp-fem[models]'``).

>>> import jax.numpy as jnp
>>> model = Model(lambda p, x: p["w"] * x, {"w": jnp.asarray(2.0)})
>>> float(model(jnp.asarray(3.0))), float(model.predict({"w": jnp.asarray(5.0)}, 3.0))
(6.0, 15.0)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from functools import partial
from typing import Any

import jax
import numpy as np

from ..errors import ShapeError, SolverConfigError

__all__ = ["Model", "check_model", "equinox_model", "flax_model"]


@partial(jax.tree_util.register_dataclass, data_fields=["params"], meta_fields=["apply"])
@dataclasses.dataclass(frozen=True)
class Model:
    """``apply(params, inputs) -> outputs`` with its trainable ``params`` (a pytree).

    ``apply`` is static (part of a compiled program's key): keep one function object per
    model, not a new lambda per call, or every call compiles anew.
    """

    apply: Callable[[Any, jax.Array], jax.Array]
    params: Any

    def predict(self, params, inputs: jax.Array) -> jax.Array:
        return self.apply(params, inputs)

    def replace_params(self, params) -> Model:
        return dataclasses.replace(self, params=params)

    def __call__(self, inputs: jax.Array) -> jax.Array:
        return self.apply(self.params, inputs)


def equinox_model(module) -> Model:
    """An Equinox module as a :class:`Model`: its floating-point arrays train, the rest
    (activations, integer fields) stays fixed (``eqx.partition``)."""
    eqx = _optional("equinox")
    params, static = eqx.partition(module, eqx.is_inexact_array)

    def apply(params, inputs):
        return eqx.combine(params, static)(inputs)

    return Model(apply, params)


def flax_model(module, variables) -> Model:
    """A Flax (linen) module and its variables (``module.init(key, x)``) as a :class:`Model`:
    every variable trains."""
    _optional("flax")

    def apply(params, inputs):
        return module.apply(params, inputs)

    return Model(apply, variables)


def _optional(name: str):
    try:
        return __import__(name)
    except ImportError:
        raise SolverConfigError(f"{name} is not installed; expected it for this model "
                                "(pip install 'prdp-fem[models]')") from None


def check_model(model, input_size: int, output_size: int, what: str) -> None:
    """Refuse an object that is not a model, or one whose output for an input of
    ``input_size`` values is not ``output_size`` real values (``what`` names them)."""
    missing = [name for name in ("params", "predict", "replace_params")
               if not hasattr(model, name)]
    if missing:
        raise SolverConfigError(
            f"model: a {type(model).__name__} without {', '.join(missing)}; expected a "
            "prdp_fem.learning.Model (Model(apply, params), equinox_model(module), "
            "flax_model(module, variables)) or a Network")
    example = jax.ShapeDtypeStruct((input_size,), np.float64)
    try:
        output = jax.eval_shape(model.predict, model.params, example)
    except Exception as error:  # the user's function: any failure is theirs to read
        raise ShapeError(f"model: applying it to an input of {input_size} values failed "
                         f"({type(error).__name__}: {error}); expected {what}") from None
    if getattr(output, "shape", None) != (output_size,) or \
            not np.issubdtype(output.dtype, np.floating):
        raise ShapeError(f"model: an input of {input_size} values gives "
                         f"{getattr(output, 'shape', type(output).__name__)} "
                         f"{getattr(output, 'dtype', '')}; expected {output_size} real "
                         f"values ({what})")
