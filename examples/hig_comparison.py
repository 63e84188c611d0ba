"""Adam, L-BFGS, gradient descent, Gauss-Newton and half-inverse gradients on one problem.

The built-in ``inclusion`` scene (hIPPYlib's coefficient problem: log-kappa in P1 from the noisy
full P2 state, H1 regularisation with gamma = 1e-8) on an n x n mesh, ``steps`` optimiser steps
from m = 0, with a converged solver (rtol 1e-10) and with a truncated one (K = K_adj = 10).

* Adam: learning rate from {0.03, 0.1, 0.3}; L-BFGS: optax's, with its zoom line search;
* gradient descent (p = +1), Gauss-Newton (p = -1) and HIG (p = -1/2): :func:`prdp_fem.optim.hig`
  with ``tau = 1e-6``; GD and HIG with ``relative=True`` and ``eta`` from {0.3, 1} (``eta = 1``:
  the full Gauss-Newton step along the top singular direction), Gauss-Newton with ``eta = 1``.

A grid's best run by final parameter error is reported (the same tuning for every method that
has a grid). All three SVD methods pay for an explicit Jacobian: the misfit block has more
rows (observed dofs) than columns (parameters), so it is taken in forward mode, one tangent
solve per parameter, and a step costs about ``n_parameters`` solves -- the point of the table is
what a step buys, and what it costs here. Times exclude compilation and were taken on a shared
machine (noisy); the CG iteration count (primal + adjoint, batched Jacobian solves included) is
the stable measure.

    python examples/hig_comparison.py [n] [steps]
"""

import sys
import time

import jax.numpy as jnp
import optax

from prdp_fem.inverse import converged, fixed, invert
from prdp_fem.optim import hig
from prdp_fem.scene import build, load_scene
from prdp_fem.scene.spec import with_overrides

METHODS = ("adam", "lbfgs", "gradient descent", "gauss-newton", "hig")
SOLVERS = {"converged": lambda: converged(1e-10), "K=10": lambda: fixed(10)}
ADAM_RATES = (0.03, 0.1, 0.3)
RELATIVE_RATES = (0.3, 1.0)


def build_problem(n: int = 12):
    """The inclusion scene on an n x n mesh, with the residual factors HIG needs."""
    scene = with_overrides(load_scene("inclusion"), {"mesh": {"n": n}})
    return build.build_inverse(scene).problem.with_residual()


def candidates(method: str) -> dict[str, optax.GradientTransformation | None]:
    """The optimisers tried for ``method``, by their learning-rate label."""
    if method == "adam":
        return {f"{lr:g}": optax.adam(lr) for lr in ADAM_RATES}
    if method == "lbfgs":
        return {"-": None}
    if method == "gauss-newton":
        return {"1": hig(1.0, exponent=-1.0)}
    exponent = 1.0 if method == "gradient descent" else -0.5
    return {f"{lr:g} rel": hig(lr, exponent, relative=True) for lr in RELATIVE_RATES}


def main(n: int = 12, steps: int = 20, methods=METHODS, solvers=tuple(SOLVERS)) -> dict:
    """Run every method with every solver; returns ``{(method, solver): row}``."""
    problem = build_problem(n)
    start_error = float(problem.parameter_error(jnp.zeros(problem.n_parameters)))
    rows = {}
    for solver in solvers:
        for method in methods:
            best = None
            for label, optimizer in candidates(method).items():
                tic = time.perf_counter()
                run = invert(problem, optimizer=optimizer, refinement=SOLVERS[solver](),
                             steps=steps)
                last = run.history[-1]
                row = dict(method=method, solver=solver, rate=label,
                           error=last.parameter_error, time=last.time,
                           compile=last.compile_time, wall=time.perf_counter() - tic,
                           iterations=last.primal_iterations + last.adjoint_iterations_total,
                           errors=[r.parameter_error for r in run.history])
                if best is None or row["error"] < best["error"]:
                    best = row
            rows[(method, solver)] = best
    return dict(rows=rows, n_parameters=problem.n_parameters,
                n_observations=problem.observation.size, start_error=start_error, steps=steps)


def format_rows(result: dict) -> str:
    lines = [f"inclusion scene, {result['n_parameters']} parameters, "
             f"{result['n_observations']} observations, {result['steps']} steps from error "
             f"{result['start_error']:.3f}",
             f"{'method':<17} {'solver':<10} {'eta':>8} {'error@5':>8} {'error':>8} "
             f"{'time s':>8} {'CG its':>10}"]
    for row in result["rows"].values():
        early = row["errors"][min(5, len(row["errors"])) - 1]
        lines.append(f"{row['method']:<17} {row['solver']:<10} {row['rate']:>8} "
                     f"{early:>8.4f} {row['error']:>8.4f} {row['time']:>8.2f} "
                     f"{row['iterations']:>10d}")
    return "\n".join(lines)


if __name__ == "__main__":
    arguments = [int(a) for a in sys.argv[1:3]]
    print(format_rows(main(*arguments)))
