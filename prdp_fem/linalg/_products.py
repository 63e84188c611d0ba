r"""Sparse products whose reverse-mode transpose is a given product, never derived by JAX.

A product kernel (:func:`~prdp_fem.linalg.prepare`) is bilinear in its floating-point leaves
``v`` (the values) and the vector ``x``: ``y = A(v) x``. JAX differentiates it as written, and
reverse mode transposes each gather ``x[columns]`` into a scatter-add: on the CPU one
``scatter`` per ELL slot, serial and uncached. This module binds one primitive whose
transpose in ``x`` is a *product* again, a gather loop like the forward one:

* :func:`symmetric_product`: for a symmetric ``A`` the transpose is the product itself;
* :func:`paired_product`: for any constant ``A`` (the assembly map ``G``, a source or
  observation matrix), a second kernel laid out for ``A^T`` on the host once
  (:class:`~prdp_fem.linalg.operator.FixedMatrix` holds the pair), whose transpose is the first.

.. math::

    \bar x = A^T \bar y \ (\text{the other kernel, or } A \bar y), \qquad
    \bar v = \frac{\partial (A(v) x)}{\partial v}^T \bar y
    \quad (\text{ELL: } \bar v_{k,i} = \bar y_i\, x_{c_{k,i}},\ \text{a gather}).

The tangent is ``A(v) dx + A(dv) x``, both terms the primitive again, so derivatives compose to
any order. Under ``vmap`` the batch axis of each operand is recorded and the product is JAX's
``vmap`` of the kernel (one fused call); the rules carry the batch axes along.

Against JAX's own transposes (measured in ``docs/performance-log.md``): through CG's symmetric
product a jitted unrolled ``value_and_grad`` in kappa has a fraction of the scatters and takes
a little over half the time, and reverse mode stores 3 n-vectors per iteration instead of 7;
through the paired assembly map an implicit ``value_and_grad`` at ``K = 0`` takes less time
too.

Only CG's operator goes through :func:`symmetric_product` (CG requires ``A`` symmetric; a
non-symmetric ``A`` would get the wrong transpose). A paired product is exact for any ``A``,
as long as its second kernel holds ``A^T`` of the same values.

>>> import numpy as np, scipy.sparse as sp, jax
>>> from prdp_fem.linalg.operator import SparseMatrix, prepare
>>> A = prepare(SparseMatrix.from_scipy(sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(4, 4))))
>>> x = np.arange(4.0)
>>> bool(np.allclose(jax.vjp(lambda x: symmetric_product(A, x), x)[1](x)[0], A(x)))
True
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

__all__ = ["paired_product", "symmetric_product"]

_product_p = Primitive("sparse_product")

# ``levels``: one tuple per enclosing vmap, outermost first, with the batch axis (0, after the
# batching rule moved it there) or None of every operand (the kernels' leaves, then x)
Levels = tuple[tuple[int | None, ...], ...]


def symmetric_product(kernel, x: jax.Array) -> jax.Array:
    """``kernel(x)`` for the product kernel of a symmetric matrix (see the module docstring)."""
    return _bind((kernel, None), x)


def paired_product(kernel, transpose_kernel, x: jax.Array) -> jax.Array:
    """``kernel(x)``, transposed in reverse mode as ``transpose_kernel`` (which must hold the
    transpose of ``kernel``'s matrix, with the same values)."""
    return _bind((kernel, transpose_kernel), x)


def _bind(pair, x: jax.Array) -> jax.Array:
    leaves, treedef = jax.tree_util.tree_flatten(pair)
    return _product_p.bind(*leaves, jnp.asarray(x), treedef=treedef, levels=(),
                           transposed=False)


def _product(*operands, treedef, levels: Levels, transposed: bool,
             in_values: bool = False) -> jax.Array:
    """The product of the pair's kernel (its second when ``transposed``; the first again when
    the matrix is symmetric), ``vmap`` ped once per level (the primitive's meaning).

    ``in_values``: the kernel's ``linear_in_values`` form of the same product, whose VJP in
    the values is a gather (for :func:`_transpose_in_values`)."""

    def apply(*args):
        kernel, transpose_kernel = jax.tree_util.tree_unflatten(treedef, args[:-1])
        if transposed and transpose_kernel is not None:
            kernel = transpose_kernel
        return kernel.linear_in_values(args[-1]) if in_values else kernel(args[-1])

    for axes in reversed(levels):  # innermost level first
        apply = jax.vmap(apply, in_axes=axes)
    return apply(*operands)


def _abstract_eval(*avals, treedef, levels, transposed):
    """The product's type, read off its operands: one batch axis per ``vmap`` level (each
    maps some operand), then the kernel's rows, in the dtype of its values and ``x``.

    ELL and COO kernels (``n_rows``) with floating values and a floating, strongly typed
    ``x`` are read; anything else (CSR, a weakly typed ``x`` whose promotion follows the
    values, integer values) is traced (``jax.eval_shape``). Tracing every bind here took a
    twentieth of the mother problem's compile.
    """
    kernel, transpose_kernel = jax.tree_util.tree_unflatten(treedef, avals[:-1])
    if transposed and transpose_kernel is not None:
        kernel = transpose_kernel
    rows, x = getattr(kernel, "n_rows", None), avals[-1]
    values = [leaf for leaf in jax.tree_util.tree_leaves(kernel)
              if jnp.issubdtype(leaf.dtype, jnp.inexact)]
    if rows is None or not values or not jnp.issubdtype(x.dtype, jnp.inexact) or any(
            aval.weak_type for aval in (*values, x)):
        out = jax.eval_shape(partial(_product, treedef=treedef, levels=levels,
                                     transposed=transposed), *avals)
        return jax.core.ShapedArray(out.shape, out.dtype)
    batch = tuple(_level_size(avals, levels, level) for level in range(len(levels)))
    dtype = jnp.result_type(*(value.dtype for value in values), x.dtype)
    return jax.core.ShapedArray((*batch, rows), dtype)


def _level_size(avals, levels: Levels, level: int) -> int:
    """The size of ``vmap`` level ``level``: an operand it maps holds it after the axes of
    the outer levels that map that operand too."""
    operand = next(i for i, axis in enumerate(levels[level]) if axis is not None)
    outer = sum(axes[operand] is not None for axes in levels[:level])
    return avals[operand].shape[outer]


def _is_value(leaf) -> bool:
    """A leaf the product is linear in (floating point); integer leaves are the layout."""
    aval = leaf.aval if ad.is_undefined_primal(leaf) else jax.typeof(leaf)
    return jnp.issubdtype(aval.dtype, jnp.inexact)


def _jvp(primals, tangents, *, treedef, levels, transposed):
    *leaves, x = primals
    *leaf_tangents, dx = tangents
    bind = partial(_product_p.bind, treedef=treedef, levels=levels, transposed=transposed)
    y = bind(*primals)
    terms = []
    if type(dx) is not ad.Zero:
        terms.append(bind(*leaves, dx))
    moved = [_is_value(leaf) and type(t) is not ad.Zero
             for leaf, t in zip(leaves, leaf_tangents, strict=True)]
    if any(moved):  # A(dv) x: the tangent values on the same layout
        tangent_leaves = [ad.instantiate_zeros(t) if _is_value(leaf) else leaf
                          for leaf, t in zip(leaves, leaf_tangents, strict=True)]
        terms.append(bind(*tangent_leaves, x))
    if not terms:
        return y, ad.Zero.from_primal_value(y)
    return y, terms[0] if len(terms) == 1 else terms[0] + terms[1]


def _transpose(cotangent, *operands, treedef, levels, transposed):
    *leaves, x = operands
    undefined_leaves = [ad.is_undefined_primal(leaf) for leaf in leaves]
    if ad.is_undefined_primal(x) and any(undefined_leaves):
        raise NotImplementedError("a sparse product is bilinear, not linear, in (values, x)")
    if type(cotangent) is ad.Zero:
        return [None] * len(operands)
    if ad.is_undefined_primal(x):
        x_bar = _transpose_in_x(cotangent, leaves, treedef, levels, transposed)
        return [None] * len(leaves) + [x_bar]
    return [*_transpose_in_values(cotangent, leaves, x, treedef, levels, transposed), None]


def _transpose_in_x(cotangent, leaves, treedef, levels, transposed):
    """``A^T ct`` (the pair's other kernel), summed over the batch levels at which ``x`` was
    not mapped."""
    all_mapped = tuple((*axes[:-1], 0) for axes in levels)
    x_bar = _product_p.bind(*leaves, cotangent, treedef=treedef, levels=all_mapped,
                            transposed=not transposed)
    unmapped = tuple(i for i, axes in enumerate(levels) if axes[-1] is None)
    return jnp.sum(x_bar, axis=unmapped) if unmapped else x_bar


def _transpose_in_values(cotangent, leaves, x, treedef, levels, transposed):
    """The VJP of ``v -> A(v) x``: per-entry gathers of ``x`` times the cotangent (zero for
    the leaves of the kernel the product does not read)."""
    undefined = [i for i, leaf in enumerate(leaves) if ad.is_undefined_primal(leaf)]

    def product_in(*values):
        filled = list(leaves)
        for i, value in zip(undefined, values, strict=True):
            filled[i] = value
        return _product(*filled, x, treedef=treedef, levels=levels, transposed=transposed,
                        in_values=True)

    # linear in the values: any point gives the same VJP
    zeros = [jnp.zeros(leaves[i].aval.shape, leaves[i].aval.dtype) for i in undefined]
    values_bar = jax.vjp(product_in, *zeros)[1](cotangent)
    out = [None] * len(leaves)
    for i, value_bar in zip(undefined, values_bar, strict=True):
        out[i] = value_bar
    return out


def _batch(operands, dims, *, treedef, levels, transposed):
    moved = [x if d is None else jnp.moveaxis(x, d, 0) for x, d in zip(operands, dims,
                                                                      strict=True)]
    axes = tuple(None if d is None else 0 for d in dims)
    return _product_p.bind(*moved, treedef=treedef, levels=(axes, *levels),
                           transposed=transposed), 0


_product_p.def_impl(jax.jit(_product, static_argnames=("treedef", "levels", "transposed")))
_product_p.def_abstract_eval(_abstract_eval)
ad.primitive_jvps[_product_p] = _jvp
ad.primitive_transposes[_product_p] = _transpose
batching.primitive_batchers[_product_p] = _batch
mlir.register_lowering(_product_p, mlir.lower_fun(_product, multiple_results=False))
