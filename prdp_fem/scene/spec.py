"""Scene files: TOML -> frozen, validated dataclasses (no numerics here; see :mod:`.build`).

A scene says what a problem needs and nothing else. Sections (all optional; everything unsaid
takes the default written in the dataclass below):

``[mesh]``
    ``generator`` (unit_square | unit_cube | l_shape | disk | rectangle_with_hole)
    with ``n`` and ``cell``, *or* ``file`` (relative to the scene file;
    ``"@meshes/NAME"`` is a mesh shipped with the package); ``refine``, ``repair``
``[pde]``
    ``element``, ``kappa_space``, ``kappa``, ``source`` (numbers or formulas in
    x, y, z, see :mod:`.expressions`), ``dirichlet`` (a value for the whole
    boundary or a table ``{boundary = value}``), ``neumann`` (a table), ``exact``, ``pins``
    (``[[x, y, value], ...]``: the
    state pinned at mesh vertices, for pure Neumann data)
``[inverse]``
    ``unknown`` (source | log_kappa), ``truth``, ``data``, ``observations``
    (full_field | sensors | boundary), ``norm``, ``sensors``, ``boundaries``,
    ``noise``, ``seed``, ``alpha``, ``regularization``, ``bounds``, ``init``
``[solver]``
    ``preconditioner``, ``gradient``, ``iterations``, ``rtol``
``[refinement]``
    ``kind`` (prdp | fixed | converged | adaptive | gap) and that kind's settings, ``monitor``;
    ``ema_window`` unset is 2 for an inversion's loss under a line-search
    optimiser, else 6 (:func:`default_ema_window`)
``[optimizer]``
    ``name`` (lbfgs | adam | sgd | newton_cg | gauss_newton | hig), ``steps``,
    ``learning_rate``; lbfgs: ``memory_size``, ``first_step`` (unit | polyak:
    the first line search starts at ``J / |slope|``); Newton: ``max_cg``,
    ``forcing``, ``c1``, ``max_backtracking``, ``gradient_rtol`` (see
    :mod:`prdp_fem.optim.newton`); hig
    (:func:`~prdp_fem.optim.hig.hig`): ``exponent``, ``tau``, ``rank``, ``relative``;
    adam, sgd: ``decay`` (constant | cosine: to zero over the run)
``[learned]``
    a learned inverse (:mod:`prdp_fem.learning.learned`): ``samples``,
    ``validation_samples``, ``test_samples`` (held out, reported), ``noise`` (relative to
    each sample's RMS), ``width`` (of the random source bumps), ``hidden`` (layer sizes),
    ``epochs``, ``batch_size``, ``seed``, ``supervised``, ``checkpoint_every`` (epochs
    between saved training states: ``--resume`` continues from the last one); its
    observations come from ``[inverse]`` (``unknown = "source"``; ``truth``/``data`` are not
    needed: the sources are random)
``[heat]``
    a learned heat stepper (:mod:`prdp_fem.learning.heat`, :class:`HeatSpec`): ``dt``,
    ``steps``, ``substeps``, ``trajectories``, ``validation_trajectories``,
    ``test_trajectories``, ``width``, ``hidden``, ``setup`` (correction |
    prediction | mixed), ``mode`` (one | nog | wig), ``unroll``, ``epochs``,
    ``batch_size``, ``seed``, ``checkpoint_every``, ``reaction`` (a Fisher-KPP rate
    ``r``: ``r u (1 - u)`` added, explicitly; 0, the default: the heat equation);
    ``[pde]`` gives ``kappa``, ``source`` and the Dirichlet data, ``[optimizer]`` is adam
    (default) or sgd
``[study]``
    ``kind`` (inverse | forward | h | learned | heat; a ``[learned]`` or
    ``[heat]`` table makes its kind the default), ``[[study.runs]]`` (``name``
    plus tables that override the scene's: ``refinement`` replaces it, ``mesh``,
    ``pde``, ``solver``, ``optimizer``, ``learned``, ``heat`` merge key by
    key), ``reference``,
    ``target_error``, ``band``, ``reached`` (band | at_or_below: when a run
    counts as at the target), ``levels``, ``elements``

A scene's size is estimated before anything is built: a ``mesh.n``, ``mesh.refine`` or
``study.levels`` whose mesh would carry more than :func:`max_dofs` degrees of freedom (default
:data:`DEFAULT_MAX_DOFS`; the environment variable ``PRDP_FEM_MAX_DOFS`` or the command's
``--max-dofs`` sets it) raises :class:`SceneResourceLimitError` with the estimate. A mesh
file's refinements are bounded here by what refining a single cell would give, and by the
file's own size once it is read (:func:`check_refined_size`, before refining).

Unknown keys and bad values raise :class:`SceneError` naming the file, the key and what is
allowed. Where the value belongs to a kind the Python API has a typed error for, the error is
both: a ``kappa`` <= 0 raises :class:`SceneCoefficientError` (a ``SceneError`` *and* a
``CoefficientError``), sensors :class:`SceneSensorError`, noise and source bounds
:class:`SceneDataError`, ``[solver]``, ``[refinement]``, ``[optimizer]`` and ``alpha``
:class:`SceneSolverConfigError`, so ``except CoefficientError`` catches a scene's bad ``kappa``
as it catches a bad array.

>>> scene = parse_scene({"mesh": {"n": 8}, "pde": {"source": "sin(pi*x)"}})
>>> scene.mesh.n, scene.pde.element, scene.inverse is None, scene.study.kind
(8, 'P1', True, 'forward')
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import os
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from .._files import checked_file
from ..errors import (
    CoefficientError,
    DataError,
    DiscretizationError,
    MeshFileError,
    ResourceLimitError,
    SceneError,
    SensorError,
    SolverConfigError,
)
from .expressions import compile_field

__all__ = [
    "BUILTIN_SCENES",
    "DEFAULT_MAX_DOFS",
    "LINE_SEARCH_OPTIMIZERS",
    "MONOTONE_EMA_WINDOW",
    "REFERENCE_EMA_WINDOW",
    "REFINEMENT_SPECS",
    "AdaptiveSpec",
    "ConvergedSpec",
    "FixedSpec",
    "HeatSpec",
    "InverseSpec",
    "LearnedSpec",
    "MeshSpec",
    "OptimizerSpec",
    "PdeSpec",
    "PrdpSpec",
    "RefinementSpec",
    "Scene",
    "SceneCoefficientError",
    "SceneDataError",
    "SceneDiscretizationError",
    "SceneError",
    "SceneResourceLimitError",
    "SceneSensorError",
    "SceneSolverConfigError",
    "SolverSpec",
    "StudySpec",
    "builtin_scene_path",
    "check_refined_size",
    "default_ema_window",
    "ema_window_of",
    "load_scene",
    "max_dofs",
    "mesh_scene",
    "parse_scene",
    "with_overrides",
]

BUILTIN_SCENES = ("cube_kappa", "mother", "inclusion", "plate_hole", "cube", "poisson_h",
                  "simp_slab", "hippylib_tutorial", "learned_plate", "heat_emulator",
                  "reaction_diffusion")
GENERATORS = ("unit_square", "unit_cube", "l_shape", "disk", "rectangle_with_hole")
PACKAGE_MESH_PREFIX = "@meshes/"

Field = float | str  # a number or a formula, validated by expressions.compile_field


class SceneCoefficientError(SceneError, CoefficientError):
    """A scene's ``pde.kappa`` that is not positive on the mesh (or log-kappa bounds)."""


class SceneDataError(SceneError, DataError):
    """A scene's noise level, source bounds or other data that cannot be used."""


class SceneSensorError(SceneError, SensorError):
    """A scene's sensors or observed boundaries: none, outside the mesh, or too many."""


class SceneSolverConfigError(SceneError, SolverConfigError):
    """A scene's ``[solver]``, ``[refinement]`` or ``[optimizer]`` setting, or its ``alpha``."""


class SceneDiscretizationError(SceneError, DiscretizationError):
    """A scene's element, coefficient space or boundary names that do not fit its mesh."""


class SceneResourceLimitError(SceneError, ResourceLimitError):
    """A scene whose mesh would carry more degrees of freedom than :func:`max_dofs`."""


#: The most degrees of freedom a scene's mesh may carry unless told otherwise (some 20 GB of
#: assembled operators, hierarchies and solver vectors in 3-D at second order).
DEFAULT_MAX_DOFS = 20_000_000
MAX_DOFS_VARIABLE = "PRDP_FEM_MAX_DOFS"


