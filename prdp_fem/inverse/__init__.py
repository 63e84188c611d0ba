"""Inverse problems: the driver (:func:`invert`), refinement controllers (PRDP, fixed K,
converged, adaptive tolerance), the reduced-Hessian CG and the all-at-once KKT solve of source
problems, histories, savings and gradient checks.
"""

from .batch import BatchInversion, invert_batch
from .comparison import ComparisonRow, compare, first_settled, format_table, settled
from .descent import DescentCheck, IterateRecorder, descent_check
from .driver import (
    InverseProblem,
    Inversion,
    InversionError,
    Objective,
    Validation,
    WarmStart,
    initial_params,
    inverse_problem,
    invert,
)
from .history import History, StepRecord
from .kkt import KKTSolution, KKTSystem, kkt_solve, kkt_system
from .parameter_choice import AlphaChoice, l_curve, morozov
from .posterior import LaplacePosterior, generalized_eigenpairs, laplace_posterior
from .reduced import ReducedCG, homogeneous, reduced_cg
from .refinement import (
    Refinement,
    RefinementState,
    Schedule,
    adaptive_tolerance,
    converged,
    fixed,
    prdp,
    state_from_dict,
    state_to_dict,
    truncation_gap,
)
from .taylor import TaylorResult, taylor_test

__all__ = [
    "AlphaChoice",
    "BatchInversion",
    "ComparisonRow",
    "DescentCheck",
    "History",
    "InverseProblem",
    "Inversion",
    "InversionError",
    "IterateRecorder",
    "KKTSolution",
    "KKTSystem",
    "LaplacePosterior",
    "Objective",
    "ReducedCG",
    "Refinement",
    "RefinementState",
    "Schedule",
    "StepRecord",
    "TaylorResult",
    "Validation",
    "WarmStart",
    "adaptive_tolerance",
    "compare",
    "converged",
    "descent_check",
    "first_settled",
    "fixed",
    "format_table",
    "generalized_eigenpairs",
    "homogeneous",
    "initial_params",
    "inverse_problem",
    "invert",
    "invert_batch",
    "kkt_solve",
    "kkt_system",
    "l_curve",
    "laplace_posterior",
    "morozov",
    "prdp",
    "reduced_cg",
    "settled",
    "state_from_dict",
    "state_to_dict",
    "taylor_test",
    "truncation_gap",
]
