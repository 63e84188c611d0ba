"""``prdp-fem scenes``: list the built-in scenes, or print one."""

from __future__ import annotations


def scenes_command(args) -> None:
    from ..scene.spec import BUILTIN_SCENES, builtin_scene_path, load_scene

    if args.name is not None:
        print(builtin_scene_path(args.name).read_text(), end="")
        return
    for name in BUILTIN_SCENES:
        scene = load_scene(name)
        print(f"{name:<12} {scene.study.kind:<8} {scene.description}")
