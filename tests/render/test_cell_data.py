"""Cell data (one scalar per tet) classified by a transfer function and
rendered as it is, constant in each tet, against the float64 reference on
the same mesh exploded (each tet with its own four vertices, all of them
carrying the tet's color and extinction: nothing averaged); the same image
when the shape stores its tets reordered; gradients against finite
differences; files, errors."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_tetvr
from mi_tetvr.mesh.generate import grid_mesh
from tests.helpers import Problem, check_along, interior_positions, rays_at, render_rays
from tests.reference import reference_render

RANGE = (-1.0, 1.0)
RESOLUTION = 16


@pytest.fixture(scope="module")
def cells():
    """A jittered grid, a scalar per tet and random texels."""
    rng = np.random.default_rng(21)
    V, T = grid_mesh(4, jitter=0.12, seed=7)
    c = V[T].mean(1)
    values = np.sin(2.2 * c[:, 0] + 1.3 * c[:, 1]) * np.cos(1.7 * c[:, 2])
    values += 0.3 * rng.normal(size=len(T))            # not a smooth field
    tf_color = rng.uniform(0.1, 1.0, (RESOLUTION, 3))
    tf_opacity = rng.uniform(0.0, 3.0, RESOLUTION)
    return V, T, values, tf_color, tf_opacity


def scene_of(V, T, values, tf_color, tf_opacity, **props):
    return mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                         "mesh0": mi_tetvr.tetmesh_dict(
                             V, T, cell_scalar=values, **texels(tf_color, tf_opacity),
                             value_min=RANGE[0], value_max=RANGE[1], **props)})


def texels(tf_color, tf_opacity):
    return {"tf_color": mi.TensorXf(np.asarray(tf_color, np.float32)),
            "tf_opacity": mi.TensorXf(np.asarray(tf_opacity, np.float32))}


def classify(values, texels):
    """The texels' linear interpolation at ``values`` (constant outside the
    first and last texel centres)."""
    lo, hi = RANGE
    centres = lo + (np.arange(RESOLUTION) + 0.5) * (hi - lo) / RESOLUTION
    texels = np.asarray(texels, np.float64).reshape(RESOLUTION, -1)
    return np.stack([np.interp(values, centres, texels[:, j]) for j in
                     range(texels.shape[1])], 1)


def test_cell_data_against_the_exploded_reference(cells):
    V, T, values, tf_color, tf_opacity = cells
    o, d = rays_at(np.random.default_rng(3), 256)
    rgb, alpha = render_rays(scene_of(*cells), o, d)
    Vx = V[T].reshape(-1, 3)
    Tx = np.arange(4 * len(T)).reshape(-1, 4)
    ref_rgb, ref_alpha = reference_render(Vx, Tx, np.repeat(classify(values, tf_color), 4, 0),
                                          np.repeat(classify(values, tf_opacity)[:, 0], 4),
                                          o, d)
    assert ref_alpha.max() > 0.5
    assert np.abs(rgb - ref_rgb).max() < 1e-4
    assert np.abs(alpha - ref_alpha).max() < 1e-4
    # Averaged onto the vertices (what cell_to_point does), the image differs.
    avg = mi_tetvr.mesh.io.cell_to_point_data(V, T, {"s": values})["s"]
    smooth = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                           "mesh0": mi_tetvr.tetmesh_dict(
                               V, T, scalar=avg, **texels(tf_color, tf_opacity),
                               value_min=RANGE[0], value_max=RANGE[1])})
    assert np.abs(render_rays(smooth, o, d)[0] - ref_rgb).max() > 0.05


def test_cell_data_overlapping_another_mesh(cells):
    """Cell data overlapped by a color mesh (the merged walk, one cursor per
    mesh, each cell's value read in its cursor's tet): against the float64
    reference of both as one medium, the cell mesh exploded; and the
    derivatives w.r.t. the cell values where they stay between two knots
    (reverse against central differences 5 %, forward against reverse 1 %)."""
    from tests.reference import reference_render_meshes
    V, T, values, tf_color, tf_opacity = cells
    rng = np.random.default_rng(8)
    VB, TB = grid_mesh(2, lo=(-0.3, -1.2, -0.4), hi=(1.2, 0.4, 1.1), jitter=0.1, seed=9)
    cB, oB = rng.uniform(0, 1, (len(VB), 3)), rng.uniform(0, 1.5, len(VB))
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "mesh0": scene_of(*cells).shapes()[0],
                          "mesh1": mi_tetvr.tetmesh_dict(VB, TB, cB, oB)})
    o, d = rays_at(rng, 256)
    rgb, alpha = render_rays(scene, o, d)
    Vx = V[T].reshape(-1, 3)
    Tx = np.arange(4 * len(T)).reshape(-1, 4)
    ref_rgb, ref_alpha = reference_render_meshes(
        [dict(vertices=Vx, tets=Tx, color=np.repeat(classify(values, tf_color), 4, 0),
              opacity=np.repeat(classify(values, tf_opacity)[:, 0], 4)),
         dict(vertices=VB, tets=TB, color=cB, opacity=oB)], o, d)
    assert np.abs(rgb - ref_rgb).max() < 3e-3
    assert np.abs(alpha - ref_alpha).max() < 3e-3
    h = 1e-3
    knots = RANGE[0] + (np.arange(RESOLUTION) + 0.5) * (RANGE[1] - RANGE[0]) / RESOLUTION
    gap = np.abs(values[:, None] - knots[None]).min(1)
    obj = Problem(None, o[:64], d[:64], rng, scene=scene, keys=("mesh0.cell_scalar",))
    check_along(obj, "mesh0.cell_scalar", h, rng,
                lambda direction: direction * (gap > 10 * h * np.abs(direction)))


@pytest.fixture
def reordering(monkeypatch):
    """Shapes store shuffled tets in Morton order, small as they are."""
    from mi_tetvr.render import buffers
    monkeypatch.setattr(buffers, "FAR_RECORDS", 8)


def test_reordered_tets_read_their_own_cells(cells, reordering):
    """Tets listed in shuffled order are stored in Morton order by the
    shape (``cell_order``): each still shows its own value."""
    V, T, values, tf_color, tf_opacity = cells
    perm = np.random.default_rng(5).permutation(len(T))
    shuffled = scene_of(V, T[perm], values[perm], tf_color, tf_opacity)
    assert shuffled.shapes()[0].cell_order is not None
    assert scene_of(*cells).shapes()[0].cell_order is None
    o, d = rays_at(np.random.default_rng(4), 128)
    a, b = render_rays(scene_of(*cells), o, d), render_rays(shuffled, o, d)
    assert a[1].max() > 0.5
    assert np.abs(a[0] - b[0]).max() < 1e-5 and np.abs(a[1] - b[1]).max() < 1e-5


@pytest.mark.parametrize("key, h", [("mesh0.cell_scalar", 1e-3), ("mesh0.tf_color", 1e-3),
                                    ("mesh0.tf_opacity", 1e-3),
                                    ("mesh0.vertex_positions", 1e-4)])
def test_cell_gradients_against_finite_differences(cells, reordering, key, h):
    """Reverse mode against central differences (5 %) along random
    directions, forward against reverse (1 %); the tets reordered, so that
    the cells' gradients go back through ``cell_order``."""
    V, T, values, tf_color, tf_opacity = cells
    perm = np.random.default_rng(5).permutation(len(T))
    rng = np.random.default_rng(11)
    o, d = rays_at(rng, 64)
    obj = Problem(None, o, d, rng, scene=scene_of(V, T[perm], values[perm], tf_color,
                                                  tf_opacity),
                  keys=("mesh0.cell_scalar", "mesh0.tf_color", "mesh0.tf_opacity",
                        "mesh0.vertex_positions"))
    restrict = None
    if key.endswith("cell_scalar"):
        # Cells whose value stays between two knots of the transfer function
        # (texel centres) over the differences' step: the image is smooth there.
        knots = RANGE[0] + (np.arange(RESOLUTION) + 0.5) * (RANGE[1] - RANGE[0]) / RESOLUTION
        gap = np.abs(values[perm][:, None] - knots[None]).min(1)
        restrict = lambda direction: direction * (gap > 10 * h * np.abs(direction))  # noqa: E731
    if key.endswith("positions"):
        mask = interior_positions(V, T)
        restrict = lambda direction: direction * mask  # noqa: E731
    check_along(obj, key, h, rng, restrict)


