"""prdp_fem: FE inverse problems through truncated, progressively refined, differentiable PCG.

Importing the package switches JAX to float64 (``jax_enable_x64``): finite-element systems and
their gradients need it. Set ``PRDP_FEM_KEEP_X64=0`` before import to leave JAX's setting alone.
"""
import os as _os

import jax as _jax

if _os.environ.get("PRDP_FEM_KEEP_X64", "1") != "0":
    _jax.config.update("jax_enable_x64", True)

from ._version import __version__
from .cg import ConvergedCG, Solution, TruncatedCG, solve
from .discretization import Discretization, discretize
from .errors import (
    DegenerateCellError,
    DiscretizationError,
    DuplicateNodeError,
    InvertedCellError,
    MeshError,
    MeshFileError,
    MeshRepairWarning,
    MixedDimensionError,
    NonFiniteCoordinatesError,
    PrdpFemError,
    SolverConfigError,
    UnsupportedCellsError,
    UnusedNodeError,
)
from .generators import disk, l_shape, rectangle_with_hole, unit_cube, unit_square
from .mesh import MeshQuality, load_mesh, mesh_from_arrays, mesh_quality, save_mesh
from .operator import SparseMatrix, diagonal, matvec, rmatvec
from .precond import IdentityPreconditioner, JacobiPreconditioner, jacobi
from .reference import (
    ReferenceSolution,
    amg_solve,
    direct_solve,
    h1_error,
    h1_seminorm,
    l2_error,
    l2_norm,
    relative_h1_error,
    relative_l2_error,
)
from .system import LinearSystem
from .taylor import TaylorResult, taylor_test

__all__ = [
    "ConvergedCG",
    "DegenerateCellError",
    "Discretization",
    "DiscretizationError",
    "DuplicateNodeError",
    "IdentityPreconditioner",
    "InvertedCellError",
    "JacobiPreconditioner",
    "LinearSystem",
    "MeshError",
    "MeshFileError",
    "MeshQuality",
    "MeshRepairWarning",
    "MixedDimensionError",
    "NonFiniteCoordinatesError",
    "PrdpFemError",
    "ReferenceSolution",
    "Solution",
    "SolverConfigError",
    "SparseMatrix",
    "TaylorResult",
    "TruncatedCG",
    "UnsupportedCellsError",
    "UnusedNodeError",
    "__version__",
    "amg_solve",
    "diagonal",
    "direct_solve",
    "discretize",
    "disk",
    "h1_error",
    "h1_seminorm",
    "jacobi",
    "l2_error",
    "l2_norm",
    "l_shape",
    "load_mesh",
    "matvec",
    "mesh_from_arrays",
    "mesh_quality",
    "rectangle_with_hole",
    "relative_h1_error",
    "relative_l2_error",
    "rmatvec",
    "save_mesh",
    "solve",
    "taylor_test",
    "unit_cube",
    "unit_square",
]
