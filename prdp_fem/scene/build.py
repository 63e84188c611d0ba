"""Turn a :class:`~prdp_fem.scene.spec.Scene` into numerics, building only what the scene uses.

* :func:`build_mesh` / :func:`build_discretization`: the mesh and the condensed system maps.
* :func:`forward_solve`: one (truncated) PCG solve of the scene's PDE. Its right-hand side is
  the exact load of the source formula, so no mass matrix is assembled; no AMG hierarchy or
  reference solve is made unless ``reference=True``; nothing is differentiated.
* :func:`build_inverse`: the :class:`~prdp_fem.inverse.InverseProblem` (synthetic data come from
  one direct solve of the truth).
* :func:`build_learned`: a learned inverse (:mod:`~prdp_fem.learning.learned`): the problem, seeded
  training and validation sets, and an untrained network.
* :func:`build_heat`: a learned heat stepper (:mod:`~prdp_fem.learning.heat`): the implicit-Euler
  problem, seeded reference trajectories (train / validation / test) and an untrained network.
* :func:`controller`, :func:`optimizer`, :func:`invert_options`, :func:`train_options`,
  :func:`heat_train_options`: the refinement controller, the optax optimiser and the keyword
  arguments of :func:`~prdp_fem.inverse.driver.invert`, :func:`~prdp_fem.learning.learned.train` and
  :func:`~prdp_fem.learning.heat.train` (:func:`training_preconditioner`: a training's
  preconditioner, an AMG hierarchy built once from the fixed operator).
"""

from __future__ import annotations

import functools
import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
import skfem

from .._xla_options import solver_options
from ..errors import (
    CoefficientError,
    DiscretizationError,
    SceneError,
    SensorError,
    ShapeError,
)
from ..fem.discretization import Discretization, discretize
from ..fem.observations import boundary_values, full_field, point_sensors, with_noise
from ..fem.parameters import Parameterization, Simp
from ..fem.priors import GaussianPrior, bilaplacian_prior
from ..fem.reference import amg_solve, direct_solve
from ..inverse.driver import InverseProblem, Validation, inverse_problem
from ..inverse.refinement import (
    Refinement,
    adaptive_tolerance,
    converged,
    fixed,
    prdp,
    truncation_gap,
)
from ..learning import heat
from ..learning.learned import (
    LearnedInverse,
    Network,
    SourceSamples,
    learned_inverse,
    mlp_init,
    random_sources,
    source_samples,
)
from ..linalg.amg import AMGCycle, PyamgCycle, RebuiltAMG, amg_preconditioner, rebuild_policy
from ..linalg.cg import ConvergedCG, Solution, TruncatedCG, solve
from ..linalg.operator import SparseMatrix
from ..mesh import generators
from ..mesh.io import load_mesh, refine
from ..optim.hig import hig
from ..optim.linesearch import lbfgs
from ..optim.newton import newton_cg, regularization_preconditioner
from .expressions import compile_field
from .spec import (
    OptimizerSpec,
    Scene,
    SceneCoefficientError,
    SceneDataError,
    SceneDiscretizationError,
    SceneSensorError,
    check_refined_size,
    ema_window_of,
)

__all__ = [
    "ForwardResult",
    "build_discretization",
    "build_heat",
    "build_inverse",
    "build_learned",
    "build_mesh",
    "coefficient_at_quadrature",
    "controller",
    "field_function",
    "forward_solve",
    "heat_train_options",
    "invert_options",
    "operator_at_coefficient",
    "optimizer",
    "parameterization_of",
    "train_options",
    "training_preconditioner",
]

# free dofs up to which synthetic data use SuperLU (else pyamg), per dimension: LU fill grows
# far faster on tetrahedra (100k free dofs of the refined cube mesh: 75 s, pyamg: under 2 s)
DIRECT_SOLVE_LIMIT = {1: 1_000_000, 2: 200_000, 3: 20_000}
REFERENCE_RTOL = 1e-12  # the relative residual a forward solve's pyamg reference is asked for
REFERENCE_ACCEPTED = 1e-8  # above it the reference is reported as failed, not compared with