def test_cell_data_from_a_file_and_refusals(cells, tmp_path):
    """A .vtu's cell array named by scalar_attribute renders as the arrays
    do; the only scalar array is taken without a name; preintegrated and
    tetproj say why they do not take cell data."""
    V, T, values, tf_color, tf_opacity = cells
    path = tmp_path / "cells.vtu"
    mi_tetvr.write_tetmesh(path, mi_tetvr.TetMesh(V, T, cell_data={"pressure": values}),
                           color=None, opacity=None)
    o, d = rays_at(np.random.default_rng(6), 64)
    want = render_rays(scene_of(*cells), o, d)[0]
    for extra in ({"scalar_attribute": "pressure"}, {}):
        scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                              "mesh0": {"type": "tetmesh", "filename": str(path),
                                        **texels(tf_color, tf_opacity), "value_min": RANGE[0],
                                        "value_max": RANGE[1], **extra}})
        assert np.abs(render_rays(scene, o, d)[0] - want).max() < 1e-6
    with pytest.raises(Exception, match="classification 'post'"):
        scene_of(*cells, classification="preintegrated")
    with pytest.raises(Exception, match="cell data"):
        proj = mi.load_dict({"type": "scene", "integrator": {"type": "tetproj"},
                             "mesh0": scene_of(*cells).shapes()[0]})
        with dr.suspend_grad():
            proj.integrator().tet_group(proj)
