"""One linear system spread over the devices of a ``jax.sharding.Mesh``.

:func:`shard` gives a square :class:`~prdp_fem.linalg.operator.SparseMatrix` a
:class:`Partition` as its layout: its unknowns are split into ``D`` parts of at most ``L``
(one per device of the mesh axis) and numbered part by part, padded to ``D L`` by identity
rows. :func:`~prdp_fem.linalg.cg.solve` then runs CG in that numbering: ``b`` is gathered
into it (sharded over the axis), every product is a halo exchange
(:mod:`prdp_fem.linalg.halo`), the dot products are reduced across the devices, and the
solution is gathered back. Both gradient modes see the renumbered system as any other, so
gradients, PRDP's traced ``K`` and counters work unchanged; results equal the single-device
solve's up to the order of summation.

The parts: by default contiguous blocks of a reverse Cuthill-McKee ordering of the matrix
graph (SciPy), which needs nothing but the pattern and couples each part to its two
neighbours only (a slab-like partition: the halo of a 2-D mesh of ``n`` unknowns is
``O(sqrt(n))`` values per side). A graph partitioner's answer (METIS through ``pymetis``, for
instance: fewer cut edges on many devices) is passed as ``parts``, one part per unknown.

>>> import jax, numpy as np, scipy.sparse as sp
>>> from prdp_fem.linalg import SparseMatrix, TruncatedCG, solve
>>> A = SparseMatrix.from_scipy(sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(6, 6)))
>>> spread = shard(A, jax.make_mesh((len(jax.devices()),), ("dofs",)))
>>> b = np.ones(6)
>>> bool(np.allclose(solve(spread, b, TruncatedCG(6)).x, solve(A, b, TruncatedCG(6)).x))
True
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jax.sharding import AxisType, Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from scipy.sparse.csgraph import reverse_cuthill_mckee

from ..errors import ShapeError, SolverConfigError
from .halo import HaloLayout, halo_layout
from .operator import SparseMatrix

__all__ = ["Partition", "partition", "shard"]


@partial(jax.tree_util.register_dataclass,
         data_fields=["gather", "position", "rows", "cols", "value_order", "halo"],
         meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Partition:
    """How the ``n`` unknowns of a square pattern are numbered over the devices.

    ``gather[p]``: the unknown at partitioned position ``p`` (``n``: padding), sharded over
    the mesh axis; ``position[i]``: the partitioned position of unknown ``i``; ``rows``,
    ``cols``: the renumbered pattern with one diagonal entry per padding row, row-sorted;
    ``value_order``: where each of its entries comes from in the values followed by the
    padding rows' ones; ``halo``: the layout of that pattern's product.
    """

    gather: jax.Array
    position: jax.Array
    rows: jax.Array
    cols: jax.Array
    value_order: jax.Array
    halo: HaloLayout

    @property
    def mesh(self) -> Mesh:
        return self.halo.mesh

    @property
    def n(self) -> int:
        """Unknowns of the matrix."""
        return int(self.position.shape[0])

    @property
    def n_padded(self) -> int:
        """Rows of the renumbered matrix: devices times rows per device."""
        return int(self.gather.shape[0])

    def partitioned(self, matrix: SparseMatrix) -> SparseMatrix:
        """``matrix`` renumbered (its values gathered; differentiable in them)."""
        return SparseMatrix(self.rows, self.cols, self.partitioned_values(matrix.values),
                            (self.n_padded, self.n_padded), self.halo)

    def partitioned_values(self, values: jax.Array) -> jax.Array:
        """The values of the renumbered matrix: ``values`` and the padding rows' ones."""
        ones = jnp.ones(self.n_padded - self.n, values.dtype)
        return jnp.concatenate([values, ones])[self.value_order]

    def to_partitioned(self, vector: jax.Array) -> jax.Array:
        """A vector of the unknowns in the partitioned numbering (zero on padding), sharded."""
        padded = jnp.concatenate([vector, jnp.zeros(1, vector.dtype)])[self.gather]
        return jax.lax.with_sharding_constraint(
            padded, NamedSharding(self.mesh, P(self.halo.axis)))

    def from_partitioned(self, vector: jax.Array) -> jax.Array:
        """The unknowns' values of a partitioned vector, in their own order."""
        return vector[self.position]

    def prepare(self, values: jax.Array) -> PartitionedProduct:
        """The product in the matrix's own numbering (for :func:`~prdp_fem.linalg.matvec`):
        renumbered in and out on every call; :func:`~prdp_fem.linalg.cg.solve` renumbers
        once per solve instead."""
        kernel = self.halo.prepare(self.partitioned_values(values))
        return PartitionedProduct(kernel, self)


@partial(jax.tree_util.register_dataclass, data_fields=["kernel", "partition"],
         meta_fields=[])
@dataclasses.dataclass(frozen=True)
class PartitionedProduct:
    """A halo product applied to vectors in the matrix's own numbering."""

    kernel: object
    partition: Partition

    @property
    def n_rows(self) -> int:
        return self.partition.n

    def __call__(self, x: jax.Array) -> jax.Array:
        part = self.partition
        return part.from_partitioned(self.kernel(part.to_partitioned(jnp.asarray(x))))

    def linear_in_values(self, x: jax.Array) -> jax.Array:
        part = self.partition
        return part.from_partitioned(
            self.kernel.linear_in_values(part.to_partitioned(jnp.asarray(x))))


