"""``render_rays``: any batch of rays through the scene's tet meshes, RGBA per
ray. Its values against the float64 brute-force reference renderer
(:mod:`tests.reference`, which shares no code with the renderer) and against
``mi.render``'s pixels at pixel-centre rays; its derivatives w.r.t. the
vertex values and positions and w.r.t. the rays' origins and directions
against central finite differences (reverse mode) and reverse mode
(forward mode); its refusals."""
import numpy as np
import pytest

import drjit as dr
import mitsuba as mi
import mi_tetvr
from mi_tetvr.camera import Camera
from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.rays import render_rays
from tests.helpers import interior_positions, make_scene, rays_at
from tests.reference import reference_render

#: Rays per batch in every test of the module (one set of kernels).
K = 64
#: Against the reference at the default settings (colors in [0, 1]), as the
#: renderer's own tests.
TOL = 3e-3


def smooth_volume(rng):
    """A jittered grid whose extinction vanishes on the boundary (the
    silhouette has no jump: the image is smooth in the rays)."""
    V, T = grid_mesh(4, jitter=0.1, seed=2)
    C = rng.uniform(0.1, 0.9, (len(V), 3))
    S = 3.0 * np.exp(-3 * (V ** 2).sum(1)) * (np.abs(V).max(1) < 0.99)
    return V, T, C, S


@pytest.fixture(scope="module")
def volume():
    rng = np.random.default_rng(7)
    mesh = smooth_volume(rng)
    return mesh, make_scene(mesh, background=(0.2, 0.3, 0.4))


def batch(seed):
    """K rays from a sphere towards the volume, each with a near and a far
    end (some near ends inside the volume)."""
    rng = np.random.default_rng(seed)
    o, d = rays_at(rng, K, radius=3.0)
    near = rng.uniform(0.0, 3.5, K)
    far = near + rng.uniform(0.5, 4.0, K)
    return o, d, np.stack([near, far], 1)


def test_matches_reference_with_extents(volume):
    """RGBA of rays cut to their extents (a near end inside the volume starts
    there) against the float64 reference of the same segments, with the
    environment seen through what is left."""
    (V, T, C, S), scene = volume
    o, d, ext = batch(1)
    rgba = np.array(render_rays(scene, o, d, ext), np.float64)
    assert rgba.shape == (K, 4)
    rgb, alpha = reference_render(V, T, C, S, o + ext[:, :1] * d, d,
                                  background=(0.2, 0.3, 0.4), t_max=ext[:, 1] - ext[:, 0])
    assert np.abs(rgba[:, :3] - rgb).max() < TOL
    assert np.abs(rgba[:, 3] - alpha).max() < TOL
    assert (alpha > 0.05).sum() > K // 4 and (alpha < 1e-6).sum() > 0   # some hit, some miss
    # a far end alone, and none: the same as the reference over (0, far) and (0, inf)
    far = np.array(render_rays(scene, o, d, ext[:, 1]), np.float64)
    ref_far = reference_render(V, T, C, S, o, d, background=(0.2, 0.3, 0.4), t_max=ext[:, 1])
    assert np.abs(far[:, 3] - ref_far[1]).max() < TOL
    whole = np.array(render_rays(scene, o, d), np.float64)
    ref_whole = reference_render(V, T, C, S, o, d, background=(0.2, 0.3, 0.4))
    assert np.abs(whole[:, :3] - ref_whole[0]).max() < TOL


