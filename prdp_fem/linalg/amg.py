"""Algebraic multigrid (AMG): one symmetric V-cycle of a pyamg hierarchy as a PCG preconditioner.

The hierarchy ``A_0 = A, A_{l+1} = R_l A_l P_l`` with ``R_l = P_l^T`` is built once on the host
by pyamg (smoothed aggregation by default, Ruge-Stueben on request) from the operator's *values*,
and is then a **fixed** linear map: not rebuilt per CG iteration, not differentiated with
respect to those values. One V-cycle ``z = M r`` with ``nu`` smoothing sweeps ``S``::

    V_l(b):  x = S_l^nu(0, b)                          pre-smoothing from zero
             x = x + P_l V_{l+1}(R_l (b - A_l x))      coarse correction
             x = S_l^nu(x, b)                          post-smoothing
    V_L(b) = A_L^+ b                                   coarsest: dense pseudo-inverse

With ``R_l = P_l^T`` and the post-smoother the adjoint of the pre-smoother, ``M`` is symmetric:
damped Jacobi ``S(x, b) = x + omega_l D_l^{-1} (b - A_l x)`` is its own adjoint, and a
symmetric Gauss-Seidel sweep (forward, then backward) is too. ``M`` is positive definite when
the smoothers converge in the energy norm (Jacobi: ``omega_l rho(D_l^{-1} A_l) < 2``).

Derivatives. ``M`` is linear in ``r`` and symmetric, so both implementations apply it through
one JAX primitive with exact linear rules: the tangent of ``z = M r`` is ``M dr`` and its
transpose is ``M ct`` (the cycle itself, not a structural transpose of its products); under
``vmap`` a batch of right-hand sides is one primitive call. The hierarchy arrays get no
derivative. So :func:`~prdp_fem.linalg.cg.solve` differentiates through it in both gradient modes,
under ``jit`` and ``vmap``.

Two implementations of the same cycle:

``"jax"`` (:class:`AMGCycle`)
    The level matrices as :class:`~prdp_fem.linalg.SparseMatrix` pytree leaves (arguments of
    the jitted solve, never closed-over constants), products through
    :func:`~prdp_fem.linalg.operator.matvec`, damped-Jacobi smoothing (parallel: one product per
    sweep) with ``omega_l = omega / rho(D_l^{-1} A_l)``. The coarse levels, from the first
    whose dense matrix is small (:func:`_first_dense_level`), are one dense matrix: ``V_l``
    itself, computed on the host. Runs on any backend, GPU included.
``"callback"`` (:class:`PyamgCycle`)
    ``jax.pure_callback`` into pyamg's own compiled cycle (``ml.aspreconditioner(cycle='V')``)
    on the CPU, symmetric Gauss-Seidel by default (fewer iterations than Jacobi).

Default: ``"jax"`` (:data:`DEFAULT_IMPLEMENTATION`), on every backend: ``prdp-fem bench amg``
(``docs/benchmarks.md``) measures our jitted PCG solving faster with the JAX cycle than with
pyamg's. Jacobi smoothing needs more iterations than symmetric Gauss-Seidel, but a JAX cycle is
a few fused products per level while pyamg's cycle is driven from Python (per-level calls, two
extra residual norms per application through ``aspreconditioner``) with a sequential smoother;
on an accelerator a callback would add a device-host round trip per iteration as well. The JAX
cycle costs more to compile. Setup is about pyamg's own: it adds the levels' kernels on the
device and estimates each level's spectral radius once, by Lanczos
(:func:`_smoothed_aggregation`), where pyamg estimates it twice by restarted Arnoldi. The
callback stays as the reference cycle and for smoothers the JAX cycle lacks.

Build once, eagerly, and pass the result (a hierarchy cannot be built from traced values)::

    M = amg_preconditioner(A)                 # a pytree with __call__(r) -> z
    sol = solve(A, b, ConvergedCG(rtol=1e-10, preconditioner=M))

>>> import numpy as np, scipy.sparse as sp
>>> from prdp_fem.linalg.operator import SparseMatrix
>>> n = 50
>>> A = SparseMatrix.from_scipy(sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n)))
>>> M = amg_preconditioner(A, implementation="jax", max_coarse=5)
>>> r, s = np.random.default_rng(0).standard_normal((2, n))
>>> bool(np.isclose(r @ M(s), s @ M(r)) and r @ M(r) > 0)
True
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
import scipy.sparse as sp
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir
from jax.typing import ArrayLike

from .._arrays import array_module  # NumPy for host values, jnp for JAX arrays
from .._checks import is_traced
from .._xla_options import AMG_CYCLE
from ..errors import DataError, ShapeError, SolverConfigError
from .operator import SparseMatrix, host_prepared

if TYPE_CHECKING:
    import pyamg

# pyamg is imported where a hierarchy is built or read, not here: it took 0.07-0.09 s of every
# import of this package, which solves without AMG never use

__all__ = [
    "DEFAULT_IMPLEMENTATION",
    "AMGCycle",
    "AMGLevel",
    "PyamgCycle",
    "RebuildPolicy",
    "RebuildState",
    "RebuiltAMG",
    "amg_hierarchy",
    "amg_preconditioner",
    "rebuild_policy",
]

KINDS = ("sa", "rs")
IMPLEMENTATIONS = ("jax", "callback")
SMOOTHERS = ("jacobi", "gauss_seidel")


#: The JAX cycle: faster than the callback on the CPU too (see the module docstring).
DEFAULT_IMPLEMENTATION = "jax"


# --------------------------------------------------------------------------------------
# the pyamg hierarchy (host)
# --------------------------------------------------------------------------------------


def amg_hierarchy(matrix: SparseMatrix | sp.spmatrix | sp.sparray, *, kind: str = "sa",
                  smoother: str = "jacobi", omega: float = 4.0 / 3.0, sweeps: int = 1,
                  max_coarse: int = 10, strength: Any = None) -> pyamg.MultilevelSolver:
    """The pyamg hierarchy of ``matrix`` with the same smoother on every level, pre and post.

    ``smoother="jacobi"``: damped Jacobi, ``omega_l = omega / rho(D_l^{-1} A_l)``
    (:func:`_rho_jacobi`), ``sweeps`` sweeps -- the smoother :class:`AMGCycle` implements, so
    the two cycles are the same map. ``"gauss_seidel"``: symmetric Gauss-Seidel (pyamg's
    default). ``kind="sa"`` with the symmetric strength (``None``, pyamg's default, or
    ``("symmetric", {"theta": t})``) is pyamg's smoothed aggregation run step by step
    (:func:`_smoothed_aggregation`); another ``strength`` is passed to pyamg's solver as is
    (``None`` with ``kind="rs"``: its default).

    >>> import scipy.sparse as sp
    >>> ml = amg_hierarchy(sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(100, 100)))
    >>> len(ml.levels) > 1 and ml.symmetric_smoothing
    True
    """
    from pyamg.relaxation.smoothing import change_smoothers

    _check_options(kind, smoother, omega, sweeps, max_coarse)
    csr = _host_matrix(matrix)
    theta = _symmetric_theta(strength) if kind == "sa" else None
    with seeded_numpy_random():
        try:
            if theta is not None:
                ml, radii = _smoothed_aggregation(csr, max_coarse, theta)
            else:
                ml, radii = _pyamg_solver(csr, kind, max_coarse, strength), None
        except (ValueError, TypeError, ArithmeticError) as error:
            raise SolverConfigError(f"kind={kind!r}, strength={strength!r}: pyamg could not "
                                    f"build a hierarchy ({error}); expected valid pyamg "
                                    "options and a symmetric positive definite matrix"
                                    ) from None
        if smoother == "jacobi":
            if radii is None:
                radii = [_rho_jacobi(level.A) for level in ml.levels[:-1]]
            # explicit per-level omega (withrho=False): AMGCycle reads back the exact values
            per_level = [("jacobi", {"omega": omega / rho, "withrho": False,
                                     "iterations": sweeps}) for rho in radii]
            change_smoothers(ml, per_level or None, per_level or None)
        else:
            symmetric_gs = ("gauss_seidel", {"sweep": "symmetric", "iterations": sweeps})
            change_smoothers(ml, symmetric_gs, symmetric_gs)
    _check_cycle(ml, f"kind={kind!r}")
    return ml


def _pyamg_solver(csr: sp.csr_matrix, kind: str, max_coarse: int,
                  strength: Any) -> pyamg.MultilevelSolver:
    """pyamg's own setup (its smoothers unset: :func:`amg_hierarchy` sets them)."""
    import pyamg

    options: dict[str, Any] = {"max_coarse": max_coarse, "presmoother": None,
                               "postsmoother": None}
    if strength is not None:
        options["strength"] = strength
    if kind == "sa":
        return pyamg.smoothed_aggregation_solver(csr, symmetry="symmetric", **options)
    return pyamg.ruge_stuben_solver(csr, **options)


