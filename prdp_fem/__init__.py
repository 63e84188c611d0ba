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


# What a script uses; everything else is in the subpackages (prdp_fem.mesh, .fem, .linalg,
# .inverse, .optim, .learning, .scene, .studies) and prdp_fem.errors. Benchmarks live in
# prdp_fem.bench only.
from . import errors, fem, inverse, learning, linalg, mesh, optim
from ._version import __version__
from .compilation_cache import enable_compilation_cache
from .errors import (
    CoefficientError,
    DataError,
    MeshError,
    MeshFileError,
    PrdpFemError,
    SceneError,
    ShapeError,
    SolverConfigError,
)
from .fem import (
    Discretization,
    Observation,
    amg_solve,
    bilaplacian_prior,
    boundary_values,
    direct_solve,
    discretize,
    full_field,
    point_sensors,
    regularizer,
    relative_h1_error,
    relative_l2_error,
    with_noise,
)
from .inverse import (
    History,
    InverseProblem,
    Inversion,
    Refinement,
    adaptive_tolerance,
    compare,
    converged,
    fixed,
    inverse_problem,
    invert,
    laplace_posterior,
    prdp,
    taylor_test,
    truncation_gap,
)
from .linalg import (
    ConvergedCG,
    IterationCounter,
    RebuiltAMG,
    Solution,
    SparseMatrix,
    Status,
    TruncatedCG,
    TruncatedJacobi,
    amg_preconditioner,
    rebuild_policy,
    solve,
)
from .mesh import (
    disk,
    l_shape,
    load_mesh,
    mesh_from_arrays,
    mesh_quality,
    rectangle_with_hole,
    save_mesh,
    unit_cube,
    unit_square,
)
from .optim import gauss_newton, hig, lbfgs, newton_cg

__all__ = [  # noqa: RUF022 (grouped by concept, as the guide presents them)
    "__version__", "enable_compilation_cache",
    # meshes
    "load_mesh", "save_mesh", "mesh_from_arrays", "mesh_quality", "unit_square", "unit_cube",
    "rectangle_with_hole", "disk", "l_shape",
    # discretisation, data, references
    "discretize", "Discretization", "Observation", "point_sensors", "full_field",
    "boundary_values", "with_noise", "regularizer", "bilaplacian_prior", "amg_solve",
    "direct_solve", "relative_l2_error", "relative_h1_error",
    # solves
    "solve", "TruncatedCG", "ConvergedCG", "TruncatedJacobi", "Solution", "Status",
    "SparseMatrix", "IterationCounter", "amg_preconditioner", "RebuiltAMG", "rebuild_policy",
    # inversion and refinement
    "inverse_problem", "InverseProblem", "invert", "Inversion", "History", "Refinement", "prdp",
    "fixed", "converged", "adaptive_tolerance", "truncation_gap", "compare", "taylor_test",
    "laplace_posterior",
    # optimisers
    "lbfgs", "newton_cg", "gauss_newton", "hig",
    # errors (all of them: prdp_fem.errors)
    "PrdpFemError", "MeshFileError", "MeshError", "SceneError", "DataError", "ShapeError",
    "SolverConfigError", "CoefficientError",
    # subpackages
    "errors", "mesh", "fem", "linalg", "inverse", "optim", "learning",
]


