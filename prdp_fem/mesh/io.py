"""Mesh input: read any meshio format, validate it, and return a tagged scikit-fem mesh.

Supported cells: ``triangle``, ``quad`` (2-D), ``tetra``, ``hexahedron`` (3-D), all linear.
Lower-dimensional cells that are facets of the mesh (Gmsh physical curves/surfaces, Medit
references, cell sets) become named boundaries; tags on the cells become named subdomains.

Validation raises one typed :mod:`prdp_fem.errors` exception per problem, naming the file:

* missing / empty / unreadable file          -> :class:`~prdp_fem.errors.MeshFileError`
* no supported cells (or only 2nd order)     -> :class:`~prdp_fem.errors.UnsupportedCellsError`
* mixed cell types, non-facet lower cells,
  2-D cells on non-planar nodes              -> :class:`~prdp_fem.errors.MixedDimensionError`
* NaN / Inf coordinates                      -> :class:`~prdp_fem.errors.NonFiniteCoordinatesError`
* duplicate or unused nodes -> :class:`~prdp_fem.errors.DuplicateNodeError`,
  :class:`~prdp_fem.errors.UnusedNodeError`
  (``repair=True`` merges / drops them instead, with a :class:`MeshRepairWarning`)
* zero-measure cells                         -> :class:`~prdp_fem.errors.DegenerateCellError`
* coordinates beyond ``+-MAX_COORDINATE``    -> :class:`~prdp_fem.errors.CoordinateRangeError`
  (cell measures would overflow)
* a Gmsh file whose node ids run past ``max(MIN_NODE_ID_LIMIT, NODE_ID_SLACK * nodes)``, or
  that declares more nodes than its size can hold -> :class:`~prdp_fem.errors.MeshFileError`
  (the reader allocates an array as long as the largest id: a few kilobytes with ids near
  2e9 would take gigabytes); checked before the file is parsed
* inverted cells: a cell whose node order is reversed (clockwise) is kept as it is, since
  scikit-fem integrates with ``|det J|`` and its operator equals the renumbered cell's; it is
  counted in :func:`mesh_quality` (``n_inverted``). Quads/hexes whose corner Jacobians change
  sign (self-intersecting "bow-tie" or non-convex cells) cannot be repaired and raise
  :class:`~prdp_fem.errors.InvertedCellError`.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import skfem

from .._files import checked_file
from .._sorting import first_of_each, unique_with_inverse
from ..errors import (
    CoordinateRangeError,
    DegenerateCellError,
    DuplicateNodeError,
    InvertedCellError,
    MeshError,
    MeshFileError,
    MeshRepairWarning,
    MixedDimensionError,
    NonFiniteCoordinatesError,
    UnsupportedCellsError,
    UnusedNodeError,
)

if TYPE_CHECKING:
    import meshio

# meshio is imported where a file is read or written or arrays become a mesh, not here: the
# built-in meshes (prdp_fem.mesh.generators) never need it, and it took 0.04-0.06 s of every import

__all__ = [
    "MeshQuality",
    "load_mesh",
    "mesh_from_arrays",
    "mesh_quality",
    "save_mesh",
]

# meshio cell type -> (topological dimension, scikit-fem mesh class, facet cell type)
SUPPORTED_CELLS = {
    "triangle": (2, skfem.MeshTri1, "line"),
    "quad": (2, skfem.MeshQuad1, "line"),
    "tetra": (3, skfem.MeshTet1, "triangle"),
    "hexahedron": (3, skfem.MeshHex1, "quad"),
}
HIGHER_ORDER_CELLS = {"triangle6", "quad8", "quad9", "tetra10", "hexahedron20", "hexahedron27"}
# scikit-fem numbers hexahedron nodes differently from meshio/VTK
_HEX_MESHIO_TO_SKFEM = np.array([0, 4, 3, 1, 7, 5, 2, 6])
HEX_SKFEM_TO_MESHIO = np.argsort(_HEX_MESHIO_TO_SKFEM)
# the three edges leaving each hexahedron corner (meshio order), right-handed for a positive cell
_HEX_CORNER_EDGES = np.array([[1, 3, 4], [2, 0, 5], [3, 1, 6], [0, 2, 7],
                              [7, 5, 0], [4, 6, 1], [5, 7, 2], [6, 4, 3]])
# integer cell data that carry region tags, in order of preference
TAG_KEYS = ("gmsh:physical", "medit:ref", "cell_tags", "tags", "ref")
# 0/1 cell data naming one region each, as save_mesh writes them for VTK-based formats
NAMED_PREFIXES = ("boundary:", "subdomain:")
# |measure| / (longest edge)^d below this is a degenerate cell
DEGENERACY_TOL = 1e-10
# nodes closer than this times the bounding-box diameter are duplicates
DUPLICATE_TOL = 1e-12
#: The largest coordinate magnitude accepted: a cell's measure (up to its edge cubed) and the
#: stiffness and mass entries must stay finite in double precision.
MAX_COORDINATE = 1e50
#: Gmsh node ids accepted up to ``max(MIN_NODE_ID_LIMIT, NODE_ID_SLACK * number of nodes)``:
#: the reader allocates one entry per id up to the largest one.
MIN_NODE_ID_LIMIT = 10_000_000
NODE_ID_SLACK = 4


def load_mesh(path: str | Path, *, repair: bool = False) -> skfem.Mesh:
    """Read a mesh file (any meshio format), validate it and return a tagged skfem mesh.

    Parameters
    ----------
    path
        Mesh file: Gmsh ``.msh`` (2.2 / 4.1, ASCII or binary), ``.vtu``, ``.vtk``, ``.xdmf``,
        Medit ``.mesh`` and the other formats meshio reads.
    repair
        Merge duplicate nodes and drop unused ones (with a :class:`MeshRepairWarning`)
        instead of raising.

    Returns
    -------
    skfem.Mesh
        With ``mesh.boundaries`` (named facet sets) and ``mesh.subdomains`` (named cell sets)
        from the file's tags; names come from Gmsh physical names where present, else the
        tag number as a string.
    """
    import meshio

    if not isinstance(path, str | os.PathLike):
        raise MeshFileError(repr(path), f"a {type(path).__name__} given as the mesh path; "
                            "expected a file path (str or os.PathLike)")
    path = Path(path)
    size = checked_file(path, "mesh file", MeshFileError)
    if size == 0:
        raise MeshFileError(path, "file is empty; expected a mesh file")
    try:
        if _check_content(path) == "Gmsh":
            _check_gmsh_nodes(path, size)
    except OSError as exc:  # a file it may not read
        raise MeshFileError(path, f"cannot be read ({exc.strerror}); expected a readable mesh "
                            "file") from None
    # .msh is also ANSYS's suffix: meshio then tries both and exits the process on failure
    file_format = "gmsh" if path.suffix.lower() == ".msh" else None
    printed, warned = io.StringIO(), io.StringIO()
    try:
        # meshio prints its read errors (stdout) and a summary (stderr) before sys.exit(1):
        # capture them, so that the error below is the only thing a failed read says
        with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(warned):
            raw = meshio.read(path, file_format=file_format)
    except (Exception, SystemExit) as exc:  # meshio raises many types: make one clear error
        said = [line for line in printed.getvalue().splitlines() if line.strip()]
        if isinstance(exc, SystemExit):  # the reason, if meshio gave one, is what it printed
            detail = said[0] if said else f"no valid {path.suffix or 'mesh'} content"
        else:
            detail = f"{type(exc).__name__}: {exc}".strip().splitlines()[0]
        raise MeshFileError(
            path,
            f"could not be read as a mesh ({detail[:200]}); expected a complete file in a meshio "
            "format such as Gmsh .msh, .vtu, .xdmf or Medit .mesh",
        ) from exc
    mesh = _mesh_from_meshio(raw, str(path), repair=repair)  # a refusal says it alone
    sys.stdout.write(printed.getvalue())  # a successful read's notes are passed on as they were
    sys.stderr.write(warned.getvalue())
    return mesh


# (a marker near the start of the file, what the content is, the suffixes it goes with)
_SIGNATURES = (
    (b"$MeshFormat", "Gmsh", (".msh",)),
    (b"<VTKFile", "VTK XML", (".vtu",)),
    (b"# vtk DataFile", "legacy VTK", (".vtk",)),
    (b"<Xdmf", "XDMF", (".xdmf", ".xmf")),
    (b"MeshVersionFormatted", "Medit", (".mesh",)),
)
# what the last line of a complete file holds (a truncated file could otherwise load in part)
_END_MARKERS = {"Gmsh": (b"$End", "an $End... section line"), "Medit": (b"End", "End"),
                "VTK XML": (b"</VTKFile>", "</VTKFile>"), "XDMF": (b"</Xdmf>", "</Xdmf>")}


def _check_content(path: Path) -> str | None:
    """Refuse a file whose content contradicts its suffix, or that stops before its end;
    return the kind of content found (``"Gmsh"``, ``"VTK XML"``, ...) or ``None``."""
    with open(path, "rb") as stream:
        head = stream.read(4096)
        stream.seek(max(path.stat().st_size - 256, 0))
        tail = stream.read()
    suffix = path.suffix.lower()
    found = next(((kind, suffixes) for marker, kind, suffixes in _SIGNATURES if marker in head),
                 None)
    if found is None:
        if suffix == ".msh" and not head.lstrip().startswith(b"$Comments"):
            first = head.lstrip().split(b"\n", 1)[0].strip()
            raise MeshFileError(
                path, f"could not be read as a mesh: it does not start with $MeshFormat (first "
                f"line {_printable(first)}); expected a Gmsh .msh file")
        return None
    kind, suffixes = found
    if suffix not in suffixes:
        raise MeshFileError(
            path, f"could not be read as a mesh: its content is a {kind} file but its suffix is "
            f"{suffix!r}; expected the suffix to match the content (rename it to "
            f"{path.stem}{suffixes[0]})")
    if kind in _END_MARKERS:
        marker, what = _END_MARKERS[kind]
        lines = tail.rstrip().splitlines()
        last = lines[-1].strip() if lines else b""
        if marker not in last:
            raise MeshFileError(
                path, f"could not be read as a mesh: the {kind} file ends with "
                f"{_printable(last)} instead of {what}, so it is truncated; expected a complete "
                f"{kind} file")
    return kind


def _check_gmsh_nodes(path: Path, size: int) -> None:
    """Refuse a Gmsh file whose ``$Nodes`` section would make the reader allocate far more
    than the file holds: ids beyond ``max(MIN_NODE_ID_LIMIT, NODE_ID_SLACK * nodes)`` (it
    allocates one entry per id up to the largest), or more nodes declared than the file's
    size can hold. Only the node section is read; a file this scan cannot follow is left to
    the reader, which reports what is wrong with it."""
    with open(path, "rb") as stream, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # np.fromfile's "could not be read to its end"
        try:
            found = _gmsh_node_ids(stream, size)
        except (ValueError, IndexError, OverflowError, UnicodeDecodeError):
            return
    if found is None:
        return
    declared, largest = found
    if isinstance(declared, str):
        raise MeshFileError(path, f"could not be read as a mesh: $Nodes declares {declared} "
                            f"but the file holds {size} bytes; expected a node count the file "
                            "can hold (is it truncated or corrupt?)")
    limit = max(MIN_NODE_ID_LIMIT, NODE_ID_SLACK * declared)
    if largest > limit:
        raise MeshFileError(
            path, f"node ids run up to {largest} for {declared} nodes; reading them would "
            f"allocate {largest} entries; expected node ids at most {limit} "
            f"(max({MIN_NODE_ID_LIMIT}, {NODE_ID_SLACK} x the node count): renumber the nodes "
            "1..N, e.g. with Gmsh's renumbering before saving)")


def _gmsh_node_ids(stream, size: int) -> tuple[int | str, int] | None:
    """``(number of nodes, largest node id)`` of an open Gmsh file, or ``(message, 0)``
    where the declared count cannot fit in ``size`` bytes; ``None`` without a node section."""
    version, binary, data_size = None, False, 8
    while True:
        line = stream.readline()
        if not line:
            return None
        name = line.strip().decode("ascii", "replace")
        if name == "$MeshFormat":
            fields = stream.readline().split()
            version, binary, data_size = fields[0].decode(), fields[1] == b"1", int(fields[2])
        elif name == "$Nodes":
            break
    if version is None:
        return None
    integer = np.dtype(f"<u{data_size}") if data_size in (4, 8) else np.dtype("<u8")

    def read(dtype, count: int) -> np.ndarray:
        return np.fromfile(stream, dtype=dtype, count=count, sep="" if binary else " ")

    if version.startswith("2"):
        declared = int(stream.readline())
        per_node = 28 if binary else 8  # int id + 3 doubles; "1 0 0 0\n"
        if declared * per_node > size:
            return f"{declared} nodes", 0
        if binary:  # the reader requires the ids 1..n in order
            return declared, declared
        ids = read(float, 4 * declared)[::4]
        return declared, int(ids.max()) if ids.size else 0
    header = read(integer if binary else np.int64, 4)
    blocks, declared = int(header[0]), int(header[1])
    per_node = data_size + 24 if binary else 8  # tag + 3 doubles; "1\n0 0 0\n"
    if declared * per_node > size or blocks * 8 > size:
        return f"{declared} nodes in {blocks} blocks", 0
    largest = 0
    for _ in range(blocks):
        read(np.int32 if binary else np.int64, 3)  # entityDim entityTag parametric
        count = int(read(integer if binary else np.int64, 1)[0])
        if count * per_node > size:
            return f"a block of {count} nodes", 0
        tags = read(integer if binary else np.int64, count)
        largest = max(largest, int(tags.max()) if tags.size else 0)
        if binary:
            stream.seek(24 * count, os.SEEK_CUR)
        else:
            read(float, 3 * count)
    return declared, largest


def _printable(line: bytes) -> str:
    text = line[-40:].decode("ascii", "replace")
    return repr(text) if text.isprintable() else "binary data"


def mesh_from_arrays(
    points: np.ndarray,
    cells: np.ndarray,
    cell_type: str,
    *,
    facets: dict[str, np.ndarray] | None = None,
    source: str = "<array mesh>",
    repair: bool = False,
) -> skfem.Mesh:
    """Validate node/cell arrays (meshio layout: ``points`` (n, d), ``cells`` (m, k)).

    ``facets`` maps boundary names to facet node arrays (m_f, k_f) that become named boundaries.
    """
    import meshio

    blocks = [meshio.CellBlock(cell_type, np.asarray(cells))]
    cell_data: dict[str, list[np.ndarray]] = {}
    field_data: dict[str, np.ndarray] = {}
    if facets:
        facet_type = SUPPORTED_CELLS.get(cell_type, (0, None, "line"))[2]
        tags = [np.zeros(len(cells), dtype=int)]
        for number, (name, nodes) in enumerate(facets.items(), start=1):
            blocks.append(meshio.CellBlock(facet_type, np.asarray(nodes)))
            tags.append(np.full(len(nodes), number))
            field_data[name] = np.array([number, SUPPORTED_CELLS[cell_type][0] - 1])
        cell_data["gmsh:physical"] = tags
    raw = meshio.Mesh(np.asarray(points, dtype=float), blocks, cell_data=cell_data,
                      field_data=field_data)
    return _mesh_from_meshio(raw, source, repair=repair)


def save_mesh(mesh: skfem.Mesh, path: str | Path, *, file_format: str | None = None,
              binary: bool = False) -> None:
    """Write ``mesh`` with its named boundaries as tagged facet cells (any meshio format).

    Boundaries and subdomains are kept by name: ``.msh`` is written as Gmsh 2.2 with physical
    names; VTK-based formats (``.vtu``, ``.vtk``, ``.xdmf``) get an integer ``cell_tags`` array
    plus one 0/1 array per region (``boundary:NAME``, ``subdomain:NAME``); Medit keeps only
    ``medit:ref`` numbers. Numbers: boundaries ``1..nb`` in sorted order, then subdomains.
    """
    import meshio

    path = Path(path)
    cell_type = meshio_cell_type(mesh)
    dim, _, facet_type = SUPPORTED_CELLS[cell_type]
    t = mesh.t.T
    if cell_type == "hexahedron":
        t = t[:, HEX_SKFEM_TO_MESHIO]
    blocks = [meshio.CellBlock(cell_type, t.astype(np.int64))]
    boundary_names = sorted(mesh.boundaries or {})
    subdomain_names = sorted(mesh.subdomains or {})
    # numeric tags: boundaries 1..nb, subdomains nb+1..; a cell in several subdomains keeps
    # the last one (numeric tags are a partition; the named arrays below keep every set)
    cell_tag = np.zeros(len(t), dtype=np.int64)
    field_data = {}
    for number, name in enumerate(subdomain_names, start=len(boundary_names) + 1):
        cell_tag[np.asarray(mesh.subdomains[name])] = number
        field_data[name] = np.array([number, dim])
    tags = [cell_tag]
    named = {f"subdomain:{name}": [np.isin(np.arange(len(t)), mesh.subdomains[name])
                                   .astype(np.int32)] for name in subdomain_names}
    named.update({f"boundary:{name}": [np.zeros(len(t), dtype=np.int32)]
                  for name in boundary_names})
    for number, name in enumerate(boundary_names, start=1):
        facet_ids = np.asarray(mesh.boundaries[name])
        facet_nodes = mesh.facets[:, facet_ids].T
        if facet_type == "quad":
            facet_nodes = _order_quad_facets(mesh, facet_nodes)
        blocks.append(meshio.CellBlock(facet_type, facet_nodes.astype(np.int64)))
        tags.append(np.full(len(facet_ids), number, dtype=np.int64))
        field_data[name] = np.array([number, dim - 1])
        for key in named:
            flag = key == f"boundary:{name}"
            named[key].append(np.full(len(facet_ids), int(flag), dtype=np.int32))
    fmt = file_format or _format_from_suffix(path)
    if fmt.startswith("gmsh"):
        cell_data = {"gmsh:physical": tags, "gmsh:geometrical": tags}
    elif fmt == "medit":
        cell_data = {"medit:ref": tags}  # numbers only: Medit has no region names
    else:
        cell_data = {"cell_tags": tags, **named}
    points = mesh.p.T
    if points.shape[1] == 2 and fmt in ("vtu", "vtk", "xdmf"):  # VTK-based formats want 3-D
        points = np.column_stack([points, np.zeros(len(points))])
    out = meshio.Mesh(points, blocks, cell_data=cell_data, field_data=field_data)
    kwargs = {}
    if fmt.startswith("gmsh"):
        kwargs["binary"] = binary
    elif fmt == "xdmf":
        kwargs["data_format"] = "XML"  # no HDF5 dependency
    meshio.write(path, out, file_format=fmt, **kwargs)


def _format_from_suffix(path: Path) -> str:
    import meshio

    suffix = path.suffix.lower()
    if suffix == ".msh":
        return "gmsh22"  # meshio's 4.1 writer needs Gmsh entities; 2.2 carries the same tags
    formats = meshio.extension_to_filetypes.get(suffix)
    if not formats:
        raise MeshFileError(path, f"unknown mesh file suffix {suffix!r}; expected one of "
                            f"{sorted(meshio.extension_to_filetypes)}")
    return formats[0]


# --------------------------------------------------------------------------------------
# validation pipeline
# --------------------------------------------------------------------------------------


def _mesh_from_meshio(raw: meshio.Mesh, source: str, *, repair: bool) -> skfem.Mesh:
    cell_type, cells, facet_blocks, cell_tags = _select_cells(raw, source)
    dim = SUPPORTED_CELLS[cell_type][0]
    points = _checked_points(raw.points, dim, source)
    _check_indices(cells, len(points), source)
    points, cells, facet_blocks = _handle_duplicates(points, cells, facet_blocks, source, repair)
    points, cells, facet_blocks = _handle_unused(points, cells, facet_blocks, source, repair)
    _check_cell_shapes(points, cells, cell_type, source)
    mesh_cls = SUPPORTED_CELLS[cell_type][1]
    t = cells[:, _HEX_MESHIO_TO_SKFEM] if cell_type == "hexahedron" else cells
    mesh = mesh_cls(np.ascontiguousarray(points.T), np.ascontiguousarray(t.T), validate=False)
    _check_not_folded(mesh, source)
    boundaries = _facet_tags(mesh, facet_blocks, raw.field_data, dim, source)
    subdomains = _cell_tags(cell_tags, raw.field_data, dim)
    return with_names(mesh, boundaries, subdomains)


def _sort_each_column(columns: np.ndarray) -> np.ndarray:
    """``np.sort(columns, axis=0)`` for a few rows: odd-even transposition, whole rows at a
    time (``np.sort`` along a short axis sorts each column on its own).

    >>> _sort_each_column(np.array([[3, 0, 2], [1, 0, 7], [2, 5, 1]])).tolist()
    [[1, 0, 1], [2, 0, 2], [3, 5, 7]]
    """
    rows = list(columns)
    for round_ in range(len(rows)):
        for i in range(round_ % 2, len(rows) - 1, 2):
            rows[i], rows[i + 1] = (np.minimum(rows[i], rows[i + 1]),
                                    np.maximum(rows[i], rows[i + 1]))
    return np.stack(rows) if rows else columns.copy()


def _distinct_columns(columns: np.ndarray, *, packed: bool | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(columns, axis=1, return_inverse=True)`` of non-negative integer columns
    (the inverse as ``np.intp``, as scikit-fem's ``t2f``).

    ``packed`` (default: where the largest key fits in ``int64``) makes each column one key,
    its rows the digits in base ``max + 1``, and deduplicates the keys
    (:func:`prdp_fem._sorting.unique_with_inverse`); otherwise the columns are sorted with
    ``np.lexsort``.

    >>> columns = np.array([[2, 0, 2, 1], [3, 1, 3, 0]])
    >>> distinct, inverse = _distinct_columns(columns)
    >>> distinct.tolist(), inverse.tolist()
    ([[0, 1, 2], [1, 0, 3]], [2, 0, 2, 1])
    >>> [a.tolist() for a in _distinct_columns(columns, packed=False)] == [distinct.tolist(),
    ...                                                                    inverse.tolist()]
    True
    """
    rows, n = columns.shape
    if n == 0:
        return columns.copy(), np.zeros(0, dtype=np.intp)
    base = int(columns.max()) + 1
    if packed is None:
        packed = base ** rows <= np.iinfo(np.int64).max
    if packed:
        key = np.zeros(n, dtype=np.int64)
        for row in columns:  # int64 arithmetic whatever the columns' integer type
            key = key * base + row.astype(np.int64)
        keys, inverse = unique_with_inverse(key)
        distinct = np.empty((rows, keys.size), dtype=columns.dtype)
        for r in range(rows - 1, -1, -1):
            keys, digit = np.divmod(keys, base)
            distinct[r] = digit
        return distinct, inverse.astype(np.intp)
    order = np.lexsort(columns[::-1])
    ordered = columns[:, order]
    starts = np.logical_or.reduce([first_of_each(row) for row in ordered])
    inverse = np.empty(n, dtype=np.intp)
    inverse[order] = np.cumsum(starts) - 1
    return np.ascontiguousarray(ordered[:, starts]), inverse


