"""Post-classified scalar fields (``tetmesh`` with a transfer function,
``classification="post"``) against the float64 reference that classifies
after interpolation (``tests.reference.reference_render_classified``), and
the errors for bad input."""
import json

import numpy as np
import pytest

import mitsuba as mi
import mi_tetvr
from mi_tetvr.transfer import read_transfer_function
from tests.helpers import (Problem, check_along, grid_field, interior_positions, make_rays,
                           rays_at, render_rays)
from tests.reference import reference_render_classified

TOL = 3e-3
RESOLUTION = 64
RANGE = (-1.0, 1.0)


@pytest.fixture(scope="module")
def peaked_tf(tmp_path_factory):
    """A transfer function with two narrow opacity peaks (1.5 % of the range
    wide) of different colors over a faint ramp."""
    path = tmp_path_factory.mktemp("tf") / "peaks.json"
    path.write_text(json.dumps({
        "color": [[0.0, 0.2, 0.2, 0.9], [0.3, 0.9, 0.2, 0.1], [0.7, 0.1, 0.9, 0.2],
                  [1.0, 0.9, 0.9, 0.9]],
        "opacity": [[0.0, 0.0], [0.29, 0.2], [0.3, 12.0], [0.31, 0.2], [0.69, 0.3],
                    [0.7, 9.0], [0.71, 0.3], [1.0, 0.4]],
        "colorspace": "linear"}))
    return path


@pytest.fixture(scope="module")
def field():
    """A jittered grid and a smooth scalar that spans the range several
    times across it (a tet's segment crosses several texels)."""
    return grid_field()


def interior(field):
    """Keeps a positions direction on the interior vertices."""
    mask = interior_positions(field[0], field[1])
    return lambda direction: direction * mask


def scene_of(field, tf_path, **props):
    V, T, scalar = field
    props = {"transfer_function": str(tf_path), "value_min": RANGE[0], "value_max": RANGE[1],
             "tf_resolution": RESOLUTION, **props}
    return mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                         "mesh0": mi_tetvr.tetmesh_dict(V, T, scalar=scalar, **props)})


def reference(field, tf_path, o, d):
    V, T, scalar = field
    color, opacity = read_transfer_function(tf_path).texels(RESOLUTION)
    return reference_render_classified(V, T, scalar, color, opacity, RANGE, o, d)


def test_post_classification_against_the_reference(field, peaked_tf):
    """Random rays through the jittered grid: post-classified within 3e-3 of
    the reference; the same mesh pre-classified (the vertices shaded, the
    colors interpolated) misses the peaks between vertices and is far off."""
    o, d = rays_at(np.random.default_rng(3), 256)
    ref_rgb, ref_alpha = reference(field, peaked_tf, o, d)
    rgb, alpha = render_rays(scene_of(field, peaked_tf), o, d)
    assert np.abs(rgb - ref_rgb).max() < TOL
    assert np.abs(alpha - ref_alpha).max() < TOL
    pre_rgb, pre_alpha = render_rays(scene_of(field, peaked_tf, classification="pre"), o, d)
    assert np.abs(pre_alpha - ref_alpha).max() > 0.1
    assert ref_alpha.max() > 0.5


def test_traverse_names_and_no_color_parameters(field, peaked_tf):
    params = mi.traverse(scene_of(field, peaked_tf))
    V = field[0]
    assert dr_width(params["mesh0.vertex_scalar"]) == len(V)
    assert dr_width(params["mesh0.tf_color"]) == 3 * RESOLUTION
    assert dr_width(params["mesh0.tf_opacity"]) == RESOLUTION
    assert "mesh0.vertex_color" not in params and "mesh0.vertex_opacity" not in params


def dr_width(x):
    import drjit as dr
    return dr.width(x)


def test_bad_input_is_refused(field, peaked_tf, tmp_path):
    V, T, scalar = field
    with pytest.raises(Exception, match="value_min < value_max"):
        scene_of(field, peaked_tf, value_min=0.5, value_max=0.5)
    bad = tmp_path / "nan.json"
    bad.write_text('{"color": [[0, 1, 1, 1]], "opacity": [[0, NaN], [1, 1]]}')
    with pytest.raises(Exception, match="non-finite"):
        scene_of(field, bad)
    neg = tmp_path / "neg.json"
    neg.write_text('{"color": [[0, 1, 1, 1]], "opacity": [[0, -1], [1, 1]]}')
    with pytest.raises(Exception, match=">= 0"):
        scene_of(field, neg)
    with pytest.raises(Exception, match="tf_resolution"):
        scene_of(field, peaked_tf, tf_resolution=1)
    with pytest.raises(Exception, match="classification"):
        scene_of(field, peaked_tf, classification="mid")


@pytest.mark.parametrize("key, h", [("mesh0.vertex_scalar", 1e-3), ("mesh0.tf_color", 1e-3),
                                    ("mesh0.tf_opacity", 1e-3),
                                    ("mesh0.vertex_positions", 1e-4)])