def test_pixel_centres_give_mi_render_pixels():
    """The rays through the pixel centres of a camera (the project's
    ``Camera.rays_drjit`` and the sensor's own ``sample_ray``) give the
    pixels ``mi.render`` gives (one sample per pixel at its centre, box
    filter), alpha its AOV."""
    rng = np.random.default_rng(3)
    V, T, C, S = smooth_volume(rng)
    cam = Camera.look_at([2.5, 1.5, 3.0], [0, 0, 0], [0, 1, 0], 16, 12, fov_x=40.0)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "sensor": cam.sensor_dict(sampler="stratified", jitter=False),
                          "env": {"type": "constant", "radiance": 0.25},
                          "mesh0": mi_tetvr.tetmesh_dict(V, T, C, S)})
    image = np.array(mi.render(scene, spp=1), np.float64)
    assert image.shape == (12, 16, 4) and image[..., 3].max() > 0.3
    ray = cam.rays_drjit()
    rgba = np.array(render_rays(scene, ray.o, ray.d), np.float64).reshape(12, 16, 4)
    np.testing.assert_allclose(rgba, image, atol=2e-6)
    # the sensor's rays at the pixel centres
    idx = dr.arange(mi.UInt32, 16 * 12)
    pos = mi.Point2f((mi.Float(idx % 16) + 0.5) / 16, (mi.Float(idx // 16) + 0.5) / 12)
    sray, _ = scene.sensors()[0].sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    rgba = np.array(render_rays(scene, sray.o, sray.d), np.float64).reshape(12, 16, 4)
    np.testing.assert_allclose(rgba, image, atol=1e-6)


def test_gradients_against_finite_differences(volume):
    """Reverse mode of a random weighting of the RGBA w.r.t. the vertex
    colors, opacities and (interior) positions and the rays' origins and
    directions, along random directions, against central differences
    (5 %); forward mode against reverse (1 %). All are differentiated at
    once (one kernel per mode)."""
    (V, T, C, S), scene = volume
    params = mi.traverse(scene)
    o, d, ext = batch(2)
    rng = np.random.default_rng(4)
    W = mi.TensorXf(rng.normal(size=(K, 4)).astype(np.float32))
    keys = ("mesh0.vertex_color", "mesh0.vertex_opacity", "mesh0.vertex_positions")
    base = {k: np.array(params[k], np.float64) for k in keys}
    base["o"], base["d"] = o.ravel(), d.ravel()
    along = {k: rng.normal(size=len(v)) for k, v in base.items()}
    along["mesh0.vertex_positions"] *= interior_positions(V, T)
    steps = {"mesh0.vertex_color": 1e-2, "mesh0.vertex_opacity": 1e-2,
             "mesh0.vertex_positions": 1e-3, "o": 1e-3, "d": 1e-3}

    def loss(x, tangents=None):
        """The loss at values ``x`` (key -> flat array), tangents on all."""
        for k in keys:
            params[k] = mi.Float(x[k].astype(np.float32))
        params.update()
        O = mi.Point3f(*x["o"].reshape(-1, 3).T.astype(np.float32))
        D = mi.Vector3f(*x["d"].reshape(-1, 3).T.astype(np.float32))
        if tangents is not None:
            for k in keys:
                dr.enable_grad(params[k])
                dr.set_grad(params[k], mi.Float(tangents[k].astype(np.float32)))
            dr.enable_grad(O, D)
            dr.set_grad(O, mi.Point3f(*tangents["o"].reshape(-1, 3).T.astype(np.float32)))
            dr.set_grad(D, mi.Vector3f(*tangents["d"].reshape(-1, 3).T.astype(np.float32)))
        return O, D, dr.sum(render_rays(scene, O, D, ext, params=params) * W, axis=None)

    zero = {k: np.zeros_like(v) for k, v in base.items()}
    O, D, value = loss(base, zero)
    dr.backward(value)
    grads = {k: np.array(dr.grad(params[k]), np.float64) for k in keys}
    grads["o"] = np.array(dr.grad(O), np.float64).T.ravel()
    grads["d"] = np.array(dr.grad(D), np.float64).T.ravel()
    for k in keys:
        dr.disable_grad(params[k])
    reverse = {k: float(grads[k] @ along[k]) for k in base}
    forward = float(np.array(dr.forward_to(loss(base, along)[2])).ravel()[0])
    for k in keys:
        dr.disable_grad(params[k])
    assert abs(forward - sum(reverse.values())) < 0.01 * sum(map(abs, reverse.values()))
    for k, h in steps.items():
        plus = {**base, k: base[k] + h * along[k]}
        minus = {**base, k: base[k] - h * along[k]}
        fd = (float(np.array(loss(plus)[2]).ravel()[0])
              - float(np.array(loss(minus)[2]).ravel()[0])) / (2 * h)
        assert abs(fd) > 1e-2, (k, fd)
        assert abs(reverse[k] - fd) < 0.05 * abs(fd), (k, reverse[k], fd)
    loss(base)


def test_refusals(volume):
    """Rays of the wrong shape, NaN or zero rays, bad extents, a scene
    without a tet mesh and an integrator that is not tetvr: one clear
    ValueError each, before anything runs."""
    _, scene = volume
    o, d, ext = batch(3)
    cases = [
        (dict(origins=o[:, :2], directions=d), r"origins must have shape \(k, 3\)"),
        (dict(origins=o, directions=d[:10]), "64 origins and 10 directions"),
        (dict(origins=np.where(np.arange(K)[:, None] == 5, np.nan, o), directions=d),
         "1 of 64 rays' origins are not finite"),
        (dict(origins=o, directions=0 * d), "64 of 64 rays' directions are zero"),
        (dict(origins=o, directions=d, extents=ext[:, ::-1]), "near < far"),
        (dict(origins=o, directions=d, extents=ext[:5]), "extents must be"),
    ]
    for kw, match in cases:
        with pytest.raises(ValueError, match=match):
            render_rays(scene, **kw)
    empty = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "ball": {"type": "sphere"}})
    with pytest.raises(ValueError, match="no tetmesh"):
        render_rays(empty, o, d)
    with pytest.raises(ValueError, match="tetvr integrator"):
        render_rays(scene, o, d, integrator=mi.load_dict({"type": "path"}))


def test_surfaces_behind_and_inside():
    """With surfaces (a sphere inside the volume, a floor and a wall behind it, a
    point light, the nested ``prb`` at direct light): each ray is the float64
    volume clipped at the analytic hit plus its transmittance times the
    closed-form diffuse radiance (tests/render/test_surfaces.py's references),
    alpha 1 where a surface is hit; the colors' gradient (the derivative pass
    renders its own primal, the nested integrator's paths) against central
    differences."""
    from tests.render.test_surfaces import analytic_surfaces, camera_rays, scene_with, volume
    rng = np.random.default_rng(41)
    mesh = volume(np.random.default_rng(40))
    o, d = camera_rays(rng, K)
    scene = scene_with(mesh, nested={"type": "prb", "max_depth": 2})
    rgba = np.array(render_rays(scene, o, d), np.float64)
    t_hit, L_surf = analytic_surfaces(o, d)
    hit = np.isfinite(t_hit)
    C, a = reference_render(*mesh, o, d, t_max=np.where(hit, t_hit, np.inf))
    assert np.abs(rgba[:, :3] - (C + (1.0 - a)[:, None] * L_surf)).max() < TOL
    np.testing.assert_allclose(rgba[hit, 3], 1.0)
    assert np.abs(rgba[~hit, 3] - a[~hit]).max() < TOL and hit.sum() > K // 4
    params = mi.traverse(scene)
    key = "mesh0.vertex_color"
    W = mi.TensorXf(rng.normal(size=(K, 4)).astype(np.float32))
    dr.enable_grad(params[key])
    dr.backward(dr.sum(render_rays(scene, o, d, params=params) * W, axis=None))
    g = np.array(dr.grad(params[key]), np.float64)
    dr.disable_grad(params[key])
    base, along, h = np.array(params[key], np.float64), rng.normal(size=len(g)), 1e-2

    def loss(x):
        params[key] = mi.Float(x.astype(np.float32))
        params.update()
        return float(np.array(dr.sum(render_rays(scene, o, d) * W, axis=None)).ravel()[0])
    fd = (loss(base + h * along) - loss(base - h * along)) / (2 * h)
    loss(base)
    assert abs(fd) > 1e-2 and abs(g @ along - fd) < 0.05 * abs(fd), (g @ along, fd)
