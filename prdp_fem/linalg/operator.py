"""Sparse matrices as JAX pytrees: row-sorted COO (BCOO-compatible), with one kernel choice.

A :class:`SparseMatrix` holds integer ``rows``/``cols`` and float ``values`` as pytree leaves and
its ``shape`` as static metadata, so it is passed *as an argument* to jitted code (never closed
over: a closed-over sparse matrix is constant-folded slowly) and is differentiable in ``values``.

.. math:: (A x)_i = \\sum_{k:\\, \\mathrm{row}_k = i} \\mathrm{values}_k \\, x_{\\mathrm{col}_k}

Products go through :func:`prepare`, the one place where the kernel is chosen: it turns the
exchange format into a kernel pytree whose ``__call__`` is the product. Loops that apply the
same matrix many times (CG) prepare it once and call the kernel; :func:`matvec` prepares and
applies in one go.

Kernels
-------
``EllMatrix`` (square matrices built by :meth:`SparseMatrix.from_coo` / :meth:`from_scipy`,
which attach an :class:`EllLayout`, and any matrix given one by
:meth:`SparseMatrix.with_layout`): the diagonal as a vector (square matrices) and the other entries
in slot-major ELLPACK form ``(w, n)`` (row ``i`` of slot ``k`` holds its ``k``-th off-diagonal
entry), so that

.. math:: (A x)_i = d_i x_i + \\sum_{k < w} V_{ki}\\, x_{C_{ki}}

is one fused loop of ``w`` contiguous gathers, multiplies and adds -- no scatter, no
segment sum, and the diagonal needs no gather. Rows longer than ``w`` keep their extra
entries in a short COO tail (``w`` minimises the padded work, see :func:`ell_layout`).
``prdp-fem bench cg`` (``docs/benchmarks.md``) measures it against one SciPy CSR SpMV of the
2-D P1 Laplacian: faster than the SpMV from tens of thousands of unknowns, where the sorted
segment sum it replaced was slower (XLA runs the fused loop on every core). ELL slot-major is
also the coalesced layout on GPUs, where a whole Jacobi-PCG iteration with it costs about one
cuSPARSE CSR SpMV, so :func:`default_kernel` is ELL on every backend.

``CsrMatrix`` (``kernel="csr"``): ``jax.experimental.sparse.csr_matvec``, cuSPARSE's SpMV on
NVIDIA GPUs, for comparisons (no ``vmap``).

``CooMatrix`` (no layout: rectangular matrices by default, a matrix built inside ``jit`` from
traced indices, or by the constructor): gather, multiply, sorted segment sum.

>>> import numpy as np, scipy.sparse as sp
>>> from prdp_fem.linalg.operator import SparseMatrix, matvec
>>> A = SparseMatrix.from_scipy(sp.csr_matrix(np.array([[2.0, -1.0], [-1.0, 2.0]])))
>>> np.asarray(matvec(A, np.array([1.0, 1.0]))).tolist()
[1.0, 1.0]
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jax.experimental import sparse as jsparse

from .._sorting import first_of_each
from ..errors import ShapeError
from ._products import paired_product, symmetric_product
from .halo import HaloLayout

__all__ = ["KERNELS", "CooMatrix", "CsrMatrix", "EllLayout", "EllMatrix", "FixedMatrix",
           "SparseMatrix", "default_kernel", "diagonal", "ell_layout", "host_prepared", "matvec",
           "prepare", "prepare_on_host", "rmatvec", "symmetric_matvec"]

# the product kernels prepare() can build (see the module docstring)
KERNELS = ("ell", "coo", "csr")

# a COO-tail entry costs about this many ELL slots (a scatter-add against a streamed gather)
_OVERFLOW_COST = 4
# wider rows are applied in a loop over chunks of this many slots: an unrolled fusion of
# hundreds of gathers (the coarse levels of a 3-D AMG hierarchy) took 9-17 s to compile
_UNROLLED_SLOTS = 32
# layouts up to this width are filled slot by slot, wider ones by a scatter of their entries
_LOOPED_SLOTS = 64


@partial(jax.tree_util.register_dataclass,
         data_fields=["diagonal", "slots", "columns", "overflow_slots", "overflow_rows",
                      "overflow_columns", "repeated_diagonal", "repeated_diagonal_rows"],
         meta_fields=[])
@dataclasses.dataclass(frozen=True)
class EllLayout:
    """Where each stored entry of a square matrix goes in the ELL kernel (indices only).

    ``diagonal[i]``: the position in ``values`` of row ``i``'s (first) diagonal entry;
    ``slots[k, i]`` / ``columns[k, i]``: position and column of row ``i``'s ``k``-th other
    entry; ``overflow_*``: entries past slot ``w``. A missing entry points at ``nnz`` (a zero
    appended to the values) with its own row as column, so padding adds ``0 * x_i``.
    ``repeated_diagonal`` / ``_rows``: positions and rows of further diagonal entries of a row
    (duplicates; usually none), which :func:`diagonal` adds to the first.
    """

    diagonal: jax.Array
    slots: jax.Array
    columns: jax.Array
    overflow_slots: jax.Array
    overflow_rows: jax.Array
    overflow_columns: jax.Array
    repeated_diagonal: jax.Array
    repeated_diagonal_rows: jax.Array


def ell_layout(rows: np.ndarray, cols: np.ndarray, n: int,
               n_cols: int | None = None) -> EllLayout:
    """The ELL layout of an ``n x n_cols`` pattern whose ``rows`` are sorted (host, NumPy).

    Square patterns (``n_cols`` is ``None`` or ``n``) keep the diagonal apart; rectangular ones
    (AMG transfer operators) have none (``diagonal`` is empty). Duplicates are kept as separate
    entries (they add up in the product). The width ``w`` minimises ``n w + 4 * (entries past
    slot w)`` (plus ``n`` when any spill, for the tail's pass), so one long row does not pad
    every row to its length. Padding points at row ``i``'s own column ``min(i, n_cols - 1)``.
    """
    return jax.device_put(_host_ell_layout(rows, cols, n, n_cols))


def _host_ell_layout(rows: np.ndarray, cols: np.ndarray, n: int,
                     n_cols: int | None = None) -> EllLayout:
    """:func:`ell_layout` with NumPy ``int32`` arrays, for a caller that puts the layout (or
    the kernel it prepares) on the device in one call.

    Built slot by slot from each row's first entry (rows are sorted, so row ``i``'s ``k``-th
    entry sits at ``start[i] + k``): ``w`` passes over ``n`` rows instead of a scatter of all
    ``nnz`` entries into the ``(w, n)`` arrays. The scatter and its ``nnz``-long temporaries
    were most of a large matrix's layout time, much of it first touches of fresh memory.
    """
    if max(np.size(rows), n, n_cols or 0) >= np.iinfo(np.int32).max:
        raise ShapeError(f"ell_layout: {np.size(rows)} entries in a {n} x {n_cols or n} "
                         "pattern; the layout's int32 indices hold fewer than 2**31 - 1")
    rows, cols = np.asarray(rows, dtype=np.int32), np.asarray(cols, dtype=np.int32)
    if np.any(rows[1:] < rows[:-1]):  # slots and first diagonal entries count along rows
        raise ShapeError("ell_layout: rows are not sorted; expected a row-sorted pattern "
                         "(SparseMatrix.from_coo and from_scipy sort it)")
    nnz = rows.size
    square = n_cols is None or n_cols == n
    n_cols = n if n_cols is None else n_cols
    counts = np.bincount(rows, minlength=n)  # entries per row, then those not on the diagonal
    diagonal, others, repeated = _diagonal_apart(rows, cols, n, nnz, counts, square)
    starts = (np.cumsum(counts) - counts).astype(np.int32)
    width = _ell_width(counts)
    if width > _UNROLLED_SLOTS:  # whole chunks for the kernel's loop (padding adds zeros)
        width = -(-width // _UNROLLED_SLOTS) * _UNROLLED_SLOTS
    own_column = np.minimum(np.arange(n, dtype=np.int32), max(n_cols - 1, 0))
    fill = _fill_by_slot if width <= _LOOPED_SLOTS else _fill_by_entry
    slots, columns = fill(counts, starts, others, cols, own_column, width, nnz)
    spill_rows, spilled = _spilled(counts, starts, width)
    if others is not None:
        spilled = others[spilled]
    return EllLayout(diagonal, slots, columns, spilled, spill_rows, cols[spilled], repeated,
                     rows[repeated])


def _fill_by_slot(counts, starts, others, cols, own_column, width: int, nnz: int):
    """The ``(w, n)`` positions and columns, one pass over the rows per slot."""
    n = counts.size
    slots = np.full((width, n), nnz, dtype=np.int32)
    columns = np.empty((width, n), dtype=np.int32)
    every_row = int(counts.min()) if n else 0  # slots below this are all full
    for k in range(width):
        present = slice(None) if k < every_row else np.flatnonzero(counts > k)
        position = starts[present] + k
        if others is not None:
            position = others[position]
        slots[k, present] = position
        if k >= every_row:
            columns[k] = own_column
        columns[k, present] = cols[position]
    return slots, columns


def _fill_by_entry(counts, starts, others, cols, own_column, width: int, nnz: int):
    """The same arrays by one scatter of the entries: for wide layouts (a few long rows, a
    coarse AMG level), where a Python pass per slot would cost more than the scatter."""
    n = counts.size
    row = np.repeat(np.arange(n, dtype=np.int32), counts)
    slot = np.arange(row.size, dtype=np.int32) - np.repeat(starts, counts)
    inside = slot < width
    position = np.flatnonzero(inside).astype(np.int32)
    if others is not None:
        position = others[position]
    slots = np.full((width, n), nnz, dtype=np.int32)
    columns = np.tile(own_column, (width, 1))
    slots[slot[inside], row[inside]] = position
    columns[slot[inside], row[inside]] = cols[position]
    return slots, columns


def _diagonal_apart(rows: np.ndarray, cols: np.ndarray, n: int, nnz: int, counts: np.ndarray,
                    square: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """The diagonal positions (``nnz`` where a row has none), the positions of the other
    entries (``None``: all of them) and those of repeated diagonal entries; ``counts`` loses
    the diagonal in place."""
    empty = np.zeros(0, dtype=np.int32)
    if not square:
        return empty, None, empty
    on_diagonal = np.flatnonzero(rows == cols).astype(np.int32)
    first = first_of_each(rows[on_diagonal])
    kept = on_diagonal[first]
    diagonal = np.full(n, nnz, dtype=np.int32)
    diagonal[rows[kept]] = kept
    counts[rows[kept]] -= 1
    others = np.delete(np.arange(nnz, dtype=np.int32), kept) if kept.size else None
    return diagonal, others, on_diagonal[~first]


def _spilled(counts: np.ndarray, starts: np.ndarray,
             width: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and (other-entry) indices of the entries past slot ``width``, in row order."""
    extra = np.maximum(counts - width, 0)
    long_rows = np.flatnonzero(extra).astype(np.int32)
    extra = extra[long_rows]
    spill_rows = np.repeat(long_rows, extra)
    within = np.arange(spill_rows.size, dtype=np.int32) - np.repeat(
        (np.cumsum(extra) - extra).astype(np.int32), extra)
    return spill_rows, starts[spill_rows] + width + within