# Names the top level held before the subpackages: a deprecated alias each, for one release.
_MOVED = {
    "AMGCost": "prdp_fem.bench.amg",
    "AMGCycle": "prdp_fem.linalg",
    "AlphaChoice": "prdp_fem.inverse",
    "ComparisonRow": "prdp_fem.inverse",
    "CooMatrix": "prdp_fem.linalg",
    "CoordinateRangeError": "prdp_fem.errors",
    "CsrMatrix": "prdp_fem.linalg",
    "DegenerateCellError": "prdp_fem.errors",
    "DiscretizationError": "prdp_fem.errors",
    "DuplicateNodeError": "prdp_fem.errors",
    "EllMatrix": "prdp_fem.linalg",
    "FixedMatrix": "prdp_fem.linalg",
    "HeatProblem": "prdp_fem.learning",
    "HigInfo": "prdp_fem.optim",
    "HigState": "prdp_fem.optim",
    "IdentityPreconditioner": "prdp_fem.linalg",
    "IncompatibleDataError": "prdp_fem.errors",
    "InversionError": "prdp_fem.inverse",
    "InvertedCellError": "prdp_fem.errors",
    "JacobiPreconditioner": "prdp_fem.linalg",
    "KERNELS": "prdp_fem.linalg",
    "LinearSystem": "prdp_fem.fem",
    "MeshQuality": "prdp_fem.mesh",
    "MeshRepairWarning": "prdp_fem.errors",
    "MixedDimensionError": "prdp_fem.errors",
    "NewtonCGState": "prdp_fem.optim",
    "NonFiniteCoordinatesError": "prdp_fem.errors",
    "Objective": "prdp_fem.inverse",
    "OutputError": "prdp_fem.errors",
    "Parameterization": "prdp_fem.fem",
    "PyamgCycle": "prdp_fem.linalg",
    "RebuildPolicy": "prdp_fem.linalg",
    "RebuildState": "prdp_fem.linalg",
    "ReferenceSolution": "prdp_fem.fem",
    "RefinementState": "prdp_fem.inverse",
    "Regularizer": "prdp_fem.fem",
    "ResidualFactors": "prdp_fem.fem",
    "ResourceLimitError": "prdp_fem.errors",
    "Schedule": "prdp_fem.inverse",
    "SensorError": "prdp_fem.errors",
    "SolverBreakdownError": "prdp_fem.errors",
    "StepRecord": "prdp_fem.inverse",
    "TaylorResult": "prdp_fem.inverse",
    "TracerError": "prdp_fem.errors",
    "UnsupportedCellsError": "prdp_fem.errors",
    "UnusedNodeError": "prdp_fem.errors",
    "Validation": "prdp_fem.inverse",
    "amg_cost": "prdp_fem.bench.amg",
    "amg_hierarchy": "prdp_fem.linalg",
    "default_kernel": "prdp_fem.linalg",
    "diagonal": "prdp_fem.linalg",
    "format_table": "prdp_fem.inverse",
    "geometric_spacing": "prdp_fem.mesh",
    "h1_error": "prdp_fem.fem",
    "h1_seminorm": "prdp_fem.fem",
    "heat_problem": "prdp_fem.learning",
    "heat_step": "prdp_fem.learning",
    "hig_update": "prdp_fem.optim",
    "jacobi": "prdp_fem.linalg",
    "jacobi_solve": "prdp_fem.linalg",
    "l2_error": "prdp_fem.fem",
    "l2_norm": "prdp_fem.fem",
    "l_curve": "prdp_fem.inverse",
    "matvec": "prdp_fem.linalg",
    "morozov": "prdp_fem.inverse",
    "prepare": "prdp_fem.linalg",
    "randomized_svd": "prdp_fem.optim",
    "regularization_preconditioner": "prdp_fem.optim",
    "residual_jacobian": "prdp_fem.optim",
    "rmatvec": "prdp_fem.linalg",
    "scale_by_zoom_linesearch": "prdp_fem.optim",
    "symmetric_matvec": "prdp_fem.linalg",
    "tensor_mesh": "prdp_fem.mesh",
    "unrolled_length": "prdp_fem.linalg",
}


def __getattr__(name: str):
    if name in _MOVED:
        import importlib
        import warnings

        where = _MOVED[name]
        warnings.warn(f"prdp_fem.{name} moved to {where}.{name}; the top-level alias goes in "
                      "the next release", DeprecationWarning, stacklevel=2)
        return getattr(importlib.import_module(where), name)
    raise AttributeError(f"module 'prdp_fem' has no attribute {name!r}")