def _symmetric_theta(strength: Any) -> float | None:
    """``theta`` of a symmetric strength of connection, in the spellings pyamg accepts for
    one setting on every level (``None``, ``"symmetric"``, ``("symmetric", {"theta": t})``);
    ``None`` for any other strength."""
    if strength is None or strength == "symmetric":
        return 0.0
    if isinstance(strength, tuple) and len(strength) == 2 and strength[0] == "symmetric" \
            and isinstance(strength[1], dict) and set(strength[1]) <= {"theta"}:
        theta = strength[1].get("theta", 0.0)
        return float(theta) if isinstance(theta, int | float) \
            and not isinstance(theta, bool) else None
    return None


#: pyamg's smoothed aggregation defaults that :func:`_smoothed_aggregation` runs
_MAX_LEVELS = 10
_IMPROVE_CANDIDATES = ("block_gauss_seidel", {"sweep": "symmetric", "iterations": 4})
_PROLONGATION_OMEGA = 4.0 / 3.0


def _smoothed_aggregation(csr: sp.csr_matrix, max_coarse: int,
                          theta: float = 0.0) -> tuple[pyamg.MultilevelSolver, list[float]]:
    r"""pyamg's ``smoothed_aggregation_solver(csr, symmetry="symmetric", strength=("symmetric",
    {"theta": theta}))`` with its other defaults, run step by step from pyamg's own parts, and
    the radius ``rho_l = rho(D_l^{-1} A_l)`` of each level above the coarsest
    (:func:`_rho_jacobi`).

    Per level: symmetric strength of connection, standard aggregation, the candidates
    ``B = 1`` improved by four symmetric block Gauss-Seidel sweeps on the finest level, the
    tentative prolongator ``T`` fitted to them, then

    .. math::

        P_l = \Bigl(I - \frac{4/3}{\rho_l} D_l^{-1} A_l\Bigr) T_l, \qquad
        R_l = P_l^T, \qquad A_{l+1} = R_l A_l P_l.

    pyamg estimates ``rho_l`` for ``P_l`` by restarted Arnoldi and keeps it to itself, and the
    Jacobi smoother needs the same radius: run here, one Lanczos estimate serves both. Given
    the same radii, the levels equal pyamg's to round-off (tested); this loop took 0.5-0.6x
    the time of pyamg's at 65k dofs.
    """
    import pyamg
    from pyamg.aggregation.aggregate import standard_aggregation
    from pyamg.aggregation.tentative import fit_candidates
    from pyamg.relaxation.utils import relaxation_as_linear_operator
    from pyamg.strength import symmetric_strength_of_connection
    from pyamg.util.utils import get_diagonal, scale_rows

    finest = pyamg.MultilevelSolver.Level()
    finest.A, finest.B = csr, np.ones((csr.shape[0], 1), dtype=csr.dtype)
    csr.symmetry = "symmetric"
    levels, radii = [finest], []
    while len(levels) < _MAX_LEVELS and levels[-1].A.shape[0] > max_coarse:
        level = levels[-1]
        strength = symmetric_strength_of_connection(level.A, theta=theta)
        aggregates, _ = standard_aggregation(strength)
        if len(levels) == 1:
            zero = np.zeros((level.A.shape[0], 1), dtype=level.A.dtype)
            level.B = relaxation_as_linear_operator(_IMPROVE_CANDIDATES, level.A, zero) @ level.B
        tentative, coarse_candidates = fit_candidates(aggregates, level.B)
        radii.append(_rho_jacobi(level.A))
        jacobi = (_PROLONGATION_OMEGA / radii[-1]) * scale_rows(
            level.A, get_diagonal(level.A, inv=True), copy=True)
        level.P = tentative - jacobi @ tentative
        level.R = level.P.T
        coarse = pyamg.MultilevelSolver.Level()
        coarse.A = level.R @ level.A @ level.P
        coarse.A.symmetry = "symmetric"
        coarse.B = coarse_candidates
        levels.append(coarse)
    return pyamg.MultilevelSolver(levels), radii