def with_names(mesh: skfem.Mesh, boundaries: dict | None = None,
               subdomains: dict | None = None) -> skfem.Mesh:
    """``mesh`` with named boundaries and subdomains.

    A boundary is an array of facet indices or a test of facet midpoints (``x`` of shape
    ``(dim, n)``), which selects among the boundary facets, as scikit-fem's
    ``with_boundaries`` does. The midpoints are taken of the boundary facets only, not of all
    of them.
    """
    named = mesh
    if boundaries:
        named = named.with_boundaries(_boundary_facets(mesh, boundaries))
    if subdomains:
        named = named.with_subdomains(subdomains)
    return named


def _boundary_facets(mesh: skfem.Mesh, boundaries: dict) -> dict:
    """Each named boundary as facet indices: arrays as given, tests evaluated at the
    midpoints of the boundary facets (built once for all of them)."""
    if not any(callable(test) for test in boundaries.values()):
        return boundaries
    on_boundary = mesh.boundary_facets()
    midpoints = mesh.p[:, mesh.facets[:, on_boundary]].mean(axis=1)
    return {name: on_boundary[_facet_mask(test, midpoints, name)] if callable(test) else test
            for name, test in boundaries.items()}


def _facet_mask(test, midpoints: np.ndarray, name: str) -> np.ndarray:
    """``test(midpoints)`` as one flag per facet, or a :class:`MeshError` naming the boundary."""
    mask = np.asarray(test(midpoints))
    if mask.shape != midpoints.shape[1:]:
        raise MeshError("<named boundaries>", f"boundary {name!r}: its test returned shape "
                        f"{mask.shape}; expected one flag per facet midpoint, shape "
                        f"{midpoints.shape[1:]}")
    return mask.astype(bool)


