"""Mesh input: shipped Gmsh files, round trips through other formats, every bad input."""

import shutil
import warnings

import meshio
import numpy as np
import pytest
import skfem
from conftest import MESH_DIR, SHIPPED_MESHES

import prdp_fem as pf
from prdp_fem import errors
from prdp_fem.mesh import save_mesh
from prdp_fem.mesh.io import _distinct_columns, with_names

EXPECTED_TAGS = {
    "square_tri.msh": ("MeshTri1", {"left", "right", "bottom", "top"}),
    "square_quad.msh": ("MeshQuad1", {"left", "right", "bottom", "top"}),
    "plate_hole.msh": ("MeshTri1", {"left", "right", "bottom", "top", "hole"}),
    "cube_tet.msh": ("MeshTet1", {"left", "right", "bottom", "top", "front", "back"}),
}


def operator_of(mesh):
    element = "Q1" if type(mesh).__name__.startswith(("MeshQuad", "MeshHex")) else "P1"
    disc = pf.discretize(mesh, element=element, kappa_space="P0")
    kappa = 1.0 + np.arange(disc.n_kappa) % 7
    return disc.stiffness_matrix(kappa)


def test_four_shipped_meshes_exist():
    assert {p.name for p in SHIPPED_MESHES} >= set(EXPECTED_TAGS)


@pytest.mark.parametrize("name", sorted(EXPECTED_TAGS))
def test_shipped_mesh_loads_with_tags(name):
    from conftest import MESH_DIR
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = pf.load_mesh(MESH_DIR / name)
    cls, tags = EXPECTED_TAGS[name]
    assert type(mesh).__name__ == cls
    assert set(mesh.boundaries) == tags
    # tagged facets are boundary facets and together cover the whole boundary
    tagged = np.unique(np.concatenate([np.asarray(v) for v in mesh.boundaries.values()]))
    np.testing.assert_array_equal(tagged, np.sort(mesh.boundary_facets()))
    quality = pf.mesh_quality(mesh)
    assert quality.quality_min > 0.1
    expected_measure = {"plate_hole.msh": 2.0 - np.pi * 0.2**2}.get(name, 1.0)
    # the hole is a polygon, so its area differs from the disk's by O(h^2)
    assert quality.total_measure == pytest.approx(expected_measure, rel=5e-3)


@pytest.mark.parametrize("path", SHIPPED_MESHES, ids=lambda p: p.name)
@pytest.mark.parametrize("formats", [(".vtu", ".xdmf"), (".mesh", ".msh")])
def test_round_trip_through_two_formats_keeps_the_operator(path, formats, tmp_path):
    mesh = pf.load_mesh(path)
    reference = operator_of(mesh)
    current = mesh
    names_kept = True
    for suffix in formats:
        target = tmp_path / f"copy{suffix}"
        save_mesh(current, target)
        current = pf.load_mesh(target)
        assert abs(operator_of(current) - reference).max() <= 1e-13 * abs(reference).max()
        sizes = {k: len(v) for k, v in current.boundaries.items()}
        names_kept = names_kept and suffix != ".mesh"  # Medit carries numbers, not names
        if not names_kept:
            assert sorted(sizes.values()) == sorted(len(v) for v in mesh.boundaries.values())
        else:
            assert sizes == {k: len(v) for k, v in mesh.boundaries.items()}
            assert {k: len(v) for k, v in current.subdomains.items()} == {
                k: len(v) for k, v in mesh.subdomains.items()}


def test_cell_sets_across_several_blocks(tmp_path):
    """Abaqus element sets over two triangle blocks land on the right cells."""
    cells = [("triangle", np.array([[0, 1, 2]])), ("triangle", np.array([[0, 2, 3]]))]
    path = tmp_path / "two.inp"
    meshio.write(path, meshio.Mesh(SQUARE, cells,
                                   cell_sets={"A": [np.array([0]), np.array([], dtype=int)],
                                              "B": [np.array([], dtype=int), np.array([0])]}))
    mesh = pf.load_mesh(path)
    assert {k: np.asarray(v).tolist() for k, v in mesh.subdomains.items()} == {"A": [0],
                                                                                "B": [1]}