@contextlib.contextmanager
def seeded_numpy_random(seed: int = 0):
    """pyamg starts its spectral-radius estimates from NumPy's global generator: seed it for
    the build (the same matrix gives the same hierarchy) and give the caller's state back.
    Every pyamg build of the package runs in it (:func:`prdp_fem.fem.reference.amg_solve` too)."""
    saved = np.random.get_state()  # noqa: NPY002 (pyamg draws from the legacy generator)
    np.random.seed(seed)  # noqa: NPY002
    try:
        yield
    finally:
        np.random.set_state(saved)  # noqa: NPY002


#: The largest Jacobi ``omega``: ``omega_l rho`` stays 5 % below 2, beyond the estimate's error
_LARGEST_OMEGA = 1.9


def _check_options(kind, smoother, omega, sweeps, max_coarse) -> None:
    if kind not in KINDS:
        raise SolverConfigError(f"kind={kind!r}: expected one of {KINDS} (smoothed aggregation "
                                "or Ruge-Stueben)")
    if smoother not in SMOOTHERS:
        raise SolverConfigError(f"smoother={smoother!r}: expected one of {SMOOTHERS}")
    if isinstance(omega, bool) or not isinstance(omega, int | float) or \
            not 0 < omega <= _LARGEST_OMEGA:
        raise SolverConfigError(
            f"omega={omega!r}: expected a number in (0, {_LARGEST_OMEGA}] (the Jacobi damping "
            "is omega / rho(D^-1 A) with rho estimated from below, within a fraction of a "
            "percent: at omega rho >= 2 the V-cycle is no longer positive definite)")
    for name, value in (("sweeps", sweeps), ("max_coarse", max_coarse)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise SolverConfigError(f"{name}={value!r}: expected an integer >= 1")


def _host_matrix(matrix) -> sp.csr_matrix:
    """``matrix`` as a checked SciPy CSR matrix: concrete, square, finite, symmetric."""
    if isinstance(matrix, SparseMatrix):
        if is_traced(matrix.values):
            raise SolverConfigError(
                "matrix: its values are traced (inside jit/grad/vmap), but the AMG hierarchy is "
                "built on the host from concrete values; expected a concrete matrix: build "
                "amg_preconditioner(A) outside the transformation and pass it as an argument")
        csr = matrix.to_scipy()
    elif sp.issparse(matrix):
        csr = sp.csr_matrix(matrix, dtype=float)
    else:
        raise SolverConfigError(f"matrix: got {type(matrix).__name__}; expected a "
                                "prdp_fem.SparseMatrix or a SciPy sparse matrix")
    if csr.shape[0] != csr.shape[1] or csr.shape[0] == 0:
        raise ShapeError(f"matrix: shape {csr.shape}; expected a non-empty square matrix")
    csr.sum_duplicates()
    if not np.isfinite(csr.data).all():
        raise DataError(f"matrix: {int((~np.isfinite(csr.data)).sum())} stored value(s) are "
                        "NaN/Inf (check kappa); expected finite values")
    asymmetry = abs(csr - csr.T).max() if csr.nnz else 0.0
    if asymmetry > 1e-10 * max(abs(csr).max(), np.finfo(float).tiny):
        raise SolverConfigError(f"matrix: not symmetric (max |A - A^T| = {asymmetry:.3g}); "
                                "expected a symmetric positive definite matrix")
    if (csr.diagonal() <= 0).any():
        raise SolverConfigError("matrix: a diagonal entry is <= 0; expected a symmetric "
                                "positive definite matrix (kappa > 0, a Dirichlet boundary)")
    return csr


#: Lanczos steps of the Jacobi smoother's spectral radius (see :func:`_rho_jacobi`)
_LANCZOS_STEPS = 30


def _rho_jacobi(matrix: sp.spmatrix) -> float:
    """``rho(D^{-1} A)``, the largest eigenvalue of the symmetric ``D^{-1/2} A D^{-1/2}``,
    estimated by :data:`_LANCZOS_STEPS` steps of Lanczos from a fixed random start.

    pyamg's ``rho_D_inv_A`` runs restarted Arnoldi (up to 75 products, each orthogonalised
    against the whole basis, driven from Python): 2.5-3.5x the time per level at 30k-261k
    dofs, and pyamg's setup made the same estimate once more to smooth each prolongator
    (:func:`_smoothed_aggregation` now shares this one). Lanczos on the symmetric form keeps
    three vectors. Its largest Ritz value approaches ``rho`` from below (0.15 % below at 65k
    dofs after 30 steps, where pyamg's read 0.1 % below), so ``omega_l rho < 2`` holds for
    every ``omega`` up to :data:`_LARGEST_OMEGA`. The start does not draw from NumPy's global
    generator. A diagonal that is not finite gives NaN, for the check cycle to refuse; one
    with an entry <= 0 (no symmetric form) gets pyamg's estimate, drawn from the generator
    that :func:`amg_hierarchy` seeds.
    """
    csr = sp.csr_matrix(matrix)
    diagonal = csr.diagonal()
    if not np.all(np.isfinite(diagonal)):
        return float("nan")
    if not np.all(diagonal > 0):
        from pyamg.relaxation.smoothing import rho_D_inv_A

        return float(rho_D_inv_A(csr))
    scale = 1.0 / np.sqrt(diagonal)
    v = np.random.default_rng(0).standard_normal(csr.shape[0])
    v /= np.linalg.norm(v)
    previous, beta, alphas, betas = np.zeros_like(v), 0.0, [], []
    for _ in range(min(_LANCZOS_STEPS, csr.shape[0])):
        w = scale * (csr @ (scale * v)) - beta * previous
        alpha = float(v @ w)
        w -= alpha * v
        beta = float(np.linalg.norm(w))
        alphas.append(alpha)
        if not beta > np.finfo(float).eps * abs(alpha):  # an invariant subspace: exact
            break
        betas.append(beta)
        previous, v = v, w / beta
    k = len(alphas)
    ritz = np.linalg.eigvalsh(np.diag(alphas) + np.diag(betas[:k - 1], 1)
                              + np.diag(betas[:k - 1], -1))
    return float(ritz[-1])


def _check_cycle(ml: pyamg.MultilevelSolver, where: str) -> None:
    """One host cycle on a fixed vector: finite and ``r.Mr > 0``, else a clear error.

    Ruge-Stueben, for one, can break down (NaN) on 3-D P1 tetrahedra: say so at build time
    rather than inside a jitted solve.
    """
    n = ml.levels[0].A.shape[0]
    r = np.cos(np.arange(n) * 0.7) + 0.5  # deterministic, not aligned with a smooth mode
    try:
        with np.errstate(all="ignore"):
            z = ml.aspreconditioner(cycle="V") @ r
        ok = np.isfinite(z).all() and float(r @ z) > 0
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):  # e.g. pinv of a NaN matrix
        ok = False
    if not ok:
        raise SolverConfigError(
            f"{where}: the V-cycle of this hierarchy is not finite and positive (NaN/Inf or "
            "r.Mr <= 0; Ruge-Stueben can fail like this on 3-D P1 tetrahedra); expected an SPD "
            "cycle: use kind='sa' or another strength")


