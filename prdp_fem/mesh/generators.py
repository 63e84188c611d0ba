"""Built-in meshes with named boundaries: unit square/cube, L-shape, disk, rectangle with hole.

Every generator returns a validated scikit-fem mesh whose ``boundaries`` name the sides
(``left``, ``right``, ``bottom``, ``top`` and, in 3-D, ``front``, ``back``), plus ``hole`` for
:func:`rectangle_with_hole` and ``boundary`` (all of it) for the curved domains.

>>> from prdp_fem.mesh.generators import unit_square
>>> mesh = unit_square(4)
>>> mesh.p.shape, sorted(mesh.boundaries)
((2, 25), ['bottom', 'left', 'right', 'top'])
"""

from __future__ import annotations

import numpy as np
import skfem

from ..errors import DiscretizationError
from .io import mesh_from_arrays, with_names

__all__ = ["disk", "geometric_spacing", "l_shape", "rectangle_with_hole", "tensor_mesh",
           "unit_cube", "unit_square"]

_TOL = 1e-10


def _sides(dim: int, lower=(0.0, 0.0, 0.0), upper=(1.0, 1.0, 1.0)):
    names = [("left", "right"), ("bottom", "top"), ("front", "back")]
    sides = {}
    for axis in range(dim):
        lo, hi = lower[axis], upper[axis]
        tol = _TOL * max(hi - lo, abs(lo), abs(hi))  # relative: domains of any scale
        sides[names[axis][0]] = lambda x, a=axis, v=lo, t=tol: np.abs(x[a] - v) < t
        sides[names[axis][1]] = lambda x, a=axis, v=hi, t=tol: np.abs(x[a] - v) < t
    return sides


def _check_n(n: int, minimum: int = 1) -> int:
    if int(n) != n or n < minimum:
        raise DiscretizationError(f"mesh resolution n={n!r}: expected an integer >= {minimum}")
    return int(n)


def unit_square(n: int, cell: str = "triangle") -> skfem.Mesh:
    """Structured ``n x n`` mesh of the unit square (``cell``: ``triangle`` or ``quad``)."""
    n = _check_n(n)
    x = np.linspace(0.0, 1.0, n + 1)
    if cell == "triangle":
        mesh = skfem.MeshTri1.init_tensor(x, x)
    elif cell == "quad":
        mesh = skfem.MeshQuad1.init_tensor(x, x)
    else:
        raise DiscretizationError(f"cell={cell!r}: expected 'triangle' or 'quad'")
    return with_names(mesh, _sides(2))


def unit_cube(n: int, cell: str = "tetra") -> skfem.Mesh:
    """Structured ``n x n x n`` mesh of the unit cube (``cell``: ``tetra`` or ``hexahedron``)."""
    n = _check_n(n)
    x = np.linspace(0.0, 1.0, n + 1)
    if cell == "tetra":
        mesh = skfem.MeshTet1.init_tensor(x, x, x)
    elif cell == "hexahedron":
        mesh = skfem.MeshHex1.init_tensor(x, x, x)
    else:
        raise DiscretizationError(f"cell={cell!r}: expected 'tetra' or 'hexahedron'")
    return with_names(mesh, _sides(3))


def tensor_mesh(*coordinates: np.ndarray, cell: str = "triangle") -> skfem.Mesh:
    """Structured mesh on the grid ``coordinates[0] x coordinates[1] (x coordinates[2])``.

    Each array must be finite and strictly increasing; the spacing may vary, so this builds
    stretched (aspect ratio ``dy/dx``), graded (:func:`geometric_spacing`) and scaled meshes.
    ``cell``: ``triangle``/``quad`` in 2-D, ``tetra``/``hexahedron`` in 3-D. Boundaries are
    named as for :func:`unit_square`.

    >>> mesh = tensor_mesh(np.linspace(0, 1, 5), np.linspace(0, 1e-4, 5))
    >>> float(mesh.p[1].max()), sorted(mesh.boundaries)
    (0.0001, ['bottom', 'left', 'right', 'top'])
    """
    cells = {2: {"triangle": skfem.MeshTri1, "quad": skfem.MeshQuad1},
             3: {"tetra": skfem.MeshTet1, "hexahedron": skfem.MeshHex1}}
    if len(coordinates) not in cells:
        raise DiscretizationError(f"tensor_mesh: {len(coordinates)} coordinate arrays; "
                                  "expected 2 or 3")
    arrays = [np.asarray(c, dtype=float) for c in coordinates]
    for axis, c in enumerate(arrays):
        if c.ndim != 1 or c.size < 2 or not np.isfinite(c).all() or not (np.diff(c) > 0).all():
            raise DiscretizationError(f"tensor_mesh: coordinates[{axis}] must be a finite, "
                                      "strictly increasing 1-D array of at least 2 values")
    dim = len(arrays)
    if cell not in cells[dim]:
        raise DiscretizationError(f"cell={cell!r}: expected one of {sorted(cells[dim])}")
    mesh = cells[dim][cell].init_tensor(*arrays)
    return with_names(mesh, _sides(dim, [c[0] for c in arrays], [c[-1] for c in arrays]))


