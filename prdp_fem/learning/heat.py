r"""Time-dependent scenes: the heat equation, implicit Euler, and networks trained through it.

Implicit Euler for :math:`\partial_t u - \nabla\cdot(\kappa \nabla u) = f` on the free dofs
(Dirichlet data ``g`` constant in time, moved to the right-hand side as in
:class:`~prdp_fem.fem.system.LinearSystem`):

.. math::

    (M + \Delta t\, A(\kappa))\, u_{n+1} = M u_n + \Delta t\, b(\kappa, f),
    \qquad b = S f + h - A_{ID}(\kappa)\, g ,

each step one PCG solve *warm-started from* :math:`u_n` (:func:`heat_step`): its initial
residual is :math:`\Delta t\,(b - A u_n)`, small for a small step, so a truncated solve of
``K`` iterations is already close. A :class:`HeatProblem` holds the system matrix, the mass
matrix and the load on the free dofs (a pytree: a jit argument).

A nonlinear variant: with ``reaction = r > 0`` the equation is Fisher-KPP's
:math:`\partial_t u - \nabla\cdot(\kappa \nabla u) = f + r\, u (1 - u)`, the reaction taken
explicitly (IMEX: :math:`(M + \Delta t A) u_{n+1} = M (u_n + \Delta t\, r\, u_n (1 - u_n)) +
\Delta t\, b`), so each step is still one SPD solve, truncated by PCG in the coarse solver. Fronts
grow and travel; an error in one step changes the growth of the next, so the gradient through
several steps (WIG) carries what one-step training (ONE) cannot see. The correction network
is then applied as it is (:func:`correction` with ``homogeneous=False``).

Learned time steppers (List, Chen, Bali, Thuerey, arXiv 2402.12971). The reference is a *fine*
solver (:func:`reference_trajectories`: ``substeps`` direct solves of step ``dt / substeps`` per
step ``dt``); the *coarse* solver :math:`S_K` is one step of size ``dt`` with ``K`` PCG
iterations. Three setups of a stepper :math:`G`:

* ``"correction"``: :math:`G(u) = S_K(u) + N_\theta(S_K(u))` (solver plus network);
* ``"prediction"``: :math:`G(u) = u + N_\theta(u)` (network alone; no solver);
* ``"mixed"``: the prediction stepper (an emulator, deployed alone) trained *through the
  solver* in a mixed chain, as the PRDP paper's heat emulators are: over a window the network
  takes the first step, :math:`s_1 = u^*_t + N_\theta(u^*_t)`, and the *fine* solver the
  others, :math:`s_{k+1} = F_K(s_k)`, with :math:`F_K` the reference's ``substeps`` implicit
  steps of ``dt / substeps``, each a PCG solve of ``K`` iterations (or to ``rtol``) warm-started
  from its input. The gradient flows through the solver (mode ``"wig"`` only), so the later
  terms of the loss teach the network where the physics takes its step. Validation and test
  rollouts are the emulator's alone: they run no solver, and PRDP's signal costs no CG
  iteration.

:math:`N_\theta` is the MLP of :mod:`prdp_fem.learning.learned`, applied *homogeneously*:
:math:`N_\theta(u) = \rho(u)\, \mathrm{MLP}(u / \rho(u))` with :math:`\rho` the RMS of ``u``
(the exact step is linear in ``u`` when ``f = 0`` and ``g = 0``; states decay by orders of
magnitude along a trajectory). Three ways to train over windows
:math:`u^*_t, \dots, u^*_{t+m}` of the reference trajectories (``m = unroll``), each with the
loss :math:`\frac1m \sum_{k=1}^{m} \|s_k - u^*_{t+k}\|_M^2 / \|u^*_{t+k}\|_M^2`:

* ``"one"``: :math:`s_{k+1} = G(u^*_{t+k})`, inputs always ground truth;
* ``"nog"``: :math:`s_{k+1} = G(\mathrm{sg}(s_k))`, :math:`s_0 = u^*_t`; the solver's input is
  stopped and so is its output: the solver is *never* differentiated (a black box);
* ``"wig"``: :math:`s_{k+1} = G(s_k)`, gradients through network and solver over all steps
  (the solve's ``gradient`` mode, implicit or unrolled).

Budgets are fair by construction: every mode sees the same windows in the same mini-batches for
the same epochs, and each window costs ``m`` network evaluations and ``m`` coarse solves (ONE's
``m`` one-step samples per window are the "m times the batch" of the reference study).

PRDP on the inner solves: a refinement controller (:mod:`prdp_fem.inverse.refinement`) picks ``K``
(or, in
tolerance mode, a relative residual tolerance) once per epoch from the *validation rollout
error*: full held-out trajectories rolled out from
:math:`u^*_0` with *converged* coarse solves, so the monitored value does not move when ``K``
does (:func:`rollout_error`: the mean over trajectories and steps of
:math:`\|u_n - u^*_n\|_M / \|u^*_n\|_M`). The CG iterations of the training solves are returned
by the jitted step (an exact tally, no host callback), those of the validation rollouts by the
rollout (``validation_iterations``: a saving counts every solve that ran); run times exclude
compilation.

>>> import prdp_fem as pf
>>> disc = pf.discretize(pf.unit_square(4), dirichlet=0.0)
>>> problem = heat_problem(disc, dt=0.01)
>>> u = np.ones(problem.n_free)
>>> u_next, iterations = heat_step(problem, u, pf.ConvergedCG(rtol=1e-12))
>>> bool(np.all(np.asarray(u_next) < u)), int(iterations) > 0   # heat flows out: it decays
(True, True)
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
import scipy.sparse.linalg as spla

from .._checks import finite_vector
from .._executables import SharedCompile, kept_programs
from ..errors import ShapeError, SolverConfigError
from ..fem.discretization import Discretization
from ..inverse.refinement import Refinement, prdp
from ..inverse.steps import (
    check_training_refinement,
    cycle_argument,
    device_settings,
    keeps_program,
    preconditioner_key,
    step_scan_length,
    step_solver,
)
from ..linalg import cg
from ..linalg.cg import ConvergedCG, IterationCounter, ReverseTally, read_counts, zero_counts
from ..linalg.operator import FixedMatrix, SparseMatrix
from ._defaults import default_optimizer
from ._gap import compile_passes, first_level
from ._gap import gap as validation_gap
from ._step_size import epoch_update
from .checkpoint import Checkpoints, CheckpointSession, TrainingState, start_state
from .learned import Network, Training, mlp_init
from .model import Model, check_model

__all__ = [
    "MODES",
    "SETUPS",
    "HeatProblem",
    "HeatRecord",
    "Trajectories",
    "batch_loss",
    "correction",
    "heat_problem",
    "heat_step",
    "initial_network",
    "random_initial_states",
    "reference_trajectories",
    "rollout",
    "rollout_error",
    "stepper",
    "train",
    "windows",
]

SETUPS = ("correction", "prediction", "mixed")
# the iteration cap of converged validation and reference solves (never reached in practice)
_CONVERGED_CAP = 100_000
MODES = ("one", "nog", "wig")

# a heat step: (problem, u, solver) -> (u_next, iterations); tests pass stand-ins
Step = Callable[[Any, jax.Array, Any], tuple[jax.Array, jax.Array]]


# --------------------------------------------------------------------------------------
# the problem and one step
# --------------------------------------------------------------------------------------


@partial(jax.tree_util.register_dataclass, data_fields=["matrix", "mass", "load", "dt"],
         meta_fields=["reaction"])
@dataclasses.dataclass(frozen=True)
class HeatProblem:
    """Implicit Euler on the free dofs: ``matrix = M + dt A``, ``mass = M``,
    ``load = dt b`` (source, Neumann data and Dirichlet lifting); a pytree.

    ``reaction`` (static; 0: the heat equation) is the rate ``r`` of a Fisher-KPP reaction
    ``r u (1 - u)``, taken explicitly (IMEX): the step stays one SPD solve with ``M + dt A``.
    """

    matrix: SparseMatrix
    mass: FixedMatrix  # symmetric, laid out once
    load: jax.Array
    dt: jax.Array
    reaction: float = 0.0

    @property
    def n_free(self) -> int:
        return int(self.matrix.shape[0])

    def rhs(self, u: jax.Array) -> jax.Array:
        """``M (u + dt r u (1 - u)) + dt b``: the right-hand side of the step from ``u``."""
        return self.mass(_reacted(u, self.dt, self.reaction)) + self.load


def _reacted(u, dt, rate: float):
    """``u + dt r u (1 - u)``: the explicit reaction of a step (``u`` itself when ``r = 0``);
    NumPy or JAX arrays."""
    return u + dt * rate * u * (1.0 - u) if rate else u


def _positive(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer) \
            or not (math.isfinite(value) and value > 0):
        raise SolverConfigError(f"{name}={value!r}: expected a finite number > 0")
    return float(value)


def _count(value: Any, name: str, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        raise SolverConfigError(f"{name}={value!r}: expected an integer >= {minimum}")
    return int(value)


def heat_problem(disc: Discretization, dt: float, *, kappa=1.0, source=None,
                 reaction: float = 0.0) -> HeatProblem:
    """The implicit-Euler :class:`HeatProblem` of step ``dt`` on ``disc`` (its Dirichlet and
    Neumann data, held constant in time), coefficient ``kappa``, nodal ``source`` (``None``:
    zero) and Fisher-KPP rate ``reaction`` (0: the heat equation)."""
    dt = _positive(dt, "dt")
    reaction = _rate(reaction)
    if source is not None:
        source = finite_vector(source, "source", disc.n_dofs)
    free = disc.free_dofs
    mass = disc.mass_matrix[free][:, free].tocsr()
    stiffness, b = disc.host_system_at(kappa, source)  # one kappa: no map kappa -> A
    matrix = (mass + dt * stiffness).tocsr()
    return HeatProblem(SparseMatrix.from_scipy(matrix), FixedMatrix.symmetric(mass),
                       jnp.asarray(dt * b), jnp.asarray(dt), reaction)


def _rate(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer) \
            or not (math.isfinite(value) and value >= 0):
        raise SolverConfigError(f"reaction={value!r}: expected a finite number >= 0")
    return float(value)


def heat_step(problem: HeatProblem, u: jax.Array, solver, *,
              counter: IterationCounter | ReverseTally | None = None
              ) -> tuple[jax.Array, jax.Array]:
    """One implicit-Euler step from ``u`` (free dofs) by ``solver`` (a
    :class:`~prdp_fem.linalg.TruncatedCG` or :class:`~prdp_fem.linalg.ConvergedCG`), warm-started
    from
    ``u``: ``(u_next, iterations)``. ``counter`` also tallies the step's adjoint solves."""
    sol = cg.solve(problem.matrix, problem.rhs(u), solver, x0=u, counter=counter)
    return sol.x, sol.iterations


