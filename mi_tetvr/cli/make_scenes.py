"""``mi-tetvr make-scenes [-o DIR]``: write the bundled scenes (XML scenes, transfer
functions) and generate the meshes and volume they use."""
from __future__ import annotations

from mi_tetvr.cli import flags

NAME = "make-scenes"
HELP = "write the bundled scenes and generate the meshes and volume they use"


def add_arguments(p):
    flags.out(p, "folder of the scenes (default: scenes/ in the current directory)",
              required=False)
    p.add_argument("--force", action="store_true",
                   help="generate the meshes and the volume again where they exist")


def run(a):
    from mi_tetvr.mesh.scenes import make_scenes
    for p in make_scenes(a.out, force=a.force):
        print(f"wrote {p}")
