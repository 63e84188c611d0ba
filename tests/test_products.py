"""symmetric_product and paired_product against the kernel differentiated by JAX, grouped
by transformation.

The reference is the same kernel applied directly: its derivatives are JAX's own (a scatter
per gather in reverse mode). The primitive must agree with them to round-off everywhere: value,
jvp, vjp in the values and in x, vmap (x batched, values batched, nested), jit, second order.
The paired product is checked on a rectangular matrix whose layouts both ways spill into
overflow tails, with the transpose's values a gather of the forward values (so a tangent in
them moves both kernels, as it must).
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp
from conftest import count_primitives

from prdp_fem.linalg import FixedMatrix, SparseMatrix, matvec, prepare, symmetric_matvec
from prdp_fem.linalg._products import paired_product, symmetric_product

N = 30

# The scatter counts read the program as it ships: the test suite compiles with XLA's classic
# CPU emitters (tests/conftest.py), which expand every scatter into a loop.
SHIPPED_EMITTERS = {"xla_cpu_use_fusion_emitters": True}


def _scatters(fn, arg) -> int:
    """How many scatters ``jit(fn)(arg)`` compiles to, with the emitters users get."""
    compiled = jax.jit(fn).lower(arg).compile(compiler_options=SHIPPED_EMITTERS)
    return compiled.as_text().count(" scatter(")


def _arrowhead() -> sp.csr_matrix:
    """SPD, with one full row and column: the ELL layout spills it into its overflow tail."""
    rng = np.random.default_rng(4)
    a = sp.random(N, N, density=0.08, random_state=rng)
    a = a + a.T + sp.diags(np.full(N, 2.0 * N))
    a = sp.lil_matrix(a)
    a[0, 1:] = a[1:, 0] = rng.uniform(0.1, 0.5, N - 1)[:, None]
    return sp.csr_matrix(a)


@pytest.fixture(params=["ell", "coo"])
def matrix(request) -> SparseMatrix:
    A = SparseMatrix.from_scipy(_arrowhead())
    if request.param == "ell":
        assert A.layout is not None and A.layout.overflow_rows.shape[0] > 0
        return A
    return A.with_kernel("coo")


def _symmetric(A: SparseMatrix):
    return lambda values, x: symmetric_product(prepare(A.with_values(values)), x)


def _plain(A: SparseMatrix):
    return lambda values, x: prepare(A.with_values(values))(x)


def _jit(fn, *args):
    """``fn(*args)`` compiled: one compile per check, not one per eager op."""
    return jax.jit(fn)(*args)


def _close(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)


def _point(A: SparseMatrix, seed: int = 0):
    rng = np.random.default_rng(seed)
    return jnp.asarray(A.values), jnp.asarray(rng.standard_normal(N))


def test_value_is_the_scipy_product(matrix):
    values, x = _point(matrix)
    np.testing.assert_allclose(_symmetric(matrix)(values, x), _arrowhead() @ np.asarray(x),
                               rtol=1e-13)


# ---- jvp -------------------------------------------------------------------------------

def test_jvp_in_values_and_x(matrix):
    values, x = _point(matrix)
    rng = np.random.default_rng(1)
    tangents = (jnp.asarray(rng.standard_normal(values.shape)), jnp.asarray(rng.standard_normal(N)))
    _close(_jit(lambda *p: jax.jvp(_symmetric(matrix), p, tangents), values, x),
           _jit(lambda *p: jax.jvp(_plain(matrix), p, tangents), values, x))


# ---- vjp -------------------------------------------------------------------------------

def test_vjp_in_values_and_x(matrix):
    values, x = _point(matrix)
    cotangent = jnp.asarray(np.random.default_rng(2).standard_normal(N))
    ours = _jit(lambda *p: jax.vjp(_symmetric(matrix), *p)[1](cotangent), values, x)
    _close(ours, _jit(lambda *p: jax.vjp(_plain(matrix), *p)[1](cotangent), values, x))
    # the x part is the product itself: A^T ct = A ct
    np.testing.assert_allclose(ours[1], _arrowhead() @ np.asarray(cotangent), rtol=1e-13)


def test_reverse_mode_in_x_compiles_without_scatters():
    """The point of the primitive: the ELL gradient in x is a second product (with the one
    scatter of its overflow tail), not a scatter per slot's gather."""
    matrix = SparseMatrix.from_scipy(_arrowhead())
    values, x = _point(matrix)

    def gradient(product):
        return jax.grad(lambda x: jnp.sum(jnp.sin(product(values, x))))

    in_one_product = _scatters(lambda x: _plain(matrix)(values, x), x)
    assert _scatters(gradient(_plain(matrix)), x) > 2 * in_one_product
    assert _scatters(gradient(_symmetric(matrix)), x) == 2 * in_one_product