def max_dofs() -> int:
    """The dof limit: ``PRDP_FEM_MAX_DOFS`` where set (a positive integer), else
    :data:`DEFAULT_MAX_DOFS`."""
    text = os.environ.get(MAX_DOFS_VARIABLE)
    if text is None:
        return DEFAULT_MAX_DOFS
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise SceneError(f"{MAX_DOFS_VARIABLE}={text!r}: expected a positive integer (the "
                         "most degrees of freedom a scene may ask for)")
    return value


# an upper bound on the vertices of each generator's mesh at resolution (or level) n
_GENERATOR_VERTICES = {
    "unit_square": lambda n: (n + 1) ** 2, "unit_cube": lambda n: (n + 1) ** 3,
    "rectangle_with_hole": lambda n: (2 * n + 1) * (n + 1),
    "l_shape": lambda n: 8 * 4 ** n, "disk": lambda n: 5 * 4 ** n}


def _dofs_per_vertex(elements, dim: int) -> int:
    """An upper bound on dofs per mesh vertex: 1 at first order; at second order the edge
    (and face, cell) dofs add at most 3 (2-D) or 7 (3-D) per vertex."""
    second = any(element in ("P2", "Q2") for element in elements)
    return (4 if dim == 2 else 8) if second else 1


def _estimated_dofs(vertices: int, dim: int, refinements: int, elements) -> int:
    """Dofs after ``refinements`` uniform refinements (each at most quadruples the vertices
    in 2-D, multiplies them by 8 in 3-D) at the highest order among ``elements``."""
    return vertices * (4 if dim == 2 else 8) ** refinements * _dofs_per_vertex(elements, dim)


def _refuse(source: str, key: str, value: int, estimate: int, what: str) -> None:
    limit = max_dofs()
    if estimate > limit:
        raise SceneResourceLimitError(
            f"{source}: {key} = {value}: {what} would carry about {estimate:.3g} degrees of "
            f"freedom; expected at most {limit} (the dof limit: set it with --max-dofs or "
            f"{MAX_DOFS_VARIABLE})")


def _check_size(scene: Scene) -> None:
    """Refuse a scene whose mesh (at any of its levels) would exceed :func:`max_dofs`,
    estimated from the settings alone, before anything is built."""
    spec, kind = scene.mesh, scene.study.kind
    elements = (scene.pde.element, *(scene.study.elements if kind == "h" else ()))
    levels = scene.study.levels if kind == "h" else ()
    if spec.file is None:
        dim = 3 if spec.generator == "unit_cube" else 2
        vertices = _GENERATOR_VERTICES[spec.generator]
        for key, n in [("mesh.n", spec.n)] + [("study.levels", n) for n in levels]:
            _refuse(scene.source, key, n, _estimated_dofs(vertices(n), dim, 0, elements),
                    f"{spec.generator}(n={n})")
        refinements = _estimated_dofs(vertices(max([spec.n, *levels])), dim, spec.refine,
                                      elements)
        _refuse(scene.source, "mesh.refine", spec.refine, refinements,
                f"{spec.generator}(n={max([spec.n, *levels])}) refined {spec.refine} times")
        return
    for key, r in [("mesh.refine", spec.refine)] + [("study.levels", r) for r in levels]:
        # a single triangle refined r times has (2^r + 1)(2^r + 2) / 2 vertices
        _refuse(scene.source, key, r, _estimated_dofs(1, 2, 0, elements)
                * (2 ** r + 1) * (2 ** r + 2) // 2, f"even one cell refined {r} times")


def check_refined_size(scene: Scene, vertices: int, dim: int, refinements: int) -> None:
    """Refuse refining a mesh of ``vertices`` vertices ``refinements`` times where the result
    would exceed :func:`max_dofs` (called with the mesh file read, before refining)."""
    elements = (scene.pde.element,
                *(scene.study.elements if scene.study.kind == "h" else ()))
    _refuse(scene.source, "mesh.refine" if refinements == scene.mesh.refine else
            "study.levels", refinements,
            _estimated_dofs(vertices, dim, refinements, elements),
            f"the {vertices}-vertex mesh {scene.mesh.file} refined {refinements} times")


class _Table:
    """Reads one TOML table key by key; whatever is left unread is an unknown key.

    ``error`` is the class of the errors it raises (a :class:`SceneError`; see the module).
    """

    def __init__(self, data: Any, section: str, source: str,
                 error: type[SceneError] = SceneError):
        if not isinstance(data, dict):
            raise SceneError(f"{source}: [{section}] must be a table, got {data!r}")
        self.data, self.section, self.source, self.error = dict(data), section, source, error
        self.read: list[str] = []

    def where(self, key: str) -> str:
        return f"{self.section}.{key}" if self.section else key

    def fail(self, key: str, expected: str, error: type[SceneError] | None = None) -> SceneError:
        return (error or self.error)(f"{self.source}: {self.where(key)} = "
                                     f"{self.data.get(key)!r}: expected {expected}")

    def get(self, key: str, default: Any, check, expected: str,
            error: type[SceneError] | None = None) -> Any:
        self.read.append(key)
        if key not in self.data:
            return default
        value = self.data[key]
        if not check(value):
            raise self.fail(key, expected, error)
        return value

    def integer(self, key: str, default: int | None, minimum: int = 0) -> int | None:
        return self.get(key, default, lambda v: _is_int(v) and v >= minimum,
                        f"an integer >= {minimum}")

    def number(self, key: str, default: float | None, *, low: float = float("-inf"),
               high: float = float("inf"), open_low: bool = False,
               error: type[SceneError] | None = None) -> float | None:
        def check(v):  # the type first: a string must fail the check, not the comparison
            return _is_number(v) and (v > low if open_low else v >= low) and v <= high
        bound = f"> {low}" if open_low else f">= {low}"
        value = self.get(key, default, check, f"a finite number {bound} and <= {high}", error)
        return None if value is None else float(value)

    def choice(self, key: str, default: str | None, choices: tuple[str, ...],
               error: type[SceneError] | None = None) -> str | None:
        return self.get(key, default, lambda v: v in choices, f"one of {list(choices)}", error)

    def boolean(self, key: str, default: bool) -> bool:
        return self.get(key, default, lambda v: isinstance(v, bool), "true or false")

    def field(self, key: str, default: Field | None, dim: int = 3) -> Field | None:
        value = self.get(key, default, lambda v: True, "")
        if value is not None:
            compile_field(value, where=f"{self.source}: {self.where(key)}", dim=dim)
        return value if not _is_number(value) else float(value)

    def field_table(self, key: str) -> tuple[tuple[str, Field], ...]:
        table = self.get(key, {}, lambda v: isinstance(v, dict), "a table {boundary = value}")
        for name, value in table.items():
            compile_field(value, where=f"{self.source}: {self.where(key)}.{name}")
        return tuple(sorted(table.items()))

    def finish(self) -> None:
        unknown = sorted(set(self.data) - set(self.read))
        if unknown:
            raise SceneError(f"{self.source}: unknown key {self.where(unknown[0])!r}; allowed "
                             f"in [{self.section or 'top level'}]: {sorted(set(self.read))}")


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) \
        and abs(value) != float("inf") and value == value


# --------------------------------------------------------------------------------------
# sections
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class MeshSpec:
    """Where the mesh comes from. ``n``: cells per unit length (squares, cubes, the holed
    rectangle) or refinement level (L-shape, disk). ``file`` is resolved against the scene."""

    generator: str | None = "unit_square"
    file: str | None = None
    n: int = 32
    cell: str | None = None  # triangle | quad (2-D generators), tetra | hexahedron (unit_cube)
    refine: int = 0          # uniform refinements after generation or loading
    repair: bool = False     # merge duplicate nodes, drop unused ones (load_mesh(repair=True))


@dataclasses.dataclass(frozen=True)
class PdeSpec:
    """``-div(kappa grad u) = source`` with Dirichlet / Neumann data; ``exact`` for h-studies."""

    element: str = "P1"
    kappa_space: str = "P0"
    kappa: Field = 1.0
    source: Field = 1.0
    dirichlet: Field | tuple[tuple[str, Field], ...] = 0.0
    neumann: tuple[tuple[str, Field], ...] = ()
    exact: Field | None = None
    pins: tuple[tuple[float, ...], ...] = ()   # (x, y[, z], value): u pinned at a vertex