def build_mesh(scene: Scene, level: int | None = None) -> skfem.Mesh:
    """The scene's mesh; ``level`` overrides ``n`` (generators) or ``refine`` (files)."""
    spec = scene.mesh
    path = scene.mesh_path()
    if path is not None:
        mesh = load_mesh(path, repair=spec.repair)
        refinements = spec.refine if level is None else level
    else:
        n = spec.n if level is None else level
        make = getattr(generators, spec.generator)
        mesh = make(n, spec.cell) if spec.cell is not None else make(n)
        refinements = spec.refine
    if refinements:  # estimated on the mesh as read, before refining builds it
        check_refined_size(scene, mesh.nvertices, mesh.dim(), refinements)
    return refine(mesh, refinements) if refinements else mesh  # tags are refined too


def field_function(scene: Scene, key: str, value, dim: int):
    return compile_field(value, where=f"{scene.source}: {key}", dim=dim)


def _boundary_data(scene: Scene, key: str, value, dim: int):
    if isinstance(value, tuple):  # {boundary = field}
        return {name: field_function(scene, f"{key}.{name}", v, dim) for name, v in value}
    return field_function(scene, key, value, dim)


def build_discretization(scene: Scene, mesh: skfem.Mesh | None = None,
                         element: str | None = None) -> Discretization:
    mesh = build_mesh(scene) if mesh is None else mesh
    dim = mesh.dim()
    neumann = _boundary_data(scene, "pde.neumann", scene.pde.neumann, dim) \
        if scene.pde.neumann else None
    try:
        return discretize(mesh, element=element or scene.pde.element,
                          kappa_space=scene.pde.kappa_space,
                          dirichlet=_boundary_data(scene, "pde.dirichlet", scene.pde.dirichlet,
                                                   dim),
                          neumann=neumann,
                          pins=[(pin[:-1], pin[-1]) for pin in scene.pde.pins])
    except DiscretizationError as exc:  # boundary names, or an element the mesh has not
        raise SceneDiscretizationError(f"{scene.source}: [pde] {exc}") from None


def coefficient(scene: Scene, disc: Discretization) -> np.ndarray:
    kappa = disc.interpolate_kappa(field_function(scene, "pde.kappa", scene.pde.kappa,
                                                  disc.mesh.dim()))
    if not (kappa > 0).all():
        raise SceneCoefficientError(f"{scene.source}: pde.kappa = {scene.pde.kappa!r}: expected "
                                    f"values > 0 on the mesh, found min {kappa.min():.3g}")
    return kappa


def coefficient_at_quadrature(scene: Scene, disc: Discretization):
    """``pde.kappa`` as a function of ``x`` for an operator assembled at one coefficient: it is
    evaluated at the quadrature points (no interpolation error: P2/Q2 keep L2 rate 3 with a
    variable kappa). A tensor coefficient is interpolated into ``pde.kappa_space`` instead."""
    if disc.kappa_kind != "scalar":
        return coefficient(scene, disc)
    return field_function(scene, "pde.kappa", scene.pde.kappa, disc.mesh.dim())


def operator_at_coefficient(scene: Scene, disc: Discretization, f=None):
    """``(A, b)`` of the scene's PDE at its own coefficient, ``pde.kappa`` evaluated at the
    quadrature points (see :func:`coefficient_at_quadrature`); a coefficient that is not
    positive there is a scene error naming the key."""
    try:
        return disc.host_system_at(coefficient_at_quadrature(scene, disc), f, name="pde.kappa")
    except CoefficientError as exc:
        raise SceneCoefficientError(f"{scene.source}: {exc}") from None


class ForwardResult(NamedTuple):
    disc: Discretization
    kappa: np.ndarray
    u: np.ndarray              # all dofs (Dirichlet data included)
    solution: Solution         # the CG diagnostics (free dofs)
    solve_time: float          # compiled solve, seconds
    relative_error: float      # nodal l2 against pyamg (NaN unless reference=True, or failed)
    reference_failure: str = ""  # why the pyamg reference is no reference ("" if it is one)


