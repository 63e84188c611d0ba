"""The heat hybrid: a network corrects a coarse implicit-Euler solver (or replaces it), trained
with ONE, NOG and WIG over a 3-step unroll, PRDP on the inner PCG solves.

    u_t = lap u in (0,1)^2, u = 0 on the boundary;  P1 on an n x n mesh
    reference (fine): 4 implicit-Euler substeps of dt/4 per step, sparse LU
    coarse solver S_K: one implicit-Euler step of dt, K Jacobi-PCG iterations from u_n
    correction: u_{n+1} = S_K(u_n) + N(S_K(u_n));   prediction: u_{n+1} = u_n + N(u_n)

Seeded smooth initial fields (three positive Gaussian bumps each), trajectories of 10 steps of
dt = 0.02: 32 for training (windows of unroll + 1 states: 8 per trajectory), 8 for validation
(the PRDP signal), 8 held out for the table. An MLP [n_free, hidden, n_free] applied
homogeneously (see prdp_fem.learning.heat), Adam with a cosine-decayed step (3e-3 to 0),
mini-batches of
16 windows. Every correction run trains with PRDP in tolerance mode (see refinement()) and
with converged solves (rtol 1e-10); the saving compares the two. Table errors: rollouts
of the held-out trajectories from u*_0 over all 10 steps, with converged coarse solves, mean of
||u_n - u*_n||_M / ||u*_n||_M over trajectories and steps; "(final)" rolls out with the
inner solves the run ended with (PRDP's last rtol) instead.

    python examples/heat_hybrid.py [n] [epochs]
"""

import sys
import time

import jax
import numpy as np
import optax

import prdp_fem as pf
from prdp_fem.inverse import converged, prdp
from prdp_fem.learning import heat, learned

# the hybrid's two setups (the mixed one, an emulator trained through the solver, is WIG only:
# examples/scenes/heat_emulator_mixed.toml)
ROWS = tuple((setup, mode) for setup in ("correction", "prediction") for mode in heat.MODES)


def build(n: int, *, dt: float = 0.02, steps: int = 10, n_train: int = 32,
          n_validation: int = 8, n_test: int = 8, seed: int = 0):
    """The coarse problem and the train / validation / test trajectories (fine solver)."""
    disc = pf.discretize(pf.unit_square(n), element="P1", dirichlet=0.0)
    problem = heat.heat_problem(disc, dt)
    total = n_train + n_validation + n_test
    initial = heat.random_initial_states(disc, total, seed=seed, width=0.2)
    trajectories = heat.reference_trajectories(disc, initial, dt=dt, steps=steps, substeps=4)
    split = np.cumsum([n_train, n_validation])
    return (problem, trajectories.take(np.arange(split[0])),
            trajectories.take(np.arange(split[0], split[1])),
            trajectories.take(np.arange(split[1], total)))


def refinement():
    """PRDP in tolerance mode: the inner solves stop at ||r|| <= rtol ||b||, rtol starting at
    1e-2 and divided by 10 at each refinement, down to the converged run's 1e-10. (Counting
    iterations instead, K0 = 1, dK = 1 refines too slowly here: K = 12 after 150 epochs, and the
    validation error, taken with converged solves, is 4.7x the converged run's.)"""
    return prdp(rtol=1e-2, rtol_factor=0.1, rtol_min=1e-10)


