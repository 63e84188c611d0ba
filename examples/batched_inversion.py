"""Batched inversion: many noise draws of one source problem in one program, against a loop.

The mother problem's state observed in full with 1 % noise, one seed per member (P1 on an
n x n mesh, L2 regulariser, alpha = 1e-6), 20 L-BFGS steps each under its own PRDP
controller: one `invert_batch` call per mode (`vmap`: the members together; `map`: in turn
inside the one program) and a loop of `invert` calls, each timed warm.

    python examples/batched_inversion.py [members] [n]
"""

import sys
import time

import numpy as np

from prdp_fem.bench.batch import noise_batch
from prdp_fem.inverse import invert, invert_batch, prdp

STEPS = 20


def run(members: int = 16, n: int = 16) -> dict:
    problems = noise_batch(n, members)
    refinement = prdp()
    calls = {mode: lambda mode=mode: invert_batch(problems, refinement=refinement,
                                                  steps=STEPS, mode=mode)
             for mode in ("vmap", "map")}
    calls["loop"] = lambda: [invert(p, refinement=refinement, steps=STEPS) for p in problems]
    results, seconds = {}, {}
    for name, call in calls.items():
        call()  # compiles (untimed)
        start = time.perf_counter()
        results[name] = call()
        seconds[name] = time.perf_counter() - start
    loop_errors = np.array([r.history[-1].parameter_error for r in results["loop"]])
    errors = {mode: np.array([h[-1].parameter_error for h in results[mode].histories])
              for mode in ("vmap", "map")}
    return {"members": members, "seconds": seconds, "loop_errors": loop_errors,
            "errors": errors, "schedules": [[r.iterations for r in h]
                                            for h in results["vmap"].histories]}


def main(argv=()):
    members = int(argv[0]) if argv else 16
    n = int(argv[1]) if len(argv) > 1 else 16
    result = run(members, n)
    print(f"{members} noise draws on a {n} x {n} mesh, {STEPS} L-BFGS steps, PRDP per member")
    for name, seconds in result["seconds"].items():
        print(f"  {name:>4}: {seconds:7.3f} s, {members / seconds:7.1f} problems/s")
    for mode, errors in result["errors"].items():
        gap = np.max(np.abs(errors - result["loop_errors"]) / result["loop_errors"])
        print(f"  {mode}: parameter errors {errors.min():.4g} .. {errors.max():.4g}, "
              f"largest relative gap to the loop's {gap:.1e}")
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