# --------------------------------------------------------------------------------------
# reference trajectories
# --------------------------------------------------------------------------------------


class Trajectories(NamedTuple):
    """States on the free dofs, ``(n_trajectories, steps + 1, n_free)``; ``[:, 0]`` initial."""

    states: jax.Array

    def take(self, index) -> Trajectories:
        return Trajectories(self.states[index])

    @property
    def steps(self) -> int:
        return int(self.states.shape[1]) - 1


def random_initial_states(disc: Discretization, n_states: int, *, seed: int = 0,
                          bumps: int = 3, width: float = 0.15) -> np.ndarray:
    """``n_states`` smooth nodal fields ``(n_states, n_dofs)``: sums of ``bumps`` Gaussians
    (widths ``width`` times the mesh's diameter) at uniform random centres, with *positive*
    amplitudes uniform in ``[0.5, 1]``. Positive, so that the slowest-decaying mode is always
    present: bumps of both signs can cancel it, and such a trajectory decays to round-off
    relative to its start within a few steps. Seeded."""
    n_states, bumps = _count(n_states, "n_states"), _count(bumps, "bumps")
    width = _positive(width, "width")
    x = disc.basis.doflocs  # (dim, n_dofs)
    low, high = x.min(axis=1), x.max(axis=1)
    sigma = width * float(np.linalg.norm(high - low))
    rng = np.random.default_rng(seed)
    centres = rng.uniform(low, high, size=(n_states, bumps, x.shape[0]))
    weights = rng.uniform(0.5, 1.0, size=(n_states, bumps))
    distance2 = ((x.T[None, None] - centres[:, :, None]) ** 2).sum(axis=-1)
    return np.einsum("sb,sbn->sn", weights, np.exp(-distance2 / (2 * sigma**2)))