def run(n: int = 10, epochs: int = 150, *, hidden: int = 128, unroll: int = 3,
        rows=ROWS, converged_modes=heat.MODES, n_train: int = 32,
        batch_size: int = 16) -> dict:
    """Train every (setup, mode) of ``rows`` from one start per setup: correction runs with
    PRDP and, for the modes in ``converged_modes``, with converged solves too. The held-out
    table and PRDP's saving against converged training."""
    problem, train_set, validation_set, test_set = build(n, n_train=n_train)
    n_windows = train_set.states.shape[0] * (train_set.steps - unroll + 1)
    exact = pf.ConvergedCG(rtol=1e-10)
    evaluate = jax.jit(lambda net, rtol, setup: heat.rollout_error(
        net, problem, test_set, pf.ConvergedCG(rtol=rtol, max_iterations=100_000),
        setup=setup)[0], static_argnums=2)
    results = {"n_free": problem.n_free,
               "coarse_alone": float(heat.rollout_error(None, problem, test_set, exact)[0]),
               "rows": {}, "records": {}, "saving": {}}
    jobs = []
    for setup, mode in rows:
        jobs.append((setup, mode, "prdp" if setup == "correction" else "none"))
        if setup == "correction" and mode in converged_modes:
            jobs.append((setup, mode, "converged"))
    for setup, mode, control in jobs:
        optimizer = optax.adam(optax.cosine_decay_schedule(
            3e-3, epochs * (n_windows // batch_size)))
        start = time.perf_counter()
        training = heat.train(problem, heat.initial_network(problem, train_set, setup,
                                                             (hidden,)), train_set,
                              validation_set, setup=setup, mode=mode, unroll=unroll,
                              optimizer=optimizer,
                              refinement=converged(1e-10) if control == "converged"
                              else refinement(),
                              epochs=epochs, batch_size=batch_size)
        wall = time.perf_counter() - start
        last = training.records[-1]
        final = max(last.rtol, 1e-10)  # the inner solves training ended with
        results["records"][setup, mode, control] = training.records
        results["rows"][setup, mode, control] = {
            "test_error": float(evaluate(training.network, 1e-10, setup)),
            "test_error_final_solver": float(evaluate(training.network, final, setup)),
            "validation_error": last.validation_error, "final_rtol": last.rtol,
            # every CG iteration that ran: forward, adjoint (WIG) and the validation rollouts
            "cg_iterations": last.primal_iterations + last.adjoint_iterations_total
            + last.validation_iterations, "time": last.time, "wall": wall}
    for setup, mode, control in jobs:
        if control != "converged":
            continue
        ours, base = (results["rows"][setup, mode, c] for c in ("prdp", "converged"))
        saving = learned.training_saving(results["records"][setup, mode, "prdp"],
                                         results["records"][setup, mode, "converged"],
                                         band=0.05, metric="validation_error")
        saving["equal_epochs"] = {
            "iterations": ours["cg_iterations"] / base["cg_iterations"],
            "time": ours["time"] / base["time"],
            "test_error": ours["test_error"] / base["test_error"]}
        results["saving"][mode] = saving
    return results


def _print(results: dict) -> None:
    print(f"n_free = {results['n_free']}; coarse solver alone (converged solves): held-out "
          f"rollout error {results['coarse_alone']:.4f}")
    print(f"{'setup':>10} {'mode':>4} {'training':>9} {'test err':>9} {'(final)':>9} "
          f"{'val err':>8} {'rtol end':>8} {'CG its':>8} {'time [s]':>8} {'wall [s]':>8}")
    for (setup, mode, control), row in results["rows"].items():
        rtol = "-" if control == "none" else f"{row['final_rtol']:.0e}"
        print(f"{setup:>10} {mode:>4} {control:>9} {row['test_error']:>9.4f} "
              f"{row['test_error_final_solver']:>9.4f} {row['validation_error']:>8.4f} "
              f"{rtol:>8} {row['cg_iterations']:>8} {row['time']:>8.2f} {row['wall']:>8.1f}")
    for mode, saving in results["saving"].items():
        equal = saving.pop("equal_epochs")
        print(f"saving (correction, {mode}):",
              {k: (float(f"{v:.3g}") if isinstance(v, float) else v) for k, v in saving.items()},
              "equal epochs, PRDP / converged:",
              {k: float(f"{v:.3g}") for k, v in equal.items()})


if __name__ == "__main__":
    args = [int(a) for a in sys.argv[1:3]]
    _print(run(*args))
