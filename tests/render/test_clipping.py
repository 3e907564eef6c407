"""Clipping (``clip_origin``/``clip_normal``, ``clip_min``/``clip_max`` of
``tetvr`` and ``tetproj``) against the mesh cut by VTK: ``vtkClipDataSet``
cuts the tet mesh at the plane, or at the box's six planes one after the
other (new vertices carry the interpolated color and opacity; a plane's
function is linear, so the cut is exact, which ``vtkBox``'s distance is not
inside a tet), ``vtkDataSetTriangleFilter`` makes the cut cells tets, and the
float64 reference renders that mesh."""
import numpy as np
import pytest

from mi_tetvr.mesh.generate import grid_mesh
from tests.helpers import (make_scene, project_rays, rays_at, render_rays,
                           tetproj_scene, vtk_plane, vtk_tet_grid)
from tests.reference import reference_projection, reference_render

TOL = 3e-3          # tetvr's default settings against the reference (as tests/render)


@pytest.fixture(scope="module")
def mesh():
    rng = np.random.default_rng(8)
    V, T = grid_mesh(4, jitter=0.12, seed=3)
    return V, T, rng.uniform(0, 1, (len(V), 3)), rng.uniform(0, 2.5, len(V))


def vtk_clip(V, T, arrays, planes):
    """The mesh cut by VTK at ``planes`` ((origin, normal), ...: what the
    normals point to is cut away) as tets with its point arrays."""
    import pyvista as pv
    from vtkmodules.vtkFiltersGeneral import vtkClipDataSet, vtkDataSetTriangleFilter
    grid = vtk_tet_grid(V, T, **arrays)
    data = grid
    for origin, normal in planes:
        clip = vtkClipDataSet()
        clip.SetInputData(data)
        clip.SetClipFunction(vtk_plane(origin, normal))
        clip.InsideOutOn()          # keep where (p - origin) . normal <= 0
        clip.Update()
        data = clip.GetOutput()
    tri = vtkDataSetTriangleFilter()
    tri.SetInputData(data)
    tri.Update()
    out = pv.wrap(tri.GetOutput())
    cells = out.cells_dict[pv.CellType.TETRA]
    return np.asarray(out.points, np.float64), cells, {k: np.asarray(out.point_data[k])
                                                       for k in arrays}


def box_planes(lo, hi):
    eye = np.eye(3)
    return [(lo, tuple(-eye[i])) for i in range(3)] + [(hi, tuple(eye[i])) for i in range(3)]


@pytest.mark.parametrize("cut", ["plane", "box"])
def test_clip_against_the_mesh_cut_by_vtk(mesh, cut):
    V, T, C, S = mesh
    plane = ((0.1, -0.05, 0.0), (0.6, 0.3, -0.74))
    box = ((-0.7, -0.4, -0.9), (0.5, 0.8, 0.3))
    if cut == "plane":
        props = {"clip_origin": list(plane[0]), "clip_normal": list(plane[1])}
        Vc, Tc, arrays = vtk_clip(V, T, {"color": C, "opacity": S}, [plane])
    else:
        props = {"clip_min": list(box[0]), "clip_max": list(box[1])}
        Vc, Tc, arrays = vtk_clip(V, T, {"color": C, "opacity": S}, box_planes(*box))
    o, d = rays_at(np.random.default_rng(4), 256, target_extent=1.2)
    rgb, alpha = render_rays(make_scene(mesh, **props), o, d)
    ref_rgb, ref_alpha = reference_render(Vc, Tc, arrays["color"], arrays["opacity"], o, d)
    assert np.abs(rgb - ref_rgb).max() < TOL
    assert np.abs(alpha - ref_alpha).max() < TOL
    full, _ = render_rays(make_scene(mesh), o, d)
    assert np.abs(full - rgb).max() > 0.1          # the cut changes the picture


def test_clipped_projection_against_the_mesh_cut_by_vtk(mesh):
    """tetproj's maximum on the clipped mesh: the reference's on VTK's cut."""
    V, T, _, _ = mesh
    scalar = np.sin(2.0 * V[:, 0] - V[:, 1]) * np.cos(1.5 * V[:, 2])
    plane = ((0.0, 0.1, 0.05), (-0.3, 1.0, 0.2))
    Vc, Tc, arrays = vtk_clip(V, T, {"s": scalar}, [plane])
    o, d = rays_at(np.random.default_rng(6), 256, target_extent=1.2)
    ref, ref_met = reference_projection(Vc, Tc, arrays["s"], o, d, "max")
    scene = tetproj_scene(V, T, scalar, clip_origin=list(plane[0]),
                          clip_normal=list(plane[1]))
    _, met, value = project_rays(scene, o, d)
    both = met & ref_met
    assert both.sum() > 50 and np.count_nonzero(met != ref_met) <= 2   # grazing the cut
    np.testing.assert_allclose(value[both], ref[both], atol=1e-5)


def test_clipped_gradients_against_finite_differences():
    """The adjoint walks the same clipped interval: gradients w.r.t. colors,
    opacities and positions of a mesh cut by a plane and a box match central
    differences (5 %, as tests/render/test_gradients.py)."""
    from tests.render.test_gradients import check_fd, jittered
    from tests.helpers import Problem
    rng = np.random.default_rng(22)
    m = jittered(rng)
    o, d = rays_at(rng, 64)
    scene = make_scene(m, clip_origin=[0.05, 0.1, 0.0], clip_normal=[0.5, -0.2, 0.8],
                       clip_min=[-0.8, -0.6, -0.9], clip_max=[0.7, 0.9, 0.8])
    check_fd(Problem(m, o, d, rng, scene=scene), rng)
