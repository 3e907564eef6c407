"""A volume out of the tool that made it: its surface at a level of a field, or its
vertices, as files that Blender, MeshLab and any glTF viewer open (``.ply``, ``.obj``,
``.glb``).

The surface is VTK's contour filter on the tets (marching tets: in each tet the field is
linear, so the level set is a triangle or a quad, cut into two triangles), which
interpolates the vertex colors linearly onto the surface's vertices: the colors there
are the field's own. Faces are wound so that their normals point down the field (out of
the dense region), as Blender and MeshLab light them. Colors are written as 8-bit sRGB,
what these programs expect of vertex colors; the mesh's colors are linear RGB.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_tetvr.color import linear_to_srgb
from mi_tetvr.extras import needs

__all__ = ["SUFFIXES", "POINT_SUFFIXES", "Surface", "default_level", "level_surface",
           "write_surface", "write_points"]

#: What a surface is written to (by trimesh).
SUFFIXES = (".ply", ".obj", ".glb")
#: What a point cloud is written to (glTF readers drop points' colors).
POINT_SUFFIXES = (".ply", ".obj")


@dataclass
class Surface:
    """A triangle mesh: ``points`` (n, 3), ``faces`` (m, 3) and linear RGB ``colors``
    (n, 3), or None."""
    points: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None


def _check_suffix(path: Path, suffixes: tuple[str, ...], what: str) -> None:
    if path.suffix.lower() not in suffixes:
        raise ValueError(f"{path}: {what} go to {', '.join(suffixes)}, not "
                         f"'{path.suffix or '(no extension)'}'")


def default_level(values: np.ndarray, name: str = "opacity") -> float:
    """The level between the field's empty and dense vertices: Otsu's threshold of
    the vertex values (scikit-image), which needs no scale and works on any units.
    A field that is constant has no surface: a ``ValueError``."""
    values = np.asarray(values, np.float64).ravel()
    lo, hi = float(values.min()), float(values.max())
    if not hi > lo:
        empty = " (an empty volume)" if hi == 0 else ""
        raise ValueError(f"no surface: the {name} is {lo:g} at every vertex{empty}")
    with needs("recon", "a surface's default level"):
        from skimage.filters import threshold_otsu
    return float(threshold_otsu(values))


def level_surface(vertices: np.ndarray, tets: np.ndarray, values: np.ndarray, level: float,
                  colors: np.ndarray | None = None, name: str = "opacity") -> Surface:
    """The surface where the field ``values`` (one per vertex, linear in each tet)
    equals ``level``, by VTK's contour filter, with ``colors`` (linear RGB per vertex)
    interpolated onto it. A level outside the field's range is a ``ValueError``
    (``name`` names the field in it)."""
    values = np.asarray(values, np.float64).ravel()
    lo, hi = float(values.min()), float(values.max())
    if not lo < level < hi:
        raise ValueError(f"no surface at {name} {level:g}: the {name} spans "
                         f"[{lo:g}, {hi:g}]" + (" (an empty volume)" if hi == 0 else ""))
    with needs("vis", "a volume's surface"):
        import pyvista as pv
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: np.asarray(tets, np.int64)},
                               np.asarray(vertices, np.float64))
    grid.point_data["field"] = values
    if colors is not None:
        grid.point_data["color"] = np.asarray(colors, np.float64)
    surf = grid.contour([level], scalars="field", method="contour").triangulate().clean()
    if surf.n_cells == 0:
        raise ValueError(f"no surface at {name} {level:g}")
    points = np.asarray(surf.points, np.float64)
    faces = np.asarray(surf.faces).reshape(-1, 4)[:, 1:]
    faces = _wound_down_the_field(vertices, tets, values, points, faces)
    rgb = np.asarray(surf.point_data["color"], np.float64) if colors is not None else None
    return Surface(points, faces, rgb)


def _wound_down_the_field(vertices, tets, values, points, faces):
    """``faces`` with each triangle's normal along the field's descent: the field a
    little way along the normal is below the field a little way back
    (:func:`~mi_tetvr.mesh.sample.sample_field`; outside the mesh it is 0)."""
    from mi_tetvr.mesh.sample import sample_field
    normal = np.cross(points[faces[:, 1]] - points[faces[:, 0]],
                      points[faces[:, 2]] - points[faces[:, 0]])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = normal / np.where(length > 0, length, 1.0)
    centre = points[faces].mean(1)
    step = 1e-3 * float(np.linalg.norm(np.ptp(np.asarray(vertices), axis=0)))
    ahead = sample_field(vertices, tets, values, centre + step * normal)
    behind = sample_field(vertices, tets, values, centre - step * normal)
    faces = faces.copy()
    flip = ahead > behind
    faces[flip] = faces[flip][:, ::-1]
    return faces


def _srgb8(colors: np.ndarray | None, n: int) -> np.ndarray:
    """RGBA 8-bit sRGB of linear RGB ``colors`` (light gray when None)."""
    rgb = np.full((n, 3), 0.8) if colors is None else np.clip(colors, 0.0, 1.0)
    rgba = np.empty((n, 4), np.uint8)
    rgba[:, :3] = np.round(linear_to_srgb(rgb) * 255.0)
    rgba[:, 3] = 255
    return rgba


def write_surface(path, surface: Surface) -> None:
    """Write ``surface`` to ``path`` (:data:`SUFFIXES`, by trimesh), its colors as
    8-bit sRGB vertex colors."""
    path = Path(path)
    _check_suffix(path, SUFFIXES, "surfaces")
    with needs("recon", "writing a surface"):
        import trimesh
    mesh = trimesh.Trimesh(surface.points, surface.faces, process=False,
                           vertex_colors=_srgb8(surface.colors, len(surface.points)))
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(path)


def write_points(path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write ``points`` (n, 3) with linear RGB ``colors`` as a point cloud
    (:data:`POINT_SUFFIXES`, by trimesh), colors as 8-bit sRGB."""
    path = Path(path)
    _check_suffix(path, POINT_SUFFIXES, "point clouds")
    if len(points) == 0:
        raise ValueError(f"{path}: no points to write")
    with needs("recon", "writing a point cloud"):
        import trimesh
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.PointCloud(np.asarray(points, np.float64),
                       colors=_srgb8(colors, len(points))).export(path)
