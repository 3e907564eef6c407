"""``mi-tetvr partition MESH -o OUT.pvtu --blocks N``: a k-d split of space into
N boxes, each box's tets (those touching it) written as a ``.vtu`` piece of a
``.pvtu`` that ParaView opens as one data set (:mod:`mi_tetvr.mesh.partition`);
``render OUT.pvtu --workers W`` renders it block by block."""
from __future__ import annotations

import time

from mi_tetvr.cli import flags
from mi_tetvr.cli.common import CommandError

NAME = "partition"
HELP = "split a tet mesh into k-d blocks: a .pvtu of .vtu pieces, for render --workers"


def add_arguments(p):
    p.add_argument("mesh", help="tet mesh file (.vtu, .vtk, .msh, .mesh, ...)")
    flags.out(p, "the partitioned mesh (.pvtu; its pieces go to a folder of its name "
                 "beside it, its boxes to NAME.blocks.json)")
    p.add_argument("--blocks", type=int, required=True, help="number of blocks (boxes)")
    flags.mesh_flags(p)
    flags.quiet(p)


def run(a):
    from pathlib import Path

    from mi_tetvr.mesh.io import read_tetmesh
    from mi_tetvr.mesh.partition import partition_mesh
    from mi_tetvr.mesh.topology import MeshError
    from mi_tetvr.progress import progress_bar
    if a.blocks < 1:
        raise ValueError(f"--blocks must be at least 1, got {a.blocks}")
    if Path(a.out).suffix.lower() != ".pvtu":
        raise ValueError(f"a partitioned mesh is written as .pvtu, got {a.out}")
    t0 = time.time()
    try:
        # (every array as the file has it: no color or opacity of its own)
        mesh = read_tetmesh(a.mesh, color=None, opacity=None, repair=a.repair,
                            cell_to_point=a.cell_to_point)
        mesh.topology        # (a mesh the renderer would refuse is refused here)
    except MeshError as e:
        raise CommandError(str(e)) from None
    bar = progress_bar(total=a.blocks, desc="pieces", unit="piece", disable=a.quiet)
    part = partition_mesh(mesh.vertices, mesh.tets, a.out, a.blocks, mesh.point_data,
                          mesh.cell_data, progress=lambda k: bar.update())
    bar.close()
    sizes = [b.tets for b in part.blocks]
    print(f"{a.mesh}: {part.tets:,} tets in {len(sizes)} blocks of {min(sizes):,} to "
          f"{max(sizes):,} tets ({sum(sizes) / part.tets - 1:.1%} on block boundaries, in "
          f"two blocks or more) in {time.time() - t0:.1f} s -> {a.out}")