def test_reverse_mode_in_the_values_is_one_gather_not_a_pad_per_slot():
    """The values' cotangent of an ELL product is ``y_bar[None, :] * x[columns]`` as one
    array: JAX's transpose of the per-slot loop pads every slot's row to the whole ``(w, n)``
    array and adds them up (what made an unrolled reverse sweep 7x its forward step)."""
    kernel = prepare(SparseMatrix.from_scipy(_arrowhead()))
    width = kernel.values.shape[0]
    assert width > 2
    x = jnp.asarray(np.random.default_rng(5).standard_normal(N))

    def gradient(product):
        return jax.grad(lambda values: jnp.sum(jnp.sin(product(
            dataclasses.replace(kernel, values=values), x))))

    plain, ours = gradient(lambda k, x: k(x)), gradient(symmetric_product)
    assert count_primitives(plain, kernel.values, "pad") == width
    assert count_primitives(ours, kernel.values, "pad") == 0
    _close(_jit(ours, kernel.values), _jit(plain, kernel.values))


# ---- vmap ------------------------------------------------------------------------------

def test_vmap_over_x_over_values_and_nested(matrix):
    values, _ = _point(matrix)
    rng = np.random.default_rng(3)
    xs = jnp.asarray(rng.standard_normal((2, 3, N)))
    scales = jnp.asarray(rng.uniform(0.5, 2.0, (2, 1)))
    batched_values = scales * values
    for in_axes, args in (((None, 0), (values, xs[0])), ((0, 0), (batched_values, xs[:, 0]))):
        ours = _jit(jax.vmap(_symmetric(matrix), in_axes), *args)
        assert ours.shape == (3 if in_axes[0] is None else 2, N)
        _close(ours, _jit(jax.vmap(_plain(matrix), in_axes), *args))
    nested = jax.vmap(jax.vmap(_symmetric(matrix), in_axes=(None, 0)), in_axes=(0, 0))
    reference = jax.vmap(jax.vmap(_plain(matrix), in_axes=(None, 0)), in_axes=(0, 0))
    _close(_jit(nested, batched_values, xs), _jit(reference, batched_values, xs))


@pytest.mark.parametrize("outer, inner", [((0, None), (None, 0)), ((None, 0), (0, None)),
                                          ((0, 0), (None, 0)), ((0, None), (0, 0))])
@pytest.mark.parametrize("x_dtype", [jnp.float64, jnp.float32])
def test_the_products_type_under_nested_vmap_is_the_kernels(matrix, outer, inner, x_dtype):
    """The primitive's type is read off its operands, not traced: batch sizes from whichever
    operand each level maps (after that operand's outer axes), dtype from values and x."""
    values, x = _point(matrix)
    levels = ((2, outer), (3, inner))

    def batched(array, mapped, dtype):
        shape = [size for size, axes in levels if axes[mapped] == 0]
        return jax.ShapeDtypeStruct((*shape, *array.shape), dtype)

    args = (batched(values, 0, values.dtype), batched(x, 1, x_dtype))

    def nested(product):
        return jax.vmap(jax.vmap(product, in_axes=inner), in_axes=outer)
    ours = jax.eval_shape(nested(_symmetric(matrix)), *args)
    reference = jax.eval_shape(nested(_plain(matrix)), *args)
    assert (ours.shape, ours.dtype) == (reference.shape, reference.dtype) == ((2, 3, N),
                                                                              jnp.float64)


@pytest.mark.parametrize("values_dtype, x", [
    (jnp.float32, lambda: jnp.broadcast_to(jnp.asarray(1.0), (N,))),  # weak: follows values
    (jnp.float32, lambda: jnp.ones(N)), (jnp.float64, lambda: jnp.arange(N, dtype=jnp.int32)),
    (jnp.int32, lambda: jnp.arange(N)), (jnp.float64, lambda: jnp.ones(N, jnp.complex64))])
def test_the_products_dtype_is_the_kernels(matrix, values_dtype, x):
    """Promotions the type cannot be read off plainly (a weakly typed x, integer values) are
    traced: the declared type is what the kernel returns, so the product compiles."""
    A = matrix.with_values(matrix.values.astype(values_dtype))
    declared = jax.eval_shape(lambda x: symmetric_product(prepare(A), x), x())
    computed = _jit(lambda x: prepare(A)(x), x())
    assert declared.dtype == computed.dtype
    np.testing.assert_array_equal(_jit(lambda x: symmetric_product(prepare(A), x), x()), computed)


# COO with the slow cases: the primitive's batching and transpose rules are the same for
# either kernel, and test_vjp_in_values_and_x[coo] checks COO's reverse mode
@pytest.mark.parametrize("matrix", ["ell", pytest.param("coo", marks=pytest.mark.slow)],
                         indirect=True)