def test_gradients_against_finite_differences(field, peaked_tf, key, h):
    """Reverse mode against central differences (5 %) along random
    directions, forward against reverse (1 %), for the scalar, the transfer
    function's texels and the positions (interior vertices)."""
    rng = np.random.default_rng(11)
    o, d = rays_at(rng, 64)
    obj = Problem(None, o, d, rng, scene=scene_of(field, peaked_tf),
                  keys=("mesh0.vertex_scalar", "mesh0.tf_color", "mesh0.tf_opacity",
                        "mesh0.vertex_positions"))
    check_along(obj, key, h, rng, interior(field) if key.endswith("positions") else None)


def test_gradients_of_walks_that_stop_in_their_first_tet(field, peaked_tf):
    """Rays that end shortly past their entry (a surface or an isosurface in
    front, ``ray.maxt``), most inside the first tet they enter: each ray's
    reverse-mode gradient against central differences and forward mode
    (a walk that stopped inside its first tet once lost its entry face's
    gradients in reverse mode)."""
    rng = np.random.default_rng(5)
    o, d = rays_at(rng, 24, target_extent=0.6)
    scene = scene_of(field, peaked_tf)
    entry = np.array(scene.ray_intersect_preliminary(make_rays(o, d)).t)
    obj = Problem(None, o, d, rng, scene=scene, keys=("mesh0.vertex_scalar",))
    obj.ray.maxt = mi.Float(entry + rng.uniform(0.02, 0.08, len(o)))
    obj.wa[:] = 0.0
    weights = obj.wL.copy()
    direction = rng.normal(size=len(field[2]))
    for k in range(len(o)):
        obj.wL = np.zeros_like(weights)
        obj.wL[k] = weights[k]
        reverse = obj.backward()["mesh0.vertex_scalar"] @ direction
        fd = obj.central("mesh0.vertex_scalar", direction, 1e-3)
        forward = obj.forward({"mesh0.vertex_scalar": direction})
        assert abs(reverse - fd) <= 0.05 * abs(fd) + 1e-6, (k, reverse, fd)
        assert abs(forward - reverse) <= 1e-3 * abs(reverse) + 1e-7, (k, forward, reverse)


def test_real_mesh_against_the_reference(data_dir, peaked_tf):
    """SPX (12,936 tets, ``scalars`` in [0, 2.254]) post-classified with the
    peaked transfer function: within 3e-3 of the reference on random rays;
    pre-classified far off. A scalar array that does not exist is refused."""
    import warnings
    from mi_tetvr.mesh.io import read_tetmesh
    path = data_dir / "tets" / "spx" / "spx.vtk"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = read_tetmesh(path)
    V, T = mesh.vertices, mesh.tets
    scalar = mesh.point_data["scalars"].reshape(-1)
    lo, hi = mesh.bounds
    diag = float(np.linalg.norm(hi - lo))
    props = {"type": "tetmesh", "filename": str(path), "transfer_function": str(peaked_tf),
             "tf_resolution": RESOLUTION, "value_min": 0.0, "value_max": 2.254,
             "opacity_scale": 8.0 / diag}

    def scene(**extra):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                                 "mesh0": {**props, **extra}})
    rng = np.random.default_rng(5)
    o, d = rays_at(rng, 96, radius=diag, target_extent=0.3 * diag)
    o += (lo + hi) / 2
    color, opacity = read_transfer_function(peaked_tf).texels(RESOLUTION)
    ref_rgb, ref_alpha = reference_render_classified(V, T, scalar, color, opacity * 8.0 / diag,
                                                     (0.0, 2.254), o, d)
    rgb, alpha = render_rays(scene(), o, d)
    assert ref_alpha.max() > 0.3
    assert np.abs(rgb - ref_rgb).max() < TOL
    assert np.abs(alpha - ref_alpha).max() < TOL
    _, pre_alpha = render_rays(scene(classification="pre"), o, d)
    assert np.abs(pre_alpha - ref_alpha).max() > 0.1
    with pytest.raises(Exception, match="no point- or cell-data array 'nope'"):
        scene(scalar_attribute="nope")


def test_preintegrated_table(field, peaked_tf, tmp_path):
    """Weiler's pre-integrated table: close to the exact post-classification
    for a smooth transfer function, within a few percent for the narrow
    peaks (trilinear in front and back scalar), far better than
    pre-classification; differentiating it is refused."""
    o, d = rays_at(np.random.default_rng(4), 256)
    smooth = tmp_path / "smooth.json"
    smooth.write_text('{"color": [[0, 0.1, 0.3, 0.9], [1, 0.9, 0.5, 0.1]],'
                      ' "opacity": [[0, 0.2], [0.5, 2.0], [1, 0.5]]}')
    for tf, tol in ((smooth, 2e-3), (peaked_tf, 0.06)):
        exact, _ = render_rays(scene_of(field, tf), o, d)
        table, _ = render_rays(scene_of(field, tf, classification="preintegrated"), o, d)
        pre, _ = render_rays(scene_of(field, tf, classification="pre"), o, d)
        err = np.abs(table - exact).max()
        assert err < tol, err
        assert err < 0.2 * np.abs(pre - exact).max()
    scene = scene_of(field, peaked_tf, classification="preintegrated")
    params = mi.traverse(scene)
    import drjit as dr
    dr.enable_grad(params["mesh0.tf_opacity"])
    with pytest.raises(ValueError, match="no derivatives"):
        render_rays(scene, o[:4], d[:4])


