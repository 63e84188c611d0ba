r"""The Laplace approximation of the posterior at a MAP point, under a Gaussian prior.

With a Gaussian prior ``N(m_pr, R^{-1})`` (:func:`~prdp_fem.fem.priors.bilaplacian_prior`) and
Gaussian noise of variance ``sigma^2``, the MAP point minimises

.. math::

    \frac{1}{\sigma^2}\,\Phi(m) + \tfrac12 \|m - m_{pr}\|_R^2
    \;\propto\; \Phi(m) + \sigma^2\, \tfrac12 \|m - m_{pr}\|_R^2,

the misfit ``Phi`` of :func:`~prdp_fem.inverse.inverse_problem` with the prior's regulariser
(:meth:`~prdp_fem.fem.priors.GaussianPrior.regularizer`) and ``alpha = sigma^2``: any driver
finds it (:func:`~prdp_fem.inverse.invert`, :func:`~prdp_fem.optim.newton.newton_cg`). The
Laplace approximation there is ``N(m_MAP, Gamma)`` with

.. math::

    \Gamma^{-1} = H + R, \qquad H = \frac{1}{\sigma^2} J^\top W J,

``H`` the misfit's Gauss-Newton Hessian (one tangent and one adjoint solve per product, here
by converged PCG). As in hIPPYlib, ``H`` is compressed by the generalised eigenproblem
``H v = lambda R v``, solved by a randomised double-pass method (Saibaba, Lee and Kitanidis,
2016) for the ``rank`` largest ``lambda``, ``V^T R V = I``:

.. math::

    \Gamma = R^{-1} - V D V^\top, \qquad D = \mathrm{diag}\Big(\frac{\lambda_i}{1 +
    \lambda_i}\Big),

exact when every eigenpair is kept. Samples are ``m_MAP + (I - V P V^T R) s`` for prior draws
``s`` of zero mean, ``P = diag(1 - 1/sqrt(1 + lambda))``; the pointwise variance is the
prior's less ``sum_i d_i v_i^2``.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla

from ..errors import SolverConfigError
from ..fem.discretization import Discretization
from ..fem.priors import GaussianPrior
from ..linalg.cg import ConvergedCG
from ..mesh.vtu import write_vtu
from .driver import InverseProblem

__all__ = ["LaplacePosterior", "generalized_eigenpairs", "laplace_posterior"]


@dataclasses.dataclass(frozen=True, eq=False)
class LaplacePosterior:
    """``N(mean, R^{-1} - V D V^T)`` (see the module): ``eigenvalues`` ``lambda`` (largest
    first) and ``eigenvectors`` ``V`` (columns, ``R``-orthonormal) of ``H v = lambda R v``."""

    mean: np.ndarray
    prior: GaussianPrior
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    hessian_products: int

    @property
    def _weights(self) -> np.ndarray:
        return self.eigenvalues / (1.0 + self.eigenvalues)

    def covariance_product(self, v: np.ndarray) -> np.ndarray:
        """``Gamma v`` (the columns of a 2-D ``v`` each)."""
        v = np.asarray(v, float)
        low_rank = self.eigenvectors @ (self._weights.reshape(-1, *[1] * (v.ndim - 1))
                                        * (self.eigenvectors.T @ v))
        return self.prior.covariance_product(v) - low_rank

    def covariance(self) -> np.ndarray:
        """``Gamma`` as a dense matrix (small problems)."""
        return self.covariance_product(np.eye(self.mean.size))

    def pointwise_variance(self, method: str = "exact", **options) -> np.ndarray:
        """``diag(Gamma)``: the prior's (:meth:`GaussianPrior.pointwise_variance`, ``method``
        and its options) less ``sum_i d_i v_i^2``."""
        prior = self.prior.pointwise_variance(method, **options)
        return prior - (self.eigenvectors ** 2) @ self._weights

    def sqrt_covariance_product(self, xi: np.ndarray) -> np.ndarray:
        """``(I - V P V^T R) A^{-1} M_L^{1/2} xi``: white noise ``xi`` to a zero-mean
        posterior draw (its covariance is ``Gamma`` exactly)."""
        xi = np.asarray(xi, float)
        prior_draw = self.prior.sqrt_covariance_product(xi)
        shrink = 1.0 - 1.0 / np.sqrt(1.0 + self.eigenvalues)
        return prior_draw - self.eigenvectors @ (
            shrink.reshape(-1, *[1] * (xi.ndim - 1))
            * (self.eigenvectors.T @ (self.prior.precision @ prior_draw)))

    def sample(self, rng: np.random.Generator, count: int | None = None) -> np.ndarray:
        """One posterior draw (``count=None``) or ``count`` draws as rows."""
        xi = rng.standard_normal(self.mean.size if count is None else (self.mean.size, count))
        draws = self.mean.reshape(-1, *[1] * (xi.ndim - 1)) + self.sqrt_covariance_product(xi)
        return draws if count is None else draws.T

    def write_vtu(self, path, disc: Discretization, *, samples: int = 3, seed: int = 0,
                  variance: str = "exact", **options) -> Path:
        """Write the MAP point (``map``), the posterior and prior pointwise variances
        (``variance``, ``prior_variance``; ``variance`` is the method, see
        :meth:`pointwise_variance`) and ``samples`` posterior draws (``sample_1``, ...) on
        ``disc``'s mesh to ``path`` (``.vtu``, atomically)."""
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 0:
            raise SolverConfigError(f"samples={samples!r}: expected an integer >= 0")
        space = "nodal" if self.prior.unknown == "source" or disc.kappa_space != "P0" \
            else "P0"
        prior_variance = self.prior.pointwise_variance(variance, **options)
        fields = {"map": (space, self.mean),
                  "variance": (space, prior_variance - (self.eigenvectors ** 2) @ self._weights),
                  "prior_variance": (space, prior_variance)}
        draws = self.sample(np.random.default_rng(seed), samples) if samples else []
        fields.update({f"sample_{i + 1}": (space, draw) for i, draw in enumerate(draws)})
        return write_vtu(disc.mesh, path, fields)


