r"""Learned inverse problems: a network maps observations to a source, trained through PCG.

A dataset of seeded smooth sources :math:`f_i` (random Gaussian bumps on the mesh) and their
noisy observations :math:`d_i = B u(f_i) + \eta_i` (converged reference solves) trains a
network :math:`N_\theta: d \mapsto f` on

.. math::

    L(\theta) = \frac{1}{|\mathcal B|} \sum_{i \in \mathcal B}
        \tfrac12 \| B\, u_K(N_\theta(d_i)) - d_i \|_W^2
        + \beta\, \tfrac12 \| N_\theta(d_i) - f_i \|_M^2 ,

where :math:`u_K` is the *truncated* PCG solve (``K`` iterations, implicit or unrolled
gradient; batched with ``vmap``) and :math:`\beta \ge 0` weighs an optional supervised term.
A refinement controller (:mod:`prdp_fem.inverse.refinement`) picks ``K`` once per epoch from the
*validation misfit*: the same observation misfit on held-out samples, computed with a
converged solve so that it does not move when ``K`` does.

The network is any model (:mod:`prdp_fem.learning.model`: a JAX function of trainable
parameters, an Equinox or a Flax module); the default is a plain-JAX MLP (:func:`mlp_init`,
:func:`mlp_apply`: ``tanh`` hidden layers, a linear output, inputs and outputs scaled by the
data's spread).

>>> import prdp_fem as pf
>>> disc = pf.discretize(pf.unit_square(4))
>>> f = random_sources(disc, 3, seed=0)
>>> f.shape, bool(np.all(np.isfinite(f)))
((3, 25), True)
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from functools import cached_property, partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

from .._executables import SharedCompile, kept_programs
from ..errors import ShapeError, SolverConfigError
from ..fem.discretization import Discretization
from ..fem.observations import Observation
from ..fem.reference import amg_solve
from ..fem.residuals import square_root_factor
from ..fem.system import LinearSystem
from ..inverse.comparison import first_settled
from ..inverse.refinement import Refinement, RefinementState, prdp
from ..inverse.steps import (
    check_training_refinement,
    cycle_argument,
    device_settings,
    keeps_program,
    preconditioner_key,
    step_scan_length,
    step_solver,
    uses_stored_value,
    value_grad_and_update,
)
from ..linalg.cg import IterationCounter
from ..linalg.operator import FixedMatrix, SparseMatrix, matvec
from ..optim.hig import JACOBIAN_MODES
from ._defaults import default_optimizer
from ._gap import compile_passes, first_level
from ._gap import gap as validation_gap
from ._step_size import epoch_update
from .checkpoint import Checkpoints, CheckpointSession, TrainingState, start_state
from .model import Model, check_model

__all__ = [
    "BatchObjective",
    "EpochRecord",
    "LearnedFactors",
    "LearnedInverse",
    "Network",
    "SourceSamples",
    "Training",
    "learned_inverse",
    "mlp_apply",
    "mlp_init",
    "random_sources",
    "source_samples",
    "train",
    "training_saving",
]


# --------------------------------------------------------------------------------------
# data
# --------------------------------------------------------------------------------------


class SourceSamples(NamedTuple):
    """Sources (nodal, ``(n, n_dofs)``) and their noisy observations (``(n, n_obs)``)."""

    sources: jax.Array
    observations: jax.Array

    def take(self, index) -> SourceSamples:
        return SourceSamples(self.sources[index], self.observations[index])


def random_sources(disc: Discretization, n_samples: int, *, seed: int = 0, bumps: int = 3,
                   width: float = 0.15, amplitude: float = 10.0) -> np.ndarray:
    """``n_samples`` smooth nodal sources: sums of ``bumps`` Gaussians (widths ``width`` times
    the mesh's diameter) at uniform random centres in its bounding box, with amplitudes
    uniform in ``[-amplitude, amplitude]``. Seeded: the same seed gives the same fields."""
    for name, value in (("n_samples", n_samples), ("bumps", bumps)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise SolverConfigError(f"{name}={value!r}: expected an integer >= 1")
    if not (math.isfinite(width) and width > 0 and math.isfinite(amplitude)):
        raise SolverConfigError(f"width={width!r}, amplitude={amplitude!r}: expected finite "
                                "numbers, width > 0")
    x = disc.basis.doflocs  # (dim, n_dofs)
    low, high = x.min(axis=1), x.max(axis=1)
    sigma = width * float(np.linalg.norm(high - low))
    rng = np.random.default_rng(seed)
    centres = rng.uniform(low, high, size=(n_samples, bumps, x.shape[0]))
    weights = rng.uniform(-amplitude, amplitude, size=(n_samples, bumps))
    distance2 = ((x.T[None, None] - centres[:, :, None]) ** 2).sum(axis=-1)
    return np.einsum("sb,sbn->sn", weights, np.exp(-distance2 / (2 * sigma**2)))


def source_samples(problem: LearnedInverse, sources: np.ndarray, *, noise: float = 0.01,
                   seed: int = 0) -> SourceSamples:
    """Observations of ``sources`` by converged reference solves (pyamg, rtol 1e-12) plus
    Gaussian noise of ``noise`` times each observation's RMS value (seeded)."""
    sources = np.asarray(sources, dtype=float)
    if sources.ndim != 2 or sources.shape[1] != problem.system.n_dofs:
        raise ShapeError(f"sources{sources.shape}: expected (n_samples, "
                         f"{problem.system.n_dofs}) nodal fields")
    if not (math.isfinite(noise) and noise >= 0):
        raise SolverConfigError(f"noise={noise!r}: expected a finite number >= 0")
    A = problem.system.operator(problem.kappa).to_scipy()
    B = problem.observation.operator.to_scipy()
    rng = np.random.default_rng(seed)
    observations = []
    for f in sources:
        b = np.asarray(problem.system.rhs(problem.kappa, jnp.asarray(f)))
        u = np.asarray(problem.system.expand(jnp.asarray(amg_solve(A, b).x)))
        d = B @ u
        rms = float(np.sqrt(np.mean(d**2)))
        observations.append(d + noise * rms * rng.standard_normal(d.shape))
    return SourceSamples(jnp.asarray(sources), jnp.asarray(np.array(observations)))


# --------------------------------------------------------------------------------------
# the network
# --------------------------------------------------------------------------------------


class Network(NamedTuple):
    """MLP weights ``[(W, b), ...]`` and the scales of its input and output (not trained
    by :func:`train`): a model (:mod:`prdp_fem.learning.model`) whose ``params`` are the
    layers."""

    layers: list
    input_scale: jax.Array
    output_scale: jax.Array

    @property
    def params(self) -> list:
        return self.layers

    def predict(self, params, observation: jax.Array) -> jax.Array:
        return mlp_apply(self._replace(layers=params), observation)

    def replace_params(self, params) -> Network:
        return self._replace(layers=params)

    def __call__(self, observation: jax.Array) -> jax.Array:
        return mlp_apply(self, observation)


def mlp_init(key: jax.Array, sizes: list[int], *, input_scale: float = 1.0,
             output_scale: float = 1.0) -> Network:
    """Layers of ``sizes`` (``[n_in, hidden..., n_out]``), weights normal with variance
    ``1 / fan_in`` (LeCun: ``tanh`` keeps unit-scale activations), biases zero."""
    if len(sizes) < 2 or any(isinstance(s, bool) or not isinstance(s, int) or s < 1
                             for s in sizes):
        raise SolverConfigError(f"sizes={sizes!r}: expected >= 2 integers >= 1")
    keys = jax.random.split(key, len(sizes) - 1)
    layers = [(jax.random.normal(k, (n_in, n_out)) / np.sqrt(n_in), jnp.zeros(n_out))
              for k, n_in, n_out in zip(keys, sizes[:-1], sizes[1:], strict=True)]
    return Network(layers, jnp.asarray(float(input_scale)), jnp.asarray(float(output_scale)))


def mlp_apply(network: Network, observation: jax.Array) -> jax.Array:
    """The source the network predicts from one observation vector."""
    h = observation / network.input_scale
    for W, b in network.layers[:-1]:
        h = jnp.tanh(h @ W + b)
    W, b = network.layers[-1]
    return network.output_scale * (h @ W + b)


# --------------------------------------------------------------------------------------
# the problem and its losses
# --------------------------------------------------------------------------------------


class LearnedFactors(NamedTuple):
    """Square-root factors for the residual form of the loss: ``L_W^T L_W = W`` (misfit
    weight) and ``L_M^T L_M = M`` (nodal mass, the supervised term); see
    :mod:`prdp_fem.fem.residuals`."""

    misfit: SparseMatrix
    source: SparseMatrix


@partial(jax.tree_util.register_dataclass,
         data_fields=["system", "kappa", "observation", "mass", "supervised", "factors"],
         meta_fields=[])
@dataclasses.dataclass(frozen=True)
class LearnedInverse:
    """The fixed physics of a learned source inversion (a pytree: a jit argument).

    ``system`` is frozen at the coefficient (``Discretization.system_at``) and ``kappa`` is
    its one coefficient, the scale ``ones(1)``;
    ``observation`` gives ``B`` and ``W`` (its data is not used: each sample has its own);
    ``mass`` is the nodal mass matrix (source errors and the supervised term);
    ``supervised`` is the weight ``beta`` of the supervised term (0: observations only);
    ``factors`` (from :meth:`with_residual`) write the loss as a sum of squares for
    Gauss-Newton-type optimisers (:class:`BatchObjective`).
    """

    system: LinearSystem
    kappa: jax.Array  # the system's coefficient: the scale ones(1) of a frozen system
    observation: Observation
    mass: FixedMatrix  # symmetric, laid out once
    supervised: jax.Array
    factors: LearnedFactors | None = None

    def misfit(self, f: jax.Array, d: jax.Array, solver,
               counter: IterationCounter | None = None) -> tuple[jax.Array, jax.Array]:
        """``1/2 ||B u(f) - d||_W^2`` with ``u`` from ``solver``, and its iteration count."""
        sol = self.system.solve(self.kappa, f, solver, counter=counter)
        r = self.observation.operator(self.system.expand(sol.x)) - d
        return 0.5 * jnp.vdot(r, self.observation.weight(r)), sol.iterations

    def source_error(self, f: jax.Array, truth: jax.Array) -> jax.Array:
        """Relative L2 error ``||f - f*||_M / ||f*||_M``."""
        e = f - truth
        return jnp.sqrt(jnp.vdot(e, self.mass(e))
                        / jnp.maximum(jnp.vdot(truth, self.mass(truth)), 1e-300))

    def with_residual(self) -> LearnedInverse:
        """The problem with the factors of ``W`` and ``M`` (built once, on the host)."""
        return dataclasses.replace(self, factors=LearnedFactors(
            SparseMatrix.from_scipy(square_root_factor(self.observation.weight.to_scipy(),
                                                       "observation weight W")),
            SparseMatrix.from_scipy(square_root_factor(self.mass.to_scipy(),
                                                       "nodal mass M"))))

    def misfit_residual(self, f: jax.Array, d: jax.Array, solver,
                        counter: IterationCounter | None = None) -> jax.Array:
        """``L_W (B u_K(f) - d)``: half its squared norm is :meth:`misfit`."""
        sol = self.system.solve(self.kappa, f, solver, counter=counter)
        r = self.observation.operator(self.system.expand(sol.x)) - d
        return matvec(self._factors().misfit, r)

    def supervised_residual(self, f: jax.Array, f_true: jax.Array) -> jax.Array:
        """``sqrt(beta) L_M (f - f*)``: half its squared norm is the supervised term."""
        return jnp.sqrt(self.supervised) * matvec(self._factors().source, f - f_true)

    def _factors(self) -> LearnedFactors:
        if self.factors is None:
            raise SolverConfigError(
                "LearnedInverse: the residual form needs the factors of W and M; call "
                "problem.with_residual() (outside jit) or let train() build them")
        return self.factors


def learned_inverse(disc: Discretization, observation: Observation, *, kappa=1.0,
                    supervised: float = 0.0) -> LearnedInverse:
    """A :class:`LearnedInverse` on ``disc`` with coefficient ``kappa`` (checked here; the
    system is frozen at it, so no map ``kappa -> A`` is built)."""
    if not (math.isfinite(supervised) and supervised >= 0):
        raise SolverConfigError(f"supervised={supervised!r}: expected a finite number >= 0")
    if observation.operator.shape[1] != disc.n_dofs:
        raise ShapeError(f"observation: operator acts on {observation.operator.shape[1]} "
                         f"dofs, expected {disc.n_dofs} (built on another discretisation?)")
    # kappa never changes: the system frozen at it, whose one coefficient is a scale
    system = disc.system_at(kappa)
    return LearnedInverse(system, jnp.ones(1), observation,
                          FixedMatrix.symmetric(disc.mass_matrix),
                          jnp.asarray(float(supervised)))


def batch_loss(network: Model | Network, problem: LearnedInverse, batch: SourceSamples,
               solver, counter: IterationCounter | None = None) -> tuple[jax.Array, jax.Array]:
    """The training loss over ``batch`` (solves batched with ``vmap``) and the CG
    iterations its forward solves ran (``counter`` also tallies every solve on the host).
    ``network`` is any model (:mod:`prdp_fem.learning.model`)."""

    def one(f_true, d):
        f = network(d)
        misfit, iterations = problem.misfit(f, d, solver, counter)
        e = f - f_true
        return misfit + problem.supervised * 0.5 * jnp.vdot(e, problem.mass(e)), \
            iterations

    losses, iterations = jax.vmap(one)(batch.sources, batch.observations)
    return jnp.mean(losses), jnp.sum(iterations)


@dataclasses.dataclass(frozen=True, eq=False)
class BatchObjective:
    r"""The batch loss as a function of the model's *parameters*: the ``value_fn`` that
    :func:`train` hands to optax (like :class:`prdp_fem.inverse.Objective` for one inversion).

    Only ``params`` are arguments (called ``layers`` below); the rest of ``network`` (an
    MLP's input and output scales) stays frozen.
    Calling it gives ``L(theta)`` (:func:`batch_loss`). Its residual, stacked over the batch,

    .. math::

        r(\theta) = \frac{1}{\sqrt{|\mathcal B|}} \begin{pmatrix}
            L_W \big(B u_K(N_\theta(d_i)) - d_i\big) \\
            \sqrt{\beta}\, L_M \big(N_\theta(d_i) - f_i\big) \end{pmatrix}_{i \in \mathcal B},
        \qquad \tfrac12 \|r\|^2 = L(\theta),

    feeds :func:`prdp_fem.optim.hig.hig` (:meth:`residual_jacobian` for the explicit Jacobian,
    :meth:`residual_blocks` for the matrix-free one) and :mod:`prdp_fem.optim.newton`
    (:meth:`gauss_newton_operator`, ``J^T J``). Every solve taps ``counter``, so line-search
    trials and Jacobian solves are in the tally. Inside a step ``counter`` is the counter's
    traced slot (a step argument), so it holds nothing mutable; build one per step (it holds
    the batch and the step's solver).
    """

    problem: LearnedInverse
    network: Model | Network   # the model; its params are replaced by the argument
    batch: SourceSamples
    solver: Any
    counter: IterationCounter | None = None

    def __call__(self, layers) -> jax.Array:
        return batch_loss(self.network.replace_params(layers), self.problem, self.batch,
                          self.solver, self.counter)[0]

    @cached_property
    def value_and_grad(self):
        """``jax.value_and_grad(self)`` as one nested program, traced once for all the places
        a step evaluates it (as :attr:`prdp_fem.inverse.driver.Objective.value_and_grad`)."""
        return jax.jit(jax.value_and_grad(self))

    def _scale(self) -> jax.Array:
        return 1.0 / jnp.sqrt(jnp.asarray(self.batch.sources.shape[0], jnp.float64))

    def _sample_misfit(self, layers, d) -> jax.Array:
        f = self.network.predict(layers, d)
        return self._scale() * self.problem.misfit_residual(f, d, self.solver, self.counter)

    def _sample_supervised(self, layers, f_true, d) -> jax.Array:
        f = self.network.predict(layers, d)
        return self._scale() * self.problem.supervised_residual(f, f_true)

    def misfit_residual(self, layers) -> jax.Array:
        """The misfit rows of ``r``, sample after sample (``|B| n_obs``)."""
        return jax.vmap(self._sample_misfit, in_axes=(None, 0))(
            layers, self.batch.observations).ravel()

    def supervised_residual(self, layers) -> jax.Array:
        """The supervised rows of ``r`` (``|B| n_dofs``; zero rows when ``beta = 0``)."""
        return jax.vmap(self._sample_supervised, in_axes=(None, 0, 0))(
            layers, self.batch.sources, self.batch.observations).ravel()

    def residual(self, layers) -> jax.Array:
        """``r(theta)``: the misfit rows of every sample, then the supervised rows."""
        return jnp.concatenate([self.misfit_residual(layers), self.supervised_residual(layers)])

    def residual_blocks(self) -> tuple:
        """``(r_misfit, r_supervised)`` as functions of the layers (:func:`~prdp_fem.optim.hig`'s
        matrix-free path: ``J v`` is one tangent solve per sample, ``J^T w`` one adjoint)."""
        return (self.misfit_residual, self.supervised_residual)

    def residual_jacobian(self, layers, mode: str = "auto") -> tuple[jax.Array, jax.Array]:
        """``(r, J)`` with ``J`` stacked over the batch, columns in ``ravel_pytree`` order.

        Per sample (``lax.map``): reverse mode costs one adjoint solve per observation, forward
        mode one tangent solve per weight; ``"auto"`` picks the cheaper (rows vs weights), so
        the Jacobian never pays the batch twice (a stacked ``jacrev`` would run every
        sample's adjoint solve for each row). The supervised rows need no solve.
        """
        if mode not in JACOBIAN_MODES:
            raise SolverConfigError(f"jacobian={mode!r}: expected one of {JACOBIAN_MODES}")
        n = ravel_pytree(layers)[0].size
        n_obs = self.problem.observation.operator.shape[0]
        reverse = mode == "reverse" or (mode == "auto" and n_obs < n)
        jacobian = jax.jacrev if reverse else jax.jacfwd
        # samples in sequence (lax.map), each sample's rows batched: a vmap over the samples
        # around the rows' vmap would hide the samples from the iteration counter's tally
        misfit = jax.lax.map(partial(jacobian(self._sample_misfit), layers),
                             self.batch.observations)
        supervised = jax.vmap(jax.jacrev(self._sample_supervised), in_axes=(None, 0, 0))(
            layers, self.batch.sources, self.batch.observations)
        matrix = jnp.concatenate([_stacked(misfit), _stacked(supervised)], axis=0)
        return self.residual(layers), matrix

    def gauss_newton_operator(self, layers):
        r"""``v -> J^T J v`` at ``layers`` (``J = dr/dtheta``), linearised once: each product
        is one tangent and one adjoint solve per sample; the Hessian of ``L`` less the
        second derivatives of the network and of nothing else (the solve is linear)."""
        _, forward = jax.linearize(self.residual, layers)
        adjoint = jax.linear_transpose(forward, layers)
        return lambda v: adjoint(forward(v))[0]


def _stacked(jacobian) -> jax.Array:
    """A per-sample Jacobian pytree (leaves ``(batch, rows, *weight shape)``) as the matrix
    ``(batch * rows, n_weights)`` whose columns follow ``ravel_pytree``."""
    leaves = jax.tree_util.tree_leaves(jacobian)
    rows = leaves[0].shape[0] * leaves[0].shape[1]
    return jnp.concatenate([jnp.reshape(leaf, (rows, -1)) for leaf in leaves], axis=1)


def validation(network: Model | Network, problem: LearnedInverse, samples: SourceSamples,
               rtol: float = 1e-10, preconditioner: Any = "jacobi",
               max_iterations: int = 100_000):
    """Mean observation misfit of held-out samples with a *converged* solve (to ``rtol``,
    at most ``max_iterations``), the mean relative source error, and the CG iterations of
    those solves (jit it; ``rtol`` and ``max_iterations`` may be traced)."""
    solver = step_solver("implicit", True, max_iterations, max_iterations, rtol, preconditioner)

    def one(f_true, d):
        f = network(d)
        misfit, iterations = problem.misfit(f, d, solver)
        return misfit, problem.source_error(f, f_true), iterations

    misfits, errors, iterations = jax.vmap(one)(samples.sources, samples.observations)
    return jnp.mean(misfits), jnp.mean(errors), jnp.sum(iterations)


# --------------------------------------------------------------------------------------
# training
# --------------------------------------------------------------------------------------


class EpochRecord(NamedTuple):
    epoch: int
    iterations: int           # K of this epoch's solves
    adjoint_iterations: int
    rtol: float               # tolerance mode (converged training), else 0
    primal_iterations: int    # cumulative forward CG iterations of the training solves
    time: float               # cumulative run time, compile excluded, validation included
    train_loss: float         # mean over the epoch's batches
    validation_misfit: float  # the monitored signal (converged solves)
    validation_error: float   # mean relative L2 error of the predicted sources
    adjoint_iterations_total: int = 0  # cumulative adjoint and tangent CG iterations
    steps: int = 0            # cumulative optimiser steps
    test_error: float = math.nan  # mean relative L2 source error of ``test_set``, untimed
    validation_iterations: int = 0  # cumulative CG iterations of the validation solves
    truncation_gap: float = math.nan  # |validation misfit at the epoch's rtol / converged - 1|
    #                                   (a truncation_gap() controller's input; else NaN)
    redone: int = 0                   # tries of this epoch discarded (a controller's redo),
    #                                   their work counted in the totals above


class Training(NamedTuple):
    network: Model | Network  # the trained model
    refinement: RefinementState
    records: list[EpochRecord]


class _StepResult(NamedTuple):
    layers: Any
    opt_state: Any
    loss: jax.Array
    grad_norm: jax.Array


def _make_step(optimizer, gradient: str, tolerance_mode: bool, preconditioner):
    """One optimiser step on the weights of ``network`` over ``batch``; the update gets
    ``value``, ``grad`` and ``value_fn`` (a :class:`BatchObjective`) like
    :func:`prdp_fem.inverse.driver.invert`'s, so L-BFGS, Newton-CG and HIG work as Adam does. The
    counter and (K, K_adj, rtol) are arguments: trainings that differ only in them run one
    compiled program (per scan length in unrolled mode)."""

    def step(layers, opt_state, network, problem, batch, counter, scan_length, K, K_adj,
             rtol, cycle=None) -> _StepResult:  # cycle: see inverse._preconditioner_key
        solver = step_solver(gradient, tolerance_mode, K, K_adj, rtol,
                         preconditioner if cycle is None else cycle, scan_length)
        value_fn = BatchObjective(problem, network, batch, solver, counter)
        value, grad, updates, opt_state, _, _ = value_grad_and_update(
            optimizer, opt_state, layers, value_fn)
        return _StepResult(optax.apply_updates(layers, updates), opt_state, value,
                           optax.tree.norm(grad))

    return step


def _new_step_program(optimizer, gradient, tolerance_mode, preconditioner) -> SharedCompile:
    optimizer = optax.with_extra_args_support(optimizer)  # keyed by the object as given
    return SharedCompile(_make_step(optimizer, gradient, tolerance_mode, preconditioner),
                         static_argnum=6)


#: The compiled step per settings, kept for the process as ``invert`` keeps its own:
#: trainings with equal settings trace and lower their step once.
_step_program = kept_programs(_new_step_program)


def _new_validation_programs(validation_rtol, preconditioner):
    """The validation pass with converged solves and the same pass at a level (``K`` and
    ``rtol`` traced: one program for every level), jitted."""
    validate = jax.jit(partial(validation, rtol=validation_rtol, preconditioner=preconditioner))
    validate_at = jax.jit(lambda net, prob, samples, K, rtol: validation(
        net, prob, samples, rtol=rtol, preconditioner=preconditioner, max_iterations=K))
    return validate, validate_at


#: The validation programs per (validation rtol, preconditioner name), kept as the step is.
_validation_programs = kept_programs(_new_validation_programs)


def _check_training_options(optimizer, gradient, epochs, batch_size, n, refinement, layers):
    if gradient not in ("implicit", "unrolled"):
        raise SolverConfigError(f"gradient={gradient!r}: expected 'implicit' or 'unrolled'")
    for name, value in (("epochs", epochs), ("batch_size", batch_size)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise SolverConfigError(f"{name}={value!r}: expected an integer >= 1")
    if batch_size > n:
        raise SolverConfigError(f"batch_size={batch_size}: expected at most the {n} training "
                                "samples")
    check_training_refinement(refinement, gradient)
    if not isinstance(optimizer, optax.GradientTransformation):
        raise SolverConfigError(f"optimizer={optimizer!r}: expected an optax "
                                "GradientTransformation (optax.adam(...), optax.lbfgs(), "
                                "prdp_fem.newton_cg(...), prdp_fem.optim.hig(...))")
    if batch_size < n and uses_stored_value(optimizer.init(layers)):
        raise SolverConfigError(
            f"optimizer=optax.lbfgs with batch_size={batch_size} < {n} training samples: its "
            "curvature pairs difference gradients of different batches; expected "
            f"batch_size={n} (full batch) for L-BFGS (Newton-CG, Gauss-Newton and HIG take "
            "mini-batches)")


def _check_split(samples: SourceSamples | None, name: str, problem: LearnedInverse,
                 n_observations: int) -> None:
    """Refuse an empty split, or one whose fields are not this problem's."""
    if samples is None:
        return
    sources, observations = samples.sources, samples.observations
    if sources.ndim != 2 or observations.ndim != 2 or sources.shape[0] != observations.shape[0] \
            or sources.shape[1] != problem.system.source.shape[1] \
            or observations.shape[1] != n_observations:
        raise ShapeError(f"{name}: sources{tuple(sources.shape)}, observations"
                         f"{tuple(observations.shape)}; expected (n, "
                         f"{problem.system.source.shape[1]}) and (n, {n_observations})")
    if sources.shape[0] == 0:
        raise ShapeError(f"{name}: no samples; expected at least one")


def train(problem: LearnedInverse, network: Model | Network, train_set: SourceSamples,
          validation_set: SourceSamples, *, optimizer: optax.GradientTransformation | None = None,
          refinement: Refinement | None = None, epochs: int = 50, batch_size: int = 16,
          gradient: str = "implicit", preconditioner: Any = "jacobi", seed: int = 0,
          validation_rtol: float = 1e-10, test_set: SourceSamples | None = None,
          checkpoints: Checkpoints | None = None, callback=None,
          learning_rate: Callable[[Any], Any] | float | None = None) -> Training:
    """Train ``network`` for ``epochs`` epochs of shuffled mini-batches (``seed``) while
    ``refinement`` (default :func:`~prdp_fem.inverse.prdp` with ``K0=5, dK=5``) picks the CG
    iterations once per epoch from the validation misfit.

    ``network`` is any model (:mod:`prdp_fem.learning.model`: ``Model(apply, params)``, an
    Equinox or Flax module through :func:`~prdp_fem.learning.model.equinox_model` and
    :func:`~prdp_fem.learning.model.flax_model`, or the built-in :class:`Network`) mapping an
    observation vector to a nodal source. Only its ``params`` train (an MLP's input and
    output scales are frozen: the optimiser sees ``network.layers`` alone), and the trained
    model comes back in :attr:`Training.network`. ``optimizer`` is any optax
    transformation: its update gets
    ``value``, ``grad`` and ``value_fn`` (a :class:`BatchObjective`), so besides
    ``optax.adam``/``optax.sgd`` it can be ``optax.lbfgs()`` (zoom line search; full batch
    only: ``batch_size`` equal to the training samples), :func:`~prdp_fem.optim.newton.newton_cg`
    (``hessian="exact"`` or ``"gauss_newton"``; full batch is the natural setting, mini-batches
    give subsampled Newton steps) or :func:`~prdp_fem.optim.hig.hig` (the Jacobian of the residual
    stacked over the batch). With a full batch the samples are not shuffled, so the loss is
    one fixed function and L-BFGS may reuse its line search's last value.

    The iteration tally is exact: every solve -- gradient, line-search trials, Hessian or
    Jacobian products -- adds its iterations on the host
    (:class:`~prdp_fem.linalg.IterationCounter`);
    tangent solves count as adjoint iterations. ``test_set``: held-out samples whose mean
    source error (converged solves, outside the timed region) each record carries as
    ``test_error``. ``checkpoints`` (:class:`~prdp_fem.learning.checkpoint.Checkpoints`):
    save the whole training state every ``checkpoints.every`` epochs and at the end, and with
    ``resume=True`` continue from the latest checkpoint, bit for bit as an uninterrupted run.
    ``callback(record)`` runs after every epoch, and first for each record a resumed run
    restored (so that a log it writes is complete).
    ``learning_rate``: ``optimizer``'s learning rate (an optax schedule of the update count,
    or a number), read only by a controller that judges stalls per unit learning rate
    (``prdp(per_learning_rate=True)``), which is fed each epoch's mean rate over the first
    step's; needed with an ``optimizer`` of your own.

    Raises :class:`~prdp_fem.errors.SolverConfigError` for bad options (including L-BFGS with
    mini-batches) or an object that is not a model, :class:`~prdp_fem.errors.CheckpointError`
    for checkpoints of another training (or a fresh run into a directory that holds some),
    :class:`~prdp_fem.errors.ShapeError` for a model whose output is not one nodal source
    per observation or an empty split, and
    :class:`~prdp_fem.inverse.driver.InversionError` when a step produces a non-finite loss or
    gradient.
    """
    from ..inverse.driver import InversionError

    n_observations = int(train_set.observations.shape[-1])
    for name, samples in (("train_set", train_set), ("validation_set", validation_set),
                          ("test_set", test_set)):
        _check_split(samples, name, problem, n_observations)
    n = int(train_set.sources.shape[0])
    refinement = prdp(K0=5, dK=5) if refinement is None else refinement
    own_optimizer = optimizer is not None
    optimizer = default_optimizer() if optimizer is None else optimizer
    check_model(network, int(train_set.observations.shape[1]), problem.system.source.shape[1],
                "the nodal source of the problem, one per observation vector")
    _check_training_options(optimizer, gradient, epochs, batch_size, n, refinement,
                            network.params)
    update_control = epoch_update(refinement, learning_rate, n // batch_size, not own_optimizer)
    key = preconditioner_key(preconditioner)
    step = _step_program(optimizer, gradient, refinement.tolerance_mode, key,
                         keep=keeps_program(key))
    optimizer = optax.with_extra_args_support(optimizer)
    if problem.factors is None:
        problem = problem.with_residual()
    counter = IterationCounter()
    # kept for a named preconditioner only: these programs close over the preconditioner
    # (the step takes an AMG cycle as an argument, so keeps_program() keeps that one too)
    validate, validate_at = _validation_programs(float(validation_rtol), preconditioner,
                                                 keep=isinstance(key, str))
    # a truncation_gap() controller is fed the change of the validation misfit when its
    # solves run at the training's tolerance: one more pass an epoch, counted and timed with
    # the validation
    gap_fed = refinement.monitor == "truncation_gap"
    rng = np.random.default_rng(seed)
    with CheckpointSession.open(checkpoints, "learned") as saved:
        state = start_state(saved, network.params, optimizer.init(network.params),
                            refinement.init(), rng, EpochRecord, epochs, callback)
        layers, opt_state, control = state.params, state.opt_state, state.control
        records, (run_time, steps) = list(state.records), (state.counters["run_time"],
                                                          state.counters["steps"])
        counter.primal, counter.adjoint = state.counters["primal"], state.counters["adjoint"]
        checked = state.counters.get("validation", 0)  # the validation solves' CG iterations
        network = network.replace_params(layers)
        if gap_fed and state.epoch == 0:  # the first level, settled on the untrained model
            control, iterations, seconds = first_level(
                refinement, control,
                lambda rtol: _misfit(validate(network, problem, validation_set)),
                lambda K, rtol: _misfit(validate_at(network, problem, validation_set, K, rtol)))
            checked, run_time = checked + iterations, run_time + seconds
        compiled = False  # the validation programs (compiled outside the timed region)
        for epoch in range(state.epoch + 1, epochs + 1):
            # a controller with redo trains an epoch again when it tightened the solves:
            # from the parameters, optimiser state and batch order the epoch started with
            started = (layers, opt_state, rng.bit_generator.state)
            redone = 0
            while True:
                settings = control.settings()
                K, K_adj, rtol = device_settings(settings)
                # read on the host, not the device
                scan_length = step_scan_length(gradient, settings[0])
                order = rng.permutation(n) if batch_size < n else np.arange(n)
                batches = [order[i:i + batch_size]
                           for i in range(0, n - batch_size + 1, batch_size)]
                losses = []
                for index in batches:
                    batch = train_set.take(index)
                    compile_before = step.seconds  # compilation is timed apart from the run
                    start = time.perf_counter()
                    result = jax.block_until_ready(
                        step(layers, opt_state, network, problem, batch, counter, scan_length, K,
                             K_adj, rtol, *cycle_argument(preconditioner)))
                    run_time += time.perf_counter() - start - (step.seconds - compile_before)
                    if not (math.isfinite(float(result.loss))
                            and math.isfinite(float(result.grad_norm))):
                        raise InversionError(
                            f"epoch {epoch}: non-finite loss or gradient (loss "
                            f"{float(result.loss)!r}, K={int(control.iterations)}, "
                            f"rtol={float(rtol)!r}); try a smaller learning rate or more CG "
                            "iterations")
                    layers, opt_state = result.layers, result.opt_state
                    losses.append(float(result.loss))
                    steps += 1
                network = network.replace_params(layers)
                if not compiled:
                    compile_passes(partial(validate, network, problem, validation_set),
                                   partial(validate_at, network, problem, validation_set)
                                   if gap_fed else None, K, rtol)
                    compiled = True
                start = time.perf_counter()
                misfit, error, iterations = validate(network, problem, validation_set)
                checked += int(iterations)  # CG iterations count everything that ran
                gap = math.nan
                if gap_fed:
                    truncated, _, iterations = validate_at(network, problem, validation_set, K,
                                                           rtol)
                    checked += int(iterations)
                    gap = validation_gap(misfit, truncated)
                previous = control
                control = update_control(control, gap if gap_fed else float(misfit), epoch)
                run_time += time.perf_counter() - start
                redo = refinement.redo and previous.settings() != control.settings()
                if redo:
                    layers, opt_state, rng.bit_generator.state = started
                    network = network.replace_params(layers)
                    redone += 1
                if uses_stored_value(opt_state) and previous.settings() != control.settings():
                    # the stored value/gradient belong to the old solver: recompute them next
                    # step (same shape and dtype as stored: the step is compiled per argument
                    # type)
                    stored = optax.tree_utils.tree_get(opt_state, "value")
                    opt_state = optax.tree_utils.tree_set(
                        opt_state, value=jax.lax.full_like(stored, jnp.inf))
                if not redo:
                    break
            test_error = math.nan if test_set is None else float(
                validate(network, problem, test_set)[1])
            record = EpochRecord(epoch, int(previous.iterations), int(previous.adjoint_iterations),
                                 float(previous.rtol), counter.primal, run_time,
                                 float(np.mean(losses)), float(misfit), float(error),
                                 counter.adjoint, steps, test_error, checked, gap, redone)
            records.append(record)
            if callback is not None:
                callback(record)
            if saved is not None:
                saved.save(TrainingState(epoch, layers, opt_state, control, rng.bit_generator.state,
                                         records, {"primal": counter.primal,
                                                   "adjoint": counter.adjoint,
                                                   "validation": checked,
                                                   "steps": steps, "run_time": run_time}),
                           final=epoch == epochs)
    return Training(network, control, records)


def _misfit(validated):
    """``(misfit, CG iterations)`` of a :func:`validation` pass."""
    misfit, _, iterations = validated
    return misfit, iterations


def training_saving(records: list[EpochRecord], converged: list[EpochRecord], *,
                    band: float = 0.01, metric: str = "validation_misfit",
                    at_or_below: bool = False) -> dict:
    """PRDP's saving against converged training, same target on both sides: the run time
    (and CG iterations) of the first epoch from which ``records`` stay within ``band`` of
    the converged run's final ``metric`` (``at_or_below``: at most ``1 + band`` times it, a
    reading that credits ending lower, named as such where it is reported), over the
    converged run's own first such epoch (not its whole run, which goes on after it has
    arrived). ``None`` fields when ``records`` never settle there."""
    if metric not in ("validation_misfit", "validation_error"):
        raise SolverConfigError(f"metric={metric!r}: expected 'validation_misfit' or "
                                "'validation_error'")
    final = getattr(converged[-1], metric)
    target = final * (1 + band)

    def settled_record(run: list[EpochRecord]) -> EpochRecord | None:
        first = first_settled([getattr(r, metric) for r in run], final, band,
                              at_or_below=at_or_below)
        return None if first is None else run[first]

    hit, base = settled_record(records), settled_record(converged)
    if hit is None:
        return {"epoch": None, "time_saving": None, "iteration_saving": None,
                "target": target}
    return {"epoch": hit.epoch, "time_saving": 1 - hit.time / base.time,
            "iteration_saving": 1 - _total_iterations(hit) / _total_iterations(base),
            "target": target}


def _total_iterations(record) -> int:
    """Every CG iteration that ran: training (primal, adjoint) and validation solves (a heat
    record's too; records written before validation solves were counted lack them)."""
    return record.primal_iterations + record.adjoint_iterations_total + \
        getattr(record, "validation_iterations", 0)