def reference_trajectories(disc: Discretization, initial, *, dt: float, steps: int,
                           substeps: int = 4, kappa=1.0, source=None,
                           reaction: float = 0.0) -> Trajectories:
    """Fine-solver trajectories: from each nodal initial field (rows of ``initial``, restricted
    to the free dofs), ``steps`` steps of size ``dt``, each made of ``substeps`` implicit-Euler
    steps of size ``dt / substeps`` (the reaction, if any, explicit: the scheme of
    :func:`heat_step`) solved directly (sparse LU: converged to round-off)."""
    steps, substeps = _count(steps, "steps"), _count(substeps, "substeps")
    dt = _positive(dt, "dt")
    initial = np.asarray(initial, dtype=float)
    if initial.ndim != 2 or initial.shape[1] != disc.n_dofs:
        raise ShapeError(f"initial{initial.shape}: expected (n_trajectories, {disc.n_dofs}) "
                         "nodal fields")
    fine = heat_problem(disc, dt / substeps, kappa=kappa, source=source, reaction=reaction)
    lu = spla.splu(fine.matrix.to_scipy().tocsc())
    mass, load = fine.mass.to_scipy(), np.asarray(fine.load)
    fine_dt, rate = float(fine.dt), fine.reaction
    u = finite_vector(initial.ravel(), "initial", initial.size).reshape(initial.shape)
    u = u[:, disc.free_dofs].T  # (n_free, n_trajectories): one LU solve per substep for all
    states = [u]
    for _ in range(steps):
        with np.errstate(over="ignore", invalid="ignore"):  # checked below, with the cause
            for _ in range(substeps):
                u = lu.solve(mass @ _reacted(u, fine_dt, rate) + load[:, None])
        if not np.all(np.isfinite(u)):
            raise SolverConfigError(f"reference_trajectories: non-finite states (dt={dt!r}, "
                                    f"reaction={rate!r}); expected dt * reaction / substeps "
                                    "small enough for the explicit reaction to be stable")
        states.append(u)
    return Trajectories(jnp.asarray(np.stack(states).transpose(2, 0, 1)))


def windows(trajectories: Trajectories, unroll: int, stride: int = 1) -> jax.Array:
    """The windows of ``unroll + 1`` consecutive states starting every ``stride`` steps (by
    default every window): ``(n_windows, unroll + 1, n_free)``, trajectory-major."""
    unroll, stride = _count(unroll, "unroll"), _count(stride, "stride")
    if unroll > trajectories.steps:
        raise SolverConfigError(f"unroll={unroll}: expected at most the {trajectories.steps} "
                                "steps of each trajectory")
    states = trajectories.states
    starts = range(0, trajectories.steps - unroll + 1, stride)
    return jnp.stack([states[:, t:t + unroll + 1] for t in starts], axis=1).reshape(
        -1, unroll + 1, states.shape[-1])


# --------------------------------------------------------------------------------------
# steppers and losses
# --------------------------------------------------------------------------------------


