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

from .._checks import finite_vector
from .._transfer import as_jax
from ..errors import DataError, SensorError, ShapeError, SolverConfigError
from ..linalg.operator import FixedMatrix
from .discretization import Discretization

__all__ = ["Observation", "boundary_values", "full_field", "point_sensors", "with_noise"]


@partial(jax.tree_util.register_dataclass, data_fields=["operator", "weight", "data",
                                                         "noise_std", "weight_trace"],
         meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Observation:
    """``B`` (n_obs x n_dofs), ``W`` (n_obs x n_obs), data ``d`` and its noise ``sigma``.

    ``B`` and ``W`` are constant: :class:`~prdp_fem.linalg.operator.FixedMatrix` products laid out
    once (``W`` as a symmetric one), not in every evaluation; ``weight_trace`` is ``tr W``.
    """

    operator: FixedMatrix
    weight: FixedMatrix
    data: jax.Array
    noise_std: jax.Array
    weight_trace: jax.Array

    @property
    def size(self) -> int:
        return int(self.data.shape[0])

    def residual(self, u: jax.Array) -> jax.Array:
        return self.operator(u) - self.data

    def misfit(self, u: jax.Array) -> jax.Array:
        """``1/2 ||B u - d||_W^2``."""
        r = self.residual(u)
        return 0.5 * jnp.vdot(r, self.weight(r))

    def misfit_norm(self, u: jax.Array) -> jax.Array:
        """``||B u - d||_W`` (compare with :meth:`noise_norm`)."""
        return jnp.sqrt(2.0 * jnp.maximum(self.misfit(u), 0.0))

    def noise_norm(self) -> jax.Array:
        """Expected ``||eta||_W = sigma sqrt(tr W)``: the discrepancy principle's target."""
        return self.noise_std * jnp.sqrt(self.weight_trace)

    def clean(self, data: np.ndarray) -> Observation:
        """The same operator with other (noise-free) data."""
        return dataclasses.replace(self, data=jnp.asarray(data, jnp.float64),
                                   noise_std=as_jax(0.0))


def _observation(operator: sp.spmatrix, weight: sp.spmatrix, u_true: np.ndarray | None,
                 data: np.ndarray | None) -> Observation:
    n_obs, n_dofs = operator.shape
    if (u_true is None) == (data is None):
        raise DataError("observation: expected exactly one of u_true= (observed through B) "
                        "or data= (the observed values)")
    if u_true is not None:
        data = operator @ finite_vector(u_true, "u_true (nodal state, all dofs)", n_dofs)
    data = finite_vector(data, "data (observed values)", n_obs)
    return Observation(FixedMatrix.from_scipy(operator), FixedMatrix.symmetric(weight),
                       as_jax(data), as_jax(0.0), as_jax(float(weight.diagonal().sum())))


def full_field(disc: Discretization, *, u_true: np.ndarray | None = None,
               data: np.ndarray | None = None, norm: str = "l2") -> Observation:
    """Every dof observed; ``norm="l2"`` weighs with the mass matrix, ``"nodal"`` with ``I``.

    Pass the true state ``u_true`` (nodal, all dofs) or the ``data`` directly; for data given
    as a function use :meth:`Discretization.project` (its L2 projection gives the same
    minimiser as the misfit against the function itself).
    """
    if norm not in ("l2", "nodal"):
        raise SolverConfigError(f"norm={norm!r}: expected 'l2' or 'nodal'")
    identity = sp.identity(disc.n_dofs, format="csr")
    weight = disc.mass_matrix if norm == "l2" else identity
    return _observation(identity, weight, u_true, data)


def point_sensors(disc: Discretization, points: np.ndarray, *,
                  u_true: np.ndarray | None = None,
                  data: np.ndarray | None = None) -> Observation:
    """Point values at ``points`` (shape ``(n_sensors, dim)``) by FE interpolation."""
    dim = disc.mesh.dim()
    try:
        points = np.atleast_2d(np.asarray(points, dtype=float))
    except (TypeError, ValueError):
        raise ShapeError(f"points: expected an array of shape (n_sensors, {dim}), got "
                         f"{points!r:.80}") from None
    if points.ndim != 2 or points.shape[1] != dim:
        raise ShapeError(f"points: expected coordinates of shape (n_sensors, {dim}), got "
                         f"{points.shape}")
    if len(points) == 0:
        raise SensorError(f"points: an empty sensor set (shape {points.shape}); expected at "
                          "least one sensor")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise SensorError(f"points: {int(bad.sum())} sensor(s) have NaN/Inf coordinates "
                          f"(first: sensor {i} at {points[i].tolist()}); expected finite "
                          "coordinates inside the mesh")
    try:
        probes = disc.basis.probes(points.T).tocsr()
        inside = np.asarray(np.abs(probes).sum(axis=1)).ravel() > 0
    except ValueError as exc:  # skfem: a point in no element; find which, one at a time
        inside = np.array([_inside(disc, p) for p in points])
        if inside.all():
            raise SensorError(f"points: the sensors could not be located in the mesh ({exc}); "
                              "expected every sensor inside the mesh") from None
    if not inside.all():
        outside = np.flatnonzero(~inside)
        raise SensorError(f"points: {len(outside)} sensor(s) lie outside the mesh (first: "
                          f"sensor {int(outside[0])} at {points[outside[0]].tolist()}); "
                          "expected every sensor inside the mesh")
    return _observation(probes, sp.identity(len(points), format="csr"), u_true, data)


def _inside(disc: Discretization, point: np.ndarray) -> bool:
    try:
        return bool(abs(disc.basis.probes(point[:, None])).sum() > 0)
    except ValueError:
        return False


def boundary_values(disc: Discretization, boundaries: Sequence[str], *,
                    u_true: np.ndarray | None = None,
                    data: np.ndarray | None = None) -> Observation:
    """Nodal values on the named boundaries (e.g. a measured Neumann side), weighted by ``I``."""
    names = disc.mesh.boundaries or {}
    if isinstance(boundaries, str):
        raise SensorError(f"boundaries={boundaries!r}: expected a list of boundary names "
                          f"among {sorted(names)}, not a single string")
    missing = [b for b in boundaries if b not in names]
    if not boundaries:
        raise SensorError(f"boundaries={list(boundaries)!r}: an empty sensor set; expected names "
                          f"among {sorted(names)}")
    if missing:
        raise SensorError(f"boundaries={list(boundaries)!r}: unknown {missing[0]!r}; expected "
                          f"names among {sorted(names)}")
    facets = np.concatenate([names[b] for b in boundaries])
    dofs = np.unique(disc.basis.get_dofs(facets=facets).all())
    if np.isin(dofs, disc.dirichlet_dofs).all():
        raise SensorError(f"boundaries={list(boundaries)!r}: every observed dof carries Dirichlet "
                           "data, so the observation does not depend on the unknown; expected a "
                           "boundary with a Neumann or natural condition")
    selection = sp.csr_matrix((np.ones(len(dofs)), (np.arange(len(dofs)), dofs)),
                              shape=(len(dofs), disc.n_dofs))
    return _observation(selection, sp.identity(len(dofs), format="csr"), u_true, data)


def with_noise(observation: Observation, level: float, seed: int = 0) -> Observation:
    """Add Gaussian noise ``sigma = level * max|d|`` (hIPPYlib's convention), seeded."""
    try:
        valid = bool(np.isfinite(level) and level >= 0) and np.ndim(level) == 0
    except (TypeError, ValueError):
        valid = False
    if not valid:
        raise DataError(f"noise level={level!r}: expected a finite number >= 0")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise DataError(f"noise seed={seed!r}: expected an integer >= 0")
    data = np.asarray(observation.data)
    sigma = float(level) * float(np.max(np.abs(data)))
    noise = sigma * np.random.default_rng(seed).standard_normal(data.shape)
    return dataclasses.replace(observation, data=as_jax(data + noise),
                               noise_std=as_jax(sigma))
