"""Make the shipped meshes with Gmsh (``pip install gmsh``; ``python meshes/make_meshes.py``).

Each mesh is small, unstructured and tagged with physical groups, and exercises one Gmsh
format variant so that the reader is tested on real generator output:

==========================  ==============================================  ================
file                        content                                         format
==========================  ==============================================  ================
square_tri.msh              unit square, triangles, sides tagged            Gmsh 4.1 ASCII
plate_hole.msh              [0,2]x[0,1] minus a disk, 5 tagged boundaries   Gmsh 2.2 ASCII
cube_tet.msh                unit cube, tetrahedra, 6 tagged faces           Gmsh 4.1 binary
square_quad.msh             unit square, recombined quads, sides tagged     Gmsh 2.2 binary
slab_hex.msh                1 x 0.25 x 1 slab, hexahedra, 6 tagged faces    Gmsh 4.1 ASCII
==========================  ==============================================  ================
"""

from pathlib import Path

import gmsh

HERE = Path(__file__).resolve().parent


def _write(name: str, version: float, binary: bool) -> None:
    gmsh.option.setNumber("Mesh.MshFileVersion", version)
    gmsh.option.setNumber("Mesh.Binary", int(binary))
    gmsh.write(str(HERE / name))


def _tag_square_sides(surface: int) -> None:
    sides = {"bottom": [], "right": [], "top": [], "left": []}
    for dim, tag in gmsh.model.getBoundary([(2, surface)], oriented=False):
        x, y, _ = gmsh.model.occ.getCenterOfMass(dim, tag)
        name = ("bottom" if y < 1e-9 else "top" if y > 1 - 1e-9
                else "left" if x < 1e-9 else "right")
        sides[name].append(tag)
    for name, tags in sides.items():
        gmsh.model.setPhysicalName(1, gmsh.model.addPhysicalGroup(1, tags), name)
    gmsh.model.setPhysicalName(2, gmsh.model.addPhysicalGroup(2, [surface]), "domain")


def square_tri() -> None:
    gmsh.model.add("square_tri")
    surface = gmsh.model.occ.addRectangle(0, 0, 0, 1, 1)
    gmsh.model.occ.synchronize()
    _tag_square_sides(surface)
    gmsh.option.setNumber("Mesh.MeshSizeMax", 0.08)
    gmsh.model.mesh.generate(2)
    _write("square_tri.msh", 4.1, binary=False)


def square_quad() -> None:
    gmsh.model.add("square_quad")
    surface = gmsh.model.occ.addRectangle(0, 0, 0, 1, 1)
    gmsh.model.occ.synchronize()
    _tag_square_sides(surface)
    gmsh.option.setNumber("Mesh.MeshSizeMax", 0.1)
    gmsh.option.setNumber("Mesh.RecombineAll", 1)
    gmsh.option.setNumber("Mesh.Algorithm", 6)  # frontal-Delaunay, then blossom recombination
    gmsh.option.setNumber("Mesh.RecombinationAlgorithm", 1)
    gmsh.model.mesh.generate(2)
    gmsh.option.setNumber("Mesh.RecombineAll", 0)
    _write("square_quad.msh", 2.2, binary=True)


def plate_hole() -> None:
    gmsh.model.add("plate_hole")
    plate = gmsh.model.occ.addRectangle(0, 0, 0, 2, 1)
    hole = gmsh.model.occ.addDisk(1, 0.5, 0, 0.2, 0.2)
    (surface_dimtag,), _ = gmsh.model.occ.cut([(2, plate)], [(2, hole)])
    gmsh.model.occ.synchronize()
    groups = {"left": [], "right": [], "bottom": [], "top": [], "hole": []}
    for dim, tag in gmsh.model.getBoundary([surface_dimtag], oriented=False):
        x, y, _ = gmsh.model.occ.getCenterOfMass(dim, tag)
        name = ("bottom" if abs(y) < 1e-9 else "top" if abs(y - 1) < 1e-9
                else "left" if abs(x) < 1e-9 else "right" if abs(x - 2) < 1e-9 else "hole")
        groups[name].append(tag)
    for name, tags in groups.items():
        gmsh.model.setPhysicalName(1, gmsh.model.addPhysicalGroup(1, tags), name)
    gmsh.model.setPhysicalName(2, gmsh.model.addPhysicalGroup(2, [surface_dimtag[1]]), "plate")
    gmsh.option.setNumber("Mesh.MeshSizeMax", 0.1)
    gmsh.option.setNumber("Mesh.MeshSizeMin", 0.03)
    gmsh.model.mesh.generate(2)
    _write("plate_hole.msh", 2.2, binary=False)


def _tag_box_faces(volume: int, size: tuple[float, float, float], name: str) -> None:
    names = {}
    for dim, tag in gmsh.model.getBoundary([(3, volume)], oriented=False):
        centre = gmsh.model.occ.getCenterOfMass(dim, tag)
        for value, extent, low, high in zip(centre, size, ("left", "bottom", "front"),
                                            ("right", "top", "back"), strict=True):
            if abs(value) < 1e-9:
                names[tag] = low
            elif abs(value - extent) < 1e-9:
                names[tag] = high
    for tag, face in names.items():
        gmsh.model.setPhysicalName(2, gmsh.model.addPhysicalGroup(2, [tag]), face)
    gmsh.model.setPhysicalName(3, gmsh.model.addPhysicalGroup(3, [volume]), name)


def cube_tet() -> None:
    gmsh.model.add("cube_tet")
    volume = gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
    gmsh.model.occ.synchronize()
    _tag_box_faces(volume, (1.0, 1.0, 1.0), "cube")
    gmsh.option.setNumber("Mesh.MeshSizeMax", 0.25)
    gmsh.model.mesh.generate(3)
    _write("cube_tet.msh", 4.1, binary=True)


def slab_hex() -> None:
    """A structured hexahedral slab, 16 x 4 x 16 cells, thin in y (bottom, top)."""
    gmsh.model.add("slab_hex")
    size = (1.0, 0.25, 1.0)
    volume = gmsh.model.occ.addBox(0, 0, 0, *size)
    gmsh.model.occ.synchronize()
    _tag_box_faces(volume, size, "slab")
    for _, curve in gmsh.model.getEntities(1):
        box = gmsh.model.getBoundingBox(1, curve)
        along_y = box[4] - box[1] > 0.1  # the bounding box is padded by 1e-7
        gmsh.model.mesh.setTransfiniteCurve(curve, 5 if along_y else 17)
    for _, surface in gmsh.model.getEntities(2):
        gmsh.model.mesh.setTransfiniteSurface(surface)
        gmsh.model.mesh.setRecombine(2, surface)
    gmsh.model.mesh.setTransfiniteVolume(volume)
    gmsh.model.mesh.generate(3)
    _write("slab_hex.msh", 4.1, binary=False)


def main() -> None:
    gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    try:
        for make in (square_tri, square_quad, plate_hole, cube_tet, slab_hex):
            gmsh.clear()
            make()
    finally:
        gmsh.finalize()


if __name__ == "__main__":
    main()
