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


def cube_tet() -> None:
    gmsh.model.add("cube_tet")
    volume = gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
    gmsh.model.occ.synchronize()
    names = {}
    for dim, tag in gmsh.model.getBoundary([(3, volume)], oriented=False):
        x, y, z = gmsh.model.occ.getCenterOfMass(dim, tag)
        for axis, value, low, high in ((0, x, "left", "right"), (1, y, "bottom", "top"),
                                       (2, z, "front", "back")):
            del axis
            if abs(value) < 1e-9:
                names[tag] = low
            elif abs(value - 1) < 1e-9:
                names[tag] = high
    for tag, name in names.items():
        gmsh.model.setPhysicalName(2, gmsh.model.addPhysicalGroup(2, [tag]), name)
    gmsh.model.setPhysicalName(3, gmsh.model.addPhysicalGroup(3, [volume]), "cube")
    gmsh.option.setNumber("Mesh.MeshSizeMax", 0.25)
    gmsh.model.mesh.generate(3)
    _write("cube_tet.msh", 4.1, binary=True)


def main() -> None:
    gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    try:
        for make in (square_tri, square_quad, plate_hole, cube_tet):
            gmsh.clear()
            make()
    finally:
        gmsh.finalize()


if __name__ == "__main__":
    main()
