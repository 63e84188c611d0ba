"""SparseMatrix: products against SciPy, conversions, and use as a jit argument."""

import dataclasses

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

import prdp_fem as pf
from prdp_fem import linalg


@pytest.fixture
def random_spd():
    rng = np.random.default_rng(1)
    a = sp.random(40, 40, density=0.1, random_state=rng)
    return (a @ a.T + 40 * sp.eye(40)).tocsr()


def test_matvec_rmatvec_diagonal_match_scipy(random_spd):
    rect = sp.random(30, 20, density=0.2, random_state=np.random.default_rng(2)).tocsr()
    x = np.random.default_rng(3).normal(size=40)
    A = pf.SparseMatrix.from_scipy(random_spd)
    np.testing.assert_allclose(linalg.matvec(A, x), random_spd @ x, rtol=1e-13)
    np.testing.assert_allclose(linalg.diagonal(A), random_spd.diagonal(), rtol=1e-14)
    R = pf.SparseMatrix.from_scipy(rect)
    y = np.arange(30.0)
    np.testing.assert_allclose(linalg.rmatvec(R, y), rect.T @ y, rtol=1e-13)
    np.testing.assert_allclose(linalg.matvec(R, np.ones(20)), rect @ np.ones(20), rtol=1e-13)


def test_diagonal_from_the_layout_adds_repeated_entries_and_missing_ones_are_zero():
    # duplicates on the diagonal (row 0 twice, row 2 three times), row 1 without a diagonal
    rows, cols = [0, 0, 0, 1, 2, 2, 2, 2], [0, 0, 1, 2, 2, 1, 2, 2]
    values = np.array([1.0, 2.0, 5.0, 7.0, 3.0, 4.0, 10.0, 20.0])
    A = pf.SparseMatrix.from_coo(rows, cols, values, (3, 3))
    assert A.layout is not None and A.layout.repeated_diagonal.shape[0] == 3
    expected = sp.coo_matrix((values, (rows, cols)), shape=(3, 3)).tocsr().diagonal()
    np.testing.assert_array_equal(linalg.diagonal(A), expected)            # [3, 0, 33]
    np.testing.assert_array_equal(linalg.diagonal(A),
                                  linalg.diagonal(dataclasses.replace(A, layout=None)))
    weights = np.arange(1.0, 4.0)
    grad = jax.grad(lambda v: jnp.sum(linalg.diagonal(A.with_values(v)) * weights))(A.values)
    on_diagonal = np.asarray(A.rows) == np.asarray(A.cols)  # (from_coo sorted the entries)
    np.testing.assert_array_equal(grad, np.where(on_diagonal, weights[np.asarray(A.rows)], 0))


def test_a_layout_of_unsorted_rows_is_refused():
    """The layout counts slots and first diagonal entries along sorted rows; a pattern in
    another order (the constructor's contract) would drop entries silently."""
    A = pf.SparseMatrix(jnp.array([1, 0, 1]), jnp.array([1, 0, 1]), jnp.array([1.0, 2.0, 4.0]),
                        (2, 2))
    with pytest.raises(pf.ShapeError, match="rows are not sorted"):
        A.with_layout()


def test_conversions_round_trip(random_spd):
    A = pf.SparseMatrix.from_scipy(random_spd)
    assert abs(A.to_scipy() - random_spd).max() == 0
    again = pf.SparseMatrix.from_bcoo(A.to_bcoo())
    np.testing.assert_array_equal(again.rows, A.rows)
    x = np.linspace(0, 1, 40)
    np.testing.assert_allclose(A.to_bcoo() @ x, random_spd @ x, rtol=1e-13)
    np.testing.assert_allclose(A.todense(), random_spd.toarray())


def test_operator_is_a_jit_argument_not_a_constant(random_spd):
    traces = []

    @jax.jit
    def apply(op, x):
        traces.append(1)
        return linalg.matvec(op, x)

    A = pf.SparseMatrix.from_scipy(random_spd)
    apply(A, jnp.ones(40))
    apply(A.with_values(2 * A.values), jnp.ones(40))  # new values: same trace
    assert len(traces) == 1
    # the values are an input of the compiled function, not baked-in constants
    lowered = jax.jit(linalg.matvec).lower(A, jnp.ones(40)).as_text()
    signature = next(line for line in lowered.splitlines() if "func.func public @main" in line)
    assert f"tensor<{A.nnz}xf64>" in signature


