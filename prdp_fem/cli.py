"""The ``prdp-fem`` command.

Subcommands
-----------
``forward``   truncated-PCG error against K and run time on a built-in scene or a mesh file
``bench cg``  PCG iteration / SciPy SpMV time ratio (see :mod:`prdp_fem.bench`)
``mesh``      load and validate a mesh file, print its quality report

Bad input (a mesh file, a scene name, an option) prints one line ``prdp-fem: error: ...`` and
exits with status 2; no traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .errors import PrdpFemError

DEFAULT_ITERATIONS = [0, 5, 10, 20, 40, 80, 160, 320, 640]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="prdp-fem", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    forward = sub.add_parser("forward", help="error of truncated PCG against K and time")
    forward.add_argument("--scene", default="square", help="square | hole | lshape | cube")
    forward.add_argument("--mesh", help="a mesh file instead of a built-in scene")
    forward.add_argument("--n", type=int, default=128, help="resolution of the scene")
    forward.add_argument("--element", default="P1", help="P1 | P2 | Q1 | Q2")
    forward.add_argument("--iterations", type=int, nargs="+", default=DEFAULT_ITERATIONS,
                         metavar="K", help="the K values to run")
    forward.add_argument("--preconditioner", default="jacobi", help="jacobi | identity")
    forward.add_argument("--out", type=Path, help="append records as JSON lines here")

    bench = sub.add_parser("bench", help="benchmarks")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    cg = bench_sub.add_parser("cg", help="PCG iteration time / SciPy SpMV time")
    cg.add_argument("--sides", type=int, nargs="+", default=[256, 512],
                    help="unit-square cells per side ((n-1)^2 dofs: 256 -> 65k, 512 -> 261k)")
    cg.add_argument("--iterations", type=int, default=100)
    cg.add_argument("--repeats", type=int, default=7)

    mesh = sub.add_parser("mesh", help="validate a mesh file and print its quality report")
    mesh.add_argument("path", type=Path)
    return parser


def _forward(args) -> None:
    from .study import build_scene, forward_convergence

    if any(k < 0 for k in args.iterations):
        raise PrdpFemError(f"--iterations {args.iterations}: expected integers >= 0")
    scene = build_scene(args.scene, n=args.n, element=args.element, mesh_path=args.mesh)
    source = args.mesh or f"scene {args.scene} (n={args.n})"
    print(f"{source}: {scene.disc.n_free} free dofs, {args.element}, "
          f"{args.preconditioner}-PCG, errors against pyamg (rtol 1e-12)")
    print(f"{'K':>6} {'iters':>6} {'time [s]':>10} {'rel L2 err':>12} {'rel energy err':>15}")

    def emit(record):
        print(f"{record.requested_iterations:>6} {record.iterations:>6} "
              f"{record.wall_time_s:>10.4f} {record.relative_l2_error:>12.3e} "
              f"{record.relative_energy_error:>15.3e}", flush=True)
        if args.out is not None:
            with args.out.open("a") as stream:  # one line per record, appended as it lands
                stream.write(json.dumps({"source": source, **record._asdict()}) + "\n")

    study = forward_convergence(scene, args.iterations, preconditioner=args.preconditioner,
                                on_record=emit)
    print(f"setup {study.setup_time_s:.2f} s (assembly + reference), "
          f"first-solve compile {study.compile_time_s:.2f} s")


def _bench_cg(args) -> None:
    from .bench import cg_iteration_cost

    print(f"{'dofs':>9} {'nnz':>9} {'SpMV [ms]':>10} {'PCG it [ms]':>12} {'ratio':>7} "
          f"{'compile [s]':>12}")
    for side in args.sides:
        cost = cg_iteration_cost(side, iterations=args.iterations, repeats=args.repeats)
        print(f"{cost.n_dofs:>9} {cost.nnz:>9} {1e3 * cost.spmv_s:>10.3f} "
              f"{1e3 * cost.iteration_s:>12.3f} {cost.ratio:>7.2f} {cost.compile_s:>12.2f}",
              flush=True)


def _mesh(args) -> None:
    from .mesh import load_mesh, mesh_quality

    mesh = load_mesh(args.path)
    for field, value in mesh_quality(mesh)._asdict().items():
        print(f"{field:>14}: {value}")
    for kind, groups in (("boundary", mesh.boundaries), ("subdomain", mesh.subdomains)):
        for name, members in (groups or {}).items():
            print(f"{kind:>14}: {name} ({len(members)})")


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.command == "forward":
            _forward(args)
        elif args.command == "bench":
            _bench_cg(args)
        elif args.command == "mesh":
            _mesh(args)
    except PrdpFemError as error:
        print(f"prdp-fem: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
