"""Discretisation: P1/P2/Q1/Q2 systems from scikit-fem, parameters, observations, regularisers,
Gaussian priors, and pyamg-converged reference solves with their norms.
"""

from .discretization import Discretization, discretize
from .observations import Observation, boundary_values, full_field, point_sensors, with_noise
from .parameters import (
    COEFFICIENT_UNKNOWNS,
    UNKNOWNS,
    Parameterization,
    Simp,
    parameter_basis,
    parameter_mass,
    simp,
)
from .priors import GaussianPrior, bilaplacian_prior
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
from .regularizers import REGULARIZERS, Regularizer, gradient_gram, regularizer, stiffness_form
from .residuals import ResidualFactors, residual_factors, square_root_factor
from .system import LinearSystem

__all__ = [
    "COEFFICIENT_UNKNOWNS",
    "REGULARIZERS",
    "UNKNOWNS",
    "Discretization",
    "GaussianPrior",
    "LinearSystem",
    "Observation",
    "Parameterization",
    "ReferenceSolution",
    "Regularizer",
    "ResidualFactors",
    "Simp",
    "amg_solve",
    "bilaplacian_prior",
    "boundary_values",
    "direct_solve",
    "discretize",
    "full_field",
    "gradient_gram",
    "h1_error",
    "h1_seminorm",
    "l2_error",
    "l2_norm",
    "parameter_basis",
    "parameter_mass",
    "point_sensors",
    "regularizer",
    "relative_h1_error",
    "relative_l2_error",
    "residual_factors",
    "simp",
    "square_root_factor",
    "stiffness_form",
    "with_noise",
]
