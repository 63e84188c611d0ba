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
A refinement controller (:mod:`prdp_fem.prdp`) picks ``K`` once per epoch from the
*validation misfit*: the same observation misfit on held-out samples, computed with a
converged solve so that it does not move when ``K`` does.

The network is a plain-JAX MLP (:func:`mlp_init`, :func:`mlp_apply`: ``tanh`` hidden layers, a
linear output, inputs and outputs scaled by the data's spread). No extra dependency: an MLP
is a dozen lines.

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
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .discretization import Discretization
from .errors import ShapeError, SolverConfigError
from .inverse import _solver
from .observations import Observation
from .operator import SparseMatrix, matvec
from .prdp import Refinement, RefinementState, prdp
from .reference import amg_solve
from .system import LinearSystem

__all__ = [
    "EpochRecord",
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
    """MLP weights ``[(W, b), ...]`` and the scales of its input and output (not trained)."""

    layers: list
    input_scale: jax.Array
    output_scale: jax.Array


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


@partial(jax.tree_util.register_dataclass,
         data_fields=["system", "kappa", "observation", "mass", "supervised"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class LearnedInverse:
    """The fixed physics of a learned source inversion (a pytree: a jit argument).

    ``observation`` gives ``B`` and ``W`` (its data is not used: each sample has its own);
    ``mass`` is the nodal mass matrix (source errors and the supervised term);
    ``supervised`` is the weight ``beta`` of the supervised term (0: observations only).
    """

    system: LinearSystem
    kappa: jax.Array
    observation: Observation
    mass: SparseMatrix
    supervised: jax.Array

    def misfit(self, f: jax.Array, d: jax.Array, solver) -> tuple[jax.Array, jax.Array]:
        """``1/2 ||B u(f) - d||_W^2`` with ``u`` from ``solver``, and its iteration count."""
        sol = self.system.solve(self.kappa, f, solver)
        r = matvec(self.observation.operator, self.system.expand(sol.x)) - d
        return 0.5 * jnp.vdot(r, matvec(self.observation.weight, r)), sol.iterations

    def source_error(self, f: jax.Array, truth: jax.Array) -> jax.Array:
        """Relative L2 error ``||f - f*||_M / ||f*||_M``."""
        e = f - truth
        return jnp.sqrt(jnp.vdot(e, matvec(self.mass, e))
                        / jnp.maximum(jnp.vdot(truth, matvec(self.mass, truth)), 1e-300))


def learned_inverse(disc: Discretization, observation: Observation, *, kappa=1.0,
                    supervised: float = 0.0) -> LearnedInverse:
    """A :class:`LearnedInverse` on ``disc`` with coefficient ``kappa`` (checked here)."""
    if not (math.isfinite(supervised) and supervised >= 0):
        raise SolverConfigError(f"supervised={supervised!r}: expected a finite number >= 0")
    if observation.operator.shape[1] != disc.n_dofs:
        raise ShapeError(f"observation: operator acts on {observation.operator.shape[1]} "
                         f"dofs, expected {disc.n_dofs} (built on another discretisation?)")
    kappa = jnp.asarray(disc.check_kappa(kappa, "kappa"))
    return LearnedInverse(disc.system, kappa, observation,
                          SparseMatrix.from_scipy(disc.mass_matrix),
                          jnp.asarray(float(supervised)))


def batch_loss(network: Network, problem: LearnedInverse, batch: SourceSamples,
               solver) -> tuple[jax.Array, jax.Array]:
    """The training loss over ``batch`` (solves batched with ``vmap``) and the CG
    iterations its forward solves ran."""

    def one(f_true, d):
        f = mlp_apply(network, d)
        misfit, iterations = problem.misfit(f, d, solver)
        e = f - f_true
        return misfit + problem.supervised * 0.5 * jnp.vdot(e, matvec(problem.mass, e)), \
            iterations

    losses, iterations = jax.vmap(one)(batch.sources, batch.observations)
    return jnp.mean(losses), jnp.sum(iterations)


def validation(network: Network, problem: LearnedInverse, samples: SourceSamples,
               rtol: float = 1e-10, preconditioner: Any = "jacobi"):
    """Mean observation misfit of held-out samples with a *converged* solve, and the mean
    relative source error (jit it: ``rtol`` is the only static choice)."""
    solver = _solver("implicit", True, 100_000, 100_000, rtol, preconditioner)

    def one(f_true, d):
        f = mlp_apply(network, d)
        return problem.misfit(f, d, solver)[0], problem.source_error(f, f_true)

    misfits, errors = jax.vmap(one)(samples.sources, samples.observations)
    return jnp.mean(misfits), jnp.mean(errors)


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


class Training(NamedTuple):
    network: Network
    refinement: RefinementState
    records: list[EpochRecord]


def _make_step(optimizer, gradient: str, tolerance_mode: bool, preconditioner):
    def step(network, opt_state, problem, batch, K, K_adj, rtol):
        solver = _solver(gradient, tolerance_mode, K, K_adj, rtol, preconditioner)
        (loss, iterations), grads = jax.value_and_grad(batch_loss, has_aux=True)(
            network, problem, batch, solver)
        # only the weights train; the scales stay as set
        grads = grads._replace(input_scale=jnp.zeros(()), output_scale=jnp.zeros(()))
        updates, opt_state = optimizer.update(grads, opt_state, network)
        return optax.apply_updates(network, updates), opt_state, loss, iterations, \
            optax.tree.norm(grads)

    return step


def train(problem: LearnedInverse, network: Network, train_set: SourceSamples,
          validation_set: SourceSamples, *, optimizer: optax.GradientTransformation | None = None,
          refinement: Refinement | None = None, epochs: int = 50, batch_size: int = 16,
          gradient: str = "implicit", preconditioner: Any = "jacobi", seed: int = 0,
          validation_rtol: float = 1e-10) -> Training:
    """Train ``network`` for ``epochs`` epochs of shuffled mini-batches (``seed``) while
    ``refinement`` (default :func:`~prdp_fem.prdp.prdp` with ``K0=5, dK=5``) picks the CG
    iterations once per epoch from the validation misfit.

    Raises :class:`~prdp_fem.errors.SolverConfigError` for bad options and
    :class:`~prdp_fem.inverse.InversionError` when a step produces a non-finite loss or
    gradient.
    """
    from .inverse import InversionError

    if gradient not in ("implicit", "unrolled"):
        raise SolverConfigError(f"gradient={gradient!r}: expected 'implicit' or 'unrolled'")
    for name, value in (("epochs", epochs), ("batch_size", batch_size)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise SolverConfigError(f"{name}={value!r}: expected an integer >= 1")
    n = int(train_set.sources.shape[0])
    if batch_size > n:
        raise SolverConfigError(f"batch_size={batch_size}: expected at most the {n} training "
                                "samples")
    refinement = prdp(K0=5, dK=5) if refinement is None else refinement
    if refinement.tolerance_mode and gradient == "unrolled":
        raise SolverConfigError("a tolerance-mode controller needs gradient='implicit'")
    optimizer = optax.adam(1e-3) if optimizer is None else optimizer
    step = jax.jit(_make_step(optimizer, gradient, refinement.tolerance_mode, preconditioner),
                   static_argnums=(4,) if gradient == "unrolled" else ())
    validate = jax.jit(partial(validation, rtol=validation_rtol,
                               preconditioner=preconditioner))
    update_control = jax.jit(refinement.update)  # one dispatch per epoch, not dozens
    compiled: set = set()
    opt_state, control = optimizer.init(network), refinement.init()
    rng = np.random.default_rng(seed)
    records, run_time, primal = [], 0.0, 0
    for epoch in range(1, epochs + 1):
        K = int(control.iterations) if gradient == "unrolled" else control.iterations
        K_adj, rtol = control.adjoint_iterations, control.rtol
        order = rng.permutation(n)
        batches = [order[i:i + batch_size] for i in range(0, n - batch_size + 1, batch_size)]
        losses = []
        for index in batches:
            batch = train_set.take(index)
            key = K if gradient == "unrolled" else None
            if key not in compiled:  # compile outside the timed region: twice, since the
                # optimiser state returned by a step may differ in weak types from init's
                warm = step(network, opt_state, problem, batch, K, K_adj, rtol)
                jax.block_until_ready(step(*warm[:2], problem, batch, K, K_adj, rtol))
                compiled.add(key)
            start = time.perf_counter()
            network, opt_state, loss, iterations, grad_norm = jax.block_until_ready(
                step(network, opt_state, problem, batch, K, K_adj, rtol))
            run_time += time.perf_counter() - start
            if not (math.isfinite(float(loss)) and math.isfinite(float(grad_norm))):
                raise InversionError(
                    f"epoch {epoch}: non-finite loss or gradient (loss {float(loss)!r}, K="
                    f"{int(control.iterations)}, rtol={float(rtol)!r}); try a smaller "
                    "learning rate or more CG iterations")
            losses.append(float(loss))
            primal += int(iterations)
        if epoch == 1:  # compile outside the timed region
            jax.block_until_ready(update_control(control, validate(network, problem,
                                                                   validation_set)[0]))
        start = time.perf_counter()
        misfit, error = validate(network, problem, validation_set)
        previous = control
        control = jax.block_until_ready(update_control(control, misfit))
        run_time += time.perf_counter() - start
        records.append(EpochRecord(epoch, int(previous.iterations),
                                   int(previous.adjoint_iterations), float(previous.rtol),
                                   primal, run_time, float(np.mean(losses)), float(misfit),
                                   float(error)))
    return Training(network, control, records)


def training_saving(records: list[EpochRecord], converged: list[EpochRecord], *,
                    band: float = 0.01, metric: str = "validation_misfit") -> dict:
    """PRDP's saving against converged training: the run time (and CG iterations) at which
    ``records`` first reach the converged run's final ``metric`` within ``band`` (relative)
    or below it, over the converged run's total. ``None`` fields when it never does."""
    if metric not in ("validation_misfit", "validation_error"):
        raise SolverConfigError(f"metric={metric!r}: expected 'validation_misfit' or "
                                "'validation_error'")
    target = getattr(converged[-1], metric) * (1 + band)
    hit = next((r for r in records if getattr(r, metric) <= target), None)
    base = converged[-1]
    if hit is None:
        return {"epoch": None, "time_saving": None, "iteration_saving": None,
                "target": target}
    return {"epoch": hit.epoch, "time_saving": 1 - hit.time / base.time,
            "iteration_saving": 1 - hit.primal_iterations / base.primal_iterations,
            "target": target}