def forward_solve(scene: Scene, *, reference: bool = False,
                  disc: Discretization | None = None) -> ForwardResult:
    """Solve the scene's PDE with PCG: ``solver.iterations[0]`` iterations, else to ``rtol``."""
    disc = build_discretization(scene) if disc is None else disc
    kappa = coefficient(scene, disc)
    load = disc.load_vector(field_function(scene, "pde.source", scene.pde.source,
                                           disc.mesh.dim()))
    A, b = operator_at_coefficient(scene, disc)  # one kappa: no map kappa -> A
    b = b + load
    spec = scene.solver
    preconditioner = solver_preconditioner(scene, A)
    solver = TruncatedCG(spec.iterations[0], preconditioner, gradient="implicit") \
        if spec.iterations else ConvergedCG(rtol=spec.rtol, preconditioner=preconditioner)
    run = jax.jit(lambda A, b: solve(A, b, solver),
                  compiler_options=solver_options(preconditioner))
    A_jax, b_jax = SparseMatrix.from_scipy(A), jnp.asarray(b)
    jax.block_until_ready(run(A_jax, b_jax))  # compile
    start = time.perf_counter()
    solution = jax.block_until_ready(run(A_jax, b_jax))
    elapsed = time.perf_counter() - start
    x = np.asarray(solution.x)
    error, failure = float("nan"), ""
    if reference:
        ref = amg_solve(A, b, rtol=REFERENCE_RTOL)
        failure = reference_failure(ref, b)
        if not failure:
            error = float(np.linalg.norm(x - ref.x) / max(np.linalg.norm(ref.x), 1e-300))
    return ForwardResult(disc, kappa, disc.expand(x), solution, elapsed, error, failure)


def reference_failure(ref, b: np.ndarray) -> str:
    """Why a pyamg solve of ``A x = b`` is no reference, or ``""``: a non-finite solution, or
    a relative residual above :data:`REFERENCE_ACCEPTED` (it was asked for
    :data:`REFERENCE_RTOL`; an error measured against it would measure pyamg's)."""
    scale = max(float(np.linalg.norm(b)), 1e-300)
    residual = ref.residual_norm / scale
    if np.isfinite(ref.x).all() and residual <= REFERENCE_ACCEPTED:
        return ""
    found = "a non-finite solution" if not np.isfinite(ref.x).all() else \
        f"relative residual {residual:.3g}"
    return (f"pyamg did not converge ({found} after {ref.iterations} iterations; asked "
            f"{REFERENCE_RTOL:g}, accepted up to {REFERENCE_ACCEPTED:g})")


def _true_state(disc: Discretization, kappa: np.ndarray, f: np.ndarray) -> np.ndarray:
    A, b = disc.host_system_at(kappa, f)  # a source scene builds no map kappa -> A
    direct = disc.n_free <= DIRECT_SOLVE_LIMIT.get(disc.mesh.dim(), 0)
    x = direct_solve(A, b).x if direct else amg_solve(A, b).x
    return disc.expand(x)


def _sensor_points(scene: Scene, disc: Discretization) -> np.ndarray:
    sensors = scene.inverse.sensors
    if not isinstance(sensors, int):
        return np.asarray(sensors, dtype=float)
    mesh = disc.mesh
    interior = np.setdiff1d(np.arange(mesh.p.shape[1]), mesh.boundary_nodes())
    if sensors > len(interior):
        raise SceneSensorError(f"{scene.source}: inverse.sensors = {sensors}: the mesh has only "
                               f"{len(interior)} interior vertices; expected at most that many")
    picked = np.random.default_rng(scene.inverse.seed).choice(interior, sensors, replace=False)
    return mesh.p[:, np.sort(picked)].T


class InverseSetup(NamedTuple):
    disc: Discretization
    problem: InverseProblem
    truth: np.ndarray | None   # the unknown field (nodal source or log kappa), if known
    prior: GaussianPrior | None = None  # regularization = "bilaplacian"