def _select_cells(raw: meshio.Mesh, source: str):
    """Pick the top-dimensional cell block; return facet blocks with their tags."""
    present = [block.type for block in raw.cells]
    supported = sorted({t for t in present if t in SUPPORTED_CELLS},
                       key=lambda t: -SUPPORTED_CELLS[t][0])
    if not supported:
        higher = sorted(set(present) & HIGHER_ORDER_CELLS)
        if higher:
            raise UnsupportedCellsError(
                source, f"holds only second-order cells {higher}; expected linear triangle, "
                "quad, tetra or hexahedron cells (export a first-order mesh; P2 is built on it)")
        found = sorted(set(present)) or "no cells"
        raise UnsupportedCellsError(
            source, f"holds {found}; expected triangle, quad, tetra or hexahedron cells")
    top_dim = SUPPORTED_CELLS[supported[0]][0]
    top_types = [t for t in supported if SUPPORTED_CELLS[t][0] == top_dim]
    if len(top_types) > 1:
        raise MixedDimensionError(
            source, f"mixes {top_types} cells; expected one cell type per mesh")
    cell_type = top_types[0]
    facet_type = SUPPORTED_CELLS[cell_type][2]
    named_keys = [k for k in raw.cell_data if k.startswith(NAMED_PREFIXES)]
    # named 0/1 arrays written by save_mesh carry the names: numeric tags would repeat them
    tag_key = None if named_keys else next((k for k in TAG_KEYS if k in raw.cell_data), None)
    cell_blocks, cell_tags, facet_blocks = [], [], []
    for i, block in enumerate(raw.cells):
        tags = None if tag_key is None else np.asarray(raw.cell_data[tag_key][i]).astype(int)
        sets = _cell_set_membership(raw, i, len(block.data))
        prefix = "subdomain:" if block.type == cell_type else "boundary:"
        for key in named_keys:
            members = np.flatnonzero(np.asarray(raw.cell_data[key][i]).ravel())
            if key.startswith(prefix) and members.size:
                sets[key[len(prefix):]] = members
        if block.type == cell_type:
            cell_blocks.append(block.data)
            cell_tags.append((tags, sets, len(block.data)))
        elif block.type == facet_type:
            facet_blocks.append((np.asarray(block.data), tags, sets))
        elif block.type in SUPPORTED_CELLS and SUPPORTED_CELLS[block.type][0] == top_dim - 1:
            raise MixedDimensionError(
                source, f"has {block.type} cells beside {cell_type} cells; lower-dimensional "
                f"cells must be {facet_type} facets of the {cell_type} mesh")
    cells = np.concatenate(cell_blocks).astype(np.int64)
    return cell_type, cells, facet_blocks, cell_tags