@dataclasses.dataclass(frozen=True)
class InverseSpec:
    """What is unknown, what is observed and how the misfit is regularised.

    Data are ``data`` (a field observed in full: the misfit is against its L2 projection) or,
    when absent, synthetic: the state of ``truth`` (solved once, directly), observed, plus
    Gaussian noise ``noise * max|d|`` seeded with ``seed``. ``sensors``: a count of random
    interior mesh vertices, or a list of coordinates. ``unknown = "density"`` recovers a SIMP
    density (``kappa = k_min + (k_max - k_min) rho ** penalty``, ``simp = (k_min, k_max,
    penalty)``; bounds default to ``[0, 1]``). ``regularization = "bilaplacian"`` is a
    Gaussian prior (``prior = (gamma, delta, mean)``,
    :func:`~prdp_fem.fem.priors.bilaplacian_prior`; ``alpha`` is then the noise variance)
    and ``posterior = (rank, samples)`` the Laplace posterior each run writes
    (:func:`~prdp_fem.inverse.posterior.laplace_posterior`).
    """

    unknown: str = "source"
    truth: Field | None = None
    data: Field | None = None
    observations: str = "full_field"
    norm: str = "l2"
    sensors: int | tuple[tuple[float, ...], ...] = 50
    boundaries: tuple[str, ...] = ()
    noise: float = 0.0
    seed: int = 0
    alpha: float = 1e-6
    regularization: str = "h1"
    bounds: tuple[float, float] | None = None
    init: Field | None = None
    simp: tuple[float, float, float] | None = None   # density: (k_min, k_max, penalty)
    # regularization = "bilaplacian": the Gaussian prior (gamma, delta, mean) and the Laplace
    # posterior written after each run (rank, samples; rank 0: none)
    prior: tuple[float, float, float] | None = None
    posterior: tuple[int, int] = (0, 0)

    @property
    def is_coefficient(self) -> bool:
        """Whether the unknown is mapped to kappa (log kappa or a density), not the source."""
        return self.unknown != "source"


@dataclasses.dataclass(frozen=True)
class SolverSpec:
    """The CG solve. ``iterations``: the K list of forward studies and ``prdp-fem solve``'s
    truncation (its first entry; none: solve to ``rtol``). ``preconditioner = "amg"``: a
    pyamg hierarchy (``amg_kind``, ``amg_implementation``) built from the run's operator; an
    inversion builds it at its initial coefficient and rebuilds it every ``rebuild_every``
    steps or once kappa moved by more than ``rebuild_factor`` (:class:`prdp_fem.RebuiltAMG`;
    0: never, the default, so that a run can switch off what its scene sets); a training
    (``study.kind = "learned"`` or ``"heat"``) builds it once, from its fixed operator.
    ``warm_start``: an inversion's solves start from the previous evaluation's solutions
    (:func:`prdp_fem.invert`'s ``warm_start``), moved every ``warm_start_every`` steps."""

    preconditioner: str = "jacobi"
    gradient: str = "implicit"
    iterations: tuple[int, ...] = ()
    rtol: float = 1e-10
    amg_kind: str = "sa"
    amg_implementation: str = "jax"
    rebuild_every: int = 0
    rebuild_factor: float = 0.0
    warm_start: bool = False
    warm_start_every: int = 1


@dataclasses.dataclass(frozen=True)
class RefinementSpec:
    """How the CG iterations are chosen during an inversion or a training (see
    :mod:`prdp_fem.inverse.refinement`): what every kind has. One subclass per ``kind``
    holds that controller's settings, with the controller's own defaults (checked by the
    test suite against its signature): :class:`PrdpSpec`, :class:`FixedSpec`,
    :class:`ConvergedSpec`, :class:`AdaptiveSpec`, :class:`GapSpec`.

    ``monitor``: what the controller watches, ``"loss"``, ``"gradient"`` or
    ``"validation"`` (a converged solve every ``validation_every`` steps, to
    ``validation_rtol``).
    """

    kind: str = dataclasses.field(default="", init=False)
    monitor: str = "loss"
    validation_every: int = 1
    validation_rtol: float = 1e-10


@dataclasses.dataclass(frozen=True)
class PrdpSpec(RefinementSpec):
    """``kind = "prdp"``: :func:`prdp_fem.inverse.prdp`'s schedule and stopping rule.

    ``ema_window`` left unset is :data:`MONOTONE_EMA_WINDOW` (2) in an inversion whose
    controller watches the loss of a line-search optimiser, else the reference's 6 (see
    :func:`default_ema_window`); ``restart`` is on in scenes (an inversion's loss moves when
    ``K`` does).
    """

    kind: str = dataclasses.field(default="prdp", init=False)
    K0: int = 25
    dK: int = 10
    K_max: int = 600
    factor: float = 1.0
    adjoint_K0: int | None = None
    adjoint_dK: int = 10
    adjoint_K_max: int = 600
    adjoint_factor: float = 1.0
    tau_step: float = 0.98
    tau_stop: float = 0.9
    ema_window: int | None = None  # None: default_ema_window (parse_scene fills it in)
    delta: int = 3
    latch: bool = False
    restart: bool = True
    stall_on_failure: bool = False
    rtol: float | None = None     # tolerance mode: the first relative tolerance ...
    rtol_factor: float = 0.1      # ... rtol *= rtol_factor at a refinement ...
    rtol_min: float = 1e-12       # ... down to rtol_min
    per_learning_rate: bool = False  # a stall judged per unit learning rate (trainings)


@dataclasses.dataclass(frozen=True)
class FixedSpec(RefinementSpec):
    """``kind = "fixed"``: :func:`prdp_fem.inverse.fixed`, ``K`` primal and ``K_adj``
    adjoint iterations every step (``None``: ``K``)."""

    kind: str = dataclasses.field(default="fixed", init=False)
    K: int = 20
    K_adj: int | None = None


@dataclasses.dataclass(frozen=True)
class ConvergedSpec(RefinementSpec):
    """``kind = "converged"``: :func:`prdp_fem.inverse.converged`, every solve to ``rtol``."""

    kind: str = dataclasses.field(default="converged", init=False)
    rtol: float = 1e-10


@dataclasses.dataclass(frozen=True)
class AdaptiveSpec(RefinementSpec):
    """``kind = "adaptive"``: :func:`prdp_fem.inverse.adaptive_tolerance`, every solve to
    ``rtol0 (|g_k| / |g_1|) ** power``, clipped to ``[rtol_min, rtol0]``, tightened by
    ``failure_factor`` at a failed line search; it watches the gradient."""

    kind: str = dataclasses.field(default="adaptive", init=False)
    monitor: str = "gradient"
    rtol0: float = 1e-2
    power: float = 1.0
    rtol_min: float = 1e-10
    failure_factor: float = 0.1


@dataclasses.dataclass(frozen=True)
class GapSpec(RefinementSpec):
    """``kind = "gap"``: :func:`prdp_fem.inverse.truncation_gap`, a training's solves to
    ``rtol``, multiplied by ``rtol_factor`` (down to ``rtol_min``) while running the validation
    at that tolerance changes its error by more than ``max_gap`` (learned and heat scenes);
    ``redo``: the epoch that tightened them is trained again; ``reference_factor``: a mixed
    heat run's reference chain runs to ``rtol * reference_factor`` (1e-10 or less: converged)."""

    kind: str = dataclasses.field(default="gap", init=False)
    monitor: str = "truncation_gap"
    rtol: float = 1e-2
    max_gap: float = 0.01
    rtol_factor: float = 0.1
    rtol_min: float = 1e-10
    redo: bool = True
    reference_factor: float = 1e-2


#: The spec class of each ``refinement.kind``.
REFINEMENT_SPECS: dict[str, type[RefinementSpec]] = {
    "prdp": PrdpSpec, "fixed": FixedSpec, "converged": ConvergedSpec, "adaptive": AdaptiveSpec,
    "gap": GapSpec}