def _ell_width(counts: np.ndarray) -> int:
    """The width ``w`` minimising ``n w + 4 spilled(w) + n [spilled(w) > 0]``."""
    if counts.size == 0 or counts.max() == 0:
        return 0
    # spilled(w) = sum over rows with c > w of (c - w), for every w at once from the histogram
    histogram = np.bincount(counts)
    lengths = np.arange(histogram.size)
    rows_longer = np.cumsum(histogram[::-1])[::-1] - histogram  # rows with c > w
    entries_longer = np.cumsum((histogram * lengths)[::-1])[::-1] - histogram * lengths
    spilled = entries_longer - lengths * rows_longer
    cost = counts.size * lengths + _OVERFLOW_COST * spilled + counts.size * (spilled > 0)
    return int(np.argmin(cost))


@partial(jax.tree_util.register_dataclass, data_fields=["rows", "cols", "values", "layout"],
         meta_fields=["shape", "kernel"])
@dataclasses.dataclass(frozen=True)
class SparseMatrix:
    """COO matrix with entries sorted by row (duplicates allowed; they add up).

    The constructor trusts its input (it runs inside jit); build from unsorted data with
    :meth:`from_coo`, :meth:`from_scipy` or :meth:`from_bcoo`, which sort and attach the ELL
    layout of square matrices (:meth:`with_values` keeps it).

    Attributes
    ----------
    rows, cols
        Integer index arrays of length ``nnz``; ``rows`` is non-decreasing.
    values
        Float array of length ``nnz`` (the differentiable part).
    shape
        ``(n_rows, n_cols)``, static.
    layout
        :class:`EllLayout` of the pattern, a :class:`~prdp_fem.linalg.sharding.Partition`
        over the devices of a mesh (:func:`~prdp_fem.linalg.sharding.shard`), or ``None``
        (the COO kernel is used).
    kernel
        ``None`` (:func:`prepare` chooses by backend) or one of :data:`KERNELS`, static:
        benchmarks compare kernels with it (:meth:`with_kernel`).
    """

    rows: jax.Array
    cols: jax.Array
    values: jax.Array
    shape: tuple[int, int]
    layout: Any = None
    kernel: str | None = None

    @property
    def nnz(self) -> int:
        return int(self.values.shape[-1])

    def with_values(self, values: jax.Array) -> SparseMatrix:
        """Same sparsity pattern (and layout), new values (e.g. ``G @ kappa``)."""
        return dataclasses.replace(self, values=values)

    def with_layout(self) -> SparseMatrix:
        """The same matrix with its ELL layout attached (needs concrete, row-sorted indices).

        The constructors attach it to square matrices (operators, applied many times); a
        rectangular one applied many times (an AMG transfer operator) asks for it here. A
        constant one that is also differentiated through (the assembly map ``G``) is a
        :class:`FixedMatrix`: with a layout alone, the backward pass of each ELL slot's gather
        would be a scatter.
        """
        return dataclasses.replace(self, layout=ell_layout(
            np.asarray(self.rows), np.asarray(self.cols), *self.shape))

    def with_kernel(self, kernel: str | None) -> SparseMatrix:
        """The same matrix, applied by ``kernel`` (one of :data:`KERNELS`; ``None``: chosen by
        backend). ``"ell"`` needs a layout."""
        if kernel is not None and kernel not in KERNELS:
            raise ValueError(f"kernel={kernel!r}: expected None or one of {KERNELS}")
        if kernel == "ell" and self.layout is None:
            raise ValueError("kernel='ell' needs an ELL layout: build the matrix with "
                             "from_scipy / from_coo, or call with_layout() first")
        return dataclasses.replace(self, kernel=kernel)

    def _with_square_layout(self) -> SparseMatrix:
        return self.with_layout() if self.shape[0] == self.shape[1] else self

    def astype(self, dtype) -> SparseMatrix:
        """The values in another precision (``solve`` then runs in it: e.g. float32, whose
        limits -- rtol >= ~1e-5, errors ~ cond * 1e-7 -- the stability suite states)."""
        return self.with_values(self.values.astype(dtype))

    @classmethod
    def from_coo(cls, rows, cols, values, shape: tuple[int, int]) -> SparseMatrix:
        """From COO arrays in any order (sorted by row here; the constructor assumes it).

        Indices must lie in ``shape``: the products gather without wrapping negative ones.
        """
        rows, cols = np.asarray(rows), np.asarray(cols)
        for name, index, size in (("rows", rows, shape[0]), ("cols", cols, shape[1])):
            if index.size and not (0 <= index.min() and index.max() < size):
                raise ShapeError(f"from_coo: {name} range from {index.min()} to {index.max()}; "
                                 f"expected indices from 0 to {size - 1} (shape {tuple(shape)})")
        order = np.lexsort((cols, rows))
        return cls(jnp.asarray(rows[order], dtype=jnp.int32),
                   jnp.asarray(cols[order], dtype=jnp.int32),
                   jnp.asarray(values, dtype=float)[order],
                   (int(shape[0]), int(shape[1])))._with_square_layout()

    @classmethod
    def from_scipy(cls, matrix: sp.spmatrix | sp.sparray,
                   layout: bool | None = None) -> SparseMatrix:
        """From SciPy; ``layout``: attach the ELL layout (``None``: to square matrices only).

        Everything is read on the host, so this also works while JAX traces a function.
        ``jax.device_put`` copies the arrays, where ``jnp.asarray`` compiled a conversion per
        shape and dtype (28 compiles, 0.25 s, to build one small linear system)."""
        return jax.device_put(_numpy_matrix(matrix, layout))

    def to_scipy(self) -> sp.csr_matrix:
        return sp.csr_matrix(
            (np.asarray(self.values), (np.asarray(self.rows), np.asarray(self.cols))),
            shape=self.shape)

    def to_bcoo(self) -> jsparse.BCOO:
        indices = jnp.stack([self.rows, self.cols], axis=-1)
        return jsparse.BCOO((self.values, indices), shape=self.shape,
                            indices_sorted=True, unique_indices=False)

    @classmethod
    def from_bcoo(cls, matrix: jsparse.BCOO) -> SparseMatrix:
        """From BCOO; entries at out-of-range indices are BCOO's padding and are dropped
        (``todense`` ignores them too)."""
        indices = np.asarray(matrix.indices)
        kept = (indices[:, 0] < matrix.shape[0]) & (indices[:, 1] < matrix.shape[1])
        return cls.from_coo(indices[kept, 0], indices[kept, 1], np.asarray(matrix.data)[kept],
                            matrix.shape)

    def todense(self) -> jax.Array:
        return jnp.zeros(self.shape, self.values.dtype).at[self.rows, self.cols].add(self.values)


