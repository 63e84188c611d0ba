"""Scene files: the TOML specification, its formulas, and building problems from it.

A scene is read with :func:`load_scene` (a path, or the name of a built-in scene) and run
with :func:`prdp_fem.studies.run_study`; :mod:`prdp_fem.scene.build` turns its parts into
meshes, discretisations, inverse problems and trainings.
"""

from .spec import BUILTIN_SCENES, Scene, SceneError, builtin_scene_path, load_scene, parse_scene

__all__ = ["BUILTIN_SCENES", "Scene", "SceneError", "builtin_scene_path", "load_scene",
           "parse_scene"]
