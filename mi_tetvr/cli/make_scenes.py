"""``mi-tetvr make-scenes``: (re)generate the meshes of the bundled scenes."""
from __future__ import annotations

from mi_tetvr.cli import flags

NAME = "make-scenes"
HELP = "(re)generate the meshes of the bundled scenes"


def add_arguments(p):
    flags.out(p, "folder of the scenes (default: the project's scenes/)", required=False)


def run(a):
    from mi_tetvr.mesh.scenes import make_scene_meshes
    for p in make_scene_meshes(a.out):
        print(f"wrote {p}")