# --------------------------------------------------------------------------------------
# one primitive for a fixed symmetric linear map, with exact linear rules
# --------------------------------------------------------------------------------------

# its name keeps a program that applies it off XLA's classic CPU emitters (xla_options)
_symmetric_map_p = Primitive(AMG_CYCLE)


def _apply_impl(r, *leaves, cycle):
    """``cycle(r, *leaves)``: ``cycle`` is a hashable static object that applies ``M`` to every
    vector along the last axis of ``r``."""
    return cycle(r, *leaves)


_apply_jit = jax.jit(_apply_impl, static_argnames="cycle")


def _bind(cycle, r: jax.Array, leaves) -> jax.Array:
    return _symmetric_map_p.bind(r, *leaves, cycle=cycle)


def _abstract_eval(r, *leaves, cycle):
    return jax.core.ShapedArray(r.shape, r.dtype)


def _jvp(primals, tangents, *, cycle):
    r, *leaves = primals
    z = _bind(cycle, r, leaves)
    dr = tangents[0]  # the hierarchy is fixed: its leaves' tangents are ignored by design
    if type(dr) is ad.Zero:
        return z, ad.Zero.from_primal_value(z)
    return z, _bind(cycle, dr, leaves)


def _transpose(cotangent, r, *leaves, cycle):
    if any(ad.is_undefined_primal(leaf) for leaf in leaves):
        raise NotImplementedError("the AMG hierarchy is fixed: it has no transpose rule")
    if type(cotangent) is ad.Zero:
        return (ad.Zero(r.aval), *[None] * len(leaves))
    return (_bind(cycle, cotangent, leaves), *[None] * len(leaves))  # M^T = M