@dataclasses.dataclass(frozen=True)
class OptimizerSpec:
    name: str = "lbfgs"
    steps: int = 100
    learning_rate: float = 1e-2   # adam, sgd, hig
    memory_size: int = 10         # lbfgs
    first_step: str = "unit"      # lbfgs: the first search's trial (prdp_fem.optim.linesearch)
    # newton_cg, gauss_newton (prdp_fem.optim.newton): inner CG cap, forcing term
    # ("eisenstat_walker",
    # "hippylib" or a number in (0, 1)), Armijo c1, halvings, stop at ||g|| <= rtol ||g_0||
    max_cg: int = 100
    forcing: str | float = "eisenstat_walker"
    c1: float = 1e-4
    max_backtracking: int = 10
    gradient_rtol: float = 0.0
    # newton_cg, gauss_newton: the inner CG preconditioned by this many AMG V-cycles of the
    # regularisation operator (prdp_fem.optim.newton.regularization_preconditioner); 0: none
    preconditioner_cycles: int = 0
    gauss_newton_steps: int = 0   # newton_cg: the first updates with the Gauss-Newton Hessian
    exponent: float = -0.5        # hig: -0.5 half-inverse, -1 Gauss-Newton, +1 gradient descent
    tau: float = 1e-6             # hig: singular values below tau * s_max are dropped
    rank: int | None = None       # hig: None explicit Jacobian, k matrix-free rank-k SVD
    relative: bool = False        # hig: learning_rate relative to s_max^-(1+exponent)
    decay: str = "constant"       # adam, sgd: "cosine" decays learning_rate to 0 over the run


@dataclasses.dataclass(frozen=True)
class LearnedSpec:
    """A learned inverse (:mod:`prdp_fem.learning.learned`): a network maps observations to sources.

    ``samples`` training and ``validation_samples`` held-out random sources (three Gaussian
    bumps of width ``width`` times the mesh diameter, seeded by ``seed``) and
    ``test_samples`` more (a draw of their own, seeded by ``seed + 2``: the reported error),
    observed through
    ``[inverse]``'s observation operator with ``noise`` times each sample's RMS; an MLP
    ``[n_obs, *hidden, n_dofs]`` trained for ``epochs`` epochs of mini-batches of
    ``batch_size`` (default ``samples``: the full batch, which L-BFGS requires);
    ``supervised``: the weight of the supervised source term.
    """

    samples: int = 64
    validation_samples: int = 16
    noise: float = 0.01
    width: float = 0.2
    hidden: tuple[int, ...] = (32,)
    epochs: int = 30
    batch_size: int = 64      # default: samples (full batch)
    seed: int = 0
    supervised: float = 1e-2
    test_samples: int = 16
    checkpoint_every: int = 10  # epochs between saved training states (and the last)


@dataclasses.dataclass(frozen=True)
class HeatSpec:
    """A learned heat stepper (:mod:`prdp_fem.learning.heat`): implicit Euler of step ``dt`` on the
    scene's mesh and ``[pde]`` (``kappa``, ``source``, Dirichlet data held in time).

    ``trajectories`` training, ``validation_trajectories`` (the PRDP signal) and
    ``test_trajectories`` (held out, reported) reference trajectories of ``steps`` steps, each
    made of ``substeps`` direct solves of ``dt / substeps``, from seeded initial fields (three
    positive Gaussian bumps of width ``width`` times the mesh diameter). An MLP
    ``[n_free, *hidden, n_free]`` trained as the ``setup`` stepper (``correction``,
    ``prediction`` or ``mixed``: the emulator trained through the fine solver, mode ``wig``)
    with ``mode`` (``one``, ``nog``, ``wig``) over windows of ``unroll`` steps, ``epochs``
    epochs of mini-batches of ``batch_size`` windows. ``reaction``: the rate ``r`` of
    a Fisher-KPP reaction ``r u (1 - u)`` (nonlinear; 0: the heat equation).
    """

    dt: float = 0.02
    steps: int = 10
    substeps: int = 4
    trajectories: int = 32
    validation_trajectories: int = 8
    test_trajectories: int = 8
    width: float = 0.2
    hidden: tuple[int, ...] = (128,)
    setup: str = "correction"
    mode: str = "nog"
    unroll: int = 3
    epochs: int = 150
    batch_size: int = 16
    seed: int = 0
    checkpoint_every: int = 10  # epochs between saved training states (and the last)
    reaction: float = 0.0      # Fisher-KPP rate r of r u (1 - u) (0: the heat equation)

    @property
    def windows(self) -> int:
        """Training windows of ``unroll + 1`` states."""
        return self.trajectories * (self.steps - self.unroll + 1)

    @property
    def solves(self) -> bool:
        """Whether training runs the solver (correction, mixed): what PRDP can refine."""
        return self.setup != "prediction"

    @property
    def chain_substeps(self) -> int:
        """Solves per solver step of the training's chain: the reference's ``substeps`` for
        the mixed setup (it trains through the fine step), else 1 (one step of ``dt``)."""
        return self.substeps if self.setup == "mixed" else 1


@dataclasses.dataclass(frozen=True)
class StudySpec:
    """What ``prdp-fem study`` sweeps. ``runs``: ``(name, overrides as canonical JSON)``."""

    kind: str = "inverse"
    runs: tuple[tuple[str, str], ...] = ()
    reference: str = "converged"
    target_error: float | None = None
    band: float = 0.01
    levels: tuple[int, ...] = (4, 8, 16, 32)
    elements: tuple[str, ...] = ("P1", "P2")
    reached: str = "band"     # band: |e - t| <= band t; at_or_below: e <= (1 + band) t


