"""prdp_fem: FE inverse problems through truncated, progressively refined, differentiable PCG.

Importing the package switches JAX to float64 (``jax_enable_x64``): finite-element systems and
their gradients need it. Set ``PRDP_FEM_KEEP_X64=0`` before import to leave JAX's setting alone.
It changes no other setting: JAX's persistent compilation cache is switched on by the
``prdp-fem`` program, and by :func:`enable_compilation_cache` in a script.
"""
import os as _os

import jax as _jax

if _os.environ.get("PRDP_FEM_KEEP_X64", "1") != "0":
    _jax.config.update("jax_enable_x64", True)

from ._version import __version__
from .bench.amg import AMGCost, amg_cost
from .compilation_cache import enable_compilation_cache
from .errors import (
    CoefficientError,
    CoordinateRangeError,
    DataError,
    DegenerateCellError,
    DiscretizationError,
    DuplicateNodeError,
    IncompatibleDataError,
    InvertedCellError,
    MeshError,
    MeshFileError,
    MeshRepairWarning,
    MixedDimensionError,
    NonFiniteCoordinatesError,
    OutputError,
    PrdpFemError,
    ResourceLimitError,
    SceneError,
    SensorError,
    ShapeError,
    SolverBreakdownError,
    SolverConfigError,
    TracerError,
    UnsupportedCellsError,
    UnusedNodeError,
)
from .fem.discretization import Discretization, discretize
from .fem.observations import Observation, boundary_values, full_field, point_sensors, with_noise
from .fem.parameters import Parameterization
from .fem.reference import (
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
from .fem.regularizers import Regularizer, regularizer
from .fem.residuals import ResidualFactors
from .fem.system import LinearSystem
from .inverse.comparison import ComparisonRow, compare, format_table
from .inverse.driver import (
    InverseProblem,
    Inversion,
    InversionError,
    Objective,
    Validation,
    inverse_problem,
    invert,
)
from .inverse.history import History, StepRecord
from .inverse.parameter_choice import AlphaChoice, l_curve, morozov

# the controllers themselves stay in their module (prdp_fem.inverse.prdp, .fixed, .converged):
# a top-level function named prdp would shadow the submodule
from .inverse.refinement import Refinement, RefinementState, Schedule
from .inverse.taylor import TaylorResult, taylor_test
from .learning.heat import HeatProblem, heat_problem, heat_step
from .linalg.amg import (
    AMGCycle,
    PyamgCycle,
    RebuildPolicy,
    RebuildState,
    RebuiltAMG,
    amg_hierarchy,
    amg_preconditioner,
    rebuild_policy,
)
from .linalg.cg import (
    ConvergedCG,
    IterationCounter,
    Solution,
    Status,
    TruncatedCG,
    solve,
    unrolled_length,
)
from .linalg.operator import (
    KERNELS,
    CooMatrix,
    CsrMatrix,
    EllMatrix,
    FixedMatrix,
    SparseMatrix,
    default_kernel,
    diagonal,
    matvec,
    prepare,
    rmatvec,
    symmetric_matvec,
)
from .linalg.precond import IdentityPreconditioner, JacobiPreconditioner, jacobi
from .linalg.stationary import TruncatedJacobi, jacobi_solve
from .mesh.generators import (
    disk,
    geometric_spacing,
    l_shape,
    rectangle_with_hole,
    tensor_mesh,
    unit_cube,
    unit_square,
)
from .mesh.io import MeshQuality, load_mesh, mesh_from_arrays, mesh_quality, save_mesh
from .optim.hig import HigInfo, HigState, hig, hig_update, randomized_svd, residual_jacobian
from .optim.linesearch import lbfgs, scale_by_zoom_linesearch
from .optim.newton import NewtonCGState, gauss_newton, newton_cg, regularization_preconditioner

__all__ = [
    "KERNELS",
    "AMGCost",
    "AMGCycle",
    "AlphaChoice",
    "CoefficientError",
    "ComparisonRow",
    "ConvergedCG",
    "CooMatrix",
    "CoordinateRangeError",
    "CsrMatrix",
    "DataError",
    "DegenerateCellError",
    "Discretization",
    "DiscretizationError",
    "DuplicateNodeError",
    "EllMatrix",
    "FixedMatrix",
    "HeatProblem",
    "HigInfo",
    "HigState",
    "History",
    "IdentityPreconditioner",
    "IncompatibleDataError",
    "InverseProblem",
    "Inversion",
    "InversionError",
    "InvertedCellError",
    "IterationCounter",
    "JacobiPreconditioner",
    "LinearSystem",
    "MeshError",
    "MeshFileError",
    "MeshQuality",
    "MeshRepairWarning",
    "MixedDimensionError",
    "NewtonCGState",
    "NonFiniteCoordinatesError",
    "Objective",
    "Observation",
    "OutputError",
    "Parameterization",
    "PrdpFemError",
    "PyamgCycle",
    "RebuildPolicy",
    "RebuildState",
    "RebuiltAMG",
    "ReferenceSolution",
    "Refinement",
    "RefinementState",
    "Regularizer",
    "ResidualFactors",
    "ResourceLimitError",
    "SceneError",
    "Schedule",
    "SensorError",
    "ShapeError",
    "Solution",
    "SolverBreakdownError",
    "SolverConfigError",
    "SparseMatrix",
    "Status",
    "StepRecord",
    "TaylorResult",
    "TracerError",
    "TruncatedCG",
    "TruncatedJacobi",
    "UnsupportedCellsError",
    "UnusedNodeError",
    "Validation",
    "__version__",
    "amg_cost",
    "amg_hierarchy",
    "amg_preconditioner",
    "amg_solve",
    "boundary_values",
    "compare",
    "default_kernel",
    "diagonal",
    "direct_solve",
    "discretize",
    "disk",
    "enable_compilation_cache",
    "format_table",
    "full_field",
    "gauss_newton",
    "geometric_spacing",
    "h1_error",
    "h1_seminorm",
    "heat_problem",
    "heat_step",
    "hig",
    "hig_update",
    "inverse_problem",
    "invert",
    "jacobi",
    "jacobi_solve",
    "l2_error",
    "l2_norm",
    "l_curve",
    "l_shape",
    "lbfgs",
    "load_mesh",
    "matvec",
    "mesh_from_arrays",
    "mesh_quality",
    "morozov",
    "newton_cg",
    "point_sensors",
    "prepare",
    "randomized_svd",
    "rebuild_policy",
    "rectangle_with_hole",
    "regularization_preconditioner",
    "regularizer",
    "relative_h1_error",
    "relative_l2_error",
    "residual_jacobian",
    "rmatvec",
    "save_mesh",
    "scale_by_zoom_linesearch",
    "solve",
    "symmetric_matvec",
    "taylor_test",
    "tensor_mesh",
    "unit_cube",
    "unit_square",
    "unrolled_length",
    "with_noise",
]