def _batch(args, dims, *, cycle):
    r, *leaves = args
    r_dim, *leaf_dims = dims
    if all(d is None for d in leaf_dims):  # None: not mapped
        # a batch of vectors under one hierarchy: one call on a (batch, ..., n) array
        return _bind(cycle, jnp.moveaxis(r, r_dim, 0), leaves), 0
    # hierarchies stacked along the batch axis (unusual): one cycle per member
    size = next(x.shape[d] for x, d in zip(args, dims, strict=True) if d is not None)
    moved = [x if d is None else jnp.moveaxis(x, d, 0) for x, d in zip(args, dims, strict=True)]

    def member(i):
        picked = [x if d is None else x[i] for x, d in zip(moved, dims, strict=True)]
        return _bind(cycle, picked[0], picked[1:])

    return jax.lax.map(member, jnp.arange(size)), 0


_symmetric_map_p.def_impl(lambda r, *leaves, cycle: _apply_jit(r, *leaves, cycle=cycle))
_symmetric_map_p.def_abstract_eval(_abstract_eval)
ad.primitive_jvps[_symmetric_map_p] = _jvp
ad.primitive_transposes[_symmetric_map_p] = _transpose
batching.primitive_batchers[_symmetric_map_p] = _batch
mlir.register_lowering(_symmetric_map_p, mlir.lower_fun(_apply_impl, multiple_results=False))


def _checked_vector(r, n: int) -> jax.Array:
    r = jnp.asarray(r)
    if r.ndim != 1 or r.shape[0] != n:
        raise ShapeError(f"r{tuple(r.shape)}: expected a vector of length {n} (the size of the "
                         "matrix the AMG hierarchy was built from)")
    return r


def _each_vector(apply_one: Callable[[jax.Array], jax.Array], r: jax.Array) -> jax.Array:
    """``apply_one`` on every vector along the last axis of ``r``."""
    if r.ndim == 1:
        return apply_one(r)
    return jax.vmap(apply_one)(r.reshape(-1, r.shape[-1])).reshape(r.shape)


# --------------------------------------------------------------------------------------
# "jax": the cycle in JAX on pytree leaves
# --------------------------------------------------------------------------------------


