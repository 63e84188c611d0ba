"""Finite-element discretisation of ``-div(kappa grad u) = f`` with scikit-fem.

:func:`discretize` picks the element (P1/P2 on triangles and tetrahedra, Q1/Q2 on quads and
hexahedra), the coefficient space (``"P0"`` per cell or ``"P1"`` nodal), Dirichlet data
(constant, callable ``g(x)`` with ``x`` of shape ``(dim, n)``, or a dict per boundary tag) and
Neumann data ``kappa du/dn = h`` (dict per tag); the maps of
:class:`~prdp_fem.fem.system.LinearSystem` are built on first use, once, in NumPy/SciPy.

The assembly map comes from scikit-fem's unsummed element data (``BilinearForm.coo_data``):
for the coefficient basis function ``psi_a`` of a cell, ``coo_data`` of
``psi_a grad u . grad v`` gives that cell's entries per unit ``kappa_a``; summing duplicates once
yields ``G`` with ``values(A) = G @ kappa`` exactly (the quadrature integrates the product).
A problem whose ``kappa`` never changes needs no ``G``: :meth:`Discretization.system_at` and
:meth:`Discretization.host_system_at` assemble the operator at that ``kappa`` in one pass.

A tensor coefficient is stored component-major in Voigt order, ``kappa = [K_xx, K_yy, K_xy]``
in 2-D and ``[K_xx, K_yy, K_zz, K_yz, K_xz, K_xy]`` in 3-D, each block one field of the
coefficient space; ``A`` stays linear in it (``K grad u . grad v = sum_ij K_ij d_j u d_i v``),
so every solver and gradient path is the same as for a scalar.

>>> from prdp_fem import unit_square
>>> disc = discretize(unit_square(4), element="P1", kappa_space="P0")
>>> disc.system.n_free, disc.system.n_kappa
(9, 32)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from functools import cached_property
from typing import NamedTuple

import jax
import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla
import skfem
from skfem.helpers import dot, grad

from .._checks import finite_vector, host_values, is_traced, positive_coefficient, real_array
from .._sorting import unique_with_inverse
from .._transfer import as_jax
from ..errors import CoefficientError, DataError, DiscretizationError, ShapeError
from ..linalg.host_cg import jacobi_pcg
from ..linalg.operator import FixedMatrix, ell_layout
from .system import LinearSystem

__all__ = ["Discretization", "discretize"]

BoundaryValue = float | Callable[[np.ndarray], np.ndarray]
BoundaryData = BoundaryValue | Mapping[str, BoundaryValue] | None

_ELEMENTS = {
    skfem.MeshTri1: {"P1": skfem.ElementTriP1, "P2": skfem.ElementTriP2},
    skfem.MeshTet1: {"P1": skfem.ElementTetP1, "P2": skfem.ElementTetP2},
    skfem.MeshQuad1: {"Q1": skfem.ElementQuad1, "Q2": skfem.ElementQuad2},
    skfem.MeshHex1: {"Q1": skfem.ElementHex1, "Q2": skfem.ElementHex2},
}
# "P2" is the second-order space (Q2 on quadrilaterals and hexahedra): a coefficient of the
# state's order keeps a P2/Q2 state's L2 rate 3 where a P1 coefficient holds it to 2
_KAPPA_ELEMENTS = {
    skfem.MeshTri1: {"P0": skfem.ElementTriP0, "P1": skfem.ElementTriP1,
                     "P2": skfem.ElementTriP2},
    skfem.MeshTet1: {"P0": skfem.ElementTetP0, "P1": skfem.ElementTetP1,
                     "P2": skfem.ElementTetP2},
    skfem.MeshQuad1: {"P0": skfem.ElementQuad0, "P1": skfem.ElementQuad1,
                      "P2": skfem.ElementQuad2},
    skfem.MeshHex1: {"P0": skfem.ElementHex0, "P1": skfem.ElementHex1,
                     "P2": skfem.ElementHex2},
}
KAPPA_KINDS = ("scalar", "tensor")
# (i, j) of each stored tensor component, Voigt order
VOIGT = {2: ((0, 0), (1, 1), (0, 1)), 3: ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))}
# relative size below which an assembled entry is structurally zero (e.g. right triangles)
_STRUCTURAL_ZERO = 1e-14
# assembled entries per pass of the maps kappa -> A (see _assembly_maps): about 250 MB with
# their indices, twice that while a pass's parts are joined
_ENTRIES_PER_PASS = 1 << 23
# relative residual of the mass-matrix solve in Discretization.project (round-off: cond <= ~4)
PROJECTION_RTOL = 1e-14


class AssemblyMaps(NamedTuple):
    """The maps ``kappa -> A`` of a discretisation (see :func:`_assembly_maps`)."""

    assembly: sp.csr_matrix                         # G: nnz x n_kappa
    pattern: tuple[np.ndarray, np.ndarray]          # (rows, cols) of A, row-sorted
    lifting_assembly: sp.csr_matrix                 # G_D: the Dirichlet columns per kappa
    lifting_pattern: tuple[np.ndarray, np.ndarray]  # (free row, index into dirichlet_dofs)


@skfem.BilinearForm
def _weighted_laplace(u, v, w):
    return w.kappa * dot(grad(u), grad(v))


def _tensor_component_form(i: int, j: int) -> skfem.BilinearForm:
    """``w.kappa`` times the part of ``K grad u . grad v`` that multiplies ``K_ij = K_ji``."""

    @skfem.BilinearForm
    def form(u, v, w):
        gu, gv = grad(u), grad(v)
        if i == j:
            return w.kappa * gu[i] * gv[i]
        return w.kappa * (gu[j] * gv[i] + gu[i] * gv[j])

    return form


@skfem.BilinearForm
def _mass(u, v, _):
    return u * v


@skfem.BilinearForm
def _laplace(u, v, _):
    return dot(grad(u), grad(v))


@dataclasses.dataclass(frozen=True, eq=False)
class Discretization:
    """A discretised problem: bases, dof split and the :class:`LinearSystem` maps.

    Use :func:`discretize` to build one. ``system`` is the JAX side (``kappa -> A``),
    ``system_at(kappa)`` the same at one fixed ``kappa``; the SciPy matrices (``mass_matrix``,
    ``laplace_matrix``, ``stiffness_matrix(kappa)``, ``host_system_at(kappa)``) and the map
    ``G`` (``assembly``, ``pattern``) are built on demand.
    """

    mesh: skfem.Mesh
    element: str
    kappa_space: str
    kappa_kind: str
    basis: skfem.CellBasis
    kappa_basis: skfem.CellBasis
    free_dofs: np.ndarray
    dirichlet_dofs: np.ndarray
    dirichlet_values: np.ndarray
    neumann: np.ndarray  # h on the free dofs

    @property
    def n_dofs(self) -> int:
        return int(self.basis.N)

    @cached_property
    def _maps(self) -> AssemblyMaps:
        # built on first use: a problem at one fixed kappa (system_at) never needs them
        return _assembly_maps(self.basis, self.kappa_basis, self.free_dofs, self._forms)

    @property
    def assembly(self) -> sp.csr_matrix:
        """``G`` (nnz x n_kappa): the values of the condensed operator are ``G kappa``."""
        return self._maps.assembly

    @property
    def pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """``(rows, cols)`` of the condensed operator (row-sorted)."""
        return self._maps.pattern

    @property
    def lifting_assembly(self) -> sp.csr_matrix:
        """``G_D``: the values of the (free, Dirichlet) block per ``kappa``."""
        return self._maps.lifting_assembly

    @property
    def lifting_pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """``(free row, index into dirichlet_dofs)`` of the Dirichlet columns."""
        return self._maps.lifting_pattern

    @property
    def _forms(self) -> list:
        """The bilinear form of each coefficient component (one for a scalar ``kappa``)."""
        if self.kappa_kind == "scalar":
            return [_weighted_laplace]
        return [_tensor_component_form(i, j) for i, j in VOIGT[self.mesh.dim()]]

    @property
    def n_free(self) -> int:
        return len(self.free_dofs)

    @property
    def n_kappa_components(self) -> int:
        """1 for a scalar ``kappa``; 3 (2-D) or 6 (3-D) symmetric tensor components."""
        return 1 if self.kappa_kind == "scalar" else len(VOIGT[self.mesh.dim()])

    @property
    def n_kappa(self) -> int:
        return self.n_kappa_components * int(self.kappa_basis.N)

    def check_kappa(self, kappa, name: str = "kappa") -> np.ndarray:
        """``kappa`` as a NumPy vector, or a :class:`CoefficientError` naming what is wrong.

        A scalar must be finite and ``> 0``; a tensor finite and symmetric positive definite at
        every point of the coefficient space. A number broadcasts (scalar kind only).
        """
        if is_traced(kappa):
            return kappa
        if self.kappa_kind == "scalar":
            return positive_coefficient(kappa, name, self.n_kappa)
        if np.ndim(kappa) == 0:
            raise CoefficientError(f"{name}: a single number for a tensor coefficient; expected "
                                   f"{self.n_kappa} Voigt components (see interpolate_kappa)")
        kappa = finite_vector(kappa, name, self.n_kappa, error=CoefficientError)
        tensors = self.kappa_tensors(kappa)
        smallest = np.linalg.eigvalsh(tensors).min(axis=1)
        largest = np.abs(tensors).max(axis=(1, 2))
        bad = smallest <= 0
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise CoefficientError(
                f"{name}: the tensor at {int(bad.sum())} point(s) is not positive definite "
                f"(first: coefficient dof {i}, smallest eigenvalue {smallest[i]:.3g}, largest "
                f"entry {largest[i]:.3g}); expected a symmetric positive definite kappa")
        return kappa

    def kappa_tensors(self, kappa: np.ndarray) -> np.ndarray:
        """Full ``(n, dim, dim)`` tensors from the Voigt components of a tensor ``kappa``."""
        dim = self.mesh.dim()
        blocks = np.asarray(kappa, dtype=float).reshape(len(VOIGT[dim]), -1)
        tensors = np.zeros((blocks.shape[1], dim, dim))
        for component, (i, j) in enumerate(VOIGT[dim]):
            tensors[:, i, j] = tensors[:, j, i] = blocks[component]
        return tensors

    @cached_property
    def lifting(self) -> sp.csr_matrix:
        """``L`` (free x n_kappa): ``A_ID(kappa) g = L kappa`` for the stored Dirichlet data."""
        rows, cols = self.lifting_pattern
        weights = sp.csr_matrix((self.dirichlet_values[cols], (rows, np.arange(len(rows)))),
                                shape=(self.n_free, len(rows)))
        return (weights @ self.lifting_assembly).tocsr()

    @cached_property
    def mass_matrix(self) -> sp.csr_matrix:
        """Mass matrix on all dofs (built on first use)."""
        return _mass.assemble(self.basis).tocsr()

    @cached_property
    def source_matrix(self) -> sp.csr_matrix:
        """``S``: free rows of the mass matrix, so that ``b_f = S f`` for nodal ``f``."""
        return self.mass_matrix[self.free_dofs].tocsr()

    @cached_property
    def laplace_matrix(self) -> sp.csr_matrix:
        """Stiffness matrix with ``kappa = 1`` on all dofs (H1-seminorm Gram matrix)."""
        return _laplace.assemble(self.basis).tocsr()

    @cached_property
    def system(self) -> LinearSystem:
        """The JAX maps ``kappa -> A``, ``(kappa, f) -> b``; builds the source map S once.

        Built eagerly even when first read inside a traced function (``jax.jit``): the arrays
        are constants of the mesh, and cached as tracers they would leak out of the trace.
        """
        with jax.ensure_compile_time_eval():
            return self._system()

    def _system(self) -> LinearSystem:
        return self._linear_system(FixedMatrix.from_scipy(self.assembly), self.pattern,
                                   FixedMatrix.from_scipy(self.lifting_assembly),
                                   self.lifting_pattern)

    def system_at(self, kappa, name: str = "kappa") -> LinearSystem:
        r"""The condensed system frozen at one coefficient ``kappa``, for problems that never
        change it (a source inversion): the one-parameter family

        .. math::

            A(s) = s\,A(\kappa), \qquad b(s, f) = S f + h - s\,A_{ID}(\kappa)\, g,

        a :class:`~prdp_fem.fem.system.LinearSystem` with ``n_kappa = 1``: pass ``s = ones(1)``
        where :attr:`system` takes ``kappa``. It is assembled at ``kappa`` in one pass of
        scikit-fem's element data, without the map ``G`` that :attr:`system` sums entry by
        entry and lays out both ways (0.3-0.45 s of the 0.89 s setup of a 256 x 256 P1
        source inversion). Entries
        below ``1e-14 sqrt(|a_ii a_jj|)`` (geometric cancellation, as on right triangles) are
        dropped, diagonals kept: a bound that does not depend on ``kappa``'s contrast
        (``|a_ij| <= sqrt(a_ii a_jj)`` for a positive semi-definite ``A``). Built anew on
        each call.

        >>> import numpy as np, jax.numpy as jnp
        >>> from prdp_fem import unit_square
        >>> disc = discretize(unit_square(4), element="P1", kappa_space="P0")
        >>> kappa = np.linspace(1.0, 2.0, disc.n_kappa)
        >>> frozen = disc.system_at(kappa)
        >>> frozen.n_kappa
        1
        >>> gap = frozen.operator(jnp.ones(1)).to_scipy() - disc.stiffness_matrix(kappa)
        >>> bool(abs(gap).max() < 1e-14)
        True
        """
        operator, lifting = self._blocks_at(kappa, name)
        values, pattern = _csr_entries(operator)
        lifting_values, lifting_pattern = _csr_entries(lifting)
        with jax.ensure_compile_time_eval():
            return self._linear_system(FixedMatrix.column(values), pattern,
                                       FixedMatrix.column(lifting_values), lifting_pattern)

    def host_system_at(self, kappa, f: np.ndarray | None = None, name: str = "kappa"
                       ) -> tuple[sp.csr_matrix, np.ndarray]:
        """``(A, b)`` at ``kappa`` on the host: the condensed operator (SciPy CSR) and the
        right-hand side ``S f + h - A_ID g`` (``f`` nodal; ``None``: 0), as
        :meth:`stiffness_matrix` and :meth:`rhs` give them, assembled in one pass as
        :meth:`system_at` is, without the map ``G``. ``name`` names ``kappa`` in errors.

        ``kappa`` may also be a function of the coordinates (``x`` of shape ``(dim, ...)``,
        scalar coefficients): it is then evaluated at the quadrature points, so the operator
        has no interpolation error in the coefficient (P2/Q2 keep their L2 rate 3 with a
        variable ``kappa``; interpolated into P0 or P1 it limits them to 2)."""
        operator, lifting = self._blocks_at(kappa, name)
        b = self.neumann - lifting @ self.dirichlet_values
        if f is not None:
            b = b + self.source_matrix @ finite_vector(f, "f", self.n_dofs)
        return operator, b

    def _blocks_at(self, kappa, name: str) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """``(A, A_ID)`` at ``kappa``: the operator and its Dirichlet columns."""
        if is_traced(kappa):
            raise CoefficientError(f"{name}: traced; expected concrete values (the system at "
                                   "one kappa is assembled on the host)")
        if callable(kappa):
            full = self._forms[0].assemble(self.basis,
                                           kappa=self._at_quadrature_points(kappa, name))
        else:
            full = _assembled_at(self.basis, self.kappa_basis, self._forms,
                                 self.check_kappa(kappa, name))
        return _condensed(full.tocsr(), self.free_dofs, self.dirichlet_dofs)

    def _at_quadrature_points(self, fn: Callable[[np.ndarray], np.ndarray],
                              name: str) -> np.ndarray:
        """``fn`` at the state basis's quadrature points, ``(cells, points)``, finite and
        ``> 0``, or a :class:`CoefficientError` naming ``name``."""
        if self.kappa_kind != "scalar":
            raise CoefficientError(f"{name}: a function for a tensor coefficient; expected "
                                   f"its {self.n_kappa} Voigt components (see interpolate_kappa)")
        x = np.asarray(self.basis.global_coordinates())
        values = real_array(host_values(fn(x), f"{name}(x)"), f"{name}(x)",
                            error=CoefficientError)
        values = np.array(_broadcast(values, x.shape[1:], f"{name}(x)"), dtype=float)
        if not np.isfinite(values).all():
            raise CoefficientError(f"{name}(x) has NaN/Inf values at quadrature points; "
                                   "expected a finite coefficient")
        if (values <= 0).any():
            raise CoefficientError(f"{name}(x) is <= 0 at {int((values <= 0).sum())} "
                                   f"quadrature point(s) (min {values.min():.3g}); expected "
                                   "kappa > 0")
        return values

    def _linear_system(self, assembly: FixedMatrix, pattern, lifting: FixedMatrix,
                       lifting_pattern) -> LinearSystem:
        return LinearSystem(
            assembly=assembly,
            rows=as_jax(pattern[0], np.int32),
            cols=as_jax(pattern[1], np.int32),
            lifting=lifting,
            lifting_rows=as_jax(lifting_pattern[0], np.int32),
            lifting_cols=as_jax(lifting_pattern[1], np.int32),
            source=FixedMatrix.from_scipy(self.source_matrix),
            neumann=as_jax(self.neumann),
            free_dofs=as_jax(self.free_dofs, np.int32),
            dirichlet_dofs=as_jax(self.dirichlet_dofs, np.int32),
            dirichlet_values=as_jax(self.dirichlet_values),
            n_dofs=self.n_dofs,
            nullspace=None if self.nullspace is None else as_jax(self.nullspace),
            layout=ell_layout(*pattern, self.n_free),
        )

    @property
    def nullspace(self) -> np.ndarray | None:
        """Constants on the free dofs for a pure Neumann problem (no Dirichlet dofs), else None."""
        return np.ones(self.n_free) if len(self.dirichlet_dofs) == 0 else None

    def stiffness_matrix(self, kappa: np.ndarray) -> sp.csr_matrix:
        """Condensed ``A(kappa)`` as SciPy CSR (reference path, no JAX): ``G kappa``, which
        builds ``G`` on first use; for one ``kappa`` only, :meth:`host_system_at` does not."""
        values = self.assembly @ self.check_kappa(kappa)
        return sp.csr_matrix((values, self.pattern), shape=(self.n_free, self.n_free))

    def rhs(self, kappa: np.ndarray, f: np.ndarray | None = None) -> np.ndarray:
        """Condensed right-hand side ``S f + h - L kappa`` (NumPy reference path; builds ``G``
        on first use, as :meth:`stiffness_matrix` does)."""
        b = self.neumann - self.lifting @ self.check_kappa(kappa)
        if f is not None:
            b = b + self.source_matrix @ finite_vector(f, "f", self.n_dofs)
        return b

    def balance_source(self, f: np.ndarray) -> np.ndarray:
        """Nodal ``f`` shifted by a constant so that pure Neumann data balance discretely.

        The discrete system is solvable iff ``1' (M f + h) = 0``; interpolating a balanced
        continuous source meets that only up to the interpolation error.
        """
        f = finite_vector(f, "f", self.n_dofs)
        ones = np.ones(self.n_dofs)
        mass_of_ones = self.mass_matrix @ ones
        imbalance = mass_of_ones @ f + self.neumann.sum()
        return f - imbalance / mass_of_ones.sum()

    def load_vector(self, f: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """Free part of ``int f v`` with ``f(x)`` evaluated at quadrature points (exact load)."""
        form = skfem.LinearForm(lambda v, w: f(w.x) * v)
        return finite_vector(form.assemble(self.basis)[self.free_dofs], "source f",
                             self.n_free)

    def interpolate(self, fn: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """Nodal values of ``fn`` at the dofs of the solution space (all dofs); finite."""
        values = real_array(host_values(fn(self.basis.doflocs), "interpolate: fn(x)"),
                            "interpolate: fn(x)")
        return finite_vector(_broadcast(values, (self.n_dofs,), "interpolate: fn(x)"),
                             "interpolate: fn(x)", self.n_dofs)

    def project(self, fn: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """L2 projection of ``fn`` onto the solution space, all dofs (``M p = int fn v``).

        A misfit ``||u - p||_M^2`` differs from ``int (u - fn)^2`` by a constant only, so both
        have the same minimiser; ``fn`` is evaluated at quadrature points.

        ``M`` is solved by Jacobi-preconditioned CG (:func:`~prdp_fem.linalg.host_cg.jacobi_pcg`):
        ``cond(D^{-1} M)`` is bounded independently of the mesh size and shape (``<= 4`` for P1
        triangles), so a few dozen iterations reach round-off where a sparse LU of a 263k-dof
        mass matrix takes seconds; SuperLU remains the fallback should CG stop short.
        """
        load = skfem.LinearForm(lambda v, w: host_values(fn(w.x), "project: fn(x)") * v
                                ).assemble(self.basis)
        load = finite_vector(load, "project: fn(x)", self.n_dofs)
        projection = jacobi_pcg(self.mass_matrix, load, PROJECTION_RTOL)
        return spla.spsolve(self.mass_matrix.tocsc(), load) if projection is None \
            else projection.x

    def interpolate_kappa(self, fn: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """``fn`` as a coefficient vector: cell centroids (P0) or the space's nodes (P1: the
        vertices; P2: vertices and edge midpoints, plus face and cell centres on Q2).

        For a tensor coefficient ``fn(x)`` returns ``(dim, dim)`` (constant) or
        ``(dim, dim, n_points)``; the result holds its Voigt components, component-major.
        """
        x = self.mesh.p[:, self.mesh.t].mean(axis=1) if self.kappa_space == "P0" \
            else self.kappa_basis.doflocs
        values = real_array(host_values(fn(x), "interpolate_kappa: fn(x)"),
                            "interpolate_kappa: fn(x)", error=CoefficientError)
        if not np.isfinite(values).all():
            raise CoefficientError("interpolate_kappa: fn(x) has NaN/Inf values; expected a "
                                   "finite coefficient")
        if self.kappa_kind == "scalar":
            return np.array(_broadcast(values, x.shape[1:], "interpolate_kappa: fn(x)"))
        dim = self.mesh.dim()
        if values.shape[:2] != (dim, dim):
            raise CoefficientError(f"tensor kappa: fn(x) has shape {values.shape}; expected "
                                   f"({dim}, {dim}) or ({dim}, {dim}, n_points)")
        values = np.broadcast_to(values.reshape(dim, dim, -1), (dim, dim, x.shape[1]))
        if not np.allclose(values, values.transpose(1, 0, 2), rtol=1e-12, atol=0.0):
            raise CoefficientError("tensor kappa: fn(x) is not symmetric; expected K_ij = K_ji")
        return np.concatenate([values[i, j] for i, j in VOIGT[dim]])

    def expand(self, u_free: np.ndarray) -> np.ndarray:
        """Full nodal vector from free values plus the Dirichlet data (NumPy)."""
        full = np.zeros(self.n_dofs)
        full[self.dirichlet_dofs] = self.dirichlet_values
        full[self.free_dofs] = np.asarray(u_free)
        return full


def discretize(
    mesh: skfem.Mesh,
    *,
    element: str = "P1",
    kappa_space: str = "P0",
    kappa_kind: str = "scalar",
    dirichlet: BoundaryData = 0.0,
    neumann: Mapping[str, BoundaryValue] | None = None,
    pins: Sequence[tuple[Sequence[float], float]] | None = None,
) -> Discretization:
    """Discretise ``-div(kappa grad u) = f`` on ``mesh``.

    Parameters
    ----------
    element
        ``"P1"``/``"P2"`` on triangle and tetrahedron meshes, ``"Q1"``/``"Q2"`` on quads and
        hexahedra (``"P1"``/``"P2"`` are accepted there as aliases of Q1/Q2).
    kappa_space
        ``"P0"`` (one value per cell), ``"P1"`` (nodal, linear/multilinear) or ``"P2"``
        (second order, Q2 on quadrilaterals and hexahedra: the order of a P2/Q2 state, whose
        L2 rate 3 a P1 coefficient would hold to 2). For one fixed coefficient,
        :meth:`Discretization.host_system_at` also takes a function of ``x``, evaluated at the
        quadrature points.
    kappa_kind
        ``"scalar"`` or ``"tensor"`` (symmetric, Voigt components per point; see the module).
    dirichlet
        ``u = g`` data: a number or callable for the whole boundary, a dict
        ``{boundary name: number | callable}``, or ``None`` for a pure Neumann problem: the
        operator is then singular with the constants as nullspace (``Discretization.nullspace``,
        handled by ``system.solve``; the data must balance, ``int f + int h = 0``).
    neumann
        ``kappa du/dn = h`` data as ``{boundary name: number | callable}``; boundaries in
        neither dict are natural (``h = 0``).
    pins
        Point constraints ``[(point, value), ...]``: ``u(point) = value`` at a node of the
        mesh (a vertex; any dof location of the element), as hIPPYlib pins a pure Neumann
        problem's state at one point. A point that is no dof location (within ``1e-9`` of the
        mesh's size) is refused, naming the nearest one.
    """
    mesh_type = type(mesh)
    if mesh_type not in _ELEMENTS:
        raise DiscretizationError(
            f"mesh of type {mesh_type.__name__}: expected a linear triangle, tetrahedron, quad or "
            "hexahedron mesh (see prdp_fem.load_mesh)")
    element_cls = _lookup(_ELEMENTS[mesh_type], _alias(element, mesh_type), "element", mesh)
    kappa_cls = _lookup(_KAPPA_ELEMENTS[mesh_type], kappa_space, "kappa_space", mesh)
    if kappa_kind not in KAPPA_KINDS:
        raise DiscretizationError(f"kappa_kind={kappa_kind!r}: expected one of {KAPPA_KINDS}")
    basis = skfem.CellBasis(mesh, element_cls())
    kappa_basis = basis.with_element(kappa_cls())
    dirichlet_dofs, dirichlet_values = _with_pins(basis, *_dirichlet(basis, mesh, dirichlet),
                                                  pins)
    constrained = np.zeros(basis.N, dtype=bool)  # a mask, not setdiff1d's sort
    constrained[dirichlet_dofs] = True
    free = np.flatnonzero(~constrained)
    if len(free) == 0:
        raise DiscretizationError("dirichlet: every dof is constrained; expected free dofs")
    _check_pinned(basis, dirichlet_dofs)
    neumann_load = _neumann(mesh, basis, neumann)[free]
    return Discretization(
        mesh=mesh, element=element, kappa_space=kappa_space, kappa_kind=kappa_kind, basis=basis,
        kappa_basis=kappa_basis, free_dofs=free, dirichlet_dofs=dirichlet_dofs,
        dirichlet_values=dirichlet_values, neumann=neumann_load)


def _check_pinned(basis, dirichlet_dofs: np.ndarray) -> None:
    """Each connected part of the mesh needs Dirichlet data, or be the only part (pure Neumann).

    Otherwise the operator has a nullspace of constants per floating part, which CG cannot
    handle from one nullspace vector.
    """
    dofs = basis.element_dofs
    edges = np.stack([np.repeat(dofs[:1], dofs.shape[0] - 1, axis=0).ravel(),
                      dofs[1:].ravel()])
    graph = sp.coo_matrix((np.ones(edges.shape[1]), edges), shape=(basis.N, basis.N))
    n_parts, part = csgraph.connected_components(graph, directed=False)
    if len(dirichlet_dofs) == 0:
        if n_parts > 1:
            raise DiscretizationError(
                f"dirichlet=None on a mesh of {n_parts} disconnected parts: the operator has "
                f"{n_parts} constant modes; expected one connected mesh, or Dirichlet data on "
                "every part")
        return
    floating = np.setdiff1d(np.arange(n_parts), part[dirichlet_dofs])
    if floating.size:
        raise DiscretizationError(
            f"dirichlet: {floating.size} of the mesh's {n_parts} disconnected parts carry no "
            "Dirichlet data, so the operator is singular; expected Dirichlet data on every part")


def _alias(element: str, mesh_type) -> str:
    if mesh_type in (skfem.MeshQuad1, skfem.MeshHex1):
        return {"P1": "Q1", "P2": "Q2"}.get(element, element)
    return element


def _lookup(table: dict, key: str, field: str, mesh) -> type:
    if key not in table:
        raise DiscretizationError(
            f"{field}={key!r} on a {type(mesh).__name__} mesh: expected one of {sorted(table)}")
    return table[key]


def _boundary_names(mesh) -> dict:
    return dict(mesh.boundaries or {})


def _facets_of(mesh, name: str, field: str) -> np.ndarray:
    boundaries = _boundary_names(mesh)
    if name not in boundaries:
        raise DiscretizationError(
            f"{field}: unknown boundary {name!r}; this mesh has {sorted(boundaries) or 'none'}")
    return np.asarray(boundaries[name])


def _dirichlet(basis, mesh, data: BoundaryData) -> tuple[np.ndarray, np.ndarray]:
    if data is None:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    if not isinstance(data, Mapping):
        data = {None: data}
    values = np.full(basis.N, np.nan)
    for name, value in data.items():
        facets = mesh.boundary_facets() if name is None else _facets_of(mesh, name, "dirichlet")
        dofs = basis.get_dofs(facets).all()
        values[dofs] = _evaluate(value, basis.doflocs[:, dofs], f"dirichlet[{name!r}]")
    dofs = np.flatnonzero(~np.isnan(values))
    return dofs, values[dofs]


def _with_pins(basis, dofs: np.ndarray, values: np.ndarray, pins) -> tuple[np.ndarray,
                                                                          np.ndarray]:
    """The Dirichlet dofs and values with each pinned point's dof added (sorted, as
    :func:`_dirichlet` gives them)."""
    if not pins:
        return dofs, values
    locations = basis.doflocs
    size = float(np.ptp(locations, axis=1).max())
    constrained = dict(zip(dofs.tolist(), values.tolist(), strict=True))
    for i, pin in enumerate(pins):
        try:
            point, value = pin
            point = np.asarray(point, dtype=float).reshape(-1)
            value = float(value)
        except (TypeError, ValueError):
            raise DiscretizationError(f"pins[{i}] = {pin!r}: expected (point, value) with a "
                                      f"point of {locations.shape[0]} coordinates") from None
        if point.shape != (locations.shape[0],) or not np.isfinite([*point, value]).all():
            raise DiscretizationError(f"pins[{i}] = {pin!r}: expected a finite point of "
                                      f"{locations.shape[0]} coordinates and a finite value")
        distance = np.linalg.norm(locations - point[:, None], axis=0)
        nearest = int(np.argmin(distance))
        if distance[nearest] > 1e-9 * size:
            raise DiscretizationError(
                f"pins[{i}]: point {point.tolist()} is not a node of the mesh (nearest dof "
                f"location {locations[:, nearest].tolist()} at distance {distance[nearest]:.3g}); "
                "expected a mesh vertex")
        constrained[nearest] = value
    order = sorted(constrained)
    return np.array(order, dtype=dofs.dtype), np.array([constrained[d] for d in order])


def _evaluate(value: BoundaryValue, x: np.ndarray, field: str) -> np.ndarray:
    result = np.broadcast_to(np.asarray(value(x) if callable(value) else value, dtype=float),
                             x.shape[1:])
    if not np.isfinite(result).all():
        raise DataError(f"{field}: boundary data is NaN/Inf; expected finite values")
    return np.array(result)


def _neumann(mesh, basis, data) -> np.ndarray:
    load = np.zeros(basis.N)
    for name, value in (data or {}).items():
        facet_basis = skfem.FacetBasis(mesh, basis.elem, facets=_facets_of(mesh, name, "neumann"))
        form = skfem.LinearForm(
            lambda v, w, value=value, name=name: _evaluate(value, w.x, f"neumann[{name!r}]") * v)
        load += form.assemble(facet_basis)
    return load


def _assembly_maps(basis, kappa_basis, free, forms):
    """G and pattern of the condensed operator; G_D and pattern of its Dirichlet columns.

    ``forms[c]`` is the bilinear form of coefficient component ``c`` (one for a scalar).
    Each assembled entry's row and column are renumbered once (free or Dirichlet), in
    ``int32``: at 512 x 512 there are 4.7 million, and every copy of them is fresh memory.
    The elements are assembled in passes of at most :data:`_ENTRIES_PER_PASS` entries, each
    pass's entries summed before the next: every element contributes ``(local dofs)^2 x
    (coefficient dofs)`` entries (64 for P1 tetrahedra with a P1 coefficient), and held all
    at once they took 20 GB for the 512k free dofs of ``unit_cube(81)``.
    """
    n = basis.N
    free_index = np.full(n, -1, dtype=np.int32)
    free_index[free] = np.arange(len(free), dtype=np.int32)
    dirichlet_index = np.full(n, -1, dtype=np.int32)
    dirichlet_index[free_index < 0] = np.arange(n - len(free), dtype=np.int32)
    n_free, n_kappa = len(free), len(forms) * kappa_basis.N
    free_parts, lifting_parts = [], []
    for rows, cols, kappa_idx, data in _assembled_entries(basis, kappa_basis, forms):
        free_row, free_col = free_index[rows], free_index[cols]
        row_free = free_row >= 0
        on_free, on_dirichlet = row_free & (free_col >= 0), row_free & (free_col < 0)
        # Dirichlet columns: their own pattern (free row, index into the Dirichlet dofs)
        lifting_parts.append(_summed(free_row[on_dirichlet],
                                     dirichlet_index[cols[on_dirichlet]], n - n_free,
                                     kappa_idx[on_dirichlet], data[on_dirichlet], n_kappa))
        # condensed pattern: entries keyed by (row, col) in free numbering
        free_parts.append(_summed(free_row[on_free], free_col[on_free], n_free,
                                  kappa_idx[on_free], data[on_free], n_kappa))
    assembly, pattern = _structural(*_merged(free_parts, n_kappa), n_free)
    lifting_assembly, lifting_pattern = _structural(*_merged(lifting_parts, n_kappa),
                                                    n - n_free)
    return AssemblyMaps(assembly, pattern, lifting_assembly, lifting_pattern)


def _assembled_entries(basis, kappa_basis, forms):
    """Row, column, coefficient index and value of every assembled entry (duplicates apart),
    pass by pass over the elements: for each component's form, one assembly per coefficient
    basis function."""
    nt = basis.nelems
    per_element = basis.Nbfun ** 2 * kappa_basis.Nbfun * len(forms)
    per_pass = max(1, _ENTRIES_PER_PASS // per_element)
    for start in range(0, nt, per_pass):
        elements = np.arange(start, min(start + per_pass, nt))
        part, kappa_part = basis, kappa_basis
        if elements.size < nt:  # the same dofs, mapping and quadrature on these elements
            part, kappa_part = (skfem.CellBasis(basis.mesh, b.elem, mapping=basis.mapping,
                                                quadrature=basis.quadrature,
                                                elements=elements, dofs=b.dofs)
                                for b in (basis, kappa_basis))
        rows, cols, kappa_idx, data = [], [], [], []
        for component, form in enumerate(forms):
            for a in range(kappa_part.Nbfun):
                coo = form.coo_data(part, kappa=kappa_part.basis[a][0])
                rows.append(coo.indices[0])
                cols.append(coo.indices[1])
                # entries run element by element within each local (i, j) block
                kappa_idx.append(component * kappa_basis.N + np.tile(
                    kappa_part.element_dofs[a], coo.data.size // elements.size))
                data.append(coo.data)
        yield tuple(parts[0] if len(parts) == 1 else np.concatenate(parts)
                    for parts in (rows, cols, kappa_idx, data))


def _summed(r, c, n_cols, kappa_idx, data, n_kappa) -> tuple[np.ndarray, sp.csr_matrix]:
    """Duplicate ``(r, c)`` entries summed: the sorted keys ``r * n_cols + c`` and the map
    ``G: kappa -> values`` on them."""
    keys, entry = unique_with_inverse(r.astype(np.int64) * n_cols + c)
    assembly = sp.csr_matrix((data, (entry, kappa_idx)), shape=(len(keys), n_kappa))
    assembly.sum_duplicates()
    return keys, assembly


def _merged(parts: list, n_kappa: int) -> tuple[np.ndarray, sp.csr_matrix]:
    """The passes' ``(keys, G)`` as one, entries of a key in several passes summed."""
    if len(parts) == 1:
        return parts[0]
    keys, entry = unique_with_inverse(np.concatenate([keys for keys, _ in parts]))
    offsets = np.cumsum([0] + [len(keys) for keys, _ in parts[:-1]])
    coos = [assembly.tocoo() for _, assembly in parts]
    rows = np.concatenate([entry[offset + coo.row] for offset, coo in zip(offsets, coos,
                                                                             strict=True)])
    merged = sp.csr_matrix((np.concatenate([coo.data for coo in coos]),
                            (rows, np.concatenate([coo.col for coo in coos]))),
                           shape=(len(keys), n_kappa))
    merged.sum_duplicates()
    return keys, merged


