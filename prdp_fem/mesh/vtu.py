"""Fields on the mesh as VTU files (ParaView), written atomically.

A time series is a ParaView collection (``.pvd``) of such files, one per time
(:func:`write_pvd`).

A field is given by the space it lives in: ``"nodal"`` (the solution space: P1/Q1 values at
the vertices; of P2/Q2 the vertex values, which skfem numbers first), ``"P1"`` (vertex values)
or ``"P0"`` (one value per cell).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import skfem

from .._atomic import atomic_path
from ..errors import DiscretizationError, ShapeError
from .io import HEX_SKFEM_TO_MESHIO, meshio_cell_type

__all__ = ["write_pvd", "write_vtu"]


def write_vtu(mesh: skfem.Mesh, path: str | Path,
              fields: Mapping[str, tuple[str, np.ndarray]]) -> Path:
    """Write ``{name: (space, values)}`` on ``mesh`` to ``path`` (``.vtu``), atomically."""
    path = Path(path)
    n_vertices, n_cells = mesh.p.shape[1], mesh.t.shape[1]
    point_data, cell_data = {}, {}
    for name, (space, values) in fields.items():
        values = np.asarray(values, dtype=float)
        if space == "P0":
            if values.shape != (n_cells,):
                raise ShapeError(f"field {name!r}: expected {n_cells} cell values, got "
                                   f"{values.shape}")
            cell_data[name] = [values]
        elif space in ("P1", "nodal"):
            if values.ndim != 1 or len(values) < n_vertices:
                raise ShapeError(f"field {name!r}: expected at least {n_vertices} nodal "
                                   f"values, got {values.shape}")
            point_data[name] = values[:n_vertices]  # vertex dofs come first in skfem
        else:
            raise DiscretizationError(f"field {name!r}: space {space!r}, expected 'nodal', "
                                      "'P1' or 'P0'")
    cell_type = meshio_cell_type(mesh)
    cells = mesh.t.T
    if cell_type == "hexahedron":
        cells = cells[:, HEX_SKFEM_TO_MESHIO]
    points = mesh.p.T
    if points.shape[1] == 2:
        points = np.column_stack([points, np.zeros(n_vertices)])
    import meshio  # here: see prdp_fem.mesh.io

    out = meshio.Mesh(points, [(cell_type, cells.astype(np.int64))], point_data=point_data,
                      cell_data=cell_data)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        meshio.write(tmp, out, file_format="vtu")
    return path


def write_pvd(path: str | Path, steps: list[tuple[float, str | Path]]) -> Path:
    """A ParaView collection at ``path`` (``.pvd``) of ``(time, VTU file)`` pairs: the files
    are named relative to ``path``'s directory, so the series moves with its folder."""
    import os
    from xml.sax.saxutils import quoteattr

    path = Path(path)
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             "  <Collection>"]
    for time, file in steps:
        relative = Path(os.path.relpath(Path(file).absolute(), path.absolute().parent))
        lines.append(f'    <DataSet timestep="{float(time)!r}" group="" part="0" '
                     f"file={quoteattr(relative.as_posix())}/>")
    lines += ["  </Collection>", "</VTKFile>", ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines))
    return path