def test_subdomains_round_trip_by_name(tmp_path):
    square = pf.unit_square(4).with_subdomains({"west": lambda x: x[0] < 0.5,
                                                "east": lambda x: x[0] > 0.5})
    for suffix in (".msh", ".vtu", ".xdmf"):
        save_mesh(square, tmp_path / f"s{suffix}")
        loaded = pf.load_mesh(tmp_path / f"s{suffix}")
        assert {k: np.sort(v).tolist() for k, v in loaded.subdomains.items()} == {
            k: np.sort(v).tolist() for k, v in square.subdomains.items()}


def test_msh22_round_trip_keeps_physical_names(tmp_path):
    mesh = pf.rectangle_with_hole(8)
    save_mesh(mesh, tmp_path / "hole.msh")
    loaded = pf.load_mesh(tmp_path / "hole.msh")
    assert {k: len(v) for k, v in loaded.boundaries.items()} == {
        k: len(v) for k, v in mesh.boundaries.items()}


@pytest.mark.parametrize("make", [
    lambda: pf.unit_square(3), lambda: pf.unit_square(3, "quad"), lambda: pf.unit_cube(2),
    lambda: pf.unit_cube(2, "hexahedron"), lambda: pf.l_shape(1), lambda: pf.disk(1),
    lambda: pf.rectangle_with_hole(4)])
def test_generators_measure_and_round_trip(make, tmp_path):
    mesh = make()
    quality = pf.mesh_quality(mesh)
    save_mesh(mesh, tmp_path / "m.vtu")
    again = pf.load_mesh(tmp_path / "m.vtu")
    np.testing.assert_allclose(again.p, mesh.p)
    assert abs(operator_of(again) - operator_of(mesh)).max() < 1e-12
    assert quality.total_measure > 0


@pytest.mark.parametrize("cell, dim", [(skfem.MeshTri1, 2), (skfem.MeshQuad1, 2),
                                       (skfem.MeshTet1, 3), (skfem.MeshHex1, 3)])
def test_named_boundaries_are_scikit_fems(cell, dim):
    """with_names names what scikit-fem's with_boundaries names (a midpoint test picks among
    the boundary facets only: "upper" leaves the interior facets above y = 0.5 out)."""
    x = np.linspace(0.0, 1.0, 4)
    def make():
        return cell.init_tensor(*[x] * dim)
    tests = {"left": lambda p: p[0] < 1e-10, "upper": lambda p: p[1] > 0.5,
             "given": np.array([0, 2], dtype=np.int32)}
    expected = make().with_boundaries(tests)
    mesh = make()
    named = with_names(mesh, tests, {"first": np.arange(3)})
    for name, facets in expected.boundaries.items():
        assert named.boundaries[name].dtype == facets.dtype
        np.testing.assert_array_equal(named.boundaries[name], facets)
    np.testing.assert_array_equal(named.subdomains["first"], np.arange(3))
    np.testing.assert_array_equal(named.facets, make().facets)


def _unstructured_meshes():
    rng = np.random.default_rng(0)
    circle = skfem.MeshTri1.init_circle(3)
    ball = skfem.MeshTet1.init_ball(2)
    yield circle
    yield ball
    # the same meshes with cells in random order: the facet numbering follows the vertices
    for mesh in (circle, ball):
        yield type(mesh)(mesh.p, mesh.t[:, rng.permutation(mesh.t.shape[1])])
    yield from (pf.load_mesh(path) for path in SHIPPED_MESHES)


@pytest.mark.parametrize("mesh", [
    *(cell.init_tensor(*[np.linspace(0.0, 1.0, 5)] * dim)
      for cell, dim in [(skfem.MeshTri1, 2), (skfem.MeshQuad1, 2), (skfem.MeshTet1, 3),
                        (skfem.MeshHex1, 3)]),
    *_unstructured_meshes()], ids=lambda mesh: f"{type(mesh).__name__}-{mesh.t.shape[1]}")