def _structural(keys: np.ndarray, assembly: sp.csr_matrix, n_cols: int):
    """``(G, (rows, cols))`` without the entries that are zero for every kappa (geometric
    cancellation), diagonals kept; rows sorted."""
    row_size = abs(assembly) @ np.ones(assembly.shape[1])  # a product: .sum(axis=1) took 2-3x
    diagonal = keys // n_cols == keys % n_cols
    scale = row_size.max() if row_size.size else 0.0
    structural = diagonal | (row_size > _STRUCTURAL_ZERO * scale)
    keys = keys[structural]
    return assembly[structural].tocsr(), (keys // n_cols, keys % n_cols)


def _assembled_at(basis, kappa_basis, forms, kappa: np.ndarray) -> sp.csr_matrix:
    """The operator on all dofs at ``kappa``: one scikit-fem assembly per coefficient
    component, summed (SciPy CSR, duplicates summed)."""
    n_basis = kappa_basis.N
    return sum(form.assemble(basis, kappa=_at_quadrature(
        kappa_basis, kappa[component * n_basis:(component + 1) * n_basis]))
        for component, form in enumerate(forms)).tocsr()


def _condensed(full: sp.csr_matrix, free: np.ndarray,
               dirichlet: np.ndarray) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """The free rows of ``full`` split into ``(A, A_ID)``: free columns, and the Dirichlet
    columns in ``dirichlet``'s order (that of ``dirichlet_values``). Geometric zeros are
    dropped (see :meth:`Discretization.system_at`), the diagonal of ``A`` kept; columns
    sorted within each row."""
    scale = np.sqrt(np.abs(full.diagonal()))
    free_rows = full[free]
    return (_dropped_zeros(free_rows[:, free], scale[free], scale[free], keep_diagonal=True),
            _dropped_zeros(free_rows[:, dirichlet], scale[free], scale[dirichlet],
                           keep_diagonal=False))


def _dropped_zeros(block: sp.csr_matrix, row_scale: np.ndarray, col_scale: np.ndarray, *,
                   keep_diagonal: bool) -> sp.csr_matrix:
    """``block`` without entries ``|a_ij| <= 1e-14 row_scale_i col_scale_j``."""
    block.sort_indices()
    coo = block.tocoo()  # row by row, columns sorted
    kept = np.abs(coo.data) > _STRUCTURAL_ZERO * row_scale[coo.row] * col_scale[coo.col]
    if keep_diagonal:
        kept |= coo.row == coo.col
    return sp.csr_matrix((coo.data[kept], (coo.row[kept], coo.col[kept])), shape=block.shape)


def _csr_entries(matrix: sp.csr_matrix) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Values and ``(rows, cols)`` of a canonical CSR matrix, row by row."""
    coo = matrix.tocoo()
    return coo.data, (coo.row, coo.col)


def _at_quadrature(kappa_basis, values: np.ndarray) -> np.ndarray:
    """A coefficient field at the quadrature points, ``(cells, points)``: what
    ``kappa_basis.interpolate`` gives, without its split of the basis into components
    (0.36 s of unique on a 512 x 512 mesh)."""
    return sum(values[kappa_basis.element_dofs[a]][:, None] * np.asarray(kappa_basis.basis[a][0])
               for a in range(kappa_basis.Nbfun))


def _broadcast(values: np.ndarray, shape: tuple[int, ...], where: str) -> np.ndarray:
    """``values`` as ``shape`` (a scalar or that shape), or a :class:`ShapeError`."""
    try:
        return np.broadcast_to(values, shape)
    except ValueError:
        raise ShapeError(f"{where}: shape {values.shape}; expected a scalar or {shape} (one "
                         "value per point it was given)") from None
