"""``mi-tetvr refine MESH --select ARRAY -o OUT``: split the edges around the top
vertices of a point-data array."""
from __future__ import annotations

from mi_tetvr.cli import flags
from mi_tetvr.cli.common import CommandError

NAME = "refine"
HELP = "split the edges around the top vertices of a point-data array"


def add_arguments(p):
    p.add_argument("mesh", help="tet mesh file")
    flags.out(p, "refined mesh file (.vtu, ...)")
    p.add_argument("--select", required=True, help="point-data array to rank vertices by "
                   "(or color, opacity)")
    p.add_argument("--rank", choices=["magnitude", "value"], default="magnitude",
                   help="magnitude (default): largest absolute values (vector norms) first, "
                   "negative as much as positive; value: highest signed values first")
    p.add_argument("--fraction", type=float, default=0.05, help="top fraction (default 0.05)")
    flags.mesh_flags(p)


def run(a):
    from mi_tetvr.cli.common import read_mesh
    from mi_tetvr.mesh.io import write_tetmesh
    from mi_tetvr.mesh.refine import refine_mesh
    mesh = read_mesh(a, a.mesh)
    try:
        out = refine_mesh(mesh, a.select, a.fraction, rank=a.rank)
    except (ValueError, FileNotFoundError, KeyError) as e:
        raise CommandError(str(e)) from None
    write_tetmesh(a.out, out)
    print(f"{a.mesh}: {len(mesh.tets):,} tets, {len(mesh.vertices):,} vertices -> "
          f"{len(out.tets):,} tets, {len(out.vertices):,} vertices -> {a.out}")
