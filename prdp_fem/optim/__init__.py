"""Optimisers that need more than an optax transformation: L-BFGS with a zoom line search,
Newton-CG, Gauss-Newton and half-inverse gradients.
"""

from .hig import (
    JACOBIAN_MODES,
    HigInfo,
    HigState,
    hig,
    hig_direction,
    hig_update,
    randomized_svd,
    residual_jacobian,
)
from .linesearch import (
    FIRST_STEPS,
    Contradiction,
    Evaluation,
    ZoomSearchState,
    lbfgs,
    scale_by_zoom_linesearch,
)
from .newton import (
    FORCING_TERMS,
    HESSIANS,
    CycledPreconditioner,
    NewtonCGState,
    gauss_newton,
    newton_cg,
    regularization_preconditioner,
)

__all__ = [
    "FIRST_STEPS",
    "FORCING_TERMS",
    "HESSIANS",
    "JACOBIAN_MODES",
    "Contradiction",
    "CycledPreconditioner",
    "Evaluation",
    "HigInfo",
    "HigState",
    "NewtonCGState",
    "ZoomSearchState",
    "gauss_newton",
    "hig",
    "hig_direction",
    "hig_update",
    "lbfgs",
    "newton_cg",
    "randomized_svd",
    "regularization_preconditioner",
    "residual_jacobian",
    "scale_by_zoom_linesearch",
]
