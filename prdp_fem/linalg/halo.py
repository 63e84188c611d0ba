r"""A square sparse matrix whose rows are spread over the devices of a ``jax.sharding.Mesh``,
its product a halo exchange inside ``jax.shard_map``.

The rows are numbered so that device ``d`` of the mesh axis owns rows ``[d L, (d + 1) L)``
(a :class:`~prdp_fem.linalg.sharding.Partition` renumbers a matrix's free dofs so). Each
device keeps its rows in the ELL form of :class:`~prdp_fem.linalg.operator.EllMatrix`, but
the columns index its *extended* vector

.. math:: \tilde x_d = [\, x_d \;|\; h_{d, s_1} \;|\; h_{d, s_2} \;|\; \dots \,],

its own ``L`` values followed by the halo: for every shift ``s`` (device ``d`` reads
values of device ``d - s``) the values it needs from that device, received by one
``jax.lax.ppermute`` in which every device sends what device ``d + s`` needs of it. Only the
shifts some device needs are exchanged: a partition into contiguous blocks of a
reverse-Cuthill-McKee ordering couples each block to its neighbours, so two ``ppermute``
calls (``s = 1`` and ``s = -1``) of a few hundred values each make the product, whatever
the mesh size. The dot products of CG on vectors sharded so are reduced by XLA across the
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
         data_fields=["diagonal", "slots", "columns", "sends", "repeated_diagonal",
                      "repeated_diagonal_rows"],
         meta_fields=["mesh", "axis", "shifts"])
@dataclasses.dataclass(frozen=True)
class HaloLayout:
    """Where each stored entry of a row-partitioned square matrix goes (indices only).

    ``diagonal[i]``: position in the values of row ``i``'s first diagonal entry (``nnz``,
    a padded zero, where it stores none); ``slots[k, i]`` / ``columns[k, i]``: position and
    *extended local* column of row ``i``'s ``k``-th other entry (a missing one points at
    ``nnz`` and the row's own column); ``sends[j]``: for shift ``shifts[j]``, the local rows
    each device sends (``(D * S_j,)``, device ``d``'s ``S_j`` first). All are sharded over
    ``axis`` of ``mesh`` along their last axis. ``repeated_diagonal`` / ``_rows``: further
    diagonal entries of a row (also in the slots), which
    :func:`~prdp_fem.linalg.operator.diagonal` adds to the first.
    """

    diagonal: jax.Array
    slots: jax.Array
    columns: jax.Array
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
        return HaloMatrix(jax.lax.with_sharding_constraint(values[self.diagonal], vector),
                          jax.lax.with_sharding_constraint(values[self.slots], slotted),
                          self.columns, self.sends, self.mesh, self.axis, self.shifts)


@partial(jax.tree_util.register_dataclass,
         data_fields=["diagonal", "values", "columns", "sends"],
         meta_fields=["mesh", "axis", "shifts"])
@dataclasses.dataclass(frozen=True)
class HaloMatrix:
    """The product kernel of a :class:`HaloLayout`: a diagonal and ELL slots per device."""

    diagonal: jax.Array
    values: jax.Array
    columns: jax.Array
    sends: tuple[jax.Array, ...]
    mesh: Mesh
    axis: str
    shifts: tuple[int, ...]

    @property
    def n_rows(self) -> int:
        return int(self.diagonal.shape[0])

    def __call__(self, x: jax.Array) -> jax.Array:
        return self._sharded(_product)(self.diagonal, self.values, self.columns, self.sends,
                                       jnp.asarray(x))

    def linear_in_values(self, x: jax.Array) -> jax.Array:
        """The same product as one reduction over the slots, whose VJP in the values is a
        gather (see :meth:`~prdp_fem.linalg.operator.EllMatrix.linear_in_values`)."""
        return self._sharded(_product_in_values)(self.diagonal, self.values, self.columns,
                                                 self.sends, jnp.asarray(x))

    def scaled(self, scale: jax.Array) -> HaloMatrix:
        """``S A S`` with ``S = diag(scale)`` (the halo of ``scale`` exchanged once)."""
        values = self._sharded(_scaled_values, out=P(None, self.axis))(
            self.diagonal, self.values, self.columns, self.sends, scale)
        return dataclasses.replace(self, diagonal=self.diagonal * scale * scale,
                                   values=values)

    def _sharded(self, local, out=None):
        axis = self.axis
        exchange = partial(_extended, axis=axis, size=self.mesh.shape[axis],
                           shifts=self.shifts)
        specs = (P(axis), P(None, axis), P(None, axis), tuple(P(axis) for _ in self.sends),
                 P(axis))
        return jax.shard_map(partial(local, exchange=exchange), mesh=self.mesh,
                             in_specs=specs, out_specs=P(axis) if out is None else out)


def _extended(x: jax.Array, sends: tuple[jax.Array, ...], *, axis: str, size: int,
              shifts: tuple[int, ...]) -> jax.Array:
    """This device's values followed by its halo, one ``ppermute`` per shift."""
    received = [jax.lax.ppermute(x[send], axis, [(d, (d + s) % size) for d in range(size)])
                for s, send in zip(shifts, sends, strict=True)]
    return jnp.concatenate([x, *received]) if received else x


def _product(diagonal, values, columns, sends, x, *, exchange):
    extended = exchange(x, sends)
    y = diagonal * x
    for k in range(values.shape[0]):  # one fused loop over the rows, as EllMatrix's
        y = y + values[k] * extended[columns[k]]
    return y


def _product_in_values(diagonal, values, columns, sends, x, *, exchange):
    return diagonal * x + jnp.sum(values * exchange(x, sends)[columns], axis=0)


def _scaled_values(diagonal, values, columns, sends, scale, *, exchange):
    return values * scale * exchange(scale, sends)[columns]


def halo_layout(rows: np.ndarray, cols: np.ndarray, local_rows: int, mesh: Mesh,
                axis: str) -> HaloLayout:
    """The :class:`HaloLayout` of a row-sorted square pattern of ``D * local_rows`` rows,
    device ``d`` of ``mesh``'s ``axis`` owning rows ``[d L, (d + 1) L)`` (host, NumPy)."""
    size = mesh.shape[axis]
    n, nnz = size * local_rows, rows.size
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    row_device, col_device = rows // local_rows, cols // local_rows
    local_cols = cols - col_device * local_rows  # becomes the extended column below
    shifts, sends = [], []
    offset = local_rows
    remote = row_device != col_device
    shift_of = (row_device - col_device) % size
    for shift in range(1, size):
        wanted = remote & (shift_of == shift)
        if not wanted.any():
            continue
        # per receiving device, the sorted columns it reads from device (receiver - shift)
        pairs = np.unique(row_device[wanted] * n + cols[wanted])
        receiver, column = pairs // n, pairs % n
        counts = np.bincount(receiver, minlength=size)
        width = int(counts.max())
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        rank = np.arange(pairs.size) - starts[receiver]
        send = np.zeros((size, width), np.int64)  # padding sends row 0, never read
        send[(receiver - shift) % size, rank] = column % local_rows
        entry = np.flatnonzero(wanted)
        key = row_device[entry] * n + cols[entry]
        local_cols[entry] = offset + rank[np.searchsorted(pairs, key)]
        shifts.append(shift if shift <= size // 2 else shift - size)
        sends.append(send.reshape(-1))
        offset += width
    diagonal, slots, columns, repeated = _ell_slots(rows, cols, local_cols, n, nnz,
                                                    local_rows)
    vector = NamedSharding(mesh, P(axis))
    slotted = NamedSharding(mesh, P(None, axis))
    replicated = NamedSharding(mesh, P())
    as32 = partial(np.asarray, dtype=np.int32)
    return HaloLayout(
        jax.device_put(as32(diagonal), vector), jax.device_put(as32(slots), slotted),
        jax.device_put(as32(columns), slotted),
        tuple(jax.device_put(as32(send), vector) for send in sends),
        jax.device_put(as32(repeated), replicated),
        jax.device_put(as32(rows[repeated]), replicated), mesh, axis, tuple(shifts))


def _ell_slots(rows, cols, local_cols, n: int, nnz: int, local_rows: int):
    """Diagonal positions, slot positions and extended columns of a row-sorted pattern;
    further diagonal entries of a row go to the slots (the product adds them) and are listed
    (for the diagonal)."""
    on_diagonal = rows == cols
    first = np.full(n, nnz, np.int64)
    diagonal_entries = np.flatnonzero(on_diagonal)
    # the first diagonal entry of each row: the last write of a reversed scatter
    first[rows[diagonal_entries[::-1]]] = diagonal_entries[::-1]
    is_first = np.zeros(nnz, bool)
    is_first[first[first < nnz]] = True
    others = np.flatnonzero(~is_first)
    counts = np.bincount(rows[others], minlength=n)
    width = int(counts.max(initial=0))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(others.size) - starts[rows[others]]
    own = np.arange(n) % local_rows
    slots = np.full((width, n), nnz, np.int64)
    columns = np.broadcast_to(own, (width, n)).copy()
    slots[rank, rows[others]] = others
    columns[rank, rows[others]] = local_cols[others]
    repeated = others[on_diagonal[others]]
    return first, slots, columns, repeated
