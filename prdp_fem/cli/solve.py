"""``prdp-fem solve``: a forward solve of a scene or a bare mesh file, written as VTU."""

from __future__ import annotations

from pathlib import Path

from ..errors import SolverConfigError

MESH_SUFFIXES = (".msh", ".vtu", ".vtk", ".xdmf", ".xmf", ".mesh", ".med", ".inp", ".obj",
                 ".ply", ".stl", ".off", ".dat", ".su2", ".avs", ".f3grid", ".h5m", ".ugrid")


def _is_mesh_file(text: str) -> bool:
    return Path(text).suffix.lower() in MESH_SUFFIXES


def solve_command(args) -> None:
    from ..mesh.vtu import write_vtu
    from ..scene.build import forward_solve
    from ..scene.spec import load_scene, mesh_scene, with_overrides

    scene = mesh_scene(args.input) if _is_mesh_file(args.input) else load_scene(args.input)
    if args.iterations is not None:
        if args.iterations < 0:
            raise SolverConfigError(f"--iterations {args.iterations}: expected an integer >= 0")
        scene = with_overrides(scene, {"solver": {"iterations": [args.iterations]}})
    result = forward_solve(scene, reference=args.reference)
    out = args.out or Path(f"{scene.name}-solution.vtu")
    write_vtu(result.disc.mesh, out, {"u": ("nodal", result.u),
                                      "kappa": (scene.pde.kappa_space, result.kappa)})
    sol = result.solution
    print(f"{scene.name}: {result.disc.n_free} free dofs, {scene.pde.element}, "
          f"{scene.solver.preconditioner}-PCG {int(sol.iterations)} iterations, residual "
          f"{float(sol.residual_norm):.3e} (initial {float(sol.initial_residual_norm):.3e}), "
          f"{result.solve_time:.4f} s")
    if args.reference and result.reference_failure:
        print(f"reference: {result.reference_failure}; no error against it to report")
    elif args.reference:
        print(f"relative l2 error against pyamg (rtol 1e-12): {result.relative_error:.3e}")
    print(f"wrote {out}")
