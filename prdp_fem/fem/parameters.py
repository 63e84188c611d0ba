r"""What an inverse problem recovers: a nodal source ``f``, or a coefficient field mapped to
``kappa``.

The optimiser works on an unconstrained vector ``z``; the physical field is

.. math::

    \text{field}(z) = z \quad\text{or, with bounds } [l, u]:\quad
    l + (u - l)\,\sigma(z), \qquad \sigma(z) = 1 / (1 + e^{-z}),

and the PDE sees ``f = field`` (``unknown="source"``, nodal in the solution space) or
``kappa = map(field)`` in the discretisation's kappa space (one value per cell for P0, nodal
for P1/P2; ``kappa`` is the nodal interpolant of the mapped field):

* ``"log_kappa"``: ``kappa = exp(m)``;
* ``"density"``: a SIMP power law ``kappa = k_min + (k_max - k_min) rho^p`` of a density
  ``rho`` in ``[0, 1]`` (:class:`Simp`; bounds default to ``(0, 1)``), the material map of
  topology optimisation;
* ``"coefficient"``: any differentiable JAX function ``kappa = map(field)`` given as
  ``coefficient_map`` (elementwise, positive where the optimiser goes).

>>> import numpy as np
>>> p = Parameterization("log_kappa", bounds=(-1.0, 1.0))
>>> round(float(p.field(p.from_field(np.array([0.5])))[0]), 12)
0.5
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import skfem

from ..errors import CoefficientError, DataError, SolverConfigError
from .discretization import Discretization

__all__ = ["COEFFICIENT_UNKNOWNS", "UNKNOWNS", "Parameterization", "Simp", "parameter_basis",
           "parameter_mass", "simp"]

#: The fields an inverse problem can recover; all but ``"source"`` are mapped to ``kappa``.
UNKNOWNS = ("source", "log_kappa", "density", "coefficient")
COEFFICIENT_UNKNOWNS = ("log_kappa", "density", "coefficient")


@dataclasses.dataclass(frozen=True)
class Simp:
    """The SIMP power law ``kappa = k_min + (k_max - k_min) rho ** penalty`` of a density
    ``rho`` in ``[0, 1]`` (Bendsoe and Sigmund): ``0 < k_min < k_max``, ``penalty >= 1``.

    >>> Simp(k_min=0.01, k_max=1.0, penalty=3.0)(0.5)
    0.13375
    """

    k_min: float = 1e-3
    k_max: float = 1.0
    penalty: float = 3.0

    def __post_init__(self):
        try:
            values = [float(v) for v in (self.k_min, self.k_max, self.penalty)]
        except (TypeError, ValueError):
            values = [float("nan")] * 3
        k_min, k_max, penalty = values
        if not (np.isfinite(values).all() and 0 < k_min < k_max and penalty >= 1):
            raise CoefficientError(
                f"SIMP map k_min={self.k_min!r}, k_max={self.k_max!r}, penalty={self.penalty!r}: "
                "expected finite 0 < k_min < k_max and penalty >= 1")
        for name, value in zip(("k_min", "k_max", "penalty"), values, strict=True):
            object.__setattr__(self, name, value)

    def __call__(self, rho):
        return self.k_min + (self.k_max - self.k_min) * rho ** self.penalty


def simp(k_min: float = 1e-3, k_max: float = 1.0, penalty: float = 3.0) -> Simp:
    """The SIMP map of ``unknown="density"`` (see :class:`Simp`)."""
    return Simp(k_min, k_max, penalty)


@dataclasses.dataclass(frozen=True)
class Parameterization:
    """``unknown`` in :data:`UNKNOWNS`; optional ``bounds = (lower, upper)`` on the field;
    ``coefficient_map``: the density's :class:`Simp` law (default ``Simp()``) or, for
    ``unknown="coefficient"``, the JAX function ``field -> kappa`` (required)."""

    unknown: str
    bounds: tuple[float, float] | None = None
    coefficient_map: Callable | None = None

    def __post_init__(self):
        if not (isinstance(self.unknown, str) and self.unknown in UNKNOWNS):
            raise SolverConfigError(f"unknown={self.unknown!r}: expected one of {UNKNOWNS}")
        self._check_map()
        if self.bounds is not None:
            # bounds on a coefficient field bound the coefficient; on a source, the source
            error = CoefficientError if self.is_coefficient else DataError
            try:
                lower, upper = (float(b) for b in self.bounds)
            except (TypeError, ValueError):  # not a pair of numbers
                lower = upper = float("nan")
            if not (np.isfinite(lower) and np.isfinite(upper) and lower < upper):
                raise error(f"bounds={self.bounds!r} on the {self.unknown} field: expected "
                            "finite (lower, upper) with lower < upper")
            if isinstance(self.coefficient_map, Simp) and not 0 <= lower < upper <= 1:
                raise error(f"bounds={self.bounds!r} on the density field: expected "
                            "0 <= lower < upper <= 1 (a SIMP density)")
            object.__setattr__(self, "bounds", (lower, upper))

    def _check_map(self) -> None:
        given = self.coefficient_map
        if self.unknown == "density":
            if given is None:
                object.__setattr__(self, "coefficient_map", Simp())
            elif not isinstance(given, Simp):
                raise SolverConfigError(f"unknown='density' with coefficient_map={given!r}: "
                                        "expected a Simp law (or unknown='coefficient' for "
                                        "another map)")
            if self.bounds is None:
                object.__setattr__(self, "bounds", (0.0, 1.0))
        elif self.unknown == "coefficient":
            if not callable(given):
                raise SolverConfigError(f"unknown='coefficient' with coefficient_map={given!r}: "
                                        "expected a JAX function field -> kappa")
        elif given is not None:
            raise SolverConfigError(f"unknown={self.unknown!r} with a coefficient_map: "
                                    "expected none (use unknown='coefficient' for a map)")

    @property
    def is_coefficient(self) -> bool:
        """Whether the field is mapped to ``kappa`` (else it is the source)."""
        return self.unknown in COEFFICIENT_UNKNOWNS

    def kappa(self, field):
        """The coefficient of a coefficient ``field`` (``exp`` for log kappa, else the map)."""
        if self.unknown == "log_kappa":
            return jnp.exp(field)
        return self.coefficient_map(field)

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
        return self.kappa(field), known


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
