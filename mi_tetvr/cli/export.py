"""``mi-tetvr export FIT|MESH -o OUT.ply|.obj|.glb``: a volume's surface at a level of
its opacity (or of another point array), colored by the field, or with ``--points`` its
vertices as a colored point cloud, for Blender, MeshLab and glTF viewers
(:mod:`mi_tetvr.mesh.export`)."""
from __future__ import annotations

from pathlib import Path

from mi_tetvr.cli import flags
from mi_tetvr.cli.common import CommandError

NAME = "export"
HELP = ("a volume's surface at an opacity level (or its vertices) as .ply, .obj or .glb, "
        "colored by the field")


def add_arguments(p):
    p.add_argument("path", help="tet mesh file, or a fit's output folder (its fitted mesh)")
    flags.out(p, "surface or point cloud file: .ply, .obj or .glb (points: .ply or .obj)")
    p.add_argument("--level", type=float, help="the field's value on the surface (default: "
                   "Otsu's threshold of the vertex values, between the empty and the dense)")
    p.add_argument("--array", help="the point array the surface is a level of (default: "
                   "opacity, else attenuation, else the mesh's only scalar)")
    p.add_argument("--points", action="store_true", help="write the vertices at or above "
                   "the level as a colored point cloud instead of the surface")
    flags.mesh_flags(p)


def mesh_path(path: Path) -> Path:
    """The mesh file of ``path``: itself, or a fit folder's fitted mesh."""
    if not path.exists():
        raise FileNotFoundError(f"not found: {path}")
    if not path.is_dir():
        return path
    if not (path / "config.json").is_file():
        raise CommandError(f"{path} is a folder but not a fit's output (no config.json)")
    from mi_tetvr.recon.outputs import fitted_file
    from mi_tetvr.recon.plan import fit_settings
    name = fitted_file(fit_settings(path))
    if not name.endswith(".vtu"):
        raise CommandError(f"{path} fitted a transfer function, not a volume: export the "
                           f"mesh it classifies")
    if not (path / name).is_file():
        raise CommandError(f"{path} has no {name} yet (the fit writes it when it ends)")
    return path / name


def field_name(point_data: dict, array: str | None, path: Path) -> str:
    """The point array a surface is a level of (see ``--array``)."""
    scalars = sorted(k for k, v in point_data.items() if v.ndim == 1 or v.shape[1] == 1)
    if array is not None:
        if array not in point_data:
            raise CommandError(f"{path} has no point array '{array}' (it has: "
                               f"{', '.join(sorted(point_data)) or 'none'})")
        if array not in scalars:
            raise CommandError(f"--array {array}: a surface is a level of one value per "
                               f"vertex, and '{array}' has {point_data[array].shape[1]}")
        return array
    for name in ("opacity", "attenuation"):
        if name in point_data:
            return name
    if len(scalars) == 1:
        return scalars[0]
    raise CommandError(f"{path}: no opacity to take a level of; name the array with --array "
                       f"(scalar arrays: {', '.join(scalars) or 'none'})")


def run(a):
    import warnings

    import numpy as np

    from mi_tetvr.extras import require
    # (VTK through pyvista, trimesh, scikit-image: before any work)
    require("recon", "mi-tetvr export", "pyvista", "trimesh", "skimage")
    from mi_tetvr.mesh.export import (POINT_SUFFIXES, SUFFIXES, default_level, level_surface,
                                      write_points, write_surface)
    from mi_tetvr.mesh.io import read_tetmesh
    out = Path(a.out)
    suffixes = POINT_SUFFIXES if a.points else SUFFIXES
    if out.suffix.lower() not in suffixes:
        raise CommandError(f"-o {out}: {'point clouds' if a.points else 'surfaces'} go to "
                           f"{', '.join(suffixes)}")
    path = mesh_path(Path(a.path))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = read_tetmesh(path, color=None, opacity=None, repair=a.repair,
                            cell_to_point=a.cell_to_point)
    pd = {k: np.asarray(v, np.float64).reshape(len(mesh.vertices), -1)
          for k, v in mesh.point_data.items()}
    name = field_name(pd, a.array, path)
    values = pd[name][:, 0]
    colors = pd["color"][:, :3] if "color" in pd and pd["color"].shape[1] >= 3 else None
    if "sh" in pd:
        # view-dependent colors (which a tetmesh renders in place of any color array):
        # their mean over the directions, the degree-0 term (its spherical harmonic is
        # 1 / (2 sqrt(pi)))
        colors = np.maximum(pd["sh"][:, :3] * (0.5 / np.sqrt(np.pi)) + 0.5, 0.0)
    try:
        level = default_level(values, name) if a.level is None else a.level
        if a.points:
            keep = values >= level
            write_points(out, mesh.vertices[keep], None if colors is None else colors[keep])
            what = f"{int(keep.sum()):,} of {len(values):,} vertices ({name} >= {level:g})"
        else:
            surface = level_surface(mesh.vertices, mesh.tets, values, level, colors, name)
            write_surface(out, surface)
            what = (f"surface at {name} {level:g}: {len(surface.points):,} vertices, "
                    f"{len(surface.faces):,} triangles")
    except ValueError as e:
        raise CommandError(f"{path}: {e}") from None
    print(f"{path}: {what}{'' if colors is not None else ', no colors (light gray)'} -> {out}")
