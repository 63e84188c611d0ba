r"""Jacobi-preconditioned CG in NumPy/SciPy, for the well-conditioned SPD systems of the setup.

Mass matrices are the use: ``cond(D^{-1} M)`` is bounded independently of the mesh size and
shape (``<= 4`` for P1 triangles, Wathen 1987), so a few dozen iterations reach round-off. It
serves :meth:`~prdp_fem.fem.discretization.Discretization.project` and the Riesz map of
:func:`~prdp_fem.inverse.reduced.reduced_cg` without a sparse factorisation and without compiling
anything. The operator's truncated, differentiable solves are :mod:`prdp_fem.linalg.cg`'s.

.. math::

    r_0 = b,\; z_0 = D^{-1} r_0,\; p_0 = z_0;\qquad
    x_{k+1} = x_k + a_k p_k,\; r_{k+1} = r_k - a_k A p_k,\;
    a_k = \frac{r_k^\top z_k}{p_k^\top A p_k},\;
    p_{k+1} = z_{k+1} + \frac{r_{k+1}^\top z_{k+1}}{r_k^\top z_k} p_k,

stopping once ``||r_k|| <= rtol ||b||``.

>>> import numpy as np, scipy.sparse as sp
>>> solution = jacobi_pcg(sp.csr_matrix(np.array([[4.0, 1.0], [1.0, 3.0]])), np.ones(2), 1e-12)
>>> np.round(solution.x, 12).tolist(), solution.iterations
([0.181818181818, 0.272727272727], 2)
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

__all__ = ["HostSolution", "dot", "jacobi_pcg", "power_of_two_scale"]


class HostSolution(NamedTuple):
    x: np.ndarray
    iterations: int


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """``a . b`` without BLAS: a threaded OpenBLAS ``ddot`` (and ``nrm2``, behind
    ``np.linalg.norm``) was measured at 7-8 ms per 66k-vector call on 2 busy cores, 400x this
    loop; SciPy's ``cg`` spent 0.4 s of a 0.5 s projection in it."""
    return float(np.einsum("i,i", a, b))


def jacobi_pcg(matrix: sp.csr_matrix, b: np.ndarray, rtol: float,
               max_iterations: int = 1000) -> HostSolution | None:
    """``x`` with ``||b - A x|| <= rtol ||b||`` (recursive residual), or None if not met.

    CG runs on ``b / 2^e`` with ``2^e <= max |b_i| < 2^(e+1)``: exact, so the iterates are
    those of ``b`` scaled, bit for bit, while ``r.r`` can neither underflow (data of 1e-170
    gave ``r.r = 0``, which met the test at once and returned ``x = 0``) nor overflow.
    """
    b = np.asarray(b, dtype=float)
    scale = power_of_two_scale(b)
    solution = _jacobi_pcg(matrix, b / scale, rtol, max_iterations)
    return None if solution is None else solution._replace(x=solution.x * scale)


def power_of_two_scale(v: np.ndarray) -> float:
    """``2^e <= max |v_i| < 2^(e+1)`` (1 for a zero ``v``), kept a normal number: dividing by
    it is exact, and brings the largest entry to ``[1, 2)`` where ``v.v`` cannot under- or
    overflow."""
    _, exponent = np.frexp(np.max(np.abs(v), initial=0.0))
    return float(np.ldexp(1.0, int(np.clip(exponent - 1, -1022, 1023)))) if exponent else 1.0


def _jacobi_pcg(matrix: sp.csr_matrix, b: np.ndarray, rtol: float,
                max_iterations: int) -> HostSolution | None:
    inverse_diagonal = 1.0 / matrix.diagonal()
    x = np.zeros_like(b)
    r = np.array(b, dtype=float)
    z = inverse_diagonal * r
    p, rz = z.copy(), dot(r, z)
    target = (rtol * rtol) * dot(r, r)
    for iteration in range(max_iterations):
        if dot(r, r) <= target:
            return HostSolution(x, iteration)
        q = matrix @ p
        alpha = rz / dot(p, q)
        x += alpha * p
        r -= alpha * q
        z = inverse_diagonal * r
        rz, rz_previous = dot(r, z), rz
        p = z + (rz / rz_previous) * p
    return HostSolution(x, max_iterations) if dot(r, r) <= target else None
