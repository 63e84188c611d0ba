"""Typed errors and warnings raised at the edges of prdp_fem.

Every input error names *where* (a file or a field), *what* was found and *what was expected*,
so that the CLI can print it as one line. All of them derive from :class:`PrdpFemError`, which
derives from ``ValueError`` so that generic handlers keep working.
"""

from __future__ import annotations

from pathlib import Path


class PrdpFemError(ValueError):
    """Base class of every input error prdp_fem raises on purpose."""


class MeshError(PrdpFemError):
    """A mesh file or mesh array cannot be used.

    ``source`` is the file path (or a description such as ``"<array mesh>"``) and
    ``problem`` a one-line explanation that says what was expected.
    """

    def __init__(self, source: str | Path, problem: str):
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")


class MeshFileError(MeshError):
    """The file is missing, empty, of an unknown format, or unreadable."""


class UnsupportedCellsError(MeshError):
    """The file holds no cell type prdp_fem can discretise (or only higher-order ones)."""


class MixedDimensionError(MeshError):
    """Cells of several types or dimensions that do not form one conforming mesh."""


class NonFiniteCoordinatesError(MeshError):
    """A node coordinate is NaN or infinite."""


class CoordinateRangeError(MeshError):
    """A node coordinate so large that cell measures would overflow (see
    :data:`prdp_fem.mesh.io.MAX_COORDINATE`)."""


class DegenerateCellError(MeshError):
    """A cell has (numerically) zero area or volume."""


class InvertedCellError(MeshError):
    """A cell is inverted in a way that cannot be repaired by renumbering its nodes."""


class DuplicateNodeError(MeshError):
    """Two nodes share coordinates: the mesh is cracked along them."""


class UnusedNodeError(MeshError):
    """A node belongs to no cell: it would make the stiffness matrix singular."""


class DiscretizationError(PrdpFemError):
    """An element, field kind or boundary condition request that does not fit the mesh."""


class SolverConfigError(PrdpFemError):
    """A solver was constructed with an invalid option."""


class CoefficientError(PrdpFemError):
    """A ``kappa`` that is NaN/Inf, ``<= 0``, or a tensor that is not positive definite."""


class DataError(PrdpFemError):
    """NaN/Inf in data: sources, Dirichlet/Neumann data, observations, initial guesses."""


class IncompatibleDataError(DataError):
    """Pure Neumann data whose net flux is not zero: the singular system has no solution."""


class ShapeError(PrdpFemError):
    """An array whose shape does not match the discretisation it is used with."""


class SensorError(PrdpFemError):
    """An empty sensor set, or sensors that lie outside the mesh."""


class SolverBreakdownError(PrdpFemError):
    """CG met ``p.Ap <= 0`` before converging: the operator is not positive definite."""


class SceneError(PrdpFemError):
    """A scene file or table that cannot be used (names the file, the key and the expectation)."""


class OutputLockedError(PrdpFemError):
    """An output directory another process is writing (names the directory and its pid)."""


class OutputError(PrdpFemError):
    """An output file that could not be written (a full disk, no permission): names the file."""

    def __init__(self, path: str | Path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class ResourceLimitError(PrdpFemError):
    """An input whose estimated size (dofs, array entries, formula length or depth) exceeds a
    documented limit: refused before anything that size is allocated."""


class TracerError(PrdpFemError):
    """A JAX tracer where concrete (host) values are required, e.g. inside ``jax.jit``."""


class MeshRepairWarning(UserWarning):
    """A mesh was changed on load (orientation fixed, nodes merged or dropped)."""


class CheckpointError(PrdpFemError):
    """A checkpoint directory that cannot be used as asked: of another training, scene or
    version, not fitting the model, or holding checkpoints a fresh run would overwrite."""
