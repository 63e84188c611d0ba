"""The condensed linear system as a differentiable, affine function of (kappa, f).

After Dirichlet condensation, the free-dof system of ``-div(kappa grad u) = f`` is

.. math::

    A(\\kappa)\\, u_I = b(\\kappa, f), \\qquad
    \\mathrm{values}(A) = G\\,\\kappa, \\qquad
    b = S f + h - L\\,\\kappa,

with the assembly map ``G`` (nnz x n_kappa), the lifting ``L kappa = A_ID(kappa) g`` (the
Dirichlet columns, assembled by their own map ``G_D``, applied to the Dirichlet data ``g``,
which is a pytree leaf: ``b`` is differentiable in it too), the source map ``S`` (free rows
of the mass matrix) and the Neumann load ``h``. All are built once by
:mod:`prdp_fem.fem.discretization` (``Discretization.system``). A system frozen at one ``kappa``
(``Discretization.system_at``) is the same class with one coefficient, a scale ``s``:
``G`` is then the ``nnz x 1`` column of ``A(kappa)``'s values, and ``G_D`` that of its
Dirichlet columns. Here they are pytree leaves, so a :class:`LinearSystem` is
passed to jitted functions as an argument. ``G``, ``G_D`` and ``S`` are
:class:`~prdp_fem.linalg.operator.FixedMatrix` pairs, laid out for their transposes too: the
gradient in ``kappa`` is ``G^T`` applied as a gather loop, not a scatter-add over ``G``'s
149k entries (inclusion scene), which took a third of an implicit gradient at ``K = 0``.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from .._checks import finite_vector, is_traced, real_dtype
from ..errors import CoefficientError, ShapeError
from ..linalg import cg
from ..linalg.operator import EllLayout, FixedMatrix, SparseMatrix
from ..linalg.sharding import Partition, partition

__all__ = ["LinearSystem"]


@partial(jax.tree_util.register_dataclass,
         data_fields=["assembly", "rows", "cols", "lifting", "lifting_rows", "lifting_cols",
                      "source", "neumann", "free_dofs", "dirichlet_dofs", "dirichlet_values",
                      "nullspace", "layout"],
         meta_fields=["n_dofs"])
@dataclasses.dataclass(frozen=True)
class LinearSystem:
    """Maps ``kappa -> A(kappa)`` and ``(kappa, f) -> b`` on the free dofs.

    ``rows``/``cols`` are the (row-sorted) sparsity pattern of ``A``; ``assembly`` is ``G``
    (``nnz x 1`` for a system frozen at one ``kappa``: ``n_kappa`` is 1, the scale ``s``);
    ``lifting`` is ``G_D`` on the pattern ``(lifting_rows, lifting_cols)`` of the Dirichlet
    columns (``lifting_cols`` index ``dirichlet_values``). ``nullspace`` is ``None``, or the
    constants when there is no Dirichlet boundary (pure Neumann: pass it to
    :func:`~prdp_fem.linalg.cg.solve`, as :meth:`solve` does).
    """

    assembly: FixedMatrix
    rows: jax.Array
    cols: jax.Array
    lifting: FixedMatrix
    lifting_rows: jax.Array
    lifting_cols: jax.Array
    source: FixedMatrix
    neumann: jax.Array
    free_dofs: jax.Array
    dirichlet_dofs: jax.Array
    dirichlet_values: jax.Array
    n_dofs: int
    nullspace: jax.Array | None = None
    # the ELL layout of (rows, cols), the fast CG kernel; or a Partition over devices
    layout: EllLayout | Partition | None = None

    @property
    def n_free(self) -> int:
        return int(self.free_dofs.shape[0])

    @property
    def n_kappa(self) -> int:
        return self.assembly.shape[1]

    def sharded(self, mesh: Mesh, *, parts: np.ndarray | None = None,
                axis: str | None = None) -> LinearSystem:
        """This system with its free dofs spread over the devices of ``mesh`` (see
        :mod:`prdp_fem.linalg.sharding`): its solves run sharded, results and derivatives as
        on one device. ``parts``: a part per free dof, else blocks of a reverse
        Cuthill-McKee ordering."""
        return dataclasses.replace(self, layout=partition(
            np.asarray(self.rows), np.asarray(self.cols), self.n_free, mesh, parts=parts,
            axis=axis))

    def operator(self, kappa: jax.Array) -> SparseMatrix:
        """``A(kappa)`` on the free dofs (linear in ``kappa``)."""
        self._check_size(kappa)
        values = self.assembly(kappa)
        return SparseMatrix(self.rows, self.cols, values, (self.n_free, self.n_free),
                            self.layout)

    def rhs(self, kappa: jax.Array, f: jax.Array | None = None) -> jax.Array:
        """``b = S f + h - A_ID(kappa) g`` (``f`` nodal in the solution space; ``None``: 0).

        Differentiable in ``kappa``, ``f`` and the Dirichlet data ``g = dirichlet_values``.
        """
        self._check_size(kappa)
        coupling = self.lifting(kappa)  # values of A_ID(kappa)
        lifted = jax.ops.segment_sum(coupling * self.dirichlet_values[self.lifting_cols],
                                     self.lifting_rows, num_segments=self.n_free,
                                     indices_are_sorted=True)
        b = self.neumann - lifted
        if f is not None:
            # from the static shape (free under jit): a short f would gather past its end
            # and give a wrong right-hand side without a word
            real_dtype(f, "f")
            if jnp.shape(f) != (self.source.shape[1],):
                raise ShapeError(f"f: a nodal source of {self.source.shape[1]} values (the "
                                 f"solution space's dofs) expected, got shape {jnp.shape(f)}")
            b = b + self.source(f)
        return b

    def _check_size(self, kappa) -> None:
        """A coefficient of the wrong length, from its static shape (free under ``jit``): a
        frozen system's product reads ``kappa[0]`` only, and would take a whole field; a
        complex or non-numeric one by its dtype (``float`` would drop an imaginary part)."""
        real_dtype(kappa, "kappa", error=CoefficientError)
        if jnp.shape(kappa) == (self.n_kappa,):
            return
        hint = (" (this system is frozen at one kappa, Discretization.system_at: pass its "
                "scale, jnp.ones(1))") if self.n_kappa == 1 else ""
        raise ShapeError(f"kappa: {self.n_kappa} coefficient value(s) expected, got shape "
                         f"{jnp.shape(kappa)}{hint}")

    def solve(self, kappa: jax.Array, f: jax.Array | None, solver, x0: jax.Array | None = None,
              counter=None):
        """:func:`~prdp_fem.linalg.cg.solve` of ``A(kappa) u = b(kappa, f)``, nullspace included.

        Called eagerly, a non-finite ``kappa`` raises :class:`~prdp_fem.errors.CoefficientError`
        (even where it would not reach the free dofs), and the assembly runs as one compiled
        program, kept per shape (the solve as :func:`~prdp_fem.linalg.cg.solve` runs it).
        """
        real_dtype(kappa, "kappa", error=CoefficientError)  # before NumPy reads its shape
        if jnp.ndim(kappa) == 1:  # a frozen system's hint before the generic length check
            self._check_size(kappa)
        kappa = finite_vector(kappa, "kappa", self.n_kappa, error=CoefficientError)
        if is_traced(self, kappa, f):
            matrix, b = self.operator(kappa), self.rhs(kappa, f)
        else:  # one program, not one per operation (cg.solve does the same for the solve)
            matrix, b = _assembled(self, kappa, f)
        return cg.solve(matrix, b, solver, x0, nullspace=self.nullspace, counter=counter)

    def expand(self, u_free: jax.Array) -> jax.Array:
        """Full nodal vector: free values plus the Dirichlet data."""
        full = jnp.zeros(self.n_dofs, dtype=u_free.dtype)
        full = full.at[self.dirichlet_dofs].set(self.dirichlet_values.astype(u_free.dtype))
        return full.at[self.free_dofs].set(u_free)


@jax.jit
def _assembled(system: LinearSystem, kappa: jax.Array, f: jax.Array | None
               ) -> tuple[SparseMatrix, jax.Array]:
    """``(A(kappa), b(kappa, f))`` of an eager :meth:`LinearSystem.solve`, as one program: op
    by op they compiled 17 small ones on a new shape (0.3 s on 2 CPU cores)."""
    return system.operator(kappa), system.rhs(kappa, f)
