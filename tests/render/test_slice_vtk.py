"""Slices (``tetproj`` mode ``slice``) against VTK's: ``vtkCutter`` cuts the
same tet mesh by the plane (polygons carrying the scalar interpolated to
their points), Mitsuba's own ray tracer intersects their triangles along
the same rays, and the scalar there (linear on each triangle) and the
coverage agree with the slice's."""
import mitsuba as mi
import numpy as np

from mi_tetvr.mesh.generate import grid_mesh
from tests.helpers import make_rays, project_rays, rays_at, tetproj_scene, vtk_plane, vtk_tet_grid


def vtk_cut(V, T, scalar, origin, normal):
    """``(points, triangles, scalar at the points)`` of VTK's cut."""
    import pyvista as pv
    from vtkmodules.vtkFiltersCore import vtkCutter
    grid = vtk_tet_grid(V, T, s=scalar)
    cutter = vtkCutter()
    cutter.SetInputData(grid)
    cutter.SetCutFunction(vtk_plane(origin, normal))
    cutter.Update()
    out = pv.wrap(cutter.GetOutput()).triangulate()
    return (np.asarray(out.points, np.float64), out.faces.reshape(-1, 4)[:, 1:],
            np.asarray(out.point_data["s"], np.float64))


def test_slice_against_vtk_cutter():
    """The scalar within 1e-5 of the range wherever both meet the plane, and
    the same rays meet it but for a few grazing the cut's rim."""
    V, T = grid_mesh(5, jitter=0.12, seed=7)
    scalar = np.sin(2.2 * V[:, 0] + 1.3 * V[:, 1]) * np.cos(1.7 * V[:, 2])
    origin, normal = [0.1, -0.05, 0.2], [0.3, 0.2, 1.0]
    points, faces, values = vtk_cut(V, T, scalar, origin, normal)
    mesh = mi.Mesh("cut", len(points), len(faces))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(points.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    params.update()
    o, d = rays_at(np.random.default_rng(12), 400, target_extent=1.2)
    si = mi.load_dict({"type": "scene", "cut": mesh}).ray_intersect(make_rays(o, d))
    hit_vtk = np.array(si.is_valid(), bool)
    prim = np.array(si.prim_index, np.int64)
    u, v = np.array(si.uv, np.float64).reshape(2, -1)
    corners = values[faces[np.where(hit_vtk, prim, 0)]]
    s_vtk = (1 - u - v) * corners[:, 0] + u * corners[:, 1] + v * corners[:, 2]

    scene = tetproj_scene(V, T, scalar, mode="slice", origin=origin, normal=normal)
    _, met, s = project_rays(scene, o, d)
    both = met & hit_vtk
    assert both.sum() > 100
    assert np.abs(s[both] - s_vtk[both]).max() < 1e-5 * (scalar.max() - scalar.min())
    assert np.count_nonzero(met != hit_vtk) <= 2