@dataclasses.dataclass(frozen=True)
class Scene:
    name: str
    description: str
    source: str               # the file (or "<table>") for messages
    directory: str | None     # for relative mesh paths
    mesh: MeshSpec
    pde: PdeSpec
    inverse: InverseSpec | None
    solver: SolverSpec
    refinement: RefinementSpec
    optimizer: OptimizerSpec
    study: StudySpec
    raw: str                  # canonical JSON of the table it came from (for variants)
    learned: LearnedSpec | None = None
    heat: HeatSpec | None = None

    @property
    def fingerprint(self) -> str:
        """Hash of everything that changes results (not the name or the description).

        The table and its directory, and the moving-average window of every PRDP run whose
        table leaves it unset and whose default is not the reference's 6: a study written
        before that default changed (to 2 for an inversion's loss under a line-search
        optimiser) must not resume into a mixed one (its finished runs had 6). Studies
        whose runs keep 6 or spell their window keep the fingerprint they had.
        """
        table = json.loads(self.raw)
        for key in ("name", "description"):
            table.pop(key, None)
        payload: list[Any] = [table, self.directory]
        defaulted = {name: run.refinement.ema_window for name, run in self.runs()
                     if run.refinement.kind == "prdp"
                     and "ema_window" not in json.loads(run.raw).get("refinement", {})}
        if any(window != REFERENCE_EMA_WINDOW for window in defaulted.values()):
            payload.append({"ema_window": defaulted})
        text = json.dumps(payload, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def mesh_path(self) -> Path | None:
        """The mesh file, resolved (relative paths against the scene's directory)."""
        if self.mesh.file is None:
            return None
        if self.mesh.file.startswith(PACKAGE_MESH_PREFIX):
            name = self.mesh.file[len(PACKAGE_MESH_PREFIX):]
            return Path(str(resources.files("prdp_fem") / "data" / "meshes" / name))
        path = Path(self.mesh.file).expanduser()
        if not path.is_absolute() and self.directory is not None:
            path = Path(self.directory) / path
        return path

    def same_problem(self, other: Scene) -> bool:
        """Whether ``other`` has this scene's mesh, PDE, data and optimiser: runs that differ
        only in the solver and the refinement, whose costs and errors compare."""
        return all(getattr(self, part) == getattr(other, part)
                   for part in ("mesh", "pde", "inverse", "optimizer"))

    def reference_of(self, name: str) -> str:
        """The converged run that run ``name``'s saving is measured against: one with the
        run's preconditioner (``study.reference`` when it has it), so that a saving is the
        refinement's and not the preconditioner's; ``study.reference`` where no converged
        run of the same problem shares the preconditioner, and for the converged runs
        themselves (their saving compares converged solvers)."""
        variants = dict(self.runs())
        reference = self.study.reference
        run = variants.get(name)
        if run is None or reference not in variants or run.refinement.kind == "converged" or \
                variants[reference].solver.preconditioner == run.solver.preconditioner:
            return reference
        return next((other for other, variant in variants.items()
                     if variant.refinement.kind == "converged"
                     and variant.solver.preconditioner == run.solver.preconditioner
                     and variant.same_problem(run)), reference)

    def variant(self, overrides: dict, name: str) -> Scene:
        """This scene with a study run's ``overrides`` (``{"refinement": {...}, "solver":
        {...}}``: ``refinement`` replaces the scene's, other tables update it), named
        ``name`` and without a ``[study]``."""
        return _variant(self, overrides, name)

    def runs(self) -> list[tuple[str, Scene]]:
        """The study's configurations as scenes.

        With no ``[[study.runs]]``: an inverse study (and a heat study whose setup solves)
        runs the scene's own configuration and a ``"converged"`` baseline (``rtol = 1e-10``);
        other studies run the scene as it is.
        """
        if not self.study.runs:
            baseline_kind = self.study.kind == "inverse" or (
                self.study.kind == "heat" and self.heat.solves)
            if not baseline_kind or self.refinement.kind == "converged":
                return [(self.name, self)]
            baseline = _variant(self, {"refinement": {"kind": "converged"}}, "converged")
            return [("converged", baseline), (self.name, self)]
        return [(name, _variant(self, json.loads(overrides), name))
                for name, overrides in self.study.runs]


# --------------------------------------------------------------------------------------
# parsing
# --------------------------------------------------------------------------------------


def _mesh(t: _Table) -> MeshSpec:
    file = t.get("file", None, lambda v: isinstance(v, str) and v, "a mesh file path")
    generator = t.choice("generator", None if file else "unit_square", GENERATORS)
    if file is not None and generator is not None:
        raise SceneError(f"{t.source}: mesh.file and mesh.generator both given; expected one")
    default_n = 3 if generator in ("l_shape", "disk") else 32
    n = t.integer("n", default_n, minimum=0 if generator in ("l_shape", "disk") else 1)
    cells = {"unit_square": ("triangle", "quad"), "unit_cube": ("tetra", "hexahedron")}
    cell = t.choice("cell", None, cells.get(generator, ()))
    spec = MeshSpec(generator, file, n, cell, t.integer("refine", 0), t.boolean("repair", False))
    t.finish()
    return spec


def _pde(t: _Table) -> PdeSpec:
    element = t.choice("element", "P1", ("P1", "P2", "Q1", "Q2"))
    kappa_space = t.choice("kappa_space", "P0", ("P0", "P1", "P2"))
    kappa, source = t.field("kappa", 1.0), t.field("source", 1.0)
    if _is_number(kappa) and kappa <= 0:
        raise t.fail("kappa", "a coefficient > 0 (a number or a formula positive on the mesh)",
                     SceneCoefficientError)
    if isinstance(t.data.get("dirichlet"), dict):
        dirichlet = t.field_table("dirichlet")
    else:
        dirichlet = t.field("dirichlet", 0.0)
    pins = t.get("pins", [], lambda v: isinstance(v, list) and all(
        isinstance(p, list) and len(p) in (3, 4) and len(p) == len(v[0])
        and all(_is_number(c) for c in p) for p in v),
        "a list of [x, y, value] (or all [x, y, z, value]) point constraints")
    spec = PdeSpec(element, kappa_space, kappa, source, dirichlet, t.field_table("neumann"),
                   t.field("exact", None), tuple(tuple(float(c) for c in p) for p in pins))
    t.finish()
    return spec


def _sensors(t: _Table):
    def check(v):
        if _is_int(v):
            return v >= 1
        return isinstance(v, list) and len(v) > 0 and all(
            isinstance(p, list) and len(p) == len(v[0]) in (2, 3)
            and all(_is_number(c) for c in p) for p in v)
    value = t.get("sensors", 50, check, "a positive count or a non-empty list of [x, y] (or "
                  "all [x, y, z]) points", SceneSensorError)
    return value if _is_int(value) else tuple(tuple(float(c) for c in p) for p in value)


def _inverse(t: _Table, learned: bool = False) -> InverseSpec:
    unknown = t.choice("unknown", "source", ("source", "log_kappa", "density"))
    truth, data = t.field("truth", None), t.field("data", None)
    observations = t.choice("observations", "full_field", ("full_field", "sensors", "boundary"))
    norm = t.choice("norm", "l2", ("l2", "nodal"))
    sensors = _sensors(t)
    boundaries = tuple(t.get("boundaries", [], lambda v: isinstance(v, list) and all(
        isinstance(b, str) for b in v), "a list of boundary names", SceneSensorError))
    noise = t.number("noise", 0.0, low=0.0, error=SceneDataError)
    seed = t.integer("seed", 0)
    alpha = t.number("alpha", 1e-6, low=0.0, error=SceneSolverConfigError)
    regularization = t.choice("regularization", "h1", ("l2", "h1", "tv", "bilaplacian"),
                              SceneSolverConfigError)
    prior, posterior = None, (0, 0)
    if regularization == "bilaplacian":  # the prior's keys exist for a Gaussian prior only
        prior = (t.number("prior_gamma", 0.1, low=0.0, open_low=True,
                          error=SceneSolverConfigError),
                 t.number("prior_delta", 0.5, low=0.0, open_low=True,
                          error=SceneSolverConfigError),
                 t.number("prior_mean", 0.0, error=SceneSolverConfigError))
        posterior = (t.integer("posterior_rank", 0), t.integer("posterior_samples", 3))
    bounds = t.get("bounds", None, lambda v: isinstance(v, list) and len(v) == 2 and all(
        _is_number(b) for b in v) and v[0] < v[1], "[lower, upper] with finite lower < upper",
        SceneDataError if unknown == "source" else SceneCoefficientError)
    law = None
    if unknown == "density":  # the SIMP law's keys exist for a density only
        from ..fem.parameters import Simp  # its defaults; loaded only for a density scene

        defaults = Simp()
        law = (t.number("k_min", defaults.k_min, low=0.0, open_low=True,
                        error=SceneCoefficientError),
               t.number("k_max", defaults.k_max, low=0.0, open_low=True,
                        error=SceneCoefficientError),
               t.number("penalty", defaults.penalty, low=1.0, error=SceneCoefficientError))
        if not law[0] < law[1]:
            raise SceneCoefficientError(f"{t.source}: inverse.k_min = {law[0]} and k_max = "
                                        f"{law[1]}: expected k_min < k_max")
        if bounds is not None and not 0 <= bounds[0] < bounds[1] <= 1:
            raise SceneCoefficientError(f"{t.source}: inverse.bounds = {bounds}: expected "
                                        "0 <= lower < upper <= 1 for a density")
    spec = InverseSpec(unknown, truth, data, observations, norm, sensors, boundaries, noise,
                       seed, alpha, regularization,
                       None if bounds is None else (float(bounds[0]), float(bounds[1])),
                       t.field("init", None), law, prior, posterior)
    t.finish()
    if learned:
        if unknown != "source":
            raise t.fail("unknown", "'source' for a learned inverse (the network predicts the "
                         "source)")
        return spec
    if data is None and truth is None:
        raise SceneError(f"{t.source}: [inverse] needs 'truth' (synthetic data) or 'data'")
    if data is not None and observations != "full_field":
        raise SceneError(f"{t.source}: inverse.data is a field observed everywhere; expected "
                         f"observations = 'full_field', got {observations!r}")
    if observations == "boundary" and not boundaries:
        raise SceneSensorError(f"{t.source}: inverse.boundaries: expected a non-empty list of "
                               "boundary names for observations = 'boundary'")
    return spec


_AMG_KEYS = ("amg_kind", "amg_implementation", "rebuild_every", "rebuild_factor")


def _solver(t: _Table) -> SolverSpec:
    spec = SolverSpec(
        t.choice("preconditioner", "jacobi", ("jacobi", "identity", "amg")),
        t.choice("gradient", "implicit", ("implicit", "unrolled")),
        tuple(t.get("iterations", [], lambda v: isinstance(v, list) and all(
            _is_int(k) and k >= 0 for k in v), "a list of integers >= 0")),
        t.number("rtol", 1e-10, low=0.0, high=0.5, open_low=True),
        t.choice("amg_kind", "sa", ("sa", "rs")),
        t.choice("amg_implementation", "jax", ("jax", "callback")),
        t.integer("rebuild_every", 0),
        float(t.get("rebuild_factor", 0.0, lambda v: _is_number(v) and (v == 0 or v > 1),
                    "0 (never) or a finite number > 1")),
        t.boolean("warm_start", False),
        t.integer("warm_start_every", 1, 1))
    t.finish()
    if "warm_start_every" in t.data and not spec.warm_start:
        raise t.fail("warm_start_every", "no value unless solver.warm_start = true")
    if spec.preconditioner != "amg":
        for key in _AMG_KEYS:
            if key in t.data:
                raise t.fail(key, "no value unless solver.preconditioner = 'amg' (it is "
                             f"{spec.preconditioner!r})")
    return spec


_REFINEMENT_KEYS = {
    kind: tuple(f.name for f in dataclasses.fields(spec) if f.init and
                f.name not in {g.name for g in dataclasses.fields(RefinementSpec)})
    for kind, spec in REFINEMENT_SPECS.items()}


def _refinement(t: _Table) -> RefinementSpec:
    kind = t.choice("kind", "prdp", tuple(_REFINEMENT_KEYS))
    spec_class = REFINEMENT_SPECS[kind]
    defaults = spec_class()
    values: dict[str, Any] = {}
    readers = {
        "K0": lambda k: t.integer(k, defaults.K0, 1),
        "dK": lambda k: t.integer(k, defaults.dK, 0),
        "K_max": lambda k: t.integer(k, defaults.K_max, 1),
        "factor": lambda k: t.number(k, defaults.factor, low=1.0),
        "adjoint_K0": lambda k: t.integer(k, defaults.adjoint_K0, 1),
        "adjoint_dK": lambda k: t.integer(k, defaults.adjoint_dK, 0),
        "adjoint_K_max": lambda k: t.integer(k, defaults.adjoint_K_max, 1),
        "adjoint_factor": lambda k: t.number(k, defaults.adjoint_factor, low=1.0),
        "tau_step": lambda k: t.number(k, defaults.tau_step, low=0.0, open_low=True),
        "tau_stop": lambda k: t.number(k, defaults.tau_stop, low=0.0, high=1.0, open_low=True),
        "ema_window": lambda k: t.integer(k, defaults.ema_window, 1),
        "delta": lambda k: t.integer(k, defaults.delta, 2),
        "latch": lambda k: t.boolean(k, defaults.latch),
        "restart": lambda k: t.boolean(k, defaults.restart),
        "stall_on_failure": lambda k: t.boolean(k, defaults.stall_on_failure),
        "per_learning_rate": lambda k: t.boolean(k, defaults.per_learning_rate),
        "rtol": lambda k: t.number(k, defaults.rtol, low=0.0, high=0.5, open_low=True),
        "rtol_factor": lambda k: t.number(k, defaults.rtol_factor, low=0.0, high=1.0,
                                          open_low=True),
        "rtol_min": lambda k: t.number(k, defaults.rtol_min, low=0.0, high=0.5,
                                       open_low=True),
        "rtol0": lambda k: t.number(k, defaults.rtol0, low=0.0, high=0.5, open_low=True),
        "power": lambda k: t.number(k, defaults.power, low=0.0, open_low=True),
        "failure_factor": lambda k: t.number(k, defaults.failure_factor, low=0.0, high=1.0,
                                             open_low=True),
        "max_gap": lambda k: t.number(k, defaults.max_gap, low=0.0, open_low=True),
        "redo": lambda k: t.boolean(k, defaults.redo),
        "reference_factor": lambda k: t.number(k, defaults.reference_factor, low=0.0,
                                               high=0.5, open_low=True),
        "K": lambda k: t.integer(k, defaults.K, 0),
        "K_adj": lambda k: t.integer(k, defaults.K_adj, 0),
    }
    for key in _REFINEMENT_KEYS[kind]:
        values[key] = readers[key](key)
    # the adaptive controller is fed the gradient norm (prdp.adaptive_tolerance)
    # and the gap controller the truncation gap of a training's validation (truncation_gap)
    values["monitor"] = t.choice("monitor", defaults.monitor, {
        "adaptive": ("gradient",), "gap": ("truncation_gap",)}.get(
            kind, ("loss", "gradient", "validation")))
    values["validation_every"] = t.integer("validation_every", defaults.validation_every, 1)
    values["validation_rtol"] = t.number("validation_rtol", defaults.validation_rtol, low=0.0,
                                         high=0.5, open_low=True)
    t.finish()
    spec = spec_class(**values)
    if kind == "adaptive" and spec.rtol_min > spec.rtol0:
        raise SceneSolverConfigError(f"{t.source}: refinement.rtol_min = {spec.rtol_min} "
                                     f"exceeds rtol0 = {spec.rtol0}; expected rtol_min <= rtol0")
    if kind == "gap" and spec.rtol_min > spec.rtol:
        raise SceneSolverConfigError(f"{t.source}: refinement.rtol_min = {spec.rtol_min} "
                                     f"exceeds rtol = {spec.rtol}; expected rtol_min <= rtol")
    if kind == "prdp" and spec.K0 > spec.K_max:
        raise SceneSolverConfigError(f"{t.source}: refinement.K0 = {spec.K0} exceeds K_max = "
                                     f"{spec.K_max}; expected K0 <= K_max")
    return spec


#: ``rtol_min`` of an adaptive controller: the converged baseline's tolerance
ADAPTIVE_RTOL_MIN = AdaptiveSpec.rtol_min

#: Optimisers that step only where their line search found a decrease: between two
#: refinements the loss they report falls monotonically.
LINE_SEARCH_OPTIMIZERS = ("lbfgs", "newton_cg", "gauss_newton")
#: The reference's moving-average window (``prdp_fem.inverse.prdp``'s default): it smooths the
#: epoch-to-epoch noise of stochastic training, a gradient norm or a validation error.
REFERENCE_EMA_WINDOW = 6
#: The window where the monitored value is the loss of a line-search optimiser in an
#: inversion: a monotone signal with no noise to smooth, whose stall the reference's window
#: sees some ten steps late (see the README's "PRDP saving on the built-in scenes").
MONOTONE_EMA_WINDOW = 2


def default_ema_window(study_kind: str, monitor: str, optimizer: str) -> int:
    """``refinement.ema_window`` where a scene leaves it unset.

    >>> default_ema_window("inverse", "loss", "lbfgs")
    2
    >>> default_ema_window("inverse", "gradient", "lbfgs")  # a gradient norm is not monotone
    6
    >>> default_ema_window("learned", "loss", "adam")
    6
    """
    monotone = study_kind == "inverse" and monitor == "loss" and \
        optimizer in LINE_SEARCH_OPTIMIZERS
    return MONOTONE_EMA_WINDOW if monotone else REFERENCE_EMA_WINDOW


def ema_window_of(scene: Scene) -> int:
    """The scene's moving-average window: the one its table gives, else
    :func:`default_ema_window` (a :class:`PrdpSpec` built by hand leaves it unset)."""
    spec = scene.refinement
    if spec.ema_window is not None:
        return spec.ema_window
    return default_ema_window(scene.study.kind, spec.monitor, scene.optimizer.name)


def _optimizer(t: _Table, default_name: str = "lbfgs") -> OptimizerSpec:
    spec = OptimizerSpec(t.choice("name", default_name,
                                  ("lbfgs", "adam", "sgd", *_NEWTON, "hig")),
                         t.integer("steps", 100, 0),
                         t.number("learning_rate", 1e-2, low=0.0, open_low=True),
                         t.integer("memory_size", 10, 1), **_newton_options(t),
                         **_hig_options(t), decay=t.choice("decay", "constant",
                                                           ("constant", "cosine")),
                         first_step=t.choice("first_step", "unit", _FIRST_STEPS))
    t.finish()
    if spec.first_step != "unit" and spec.name != "lbfgs":
        raise SceneSolverConfigError(f"{t.source}: optimizer.first_step = "
                                     f"{spec.first_step!r} with optimizer.name = "
                                     f"{spec.name!r}: expected a first step only for 'lbfgs'")
    if spec.preconditioner_cycles and spec.name not in _NEWTON:
        raise SceneSolverConfigError(f"{t.source}: optimizer.preconditioner_cycles = "
                                     f"{spec.preconditioner_cycles} with optimizer.name = "
                                     f"{spec.name!r}: expected it only for 'newton_cg' or "
                                     "'gauss_newton'")
    if spec.gauss_newton_steps and spec.name != "newton_cg":
        raise SceneSolverConfigError(f"{t.source}: optimizer.gauss_newton_steps = "
                                     f"{spec.gauss_newton_steps} with optimizer.name = "
                                     f"{spec.name!r}: expected it only for 'newton_cg' (its "
                                     "first updates then use the Gauss-Newton Hessian)")
    if spec.decay != "constant" and spec.name not in ("adam", "sgd"):
        raise SceneSolverConfigError(f"{t.source}: optimizer.decay = {spec.decay!r} with "
                                     f"optimizer.name = {spec.name!r}: expected a decay only "
                                     "for 'adam' or 'sgd'")
    return spec


_NEWTON = ("newton_cg", "gauss_newton")
#: lbfgs's first line-search trials (prdp_fem.optim.linesearch.FIRST_STEPS: this module stays free
#: of jax, so that a scene is checked before jax is imported)
_FIRST_STEPS = ("unit", "polyak")


def _hig_options(t: _Table) -> dict[str, Any]:
    """The half-inverse-gradient keys of ``[optimizer]`` (read whatever the name)."""
    return dict(exponent=t.number("exponent", -0.5),
                tau=float(t.get("tau", 1e-6, lambda v: _is_number(v) and 0 <= v < 1,
                                "a number in [0, 1) (relative singular-value cut-off)")),
                rank=t.integer("rank", None, 1),
                relative=t.boolean("relative", False))


def _newton_options(t: _Table) -> dict[str, Any]:
    """The Newton-CG / Gauss-Newton keys of ``[optimizer]`` (read whatever the name)."""
    forcing = t.get("forcing", "eisenstat_walker", lambda v: v in ("eisenstat_walker",
                                                                   "hippylib")
                    or (_is_number(v) and 0 < v < 1),
                    "'eisenstat_walker', 'hippylib' or a number in (0, 1)")
    return dict(max_cg=t.integer("max_cg", 100, 1),
                forcing=forcing if isinstance(forcing, str) else float(forcing),
                c1=float(t.get("c1", 1e-4, lambda v: _is_number(v) and 0 < v < 0.5,
                               "a number in (0, 0.5)")),
                max_backtracking=t.integer("max_backtracking", 10, 0),
                gradient_rtol=t.number("gradient_rtol", 0.0, low=0.0),
                preconditioner_cycles=t.integer("preconditioner_cycles", 0, 0),
                gauss_newton_steps=t.integer("gauss_newton_steps", 0, 0))


def _runs(t: _Table) -> tuple[tuple[str, str], ...]:
    runs = t.get("runs", [], lambda v: isinstance(v, list) and all(
        isinstance(r, dict) for r in v), "a list of [[study.runs]] tables")
    parsed, seen = [], set()
    for index, run in enumerate(runs):
        where = f"study.runs[{index}]"
        name = run.get("name")
        if not (isinstance(name, str) and name.strip()):
            raise SceneError(f"{t.source}: {where}.name = {name!r}: expected a non-empty string")
        if name in seen:
            raise SceneError(f"{t.source}: {where}.name = {name!r}: run names must be unique")
        seen.add(name)
        extra = sorted(set(run) - {"name", *_RUN_SECTIONS})
        if extra:
            raise SceneError(f"{t.source}: unknown key '{where}.{extra[0]}'; allowed: "
                             f"{['name', *_RUN_SECTIONS]}")
        overrides = {k: v for k, v in run.items() if k != "name"}
        parsed.append((name, json.dumps(overrides, sort_keys=True)))
    return tuple(parsed)


_RUN_SECTIONS = ("mesh", "pde", "solver", "refinement", "optimizer", "learned", "heat")


def _learned(t: _Table) -> LearnedSpec:
    samples = t.integer("samples", LearnedSpec.samples, 1)
    spec = LearnedSpec(
        samples, t.integer("validation_samples", LearnedSpec.validation_samples, 1),
        t.number("noise", LearnedSpec.noise, low=0.0, error=SceneDataError),
        t.number("width", LearnedSpec.width, low=0.0, open_low=True),
        tuple(t.get("hidden", list(LearnedSpec.hidden), lambda v: isinstance(v, list) and all(
            _is_int(n) and n >= 1 for n in v), "a list of hidden layer sizes (integers >= 1)")),
        t.integer("epochs", LearnedSpec.epochs, 1),
        t.get("batch_size", samples,
              lambda v: _is_int(v) and 1 <= v <= samples,
              f"an integer from 1 to learned.samples = {samples}"),
        t.integer("seed", LearnedSpec.seed, 0),
        t.number("supervised", LearnedSpec.supervised, low=0.0),
        t.integer("test_samples", LearnedSpec.test_samples, 1),
        t.integer("checkpoint_every", LearnedSpec.checkpoint_every, 1))
    t.finish()
    return spec


def _heat(t: _Table) -> HeatSpec:
    d = HeatSpec()
    steps = t.integer("steps", d.steps, 1)
    spec = HeatSpec(
        t.number("dt", d.dt, low=0.0, open_low=True), steps,
        t.integer("substeps", d.substeps, 1), t.integer("trajectories", d.trajectories, 1),
        t.integer("validation_trajectories", d.validation_trajectories, 1),
        t.integer("test_trajectories", d.test_trajectories, 1),
        t.number("width", d.width, low=0.0, open_low=True),
        tuple(t.get("hidden", list(d.hidden), lambda v: isinstance(v, list) and all(
            _is_int(n) and n >= 1 for n in v), "a list of hidden layer sizes (integers >= 1)")),
        t.choice("setup", d.setup, ("correction", "prediction", "mixed")),
        t.choice("mode", d.mode, ("one", "nog", "wig")),
        t.get("unroll", d.unroll, lambda v: _is_int(v) and 1 <= v <= steps,
              f"an integer from 1 to heat.steps = {steps}"),
        t.integer("epochs", d.epochs, 1), t.integer("batch_size", d.batch_size, 1),
        t.integer("seed", d.seed, 0), t.integer("checkpoint_every", d.checkpoint_every, 1),
        t.number("reaction", d.reaction, low=0.0))
    if spec.setup == "mixed" and spec.mode != "wig":
        raise t.error(f"{t.source}: heat.mode = {spec.mode!r} with heat.setup = 'mixed': "
                      "expected 'wig' (the mixed chain trains the network through the "
                      "solver's steps)")
    if spec.setup == "mixed" and spec.unroll < 2:
        raise t.error(f"{t.source}: heat.unroll = {spec.unroll} with heat.setup = 'mixed': "
                      "expected at least 2 (a network step and a solver step)")
    if spec.batch_size > spec.windows:
        raise t.fail("batch_size", f"at most the {spec.windows} training windows (heat."
                     f"trajectories = {spec.trajectories} x {spec.steps - spec.unroll + 1} "
                     "starts of heat.unroll + 1 states)")
    t.finish()
    return spec


def _study_kind(table: dict, has_inverse: bool) -> str:
    """The study kind a table asks for (read before the sections that depend on it)."""
    study = table.get("study")
    kind = study.get("kind") if isinstance(study, dict) else None
    if isinstance(kind, str):
        return kind
    for section in ("learned", "heat"):
        if section in table:
            return section
    return "inverse" if has_inverse else "forward"


def _study(t: _Table, has_inverse: bool, default_kind: str) -> StudySpec:
    kind = t.choice("kind", default_kind, ("inverse", "forward", "h", "learned", "heat"))
    spec = StudySpec(
        kind, _runs(t), t.get("reference", "converged", lambda v: isinstance(v, str),
                              "the name of a run"),
        t.number("target_error", None, low=0.0, open_low=True),
        t.number("band", 0.01, low=0.0, high=1.0, open_low=True),
        tuple(t.get("levels", [4, 8, 16, 32], lambda v: isinstance(v, list) and len(v) >= 2
                    and all(_is_int(n) and n >= 0 for n in v) and v == sorted(set(v)),
                    "an increasing list of at least two mesh levels (n, or refinements "
                    "of a mesh file)")),
        tuple(t.get("elements", ["P1", "P2"], lambda v: isinstance(v, list) and v and all(
            e in ("P1", "P2", "Q1", "Q2") for e in v), "a list of P1, P2, Q1, Q2")),
        t.choice("reached", "band", ("band", "at_or_below")))
    t.finish()
    if kind in ("inverse", "learned") and not has_inverse:
        raise SceneError(f"{t.source}: study.kind = {kind!r} needs an [inverse] section"
                         + (" (its observations)" if kind == "learned" else ""))
    return spec


_SECTIONS = ("mesh", "pde", "inverse", "solver", "refinement", "optimizer", "learned",
             "heat", "study")


def _is_file_name(value: Any) -> bool:
    """A non-empty string that is one path component on every platform."""
    return (isinstance(value, str) and bool(value.strip()) and value not in (".", "..")
            and not any(c in value for c in "/\\\0"))


def parse_scene(table: dict, *, source: str = "<table>", directory: str | None = None,
                default_name: str = "scene", _with_runs: bool = True) -> Scene:
    """Validate a scene table (as :func:`tomllib.loads` returns it) into a :class:`Scene`."""
    top = _Table(table, "", source)
    # the name becomes file and directory names (./study-NAME, ./NAME-solution.vtu): one
    # path component, so that no output lands outside the directory the user works in
    name = top.get("name", default_name, _is_file_name,
                   "a non-empty string usable as a file name (no '/', '\\' or NUL, not '..')")
    description = top.get("description", "", lambda v: isinstance(v, str), "a string")
    sections = {key: top.get(key, {}, lambda v: isinstance(v, dict), f"a [{key}] table")
                for key in _SECTIONS}
    top.finish()
    has_inverse = "inverse" in table
    if "study" in table and not _with_runs:
        raise SceneError(f"{source}: a study run cannot contain a [study] section")
    kind = _study_kind(table, has_inverse)
    learned, heat = kind == "learned", kind == "heat"
    for section in ("learned", "heat"):
        if section in table and kind != section:
            raise SceneError(f"{source}: a [{section}] section with study.kind = {kind!r}; "
                             f"expected study.kind = '{section}' (or no [{section}] section)")
    if heat and has_inverse:
        raise SceneError(f"{source}: an [inverse] section with study.kind = 'heat'; expected "
                         "none (a heat study learns a time stepper, it observes nothing)")
    scene = Scene(
        name=name, description=description, source=source, directory=directory,
        mesh=_mesh(_Table(sections["mesh"], "mesh", source)),
        pde=_pde(_Table(sections["pde"], "pde", source)),
        inverse=_inverse(_Table(sections["inverse"], "inverse", source), learned)
        if has_inverse else None,
        solver=_solver(_Table(sections["solver"], "solver", source, SceneSolverConfigError)),
        refinement=_refinement(_Table(sections["refinement"], "refinement", source,
                                      SceneSolverConfigError)),
        optimizer=_optimizer(_Table(sections["optimizer"], "optimizer", source,
                                    SceneSolverConfigError), "adam" if heat else "lbfgs"),
        study=_study(_Table(sections["study"], "study", source), has_inverse, kind),
        raw=json.dumps(table, sort_keys=True),
        learned=_learned(_Table(sections["learned"], "learned", source)) if learned else None,
        heat=_heat(_Table(sections["heat"], "heat", source)) if heat else None)
    if isinstance(scene.refinement, PrdpSpec):
        scene = dataclasses.replace(scene, refinement=dataclasses.replace(
            scene.refinement, ema_window=ema_window_of(scene)))
    if learned:
        _check_learned_optimizer(scene)
    if kind != "inverse" and scene.refinement.kind == "adaptive":
        raise SceneSolverConfigError(
            f"{source}: refinement.kind = 'adaptive' with study.kind = {kind!r}: expected "
            "'prdp', 'fixed' or 'converged' (the adaptive controller follows an inversion's "
            "gradient)")
    if kind not in ("learned", "heat") and scene.refinement.kind == "gap":
        raise SceneSolverConfigError(
            f"{source}: refinement.kind = 'gap' with study.kind = {kind!r}: expected a "
            "learned or heat study (the truncation gap is measured on a training's "
            "validation set)")
    if getattr(scene.refinement, "per_learning_rate", False):
        if kind not in ("learned", "heat"):
            raise SceneSolverConfigError(
                f"{source}: refinement.per_learning_rate = true with study.kind = {kind!r}: "
                "expected a learned or heat study (the trainers feed the controller their "
                "learning rate)")
        if scene.optimizer.name in ("lbfgs", "newton_cg", "gauss_newton"):
            raise SceneSolverConfigError(
                f"{source}: refinement.per_learning_rate = true with optimizer.name = "
                f"{scene.optimizer.name!r}: expected an optimiser with a learning rate "
                "('adam', 'sgd' or 'hig')")
    if kind != "inverse" and scene.solver.warm_start:
        raise SceneSolverConfigError(
            f"{source}: solver.warm_start = true with study.kind = {kind!r}: expected false "
            "or no value (warm starts carry an inversion's solves from step to step)")
    rebuilds = scene.solver.rebuild_every or scene.solver.rebuild_factor
    if kind in ("forward", "h", "learned", "heat") and rebuilds:
        raise SceneSolverConfigError(
            f"{source}: solver.rebuild_every / rebuild_factor with study.kind = {kind!r}: "
            "expected 0 or no value (a hierarchy is rebuilt between the optimiser steps of "
            "an inversion; a forward solve or a training builds it once for its fixed "
            "operator)")
    if heat and scene.optimizer.name not in ("adam", "sgd"):
        raise SceneSolverConfigError(
            f"{source}: optimizer.name = {scene.optimizer.name!r} with study.kind = 'heat': "
            "expected 'adam' or 'sgd' (heat training runs mini-batches of windows)")
    _check_size(scene)
    if _with_runs:
        scene.runs()  # validate every configuration now, not halfway through a study
        names = [n for n, _ in scene.study.runs]
        if "reference" in sections["study"] and scene.study.reference not in names:
            raise SceneError(f"{source}: study.reference = {scene.study.reference!r}: expected "
                             f"one of the run names {names}")
    return scene


def _check_learned_optimizer(scene: Scene) -> None:
    spec = scene.learned
    if scene.optimizer.name == "lbfgs" and spec.batch_size < spec.samples:
        raise SceneSolverConfigError(
            f"{scene.source}: optimizer.name = 'lbfgs' with learned.batch_size = "
            f"{spec.batch_size} < learned.samples = {spec.samples}: expected a full batch "
            "(batch_size = samples) for L-BFGS, whose curvature pairs need one objective")


def _variant(scene: Scene, overrides: dict, name: str) -> Scene:
    table = json.loads(scene.raw)
    table.pop("study", None)
    if scene.study.kind in ("learned", "heat"):
        table.setdefault(scene.study.kind, {})  # the variant stays of the study's kind
    for section, values in overrides.items():
        if section == "refinement":
            table["refinement"] = copy.deepcopy(values)
        else:
            merged = dict(table.get(section, {}))
            if section == "solver" and values.get("preconditioner", "amg") != "amg":
                # a run leaving the scene's AMG leaves its AMG settings too
                merged = {k: v for k, v in merged.items() if k not in _AMG_KEYS}
            merged.update(values)
            table[section] = merged
    table["name"] = name
    return parse_scene(table, source=f"{scene.source} (run {name!r})",
                       directory=scene.directory, _with_runs=False)


def builtin_scene_path(name: str) -> Path:
    """The TOML file of a built-in scene (see :data:`BUILTIN_SCENES`)."""
    if name not in BUILTIN_SCENES:
        raise SceneError(f"scene {name!r}: expected a .toml file or a built-in scene "
                         f"{list(BUILTIN_SCENES)}")
    return Path(str(resources.files("prdp_fem") / "data" / "scenes" / f"{name}.toml"))


def load_scene(path_or_name: str | Path) -> Scene:
    """Read a scene file, or a built-in scene by name (a directory of that name, such as a
    study's output, does not hide the built-in scene)."""
    text_path = str(path_or_name)
    given = Path(text_path)
    builtin = text_path in BUILTIN_SCENES and given.is_dir()
    path = given if not builtin and (text_path.endswith(".toml") or given.exists()
                                     or given.is_symlink()) else builtin_scene_path(text_path)
    checked_file(path, "scene .toml file or a built-in scene name", SceneError,
                 missing="scene file does not exist")
    try:
        table = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{path}: not valid TOML ({exc})") from None
    except UnicodeDecodeError:
        raise SceneError(f"{path}: not a text file (expected TOML)") from None
    except OSError as exc:  # a file it may not read
        raise SceneError(f"{path}: cannot be read ({exc.strerror}); expected a readable scene "
                         "file") from None
    return parse_scene(table, source=str(path), directory=str(path.resolve().parent),
                       default_name=path.stem)


def with_overrides(scene: Scene, overrides: dict) -> Scene:
    """The scene with ``{section: {key: value}}`` merged in (validated again; new fingerprint)."""
    table = json.loads(scene.raw)
    for section, values in overrides.items():
        table[section] = {**table.get(section, {}), **values}
    return parse_scene(table, source=scene.source, directory=scene.directory,
                       default_name=scene.name)


def mesh_scene(path: str | Path) -> Scene:
    """The default problem on a bare mesh file: ``-lap u = 1``, ``u = 0`` on the boundary."""
    path = Path(path)
    checked_file(path, "mesh file", MeshFileError)  # Path.resolve raises on a link loop
    return parse_scene({"name": path.stem, "mesh": {"file": str(path.resolve())}},
                       source=str(path), directory=str(path.resolve().parent))
