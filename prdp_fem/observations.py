r"""Observations of the state: ``d = B u + eta`` and the weighted misfit.

An :class:`Observation` holds a linear observation operator ``B`` (on the full nodal state), a
symmetric positive semi-definite weight ``W`` and the data ``d``:

.. math::

    \Phi(u) = \tfrac12 (B u - d)^\top W (B u - d), \qquad
    \mathbb{E}\,\|\eta\|_W^2 = \sigma^2 \operatorname{tr} W

for white noise of standard deviation ``sigma`` (the noise level the discrepancy principle aims
at). Builders: :func:`full_field` (``W`` the mass matrix: the L2 misfit of hIPPYlib and
dolfin-adjoint, or identity), :func:`point_sensors` (interpolation at points) and
:func:`boundary_values` (the dofs on tagged boundaries). :func:`with_noise` adds seeded Gaussian
noise at a relative level.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from .discretization import Discretization
from .errors import PrdpFemError
from .operator import SparseMatrix, matvec

__all__ = ["Observation", "boundary_values", "full_field", "point_sensors", "with_noise"]


@partial(jax.tree_util.register_dataclass, data_fields=["operator", "weight", "data",
                                                         "noise_std"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Observation:
    """``B`` (n_obs x n_dofs), ``W`` (n_obs x n_obs), data ``d`` and its noise ``sigma``."""

    operator: SparseMatrix
    weight: SparseMatrix
    data: jax.Array
    noise_std: jax.Array

    @property
    def size(self) -> int:
        return int(self.data.shape[0])

    def residual(self, u: jax.Array) -> jax.Array:
        return matvec(self.operator, u) - self.data

    def misfit(self, u: jax.Array) -> jax.Array:
        """``1/2 ||B u - d||_W^2``."""
        r = self.residual(u)
        return 0.5 * jnp.vdot(r, matvec(self.weight, r))

    def misfit_norm(self, u: jax.Array) -> jax.Array:
        """``||B u - d||_W`` (compare with :meth:`noise_norm`)."""
        return jnp.sqrt(2.0 * jnp.maximum(self.misfit(u), 0.0))

    def noise_norm(self) -> jax.Array:
        """Expected ``||eta||_W = sigma sqrt(tr W)``: the discrepancy principle's target."""
        trace = jnp.sum(jnp.where(self.weight.rows == self.weight.cols, self.weight.values, 0.0))
        return self.noise_std * jnp.sqrt(trace)

    def clean(self, data: np.ndarray) -> Observation:
        """The same operator with other (noise-free) data."""
        return dataclasses.replace(self, data=jnp.asarray(data, jnp.float64),
                                   noise_std=jnp.zeros(()))


def _observation(operator: sp.spmatrix, weight: sp.spmatrix, u_true: np.ndarray | None,
                 data: np.ndarray | None) -> Observation:
    n_obs, n_dofs = operator.shape
    if (u_true is None) == (data is None):
        raise PrdpFemError("observation: expected exactly one of u_true= (observed through B) "
                           "or data= (the observed values)")
    if u_true is not None:
        u_true = np.asarray(u_true, dtype=float)
        if u_true.shape != (n_dofs,) or not np.isfinite(u_true).all():
            raise PrdpFemError(f"u_true: expected {n_dofs} finite nodal values, got shape "
                               f"{u_true.shape}")
        data = operator @ u_true
    data = np.asarray(data, dtype=float)
    if data.shape != (n_obs,) or not np.isfinite(data).all():
        raise PrdpFemError(f"data: expected {n_obs} finite values, got shape {data.shape}")
    return Observation(SparseMatrix.from_scipy(operator), SparseMatrix.from_scipy(weight),
                       jnp.asarray(data), jnp.zeros(()))


def full_field(disc: Discretization, *, u_true: np.ndarray | None = None,
               data: np.ndarray | None = None, norm: str = "l2") -> Observation:
    """Every dof observed; ``norm="l2"`` weighs with the mass matrix, ``"nodal"`` with ``I``.

    Pass the true state ``u_true`` (nodal, all dofs) or the ``data`` directly; for data given
    as a function use :meth:`Discretization.project` (its L2 projection gives the same
    minimiser as the misfit against the function itself).
    """
    if norm not in ("l2", "nodal"):
        raise PrdpFemError(f"norm={norm!r}: expected 'l2' or 'nodal'")
    identity = sp.identity(disc.n_dofs, format="csr")
    weight = disc.mass_matrix if norm == "l2" else identity
    return _observation(identity, weight, u_true, data)


def point_sensors(disc: Discretization, points: np.ndarray, *,
                  u_true: np.ndarray | None = None,
                  data: np.ndarray | None = None) -> Observation:
    """Point values at ``points`` (shape ``(n_sensors, dim)``) by FE interpolation."""
    points = np.atleast_2d(np.asarray(points, dtype=float))
    dim = disc.mesh.dim()
    if points.ndim != 2 or points.shape[1] != dim or not np.isfinite(points).all():
        raise PrdpFemError(f"points: expected finite coordinates of shape (n_sensors, {dim}), "
                           f"got {points.shape}")
    try:
        probes = disc.basis.probes(points.T).tocsr()
    except ValueError as exc:  # skfem: a point in no element
        raise PrdpFemError(f"points: every sensor must lie inside the mesh ({exc})") from None
    inside = np.asarray(np.abs(probes).sum(axis=1)).ravel() > 0
    if not inside.all():
        raise PrdpFemError(f"points: sensors {np.flatnonzero(~inside)[:5].tolist()} lie outside "
                           "the mesh")
    return _observation(probes, sp.identity(len(points), format="csr"), u_true, data)


def boundary_values(disc: Discretization, boundaries: Sequence[str], *,
                    u_true: np.ndarray | None = None,
                    data: np.ndarray | None = None) -> Observation:
    """Nodal values on the named boundaries (e.g. a measured Neumann side), weighted by ``I``."""
    names = disc.mesh.boundaries or {}
    missing = [b for b in boundaries if b not in names]
    if missing or not boundaries:
        raise PrdpFemError(f"boundaries={list(boundaries)!r}: expected names among "
                           f"{sorted(names)}")
    facets = np.concatenate([names[b] for b in boundaries])
    dofs = np.unique(disc.basis.get_dofs(facets=facets).all())
    if np.isin(dofs, disc.dirichlet_dofs).all():
        raise PrdpFemError(f"boundaries={list(boundaries)!r}: every observed dof carries Dirichlet "
                           "data, so the observation does not depend on the unknown; expected a "
                           "boundary with a Neumann or natural condition")
    selection = sp.csr_matrix((np.ones(len(dofs)), (np.arange(len(dofs)), dofs)),
                              shape=(len(dofs), disc.n_dofs))
    return _observation(selection, sp.identity(len(dofs), format="csr"), u_true, data)


def with_noise(observation: Observation, level: float, seed: int = 0) -> Observation:
    """Add Gaussian noise ``sigma = level * max|d|`` (hIPPYlib's convention), seeded."""
    if not (np.isfinite(level) and level >= 0):
        raise PrdpFemError(f"noise level={level!r}: expected a finite number >= 0")
    data = np.asarray(observation.data)
    sigma = float(level) * float(np.max(np.abs(data)))
    noise = sigma * np.random.default_rng(seed).standard_normal(data.shape)
    return dataclasses.replace(observation, data=jnp.asarray(data + noise),
                               noise_std=jnp.asarray(sigma))
