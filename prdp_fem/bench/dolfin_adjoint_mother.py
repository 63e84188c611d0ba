"""The mother problem as dolfin-adjoint's users solve it: the peer side of ``bench mother``.

Run by the peer's Python (legacy FEniCS with dolfin-adjoint), not imported by the package:

    python -m prdp_fem.bench.dolfin_adjoint_mother N [TOL]

P1 state and P1 control on ``UnitSquareMesh(N, N)``, ``-lap u = f``, ``u = 0`` on the
boundary, ``J = 1/2 ||u - d||^2 + alpha/2 ||f||^2`` with ``d = sin(pi x) sin(pi y) / (2 pi^2)``
and ``alpha = 1e-6``, from ``f = 0``; ``minimize(rf, method="L-BFGS-B", tol=TOL,
options={"gtol": TOL, "factr": 0})`` (the dolfin-adjoint tutorial's settings, default
``TOL = 1e-10``), the state and adjoint solved by dolfin's default direct solver. Prints one
JSON line: the relative L2 error of ``f`` against the nodal interpolant of
``f* = sin(pi x) sin(pi y) / (1 + 4 alpha pi^4)``, the functional evaluations, and the
seconds spent importing and solving (the benchmark times the whole process itself).

How to install the peer (Debian 12; the benchmark prints this where it is missing; ``--no-deps``
keeps Debian's NumPy 1.x, which its form compiler needs)::

    apt-get install python3-dolfin python3-scipy
    python3 -m venv --system-site-packages PEER_VENV
    PEER_VENV/bin/pip install --no-deps dolfin-adjoint==2023.0.0 pyadjoint-ad==2023.0.0

then ``prdp-fem bench mother --peer-python PEER_VENV/bin/python``.
"""

from __future__ import annotations

import json
import math
import sys
import time

ALPHA = 1e-6


def main(argv: list[str]) -> None:
    start = time.perf_counter()
    n = int(argv[0])
    tol = float(argv[1]) if len(argv) > 1 else 1e-10
    import fenics as fe  # the peer's own packages: here, not at the top of the module
    import fenics_adjoint as fa

    fe.set_log_level(fe.LogLevel.ERROR)
    imported = time.perf_counter() - start
    mesh = fa.UnitSquareMesh(n, n)
    space = fe.FunctionSpace(mesh, "CG", 1)
    control = fa.Function(space, name="Control")
    state, test = fa.Function(space, name="State"), fe.TestFunction(space)
    equation = (fe.inner(fe.grad(state), fe.grad(test)) - control * test) * fe.dx
    fa.solve(equation == 0, state, fa.DirichletBC(space, 0.0, "on_boundary"))
    data = fa.Expression("sin(pi*x[0])*sin(pi*x[1])/(2*pi*pi)", degree=3)
    alpha = fa.Constant(ALPHA)
    functional = fa.assemble(0.5 * fe.inner(state - data, state - data) * fe.dx
                             + alpha / 2 * control ** 2 * fe.dx)
    reduced = fa.ReducedFunctional(functional, fa.Control(control))
    evaluations = []
    reduced.eval_cb_post = lambda *args: evaluations.append(1)
    optimum = fa.minimize(reduced, method="L-BFGS-B", tol=tol,
                          options={"gtol": tol, "factr": 0.0, "disp": False})
    solved = time.perf_counter() - start - imported
    truth = fe.interpolate(fe.Expression("sin(pi*x[0])*sin(pi*x[1])/(1 + 4*a*pi*pi*pi*pi)",
                                         a=ALPHA, degree=3), space)
    error = math.sqrt(fe.assemble((optimum - truth) ** 2 * fe.dx)
                      / fe.assemble(truth ** 2 * fe.dx))
    print(json.dumps({"n": n, "dofs": space.dim(), "error": error,
                      "evaluations": len(evaluations), "import_s": imported,
                      "solve_s": solved, "printed_at": time.time()}), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
