"""The trainings' default optimizer, one object for the process."""

from __future__ import annotations

from functools import lru_cache

import optax


@lru_cache(maxsize=1)
def default_optimizer() -> optax.GradientTransformation:
    """Adam with a learning rate of 1e-3, one object for every training that passes none
    (pure and immutable, as optax's transformations are): such trainings share their
    compiled step, which is kept per optimizer object."""
    return optax.adam(1e-3)