def partition(rows: np.ndarray, cols: np.ndarray, n: int, mesh: Mesh, *,
              parts: np.ndarray | None = None, axis: str | None = None) -> Partition:
    """The :class:`Partition` of the row-sorted ``n x n`` pattern ``(rows, cols)`` over
    ``axis`` of ``mesh`` (its only axis by default); ``parts``: the part (device index
    along the axis) of every unknown, else blocks of a reverse Cuthill-McKee ordering."""
    axis = _mesh_axis(mesh, axis)
    # GSPMD places what the solve computes (jax.make_mesh's explicit axes would make every
    # gather of a replicated array by sharded indices name its output sharding)
    mesh = Mesh(mesh.devices, mesh.axis_names,
                axis_types=(AxisType.Auto,) * len(mesh.axis_names))
    size = mesh.shape[axis]
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    if parts is None:
        graph = sp.csr_matrix((np.ones(rows.size, np.int8), (rows, cols)), shape=(n, n))
        order = np.asarray(reverse_cuthill_mckee(graph, symmetric_mode=True), np.int64)
        owner = np.empty(n, np.int64)
        owner[order] = np.arange(n) // -(-n // size)
    else:
        owner = _checked_parts(parts, n, size)
        order = np.arange(n)
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    by_part = np.lexsort((rank, owner))
    counts = np.bincount(owner, minlength=size)
    local_rows = max(int(counts.max()), 1)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    position = np.empty(n, np.int64)
    position[by_part] = owner[by_part] * local_rows + np.arange(n) - starts[owner[by_part]]
    padded = size * local_rows
    gather = np.full(padded, n, np.int64)
    gather[position] = np.arange(n)
    padding = np.flatnonzero(gather == n)
    new_rows = np.concatenate([position[rows], padding])
    new_cols = np.concatenate([position[cols], padding])
    value_order = np.lexsort((new_cols, new_rows))
    new_rows, new_cols = new_rows[value_order], new_cols[value_order]
    halo = halo_layout(new_rows, new_cols, local_rows, mesh, axis)
    vector, replicated = NamedSharding(mesh, P(axis)), NamedSharding(mesh, P())
    as32 = partial(np.asarray, dtype=np.int32)
    return Partition(jax.device_put(as32(gather), vector),
                     jax.device_put(as32(position), replicated),
                     jax.device_put(as32(new_rows), replicated),
                     jax.device_put(as32(new_cols), replicated),
                     jax.device_put(as32(value_order), replicated), halo)


def shard(matrix: SparseMatrix, mesh: Mesh, *, parts: np.ndarray | None = None,
          axis: str | None = None) -> SparseMatrix:
    """``matrix`` with its unknowns spread over ``mesh`` (see the module docstring): pass
    it to :func:`~prdp_fem.linalg.cg.solve` as any other matrix."""
    if matrix.shape[0] != matrix.shape[1]:
        raise ShapeError(f"shard: a {matrix.shape[0]} x {matrix.shape[1]} matrix; expected "
                         "a square one (the operator of a linear system)")
    rows, cols = np.asarray(matrix.rows), np.asarray(matrix.cols)
    if rows.size and np.any(np.diff(rows) < 0):
        raise ShapeError("shard: rows are not sorted; expected a row-sorted pattern (build "
                         "the matrix with SparseMatrix.from_coo or from_scipy)")
    layout = partition(rows, cols, matrix.shape[0], mesh, parts=parts, axis=axis)
    return dataclasses.replace(matrix, layout=layout, kernel=None)


def _mesh_axis(mesh: Mesh, axis: str | None) -> str:
    if not isinstance(mesh, Mesh):
        raise SolverConfigError(f"mesh={mesh!r}: expected a jax.sharding.Mesh "
                                "(e.g. jax.make_mesh((4,), ('x',)))")
    if axis is None:
        if len(mesh.axis_names) != 1:
            raise SolverConfigError(f"mesh axes {mesh.axis_names}: name the one to spread "
                                    "the unknowns over (axis=...)")
        return mesh.axis_names[0]
    if axis not in mesh.axis_names:
        raise SolverConfigError(f"axis={axis!r}: expected one of the mesh's axes "
                                f"{mesh.axis_names}")
    return axis


def _checked_parts(parts, n: int, size: int) -> np.ndarray:
    owner = np.asarray(parts)
    if owner.shape != (n,) or not np.issubdtype(owner.dtype, np.integer):
        raise ShapeError(f"parts: one integer part per unknown ({n}) expected, got "
                         f"{owner.dtype} of shape {owner.shape}")
    if owner.size and (owner.min() < 0 or owner.max() >= size):
        raise ShapeError(f"parts: values {owner.min()} .. {owner.max()}; expected parts "
                         f"0 .. {size - 1}, one per device of the mesh axis ({size} devices)")
    return owner.astype(np.int64)