@partial(jax.tree_util.register_dataclass,
         data_fields=["matrix", "prolongation", "restriction", "smoother_scale"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class AMGLevel:
    """One level above the coarsest: ``A_l``, ``P_l``, ``R_l = P_l^T`` as prepared product
    kernels (:func:`~prdp_fem.linalg.operator.prepare`, once per build: the hierarchy is constant)
    and ``omega_l / diag(A_l)``."""

    matrix: Any
    prolongation: Any
    restriction: Any
    smoother_scale: jax.Array


@partial(jax.tree_util.register_dataclass, data_fields=["levels", "coarse_map"],
         meta_fields=["sweeps"])
@dataclasses.dataclass(frozen=True)
class AMGCycle:
    """The V-cycle in JAX: damped-Jacobi smoothing on ``levels``, the cycle below them (down
    to ``A_L^+`` on the coarsest level) as one dense matrix, ``coarse_map``.

    Build with :func:`amg_preconditioner` (``implementation="jax"``) or
    :meth:`from_pyamg`. A pytree: pass it to jitted functions as an argument.
    """

    levels: tuple[AMGLevel, ...]
    coarse_map: jax.Array  # the cycle below ``levels``, one dense matrix (_first_dense_level)
    sweeps: int

    @classmethod
    def from_pyamg(cls, ml: pyamg.MultilevelSolver) -> AMGCycle:
        """The arrays of a pyamg hierarchy whose smoothers are damped Jacobi (as
        :func:`amg_hierarchy` sets them with ``smoother="jacobi"``); same map as
        ``ml.aspreconditioner(cycle='V')``."""
        _check_cycle(ml, "hierarchy")
        return cls._from_checked(ml)

    @classmethod
    def _from_checked(cls, ml: pyamg.MultilevelSolver) -> AMGCycle:
        """:meth:`from_pyamg` of a hierarchy whose cycle :func:`amg_hierarchy` checked."""
        cut = _first_dense_level(ml)
        levels, tail, sweeps = [], [], 1  # device kernels above the cut, host products below
        for depth, level in enumerate(ml.levels[:-1]):
            omega, sweeps = _jacobi_parameters(level, depth)
            a = sp.csr_matrix(level.A)  # diagonal on the host: no compile per level shape
            product = _sparse if depth < cut else _HostProduct
            (levels if depth < cut else tail).append(AMGLevel(
                product(a), product(level.P), product(level.P.T), omega / a.diagonal()))
        coarsest = scipy.linalg.pinv(sp.csr_matrix(ml.levels[-1].A).toarray())
        # every level's arrays in one transfer: one call per matrix was a tenth of the build
        levels, coarse_map = jax.device_put((tuple(levels), _dense_map(tail, coarsest, sweeps)))
        return cls(levels, coarse_map, sweeps)

    @property
    def n(self) -> int:
        return self.levels[0].smoother_scale.shape[0] if self.levels \
            else self.coarse_map.shape[0]

    def __call__(self, r: jax.Array) -> jax.Array:
        r = _checked_vector(r, self.n)
        leaves, treedef = jax.tree_util.tree_flatten(self)
        return _bind(_JaxCycle(treedef), r, leaves)


def _sparse(matrix):
    """The product kernel of a host matrix (explicit zeros dropped), ELL: applied every cycle.

    Laid out and prepared in NumPy (NumPy leaves; the caller puts the hierarchy on the
    device): as eager JAX ops, the gathers of ``prepare`` were a sixth of a rebuild's time
    (65k dofs, six levels).
    """
    csr = sp.csr_matrix(matrix, dtype=float)
    csr.eliminate_zeros()
    return host_prepared(csr)


#: A level is applied as a dense matrix when that matrix holds at most this fraction of the
#: finest matrix's stored entries: its product then has at most half the multiplications of
#: one finest product, of which a cycle runs three or more, and is a contiguous BLAS product
#: rather than a gather per entry (at 250k dofs in 3-D, a dense level of 702 rows left the
#: solve's time unchanged) ...
_DENSE_FRACTION = 0.5
#: ... or has at most this many rows.
_DENSE_ROWS = 64


def _first_dense_level(ml: pyamg.MultilevelSolver) -> int:
    """The first level from which the JAX cycle applies the rest of the V-cycle as one dense
    matrix (the coarsest level at the latest).

    Every level costs the cycle's compilation about the same, whatever its size, while a
    coarse level's products are cheap to run. A dense tail cut the compile of the AMG-PCG
    solve from 1.4-1.7 s to 1.1-1.4 s on 2-D P1 at 65k dofs (levels of 136, 16 and 2 rows)
    and from 2.4-3.0 s to 1.1-1.4 s on 3-D P1 at 250k (702, 12 and 1), the solve's time
    unchanged.
    """
    bound = max(_DENSE_FRACTION * ml.levels[0].A.nnz, _DENSE_ROWS**2)
    return next((depth for depth, level in enumerate(ml.levels)
                 if level.A.shape[0] ** 2 <= bound), len(ml.levels) - 1)


@dataclasses.dataclass(frozen=True)
class _HostProduct:
    """``x -> (matrix @ x^T)^T`` on the host: a level's product on every row of ``x``."""

    matrix: Any

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(self.matrix @ x.T).T


def _dense_map(levels, coarsest: np.ndarray, sweeps: int) -> np.ndarray:
    """The V-cycle of ``levels`` above ``coarsest`` (``A_L^+``) as a dense matrix: the cycle
    :func:`_v_cycle` itself, run on the host on the identity's rows (that gives ``V^T``, so
    the result is ``V`` whether or not it is symmetric to the last bit)."""
    if not levels:
        return coarsest
    n = levels[0].smoother_scale.shape[0]
    return np.ascontiguousarray(_v_cycle(levels, coarsest, sweeps, np.eye(n)).T)


def _jacobi_parameters(level, depth: int) -> tuple[float, int]:
    """``(omega_l, sweeps)`` of a level whose pre- and post-smoothers are the same Jacobi."""
    from pyamg.relaxation import relaxation

    found = []
    for smoother in (level.presmoother, level.postsmoother):
        if getattr(smoother, "func", None) is not relaxation.jacobi:
            raise SolverConfigError(
                f"hierarchy: level {depth} smooths with {getattr(smoother, '__name__', smoother)}"
                "; expected damped Jacobi before and after (amg_hierarchy(..., "
                "smoother='jacobi')), the smoother the JAX cycle implements")
        found.append((float(smoother.keywords["omega"]), int(smoother.keywords["iterations"])))
    if found[0] != found[1]:
        raise SolverConfigError(f"hierarchy: level {depth} pre-smoother {found[0]} and "
                                f"post-smoother {found[1]} differ; expected the same (symmetry)")
    return found[0]


@dataclasses.dataclass(frozen=True)
class _JaxCycle:
    """Static part of :class:`AMGCycle` inside the primitive: how to rebuild it from leaves."""

    treedef: Any

    def __call__(self, r, *leaves):
        cycle = jax.tree_util.tree_unflatten(self.treedef, leaves)
        apply_one = partial(_v_cycle, cycle.levels, cycle.coarse_map, cycle.sweeps)
        return _each_vector(apply_one, r.astype(cycle.coarse_map.dtype)).astype(r.dtype)


def _v_cycle(levels, coarse_map, sweeps: int, b: jax.Array) -> jax.Array:
    """``V_l(b)`` of the module docstring (recursion unrolled at trace time), for every vector
    along the last axis of ``b``; below ``levels``, ``coarse_map @ b``."""
    if not levels:
        return b @ coarse_map.T
    level = levels[0]
    x = level.smoother_scale * b  # the first sweep from x = 0 needs no product
    x = _jacobi(level, b, x, sweeps - 1)
    residual = b - level.matrix(x)
    coarse = _v_cycle(levels[1:], coarse_map, sweeps, level.restriction(residual))
    x = x + level.prolongation(coarse)
    return _jacobi(level, b, x, sweeps)


def _jacobi(level: AMGLevel, b: jax.Array, x: jax.Array, sweeps: int) -> jax.Array:
    """``sweeps`` times ``x <- x + omega D^{-1} (b - A x)`` (Jacobi is its own adjoint)."""
    for _ in range(sweeps):
        x = x + level.smoother_scale * (b - level.matrix(x))
    return x


# --------------------------------------------------------------------------------------
# "callback": pyamg's own cycle on the host
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class _HostCycle:
    """pyamg's V-cycle as a host function; hashed by identity (one per build)."""

    hierarchy: pyamg.MultilevelSolver
    n: int
    operator: Any = dataclasses.field(init=False, repr=False)  # ml.aspreconditioner('V')

    def __post_init__(self):
        object.__setattr__(self, "operator", self.hierarchy.aspreconditioner(cycle="V"))

    def apply(self, r: np.ndarray) -> np.ndarray:
        flat = np.asarray(r, dtype=float).reshape(-1, self.n)
        out = np.stack([self.operator @ row for row in flat])
        return out.reshape(r.shape).astype(r.dtype)

    def __call__(self, r):
        return jax.pure_callback(self.apply, jax.ShapeDtypeStruct(r.shape, r.dtype), r)


@partial(jax.tree_util.register_dataclass, data_fields=[], meta_fields=["host"])
@dataclasses.dataclass(frozen=True)
class PyamgCycle:
    """pyamg's V-cycle through ``jax.pure_callback`` (CPU); no array leaves.

    The hierarchy is static metadata hashed by identity: a rebuilt preconditioner compiles
    the solve anew (so does :class:`AMGCycle` when the level sizes change).
    """

    host: _HostCycle

    @classmethod
    def from_pyamg(cls, ml: pyamg.MultilevelSolver) -> PyamgCycle:
        _check_cycle(ml, "hierarchy")
        return cls._from_checked(ml)

    @classmethod
    def _from_checked(cls, ml: pyamg.MultilevelSolver) -> PyamgCycle:
        """:meth:`from_pyamg` of a hierarchy whose cycle :func:`amg_hierarchy` checked."""
        if not ml.symmetric_smoothing:
            raise SolverConfigError("hierarchy: its pre- and post-smoothers are not adjoint; "
                                    "expected a symmetric cycle (CG needs an SPD "
                                    "preconditioner)")
        return cls(_HostCycle(ml, ml.levels[0].A.shape[0]))

    @property
    def hierarchy(self) -> pyamg.MultilevelSolver:
        return self.host.hierarchy

    @property
    def n(self) -> int:
        return self.host.n

    def __call__(self, r: jax.Array) -> jax.Array:
        return _bind(self.host, _checked_vector(r, self.n), ())


# --------------------------------------------------------------------------------------
# the front door
# --------------------------------------------------------------------------------------


def amg_preconditioner(matrix: SparseMatrix | sp.spmatrix | sp.sparray, *, kind: str = "sa",
                       implementation: str | None = None, smoother: str | None = None,
                       omega: float = 4.0 / 3.0, sweeps: int = 1, max_coarse: int = 10,
                       strength: Any = None) -> AMGCycle | PyamgCycle:
    """A V-cycle preconditioner for ``matrix`` (built now, on the host, from its values).

    Parameters
    ----------
    matrix
        Symmetric positive definite, concrete (not traced).
    kind
        ``"sa"`` (smoothed aggregation, default) or ``"rs"`` (Ruge-Stueben; 2-D problems).
    implementation
        ``"jax"`` or ``"callback"``; ``None`` means :data:`DEFAULT_IMPLEMENTATION`.
    smoother
        ``"jacobi"`` (the only one ``"jax"`` implements) or ``"gauss_seidel"`` (symmetric);
        ``None``: Jacobi for ``"jax"``, Gauss-Seidel for ``"callback"``.
    omega, sweeps, max_coarse, strength
        Jacobi damping ``omega / rho(D^-1 A)``, smoothing sweeps before and after, the size
        below which a level is solved directly, pyamg's strength-of-connection option.
    """
    implementation, smoother = _resolved(implementation, smoother)
    ml = amg_hierarchy(matrix, kind=kind, smoother=smoother, omega=omega, sweeps=sweeps,
                       max_coarse=max_coarse, strength=strength)
    return checked_cycle(ml, implementation)


def _resolved(implementation: str | None, smoother: str | None) -> tuple[str, str]:
    """``(implementation, smoother)`` with the defaults filled in, checked together."""
    implementation = DEFAULT_IMPLEMENTATION if implementation is None else implementation
    if implementation not in IMPLEMENTATIONS:
        raise SolverConfigError(f"implementation={implementation!r}: expected one of "
                                f"{IMPLEMENTATIONS}")
    if smoother is None:
        smoother = "jacobi" if implementation == "jax" else "gauss_seidel"
    if smoother not in SMOOTHERS:
        raise SolverConfigError(f"smoother={smoother!r}: expected one of {SMOOTHERS}")
    if implementation == "jax" and smoother != "jacobi":
        raise SolverConfigError(f"smoother={smoother!r}: implementation='jax' implements "
                                "'jacobi' only (a parallel smoother)")
    return implementation, smoother


def checked_cycle(ml: pyamg.MultilevelSolver, implementation: str) -> AMGCycle | PyamgCycle:
    """The ``implementation`` cycle of a hierarchy from :func:`amg_hierarchy`, which has run
    the check cycle already (``from_pyamg`` runs it again)."""
    cycle = AMGCycle if implementation == "jax" else PyamgCycle
    return cycle._from_checked(ml)


# --------------------------------------------------------------------------------------
# when to rebuild (optax style: pure state, init / update)
# --------------------------------------------------------------------------------------


class RebuildState(NamedTuple):
    """Steps since the last build and the values the hierarchy was built from."""

    steps_since_build: ArrayLike
    reference_values: ArrayLike


class RebuildPolicy(NamedTuple):
    """``init(values) -> state`` at a build; ``update(state, values) -> (rebuild, state)``."""

    init: Callable[[ArrayLike], RebuildState]
    update: Callable[[RebuildState, ArrayLike], tuple[ArrayLike, RebuildState]]


def rebuild_policy(*, every: int | None = None, factor: float | None = None) -> RebuildPolicy:
    """When to rebuild the hierarchy: every ``every`` optimiser steps, or once some value
    (kappa, or the operator values) has moved by more than ``factor`` since the last build,
    ``v / v_ref`` outside ``[1/factor, factor]`` (a sign change or NaN counts as moved).

    ``update`` returns ``rebuild`` (a bool array) and the state to keep: reset to the current
    values when ``rebuild`` (the caller then rebuilds), else one step older. Pure; it computes
    with NumPy on host values (no dispatch: :func:`prdp_fem.inverse.driver.invert` calls it every
    step) and with ``jnp`` on JAX arrays and under ``jit``. The rebuild itself happens on the
    host.

    >>> import jax.numpy as jnp
    >>> policy = rebuild_policy(every=3, factor=2.0)
    >>> state = policy.init(jnp.ones(4))
    >>> [bool(policy.update(state, jnp.full(4, v))[0]) for v in (1.5, 2.5, 0.4)]
    [False, True, True]
    >>> for step in range(3):
    ...     rebuild, state = policy.update(state, jnp.ones(4))
    >>> bool(rebuild), int(state.steps_since_build)
    (True, 0)
    """
    if every is None and factor is None:
        raise SolverConfigError("every=None, factor=None: expected at least one rebuild "
                                "criterion")
    if every is not None and (isinstance(every, bool) or not isinstance(every, int)
                              or every < 1):
        raise SolverConfigError(f"every={every!r}: expected an integer >= 1 (optimiser steps)")
    if factor is not None and (isinstance(factor, bool) or not isinstance(factor, int | float)
                               or not 1 < factor < np.inf):
        raise SolverConfigError(f"factor={factor!r}: expected a finite number > 1")

    def init(values) -> RebuildState:
        xp = array_module(values)
        return RebuildState(xp.zeros((), np.int32), xp.asarray(values))

    def update(state: RebuildState, values) -> tuple[ArrayLike, RebuildState]:
        xp = array_module(*state, values)
        with np.errstate(divide="ignore", invalid="ignore"):  # NaN values count as moved
            values = xp.asarray(values)
            steps = state.steps_since_build + 1
            rebuild = xp.asarray(False)
            if every is not None:
                rebuild = rebuild | (steps >= every)
            if factor is not None:
                rebuild = rebuild | _moved(xp, values, state.reference_values, factor)
            kept = RebuildState(steps, state.reference_values)
            fresh = RebuildState(xp.zeros_like(steps), values)
            return rebuild, RebuildState(*(xp.where(rebuild, new, old)
                                           for new, old in zip(fresh, kept, strict=True)))

    return RebuildPolicy(init, update)


def _moved(xp, values: ArrayLike, reference: ArrayLike, factor: float) -> ArrayLike:
    """Some ``values / reference`` outside ``[1/factor, factor]`` (0/0 counts as unmoved)."""
    nonzero = reference != 0
    ratio = xp.where(nonzero, values / xp.where(nonzero, reference, 1.0),
                     xp.where(values == 0, 1.0, np.inf))
    within = (ratio >= 1.0 / factor) & (ratio <= factor)  # False for NaN and sign changes
    return ~xp.all(within)


# --------------------------------------------------------------------------------------
# a preconditioner that an inversion rebuilds
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class RebuiltAMG:
    """An AMG preconditioner that :func:`prdp_fem.inverse.driver.invert` builds from the operator
    at the current coefficient, and builds again whenever ``policy`` says so (``None``: built
    at the start and kept).

    ``invert(problem, preconditioner=RebuiltAMG(rebuild_policy(every=10)))`` builds
    :func:`amg_preconditioner` of ``A(kappa(z_0))`` before the first step, then after every
    step asks ``policy.update(state, kappa(z_k))``. When it says rebuild, the next step (if
    any) starts by building the hierarchy of ``A(kappa(z_k))``. Every build is run time (the
    first counted in the first step's time): the setup is part of the method's cost, and a
    saving that left it out would flatter an AMG run against a Jacobi one (a hierarchy passed
    in as an :class:`AMGCycle` is the caller's, built before the run and not timed). After a
    rebuild the optimiser's stored value is recomputed with it (with
    truncated solves: a converged ``J`` does not depend on the preconditioner). The JAX
    cycle is an argument of the step program, so a hierarchy of the same shapes runs the
    step already compiled; other shapes, or the ``"callback"`` cycle (closed over), compile
    a new one. ``StepRecord.rebuilds`` counts the rebuilds, from the step that first uses
    each. The other arguments are :func:`amg_preconditioner`'s, checked here.

    A source inversion never changes ``kappa``: only ``every`` rebuilds it, to no use.
    """

    policy: RebuildPolicy | None = None
    kind: str = "sa"
    implementation: str | None = None
    smoother: str | None = None
    omega: float = 4.0 / 3.0
    sweeps: int = 1
    max_coarse: int = 10
    strength: Any = None

    def __post_init__(self):
        if self.policy is not None and not isinstance(self.policy, RebuildPolicy):
            raise SolverConfigError(f"policy={self.policy!r}: expected None or a RebuildPolicy "
                                    "from prdp_fem.rebuild_policy(every=..., factor=...)")
        _, smoother = _resolved(self.implementation, self.smoother)
        _check_options(self.kind, smoother, self.omega, self.sweeps, self.max_coarse)

    def build(self, matrix: SparseMatrix | sp.spmatrix | sp.sparray) -> AMGCycle | PyamgCycle:
        """:func:`amg_preconditioner` of ``matrix`` with these options."""
        return amg_preconditioner(matrix, kind=self.kind, implementation=self.implementation,
                                  smoother=self.smoother, omega=self.omega,
                                  sweeps=self.sweeps, max_coarse=self.max_coarse,
                                  strength=self.strength)
