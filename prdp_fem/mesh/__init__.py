"""Meshes: reading and checking mesh files, generators for the built-in shapes, writing results.
"""

from .generators import (
    disk,
    geometric_spacing,
    l_shape,
    rectangle_with_hole,
    tensor_mesh,
    unit_cube,
    unit_square,
)
from .io import MeshQuality, load_mesh, mesh_from_arrays, mesh_quality, save_mesh
from .vtu import write_vtu

__all__ = [
    "MeshQuality",
    "disk",
    "geometric_spacing",
    "l_shape",
    "load_mesh",
    "mesh_from_arrays",
    "mesh_quality",
    "rectangle_with_hole",
    "save_mesh",
    "tensor_mesh",
    "unit_cube",
    "unit_square",
    "write_vtu",
]
