r"""What an inverse problem recovers: a nodal source ``f`` or a log-coefficient ``m = log kappa``.

The optimiser works on an unconstrained vector ``z``; the physical field is

.. math::

    \text{field}(z) = z \quad\text{or, with bounds } [l, u]:\quad
    l + (u - l)\,\sigma(z), \qquad \sigma(z) = 1 / (1 + e^{-z}),

and the PDE sees ``f = field`` (source, nodal in the solution space) or
``kappa = exp(field)`` (log-coefficient, in the discretisation's kappa space: one value per cell
for P0, nodal for P1, where ``kappa`` is the nodal interpolant of ``e^m``).

>>> import numpy as np
>>> p = Parameterization("log_kappa", bounds=(-1.0, 1.0))
>>> round(float(p.field(p.from_field(np.array([0.5])))[0]), 12)
0.5
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import skfem

from ..errors import CoefficientError, DataError, SolverConfigError
from .discretization import Discretization

__all__ = ["UNKNOWNS", "Parameterization", "parameter_basis", "parameter_mass"]

UNKNOWNS = ("source", "log_kappa")


@dataclasses.dataclass(frozen=True)
class Parameterization:
    """``unknown`` in :data:`UNKNOWNS`; optional ``bounds = (lower, upper)`` on the field."""

    unknown: str
    bounds: tuple[float, float] | None = None

    def __post_init__(self):
        if not (isinstance(self.unknown, str) and self.unknown in UNKNOWNS):
            raise SolverConfigError(f"unknown={self.unknown!r}: expected one of {UNKNOWNS}")
        if self.bounds is not None:
            # bounds on log kappa bound the coefficient; on a source, the source values
            error = CoefficientError if self.unknown == "log_kappa" else DataError
            try:
                lower, upper = (float(b) for b in self.bounds)
            except (TypeError, ValueError):  # not a pair of numbers
                lower = upper = float("nan")
            if not (np.isfinite(lower) and np.isfinite(upper) and lower < upper):
                raise error(f"bounds={self.bounds!r} on the {self.unknown} field: expected "
                            "finite (lower, upper) with lower < upper")
            object.__setattr__(self, "bounds", (lower, upper))

    def field(self, z: jax.Array) -> jax.Array:
        """The physical field (source values or log kappa) of the optimisation vector ``z``."""
        if self.bounds is None:
            return z
        lower, upper = self.bounds
        return lower + (upper - lower) * jax.nn.sigmoid(z)

    def from_field(self, field: np.ndarray) -> jax.Array:
        """``z`` with ``field(z) = field`` (clipped just inside the bounds)."""
        field = jnp.asarray(field, dtype=jnp.float64)
        if self.bounds is None:
            return field
        lower, upper = self.bounds
        t = jnp.clip((field - lower) / (upper - lower), 1e-12, 1 - 1e-12)
        return jnp.log(t) - jnp.log1p(-t)

    def coefficients(self, z: jax.Array, known: jax.Array) -> tuple[jax.Array, jax.Array]:
        """``(kappa, f)`` for the PDE's system: the unknown from ``z``, the other one
        ``known`` (for a source inversion the coefficient of its frozen system, the scale
        ``ones(1)``: see :class:`~prdp_fem.inverse.driver.InverseProblem`)."""
        field = self.field(z)
        if self.unknown == "source":
            return known, field
        return jnp.exp(field), known


def parameter_basis(disc: Discretization, unknown: str) -> skfem.CellBasis:
    """The FE basis the unknown lives in: the solution space (source) or the kappa space."""
    if not (isinstance(unknown, str) and unknown in UNKNOWNS):
        raise SolverConfigError(f"unknown={unknown!r}: expected one of {UNKNOWNS}")
    return disc.basis if unknown == "source" else disc.kappa_basis


@skfem.BilinearForm
def _mass(u, v, _):
    return u * v


def parameter_mass(disc: Discretization, unknown: str) -> sp.csr_matrix:
    """Mass matrix of the parameter space (the L2 inner product of parameter errors)."""
    if unknown == "source":
        return disc.mass_matrix
    return _mass.assemble(disc.kappa_basis).tocsr()