def test_vmap_of_grad_and_grad_of_vmap(matrix):
    values, _ = _point(matrix)
    rng = np.random.default_rng(5)
    xs = jnp.asarray(rng.standard_normal((3, N)))
    scales = jnp.asarray(rng.uniform(0.5, 2.0, (3, 1)))

    def loss(product):
        return lambda v, x: jnp.sum(jnp.cos(product(v, x)))

    # (0, None): reverse mode through a batch of matrices at one x sums x's cotangent
    for in_axes in ((None, 0), (0, 0), (0, None)):
        v = values if in_axes[0] is None else scales * values
        x = xs if in_axes[1] == 0 else xs[0]
        per_member = jax.vmap(jax.grad(loss(_symmetric(matrix)), argnums=(0, 1)), in_axes)
        reference = _jit(jax.vmap(jax.grad(loss(_plain(matrix)), argnums=(0, 1)), in_axes),
                         v, x)
        _close(_jit(per_member, v, x), reference)

        def summed(product, in_axes=in_axes):
            return lambda vs, us: jnp.sum(jax.vmap(loss(product), in_axes)(vs, us))

        # the gradient of the batch's sum: the members' gradients (JAX's own, above), summed
        # over the batch where an operand is shared (one program fewer than differentiating
        # the plain kernel's sum again)
        summed_reference = tuple(g if axis == 0 else g.sum(axis=0)
                                 for g, axis in zip(reference, in_axes, strict=True))
        _close(_jit(jax.grad(summed(_symmetric(matrix)), argnums=(0, 1)), v, x),
               summed_reference)


# ---- jit and second order --------------------------------------------------------------

def test_jitted_hessian_vector_product(matrix):
    """Forward over reverse: the transposes are differentiated again (values and x mixed).

    The direction in the values is symmetric, as every change of an assembled stiffness
    matrix is: the transpose in x assumes ``A^T = A`` along it.
    """
    values, x = _point(matrix)
    rng = np.random.default_rng(6)
    r, s = rng.standard_normal((2, N))
    symmetric_change = r[matrix.rows] * r[matrix.cols] + s[matrix.rows] + s[matrix.cols]
    direction = (jnp.asarray(symmetric_change), jnp.asarray(rng.standard_normal(N)))

    def hvp(product):
        loss = lambda v, x: jnp.sum(jnp.sin(product(v, x)) * x)  # noqa: E731
        grad = jax.grad(loss, argnums=(0, 1))
        return jax.jit(lambda v, x: jax.jvp(grad, (v, x), direction)[1])

    _close(hvp(_symmetric(matrix))(values, x), hvp(_plain(matrix))(values, x))


# ---- paired products (a rectangular A with a kernel laid out for A^T) --------------------

ROWS, COLS = 40, 25


def _tall() -> sp.csr_matrix:
    """40 x 25, with one full row and one full column: both layouts spill into a tail."""
    rng = np.random.default_rng(7)
    a = sp.lil_matrix(sp.random(ROWS, COLS, density=0.1, random_state=rng))
    a[3, :] = rng.uniform(0.5, 1.0, COLS)
    a[:, 5] = rng.uniform(0.5, 1.0, (ROWS, 1))
    return sp.csr_matrix(a)


@functools.cache
def _paired_parts():
    """The forward matrix (with its layout) and, for the transpose, its pattern plus the
    position in the forward values of each transposed entry."""
    tall = _tall()
    A = SparseMatrix.from_scipy(tall).with_layout()
    positions = sp.csr_matrix((np.arange(1.0, A.nnz + 1.0), (np.asarray(A.rows),
                                                             np.asarray(A.cols))), tall.shape)
    T = SparseMatrix.from_scipy(positions.T).with_layout()
    return A, T, np.asarray(T.values).astype(int) - 1


def _paired():
    A, T, gather = _paired_parts()
    assert A.layout.overflow_rows.shape[0] > 0 and T.layout.overflow_rows.shape[0] > 0
    return lambda values, x: paired_product(prepare(A.with_values(values)),
                                            prepare(T.with_values(values[gather])), x)


def _paired_plain():
    A, _, _ = _paired_parts()
    return lambda values, x: prepare(A.with_values(values))(x)


def _paired_point(seed: int = 0):
    A, _, _ = _paired_parts()
    rng = np.random.default_rng(seed)
    return jnp.asarray(A.values), jnp.asarray(rng.standard_normal(COLS))


