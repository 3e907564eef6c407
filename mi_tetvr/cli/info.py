"""``mi-tetvr info MESH``: counts, bounds, boundary, quality and arrays of a mesh file, or
what is wrong with it and what ``--repair`` would drop."""
from __future__ import annotations

import json

from mi_tetvr.cli import flags
from mi_tetvr.cli.common import CommandError

NAME = "info"
HELP = "counts, bounds, boundary, quality and arrays of a mesh"


def add_arguments(p):
    p.add_argument("mesh", help="tet mesh file (.vtu, .vtk, .msh, .mesh, ...)")
    p.add_argument("--color", default="color", help="color point array (default color)")
    p.add_argument("--opacity", default="opacity", help="opacity point array (default opacity)")
    p.add_argument("--json", action="store_true", help="print the report as JSON (always, "
                   "also for a mesh with problems)")
    flags.mesh_flags(p)


def mesh_report(path, color="color", opacity="opacity", repair=False, cell_to_point=False):
    """What ``info`` says of a mesh file: its summary, or when it cannot be
    rendered, the problem (``problems``) and what ``--repair`` would drop
    (``repair``). Raises only for a file that cannot be read at all."""
    import warnings

    from mi_tetvr.mesh.io import read_mesh_file, read_tetmesh, tets_from_cells
    from mi_tetvr.mesh.topology import MeshError, repair_tets
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        try:
            mesh = read_tetmesh(path, color=color, opacity=opacity, repair=repair,
                                cell_to_point=cell_to_point)
            report = mesh.summary()
        except MeshError as e:
            raw = read_mesh_file(path)
            try:
                tets = tets_from_cells(raw, path)
            except MeshError:
                raise e from None
            keep, dropped = repair_tets(raw.points[:, :3], tets)
            report = {"vertices": len(raw.points), "tets": len(tets),
                      "problems": [str(e)],
                      "repair": {"drops": int((~keep).sum()),
                                 **{k: len(v) for k, v in dropped.items()
                                    if k != "boundary_faces"},
                                 "boundary_faces": dropped["boundary_faces"]}}
    if said:
        report["warnings"] = [str(w.message) for w in said]
    return report


def run(a):
    try:
        s = mesh_report(a.mesh, a.color, a.opacity, a.repair, a.cell_to_point)
    except (ValueError, FileNotFoundError) as e:
        if a.json:
            print(json.dumps({"mesh": a.mesh, "error": str(e)}, indent=2))
            raise CommandError() from None
        raise CommandError(str(e)) from None
    if a.json:
        print(json.dumps(s, indent=2))
        return
    from mi_tetvr.mesh.topology import format_summary
    print(f"{a.mesh}")
    arrays = s.pop("arrays", {})
    notes = [f"{key[:-1]:<20} {text}" for key in ("problems", "warnings")
             for text in s.pop(key, [])]
    print("\n".join("  " + line for line in format_summary(s).splitlines() + notes))
    for name, d in arrays.items():
        rng = "" if d["range"] is None else f"  [{d['range'][0]:.6g}, {d['range'][1]:.6g}]"
        print(f"  {d['kind']} array {name!r:<14} {tuple(d['shape'])}{rng}")
