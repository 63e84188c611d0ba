"""Taylor test: check a gradient of any scalar function against the function itself.

For a direction ``dx`` and steps ``h_i = h0 / 2**i``,

.. math:: R_0(h) = |J(x + h\\,dx) - J(x)|, \\qquad
          R_1(h) = |J(x + h\\,dx) - J(x) - h \\langle \\nabla J(x), dx \\rangle|.

A correct gradient gives ``R_1 = O(h^2)`` (rate 2) while ``R_0 = O(h)``; a wrong one leaves
``R_1`` at rate 1. Works on arrays and on pytrees of arrays (``dx`` of the same structure).

>>> import jax.numpy as jnp
>>> result = taylor_test(lambda x: jnp.sum(jnp.sin(x)), jnp.array([0.1, 0.2]),
...                      jnp.array([1.0, -1.0]))
>>> bool(result.passed())
True
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["TaylorResult", "taylor_test"]


class TaylorResult(NamedTuple):
    """Steps, remainders and observed rates of a Taylor test."""

    steps: np.ndarray
    zeroth_order: np.ndarray  # R_0(h)
    first_order: np.ndarray  # R_1(h)
    rates: np.ndarray  # log2(R_1(h_i) / R_1(h_{i+1}))

    def passed(self, expected: float = 2.0, tol: float = 0.15) -> bool:
        """Median rate within ``tol`` of ``expected``, over steps above round-off.

        With no rate above round-off (``fn`` linear along ``dx``: ``R_1`` is round-off at every
        step) it passes when ``R_1`` stays below 1e-8 ``R_0`` while ``R_0`` shrinks with ``h``.
        """
        usable = self.rates[np.isfinite(self.rates)]
        if usable.size:
            return abs(float(np.median(usable)) - expected) <= tol
        moving = self.zeroth_order > 0
        return bool(moving.all() and np.all(self.first_order <= 1e-8 * self.zeroth_order))


def _vdot_tree(a: Any, b: Any) -> jax.Array:
    leaves = jax.tree_util.tree_leaves(jax.tree_util.tree_map(jnp.vdot, a, b))
    return sum(leaves, jnp.zeros(()))


def taylor_test(
    fn: Callable[[Any], jax.Array],
    x: Any,
    dx: Any | None = None,
    *,
    gradient: Any | None = None,
    h0: float = 1e-2,
    n_steps: int = 6,
    seed: int = 0,
) -> TaylorResult:
    """Taylor test of ``gradient`` (default ``jax.grad(fn)(x)``) at ``x`` along ``dx``.

    ``dx`` defaults to a seeded standard-normal direction scaled to the size of ``x``.
    Rates are computed only where ``R_1`` is above round-off (``1e-13 |J(x)|``); other entries
    are NaN so that :meth:`TaylorResult.passed` ignores them.
    """
    if dx is None:
        leaves, tree = jax.tree_util.tree_flatten(x)
        keys = jax.random.split(jax.random.PRNGKey(seed), len(leaves))
        dx = jax.tree_util.tree_unflatten(tree, [
            jax.random.normal(k, jnp.shape(leaf)) * (jnp.linalg.norm(leaf) /
                                                    np.sqrt(max(np.size(leaf), 1)) + 1.0)
            for k, leaf in zip(keys, leaves, strict=True)])
    if gradient is None:
        gradient = jax.grad(fn)(x)
    f0 = float(fn(x))
    slope = float(_vdot_tree(gradient, dx))
    steps = h0 / 2.0 ** np.arange(n_steps)
    r0, r1 = [], []
    for h in steps:
        moved = jax.tree_util.tree_map(lambda a, d, h=h: a + h * d, x, dx)
        fh = float(fn(moved))
        r0.append(abs(fh - f0))
        r1.append(abs(fh - f0 - h * slope))
    r0, r1 = np.array(r0), np.array(r1)
    floor = 1e-13 * max(abs(f0), 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        rates = np.log2(r1[:-1] / r1[1:])
    rates[(r1[1:] <= floor) | (r1[:-1] <= floor)] = np.nan
    return TaylorResult(steps, r0, r1, rates)
