r"""A square sparse matrix whose rows are spread over the devices of a ``jax.sharding.Mesh``,
its product a halo exchange inside ``jax.shard_map``.

The rows are numbered so that device ``d`` of the mesh axis owns rows ``[d L, (d + 1) L)``
(a :class:`~prdp_fem.linalg.sharding.Partition` renumbers a matrix's free dofs so). Each
device keeps the entries of its rows whose columns it owns in the ELL form of
:class:`~prdp_fem.linalg.operator.EllMatrix` (local columns), and the few whose columns live
on another device -- the interface -- as a short list that reads the *halo*

.. math:: h_d = [\, h_{d, s_1} \;|\; h_{d, s_2} \;|\; \dots \,],

for every shift ``s`` (device ``d`` reads values of device ``d - s``) the values it needs
from that device, received by one ``jax.lax.ppermute`` in which every device sends what
device ``d + s`` needs of it. The product is

.. math:: y_d = \mathrm{diag}_d\, x_d + \sum_{k < w} V_{k}\, x_d[C_{k}]
          + \text{(interface entries)} \cdot h_d,

the last term a scatter-add of the interface's entries: the local part never copies
``x_d`` into a vector extended by the halo (that copy cost an eighth of an iteration at 1M
dofs on 4 devices). Only the shifts some device needs are exchanged: a partition into
contiguous blocks of a reverse Cuthill-McKee ordering couples each block to its neighbours,
so two ``ppermute`` calls (``s = 1`` and ``s = -1``) of ``O(sqrt(n))`` values each (2-D) make
the product. The dot products of CG on vectors sharded so are reduced by XLA across the
devices (an all-reduce, ``psum``).
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

__all__ = ["HaloLayout", "HaloMatrix", "halo_layout"]


@partial(jax.tree_util.register_dataclass,
         data_fields=["diagonal", "slots", "columns", "boundary", "boundary_rows",
                      "boundary_columns", "sends", "repeated_diagonal",
                      "repeated_diagonal_rows"],
         meta_fields=["mesh", "axis", "shifts"])
@dataclasses.dataclass(frozen=True)
class HaloLayout:
    """Where each stored entry of a row-partitioned square matrix goes (indices only).

    ``diagonal[i]``: position in the values of row ``i``'s first diagonal entry (``nnz``,
    a padded zero, where it stores none); ``slots[k, i]`` / ``columns[k, i]``: position and
    *local* column of row ``i``'s ``k``-th other entry on its own device (a missing one
    points at ``nnz`` and the row's own column); ``boundary`` / ``boundary_rows`` /
    ``boundary_columns``: position, local row and halo index of each entry whose column lives
    on another device (``(D * B,)``, device ``d``'s ``B`` first, padded with zeros);
    ``sends[j]``: for shift ``shifts[j]``, the local rows each device sends (``(D * S_j,)``).
    All are sharded over ``axis`` of ``mesh`` along their last axis. ``repeated_diagonal`` /
    ``_rows``: further diagonal entries of a row (also in the slots), which
    :func:`~prdp_fem.linalg.operator.diagonal` adds to the first.
    """

    diagonal: jax.Array
    slots: jax.Array
    columns: jax.Array
    boundary: jax.Array
    boundary_rows: jax.Array
    boundary_columns: jax.Array
    sends: tuple[jax.Array, ...]
    repeated_diagonal: jax.Array
    repeated_diagonal_rows: jax.Array
    mesh: Mesh
    axis: str
    shifts: tuple[int, ...]

    def prepare(self, values: jax.Array) -> HaloMatrix:
        """The product kernel of the matrix with these ``values``."""
        values = jnp.concatenate([values, jnp.zeros(1, values.dtype)])  # nnz: missing
        vector = NamedSharding(self.mesh, P(self.axis))
        slotted = NamedSharding(self.mesh, P(None, self.axis))
        placed = jax.lax.with_sharding_constraint
        return HaloMatrix(placed(values[self.diagonal], vector),
                          placed(values[self.slots], slotted), self.columns,
                          placed(values[self.boundary], vector), self.boundary_rows,
                          self.boundary_columns, self.sends, self.mesh, self.axis,
                          self.shifts)


@partial(jax.tree_util.register_dataclass,
         data_fields=["diagonal", "values", "columns", "boundary_values", "boundary_rows",
                      "boundary_columns", "sends"],
         meta_fields=["mesh", "axis", "shifts"])
@dataclasses.dataclass(frozen=True)
class HaloMatrix:
    """The product kernel of a :class:`HaloLayout`: per device, a diagonal and ELL slots
    over its own values, and the few entries that read the halo."""

    diagonal: jax.Array
    values: jax.Array
    columns: jax.Array
    boundary_values: jax.Array
    boundary_rows: jax.Array
    boundary_columns: jax.Array
    sends: tuple[jax.Array, ...]
    mesh: Mesh
    axis: str
    shifts: tuple[int, ...]

    @property
    def n_rows(self) -> int:
        return int(self.diagonal.shape[0])

    def __call__(self, x: jax.Array) -> jax.Array:
        return self._sharded(_product)(*self._operands(), jnp.asarray(x))

    def linear_in_values(self, x: jax.Array) -> jax.Array:
        """The same product as one reduction over the slots, whose VJP in the values is a
        gather (see :meth:`~prdp_fem.linalg.operator.EllMatrix.linear_in_values`)."""
        return self._sharded(_product_in_values)(*self._operands(), jnp.asarray(x))

    def scaled(self, scale: jax.Array) -> HaloMatrix:
        """``S A S`` with ``S = diag(scale)`` (the halo of ``scale`` exchanged once)."""
        axis = self.axis
        values, boundary_values = self._sharded(_scaled_values, out=(P(None, axis), P(axis)))(
            *self._operands(), scale)
        return dataclasses.replace(self, diagonal=self.diagonal * scale * scale,
                                   values=values, boundary_values=boundary_values)

    def _operands(self) -> tuple:
        return (self.diagonal, self.values, self.columns, self.boundary_values,
                self.boundary_rows, self.boundary_columns, self.sends)

    def _sharded(self, local, out=None):
        axis = self.axis
        exchange = partial(_halo, axis=axis, size=self.mesh.shape[axis], shifts=self.shifts)
        vector, slotted = P(axis), P(None, axis)
        specs = (vector, slotted, slotted, vector, vector, vector,
                 tuple(vector for _ in self.sends), vector)
        return jax.shard_map(partial(local, exchange=exchange), mesh=self.mesh,
                             in_specs=specs, out_specs=vector if out is None else out)


def _halo(x: jax.Array, sends: tuple[jax.Array, ...], *, axis: str, size: int,
          shifts: tuple[int, ...]) -> jax.Array:
    """The values this device reads from the others, one ``ppermute`` per shift."""
    received = [jax.lax.ppermute(x[send], axis, [(d, (d + s) % size) for d in range(size)])
                for s, send in zip(shifts, sends, strict=True)]
    return jnp.concatenate(received) if received else x[:0]


def _add_boundary(y, boundary_values, boundary_rows, boundary_columns, halo):
    """``y`` plus the entries that read the halo (a short scatter-add: the interface's)."""
    if not boundary_rows.shape[0]:
        return y
    return y.at[boundary_rows].add(boundary_values * halo[boundary_columns])


def _product(diagonal, values, columns, boundary_values, boundary_rows, boundary_columns,
             sends, x, *, exchange):
    y = diagonal * x
    for k in range(values.shape[0]):  # one fused loop over the rows, as EllMatrix's
        y = y + values[k] * x[columns[k]]
    return _add_boundary(y, boundary_values, boundary_rows, boundary_columns,
                         exchange(x, sends))


def _product_in_values(diagonal, values, columns, boundary_values, boundary_rows,
                       boundary_columns, sends, x, *, exchange):
    y = diagonal * x + jnp.sum(values * x[columns], axis=0)
    return _add_boundary(y, boundary_values, boundary_rows, boundary_columns,
                         exchange(x, sends))


def _scaled_values(diagonal, values, columns, boundary_values, boundary_rows,
                   boundary_columns, sends, scale, *, exchange):
    halo = exchange(scale, sends)
    boundary = boundary_values * scale[boundary_rows] * halo[boundary_columns] \
        if boundary_rows.shape[0] else boundary_values
    return values * scale * scale[columns], boundary


def halo_layout(rows: np.ndarray, cols: np.ndarray, local_rows: int, mesh: Mesh,
                axis: str) -> HaloLayout:
    """The :class:`HaloLayout` of a row-sorted square pattern of ``D * local_rows`` rows,
    device ``d`` of ``mesh``'s ``axis`` owning rows ``[d L, (d + 1) L)`` (host, NumPy)."""
    size = mesh.shape[axis]
    n, nnz = size * local_rows, rows.size
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    row_device, col_device = rows // local_rows, cols // local_rows
    remote = row_device != col_device
    halo_index = np.zeros(nnz, np.int64)  # of the remote entries
    shift_of = (row_device - col_device) % size
    shifts, sends, offset = [], [], 0
    for shift in range(1, size):
        wanted = remote & (shift_of == shift)
        if not wanted.any():
            continue
        # per receiving device, the sorted columns it reads from device (receiver - shift)
        pairs = np.unique(row_device[wanted] * n + cols[wanted])
        receiver, column = pairs // n, pairs % n
        counts = np.bincount(receiver, minlength=size)
        width = int(counts.max())
        rank = np.arange(pairs.size) - _starts(counts)[receiver]
        send = np.zeros((size, width), np.int64)  # padding sends row 0, never read
        send[(receiver - shift) % size, rank] = column % local_rows
        entry = np.flatnonzero(wanted)
        key = row_device[entry] * n + cols[entry]
        halo_index[entry] = offset + rank[np.searchsorted(pairs, key)]
        shifts.append(shift if shift <= size // 2 else shift - size)
        sends.append(send.reshape(-1))
        offset += width
    # the remote entries per device, padded to the longest list by zeros at row 0
    crossing = np.flatnonzero(remote)
    counts = np.bincount(row_device[crossing], minlength=size)
    width = int(counts.max(initial=0))
    rank = np.arange(crossing.size) - _starts(counts)[row_device[crossing]]
    boundary = np.full((size, width), nnz, np.int64)
    boundary_rows = np.zeros((size, width), np.int64)
    boundary_columns = np.zeros((size, width), np.int64)
    where = (row_device[crossing], rank)
    boundary[where] = crossing
    boundary_rows[where] = rows[crossing] % local_rows
    boundary_columns[where] = halo_index[crossing]
    diagonal, slots, columns, repeated = _ell_slots(rows, cols, remote, n, local_rows)
    vector = NamedSharding(mesh, P(axis))
    slotted = NamedSharding(mesh, P(None, axis))
    replicated = NamedSharding(mesh, P())

    def put(array, sharding):
        return jax.device_put(np.asarray(array, np.int32), sharding)

    return HaloLayout(
        put(diagonal, vector), put(slots, slotted), put(columns, slotted),
        put(boundary.reshape(-1), vector), put(boundary_rows.reshape(-1), vector),
        put(boundary_columns.reshape(-1), vector), tuple(put(send, vector) for send in sends),
        put(repeated, replicated), put(rows[repeated], replicated), mesh, axis, tuple(shifts))


def _starts(counts: np.ndarray) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(counts)[:-1]])


def _ell_slots(rows, cols, remote, n: int, local_rows: int):
    """Diagonal positions, slot positions and local columns of the entries of a row-sorted
    pattern that stay on their device (not ``remote``); further diagonal entries of a row go
    to the slots (the product adds them) and are listed (for the diagonal)."""
    nnz = rows.size
    on_diagonal = rows == cols
    first = np.full(n, nnz, np.int64)
    diagonal_entries = np.flatnonzero(on_diagonal)
    # the first diagonal entry of each row: the last write of a reversed scatter
    first[rows[diagonal_entries[::-1]]] = diagonal_entries[::-1]
    is_first = np.zeros(nnz, bool)
    is_first[first[first < nnz]] = True
    others = np.flatnonzero(~is_first & ~remote)
    counts = np.bincount(rows[others], minlength=n)
    width = int(counts.max(initial=0))
    rank = np.arange(others.size) - _starts(counts)[rows[others]]
    slots = np.full((width, n), nnz, np.int64)
    columns = np.broadcast_to(np.arange(n) % local_rows, (width, n)).copy()
    slots[rank, rows[others]] = others
    columns[rank, rows[others]] = cols[others] % local_rows
    repeated = others[on_diagonal[others]]
    return first, slots, columns, repeated
