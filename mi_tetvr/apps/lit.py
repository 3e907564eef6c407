"""A scalar mesh lit by a scene's emitters (``render MESH --lights XML``):
the volume as a scattering medium, its isosurfaces and slices as surfaces,
path traced with shadows.

The surfaces are VTK's: its contour filter for isosurfaces and its cut for a
slice plane (through pyvista), turned into Mitsuba meshes with a diffuse BSDF
of the transfer function's color (per vertex for a slice). ``--mode dvr``
renders the volume with ``tetpath`` (the transfer function's colors its
albedo, its opacity the extinction, classified at the vertices), the
surfaces inside it lit through it; ``--mode iso|slice`` renders the surfaces
alone with Mitsuba's own ``path``.
"""
from __future__ import annotations

import numpy as np

from mi_tetvr.extras import needs

__all__ = ["lit_scene", "surface_meshes"]

#: Samples per pixel of a lit render without ``--spp``.
LIT_SPP = 64


def _mitsuba_mesh(name, polydata, shade, per_vertex):
    """A Mitsuba mesh of a pyvista surface (triangulated), with smooth
    vertex normals and a diffuse BSDF of the transfer function's color
    (``shade``) at its scalar ``s``: one color (an isosurface's), or per
    vertex (a ``mesh_attribute``)."""
    import mitsuba as mi
    tri = polydata.triangulate().clean()
    tri = tri.compute_normals(cell_normals=False, point_normals=True, auto_orient_normals=False,
                              consistent_normals=True, split_vertices=False)
    faces = np.asarray(tri.faces).reshape(-1, 4)[:, 1:]
    points = np.asarray(tri.points, np.float32)
    values = np.asarray(tri.point_data["s"], np.float64)
    colors = shade(values) if per_vertex else shade(values.mean())[0]
    reflectance = ({"type": "mesh_attribute", "name": "vertex_color"} if per_vertex
                   else {"type": "rgb", "value": [float(c) for c in colors]})
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "twosided", "bsdf": {
        "type": "diffuse", "reflectance": reflectance}})
    mesh = mi.Mesh(name, len(points), len(faces), props, True, False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(points.ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    params["vertex_normals"] = mi.Float(np.asarray(tri.point_data["Normals"],
                                                   np.float32).ravel())
    if per_vertex:
        mesh.add_attribute("vertex_color", 3, mi.Float(np.asarray(colors, np.float32).ravel()))
    params.update()
    return mesh


def surface_meshes(mesh, scalar, tf, value_range, surface, iso=None, plane=None):
    """``{name: Mitsuba mesh}`` of the isosurfaces (``surface="iso"`` at the
    values ``iso``) or the slice (``"slice"``, ``plane`` = point and normal)
    of the tet mesh's ``scalar`` (point data), colored by the transfer
    function ``tf`` over ``value_range``; ValueError where they are empty."""
    with needs("vis", "lighting a scalar mesh's isosurfaces and slice (VTK)"):
        import pyvista as pv
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: np.asarray(mesh.tets, np.int64)},
                               np.asarray(mesh.vertices, np.float64))
    values = np.asarray(mesh.point_data[scalar], np.float64)
    grid.point_data["s"] = values
    lo, hi = value_range

    def shade(v):
        color, _ = tf.shade(np.atleast_1d(np.asarray(v, np.float64)), (lo, hi))
        return np.clip(color, 0.0, 1.0)
    out = {}
    if surface == "iso":
        for k, v in enumerate(iso):
            poly = grid.contour([float(v)], scalars="s")
            if poly.n_cells == 0:
                raise ValueError(f"--lights: no isosurface at {v:g} (the scalar spans "
                                 f"[{values.min():g}, {values.max():g}])")
            out[f"isosurface_{k}"] = _mitsuba_mesh(f"isosurface_{k}", poly, shade, False)
    else:
        poly = grid.slice(normal=tuple(plane[3:]), origin=tuple(plane[:3]))
        if poly.n_cells == 0:
            raise ValueError(f"--lights: the plane {tuple(plane)} misses the mesh")
        out["slice"] = _mitsuba_mesh("slice", poly, shade, True)
    return out


def lit_scene(settings, mesh, framing, scene, props):
    """The scene of ``render MESH --lights XML`` (see the module docstring):
    the framing's camera (``scene``: :func:`~mi_tetvr.apps.framing.framed_scene`'s
    dict, completed here), the lights' scene, and the volume or its surfaces
    (``props``: :func:`~mi_tetvr.apps.framing.shape_props`'s)."""
    import mi_tetvr
    from mi_tetvr.render.surfaces import lights_scene
    from mi_tetvr.transfer import read_transfer_function
    s = settings
    scene["sensor"]["sampler"] = {"type": "independent", "sample_count": s.spp or LIT_SPP}
    scene.update(lights_scene(s.lights))
    value_range = (props["value_min"], props["value_max"])
    surface = s.surface
    if surface is not None:
        tf = read_transfer_function(props["transfer_function"])
        lo, hi = framing["lo"], framing["hi"]
        iso = s.iso or (sum(framing["value_range"]) / 2,)
        plane = s.plane or (*((lo + hi) / 2), *s.up_axis)
        scene.update(surface_meshes(mesh, props["scalar_attribute"], tf, value_range, surface,
                                    iso, plane))
    if s.mode == "dvr":
        name = props.pop("scalar_attribute")
        scene["integrator"] = {"type": "tetpath"}
        scene["volume"] = mi_tetvr.tetmesh_dict(mesh.vertices, mesh.tets,
                                                scalar=mesh.point_data[name], **props,
                                                classification="pre", albedo="color")
    else:
        scene["integrator"] = {"type": "path"}
    return scene
