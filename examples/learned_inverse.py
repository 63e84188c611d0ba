"""Learned source inversion: an MLP maps full-field observations to the source, trained through
truncated Jacobi-PCG solves, PRDP against converged training.

    -lap u = f in (0,1)^2, u = 0 on the boundary;  d = u(f) + 1 % noise;  N_theta: d -> f

Seeded smooth sources (three Gaussian bumps each), 128 training and 32 validation samples, an
MLP [n_dofs, 64, n_dofs], Adam with a cosine-decayed step (3e-3 to 0), mini-batches of 16, loss
= observation misfit through the solver + 1e-2 x supervised source misfit. PRDP (K0 = 2,
dK = 2) watches the validation misfit (converged solves) once per epoch; the baseline trains
with converged solves (rtol 1e-10).

    python examples/learned_inverse.py [n] [epochs]
"""

import sys
import time

import jax
import numpy as np
import optax

import prdp_fem as pf
from prdp_fem.inverse import converged, prdp
from prdp_fem.learning import learned


def build(n: int, n_train: int = 128, n_validation: int = 32, seed: int = 0):
    """The problem, the training and validation sets and an untrained network."""
    disc = pf.discretize(pf.unit_square(n), element="P1", kappa_space="P0", dirichlet=0.0)
    problem = learned.learned_inverse(disc, pf.full_field(disc, data=np.zeros(disc.n_dofs)),
                                      supervised=1e-2)
    sources = learned.random_sources(disc, n_train + n_validation, seed=seed, width=0.2)
    samples = learned.source_samples(problem, sources, noise=0.01, seed=seed + 1)
    train_set = samples.take(np.arange(n_train))
    validation_set = samples.take(np.arange(n_train, n_train + n_validation))
    network = learned.mlp_init(
        jax.random.PRNGKey(seed), [disc.n_dofs, 64, disc.n_dofs],
        input_scale=float(np.std(np.asarray(train_set.observations))),
        output_scale=float(np.std(sources)))
    return problem, train_set, validation_set, network


def run(n: int = 24, epochs: int = 80) -> dict:
    """Train with PRDP and with converged solves from the same start; the records and the
    saving (time and CG iterations to the converged run's final validation misfit)."""
    problem, train_set, validation_set, network = build(n)
    batches_per_epoch = train_set.sources.shape[0] // 16
    results = {}
    for name, refinement in (("converged", converged(1e-10)), ("prdp", prdp(K0=2, dK=2))):
        optimizer = optax.adam(optax.cosine_decay_schedule(3e-3, epochs * batches_per_epoch))
        start = time.perf_counter()
        training = learned.train(problem, network, train_set, validation_set,
                                 optimizer=optimizer, refinement=refinement, epochs=epochs,
                                 batch_size=16)
        results[name] = training.records
        results[name + "_wall"] = time.perf_counter() - start
    results["saving"] = learned.training_saving(results["prdp"], results["converged"])
    return results


def _print(results: dict) -> None:
    print(f"{'run':>10} {'epoch':>6} {'K':>4} {'CG its':>9} {'time [s]':>9} "
          f"{'val misfit':>11} {'source err':>11}")
    for name in ("converged", "prdp"):
        records = results[name]
        for r in records[:: max(len(records) // 8, 1)] + records[-1:]:
            K = "conv" if r.rtol > 0 else str(r.iterations)
            print(f"{name:>10} {r.epoch:>6} {K:>4} {r.primal_iterations:>9} {r.time:>9.3f} "
                  f"{r.validation_misfit:>11.3e} {r.validation_error:>11.4f}")
    print("saving:", {k: (float(f"{v:.3g}") if isinstance(v, float) else v)
                      for k, v in results["saving"].items()})


if __name__ == "__main__":
    args = [int(a) for a in sys.argv[1:3]]
    _print(run(*args))