def build_inverse(scene: Scene, disc: Discretization | None = None) -> InverseSetup:
    """The inverse problem of the scene (data synthetic from ``truth`` unless ``data`` given)."""
    spec = scene.inverse
    if spec is None:
        raise SceneError(f"{scene.source}: no [inverse] section; expected one to invert")
    disc = build_discretization(scene) if disc is None else disc
    dim = disc.mesh.dim()
    source_unknown = spec.unknown == "source"
    parameterization = parameterization_of(scene)
    to_field = disc.interpolate if source_unknown else disc.interpolate_kappa
    truth = None if spec.truth is None else to_field(
        field_function(scene, "inverse.truth", spec.truth, dim))
    if source_unknown:
        known = coefficient(scene, disc)
    else:
        known = disc.interpolate(field_function(scene, "pde.source", scene.pde.source, dim))
    if spec.data is not None:
        observation = full_field(disc, norm=spec.norm, data=disc.project(
            field_function(scene, "inverse.data", spec.data, dim)))
    else:
        kappa, f = (known, truth) if source_unknown else (
            np.asarray(parameterization.kappa(truth)), known)
        u_true = _true_state(disc, kappa, f)
        observation = _observation(scene, disc, u_true)
        if spec.noise > 0:
            observation = with_noise(observation, spec.noise, spec.seed)
    prior = None if spec.prior is None else bilaplacian_prior(
        disc, spec.unknown, gamma=spec.prior[0], delta=spec.prior[1], mean=spec.prior[2])
    problem = inverse_problem(disc, observation, unknown=spec.unknown, alpha=spec.alpha,
                              regularization=spec.regularization if prior is None
                              else prior.regularizer(), known=known, truth=truth,
                              bounds=spec.bounds,
                              coefficient_map=parameterization.coefficient_map,
                              residual=scene.optimizer.name == "hig")
    return InverseSetup(disc, problem, truth, prior)


def parameterization_of(scene: Scene) -> Parameterization:
    """The scene's unknown, bounds and coefficient map (a density's SIMP law)."""
    spec = scene.inverse
    law = None if spec.simp is None else Simp(*spec.simp)
    return Parameterization(spec.unknown, spec.bounds, law)


def _observation(scene: Scene, disc: Discretization, u: np.ndarray):
    """``[inverse]``'s observation operator, with ``u`` as its data."""
    spec = scene.inverse
    if spec.observations == "full_field":
        return full_field(disc, norm=spec.norm, u_true=u)
    key = "sensors" if spec.observations == "sensors" else "boundaries"
    try:
        return point_sensors(disc, _sensor_points(scene, disc), u_true=u) \
            if key == "sensors" else boundary_values(disc, spec.boundaries, u_true=u)
    except (SensorError, ShapeError) as exc:
        if isinstance(exc, SceneError):
            raise
        raise SceneSensorError(f"{scene.source}: inverse.{key}: {exc}") from None


class LearnedSetup(NamedTuple):
    disc: Discretization
    problem: LearnedInverse
    train_set: SourceSamples
    validation_set: SourceSamples
    network: Network          # untrained (seeded), scales from the training data
    test_set: SourceSamples | None = None
    split: dict | None = None  # sample indices of each set, as checkpoints record them


def build_learned(scene: Scene) -> LearnedSetup:
    """The learned inverse of the scene: ``[learned]`` samples observed through ``[inverse]``'s
    observation operator (converged reference solves plus noise), an MLP
    ``[n_obs, *hidden, n_dofs]`` with LeCun-normal weights seeded by ``learned.seed``.

    Training and validation sources are one draw (seed ``learned.seed``), the test sources a
    draw of their own (seed ``learned.seed + 2``), so that adding test samples leaves the
    others as they were."""
    spec = scene.learned
    if spec is None or scene.inverse is None:
        raise SceneError(f"{scene.source}: expected study.kind = 'learned' with an [inverse] "
                         "section (the observations)")
    disc = build_discretization(scene)
    observation = _observation(scene, disc, np.zeros(disc.n_dofs))
    problem = learned_inverse(disc, observation, kappa=coefficient(scene, disc),
                              supervised=spec.supervised)
    n = spec.samples + spec.validation_samples
    sources = random_sources(disc, n, seed=spec.seed, width=spec.width)
    samples = source_samples(problem, sources, noise=spec.noise, seed=spec.seed + 1)
    test_set = source_samples(
        problem, random_sources(disc, spec.test_samples, seed=spec.seed + 2, width=spec.width),
        noise=spec.noise, seed=spec.seed + 3)
    train_set = samples.take(np.arange(spec.samples))
    validation_set = samples.take(np.arange(spec.samples, n))
    network = mlp_init(jax.random.PRNGKey(spec.seed),
                       [int(observation.operator.shape[0]), *spec.hidden, disc.n_dofs],
                       input_scale=float(np.std(np.asarray(train_set.observations))),
                       output_scale=float(np.std(sources[:spec.samples])))
    return LearnedSetup(disc, problem.with_residual(), train_set, validation_set, network,
                        test_set, data_split(spec.samples, spec.validation_samples,
                                             spec.test_samples))