def geometric_spacing(n: int, ratio: float, length: float = 1.0) -> np.ndarray:
    """``n + 1`` points on ``[0, length]``; cells grow geometrically to ``h_max/h_min = ratio``.

    >>> x = geometric_spacing(4, 8.0)
    >>> float(np.diff(x).max() / np.diff(x).min())
    8.0
    """
    n = _check_n(n)
    if not (np.isfinite(ratio) and ratio >= 1 and np.isfinite(length) and length > 0):
        raise DiscretizationError(f"geometric_spacing: ratio={ratio!r}, length={length!r}; "
                                  "expected ratio >= 1 and length > 0")
    growth = float(ratio) ** (1.0 / max(n - 1, 1))
    cells = growth ** np.arange(n)
    x = np.concatenate([[0.0], np.cumsum(cells)])
    return length * x / x[-1]


def l_shape(refinements: int = 3) -> skfem.Mesh:
    """L-shaped domain ``[-1, 1]^2`` minus the lower-right quadrant (re-entrant corner at 0)."""
    refinements = _check_n(refinements, 0)
    mesh = skfem.MeshTri1.init_lshaped().refined(refinements)
    return with_names(mesh, {"boundary": lambda x: np.ones_like(x[0], dtype=bool)})


def disk(refinements: int = 3) -> skfem.Mesh:
    """Unit disk (boundary nodes on the circle at every refinement)."""
    refinements = _check_n(refinements, 0)
    mesh = skfem.MeshTri1.init_circle(refinements)
    return with_names(mesh, {"boundary": lambda x: np.ones_like(x[0], dtype=bool)})


def rectangle_with_hole(
    n: int = 16,
    width: float = 2.0,
    height: float = 1.0,
    hole: tuple[float, float, float, float] = (0.75, 1.25, 0.25, 0.75),
) -> skfem.Mesh:
    """Triangulated ``[0, width] x [0, height]`` with the rectangular hole ``(x0, x1, y0, y1)``.

    ``n`` cells per unit length. Boundaries: ``left``, ``right``, ``bottom``, ``top``, ``hole``.
    """
    n = _check_n(n, 2)
    x0, x1, y0, y1 = hole
    if not (0 < x0 < x1 < width and 0 < y0 < y1 < height):
        raise DiscretizationError(
            f"hole={hole!r}: expected 0 < x0 < x1 < width and 0 < y0 < y1 < height")
    grid = skfem.MeshTri1.init_tensor(np.linspace(0, width, round(n * width) + 1),
                                      np.linspace(0, height, round(n * height) + 1))
    centroid = grid.p[:, grid.t].mean(axis=1)
    inside = ((centroid[0] > x0) & (centroid[0] < x1) & (centroid[1] > y0) & (centroid[1] < y1))
    cells = grid.t[:, ~inside].T
    used = np.unique(cells)
    renumber = np.full(grid.p.shape[1], -1)
    renumber[used] = np.arange(len(used))
    mesh = mesh_from_arrays(grid.p[:, used].T, renumber[cells], "triangle",
                            source="<rectangle_with_hole>")
    sides = _sides(2, upper=(width, height))

    def on_hole(x):
        within_x = (x[0] > x0 - _TOL) & (x[0] < x1 + _TOL)
        within_y = (x[1] > y0 - _TOL) & (x[1] < y1 + _TOL)
        return within_x & within_y

    return with_names(mesh, {**sides, "hole": on_hole})
