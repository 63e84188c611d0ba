r"""Regularisers of the parameter field ``m``: L2, H1 seminorm, smoothed total variation.

.. math::

    R_{L2}(m) = \tfrac12 \|m - m_0\|_{L^2}^2, \qquad
    R_{H1}(m) = \tfrac12 \int |\nabla (m - m_0)|^2, \qquad
    R_{TV}(m) = \int \sqrt{|\nabla m|^2 + \varepsilon^2}.

All three are evaluated as ``sum_p w_p phi(|g_p|)`` over "gradient points" ``p`` with
``g = D m`` for a sparse ``D`` built once:

* nodal spaces (a source in P1/P2, log-kappa in P1): ``D`` gives the exact gradient at each
  quadrature point and ``w_p`` its quadrature weight, so ``R_H1`` equals ``1/2 m^T L m`` with
  the stiffness matrix ``L``;
* piecewise constants (log-kappa in P0): a gradient does not exist, so ``D`` takes the jump across
  each interior facet divided by the distance between the two cell centroids and ``w_p`` is
  ``|facet| x distance`` (two-point flux): ``R_TV`` tends to the exact total variation
  ``sum |facet| |jump|`` of a piecewise constant field as ``eps -> 0``.

>>> import prdp_fem as pf, numpy as np
>>> disc = pf.discretize(pf.unit_square(4), element="P1", kappa_space="P1")
>>> reg = regularizer(disc, "log_kappa", "h1")
>>> m = disc.interpolate_kappa(lambda x: x[0])       # |grad m| = 1 on the unit square
>>> round(float(reg(m)), 12)
0.5
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from .._checks import finite_vector
from .._transfer import as_jax
from ..errors import SolverConfigError
from ..linalg.operator import FixedMatrix, SparseMatrix, matvec
from .discretization import Discretization
from .parameters import COEFFICIENT_UNKNOWNS, parameter_basis, parameter_mass

__all__ = ["REGULARIZERS", "Regularizer", "gradient_gram", "regularizer", "stiffness_form"]

REGULARIZERS = ("l2", "h1", "tv")


@partial(jax.tree_util.register_dataclass,
         data_fields=["matrix", "weights", "reference", "epsilon", "gram"],
         meta_fields=["kind", "dim"])
@dataclasses.dataclass(frozen=True)
class Regularizer:
    """``kind`` in :data:`REGULARIZERS`; ``matrix`` is the mass matrix (L2) or ``D``.

    ``gram`` is the quadratic form's matrix of L2 and H1 (the mass matrix, ``D^T diag(w) D``):
    a symmetric :class:`~prdp_fem.linalg.operator.FixedMatrix`, laid out once. The value is
    ``1/2 m^T gram m`` and its gradient one product with it, instead of the tall ``D`` (whose
    reverse pass is a scatter): on the inclusion scene's P1 log-kappa, 7k entries instead of
    74k.
    """

    kind: str
    matrix: SparseMatrix
    weights: jax.Array
    reference: jax.Array
    epsilon: jax.Array
    dim: int
    gram: FixedMatrix | None = None

    def __call__(self, field: jax.Array) -> jax.Array:
        if self.gram is not None:
            m = field - self.reference
            return 0.5 * jnp.vdot(m, self.gram(m))
        g = matvec(self.matrix, field).reshape(-1, self.dim)
        return jnp.vdot(self.weights, jnp.sqrt(jnp.sum(g * g, axis=1) + self.epsilon ** 2))


def regularizer(disc: Discretization, unknown: str, kind: str = "h1", *,
                reference: np.ndarray | float = 0.0, epsilon: float = 1e-3) -> Regularizer:
    """Build ``kind`` for the parameter space of ``unknown`` (one of :data:`UNKNOWNS`).

    ``reference`` is ``m_0`` (L2, H1); ``epsilon`` smooths TV (in units of the gradient).
    """
    if not (isinstance(kind, str) and kind in REGULARIZERS):
        raise SolverConfigError(f"regularizer={kind!r}: expected one of {REGULARIZERS}")
    try:
        valid = np.ndim(epsilon) == 0 and bool(np.isfinite(epsilon) and epsilon > 0)
    except (TypeError, ValueError):
        valid = False
    if not valid:
        raise SolverConfigError(f"epsilon={epsilon!r}: expected a finite number > 0")
    basis = parameter_basis(disc, unknown)
    m0 = finite_vector(reference, f"reference (m_0 of the {unknown} field)", basis.N)
    if kind == "l2":
        matrix, weights, dim = parameter_mass(disc, unknown), np.ones(1), 1
    else:
        matrix, weights, dim = _gradient_points(disc, unknown)
    operator = SparseMatrix.from_scipy(matrix)
    # L2: the mass matrix is its own Gram form; laid out once, not in every evaluation
    gram = {"l2": matrix, "h1": None, "tv": None}[kind]
    if kind == "h1":
        gram = gradient_gram(matrix, weights, dim)
    gram = None if gram is None else FixedMatrix.symmetric(gram)
    return Regularizer(kind, operator, as_jax(weights), as_jax(m0),
                       as_jax(float(epsilon)), dim, gram)


def stiffness_form(disc: Discretization, unknown: str) -> sp.csr_matrix:
    """The H1 seminorm's matrix of ``unknown``'s parameter space, ``1/2 m^T K m = R_H1(m)``:
    the stiffness matrix for nodal spaces, two-point fluxes for P0 (host, SciPy)."""
    return gradient_gram(*_gradient_points(disc, unknown))


def _gradient_points(disc: Discretization, unknown: str) -> tuple[sp.csr_matrix, np.ndarray,
                                                                   int]:
    """``(D, w, dim)``: the gradient (or jump) operator of the parameter space, its point
    weights and the components per point (see the module)."""
    if unknown in COEFFICIENT_UNKNOWNS and disc.kappa_space == "P0":
        matrix, weights = _facet_jumps(disc.mesh)
        return matrix, weights, 1
    matrix, weights = _quadrature_gradients(parameter_basis(disc, unknown))
    return matrix, weights, disc.mesh.dim()


def gradient_gram(gradient: sp.spmatrix, weights: np.ndarray, dim: int) -> sp.csr_matrix:
    """``D^T diag(w) D`` (each point's weight on its ``dim`` components): the H1 seminorm's
    matrix for a gradient operator ``D`` with point weights ``w`` (host, SciPy)."""
    return sp.csr_matrix(gradient.T @ sp.diags(np.repeat(np.asarray(weights), dim)) @ gradient)


def _quadrature_gradients(basis) -> tuple[sp.csr_matrix, np.ndarray]:
    """``D``: nodal values -> gradient at every quadrature point; weights ``dx``."""
    dim, n_cells, n_qp = basis.basis[0][0].grad.shape
    rows, cols, vals = [], [], []
    point = (np.arange(n_cells)[:, None] * n_qp + np.arange(n_qp)[None, :])  # (cell, qp)
    for i, phi in enumerate(basis.basis):
        grad = phi[0].grad  # (dim, cells, qp)
        dofs = np.broadcast_to(basis.element_dofs[i][:, None], (n_cells, n_qp))
        for d in range(dim):
            rows.append((point * dim + d).ravel())
            cols.append(dofs.ravel())
            vals.append(grad[d].ravel())
    matrix = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                           shape=(n_cells * n_qp * dim, basis.N))
    return matrix, np.asarray(basis.dx).ravel()


def _facet_jumps(mesh) -> tuple[sp.csr_matrix, np.ndarray]:
    """``D``: cell values -> jump / centroid distance on interior facets; ``|F| x distance``."""
    f2t = mesh.f2t
    interior = np.flatnonzero(f2t[1] >= 0)
    left, right = f2t[0, interior], f2t[1, interior]
    centroids = mesh.p[:, mesh.t].mean(axis=1)
    distance = np.linalg.norm(centroids[:, right] - centroids[:, left], axis=0)
    area = _facet_measure(mesh, interior)
    n = len(interior)
    matrix = sp.csr_matrix(
        (np.concatenate([1.0 / distance, -1.0 / distance]),
         (np.concatenate([np.arange(n), np.arange(n)]), np.concatenate([right, left]))),
        shape=(n, mesh.t.shape[1]))
    return matrix, area * distance


def _facet_measure(mesh, facets: np.ndarray) -> np.ndarray:
    corners = mesh.p[:, mesh.facets[:, facets]]  # (dim, nodes per facet, n)
    if mesh.dim() == 2:
        return np.linalg.norm(corners[:, 1] - corners[:, 0], axis=0)
    if corners.shape[1] == 3:
        return 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                             corners[:, 2] - corners[:, 0], axis=0), axis=0)
    # planar quadrilateral facet, nodes in any order (skfem sorts them): half the cross
    # product of the diagonals, and the true diagonals are the pairing with the largest one
    pairings = ((0, 2, 1, 3), (0, 1, 2, 3), (0, 3, 1, 2))
    return np.max([0.5 * np.linalg.norm(np.cross(corners[:, a] - corners[:, b],
                                                 corners[:, c] - corners[:, d], axis=0), axis=0)
                   for a, b, c, d in pairings], axis=0)