def _cell_set_membership(raw: meshio.Mesh, block_index: int, n: int) -> dict[str, np.ndarray]:
    """Cell sets (XDMF, Exodus, Abaqus...) restricted to one block, as local index arrays."""
    sets = {}
    for name, per_block in (raw.cell_sets or {}).items():
        if name.startswith("gmsh:") or block_index >= len(per_block):
            continue
        members = per_block[block_index]
        if members is not None and len(members):
            sets[name] = np.asarray(members, dtype=np.int64)[np.asarray(members) < n]
    return sets


def _checked_points(points: np.ndarray, dim: int, source: str) -> np.ndarray:
    points = np.asarray(points, dtype=float)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise NonFiniteCoordinatesError(
            source, f"{int(bad.sum())} node(s) have NaN/Inf coordinates (first: node {first} "
            f"at {points[first].tolist()}); expected finite coordinates")
    huge = np.abs(points).max(axis=1, initial=0.0) > MAX_COORDINATE
    if huge.any():
        first = int(np.flatnonzero(huge)[0])
        raise CoordinateRangeError(
            source, f"{int(huge.sum())} node(s) have coordinates beyond +-{MAX_COORDINATE:g} "
            f"(first: node {first} at {points[first].tolist()}): cell areas and volumes would "
            f"overflow in double precision; expected |coordinates| <= {MAX_COORDINATE:g} "
            "(rescale the mesh, e.g. to metres or kilometres)")
    if dim == 2 and points.shape[1] == 3:
        z = points[:, 2]
        if np.ptp(z) > 1e-12 * max(np.ptp(points[:, :2]), 1.0):
            raise MixedDimensionError(
                source, f"has 2-D cells on nodes spanning 3-D (z from {z.min():g} to "
                f"{z.max():g}); expected a planar 2-D mesh (surfaces in 3-D are not supported)")
        points = points[:, :2]
    if points.shape[1] < dim:
        raise MixedDimensionError(
            source, f"has {dim}-D cells but {points.shape[1]}-D node coordinates")
    return np.ascontiguousarray(points[:, :dim])