def laplace_posterior(problem: InverseProblem, z_map, prior: GaussianPrior, *, rank: int,
                      oversampling: int = 10, seed: int = 0,
                      solver=None) -> LaplacePosterior:
    """The Laplace approximation at ``z_map`` (see the module).

    ``problem`` is the MAP problem: the prior's regulariser and ``alpha`` the noise variance
    ``sigma^2`` (both checked). ``rank`` eigenpairs of ``H v = lambda R v`` are kept, found
    from ``rank + oversampling`` random directions (capped at the parameter count; with every
    direction the approximation is exact to round-off). ``solver``: the state, tangent and
    adjoint solves of the Hessian products (default: Jacobi-PCG to ``rtol = 1e-12``).
    Unbounded parameterisations only (the prior is on ``z`` itself).
    """
    n = problem.n_parameters
    if problem.regularizer.kind != "bilaplacian" or problem.regularizer.reference.shape != \
            prior.mean.shape or not np.array_equal(np.asarray(problem.regularizer.reference),
                                                   prior.mean):
        raise SolverConfigError("laplace_posterior: the problem's regularization is not this "
                                "prior's; expected inverse_problem(..., regularization="
                                "prior.regularizer(), alpha=noise variance)")
    if not problem.alpha > 0:
        raise SolverConfigError(f"alpha={problem.alpha!r}: the noise variance; expected > 0")
    if problem.parameterization.bounds is not None:
        raise SolverConfigError("laplace_posterior: bounds map the parameters nonlinearly; "
                                "expected an unbounded unknown")
    for name, value, least in (("rank", rank, 1), ("oversampling", oversampling, 0)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < least:
            raise SolverConfigError(f"{name}={value!r}: expected an integer >= {least}")
    solver = ConvergedCG(rtol=1e-12, preconditioner="jacobi") if solver is None else solver
    z_map = jnp.asarray(z_map, jnp.float64)
    misfit_problem, sigma2 = problem.with_alpha(0.0), float(problem.alpha)

    def hessian(block: np.ndarray) -> np.ndarray:
        return np.asarray(_misfit_hessian_block(misfit_problem, z_map, jnp.asarray(block),
                                                solver)) / sigma2

    eigenvalues, eigenvectors = generalized_eigenpairs(
        hessian, prior.precision, prior.covariance_product, n, rank, oversampling, seed)
    return LaplacePosterior(np.asarray(z_map), prior, eigenvalues, eigenvectors,
                            2 * min(rank + oversampling, n))


@partial(jax.jit, static_argnames="solver")
def _misfit_hessian_block(problem: InverseProblem, z, block, solver):
    """The misfit's Gauss-Newton Hessian at ``z`` on every column of ``block`` (one program
    per problem structure, solver and block shape: a sweep of ranks compiles once)."""
    misfit_hessian = problem.gauss_newton_operator(z, solver)
    return jax.vmap(misfit_hessian, in_axes=1, out_axes=1)(block)


def generalized_eigenpairs(hessian, precision, inverse_precision, n: int, rank: int,
                           oversampling: int = 10, seed: int = 0
                           ) -> tuple[np.ndarray, np.ndarray]:
    """The ``rank`` largest eigenpairs of ``H v = lambda B v`` by the randomised double-pass
    method (Saibaba, Lee and Kitanidis 2016, hIPPYlib's ``doublePassG``): ``V^T B V = I``.

    ``hessian(X)`` and ``inverse_precision(X)`` apply ``H`` and ``B^{-1}`` to the columns of
    ``X``; ``precision`` is ``B`` (anything with ``@``). Two passes of ``H`` over ``k = min(rank
    + oversampling, n)`` columns.
    """
    k = min(rank + oversampling, n)
    omega = np.random.default_rng(seed).standard_normal((n, k))
    y = inverse_precision(hessian(omega))
    q = _b_orthonormal(y, precision)
    t = q.T @ hessian(q)
    values, vectors = sla.eigh(0.5 * (t + t.T))
    order = np.argsort(values)[::-1][:rank]
    return values[order], q @ vectors[:, order]


def _b_orthonormal(y: np.ndarray, precision) -> np.ndarray:
    """Columns spanning ``y``'s range, orthonormal in ``B``: ``y U S^{-1/2}`` from the
    eigenpairs ``(S, U)`` of ``y^T B y``, directions below ``1e-12`` of the largest dropped
    (``H`` of lower rank than the sample: they carry ``lambda = 0``), twice for round-off."""
    q = y
    for _ in range(2):
        gram = q.T @ (precision @ q)
        values, vectors = sla.eigh(0.5 * (gram + gram.T))
        kept = values > 1e-12 * max(values.max(), 0.0) if values.size else values > 0
        q = q @ (vectors[:, kept] / np.sqrt(values[kept]))
    return q
