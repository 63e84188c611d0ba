r"""Held-out evaluation of a trained model: test metrics and predictions on the mesh.

* :func:`evaluate_learned` -- a learned inverse's predicted sources for held-out samples, their
  relative :math:`L^2` errors :math:`\|f - f^*\|_M / \|f^*\|_M` and observation misfits
  (converged solves);
* :func:`evaluate_rollouts` -- a learned time stepper's rollouts from held-out initial states
  (converged coarse solves) and their relative error at every step, the mean of which is
  :func:`~prdp_fem.learning.heat.rollout_error`.

Each returns the arrays and :meth:`metrics` (plain numbers, for JSON);
:func:`write_source_predictions` and :func:`write_rollouts` put them on the mesh as VTU files
(a rollout as a ParaView ``.pvd`` time series).

>>> import prdp_fem as pf
>>> from prdp_fem.learning import Model, learned
>>> disc = pf.discretize(pf.unit_square(4), dirichlet=0.0)
>>> problem = learned.learned_inverse(disc, pf.full_field(disc, data=np.zeros(disc.n_dofs)))
>>> samples = learned.source_samples(problem, learned.random_sources(disc, 2), noise=0.0)
>>> exact = Model(lambda p, d: p, samples.sources[0])   # predicts sample 0's source
>>> errors = evaluate_learned(problem, exact, samples).source_errors
>>> float(errors[0]) < 1e-12 < float(errors[1])
True
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..fem.discretization import Discretization
from ..linalg.cg import ConvergedCG
from ..mesh.vtu import write_pvd, write_vtu
from .heat import HeatProblem, Trajectories, heat_step, rollout
from .learned import LearnedInverse, SourceSamples
from .model import Model

__all__ = ["LearnedEvaluation", "RolloutEvaluation", "evaluate_learned", "evaluate_rollouts",
           "write_rollouts", "write_source_predictions"]


class LearnedEvaluation(NamedTuple):
    """Per held-out sample: the predicted source ``(n, n_dofs)``, its relative L2 error and
    its observation misfit ``1/2 ||B u(f) - d||_W^2`` (converged solve)."""

    predictions: np.ndarray
    source_errors: np.ndarray
    misfits: np.ndarray

    def metrics(self) -> dict[str, Any]:
        """Mean, median and largest source error, mean misfit, the number of samples."""
        errors = self.source_errors
        return {"samples": int(errors.size), "test_error": float(np.mean(errors)),
                "median_error": float(np.median(errors)), "max_error": float(np.max(errors)),
                "test_misfit": float(np.mean(self.misfits))}


def evaluate_learned(problem: LearnedInverse, model, samples: SourceSamples, *,
                     rtol: float = 1e-10, preconditioner: Any = "jacobi") -> LearnedEvaluation:
    """``model`` (any :mod:`~prdp_fem.learning.model` model) on ``samples``: its predicted
    sources, their errors against the true ones and the misfits of converged solves."""
    solver = ConvergedCG(rtol=rtol, max_iterations=100_000, preconditioner=preconditioner)

    @jax.jit
    def predict(model, problem, samples):
        def one(f_true, d):
            f = model(d)
            return f, problem.source_error(f, f_true), problem.misfit(f, d, solver)[0]

        return jax.vmap(one)(samples.sources, samples.observations)

    predictions, errors, misfits = predict(model, problem, samples)
    return LearnedEvaluation(np.asarray(predictions), np.asarray(errors), np.asarray(misfits))


class RolloutEvaluation(NamedTuple):
    """Per held-out trajectory: the rollout ``(n, steps + 1, n_free)`` from its initial state
    and the relative error ``||u_n - u*_n||_M / ||u*_n||_M`` at steps ``1..steps``."""

    rollouts: np.ndarray
    errors: np.ndarray

    def metrics(self) -> dict[str, Any]:
        """The mean error over trajectories and steps (the rollout error), its spread over
        trajectories, the mean error at the last step and per step."""
        per_trajectory = self.errors.mean(axis=1)
        return {"trajectories": int(self.errors.shape[0]),
                "test_error": float(self.errors.mean()),
                "max_error": float(per_trajectory.max()),
                "final_step_error": float(self.errors[:, -1].mean()),
                "error_per_step": [float(e) for e in self.errors.mean(axis=0)]}


def evaluate_rollouts(problem: HeatProblem, model: Model | None, trajectories: Trajectories, *,
                      setup: str = "correction", rtol: float = 1e-10,
                      preconditioner: Any = "jacobi", step=heat_step) -> RolloutEvaluation:
    """Roll ``model`` (the ``setup`` stepper; ``None``: the coarse solver alone) out from
    each trajectory's initial state with converged coarse solves."""
    solver = ConvergedCG(rtol=rtol, max_iterations=100_000, preconditioner=preconditioner)
    truth = trajectories.states

    @jax.jit
    def roll(model, problem, truth):
        def one(states):
            predicted, _ = rollout(model, problem, states[0], states.shape[0] - 1, solver,
                                   setup=setup, step=step)
            e = predicted[1:] - states[1:]
            norm2 = jax.vmap(lambda v: jnp.vdot(v, problem.mass(v)))
            return predicted, jnp.sqrt(norm2(e) / jnp.maximum(norm2(states[1:]), 1e-300))

        return jax.vmap(one)(truth)

    rollouts, errors = roll(model, problem, truth)
    return RolloutEvaluation(np.asarray(rollouts), np.asarray(errors))


def write_source_predictions(directory: str | Path, disc: Discretization,
                             samples: SourceSamples, evaluation: LearnedEvaluation,
                             count: int) -> list[Path]:
    """The first ``count`` samples as ``sample_000.vtu``, ... in ``directory``: predicted and
    true source and their difference (nodal fields)."""
    paths = []
    for i in range(min(count, len(evaluation.source_errors))):
        truth = np.asarray(samples.sources[i])
        predicted = evaluation.predictions[i]
        paths.append(write_vtu(disc.mesh, Path(directory) / f"sample_{i:03d}.vtu", {
            "predicted": ("nodal", predicted), "true": ("nodal", truth),
            "error": ("nodal", predicted - truth)}))
    return paths


def write_rollouts(directory: str | Path, disc: Discretization, trajectories: Trajectories,
                   evaluation: RolloutEvaluation, dt: float, count: int) -> list[Path]:
    """The first ``count`` rollouts as ParaView time series ``rollout_000.pvd`` (one VTU per
    step in ``rollout_000/``) in ``directory``: predicted and reference state and their
    difference, on the whole mesh (the Dirichlet values on the boundary)."""
    directory = Path(directory)
    paths = []
    for i in range(min(count, evaluation.rollouts.shape[0])):
        name = f"rollout_{i:03d}"
        steps = []
        for n, (predicted, reference) in enumerate(zip(
                evaluation.rollouts[i], np.asarray(trajectories.states[i]), strict=True)):
            predicted, reference = _on_mesh(disc, predicted), _on_mesh(disc, reference)
            path = write_vtu(disc.mesh, directory / name / f"step_{n:04d}.vtu", {
                "predicted": ("nodal", predicted), "reference": ("nodal", reference),
                "error": ("nodal", predicted - reference)})
            steps.append((n * dt, path))
        paths.append(write_pvd(directory / f"{name}.pvd", steps))
    return paths


def _on_mesh(disc: Discretization, free_values: np.ndarray) -> np.ndarray:
    full = np.zeros(disc.n_dofs)
    full[disc.dirichlet_dofs] = disc.dirichlet_values
    full[disc.free_dofs] = free_values
    return full