def _check_choice(value: Any, name: str, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise SolverConfigError(f"{name}={value!r}: expected one of {allowed}")


def correction(network: Model | Network | None, u: jax.Array, *,
               homogeneous: bool = True) -> jax.Array:
    """``N(u) = rho(u) model(u / rho(u))``, ``rho`` the RMS of ``u`` (zero at ``u = 0``, with
    finite gradients); ``homogeneous=False``: ``model(u)`` (a nonlinear step is not
    homogeneous in ``u``); ``network=None``: zero. ``network`` is any model
    (:mod:`prdp_fem.learning.model`) from the free dofs to the free dofs."""
    if network is None:
        return jnp.zeros_like(u)
    if not homogeneous:
        return network(u)
    power = jnp.mean(u**2)
    positive = power > 0
    rho = jnp.sqrt(jnp.where(positive, power, 1.0))  # safe before the square root
    return jnp.where(positive, rho, 0.0) * network(u / rho)


def stepper(setup: str, network: Model | Network | None, problem: HeatProblem, u: jax.Array, solver,
            *, stop_solver: bool = False, step: Step = heat_step):
    """``G(u)`` of ``setup`` and the CG iterations it ran. ``stop_solver`` stops the gradient
    at the solver's input and output (NOG: the solver is never differentiated)."""
    _check_choice(setup, "setup", SETUPS)
    homogeneous = not problem.reaction  # the heat step is linear in u (f = 0, g = 0)
    if setup in ("prediction", "mixed"):  # mixed: trained through the solver, deployed alone
        return u + correction(network, u, homogeneous=homogeneous), jnp.zeros((), jnp.int32)
    if stop_solver:
        u = jax.lax.stop_gradient(u)
    coarse, iterations = step(problem, u, solver)
    if stop_solver:
        coarse = jax.lax.stop_gradient(coarse)
    return coarse + correction(network, coarse, homogeneous=homogeneous), iterations


def _relative_norm2(problem: HeatProblem, e: jax.Array, reference: jax.Array) -> jax.Array:
    """``||e||_M^2 / ||reference||_M^2``."""
    return jnp.vdot(e, problem.mass(e)) / jnp.maximum(
        jnp.vdot(reference, problem.mass(reference)), 1e-300)


def _relative_error2(problem: HeatProblem, u: jax.Array, truth: jax.Array) -> jax.Array:
    return _relative_norm2(problem, u - truth, truth)


def window_loss(network: Model | Network, problem: HeatProblem, window: jax.Array, solver, *,
                setup: str, mode: str, step: Step = heat_step, substeps: int = 1):
    """The loss of one window ``(m + 1, n_free)`` (see the module docstring) and its CG
    iterations. ``substeps``: steps of ``problem`` per solver step of the mixed chain."""
    _check_choice(mode, "mode", MODES)
    if setup == "mixed":
        _check_mixed(mode, window.shape[0] - 1)
        return _chain_loss(network, problem, window, solver, substeps, step)
    m = window.shape[0] - 1
    s, total, iterations = window[0], 0.0, jnp.zeros((), jnp.int32)
    for k in range(m):
        start = window[k] if mode == "one" else s
        s, its = stepper(setup, network, problem, start, solver, stop_solver=mode != "wig",
                         step=step)
        total = total + _relative_error2(problem, s, window[k + 1])
        iterations = iterations + its
        if mode == "nog":  # s_{k+1} = G(sg(s_k)): no gradient from one step to the next
            s = jax.lax.stop_gradient(s)
    return total / m, iterations


def _check_mixed(mode: str, unroll: int) -> None:
    if mode != "wig":
        raise SolverConfigError(f"mode={mode!r} with setup='mixed': expected 'wig' (the mixed "
                                "chain trains the network through the solver's steps)")
    if unroll < 2:
        raise SolverConfigError(f"unroll={unroll} with setup='mixed': expected at least 2 (a "
                                "network step and a solver step)")


def chain_states(network: Model | Network, problem: HeatProblem, window: jax.Array, solver, *,
                 substeps: int = 1, step: Step = heat_step):
    """The mixed chain over ``window`` (``(m + 1, n_free)``): the network's step from
    ``window[0]``, then solver steps of ``substeps`` solves each, differentiable; its states
    ``s_1 .. s_m`` (``(m, n_free)``) and the CG iterations."""
    m = window.shape[0] - 1
    s, _ = stepper("prediction", network, problem, window[0], solver, step=step)
    states, iterations = [s], jnp.zeros((), jnp.int32)
    for _ in range(1, m):
        for _ in range(substeps):
            s, its = step(problem, s, solver)
            iterations = iterations + its
        states.append(s)
    return jnp.stack(states), iterations


def _chain_loss(network, problem: HeatProblem, window: jax.Array, solver, substeps: int,
                step: Step):
    """The loss of the module docstring over the mixed chain and its CG iterations."""
    states, iterations = chain_states(network, problem, window, solver, substeps=substeps,
                                      step=step)
    total = _relative_error2(problem, states[0], window[1])
    for k in range(1, states.shape[0]):
        total = total + _relative_error2(problem, states[k], window[k + 1])
    return total / states.shape[0], iterations


def chain_gap(problem: HeatProblem, batch: jax.Array, converged: jax.Array,
              truncated: jax.Array) -> jax.Array:
    r"""The truncation gap of mixed chains over ``batch`` (``(B, m + 1, n_free)`` windows) from
    their states with converged solves and with truncated ones (``(B, m, n_free)`` each):

    .. math::

        \gamma = \Big(\sum_{w,k} \|s^t_{w,k} - s^c_{w,k}\|_M^2 / \|u^*_{w,k}\|_M^2
        \Big/ \sum_{w,k} \|s^c_{w,k} - u^*_{w,k}\|_M^2 / \|u^*_{w,k}\|_M^2\Big)^{1/2},

    the truncation's change of the residuals the loss is made of, relative to those residuals.
    By the triangle inequality it bounds ``|e_t / e_c - 1|`` for the chain's error
    ``e = sqrt(loss)`` -- the validation gap's meaning -- without the cancellation a
    difference of two losses has: a truncated step that under-damps can move a state closer
    to the data as easily as away from it."""
    truth = batch[:, 1:]
    pairs = jax.vmap(jax.vmap(lambda e, t: _relative_norm2(problem, e, t)))
    change = jnp.sum(pairs(truncated - converged, truth))
    residual = jnp.sum(pairs(converged - truth, truth))
    return jnp.sqrt(change / jnp.maximum(residual, 1e-300))


def batch_loss(network: Model | Network, problem: HeatProblem, batch: jax.Array, solver, *,
               setup: str, mode: str, step: Step = heat_step, substeps: int = 1):
    """Mean :func:`window_loss` over ``batch`` (``(B, m + 1, n_free)``, solves under ``vmap``)
    and the total CG iterations of its forward solves."""
    losses, iterations = jax.vmap(
        lambda w: window_loss(network, problem, w, solver, setup=setup, mode=mode,
                              step=step, substeps=substeps))(batch)
    return jnp.mean(losses), jnp.sum(iterations)


def rollout(network: Model | Network | None, problem: HeatProblem, u0: jax.Array, steps: int,
            solver, *, setup: str = "correction", step: Step = heat_step):
    """``steps`` steps of ``G`` from ``u0``: the states ``(steps + 1, n_free)`` and the CG
    iterations. ``network=None`` with ``setup="correction"`` is the coarse solver alone; the
    mixed setup rolls out its emulator alone (as the prediction setup)."""
    def body(u, _):
        u_next, iterations = stepper(setup, network, problem, u, solver, step=step)
        return u_next, (u_next, iterations)

    _, (states, iterations) = jax.lax.scan(body, u0, None, length=steps)
    return jnp.concatenate([u0[None], states]), jnp.sum(iterations)


def rollout_error(network: Model | Network | None, problem: HeatProblem, trajectories: Trajectories,
                  solver, *, setup: str = "correction", step: Step = heat_step):
    """Mean over trajectories and steps ``n >= 1`` of ``||u_n - u*_n||_M / ||u*_n||_M`` for
    rollouts from ``u*_0`` (vmapped), and their total CG iterations."""
    truth = trajectories.states

    def one(states):
        predicted, iterations = rollout(network, problem, states[0], states.shape[0] - 1,
                                        solver, setup=setup, step=step)
        errors = jax.vmap(lambda u, t: jnp.sqrt(_relative_error2(problem, u, t)))(
            predicted[1:], states[1:])
        return jnp.mean(errors), iterations

    errors, iterations = jax.vmap(one)(truth)
    return jnp.mean(errors), jnp.sum(iterations)


# --------------------------------------------------------------------------------------
# training
# --------------------------------------------------------------------------------------


class HeatRecord(NamedTuple):
    epoch: int
    iterations: int           # K of this epoch's solves (0 for the prediction setup)
    adjoint_iterations: int
    rtol: float               # tolerance mode (converged training), else 0
    primal_iterations: int    # cumulative forward CG iterations of the training solves
    time: float               # cumulative run time, compile excluded, validation included
    train_loss: float         # mean over the epoch's batches
    validation_error: float   # rollout error of the validation trajectories (converged)
    adjoint_iterations_total: int = 0  # cumulative adjoint CG iterations (WIG; else 0)
    test_error: float = math.nan       # held-out rollout error (``test_set``), untimed
    validation_iterations: int = 0     # cumulative CG iterations of the validation rollouts
    truncation_gap: float = math.nan   # |validation error at the epoch's rtol / converged - 1|
    #                                    (mixed: chain_gap() on validation windows; a
    #                                    truncation_gap() controller's input; else NaN)
    redone: int = 0                    # tries of this epoch discarded (a controller's redo),
    #                                    their work counted in the totals above


@jax.jit
def _converged_steps(problem: HeatProblem, states: jax.Array) -> jax.Array:
    """One converged step of ``problem`` from each of ``states`` (one program per shape)."""
    exact = ConvergedCG(rtol=1e-12)
    return jax.vmap(lambda x: heat_step(problem, x, exact)[0])(states)


def initial_network(problem: HeatProblem, train_set: Trajectories, setup: str,
                    hidden: tuple[int, ...] = (128,), seed: int = 0) -> Network:
    """An untrained MLP ``[n_free, *hidden, n_free]`` whose output scale is the spread of its
    targets relative to its (RMS-normalised) inputs over ``train_set``'s one-step pairs: the
    converged coarse step's error (correction) or the step itself (prediction, mixed)."""
    _check_choice(setup, "setup", SETUPS)
    pairs = windows(train_set, 1)
    u, target = pairs[:, 0], pairs[:, 1]
    if setup == "correction":
        u = _converged_steps(problem, u)
    u, target = np.asarray(u), np.asarray(target)
    rho = np.sqrt(np.mean(u**2, axis=1, keepdims=True))
    rho = np.where((rho > 0) & (not problem.reaction), rho, 1.0)  # see correction()
    scale = float(np.std((target - u) / rho))
    return mlp_init(jax.random.PRNGKey(seed), [problem.n_free, *hidden, problem.n_free],
                    output_scale=scale if scale > 0 else 1.0)


def _make_step(optimizer, setup, mode, gradient, tolerance_mode, preconditioner, step_fn,
               counted: bool, substeps: int):
    """One optimiser step; (K, K_adj, rtol) are arguments, so trainings that differ only in
    them run one compiled program (per scan length in unrolled mode). It returns the forward
    solves' CG iterations and the seed's gradient of a
    :class:`~prdp_fem.linalg.ReverseTally` (:func:`~prdp_fem.linalg.read_counts`), whose
    ``"adjoint"`` entry counts the backward pass's solves where ``counted`` (``step_fn`` is
    :func:`heat_step`, which takes a counter): no host call, so the step keeps JAX's fast
    dispatch path."""

    def step(network, opt_state, problem, batch, scan_length, K, K_adj, rtol,
             cycle=None):  # cycle: see inverse._preconditioner_key
        solver = step_solver(gradient, tolerance_mode, K, K_adj, rtol,
                         preconditioner if cycle is None else cycle, scan_length)

        def loss_of(params, seed):  # the model's params train; the rest (an MLP's scales) not
            stepper = partial(step_fn, counter=ReverseTally(seed)) if counted else step_fn
            return batch_loss(network.replace_params(params), problem, batch, solver,
                              setup=setup, mode=mode, step=stepper, substeps=substeps)

        (loss, iterations), (grads, counts) = jax.value_and_grad(
            loss_of, argnums=(0, 1), has_aux=True)(network.params, zero_counts())
        updates, opt_state = optimizer.update(grads, opt_state, network.params)
        params = optax.apply_updates(network.params, updates)
        return network.replace_params(params), opt_state, loss, iterations, counts, \
            optax.tree.norm(grads)

    return step


def _new_step_program(optimizer, setup, mode, gradient, tolerance_mode, preconditioner,
                      step, counted, substeps) -> SharedCompile:
    return SharedCompile(_make_step(optimizer, setup, mode, gradient, tolerance_mode,
                                    preconditioner, step, counted, substeps),
                         static_argnum=4)


#: The compiled step per settings (optimizer object, setup, mode, gradient, tolerance mode,
#: preconditioner, step function, counted, substeps), kept for the process: a study's PRDP and
#: converged runs of one mode trace and lower it once (about 0.8 s for the heat scene's
#: correction step).
_step_program = kept_programs(_new_step_program)


def _new_validation_programs(setup, step, validation_rtol, preconditioner):
    """The validation rollout with converged solves and the same rollout at a level (``K``
    and ``rtol`` traced: one program for every level), jitted."""
    solver = ConvergedCG(rtol=validation_rtol, max_iterations=_CONVERGED_CAP,
                         preconditioner=preconditioner)
    validate = jax.jit(lambda net, prob, val: rollout_error(
        net, prob, val, solver, setup=setup, step=step))
    validate_at = jax.jit(lambda net, prob, val, K, rtol: rollout_error(
        net, prob, val, ConvergedCG(rtol=rtol, max_iterations=K, preconditioner=preconditioner),
        setup=setup, step=step))
    return validate, validate_at


#: The validation programs per (setup, step, validation rtol, preconditioner name), kept as
#: the step is: a study's runs and a bench's seeds trace them once per shape.
_validation_programs = kept_programs(_new_validation_programs)


def _new_chain_programs(step, preconditioner, substeps):
    """The mixed chain's states over windows at a level (``K`` and ``rtol`` traced: the
    reference and the level share one program) and :func:`chain_gap`, jitted: what a
    truncation_gap() controller is fed when the validation rollouts run no solver."""
    def chain(net, prob, batch, K, rtol):
        solver = ConvergedCG(rtol=rtol, max_iterations=K, preconditioner=preconditioner)
        states, iterations = jax.vmap(lambda w: chain_states(
            net, prob, w, solver, substeps=substeps, step=step))(batch)
        return states, jnp.sum(iterations)

    return jax.jit(chain), jax.jit(chain_gap)


#: The mixed chain's gap programs per (step, preconditioner name, substeps).
_chain_programs = kept_programs(_new_chain_programs)


class _GapPasses(NamedTuple):
    """What a truncation_gap() controller is fed from: ``reference(net, rtol, validated=None)``
    (the reference for the level ``rtol``) and ``at(net, K, rtol)`` return a value and its CG
    iterations (``validated``: the epoch's converged validation ``(error, iterations)``,
    reused where it is the reference), ``of(reference value, value at the level)`` the gap,
    ``compile(net)`` runs what the validation's compilation does not cover;
    ``follows_level``: whether the reference depends on the level."""
    reference: Callable
    at: Callable
    of: Callable
    compile: Callable
    follows_level: bool


def _gap_passes(setup, problem, validation_set, unroll, substeps, step, validation_rtol,
                preconditioner, validate, validate_at, reference_factor, *,
                keep) -> _GapPasses:
    """The validation rollouts (converged, their error the reference, and at the level) --
    or, for the mixed setup, whose rollouts run no solver, the training's own chain over the
    validation windows starting every ``unroll`` steps, compared by :func:`chain_gap`: the
    reference chain to ``rtol * reference_factor`` (``None``: to ``validation_rtol``), never
    tighter than ``validation_rtol``."""
    if setup != "mixed":
        def reference(net, rtol, validated=None):
            return validate(net, problem, validation_set) if validated is None else validated

        return _GapPasses(reference,
                          lambda net, K, rtol: validate_at(net, problem, validation_set, K,
                                                           rtol),
                          validation_gap, lambda net: None, False)
    chain, gap_program = _chain_programs(step, preconditioner, substeps, keep=keep)
    gap_windows = windows(validation_set, unroll, stride=unroll)

    def reference(net, rtol, validated=None):
        del validated  # the validation ran no solver: the chain's reference is its own
        tolerance = validation_rtol if reference_factor is None else max(
            float(rtol) * reference_factor, validation_rtol)
        K, _, tolerance = device_settings((_CONVERGED_CAP, _CONVERGED_CAP, tolerance))
        return chain(net, problem, gap_windows, K, tolerance)

    def compile_gap(net):  # the gap, outside the timed region (the chain is the level's
        del net  # program, compiled with it): states of the chain's shape, no chain run
        states = jnp.zeros_like(gap_windows[:, 1:])
        jax.block_until_ready(gap_program(problem, gap_windows, states, states))

    return _GapPasses(reference,
                      lambda net, K, rtol: chain(net, problem, gap_windows, K, rtol),
                      lambda converged, truncated: float(
                          gap_program(problem, gap_windows, converged, truncated)),
                      compile_gap, reference_factor is not None)


def train(problem: HeatProblem, network: Model | Network, train_set: Trajectories,
          validation_set: Trajectories, *, setup: str = "correction", mode: str = "nog",
          unroll: int = 3, optimizer: optax.GradientTransformation | None = None,
          refinement: Refinement | None = None, epochs: int = 30, batch_size: int = 16,
          gradient: str = "implicit", preconditioner: Any = "jacobi", seed: int = 0,
          validation_rtol: float = 1e-10, step: Step = heat_step, substeps: int = 1,
          test_set: Trajectories | None = None, checkpoints: Checkpoints | None = None,
          callback: Callable[[HeatRecord], None] | None = None,
          learning_rate: Callable[[Any], Any] | float | None = None) -> Training:
    """Train ``network`` (any model, :mod:`prdp_fem.learning.model`, from the free dofs to
    the free dofs; only its ``params`` train, an MLP's scales stay fixed) as the ``setup``
    stepper with ``mode`` over windows of ``unroll``
    steps: ``epochs`` epochs of shuffled mini-batches of windows (``seed``), ``K`` picked
    once per epoch by ``refinement`` (default :func:`~prdp_fem.inverse.prdp` with ``K0=1, dK=1``,
    the reference's heat schedule) from the validation rollout error. ``step`` replaces
    :func:`heat_step` (a stand-in solver). The prediction setup runs no solver (``K`` = 0).
    The mixed setup (``mode="wig"``, ``unroll >= 2``) trains through ``problem``'s solves, each
    solver step of its chain ``substeps`` steps of ``problem`` (pass the reference's fine step,
    ``dt / substeps``, and its ``substeps``); its validation and test rollouts are the network's
    alone.

    WIG's adjoint solves are tallied in the step's program (a
    :class:`~prdp_fem.linalg.ReverseTally`; ONE and NOG run none). ``test_set``: held-out
    trajectories whose rollout error (converged solves, outside the timed region) each record
    carries as ``test_error``.
    ``checkpoints``: save and resume the whole training state, as
    :func:`~prdp_fem.learning.learned.train` does.
    ``callback(record)`` runs after every epoch, also outside the timed region (and first for
    each record a resumed run restored).
    ``learning_rate``: ``optimizer``'s learning rate (an optax schedule of the update count,
    or a number), read only by a controller that judges stalls per unit learning rate
    (``prdp(per_learning_rate=True)``), which is fed each epoch's mean rate over the first
    step's; needed with an ``optimizer`` of your own.

    Returns a :class:`~prdp_fem.learning.learned.Training` of :class:`HeatRecord` s. Raises
    :class:`~prdp_fem.errors.SolverConfigError` / :class:`~prdp_fem.errors.ShapeError` for
    bad options and :class:`~prdp_fem.inverse.driver.InversionError` when a step produces a
    non-finite loss or gradient.
    """
    from ..inverse.driver import InversionError

    _check_choice(setup, "setup", SETUPS)
    _check_choice(mode, "mode", MODES)
    if gradient not in ("implicit", "unrolled"):
        raise SolverConfigError(f"gradient={gradient!r}: expected 'implicit' or 'unrolled'")
    epochs, batch_size = _count(epochs, "epochs"), _count(batch_size, "batch_size")
    substeps = _count(substeps, "substeps")
    if setup == "mixed":
        _check_mixed(mode, _count(unroll, "unroll"))
    for name, data in (("train_set", train_set), ("validation_set", validation_set),
                       ("test_set", test_set)):
        if data is None:
            continue
        if data.states.ndim != 3 or data.states.shape[-1] != problem.n_free:
            raise ShapeError(f"{name}: states{tuple(data.states.shape)}; expected "
                             f"(n_trajectories, steps + 1, {problem.n_free})")
        if data.states.shape[0] == 0:
            raise ShapeError(f"{name}: no trajectories; expected at least one")
    check_model(network, problem.n_free, problem.n_free, "the free dofs of the problem")
    data = windows(train_set, unroll)
    n = int(data.shape[0])
    if batch_size > n:
        raise SolverConfigError(f"batch_size={batch_size}: expected at most the {n} training "
                                f"windows ({train_set.states.shape[0]} trajectories x "
                                f"{train_set.steps - unroll + 1} starts)")
    refinement = prdp(K0=1, dK=1) if refinement is None else refinement
    check_training_refinement(refinement, gradient)
    solves = setup != "prediction"
    update_control = epoch_update(refinement, learning_rate, n // batch_size, optimizer is None)
    optimizer = default_optimizer() if optimizer is None else optimizer
    # only WIG differentiates the solver; count its adjoint solves when the step is ours
    counted = step is heat_step and solves and mode == "wig"
    key = preconditioner_key(preconditioner)
    step_fn = _step_program(optimizer, setup, mode, gradient, refinement.tolerance_mode, key,
                            step, counted, substeps, keep=keeps_program(key))
    # kept for a named preconditioner only: these programs close over the preconditioner
    # (the step takes an AMG cycle as an argument, so keeps_program() keeps that one too)
    validate, validate_at = _validation_programs(setup, step, float(validation_rtol),
                                                 preconditioner, keep=isinstance(key, str))
    # a truncation_gap() controller is fed the change of the validation error when its
    # rollouts run at the training's tolerance: one more rollout an epoch, counted and timed
    # with the validation (the mixed setup: one converged and one truncated chain)
    gap_fed = solves and refinement.monitor == "truncation_gap"
    gap = _gap_passes(setup, problem, validation_set, unroll, substeps, step,
                      float(validation_rtol), preconditioner, validate, validate_at,
                      refinement.reference_factor, keep=isinstance(key, str)) \
        if gap_fed else None
    rng = np.random.default_rng(seed)
    with CheckpointSession.open(checkpoints, "heat") as saved:
        state = start_state(saved, network.params, optimizer.init(network.params),
                            refinement.init(), rng, HeatRecord, epochs, callback)
        network = network.replace_params(state.params)
        opt_state, control, records = state.opt_state, state.control, list(state.records)
        primal, run_time = state.counters["primal"], state.counters["run_time"]
        adjoint = state.counters["adjoint"]
        checked = state.counters.get("validation", 0)  # the validation solves' CG iterations
        if gap_fed and state.epoch == 0:  # the first level, settled on the untrained model
            gap.compile(network)
            control, iterations, seconds = first_level(
                refinement, control, partial(gap.reference, network), partial(gap.at, network),
                gap.of, reference_follows_level=gap.follows_level)
            checked, run_time = checked + iterations, run_time + seconds
        compiled = False  # the validation programs (compiled outside the timed region)
        for epoch in range(state.epoch + 1, epochs + 1):
            # a controller with redo trains an epoch again when it tightened the solves:
            # from the parameters, optimiser state and batch order the epoch started with
            started = (network, opt_state, rng.bit_generator.state)
            redone = 0
            while True:
                # no solver: one compile, nothing to refine
                settings = control.settings() if solves else (0, 0, 0.0)
                K, K_adj, rtol = device_settings(settings)
                # read on the host, not the device
                scan_length = step_scan_length(gradient, settings[0])
                order = rng.permutation(n)
                losses = []
                for i in range(0, n - batch_size + 1, batch_size):
                    batch = data[order[i:i + batch_size]]
                    compile_before = step_fn.seconds  # compilation is timed apart from the run
                    start = time.perf_counter()
                    network, opt_state, loss, iterations, counts, grad_norm = \
                        jax.block_until_ready(step_fn(network, opt_state, problem, batch,
                                                      scan_length, K, K_adj, rtol,
                                                      *cycle_argument(preconditioner)))
                    run_time += time.perf_counter() - start - (step_fn.seconds - compile_before)
                    if not (math.isfinite(float(loss)) and math.isfinite(float(grad_norm))):
                        raise InversionError(
                            f"epoch {epoch}: non-finite loss or gradient (loss {float(loss)!r}, "
                            f"setup={setup!r}, mode={mode!r}, K={int(control.iterations)}); try "
                            "a smaller learning rate or more CG iterations")
                    losses.append(float(loss))
                    primal += int(iterations)
                    adjoint += read_counts(counts)["adjoint"]
                if not compiled:
                    compile_passes(partial(validate, network, problem, validation_set),
                                   partial(gap.at, network) if gap_fed else None, K, rtol)
                    if gap_fed:
                        gap.compile(network)
                    compiled = True
                start = time.perf_counter()
                error, iterations = validate(network, problem, validation_set)
                checked += int(iterations)  # CG iterations count everything that ran
                measured_gap = math.nan
                if gap_fed:
                    reference, iterations = gap.reference(network, rtol,
                                                          validated=(error, 0))
                    truncated, more = gap.at(network, K, rtol)
                    checked += int(iterations) + int(more)
                    measured_gap = gap.of(reference, truncated)
                previous = control
                if solves:
                    control = update_control(
                        control, measured_gap if gap_fed else float(error), epoch)
                run_time += time.perf_counter() - start
                if not (refinement.redo and solves
                        and control.settings() != previous.settings()):
                    break
                network, opt_state, rng.bit_generator.state = started
                redone += 1
            test_error = math.nan if test_set is None else float(
                validate(network, problem, test_set)[0])
            record = HeatRecord(
                epoch, int(previous.iterations) if solves else 0,
                int(previous.adjoint_iterations) if solves else 0,
                float(previous.rtol) if solves else 0.0, primal, run_time,
                float(np.mean(losses)), float(error), adjoint, test_error, checked,
                measured_gap, redone)
            records.append(record)
            if callback is not None:
                callback(record)
            if saved is not None:
                saved.save(TrainingState(epoch, network.params, opt_state, control,
                                         rng.bit_generator.state, records,
                                         {"primal": primal, "adjoint": adjoint,
                                          "validation": checked,
                                          "steps": 0, "run_time": run_time}),
                           final=epoch == epochs)
    return Training(network, control, records)