def data_split(train: int, validation: int, test: int) -> dict[str, list[int]]:
    """The indices of each set in the order the scene draws its data (training, validation,
    test), as a checkpoint records them."""
    first, second = train, train + validation
    return {"train": list(range(first)), "validation": list(range(first, second)),
            "test": list(range(second, second + test))}


def train_options(scene: Scene, problem: LearnedInverse) -> dict[str, Any]:
    """Keyword arguments of :func:`~prdp_fem.learning.learned.train` for this scene and its
    ``problem`` (:attr:`LearnedSetup.problem`, whose operator an AMG hierarchy is built
    from)."""
    spec = scene.learned
    updates = spec.epochs * (spec.samples // spec.batch_size)
    return dict(optimizer=optimizer(scene, updates), refinement=controller(scene),
                learning_rate=learning_rate(scene, updates), epochs=scene.learned.epochs,
                batch_size=scene.learned.batch_size,
                gradient=scene.solver.gradient,
                preconditioner=training_preconditioner(scene, problem),
                seed=scene.learned.seed, validation_rtol=scene.refinement.validation_rtol)


def training_preconditioner(scene: Scene, problem: LearnedInverse | heat.HeatProblem
                            ) -> str | AMGCycle | PyamgCycle:
    """The preconditioner of a training's solves: the scene's name, or for ``"amg"`` the
    hierarchy of the problem's fixed operator (``K`` at the frozen coefficient of a learned
    inverse, ``M + dt A`` of a heat step), built once: every training and validation solve
    shares it."""
    if scene.solver.preconditioner != "amg":
        return scene.solver.preconditioner
    matrix = problem.matrix if isinstance(problem, heat.HeatProblem) else \
        problem.system.operator(problem.kappa)
    return solver_preconditioner(scene, matrix)


def initial_field(scene: Scene, disc: Discretization) -> np.ndarray | None:
    if scene.inverse.init is None:
        return None
    fn = field_function(scene, "inverse.init", scene.inverse.init, disc.mesh.dim())
    unknown, bounds = scene.inverse.unknown, scene.inverse.bounds
    field = disc.interpolate(fn) if unknown == "source" else disc.interpolate_kappa(fn)
    if bounds is not None and ((field < bounds[0]) | (field > bounds[1])).any():
        error = SceneDataError if unknown == "source" else SceneCoefficientError
        raise error(f"{scene.source}: inverse.init = {scene.inverse.init!r}: values from "
                    f"{field.min():.3g} to {field.max():.3g} on the mesh; expected values within "
                    f"inverse.bounds = {list(bounds)}")
    return field


class HeatSetup(NamedTuple):
    disc: Discretization
    problem: heat.HeatProblem
    train_set: heat.Trajectories
    validation_set: heat.Trajectories
    test_set: heat.Trajectories
    network: Network          # untrained (seeded), its output scale from the training data
    split: dict | None = None  # trajectory indices of each set, as checkpoints record them


def build_heat(scene: Scene) -> HeatSetup:
    """The heat stepper of the scene: implicit Euler of ``heat.dt`` (the mixed setup:
    ``heat.dt / heat.substeps``, the reference's step its chain solves) with ``[pde]``'s
    ``kappa``, ``source`` and Dirichlet data; reference trajectories from seeded initial fields
    (train, validation and test, in that order, from one draw); an untrained network
    (:func:`~prdp_fem.learning.heat.initial_network`)."""
    spec = scene.heat
    if spec is None:
        raise SceneError(f"{scene.source}: expected study.kind = 'heat' with a [heat] section")
    disc = build_discretization(scene)
    kappa = coefficient(scene, disc)
    source = disc.interpolate(field_function(scene, "pde.source", scene.pde.source,
                                             disc.mesh.dim()))
    # the mixed setup trains through the reference's own fine step (its chain runs
    # substeps of it per step): the data's scheme, so a converged chain has no bias
    problem = heat.heat_problem(disc, spec.dt / spec.chain_substeps, kappa=kappa,
                                source=source, reaction=spec.reaction)
    counts = (spec.trajectories, spec.validation_trajectories, spec.test_trajectories)
    initial = heat.random_initial_states(disc, sum(counts), seed=spec.seed, width=spec.width)
    data = heat.reference_trajectories(disc, initial, dt=spec.dt, steps=spec.steps,
                                       substeps=spec.substeps, kappa=kappa, source=source,
                                       reaction=spec.reaction)
    first, second = np.cumsum(counts[:2])
    train_set = data.take(np.arange(first))
    network = heat.initial_network(problem, train_set, spec.setup, spec.hidden, spec.seed)
    return HeatSetup(disc, problem, train_set, data.take(np.arange(first, second)),
                     data.take(np.arange(second, sum(counts))), network, data_split(*counts))


def heat_train_options(scene: Scene, problem: heat.HeatProblem) -> dict[str, Any]:
    """Keyword arguments of :func:`~prdp_fem.learning.heat.train` for this scene and its
    ``problem`` (:attr:`HeatSetup.problem`, whose ``M + dt A`` an AMG hierarchy is built
    from)."""
    spec = scene.heat
    updates = spec.epochs * (spec.windows // spec.batch_size)
    return dict(setup=spec.setup, mode=spec.mode, unroll=spec.unroll,
                optimizer=optimizer(scene, updates), refinement=controller(scene),
                learning_rate=learning_rate(scene, updates),
                epochs=spec.epochs, batch_size=spec.batch_size, gradient=scene.solver.gradient,
                preconditioner=training_preconditioner(scene, problem), seed=spec.seed,
                validation_rtol=scene.refinement.validation_rtol,
                substeps=spec.chain_substeps)


def controller(scene: Scene) -> Refinement:
    spec = scene.refinement
    if spec.kind == "fixed":
        return fixed(spec.K, spec.K_adj)
    if spec.kind == "converged":
        return converged(spec.rtol)
    if spec.kind == "gap":
        return truncation_gap(spec.rtol, max_gap=spec.max_gap, rtol_factor=spec.rtol_factor,
                              rtol_min=spec.rtol_min, redo=spec.redo,
                              reference_factor=spec.reference_factor)
    if spec.kind == "adaptive":
        return adaptive_tolerance(spec.rtol0, power=spec.power, rtol_min=spec.rtol_min,
                                  failure_factor=spec.failure_factor)
    adjoint = None if spec.adjoint_K0 is None else (
        spec.adjoint_K0, spec.adjoint_dK, spec.adjoint_K_max, spec.adjoint_factor)
    return prdp(spec.K0, spec.dK, spec.K_max, factor=spec.factor, adjoint=adjoint,
                tau_step=spec.tau_step, tau_stop=spec.tau_stop, ema_window=ema_window_of(scene),
                delta=spec.delta, latch=spec.latch, restart=spec.restart,
                stall_on_failure=spec.stall_on_failure, rtol=spec.rtol,
                rtol_factor=spec.rtol_factor, rtol_min=spec.rtol_min,
                per_learning_rate=spec.per_learning_rate)


def optimizer(scene: Scene, updates: int | None = None) -> optax.GradientTransformation:
    """The scene's optax optimiser; ``updates``: how many updates the run makes (what a
    ``decay = "cosine"`` learning rate decays over; default ``optimizer.steps``).

    One object per setting (pure and immutable, as optax's transformations are): a study's
    runs with equal optimiser settings share one compiled step (see
    ``prdp_fem._executables.kept_programs``)."""
    spec = scene.optimizer
    return _optimizer(spec, spec.steps if updates is None else int(updates))


def _preconditioned_newton(spec: OptimizerSpec, problem: InverseProblem):
    """Newton-CG / Gauss-Newton with its inner CG preconditioned by ``preconditioner_cycles``
    V-cycles of ``problem``'s regularisation operator (built for this problem: not shared)."""
    return newton_cg(hessian="exact" if spec.name == "newton_cg" else "gauss_newton",
                     max_cg=spec.max_cg, forcing=spec.forcing, c1=spec.c1,
                     max_backtracking=spec.max_backtracking, rtol=spec.gradient_rtol,
                     gauss_newton_steps=spec.gauss_newton_steps,
                     preconditioner=regularization_preconditioner(
                         problem, spec.preconditioner_cycles))


@functools.lru_cache(maxsize=16)
def _optimizer(spec: OptimizerSpec, updates: int) -> optax.GradientTransformation:
    if spec.name == "lbfgs":
        return lbfgs(memory_size=spec.memory_size, first_step=spec.first_step)
    if spec.name in ("newton_cg", "gauss_newton"):
        return newton_cg(hessian="exact" if spec.name == "newton_cg" else "gauss_newton",
                         max_cg=spec.max_cg, forcing=spec.forcing, c1=spec.c1,
                         max_backtracking=spec.max_backtracking, rtol=spec.gradient_rtol,
                         gauss_newton_steps=spec.gauss_newton_steps)
    if spec.name == "hig":
        return hig(spec.learning_rate, spec.exponent, spec.tau, spec.rank,
                   relative=spec.relative)
    return getattr(optax, spec.name)(_learning_rate(spec, updates))


@functools.lru_cache(maxsize=16)
def _learning_rate(spec: OptimizerSpec, updates: int):
    """A first-order optimiser's learning rate: a number, or its ``decay`` schedule."""
    if spec.decay == "cosine":
        return optax.cosine_decay_schedule(spec.learning_rate, max(updates, 1))
    return spec.learning_rate


def learning_rate(scene: Scene, updates: int) -> Any:
    """The learning rate of the scene's optimiser over ``updates`` updates (a number or an
    optax schedule), ``None`` for one that has none (L-BFGS, Newton-CG, Gauss-Newton)."""
    spec = scene.optimizer
    if spec.name in ("lbfgs", "newton_cg", "gauss_newton"):
        return None
    if spec.name == "hig":  # a constant step (no decay)
        return spec.learning_rate
    return _learning_rate(spec, int(updates))


def solver_preconditioner(scene: Scene, matrix) -> str | AMGCycle | PyamgCycle:
    """The preconditioner of a solve with ``matrix`` (SciPy, or a
    :class:`~prdp_fem.linalg.operator.SparseMatrix`): the scene's name, or for ``"amg"`` the
    hierarchy built from ``matrix`` now."""
    spec = scene.solver
    if spec.preconditioner != "amg":
        return spec.preconditioner
    return amg_preconditioner(matrix, kind=spec.amg_kind,
                              implementation=spec.amg_implementation)


def inversion_preconditioner(scene: Scene) -> str | RebuiltAMG:
    """An inversion's preconditioner: the scene's name, or for ``"amg"`` a
    :class:`~prdp_fem.linalg.amg.RebuiltAMG` (built at the initial coefficient, rebuilt as
    ``rebuild_every`` / ``rebuild_factor`` say; kept when neither is set)."""
    spec = scene.solver
    if spec.preconditioner != "amg":
        return spec.preconditioner
    every, factor = spec.rebuild_every or None, spec.rebuild_factor or None  # 0: never
    policy = rebuild_policy(every=every, factor=factor) \
        if every is not None or factor is not None else None
    return RebuiltAMG(policy, kind=spec.amg_kind, implementation=spec.amg_implementation)


def invert_options(scene: Scene, disc: Discretization,
                   problem: InverseProblem | None = None) -> dict[str, Any]:
    """Keyword arguments of :func:`~prdp_fem.inverse.driver.invert` for this scene.
    ``problem``: the inversion's, which a Newton optimiser preconditioned by the
    regularisation operator (``optimizer.preconditioner_cycles``) is built for."""
    spec = scene.refinement
    monitor: str | Validation | None = None if spec.kind == "adaptive" else spec.monitor
    if monitor == "validation":
        monitor = Validation(spec.validation_every, spec.validation_rtol)
    cycles = scene.optimizer.preconditioner_cycles
    if cycles and problem is None:
        raise SceneError(f"{scene.source}: optimizer.preconditioner_cycles = {cycles} needs "
                         "the inverse problem (invert_options(scene, disc, problem))")
    built = _preconditioned_newton(scene.optimizer, problem) if cycles else optimizer(scene)
    return dict(optimizer=built, refinement=controller(scene),
                gradient=scene.solver.gradient, steps=scene.optimizer.steps,
                init=initial_field(scene, disc), preconditioner=inversion_preconditioner(scene),
                monitor=monitor, warm_start=scene.solver.warm_start,
                warm_start_every=scene.solver.warm_start_every)
