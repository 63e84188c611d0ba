r"""Gaussian priors of the parameter field: the bi-Laplacian prior.

A bi-Laplacian prior (as hIPPYlib's ``BiLaplacianPrior``) on the field ``m`` of an unknown
has mean ``m_pr`` and precision

.. math::

    R = A M_L^{-1} A, \qquad A = \gamma K + \delta M,

the FE form of :math:`(\delta I - \gamma \Delta)^2` with natural (zero-flux) boundary
conditions: ``K`` is the stiffness matrix of the parameter space (the H1 seminorm's matrix of
:func:`~prdp_fem.fem.regularizers.regularizer`; two-point fluxes for P0), ``M`` its mass
matrix and ``M_L`` the lumped mass (diagonal, the row sums for P1/Q1, HRZ lumping --
``diag(M)`` scaled to the total mass -- otherwise). The lumped mass in the middle keeps ``R``
sparse and makes sampling exact: ``m = m_pr + A^{-1} M_L^{1/2} xi`` with ``xi ~ N(0, I)``
has covariance :math:`R^{-1} = A^{-1} M_L A^{-1}`. ``sqrt(gamma / delta)`` is about the
correlation length, ``1 / (delta sqrt(...))``-type scales set the variance (see
:meth:`GaussianPrior.pointwise_variance`).

The prior's negative log density is ``1/2 ||m - m_pr||_R^2``: :meth:`GaussianPrior.regularizer`
gives it as a :class:`~prdp_fem.fem.regularizers.Regularizer`, so the MAP point is an
inversion with ``alpha`` equal to the noise variance (see
:func:`prdp_fem.inverse.posterior.laplace_posterior`).

>>> import prdp_fem as pf, numpy as np
>>> disc = pf.discretize(pf.unit_square(8), element="P1", kappa_space="P1")
>>> prior = bilaplacian_prior(disc, "log_kappa", gamma=0.1, delta=1.0)
>>> samples = prior.sample(np.random.default_rng(0), 2000)
>>> bool(np.allclose(samples.var(axis=0).mean(), prior.pointwise_variance().mean(), rtol=0.1))
True
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .._checks import finite_vector
from .._transfer import as_jax
from ..errors import SolverConfigError
from ..linalg.operator import FixedMatrix, SparseMatrix
from .discretization import Discretization
from .parameters import parameter_basis, parameter_mass
from .regularizers import Regularizer, stiffness_form

__all__ = ["GaussianPrior", "bilaplacian_prior"]


@dataclasses.dataclass(frozen=True, eq=False)
class GaussianPrior:
    """A Gaussian prior ``N(mean, R^{-1})`` with ``R = A M_L^{-1} A`` (see the module).

    ``operator`` is ``A`` and ``lumped_mass`` the diagonal of ``M_L`` (host, SciPy/NumPy);
    ``precision`` is ``R``. Build one with :func:`bilaplacian_prior`.
    """

    unknown: str
    gamma: float
    delta: float
    mean: np.ndarray
    operator: sp.csc_matrix
    lumped_mass: np.ndarray
    precision: sp.csr_matrix

    @property
    def size(self) -> int:
        return self.mean.size

    @property
    def _factor(self):
        # A's sparse LU, made once per prior (A is fixed); a frozen dataclass caches by hand
        factor = self.__dict__.get("_lu")
        if factor is None:
            factor = spla.splu(self.operator.tocsc())
            object.__setattr__(self, "_lu", factor)
        return factor

    def regularizer(self) -> Regularizer:
        """``1/2 ||m - mean||_R^2`` as a regulariser (kind ``"bilaplacian"``): pass it as an
        inverse problem's ``regularization`` with ``alpha`` the noise variance."""
        # its square-root factor M_L^{-1/2} A as the point operator, every weight 1: the
        # Gauss-Newton residual of HIG and Gauss-Newton (prdp_fem.fem.residuals) is then
        # r_R = sqrt(alpha) M_L^{-1/2} A (m - mean), with 1/2 |r_R|^2 = alpha R
        factor = sp.diags(1.0 / np.sqrt(self.lumped_mass)) @ self.operator
        return Regularizer("bilaplacian", SparseMatrix.from_scipy(factor.tocsr()),
                           as_jax(np.ones(self.size)), as_jax(self.mean), as_jax(0.0), 1,
                           FixedMatrix.symmetric(self.precision))

    def covariance_product(self, v: np.ndarray) -> np.ndarray:
        """``R^{-1} v = A^{-1} M_L A^{-1} v`` (columns of a 2-D ``v`` each)."""
        return self._factor.solve(self.lumped_mass.reshape(-1, *[1] * (np.ndim(v) - 1))
                                  * self._factor.solve(np.asarray(v, float)))

    def sqrt_covariance_product(self, xi: np.ndarray) -> np.ndarray:
        """``A^{-1} M_L^{1/2} xi``: white noise ``xi`` to a zero-mean prior draw."""
        scale = np.sqrt(self.lumped_mass).reshape(-1, *[1] * (np.ndim(xi) - 1))
        return self._factor.solve(scale * np.asarray(xi, float))

    def sample(self, rng: np.random.Generator, count: int | None = None) -> np.ndarray:
        """One draw (``count=None``) or ``count`` draws as rows."""
        xi = rng.standard_normal(self.size if count is None else (self.size, count))
        draws = self.mean.reshape(-1, *[1] * (np.ndim(xi) - 1)) + \
            self.sqrt_covariance_product(xi)
        return draws if count is None else draws.T

    def pointwise_variance(self, method: str = "exact", *, probes: int = 200,
                           seed: int = 0) -> np.ndarray:
        """The prior variance at every parameter dof: ``diag(R^{-1})``.

        ``"exact"``: the rows of ``A^{-1} M_L^{1/2}``, one solve per dof (dense, ``n^2``
        memory: small problems); ``"randomized"``: the unbiased estimate
        ``mean_k z_k * R^{-1} z_k`` over ``probes`` Rademacher vectors.
        """
        if method == "exact":
            square_root = self.sqrt_covariance_product(np.eye(self.size))
            return np.einsum("ij,ij->i", square_root, square_root)
        if method == "randomized":
            check_positive_int(probes, "probes")
            z = np.random.default_rng(seed).choice([-1.0, 1.0], size=(self.size, probes))
            return np.mean(z * self.covariance_product(z), axis=1)
        raise SolverConfigError(f"method={method!r}: expected 'exact' or 'randomized'")