LIGHTING = (0.15, 0.6, 0.3, 8.0)


def shaded_scene(field, tf_path):
    return scene_of(field, tf_path, shade=True,
                    **dict(zip(("ambient", "diffuse", "specular", "specular_power"), LIGHTING)))


def test_shaded_against_the_reference(field, peaked_tf):
    """shade (a headlight at each tet's gradient of the scalar, ParaView's
    Shade) against the float64 reference that lights the colors the same
    way (``reference_render_shaded``, its own float64 tet gradients): within
    3e-3, and far from the unlit image."""
    from tests.reference import reference_render_shaded
    V, T, scalar = field
    o, d = rays_at(np.random.default_rng(3), 256)
    color, opacity = read_transfer_function(peaked_tf).texels(RESOLUTION)
    ref_rgb, ref_alpha = reference_render_shaded(V, T, scalar, color, opacity, RANGE, LIGHTING,
                                                 o, d)
    rgb, alpha = render_rays(shaded_scene(field, peaked_tf), o, d)
    assert np.abs(rgb - ref_rgb).max() < TOL
    assert np.abs(alpha - ref_alpha).max() < TOL
    assert np.abs(render_rays(scene_of(field, peaked_tf), o, d)[0] - ref_rgb).max() > 0.05
    with pytest.raises(Exception, match="shade lights"):
        scene_of(field, peaked_tf, shade=True, classification="preintegrated")
    with pytest.raises(Exception, match="'ambient' lights"):
        scene_of(field, peaked_tf, ambient=0.3, classification="pre")


@pytest.mark.parametrize("key, h", [("mesh0.vertex_scalar", 1e-4), ("mesh0.tf_color", 1e-3),
                                    ("mesh0.vertex_positions", 1e-4)])
def test_shaded_gradients_against_finite_differences(field, peaked_tf, key, h):
    """The lit image's derivatives (through the normals too: a tet's
    gradient depends on its scalars and positions): reverse mode against
    central differences (5 %), forward against reverse (1 %). (The two-sided
    light |n.d| has a kink where a tet's gradient is across the ray: the
    steps are small enough not to reach one.)"""
    rng = np.random.default_rng(11)
    o, d = rays_at(rng, 64)
    keys = ("mesh0.vertex_scalar", "mesh0.tf_color", "mesh0.vertex_positions")
    obj = Problem(None, o, d, rng, scene=shaded_scene(field, peaked_tf), keys=keys)
    check_along(obj, key, h, rng, interior(field) if key.endswith("positions") else None)


def test_shaded_overlapping_another_mesh(field, peaked_tf):
    """A shaded mesh overlapped by a color mesh (the merged walk, one cursor
    per mesh, each piece lit at its cursor's tet's gradient): against the
    float64 reference of both as one medium, the shaded one lit alike; and
    its derivatives w.r.t. the scalar (reverse against central differences
    5 %, forward against reverse 1 %)."""
    from mi_tetvr.mesh.generate import grid_mesh
    from tests.reference import reference_render_meshes
    V, T, scalar = field
    rng = np.random.default_rng(13)
    VB, TB = grid_mesh(2, lo=(-0.4, -1.2, -0.3), hi=(1.3, 0.5, 1.1), jitter=0.1, seed=4)
    cB, oB = rng.uniform(0, 1, (len(VB), 3)), rng.uniform(0, 1.5, len(VB))
    lighting = dict(zip(("ambient", "diffuse", "specular", "specular_power"), LIGHTING))
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "tetvr"},
        "mesh0": mi_tetvr.tetmesh_dict(V, T, scalar=scalar, transfer_function=str(peaked_tf),
                                       value_min=RANGE[0], value_max=RANGE[1],
                                       tf_resolution=RESOLUTION, shade=True, **lighting),
        "mesh1": mi_tetvr.tetmesh_dict(VB, TB, cB, oB)})
    o, d = rays_at(rng, 256)
    color, opacity = read_transfer_function(peaked_tf).texels(RESOLUTION)
    ref_rgb, ref_alpha = reference_render_meshes(
        [dict(vertices=V, tets=T, scalar=scalar, tf_color=color, tf_opacity=opacity,
              value_range=RANGE, lighting=LIGHTING),
         dict(vertices=VB, tets=TB, color=cB, opacity=oB)], o, d)
    rgb, alpha = render_rays(scene, o, d)
    assert np.abs(rgb - ref_rgb).max() < TOL
    assert np.abs(alpha - ref_alpha).max() < TOL
    obj = Problem(None, o[:64], d[:64], rng, scene=scene, keys=("mesh0.vertex_scalar",))
    check_along(obj, "mesh0.vertex_scalar", 1e-4, rng)
