"""``prdp-fem mesh-info``: cells, quality, tags and problems of a mesh file."""

from __future__ import annotations

from ._shared import format_cell


def mesh_info_command(args) -> None:
    import warnings

    from ..errors import MeshError, MeshRepairWarning
    from ..mesh.io import load_mesh, mesh_quality

    problems = []
    try:
        mesh = load_mesh(args.path)
    except MeshError as error:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", MeshRepairWarning)
            try:
                mesh = load_mesh(args.path, repair=True)
            except MeshError:
                raise error from None
        problems.append(f"{error.problem} (repairable: load_mesh(repair=True) or "
                        "mesh.repair = true in a scene)")
        problems += [str(w.message) for w in caught]
    quality = mesh_quality(mesh)
    print(f"{args.path}")
    for field, value in quality._asdict().items():
        print(f"{field:>14}: {format_cell(value) if isinstance(value, float) else value}")
    for kind, groups in (("boundary", mesh.boundaries), ("subdomain", mesh.subdomains)):
        for name, members in (groups or {}).items():
            print(f"{kind:>14}: {name} ({len(members)})")
    if not mesh.boundaries:
        problems.append("no tagged boundaries: Dirichlet data can only be given for the "
                        "whole boundary")
    if quality.quality_min < 0.1:
        problems.append(f"poorly shaped cells: minimum quality {quality.quality_min:.3g} "
                        "(1 = equilateral); expect slow CG convergence")
    if quality.h_max / quality.h_min > 100:
        problems.append(f"strongly graded: longest / shortest edge = "
                        f"{quality.h_max / quality.h_min:.3g}")
    print(f"{'problems':>14}: {'none found' if not problems else len(problems)}")
    for problem in problems:
        print(f"{'':>14}  - {problem}")
    if quality.n_inverted:
        print(f"{'note':>14}: {quality.n_inverted} cells numbered clockwise (valid as they are)")
