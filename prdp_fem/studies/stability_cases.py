"""The stiff and extreme cases of the stability suite: each a small, seeded problem.

A case builds only when run (:attr:`StabilityCase.build`), so listing the catalogue is free.
Groups:

``contrast``
    ``kappa`` contrast 1, 1e3, 1e6, 1e10: a disk inclusion, a 4 x 4 checkerboard, and smooth
    log-normal random fields ``exp(sigma g)`` with ``sigma`` up to 5 (contrast ~1e13).
``anisotropy``
    A rotated tensor ``kappa = R diag(1, ratio) R'`` with ratio down to 1e-6.
``mesh``
    Cell aspect ratios 1e2 and 1e4, cap triangles with angles near 0 and pi, geometric grading
    with ``h_max / h_min = 1e3``.
``scale``
    The unit square scaled to 1e-6 and 1e6 (the solution scales as ``L^2``).
``neumann``
    Pure Neumann with balanced data (the constants are the nullspace), and with unbalanced
    data, which must be refused with :class:`~prdp_fem.errors.IncompatibleDataError`.
``precision``
    float32 on a benign and a high-contrast problem: its limits (rtol ~1e-5 at best, errors
    ~ ``kappa(MA) * 1e-7``) are stated by the flags it raises.
``element``
    P2 and a 3-D tetrahedral inclusion.

Every case also runs ``K = 0, 1`` and ``K = 10 n`` (see :mod:`prdp_fem.studies.stability`).

>>> [case.name for case in CASES if case.group == "neumann"]
['neumann_balanced', 'neumann_unbalanced']
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import scipy.spatial

from ..errors import IncompatibleDataError, PrdpFemError
from ..fem.discretization import Discretization, discretize
from ..mesh.generators import geometric_spacing, tensor_mesh, unit_cube, unit_square
from ..mesh.io import mesh_from_arrays

__all__ = ["CASES", "CaseProblem", "StabilityCase", "case_named"]

N_SIDE = 20  # cells per side in 2-D: a few hundred dofs, so K = 10 n unrolled stays cheap


class CaseProblem(NamedTuple):
    """What a case builds: the discretisation, ``kappa`` and the nodal source ``f``."""

    disc: Discretization
    kappa: np.ndarray
    source: np.ndarray


@dataclasses.dataclass(frozen=True)
class StabilityCase:
    """One case: a name, its group, a one-line description and a builder.

    ``dtype`` is the working precision of the JAX solves; ``expected_error`` an error type
    the case must raise (eagerly) and flag (under ``jit``) instead of solving; ``fast`` puts it
    in the default test subset.
    """

    name: str
    group: str
    description: str
    build: Callable[[], CaseProblem]
    dtype: str = "float64"
    expected_error: type[Exception] | None = None
    fast: bool = False


# --------------------------------------------------------------------------------------
# coefficient fields
# --------------------------------------------------------------------------------------


def _inclusion(contrast: float) -> Callable[[np.ndarray], np.ndarray]:
    return lambda x: np.where((x[0] - 0.5) ** 2 + (x[1] - 0.5) ** 2 < 0.25 ** 2, contrast, 1.0)


def _checkerboard(contrast: float, squares: int = 4) -> Callable[[np.ndarray], np.ndarray]:
    def field(x):
        parity = (np.floor(squares * x[0]) + np.floor(squares * x[1])) % 2
        return np.where(parity == 1, contrast, 1.0)
    return field


def _lognormal(sigma: float, seed: int, length: float = 0.2,
               modes: int = 64) -> Callable[[np.ndarray], np.ndarray]:
    """``exp(sigma g)``, ``g`` a smooth, unit-variance Gaussian field (random Fourier features)."""
    rng = np.random.default_rng(seed)
    frequencies = rng.standard_normal((modes, 2)) / length
    phases = rng.uniform(0.0, 2.0 * np.pi, modes)

    def field(x):
        g = np.sqrt(2.0 / modes) * np.cos(np.tensordot(frequencies, x[:2], axes=1)
                                           + phases[:, None]).sum(axis=0)
        return np.exp(sigma * g)
    return field


def _rotated_tensor(ratio: float, angle: float) -> Callable[[np.ndarray], np.ndarray]:
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[c, -s], [s, c]])
    tensor = rotation @ np.diag([1.0, ratio]) @ rotation.T
    return lambda x: tensor


def _unit_source(disc: Discretization) -> np.ndarray:
    return np.ones(disc.n_dofs)


# --------------------------------------------------------------------------------------
# builders
# --------------------------------------------------------------------------------------


def _scalar(mesh, kappa_fn, element: str = "P1") -> CaseProblem:
    disc = discretize(mesh, element=element, kappa_space="P0")
    return CaseProblem(disc, disc.interpolate_kappa(kappa_fn), _unit_source(disc))


def _anisotropic(ratio: float) -> Callable[[], CaseProblem]:
    def build():
        disc = discretize(unit_square(N_SIDE), kappa_space="P0", kappa_kind="tensor")
        return CaseProblem(disc, disc.interpolate_kappa(_rotated_tensor(ratio, np.pi / 6)),
                           _unit_source(disc))
    return build


def _cap_triangles(n: int = N_SIDE, lift: float = 1e-3):
    """Unit square whose middle row of nodes sits ``lift * h`` above the row below, shifted by
    ``h / 2``: Delaunay joins them into cap triangles (angles ~``2 lift`` and ~``pi``)."""
    h = 1.0 / n
    x = np.linspace(0.0, 1.0, n + 1)
    rows = []
    for j in range(n + 1):
        if j == n // 2:
            xs = np.concatenate([[0.0], (np.arange(n) + 0.5) * h, [1.0]])
            rows.append(np.column_stack([xs, np.full(len(xs), (j - 1 + lift) * h)]))
        else:
            rows.append(np.column_stack([x, np.full(n + 1, j * h)]))
    points = np.vstack(rows)
    cells = scipy.spatial.Delaunay(points).simplices
    mesh = mesh_from_arrays(points, cells, "triangle", source="<cap triangles>")
    return mesh


def _neumann(balanced: bool) -> Callable[[], CaseProblem]:
    def build():
        disc = discretize(unit_square(N_SIDE), dirichlet=None)
        f = disc.interpolate(lambda x: np.cos(np.pi * x[0]) * np.cos(2 * np.pi * x[1]) + 0.1)
        return CaseProblem(disc, np.ones(disc.n_kappa),
                           disc.balance_source(f) if balanced else f)
    return build


def _scaled(length: float) -> Callable[[], CaseProblem]:
    return lambda: _scalar(tensor_mesh(*[np.linspace(0.0, length, N_SIDE + 1)] * 2),
                           lambda x: np.ones(x.shape[1:]))


def _aspect(ratio: float) -> Callable[[], CaseProblem]:
    return lambda: _scalar(tensor_mesh(np.linspace(0.0, 1.0, N_SIDE + 1),
                                       np.linspace(0.0, 1.0 / ratio, N_SIDE + 1)),
                           lambda x: np.ones(x.shape[1:]))


CASES: tuple[StabilityCase, ...] = (
    StabilityCase("contrast_1", "contrast", "kappa = 1 (baseline)",
        lambda: _scalar(unit_square(N_SIDE), lambda x: np.ones(x.shape[1:])), fast=True),
    StabilityCase("inclusion_1e3", "contrast", "disk inclusion, contrast 1e3",
        lambda: _scalar(unit_square(N_SIDE), _inclusion(1e3))),
    StabilityCase("inclusion_1e6", "contrast", "disk inclusion, contrast 1e6",
        lambda: _scalar(unit_square(N_SIDE), _inclusion(1e6))),
    StabilityCase("inclusion_1e10", "contrast", "disk inclusion, contrast 1e10",
        lambda: _scalar(unit_square(N_SIDE), _inclusion(1e10)), fast=True),
    StabilityCase("checkerboard_1e6", "contrast", "4 x 4 checkerboard, contrast 1e6",
        lambda: _scalar(unit_square(N_SIDE), _checkerboard(1e6))),
    StabilityCase("checkerboard_1e10", "contrast", "4 x 4 checkerboard, contrast 1e10",
        lambda: _scalar(unit_square(N_SIDE), _checkerboard(1e10))),
    StabilityCase("lognormal_s1", "contrast", "log-normal field, sigma 1",
        lambda: _scalar(unit_square(N_SIDE), _lognormal(1.0, seed=1))),
    StabilityCase("lognormal_s3", "contrast", "log-normal field, sigma 3",
        lambda: _scalar(unit_square(N_SIDE), _lognormal(3.0, seed=3))),
    StabilityCase("lognormal_s5", "contrast", "log-normal field, sigma 5",
        lambda: _scalar(unit_square(N_SIDE), _lognormal(5.0, seed=5))),
    StabilityCase("anisotropy_1e-3", "anisotropy", "tensor kappa, ratio 1e-3, rotated 30 deg",
        _anisotropic(1e-3)),
    StabilityCase("anisotropy_1e-6", "anisotropy", "tensor kappa, ratio 1e-6, rotated 30 deg",
        _anisotropic(1e-6), fast=True),
    StabilityCase("aspect_1e2", "mesh", "cells of aspect ratio 1e2",
        _aspect(1e2)),
    StabilityCase("aspect_1e4", "mesh", "cells of aspect ratio 1e4",
        _aspect(1e4), fast=True),
    StabilityCase("cap_triangles", "mesh", "a row of cap triangles (angles ~2e-3 rad and ~pi)",
        lambda: _scalar(_cap_triangles(), lambda x: np.ones(x.shape[1:]))),
    StabilityCase("graded_1e3", "mesh", "geometric grading, h_max / h_min = 1e3",
        lambda: _scalar(tensor_mesh(geometric_spacing(N_SIDE, 1e3),
                                      geometric_spacing(N_SIDE, 1e3)),
                          lambda x: np.ones(x.shape[1:]))),
    StabilityCase("scale_1e-6", "scale", "unit square scaled to 1e-6", _scaled(1e-6)),
    StabilityCase("scale_1e6", "scale", "unit square scaled to 1e6", _scaled(1e6)),
    StabilityCase("neumann_balanced", "neumann",
                  "pure Neumann, balanced data (nullspace handled)",
        _neumann(balanced=True), fast=True),
    StabilityCase("neumann_unbalanced", "neumann",
                  "pure Neumann, unbalanced data (must be refused)",
        _neumann(balanced=False), expected_error=IncompatibleDataError, fast=True),
    StabilityCase("float32_contrast_1", "precision", "float32, kappa = 1",
        lambda: _scalar(unit_square(N_SIDE), lambda x: np.ones(x.shape[1:])),
        dtype="float32", fast=True),
    StabilityCase("float32_inclusion_1e6", "precision", "float32, disk inclusion, contrast 1e6",
        lambda: _scalar(unit_square(N_SIDE), _inclusion(1e6)), dtype="float32"),
    StabilityCase("p2_checkerboard_1e6", "element", "P2 elements, checkerboard contrast 1e6",
        lambda: _scalar(unit_square(N_SIDE // 2), _checkerboard(1e6), element="P2")),
    StabilityCase("cube_inclusion_1e6", "element", "3-D tetrahedra, ball inclusion contrast 1e6",
        lambda: _scalar(unit_cube(6), lambda x: np.where(
              ((x - 0.5) ** 2).sum(axis=0) < 0.3 ** 2, 1e6, 1.0))),
)


def case_named(name: str) -> StabilityCase:
    """The case called ``name``; an unknown name raises :class:`PrdpFemError` listing them."""
    for case in CASES:
        if case.name == name:
            return case
    raise PrdpFemError(f"case {name!r}: expected one of {[c.name for c in CASES]}")
