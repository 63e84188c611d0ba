"""``prdp-fem forward``: truncated-PCG error against K and run time."""

from __future__ import annotations

import json

from ..errors import SolverConfigError

DEFAULT_ITERATIONS = [0, 5, 10, 20, 40, 80, 160, 320, 640]


def forward_command(args) -> None:
    from ..studies.forward import build_scene, forward_convergence

    if any(k < 0 for k in args.iterations):
        raise SolverConfigError(f"--iterations {args.iterations}: expected integers >= 0")
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
            from .._atomic import output_error

            try:
                with args.out.open("a") as stream:  # one line per record, as it lands
                    stream.write(json.dumps({"source": source, **record._asdict()}) + "\n")
            except OSError as error:  # a full disk: name the file
                raise output_error(args.out, error) from error

    study = forward_convergence(scene, args.iterations, preconditioner=args.preconditioner,
                                on_record=emit)
    print(f"setup {study.setup_time_s:.2f} s (assembly + reference), "
          f"first-solve compile {study.compile_time_s:.2f} s")