def _check_indices(cells: np.ndarray, n_points: int, source: str) -> None:
    if cells.size and (cells.min() < 0 or cells.max() >= n_points):
        raise MeshFileError(
            source, f"a cell references node {int(cells.max())} but the file has {n_points} "
            "nodes; expected node indices in range")


def _handle_duplicates(points, cells, facet_blocks, source, repair):
    diameter = float(np.ptp(points, axis=0).max()) or 1.0
    keys = np.round(points / (DUPLICATE_TOL * diameter * 1e3)).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    if len(first) == len(points):
        return points, cells, facet_blocks
    canonical = first[inverse]
    dup = np.flatnonzero(canonical != np.arange(len(points)))
    if not repair:
        i = int(dup[0])
        raise DuplicateNodeError(
            source, f"{len(dup)} duplicate node(s) (first: node {i} repeats node "
            f"{int(canonical[i])} at {points[i].tolist()}); expected distinct nodes "
            "(load with repair=True to merge them)")
    warnings.warn(f"{source}: merged {len(dup)} duplicate node(s)", MeshRepairWarning,
                  stacklevel=4)
    cells = canonical[cells]
    facet_blocks = [(canonical[f], tags, sets) for f, tags, sets in facet_blocks]
    return points, cells, facet_blocks


def _handle_unused(points, cells, facet_blocks, source, repair):
    used = np.zeros(len(points), dtype=bool)
    used[cells.ravel()] = True
    if used.all():
        return points, cells, facet_blocks
    unused = np.flatnonzero(~used)
    if not repair:
        raise UnusedNodeError(
            source, f"{len(unused)} node(s) belong to no cell (first: node {int(unused[0])} at "
            f"{points[unused[0]].tolist()}); expected every node in a cell "
            "(load with repair=True to drop them)")
    warnings.warn(f"{source}: dropped {len(unused)} unused node(s)", MeshRepairWarning,
                  stacklevel=4)
    new_index = np.cumsum(used) - 1
    kept_blocks = []
    for facets, tags, sets in facet_blocks:
        keep = used[facets].all(axis=1)
        kept_sets = {k: v[keep[v]] for k, v in sets.items()}  # indices shift below
        remap = np.cumsum(keep) - 1
        kept_sets = {k: remap[v] for k, v in kept_sets.items()}
        kept_blocks.append((new_index[facets[keep]],
                            None if tags is None else tags[keep], kept_sets))
    return points[used], new_index[cells], kept_blocks