def test_matvec_is_differentiable_in_values(random_spd):
    A = pf.SparseMatrix.from_scipy(random_spd)
    x = jnp.arange(40.0)
    y = jnp.ones(40)
    # jitted: one program (op by op, JAX's transpose pads each ELL slot in a program of its own)
    grad = jax.jit(jax.grad(lambda v: y @ linalg.matvec(A.with_values(v), x)))(A.values)
    np.testing.assert_allclose(grad, y[A.rows] * x[A.cols])


def test_vmap_over_vectors(random_spd):
    A = pf.SparseMatrix.from_scipy(random_spd)
    X = np.random.default_rng(4).normal(size=(5, 40))
    Y = jax.vmap(linalg.matvec, in_axes=(None, 0))(A, X)
    np.testing.assert_allclose(Y, (random_spd @ X.T).T, rtol=1e-13)


@pytest.mark.parametrize("rows, cols", [([0, -1], [0, 1]), ([0, 1], [0, 3])])
def test_from_coo_refuses_indices_outside_the_shape(rows, cols):
    with pytest.raises(pf.ShapeError, match=r"from_coo: (rows|cols) range from .* expected "
                       r"indices from 0 to 2 \(shape \(3, 3\)\)"):
        pf.SparseMatrix.from_coo(rows, cols, [1.0, 2.0], (3, 3))


def test_from_bcoo_drops_the_padding_of_a_bcoo(random_spd):
    """BCOO pads with out-of-range indices (here (40, 40)) and zero data; they are dropped,
    not refused."""
    from jax.experimental import sparse as jsparse

    padded = jsparse.BCOO.fromdense(jnp.asarray(random_spd.toarray()), nse=random_spd.nnz + 7)
    assert int(np.asarray(padded.indices).max()) == 40
    A = pf.SparseMatrix.from_bcoo(padded)
    x = np.random.default_rng(0).normal(size=40)
    np.testing.assert_allclose(linalg.matvec(A, x), random_spd @ x, rtol=1e-13)
    assert A.values.shape[0] == random_spd.nnz


def test_from_coo_sorts_and_sums(random_spd):
    coo = random_spd.tocoo()
    order = np.random.default_rng(5).permutation(coo.nnz)
    A = pf.SparseMatrix.from_coo(coo.row[order], coo.col[order], coo.data[order], coo.shape)
    assert np.all(np.diff(np.asarray(A.rows)) >= 0)
    x = np.linspace(-1, 1, 40)
    np.testing.assert_allclose(linalg.matvec(A, x), random_spd @ x, rtol=1e-13)


@jax.jit
def _products(A, x):
    return linalg.matvec(A, x), linalg.rmatvec(A, x), linalg.diagonal(A)


# each shape compiles: one program an example (the three run op by op took ~1 s an example)
@settings(max_examples=8, deadline=None)
@given(n=st.integers(1, 12), nnz=st.integers(0, 60), seed=st.integers(0, 2**31 - 1))
def test_matvec_matches_scipy_for_any_coo(n, nnz, seed):
    """Duplicates, empty rows, any order: matvec, rmatvec and diagonal equal SciPy's."""
    rng = np.random.default_rng(seed)
    rows, cols = rng.integers(0, n, nnz), rng.integers(0, n, nnz)
    values = rng.normal(size=nnz)
    reference = sp.csr_matrix((values, (rows, cols)), shape=(n, n))
    A = pf.SparseMatrix.from_coo(rows, cols, values, (n, n))
    x = rng.normal(size=n)
    product, transposed, diagonal = _products(A, jnp.asarray(x))
    np.testing.assert_allclose(product, reference @ x, atol=1e-12)
    np.testing.assert_allclose(transposed, reference.T @ x, atol=1e-12)
    np.testing.assert_allclose(diagonal, reference.diagonal(), atol=1e-12)


# ------------------------------------------------------------------------------------------
# the ELL kernel (the default for matrices with a layout) against SciPy and the COO kernel
# ------------------------------------------------------------------------------------------


def _star(n: int) -> sp.csr_matrix:
    """A hub row/column coupled to every node: one row far longer than the rest."""
    hub = sp.lil_matrix((n, n))
    hub[0, 1:] = -1.0
    hub[1:, 0] = -1.0
    return (hub + sp.diags(np.full(n, float(n)))).tocsr()