# --------------------------------------------------------------------------------------
# kernels: prepared once, applied many times
# --------------------------------------------------------------------------------------


@partial(jax.tree_util.register_dataclass,
         data_fields=["diagonal", "values", "columns", "overflow_values", "overflow_rows",
                      "overflow_columns"], meta_fields=["n_rows"])
@dataclasses.dataclass(frozen=True)
class EllMatrix:
    """A diagonal (square matrices; else empty) plus slot-major ELL entries (see module)."""

    diagonal: jax.Array
    values: jax.Array
    columns: jax.Array
    overflow_values: jax.Array
    overflow_rows: jax.Array
    overflow_columns: jax.Array
    n_rows: int

    def __call__(self, x: jax.Array) -> jax.Array:
        x = jnp.asarray(x)
        if self.diagonal.shape[0]:
            y = self.diagonal * x
        else:
            y = jnp.zeros(self.n_rows, jnp.result_type(self.values, x))
        width = self.values.shape[0]
        if width <= _UNROLLED_SLOTS:
            y = _add_slots(y, self.values, self.columns, x)  # one fused loop over the rows
        else:  # wide rows (coarse AMG levels): a loop over chunks, not one huge fusion
            def add_chunk(chunk, y):
                start = chunk * _UNROLLED_SLOTS
                take = partial(jax.lax.dynamic_slice_in_dim, start_index=start,
                               slice_size=_UNROLLED_SLOTS)
                return _add_slots(y, take(self.values), take(self.columns), x)

            y = jax.lax.fori_loop(0, width // _UNROLLED_SLOTS, add_chunk, y)
        return self._add_overflow(y, x)

    def linear_in_values(self, x: jax.Array) -> jax.Array:
        """The same product with the slots summed in one reduction: the form reverse mode
        transposes in the values (:mod:`prdp_fem.linalg._products`).

        Its VJP there is one gather, ``values_bar = y_bar[None, :] * x[columns]``. The
        per-slot loop of ``__call__`` (one fused pass in the forward direction) transposes
        into a pad and an add of the whole ``(w, n)`` array per slot: on the inclusion
        scene's 4k P2 dofs (w = 16) that made an unrolled iteration's reverse sweep 7x its
        forward step.
        """
        x = jnp.asarray(x)
        y = jnp.sum(self.values * _gather(x, self.columns), axis=0)
        if self.diagonal.shape[0]:
            y = y + self.diagonal * x
        return self._add_overflow(y, x)

    def _add_overflow(self, y: jax.Array, x: jax.Array) -> jax.Array:
        if self.overflow_rows.shape[0]:
            y = y.at[self.overflow_rows].add(  # rows are never negative: see _gather
                self.overflow_values * _gather(x, self.overflow_columns),
                wrap_negative_indices=False)
        return y

    def scaled(self, scale: jax.Array) -> EllMatrix:
        """``S A S`` with ``S = diag(scale)``."""
        return dataclasses.replace(
            self, diagonal=self.diagonal * scale * scale,
            values=self.values * scale * scale[self.columns],
            overflow_values=self.overflow_values * scale[self.overflow_rows]
            * scale[self.overflow_columns])


def _add_slots(y: jax.Array, values: jax.Array, columns: jax.Array, x: jax.Array) -> jax.Array:
    for k in range(values.shape[0]):
        y = y + values[k] * _gather(x, columns[k])
    return y


def _gather(x: jax.Array, index: jax.Array) -> jax.Array:
    """``x[index]`` for a layout's indices, which are never negative.

    ``x[index]`` also wraps negative indices: a ``select`` on the index array. Inside a
    while loop the select is loop-invariant, so XLA hoists it out as a kernel of its own,
    one per ELL slot: 145 extra kernels for an AMG V-cycle in CG's loop, which compiled 2.3x
    slower than the cycle alone. Out-of-range indices still clamp (gather's semantics).

    Bound as the ``gather`` that ``x.at[index].get(wrap_negative_indices=False)`` binds,
    without NumPy indexing's parsing of the index: a product traces one gather per slot, in
    its abstract evaluation, its lowering and each derivative, and the parsing was most of
    it.
    """
    return jax.lax.gather(jnp.asarray(x), jax.lax.broadcast_in_dim(index, (*index.shape, 1),
                                                                   tuple(range(index.ndim))),
                          _ELEMENTS, (1,), mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS)


# gather single elements of a vector (x[index] for an index array of any shape)
_ELEMENTS = jax.lax.GatherDimensionNumbers(offset_dims=(), collapsed_slice_dims=(0,),
                                           start_index_map=(0,))


@partial(jax.tree_util.register_dataclass, data_fields=["rows", "cols", "values"],
         meta_fields=["n_rows"])
@dataclasses.dataclass(frozen=True)
class CooMatrix:
    """Row-sorted COO: gather, multiply, sorted segment sum."""

    rows: jax.Array
    cols: jax.Array
    values: jax.Array
    n_rows: int

    def __call__(self, x: jax.Array) -> jax.Array:
        return jax.ops.segment_sum(self.values * _gather(x, self.cols), self.rows,
                                   num_segments=self.n_rows, indices_are_sorted=True)

    def linear_in_values(self, x: jax.Array) -> jax.Array:
        """The product (its VJP in the values is already one gather)."""
        return self(x)

    def scaled(self, scale: jax.Array) -> CooMatrix:
        """``S A S`` with ``S = diag(scale)`` (square matrices)."""
        return dataclasses.replace(self, values=self.values * scale[self.rows]
                                   * scale[self.cols])


@partial(jax.tree_util.register_dataclass, data_fields=["rows", "cols", "indptr", "values"],
         meta_fields=["shape"])
@dataclasses.dataclass(frozen=True)
class CsrMatrix:
    """Row-sorted CSR through ``jax.experimental.sparse.csr_matvec``: cuSPARSE's SpMV on
    NVIDIA GPUs (the vendor path), a segment sum elsewhere. JAX gives the call no batching
    rule, so it does not ``vmap``: it is a benchmark's comparison, never the default."""

    rows: jax.Array  # for scaled()
    cols: jax.Array
    indptr: jax.Array
    values: jax.Array
    shape: tuple[int, int]

    def __call__(self, x: jax.Array) -> jax.Array:
        csr = jsparse.CSR((self.values, self.cols, self.indptr), shape=self.shape)
        return jsparse.csr_matvec(csr, jnp.asarray(x, self.values.dtype))

    def linear_in_values(self, x: jax.Array) -> jax.Array:
        """The product (JAX's own rules transpose it in the values)."""
        return self(x)

    def scaled(self, scale: jax.Array) -> CsrMatrix:
        """``S A S`` with ``S = diag(scale)`` (square matrices)."""
        return dataclasses.replace(self, values=self.values * scale[self.rows]
                                   * scale[self.cols])


def default_kernel(backend: str | None = None) -> str:
    """The kernel of a matrix with an ELL layout on ``backend`` (default: JAX's default).

    ELL on CPU (one fused gather loop; measured against COO in ``prdp-fem bench cg``) and on
    GPU (coalesced slot-major loads; measured against cuSPARSE's CSR SpMV and the COO
    segment sum on an H100, see the README's Performance section).
    """
    backend = jax.default_backend() if backend is None else backend
    return {"cpu": "ell"}.get(backend, "ell")


def prepare(matrix: SparseMatrix) -> EllMatrix | CooMatrix | CsrMatrix:
    """The product kernel of ``matrix``: the one place where the kernel is chosen.

    ``matrix.kernel`` when set; else :func:`default_kernel` of the backend when the matrix
    carries a layout, and COO when it does not. Differentiable in the values (a gather of
    them); prepare once per solve, not per product.
    """
    if matrix.layout is not None and not isinstance(matrix.layout, EllLayout):
        # a layout over the devices of a mesh (prdp_fem.linalg.sharding) has its own kernel
        return matrix.layout.prepare(matrix.values)
    kernel = matrix.kernel
    if kernel is None:
        kernel = "coo" if matrix.layout is None else default_kernel()
    if kernel == "coo" or (kernel == "ell" and matrix.layout is None):
        return CooMatrix(matrix.rows, matrix.cols, matrix.values, matrix.shape[0])
    if kernel == "csr":
        indptr = jnp.searchsorted(matrix.rows, jnp.arange(matrix.shape[0] + 1),
                                  side="left").astype(matrix.rows.dtype)
        return CsrMatrix(matrix.rows, matrix.cols, indptr, matrix.values, matrix.shape)
    layout = matrix.layout
    padded = _padded(matrix.values)
    return EllMatrix(padded[layout.diagonal], padded[layout.slots], layout.columns,
                     padded[layout.overflow_slots], layout.overflow_rows,
                     layout.overflow_columns, matrix.shape[0])


def _padded(values: jax.Array) -> jax.Array:
    """The values with the zero that a layout's missing entries point at (position nnz);
    NumPy values stay NumPy (a kernel prepared on the host)."""
    xp = np if isinstance(values, np.ndarray) else jnp
    return xp.concatenate([values, xp.zeros((1,), values.dtype)])


@partial(jax.tree_util.register_dataclass, data_fields=["forward", "transpose"],
         meta_fields=["shape"])
@dataclasses.dataclass(frozen=True)
class FixedMatrix:
    r"""A constant matrix, prepared once for ``A x`` and, in reverse mode, ``A^T y``.

    :func:`matvec` prepares a :class:`SparseMatrix` per call, and JAX transposes the kernel's
    gathers into scatter-adds. A matrix that never changes within a problem (the assembly map
    ``G``, the lifting and source maps of :class:`~prdp_fem.fem.system.LinearSystem`) is instead
    laid out here both ways on the host, and its product goes through
    :func:`~prdp_fem.linalg._products.paired_product`: the transpose is the second kernel, a gather
    loop too. Both kernels are chosen by :func:`prepare`. The values stay differentiable (as
    pytree leaves), but a tangent of them must keep the pair consistent: build a new one with
    :meth:`from_scipy` for other values.

    >>> import numpy as np, scipy.sparse as sp, jax
    >>> G = FixedMatrix.from_scipy(sp.csr_matrix(np.array([[1.0, 0.0], [2.0, 3.0], [0.0, 4.0]])))
    >>> y = np.array([1.0, 1.0, 1.0])
    >>> jax.vjp(G, np.zeros(2))[1](y)[0].tolist(), G.T(y).tolist()
    ([3.0, 7.0], [3.0, 7.0])
    """

    forward: EllMatrix | CooMatrix | CsrMatrix
    transpose: EllMatrix | CooMatrix | CsrMatrix | None  # None: symmetric (the forward one)
    shape: tuple[int, int]

    def __call__(self, x: jax.Array) -> jax.Array:
        return paired_product(self.forward, self.transpose, x)

    @property
    def T(self) -> FixedMatrix:  # the matrix transpose, as in NumPy
        if self.transpose is None:
            return self
        return FixedMatrix(self.transpose, self.forward, self.shape[::-1])

    @classmethod
    def symmetric(cls, matrix: sp.spmatrix | sp.sparray) -> FixedMatrix:
        """A constant *symmetric* matrix (a mass, Gram or misfit weight matrix) laid out once
        on the host, one kernel for both directions
        (:func:`~prdp_fem.linalg._products.symmetric_product`).

        A :class:`SparseMatrix` through :func:`symmetric_matvec` lays its values out in every
        product's program: at 66k unknowns, 0.8 ms for each 460k-value matrix per evaluation
        of the mother problem's loss.

        >>> import numpy as np, scipy.sparse as sp
        >>> M = FixedMatrix.symmetric(sp.csr_matrix(np.array([[2.0, 1.0], [1.0, 3.0]])))
        >>> M(np.array([1.0, 1.0])).tolist(), M.T is M
        ([3.0, 4.0], True)
        """
        csr = sp.csr_matrix(matrix)
        if csr.shape[0] != csr.shape[1]:
            raise ShapeError(f"FixedMatrix.symmetric: a {csr.shape[0]} x {csr.shape[1]} "
                             "matrix; expected a square one")
        asymmetry = abs(csr - csr.T).max() if csr.nnz else 0.0
        if csr.nnz and asymmetry > 1e-12 * abs(csr).max():  # beyond an assembly's round-off
            raise ShapeError(f"FixedMatrix.symmetric: the matrix is not symmetric (|A - A^T| "
                             f"up to {asymmetry:.3g}); expected A = A^T, or "
                             "FixedMatrix.from_scipy for a general one")
        return cls(jax.device_put(host_prepared(csr)), None, tuple(int(s) for s in csr.shape))

    @classmethod
    def from_scipy(cls, matrix: sp.spmatrix | sp.sparray) -> FixedMatrix:
        """Lay out ``matrix`` and its transpose (on the host)."""
        csr = sp.csr_matrix(matrix)
        # prepared in NumPy: as eager JAX ops they compiled each gather and concatenation
        forward, transpose = jax.device_put((host_prepared(csr), host_prepared(csr.T)))
        return cls(forward, transpose, tuple(int(s) for s in csr.shape))

    @classmethod
    def column(cls, values: np.ndarray) -> FixedMatrix:
        """The ``n x 1`` matrix ``values`` (``x -> values * x[0]``; host values). Its
        transpose is one row of ``n`` entries: a COO sum, where an ELL layout would be one
        row ``n`` slots wide."""
        values = np.asarray(values, dtype=np.float64)
        column = sp.csr_matrix((values, (np.arange(values.size), np.zeros(values.size, int))),
                               shape=(values.size, 1))
        forward, transpose = jax.device_put(
            (host_prepared(column), prepare(_numpy_matrix(column.T, layout=False))))
        return cls(forward, transpose, (values.size, 1))

    def to_scipy(self) -> sp.csr_matrix:
        """The matrix as SciPy CSR, read back from the forward kernel (host; the layout's
        padding and any stored zeros are dropped)."""
        return _kernel_entries(self.forward, self.shape)


def prepare_on_host(matrix: SparseMatrix) -> EllMatrix | CooMatrix | CsrMatrix:
    """:func:`prepare` run in NumPy on the host, then put on the device: for a matrix that
    stays constant (no JAX op to compile or dispatch per gather; concrete values only)."""
    return jax.device_put(prepare(jax.tree_util.tree_map(np.asarray, matrix)))


def host_prepared(matrix: sp.spmatrix | sp.sparray) -> EllMatrix | CooMatrix | CsrMatrix:
    """The product kernel of a constant SciPy matrix with its ELL layout (any shape), laid out
    and prepared in NumPy: NumPy leaves, for the caller to put on the device with the rest of
    its arrays in one ``jax.device_put`` (an AMG hierarchy, a :class:`FixedMatrix` pair).
    ``prepare_on_host(SparseMatrix.from_scipy(matrix, layout=True))`` without the round trip
    through the device: 17 transfers per matrix were a third of the JAX side of an AMG
    rebuild, and one per matrix still a tenth of it."""
    return prepare(_numpy_matrix(matrix, layout=True))


def _numpy_matrix(matrix: sp.spmatrix | sp.sparray, layout: bool | None) -> SparseMatrix:
    """:meth:`SparseMatrix.from_scipy` with NumPy leaves (see there)."""
    csr = sp.csr_matrix(matrix)
    csr.sum_duplicates()
    coo = csr.tocoo()  # from a canonical CSR: sorted by row, then column
    shape = tuple(int(s) for s in csr.shape)
    if layout is None:
        layout = shape[0] == shape[1]
    return SparseMatrix(coo.row.astype(np.int32), coo.col.astype(np.int32),
                        coo.data.astype(np.float64), shape,
                        _host_ell_layout(coo.row, coo.col, *shape) if layout else None)


def _kernel_entries(kernel, shape: tuple[int, int]) -> sp.csr_matrix:
    """The entries a product kernel applies, as SciPy CSR (duplicates summed, zeros dropped)."""
    if isinstance(kernel, EllMatrix):
        width, n = kernel.values.shape
        diagonal = np.arange(kernel.diagonal.shape[0])
        rows = [diagonal, np.tile(np.arange(n), width), np.asarray(kernel.overflow_rows)]
        cols = [diagonal, np.asarray(kernel.columns).ravel(),
                np.asarray(kernel.overflow_columns)]
        values = [np.asarray(kernel.diagonal), np.asarray(kernel.values).ravel(),
                  np.asarray(kernel.overflow_values)]
    else:  # COO and CSR keep their row-sorted triplets
        rows, cols, values = [kernel.rows], [kernel.cols], [kernel.values]
    matrix = sp.csr_matrix((np.concatenate([np.asarray(v) for v in values]),
                            (np.concatenate([np.asarray(r) for r in rows]),
                             np.concatenate([np.asarray(c) for c in cols]))), shape=shape)
    matrix.sum_duplicates()
    matrix.eliminate_zeros()
    return matrix


def matvec(matrix: SparseMatrix | FixedMatrix, x: jax.Array) -> jax.Array:
    """``A @ x`` (differentiable in values and x; a :class:`FixedMatrix` is its product)."""
    if isinstance(matrix, FixedMatrix):
        return matrix(x)
    return prepare(matrix)(x)


def symmetric_matvec(matrix: SparseMatrix | FixedMatrix, x: jax.Array) -> jax.Array:
    """``A @ x`` for a *symmetric* ``A`` (a mass, Gram or misfit weight matrix): reverse mode
    transposes it as the product itself (:func:`~prdp_fem.linalg._products.symmetric_product`), not
    as a scatter-add per ELL slot. The gradient of ``1/2 r^T W r`` at 4225 dofs compiled to
    18 scatters this way removes (inclusion scene). Wrong for a non-symmetric ``A``. A
    :class:`FixedMatrix` is its own product (laid out once: :meth:`FixedMatrix.symmetric`)."""
    if isinstance(matrix, FixedMatrix):
        return matrix(x)
    return symmetric_product(prepare(matrix), x)


def rmatvec(matrix: SparseMatrix, y: jax.Array) -> jax.Array:
    """``A.T @ y``."""
    return jax.ops.segment_sum(matrix.values * y[matrix.rows], matrix.cols,
                               num_segments=matrix.shape[1])


def diagonal(matrix: SparseMatrix) -> jax.Array:
    """Main diagonal (zero where a row stores no diagonal entry; duplicates add up).

    With a square layout it is a gather of the stored positions (plus any repeated diagonal
    entries); without, a segment sum over all entries, which cost 10 % of an implicit-mode
    gradient at K = 0 on the inclusion scene (the Jacobi preconditioner of every solve).
    """
    layout = matrix.layout
    if isinstance(layout, EllLayout | HaloLayout) and layout.diagonal.shape[0] == matrix.shape[0]:
        d = _padded(matrix.values)[layout.diagonal]
        if layout.repeated_diagonal.shape[0]:
            d = d.at[layout.repeated_diagonal_rows].add(matrix.values[layout.repeated_diagonal])
        return d
    on_diagonal = matrix.rows == matrix.cols
    return jax.ops.segment_sum(jnp.where(on_diagonal, matrix.values, 0.0), matrix.rows,
                               num_segments=matrix.shape[0], indices_are_sorted=True)