def _signed_measures(points: np.ndarray, cells: np.ndarray, cell_type: str) -> np.ndarray:
    """Signed measure per cell; for quads/hexes, the corner Jacobians (n_cells, n_corners)."""
    x = points[cells]  # (n, k, d)
    if cell_type == "triangle":
        e1, e2 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
        return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    if cell_type == "tetra":
        e = x[:, 1:] - x[:, :1]
        return np.linalg.det(e) / 6.0
    if cell_type == "quad":
        nxt, prv = np.roll(x, -1, axis=1), np.roll(x, 1, axis=1)
        a, b = nxt - x, prv - x
        return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    # hexahedron, meshio order: bottom 0-3, top 4-7; corner Jacobians from 3 edges per corner
    edges = x[:, _HEX_CORNER_EDGES] - x[:, :, None, :]  # (n, 8, 3, 3)
    return np.linalg.det(edges)


def _longest_edge(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    x = points[cells]
    k = cells.shape[1]
    i, j = np.triu_indices(k, 1)
    return np.linalg.norm(x[:, i] - x[:, j], axis=-1).max(axis=1)


def _check_cell_shapes(points, cells, cell_type, source) -> None:
    measure = _signed_measures(points, cells, cell_type)
    dim = SUPPORTED_CELLS[cell_type][0]
    scale = _longest_edge(points, cells) ** dim
    corner = measure if measure.ndim == 2 else measure[:, None]
    tiny = np.abs(corner) <= DEGENERACY_TOL * scale[:, None]
    if tiny.any():
        bad = np.flatnonzero(tiny.any(axis=1))
        i = int(bad[0])
        raise DegenerateCellError(
            source, f"{len(bad)} {cell_type} cell(s) have zero {'area' if dim == 2 else 'volume'}"
            f" (first: cell {i} with nodes {cells[i].tolist()}); expected cells of positive "
            "measure")
    negative = corner < 0
    mixed = negative.any(axis=1) & ~negative.all(axis=1)
    if mixed.any():
        i = int(np.flatnonzero(mixed)[0])
        raise InvertedCellError(
            source, f"{int(mixed.sum())} {cell_type} cell(s) are self-intersecting or non-convex "
            f"(first: cell {i} with nodes {cells[i].tolist()}); expected convex cells with a "
            "consistent node order")
    # a consistently inverted cell is a valid cell: scikit-fem integrates with |det J|, so
    # its operator equals that of the renumbered cell (tested); nothing to repair


def _check_not_folded(mesh: skfem.Mesh, source: str) -> None:
    """Cells on either side of an interior facet must lie on opposite sides of it."""
    left, right = mesh.f2t
    interior = right >= 0
    if not interior.any():
        return
    facets = mesh.facets[:, interior]
    x0 = mesh.p[:, facets[0]]
    if mesh.dim() == 2:
        tangent = mesh.p[:, facets[1]] - x0
        normal = np.array([-tangent[1], tangent[0]])
    else:
        normal = np.cross((mesh.p[:, facets[1]] - x0).T, (mesh.p[:, facets[2]] - x0).T).T
    centroids = mesh.p[:, mesh.t].mean(axis=1)
    side_left = np.einsum("dn,dn->n", centroids[:, left[interior]] - x0, normal)
    side_right = np.einsum("dn,dn->n", centroids[:, right[interior]] - x0, normal)
    folded = np.sign(side_left) * np.sign(side_right) >= 0  # signs: no overflow at any scale
    if folded.any():
        k = int(np.flatnonzero(folded)[0])
        a, b = int(left[interior][k]), int(right[interior][k])
        raise InvertedCellError(
            source, f"{int(folded.sum())} interior facet(s) have both neighbouring cells on the "
            f"same side (first: cells {a} and {b}): the mesh is folded by inverted cells; "
            "expected non-overlapping cells")


def _match_rows(reference: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Index of each query row (as a node set) among reference rows, -1 if absent.

    >>> _match_rows(np.array([[0, 1], [1, 2], [2, 0]]), np.array([[0, 2], [1, 0], [3, 1]]))
    array([ 2,  0, -1])
    """
    if len(query) == 0:
        return np.zeros(0, dtype=np.int64)
    # the node sets as sorted columns, numbered together (np.unique(axis=0) took 0.7 s for
    # the tagged boundary of a 512 x 512 mesh: a sort of records)
    _, inverse = _distinct_columns(_sort_each_column(np.hstack([reference.T, query.T])))
    lookup = np.full(inverse.max() + 1, -1, dtype=np.int64)
    lookup[inverse[: len(reference)]] = np.arange(len(reference))
    return lookup[inverse[len(reference):]]


def _tag_name(tag: int, field_data: dict, dim: int) -> str:
    for name, value in (field_data or {}).items():
        value = np.atleast_1d(value)
        if int(value[0]) == tag and (len(value) < 2 or int(value[1]) == dim):
            return str(name)
    return str(tag)


def _facet_tags(mesh, facet_blocks, field_data, dim, source) -> dict[str, np.ndarray]:
    groups: dict[str, list[np.ndarray]] = {}
    for nodes, tags, sets in facet_blocks:
        ids = _match_rows(mesh.facets.T, nodes)
        if (ids < 0).any():
            raise MixedDimensionError(
                source, f"{int((ids < 0).sum())} lower-dimensional cell(s) are not facets of "
                "the mesh; expected boundary/interface facets only")
        if tags is not None:
            for tag in np.unique(tags):
                groups.setdefault(_tag_name(int(tag), field_data, dim - 1), []).append(
                    ids[tags == tag])
        for name, members in sets.items():
            groups.setdefault(name, []).append(ids[members])
    return {name: np.unique(np.concatenate(parts)).astype(np.int64)
            for name, parts in groups.items()}


def _cell_tags(cell_tags, field_data, dim) -> dict[str, np.ndarray]:
    groups: dict[str, list[np.ndarray]] = {}
    offset = 0
    for tags, sets, n in cell_tags:
        named = tags is not None and any(
            _tag_name(int(t), field_data, dim) != str(int(t)) for t in np.unique(tags))
        if tags is not None and (named or len(np.unique(tags)) > 1):
            for tag in np.unique(tags):
                groups.setdefault(_tag_name(int(tag), field_data, dim), []).append(
                    offset + np.flatnonzero(tags == tag))
        for name, members in sets.items():
            groups.setdefault(name, []).append(offset + members)
        offset += n
    return {name: np.unique(np.concatenate(parts)).astype(np.int64)
            for name, parts in groups.items()}


def meshio_cell_type(mesh: skfem.Mesh) -> str:
    for name, (_, cls, _) in SUPPORTED_CELLS.items():
        if isinstance(mesh, cls):
            return name
    raise UnsupportedCellsError(type(mesh).__name__, "expected a linear tri/quad/tet/hex mesh")


def _order_quad_facets(mesh: skfem.Mesh, facet_nodes: np.ndarray) -> np.ndarray:
    """Put the 4 nodes of each hexahedron face in cyclic order (skfem stores them sorted)."""
    x = mesh.p.T[facet_nodes]  # (n, 4, 3)
    centre = x.mean(axis=1, keepdims=True)
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    u = x[:, 0] - centre[:, 0]
    v = np.cross(normal, u)
    rel = x - centre
    angle = np.arctan2(np.einsum("nkd,nd->nk", rel, v), np.einsum("nkd,nd->nk", rel, u))
    return np.take_along_axis(facet_nodes, np.argsort(angle, axis=1), axis=1)


# --------------------------------------------------------------------------------------
# quality report
# --------------------------------------------------------------------------------------


class MeshQuality(NamedTuple):
    """Summary of a mesh: sizes, extreme cell measures and a shape-quality range.

    ``n_inverted`` counts cells numbered clockwise (valid, see :mod:`prdp_fem.mesh.io`).
    ``quality`` is 1 for an equilateral simplex / square cell and tends to 0 for slivers:
    triangles ``4 sqrt(3) A / sum l^2``, tetrahedra ``6 sqrt(2) V / l_rms^3``, quads/hexes
    the smallest scaled corner Jacobian (corner Jacobian over the product of its edges).
    """

    cell_type: str
    dim: int
    n_nodes: int
    n_cells: int
    h_min: float
    h_max: float
    measure_min: float
    measure_max: float
    total_measure: float
    quality_min: float
    quality_mean: float
    n_inverted: int


def mesh_quality(mesh: skfem.Mesh) -> MeshQuality:
    """Sizes and shape quality of ``mesh``."""
    cell_type = meshio_cell_type(mesh)
    dim = SUPPORTED_CELLS[cell_type][0]
    points = mesh.p.T
    cells = mesh.t.T
    if cell_type == "hexahedron":
        cells = cells[:, HEX_SKFEM_TO_MESHIO]
    x = points[cells]
    k = cells.shape[1]
    i, j = np.triu_indices(k, 1)
    lengths = np.linalg.norm(x[:, i] - x[:, j], axis=-1)
    signed = _signed_measures(points, cells, cell_type)
    n_inverted = int((signed.reshape(len(cells), -1) < 0).all(axis=1).sum())
    measure = np.abs(signed)
    if cell_type == "triangle":
        quality = 4 * np.sqrt(3) * measure / (lengths**2).sum(axis=1)
    elif cell_type == "tetra":
        quality = 6 * np.sqrt(2) * measure / np.sqrt((lengths**2).mean(axis=1)) ** 3
    else:  # scaled Jacobian: corner Jacobian over the product of its edge lengths
        quality = _scaled_jacobian(x, cell_type)
        measure = np.asarray(skfem.Functional(lambda w: 1.0 + 0 * w.x[0]).elemental(
            skfem.Basis(mesh, _p0_element(mesh))))
    return MeshQuality(
        cell_type=cell_type, dim=dim, n_nodes=points.shape[0], n_cells=cells.shape[0],
        h_min=float(lengths.min()), h_max=float(lengths.max()),
        measure_min=float(measure.min()), measure_max=float(measure.max()),
        total_measure=float(measure.sum()),
        quality_min=float(quality.min()), quality_mean=float(quality.mean()),
        n_inverted=n_inverted,
    )


def _scaled_jacobian(x: np.ndarray, cell_type: str) -> np.ndarray:
    if cell_type == "quad":
        a, b = np.roll(x, -1, axis=1) - x, np.roll(x, 1, axis=1) - x
        det = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
        norms = np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)
    else:
        edges = x[:, _HEX_CORNER_EDGES] - x[:, :, None, :]
        det = np.linalg.det(edges)
        norms = np.linalg.norm(edges, axis=-1).prod(axis=-1)
    return np.abs(det / norms).min(axis=1)


def _p0_element(mesh: skfem.Mesh) -> skfem.Element:
    return {skfem.MeshTri1: skfem.ElementTriP0, skfem.MeshQuad1: skfem.ElementQuad0,
            skfem.MeshTet1: skfem.ElementTetP0, skfem.MeshHex1: skfem.ElementHex0}[type(mesh)]()


# --------------------------------------------------------------------------------------
# refinement that keeps named boundaries
# --------------------------------------------------------------------------------------


class _DropInvalidatedTags(logging.Filter):
    """Hides scikit-fem's warning that refinement lost the tags (restored here)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "Named boundaries invalidated" not in record.getMessage()


def refine(mesh: skfem.Mesh, times: int) -> skfem.Mesh:
    """``times`` uniform refinements, named boundaries kept.

    scikit-fem carries the tags of triangle and quadrilateral meshes through a refinement;
    those of a tetrahedral mesh it drops, and here each tagged facet passes its tag to its
    four children. A hexahedral mesh's tags are dropped (with scikit-fem's warning).
    """
    # the logger of the module that warns (scikit-fem logs by module name)
    logger = logging.getLogger(skfem.Mesh.refined.__module__)
    for _ in range(times):
        tags = mesh.boundaries
        keeps = isinstance(mesh, skfem.MeshTet1) and bool(tags)
        quiet = _DropInvalidatedTags()
        if keeps:
            logger.addFilter(quiet)
        try:
            finer = mesh.refined(1)
        finally:
            logger.removeFilter(quiet)
        if keeps and finer.boundaries is None:
            finer = finer.with_boundaries(_tet_child_facets(mesh, finer, tags))
        mesh = finer
    return mesh


def _tet_child_facets(coarse: skfem.Mesh, fine: skfem.Mesh, tags: dict) -> dict:
    """The facets of ``fine`` (a uniform refinement of the tetrahedral ``coarse``, whose
    edge midpoints are its nodes ``n_coarse + edge``) that tile each tagged facet."""
    n_coarse = coarse.p.shape[1]
    midpoint = n_coarse + np.asarray(coarse.f2e)      # (3, facets): the midpoints' nodes
    edges = np.asarray(coarse.edges)
    fine_boundary = fine.boundary_facets()
    index = {tuple(sorted(v)): i for v, i in zip(fine.facets[:, fine_boundary].T.tolist(),
                                                 fine_boundary.tolist(), strict=True)}
    result = {}
    for name, facets in tags.items():
        children = []
        for f in np.asarray(facets).tolist():
            mids = midpoint[:, f]
            ends = edges[:, coarse.f2e[:, f]]          # (2, 3): each midpoint's edge ends
            triples = [tuple(sorted(mids))]
            for vertex in coarse.facets[:, f]:
                touching = mids[np.any(ends == vertex, axis=0)]
                triples.append(tuple(sorted((int(vertex), *touching.tolist()))))
            try:
                children.extend(index[t] for t in triples)
            except KeyError:
                raise MeshError(f"refining boundary {name!r}: facet {f} has no children on "
                                "the refined boundary; expected a uniform refinement") from None
        result[name] = np.sort(np.asarray(children, dtype=np.int64))
    return result