def test_paired_value_and_transpose_are_scipy_products():
    values, x = _paired_point()
    np.testing.assert_allclose(_paired()(values, x), _tall() @ np.asarray(x), rtol=1e-13)
    fixed = FixedMatrix.from_scipy(_tall())
    y = np.random.default_rng(1).standard_normal(ROWS)
    np.testing.assert_allclose(fixed.T(y), _tall().T @ y, rtol=1e-13)
    assert fixed.shape == (ROWS, COLS) and fixed.T.shape == (COLS, ROWS)
    for read_back, reference in ((fixed.to_scipy(), _tall()), (fixed.T.to_scipy(), _tall().T)):
        assert abs(read_back - reference).max() == 0 and read_back.nnz == reference.nnz


def test_paired_jvp_and_vjp_in_values_and_x():
    values, x = _paired_point()
    rng = np.random.default_rng(2)
    tangents = (jnp.asarray(rng.standard_normal(values.shape)),
                jnp.asarray(rng.standard_normal(COLS)))
    _close(_jit(lambda *p: jax.jvp(_paired(), p, tangents), values, x),
           _jit(lambda *p: jax.jvp(_paired_plain(), p, tangents), values, x))
    cotangent = jnp.asarray(rng.standard_normal(ROWS))
    ours = _jit(lambda *p: jax.vjp(_paired(), *p)[1](cotangent), values, x)
    _close(ours, _jit(lambda *p: jax.vjp(_paired_plain(), *p)[1](cotangent), values, x))
    np.testing.assert_allclose(ours[1], _tall().T @ np.asarray(cotangent), rtol=1e-13)


def test_paired_reverse_mode_in_x_is_the_transpose_kernel():
    """The gradient in x compiles to the transpose kernel: its one tail scatter, not one per
    slot of the forward kernel."""
    fixed = FixedMatrix.from_scipy(_tall())
    x = jnp.asarray(np.random.default_rng(3).standard_normal(COLS))

    def gradient(product):
        return jax.grad(lambda x: jnp.sum(jnp.sin(product(x))))

    forward = _scatters(lambda x: fixed(x), x)
    transpose = _scatters(lambda y: fixed.T(y), jnp.ones(ROWS))
    assert _scatters(gradient(fixed), x) == forward + transpose
    assert _scatters(gradient(fixed.forward), x) > forward + transpose


def test_paired_vmap_nested_and_vmap_of_grad():
    values, _ = _paired_point()
    rng = np.random.default_rng(4)
    xs = jnp.asarray(rng.standard_normal((2, 3, COLS)))
    batched_values = jnp.asarray(rng.uniform(0.5, 2.0, (2, 1))) * values
    nested = jax.vmap(jax.vmap(_paired(), in_axes=(None, 0)), in_axes=(0, 0))
    reference = jax.vmap(jax.vmap(_paired_plain(), in_axes=(None, 0)), in_axes=(0, 0))
    _close(_jit(nested, batched_values, xs), _jit(reference, batched_values, xs))

    def loss(product):
        return lambda v, x: jnp.sum(jnp.cos(product(v, x)))

    for in_axes, v, x in (((None, 0), values, xs[0]), ((0, None), batched_values, xs[0, 0])):
        _close(_jit(jax.vmap(jax.grad(loss(_paired()), argnums=(0, 1)), in_axes), v, x),
               _jit(jax.vmap(jax.grad(loss(_paired_plain()), argnums=(0, 1)), in_axes), v, x))


def test_paired_jitted_hessian_vector_product():
    """Forward over reverse, in any direction of the values (no symmetry needed)."""
    values, x = _paired_point()
    rng = np.random.default_rng(6)
    direction = (jnp.asarray(rng.standard_normal(values.shape)),
                 jnp.asarray(rng.standard_normal(COLS)))

    def hvp(product):
        loss = lambda v, x: jnp.sum(jnp.sin(product(v, x))) * jnp.sum(x)  # noqa: E731
        grad = jax.grad(loss, argnums=(0, 1))
        return jax.jit(lambda v, x: jax.jvp(grad, (v, x), direction)[1])

    _close(hvp(_paired())(values, x), hvp(_paired_plain())(values, x))


# ---- symmetric_matvec: a quadratic form's gradient without scatters --------------------

def test_symmetric_matvec_gradient_of_a_quadratic_form():
    """``1/2 r^T W r`` through symmetric_matvec: the same value and gradient ``W r`` as
    JAX's own transposes, compiled with the overflow tail's scatter only."""
    W = SparseMatrix.from_scipy(_arrowhead())
    r = jnp.asarray(np.random.default_rng(8).standard_normal(N))

    def form(product):
        return lambda r: 0.5 * jnp.vdot(r, product(W, r))

    ours = jax.jit(jax.value_and_grad(form(symmetric_matvec)))(r)
    _close(ours, jax.jit(jax.value_and_grad(form(matvec)))(r))
    np.testing.assert_allclose(ours[1], _arrowhead() @ np.asarray(r), rtol=1e-13)

    assert _scatters(jax.grad(form(symmetric_matvec)), r) < _scatters(jax.grad(form(matvec)), r)