def bilaplacian_prior(disc: Discretization, unknown: str, *, gamma: float, delta: float,
                      mean: np.ndarray | float = 0.0) -> GaussianPrior:
    """The bi-Laplacian prior of ``unknown``'s parameter field (see the module).

    ``gamma``, ``delta``: finite numbers > 0; ``mean``: a number or a vector of the parameter
    space. Raises :class:`~prdp_fem.errors.SolverConfigError` naming the bad one.
    """
    for name, value in (("gamma", gamma), ("delta", delta)):
        check_positive(value, name)
    basis = parameter_basis(disc, unknown)
    mean = np.asarray(finite_vector(mean, f"mean (the prior mean of the {unknown} field)",
                                    basis.N), float)
    stiffness = stiffness_form(disc, unknown)
    mass = parameter_mass(disc, unknown).tocsr()
    operator = (gamma * stiffness + delta * mass).tocsc()
    lumped = _lumped(mass)
    precision = (operator.T @ sp.diags(1.0 / lumped) @ operator).tocsr()
    return GaussianPrior(unknown, float(gamma), float(delta), mean, operator, lumped,
                         0.5 * (precision + precision.T))


def _lumped(mass: sp.csr_matrix) -> np.ndarray:
    """The row sums where all are positive (P0, P1, Q1), else HRZ: the diagonal scaled to the
    total mass (P2 row sums vanish or turn negative at vertices)."""
    rows = np.asarray(mass.sum(axis=1)).ravel()
    if np.all(rows > 0):
        return rows
    diagonal = mass.diagonal()
    return diagonal * (rows.sum() / diagonal.sum())


def check_positive(value, name: str) -> None:
    try:
        valid = np.ndim(value) == 0 and bool(np.isfinite(value) and value > 0)
    except (TypeError, ValueError):
        valid = False
    if not valid:
        raise SolverConfigError(f"{name}={value!r}: expected a finite number > 0")


def check_positive_int(value, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise SolverConfigError(f"{name}={value!r}: expected an integer >= 1")