def test_long_rows_spill_into_the_coo_tail_and_still_multiply_right():
    matrix = _star(60)
    A = pf.SparseMatrix.from_scipy(matrix)
    assert A.layout.slots.shape[0] < 59  # not padded to the hub's length
    assert A.layout.overflow_rows.shape[0] > 0
    x = np.random.default_rng(0).normal(size=60)
    np.testing.assert_allclose(linalg.matvec(A, x), matrix @ x, rtol=1e-13)


def _layout_by_definition(rows, cols, n, n_cols):
    """The ELL layout read off row by row (the definition in ``ell_layout``'s docstring):
    a square row's first diagonal entry apart, its other entries in order in slots
    ``0..w-1``, the rest in the tail; padding points at ``nnz`` and the row's own column. The
    width ``w`` minimises ``n w + 4 spilled(w) + n [spilled(w) > 0]`` (the first minimum),
    rounded up to whole 32-slot chunks past 32."""
    nnz, square = len(rows), n_cols == n
    diagonal, repeated = [nnz] * n if square else [], []
    others = [[] for _ in range(n)]
    for position, (i, j) in enumerate(zip(rows, cols, strict=True)):
        if square and i == j and diagonal[i] == nnz:
            diagonal[i] = position
            continue
        others[i].append(position)
        if square and i == j:
            repeated.append(position)
    counts = [len(row) for row in others]

    def cost(w):
        spilled = sum(max(c - w, 0) for c in counts)
        return n * w + 4 * spilled + n * (spilled > 0)

    width = min(range(max(counts) + 1), key=cost)
    width = -(-width // 32) * 32 if width > 32 else width
    slots = [[row[k] if k < len(row) else nnz for row in others] for k in range(width)]
    columns = [[cols[row[k]] if k < len(row) else min(i, n_cols - 1)
                for i, row in enumerate(others)] for k in range(width)]
    tail = [(i, p) for i, row in enumerate(others) for p in row[width:]]
    return {"diagonal": diagonal, "slots": slots, "columns": columns,
            "overflow_slots": [p for _, p in tail], "overflow_rows": [i for i, _ in tail],
            "overflow_columns": [cols[p] for _, p in tail], "repeated_diagonal": repeated,
            "repeated_diagonal_rows": [rows[p] for p in repeated]}


@settings(max_examples=200, deadline=None)
@given(n=st.integers(1, 9), n_cols=st.integers(1, 9), square=st.booleans(),
       entries=st.lists(st.tuples(st.integers(0, 8), st.integers(0, 8)), max_size=70),
       hub=st.integers(0, 40), wide=st.sampled_from([0, 0, 40, 70]))
def test_the_ell_layout_is_its_definition(n, n_cols, square, entries, hub, wide):
    """Duplicates, repeated diagonals, empty rows, rectangular shapes, a long row (``hub``
    more entries in row 0, so some spill into the tail) and wide layouts (``wide`` more
    entries in every row: rounded up to whole 32-slot chunks, and past 64 filled by a
    scatter instead of slot by slot); each build must place every entry where the
    row-by-row reading does, in the same order, at the width of the cost model."""
    from prdp_fem.linalg.operator import _host_ell_layout
    n_cols = n if square else n_cols
    entries = sorted([(i % n, j % n_cols) for i, j in entries]
                     + [(0, k % n_cols) for k in range(hub)]
                     + [(i, k % n_cols) for i in range(n) for k in range(wide)],
                     key=lambda e: e[0])
    rows = [i for i, _ in entries]
    cols = [j for _, j in entries]
    layout = _host_ell_layout(np.array(rows, dtype=int), np.array(cols, dtype=int), n,
                              None if square else n_cols)
    expected = _layout_by_definition(rows, cols, n, n_cols)
    for field, value in expected.items():
        got = getattr(layout, field)
        assert got.dtype == np.int32, field
        np.testing.assert_array_equal(got, np.array(value, dtype=np.int32).reshape(got.shape),
                                      err_msg=field)


def _primitives(jaxpr) -> set[str]:
    names = set()
    for equation in jaxpr.eqns:
        names.add(equation.primitive.name)
        for sub in jax.extend.core.jaxprs_in_params(equation.params):
            names |= _primitives(sub)
    return names


@pytest.mark.parametrize("kernel", ["ell", "coo"])
def test_products_gather_without_wrapping_negative_indices(kernel):
    """The layouts' indices are never negative: a product has gathers and no select on its
    indices, which XLA hoisted out of CG's while loop as one kernel per ELL slot (an AMG
    V-cycle in the loop compiled 2.3x slower than on its own). Star rows also spill into the
    COO tail, whose gather is checked too."""
    A = pf.SparseMatrix.from_scipy(_star(60)).with_kernel(kernel)
    prepared = linalg.prepare(A)
    jaxpr = jax.make_jaxpr(prepared)(jnp.ones(60)).jaxpr
    names = _primitives(jaxpr)
    assert "gather" in names and not names & {"select_n", "lt"}, names
    np.testing.assert_allclose(prepared(np.arange(60.0)), _star(60) @ np.arange(60.0),
                               rtol=1e-13)


@pytest.mark.parametrize("matrix", ["random", "star"])
def test_ell_and_coo_kernels_agree_in_value_jvp_and_vjp(random_spd, matrix):
    matrix = random_spd if matrix == "random" else _star(40)
    ell = pf.SparseMatrix.from_scipy(matrix)
    coo = pf.SparseMatrix(ell.rows, ell.cols, ell.values, ell.shape)
    csr = ell.with_kernel("csr")
    assert isinstance(linalg.prepare(ell), linalg.EllMatrix) and isinstance(linalg.prepare(coo),
                                                                     linalg.CooMatrix)
    assert isinstance(linalg.prepare(csr), linalg.CsrMatrix)
    rng = np.random.default_rng(1)
    x, dx, dv, y = (rng.normal(size=s) for s in (40, 40, ell.nnz, 40))

    @jax.jit  # one program a kernel (op by op, each product and rule compiled its own)
    def derivatives(A, x, dv, dx, y):
        def product(values, x):
            return linalg.matvec(A.with_values(values), x)

        value, tangent = jax.jvp(product, (A.values, x), (dv, dx))
        return value, tangent, *jax.vjp(product, A.values, x)[1](y)

    for A in (ell, coo, csr):
        value, tangent, values_bar, x_bar = derivatives(A, x, dv, dx, y)
        np.testing.assert_allclose(value, matrix @ x, rtol=1e-12)
        np.testing.assert_allclose(tangent, A.with_values(dv).to_scipy() @ x + matrix @ dx,
                                   rtol=1e-12)
        np.testing.assert_allclose(values_bar, y[A.rows] * x[A.cols], rtol=1e-12)
        np.testing.assert_allclose(x_bar, matrix.T @ y, rtol=1e-12)


@settings(max_examples=6, deadline=None)
@given(n=st.integers(1, 12), nnz=st.integers(0, 60), seed=st.integers(0, 2**31 - 1))
def test_scaled_kernel_is_S_A_S(n, nnz, seed):
    """Duplicates, empty rows, missing diagonals: ``prepare(A).scaled(s)`` is ``S A S``."""
    rng = np.random.default_rng(seed)
    rows, cols, values = rng.integers(0, n, nnz), rng.integers(0, n, nnz), rng.normal(size=nnz)
    reference = sp.csr_matrix((values, (rows, cols)), shape=(n, n))  # sums the duplicates
    A = pf.SparseMatrix.from_coo(rows, cols, values, (n, n))
    s, x = rng.uniform(0.5, 2.0, n), rng.normal(size=n)
    scaled = sp.diags(s) @ reference @ sp.diags(s)
    coo = pf.SparseMatrix(A.rows, A.cols, A.values, A.shape)
    matrices = (A, coo, A.with_kernel("csr"))  # ELL, COO and CSR kernels
    for product in _scaled_products(matrices, jnp.asarray(s), jnp.asarray(x)):
        np.testing.assert_allclose(product, scaled @ x, atol=1e-12)


@jax.jit
def _scaled_products(matrices, s, x):  # one program an example, the kernels prepared in it
    return [linalg.prepare(matrix).scaled(s)(x) for matrix in matrices]


@pytest.mark.parametrize("shape", [(7, 30), (30, 7)])
def test_rectangular_ell_has_no_diagonal_and_multiplies_right(shape):
    """AMG transfer operators and the assembly map are rectangular: ELL without a diagonal."""
    matrix = sp.random(*shape, density=0.3, random_state=3, format="csr")
    A = pf.SparseMatrix.from_scipy(matrix)
    assert isinstance(linalg.prepare(A), linalg.CooMatrix)  # one-off products: the segment sum
    kernel = linalg.prepare(A.with_layout())
    assert isinstance(kernel, linalg.EllMatrix) and kernel.diagonal.shape == (0,)
    x = np.random.default_rng(2).normal(size=shape[1])
    np.testing.assert_allclose(kernel(x), matrix @ x, rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("shape", [(30, 30), (40, 17), (17, 40)])
def test_a_kernel_prepared_on_the_host_is_the_device_kernel_of_its_layout(shape):
    """host_prepared (AMG levels, FixedMatrix) skips the device round trip of
    prepare_on_host(from_scipy(...)): the same arrays, in NumPy, the same product."""
    from prdp_fem.linalg import host_prepared, prepare_on_host
    matrix = sp.random(*shape, density=0.3, random_state=4, format="csr")
    matrix.setdiag(np.arange(1.0, min(shape) + 1))  # a diagonal, as A_l has
    kernel = host_prepared(matrix)
    reference = prepare_on_host(pf.SparseMatrix.from_scipy(matrix, layout=True))
    assert isinstance(kernel, linalg.EllMatrix)
    for leaf, expected in zip(jax.tree_util.tree_leaves(kernel),
                              jax.tree_util.tree_leaves(reference), strict=True):
        assert isinstance(leaf, np.ndarray) and leaf.dtype == expected.dtype
        np.testing.assert_array_equal(leaf, expected)
    x = np.random.default_rng(5).normal(size=shape[1])
    np.testing.assert_allclose(jax.device_put(kernel)(x), matrix @ x, rtol=1e-13, atol=1e-14)


def test_wide_rows_past_the_unrolled_slots_multiply_and_differentiate_right():
    """A dense-ish matrix (ELL width > 32, as on coarse AMG levels): value, jvp and vjp."""
    matrix = sp.random(40, 40, density=0.95, random_state=4, format="csr") + sp.eye(40)
    A = pf.SparseMatrix.from_scipy(matrix)
    assert linalg.prepare(A).values.shape[0] > 32
    rng = np.random.default_rng(5)
    x, dx, y = rng.normal(size=40), rng.normal(size=40), rng.normal(size=40)
    # jitted: one program each (op by op, each product and rule compiled its own)
    value, tangent = jax.jit(lambda x, dx: jax.jvp(lambda x: linalg.matvec(A, x), (x,), (dx,)))(
        x, dx)
    np.testing.assert_allclose(value, matrix @ x, rtol=1e-12)
    np.testing.assert_allclose(tangent, matrix @ dx, rtol=1e-12)
    values_bar = jax.jit(jax.grad(lambda v: y @ linalg.matvec(A.with_values(v), x)))(A.values)
    np.testing.assert_allclose(values_bar, y[A.rows] * x[A.cols], rtol=1e-12)


def test_kernel_choice_by_backend_and_by_name(random_spd):
    """``prepare`` builds the named kernel; unnamed, the backend's default (ELL with a layout,
    measured fastest on CPU and on an H100), COO without a layout; bad names are refused."""
    A = pf.SparseMatrix.from_scipy(random_spd)
    assert linalg.default_kernel("cpu") == linalg.default_kernel("gpu") == "ell"
    assert type(linalg.prepare(A)) is {"ell": linalg.EllMatrix}[linalg.default_kernel()]
    assert type(linalg.prepare(A.with_kernel("coo"))) is linalg.CooMatrix
    bare = pf.SparseMatrix(A.rows, A.cols, A.values, A.shape)
    assert type(linalg.prepare(bare)) is linalg.CooMatrix
    with pytest.raises(ValueError, match="kernel='bcsr'"):
        A.with_kernel("bcsr")
    with pytest.raises(ValueError, match="needs an ELL layout"):
        bare.with_kernel("ell")
    assert A.with_kernel("csr").with_values(A.values * 2).kernel == "csr"  # kept


@pytest.mark.parametrize("gradient", ["implicit",
                                      pytest.param("unrolled", marks=pytest.mark.slow)])
def test_a_named_kernel_runs_forward_and_backward_and_changes_no_number(random_spd, gradient):
    """The kernel rides through solve's custom derivative rules (a static field): the CSR
    product appears in the forward and the backward sweep, and value and gradient equal the
    ELL kernel's."""
    A = pf.SparseMatrix.from_scipy(random_spd)
    b = np.random.default_rng(2).normal(size=40)
    solver = pf.TruncatedCG(8, gradient=gradient)

    def loss(matrix):
        return lambda values: jnp.sum(pf.solve(matrix.with_values(values), b, solver).x ** 2)

    csr = A.with_kernel("csr")
    # each program traced once: its jaxpr is read, then it is compiled and run
    traced, traced_ell = (jax.jit(jax.value_and_grad(loss(matrix))).trace(matrix.values)
                          for matrix in (csr, A))
    assert "csr_matvec" in str(traced.jaxpr)
    assert "csr_matvec" not in str(traced_ell.jaxpr)
    value, grad = traced.lower().compile()(csr.values)
    value_ell, grad_ell = traced_ell.lower().compile()(A.values)
    np.testing.assert_allclose(value, value_ell, rtol=1e-12)
    np.testing.assert_allclose(grad, grad_ell, rtol=1e-10, atol=1e-14 * np.abs(grad_ell).max())


@pytest.mark.parametrize("size", [0, 1, 7])
def test_a_column_map_and_its_transpose(size):
    """FixedMatrix.column: x -> values * x[0], its transpose a sum of values * y (a COO row,
    where an ELL layout would be one row `size` slots wide); reverse mode uses it."""
    values = np.linspace(-1.0, 2.0, size)
    column = linalg.FixedMatrix.column(values)
    assert column.shape == (size, 1)
    np.testing.assert_allclose(column(jnp.asarray([3.0])), 3.0 * values, rtol=1e-15)
    y = np.cos(np.arange(size))
    np.testing.assert_allclose(column.T(jnp.asarray(y)), [values @ y], rtol=1e-14, atol=1e-15)
    _, pullback = jax.vjp(column, jnp.asarray([3.0]))
    np.testing.assert_allclose(pullback(jnp.asarray(y))[0], [values @ y], rtol=1e-14,
                               atol=1e-15)
    np.testing.assert_array_equal(column.to_scipy().toarray(), values.reshape(-1, 1))


def test_a_symmetric_fixed_matrix_is_its_own_transpose_in_every_mode():
    """FixedMatrix.symmetric: one kernel both ways; the product, its jvp and vjp, and vmap
    equal SciPy's, and matvec / symmetric_matvec take it as they take a SparseMatrix."""
    disc = pf.discretize(pf.unit_square(6), element="P2")
    M = disc.mass_matrix.tocsr()
    fixed = linalg.FixedMatrix.symmetric(M)
    assert fixed.transpose is None and fixed.T is fixed and fixed.shape == M.shape
    x = np.sin(np.arange(M.shape[0], dtype=float))
    y = np.cos(np.arange(M.shape[0], dtype=float))
    for product in (fixed, lambda v: linalg.matvec(fixed, v),
                    lambda v: linalg.symmetric_matvec(fixed, v)):
        np.testing.assert_allclose(product(jnp.asarray(x)), M @ x, rtol=1e-13, atol=1e-16)
    _, tangent = jax.jvp(fixed, (jnp.asarray(x),), (jnp.asarray(y),))
    np.testing.assert_allclose(tangent, M @ y, rtol=1e-13, atol=1e-16)
    _, pullback = jax.vjp(fixed, jnp.asarray(x))
    np.testing.assert_allclose(pullback(jnp.asarray(y))[0], M.T @ y, rtol=1e-13, atol=1e-16)
    batch = jnp.stack([x, y])
    np.testing.assert_allclose(jax.vmap(fixed)(batch), (M @ np.stack([x, y]).T).T, rtol=1e-13,
                               atol=1e-16)
    assert (abs(fixed.to_scipy() - M)).max() == 0.0


def test_a_symmetric_fixed_matrix_refuses_a_matrix_that_is_not():
    with pytest.raises(pf.ShapeError, match="not symmetric"):
        linalg.FixedMatrix.symmetric(sp.csr_matrix(np.array([[2.0, 1.0], [0.0, 3.0]])))
    with pytest.raises(pf.ShapeError, match="expected a square one"):
        linalg.FixedMatrix.symmetric(sp.csr_matrix(np.ones((2, 3))))
    assert linalg.FixedMatrix.symmetric(sp.csr_matrix((0, 0))).shape == (0, 0)