def test_distinct_facets_are_scikit_fem_s(mesh):
    """The distinct sorted vertex tuples (what matching a file's tagged facets relies on) are
    scikit-fem's facets and cell-to-facet map, to the number."""
    corners = np.sort(np.hstack([mesh.t[list(ix)] for ix in mesh.elem.refdom.facets]), axis=0)
    facets, t2f = skfem.Mesh.build_entities(mesh.t, mesh.elem.refdom.facets)
    by_lexsort, inverse = _distinct_columns(corners, packed=False)
    np.testing.assert_array_equal(by_lexsort, facets)
    np.testing.assert_array_equal(inverse, t2f.ravel())


def test_distinct_columns_is_numpy_s_unique_along_columns():
    rng = np.random.default_rng(1)
    cases = [(1, 5, 40, np.int32), (2, 9, 300, np.int32), (3, 4, 200, np.int64),
             (4, 70000, 50, np.int32), (2, 3, 0, np.int32), (3, 2 ** 30, 60, np.uint64)]
    for rows, high, n, dtype in cases:
        columns = rng.integers(0, high, size=(rows, n)).astype(dtype)
        columns[:, n // 2:] = columns[:, : n - n // 2]  # repeated columns in every case
        expected, inverse = np.unique(columns, axis=1, return_inverse=True)
        for packed in (None, True, False):
            if packed and high ** rows >= 2 ** 62:
                continue  # the packed key does not fit: None picks the lexsort for it
            got, got_inverse = _distinct_columns(columns, packed=packed)
            assert got.dtype == columns.dtype
            np.testing.assert_array_equal(got, expected.reshape(rows, -1))
            np.testing.assert_array_equal(got_inverse, inverse.ravel())


def test_tagged_node_sets_are_found_among_the_facets_in_any_node_order():
    """_match_rows (a file's tagged facets among the mesh's) against a dictionary lookup of
    the node sets: any node order in either, absent sets -1, one or three nodes."""
    rng = np.random.default_rng(3)
    for width in (1, 2, 3):
        reference = np.unique(np.sort(rng.integers(0, 40, (300, width)), axis=1), axis=0)
        reference = rng.permuted(reference[rng.permutation(len(reference))], axis=1)
        present = reference[rng.integers(0, len(reference), 150)]
        query = rng.permuted(np.vstack([present, rng.integers(0, 45, (50, width))]),
                             axis=1).astype(np.int64)
        where = {frozenset(row): i for i, row in enumerate(reference.tolist())}
        expected = [where.get(frozenset(row), -1) for row in query.tolist()]
        got = pf.mesh.io._match_rows(reference.astype(np.int32), query)
        assert got.tolist() == expected and -1 in expected and len(set(expected)) > 20


def test_a_boundary_test_must_flag_each_facet():
    """A midpoint test that returns one flag, not one per facet, is refused by name (scikit-fem
    raised a bare ValueError; indexing with it would have stored a 2-D array)."""
    mesh = skfem.MeshTri1.init_tensor(np.linspace(0, 1, 3), np.linspace(0, 1, 3))
    with pytest.raises(pf.MeshError, match=r"boundary 'all'.*shape \(\).*one flag per facet"):
        with_names(mesh, {"all": lambda x: True})


def test_generator_measures():
    assert pf.mesh_quality(pf.l_shape(2)).total_measure == pytest.approx(3.0)
    assert pf.mesh_quality(pf.rectangle_with_hole(8)).total_measure == pytest.approx(1.75)
    assert pf.mesh_quality(pf.unit_cube(3, "hexahedron")).total_measure == pytest.approx(1.0)
    # inscribed polygon: area below pi, converging at O(h^2)
    assert pf.mesh_quality(pf.disk(4)).total_measure == pytest.approx(np.pi, rel=2e-2)


def test_clockwise_cells_give_the_same_operator():
    square = pf.unit_square(4, "quad")
    cells = square.t.T
    flipped = pf.mesh_from_arrays(square.p.T, cells[:, ::-1], "quad")
    assert pf.mesh_quality(flipped).n_inverted != pf.mesh_quality(square).n_inverted
    assert abs(operator_of(flipped) - operator_of(square)).max() < 1e-13


# ------------------------------------------------------------------------------------------
# bad input: one typed error each, naming the file and the problem
# ------------------------------------------------------------------------------------------


def write(tmp_path, name, points, cells, **kwargs):
    path = tmp_path / name
    meshio.write(path, meshio.Mesh(points, cells, **kwargs))
    return path


SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
TWO_TRIANGLES = [("triangle", np.array([[0, 1, 2], [0, 2, 3]]))]


@pytest.mark.parametrize(("name", "content", "message"), [
    ("nope.msh", None, r"nope\.msh: file does not exist"),
    ("empty.msh", "", r"empty\.msh: file is empty"),
    ("junk.msh", "this is not a mesh\n", r"junk\.msh: could not be read as a mesh"),
    ("mesh.unknown", "1 2 3\n", r"mesh\.unknown: could not be read"),
])
def test_bad_files(tmp_path, name, content, message):
    if content is not None:
        (tmp_path / name).write_text(content)
    with pytest.raises(pf.MeshFileError, match=message):
        pf.load_mesh(tmp_path / name)


def test_directory_is_not_a_mesh(tmp_path):
    with pytest.raises(pf.MeshFileError, match="not a regular file"):
        pf.load_mesh(tmp_path)


def test_no_supported_cells(tmp_path):
    path = write(tmp_path, "lines.vtu", SQUARE, [("line", np.array([[0, 1], [1, 2]]))])
    with pytest.raises(errors.UnsupportedCellsError, match=r"lines\.vtu: holds \['line'\]"):
        pf.load_mesh(path)


def test_second_order_cells_are_named(tmp_path):
    points = np.vstack([SQUARE, [[0.5, 0], [0.5, 0.5], [0, 0.5]]])
    path = write(tmp_path, "p2.vtu", points, [("triangle6", np.array([[0, 1, 3, 4, 5, 6]]))])
    with pytest.raises(errors.UnsupportedCellsError, match=r"second-order cells.*triangle6"):
        pf.load_mesh(path)


def test_mixed_cell_types(tmp_path):
    points = np.vstack([SQUARE, [[2.0, 0.0], [2.0, 1.0]]])
    cells = [("triangle", np.array([[0, 1, 2], [0, 2, 3]])), ("quad", np.array([[1, 4, 5, 2]]))]
    path = write(tmp_path, "mixed.vtu", points, cells)
    with pytest.raises(errors.MixedDimensionError, match=r"mixed\.vtu: mixes"):
        pf.load_mesh(path)


def test_lower_dimensional_cells_that_are_not_facets(tmp_path):
    cells = [*TWO_TRIANGLES, ("line", np.array([[1, 3]]))]  # the diagonal is 0-2, not 1-3
    path = write(tmp_path, "stray.vtu", SQUARE, cells)
    with pytest.raises(errors.MixedDimensionError, match="not facets of the mesh"):
        pf.load_mesh(path)


def test_surface_in_3d_is_mixed_dimension(tmp_path):
    points = np.column_stack([SQUARE, [0.0, 0.0, 1.0, 0.0]])
    path = write(tmp_path, "bent.vtu", points, TWO_TRIANGLES)
    with pytest.raises(errors.MixedDimensionError, match="nodes spanning 3-D"):
        pf.load_mesh(path)


def test_nan_coordinates(tmp_path):
    points = SQUARE.copy()
    points[2, 1] = np.nan
    path = write(tmp_path, "nan.vtu", points, TWO_TRIANGLES)
    with pytest.raises(errors.NonFiniteCoordinatesError, match=r"nan\.vtu: 1 node.*node 2"):
        pf.load_mesh(path)


def test_inf_coordinates():
    points = SQUARE.copy()
    points[0, 0] = np.inf
    with pytest.raises(errors.NonFiniteCoordinatesError, match="NaN/Inf"):
        pf.mesh_from_arrays(points, TWO_TRIANGLES[0][1], "triangle")


def test_degenerate_cell(tmp_path):
    points = np.vstack([SQUARE, [[2.0, 0.0]]])
    cells = [("triangle", np.array([[0, 1, 2], [0, 2, 3], [0, 1, 4]]))]  # 0,1,4 collinear
    path = write(tmp_path, "flat.vtu", points, cells)
    with pytest.raises(errors.DegenerateCellError, match=r"flat\.vtu: 1 triangle cell.*zero area"):
        pf.load_mesh(path)


def test_bowtie_quad_is_inverted(tmp_path):
    path = write(tmp_path, "bowtie.vtu", SQUARE, [("quad", np.array([[0, 1, 3, 2]]))])
    with pytest.raises(errors.InvertedCellError, match="self-intersecting"):
        pf.load_mesh(path)


def test_folded_mesh_is_inverted():
    # node 4 pulled through the opposite edge: its cells overlap their neighbours
    square = pf.unit_square(2)
    points = square.p.T.copy()
    centre = int(np.argmin(np.linalg.norm(points - 0.5, axis=1)))
    points[centre] = [1.2, 0.9]
    with pytest.raises(errors.InvertedCellError, match="folded"):
        pf.mesh_from_arrays(points, square.t.T, "triangle", source="folded.msh")


def test_duplicate_nodes_raise_then_repair(tmp_path):
    points = np.vstack([SQUARE, [[0.0, 0.0]]])  # node 4 duplicates node 0
    cells = [("triangle", np.array([[0, 1, 2], [4, 2, 3]]))]
    path = write(tmp_path, "dup.vtu", points, cells)
    with pytest.raises(errors.DuplicateNodeError, match=r"dup\.vtu: 1 duplicate node.*node 4"):
        pf.load_mesh(path)
    with pytest.warns(errors.MeshRepairWarning) as record:
        mesh = pf.load_mesh(path, repair=True)
    messages = [str(w.message) for w in record]
    assert any("merged 1 duplicate" in m for m in messages)
    assert any("dropped 1 unused" in m for m in messages)  # the merged copy is left unused
    assert mesh.p.shape[1] == 4
    assert pf.mesh_quality(mesh).total_measure == pytest.approx(1.0)


def test_unused_nodes_raise_then_repair(tmp_path):
    points = np.vstack([SQUARE, [[5.0, 5.0]]])
    path = write(tmp_path, "unused.vtu", points, TWO_TRIANGLES)
    with pytest.raises(errors.UnusedNodeError, match=r"unused\.vtu: 1 node.*belong to no cell"):
        pf.load_mesh(path)
    with pytest.warns(errors.MeshRepairWarning, match="dropped 1 unused"):
        mesh = pf.load_mesh(path, repair=True)
    assert mesh.p.shape[1] == 4


def test_node_index_out_of_range(tmp_path):
    with pytest.raises(pf.MeshFileError, match="references node 7"):
        pf.mesh_from_arrays(SQUARE, np.array([[0, 1, 7]]), "triangle")


def test_errors_are_value_errors_with_source_and_problem(tmp_path):
    shutil.copy(SHIPPED_MESHES[0], tmp_path / "ok.msh")
    with pytest.raises(ValueError) as info:
        pf.load_mesh(tmp_path / "missing.vtu")
    assert info.value.source.endswith("missing.vtu")
    assert "expected" in info.value.problem


def test_refining_a_tetrahedral_mesh_keeps_its_named_boundaries(caplog):
    from prdp_fem.mesh.io import refine
    coarse = pf.load_mesh(MESH_DIR / "cube_tet.msh")
    fine = refine(coarse, 2)
    assert "invalidated" not in caplog.text
    axis = {"left": (0, 0.0), "right": (0, 1.0), "bottom": (1, 0.0), "top": (1, 1.0),
            "front": (2, 0.0), "back": (2, 1.0)}
    for name, facets in fine.boundaries.items():
        assert len(facets) == 16 * len(coarse.boundaries[name])
        centroids = fine.p[:, fine.facets[:, facets]].mean(axis=1)
        dim, value = axis[name]
        np.testing.assert_allclose(centroids[dim], value, atol=1e-12)
    tagged = np.sort(np.concatenate(list(fine.boundaries.values())))
    np.testing.assert_array_equal(tagged, np.sort(fine.boundary_facets()))
