"""Surfaces drawn inside the volume (``tetvr`` with a ``tetproj`` overlay,
ParaView's volume with a contour or a slice) and translucent surfaces
(``tetproj`` with ``opacity`` below 1), against the float64 references
composited by hand: the isosurfaces' depths and smooth normals
(``reference_isosurface``), the slice's scalar (``reference_slice``), the
volume between them (``reference_render_classified``) and the transfer
function's texels read off the shape; and their derivatives (the scalars,
the isovalue, the transfer function, the positions) against central
differences of the rendered images."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_tetvr
from tests.helpers import (check_derivatives, grid_field, grid_field_scene, interior_positions,
                           make_rays, rays_at)
from tests.reference import reference_isosurface, reference_render_classified, reference_slice

RANGE = (-1.0, 1.0)
RESOLUTION = 64
SIZE = 32
#: Isovalues half way between texel centres (the transfer function is
#: linear around them).
ISO = [RANGE[0] + k * (RANGE[1] - RANGE[0]) / RESOLUTION for k in (40, 18)]
PLANE = ([0.1, 0.0, -0.05], [0.3, 0.2, 1.0])


MESH = grid_field()[:2]


def overlay_of(mode, opacity, values=ISO):
    out = {"type": "tetproj", "mode": mode, "opacity": opacity}
    if mode == "iso":
        out["iso"] = ",".join(str(v) for v in values)
    else:
        out.update(origin=PLANE[0], normal=PLANE[1])
    return out


def scene_of(integrator):
    return grid_field_scene(integrator, "viridis", SIZE, RESOLUTION)


def tf_color_at(params, value):
    """The transfer function's color at ``value`` (texel centres, linear
    between them, constant outside), from the shape's texels."""
    texels = np.array(params["m.tf_color"], np.float64).reshape(-1, 3)
    lo, hi = RANGE
    centres = lo + (np.arange(len(texels)) + 0.5) * (hi - lo) / len(texels)
    return np.stack([np.interp(value, centres, texels[:, c]) for c in range(3)], -1)


def reference_layers(params, mode, opacity, o, d, volume, layers=8, eps=1e-6):
    """The composite of ``tetvr`` + overlay (``volume``) or of ``tetproj``
    alone, layer by layer in float64."""
    V, T = MESH
    scalar = np.array(params["m.vertex_scalar"], np.float64)
    tf_c = np.array(params["m.tf_color"], np.float64).reshape(-1, 3)
    tf_s = np.array(params["m.tf_opacity"], np.float64)
    k = len(o)

    def vol(t0, t1):
        if not volume:
            return np.zeros((k, 3)), np.ones(k)
        ok = t1 > t0
        rgb, alpha = reference_render_classified(
            V, T, scalar, tf_c, tf_s, RANGE, o + np.where(ok, t0, 0)[:, None] * d, d,
            t_max=np.where(ok, t1 - t0, -1.0))
        return rgb, 1.0 - alpha

    L, W = np.zeros((k, 3)), np.ones(k)
    start = np.zeros(k)
    go = np.ones(k, bool)
    for _ in range(layers):
        if mode == "iso":
            hits = [reference_isosurface(V, T, scalar, o, d, v, np.where(start > 0, start, -1))
                    for v in ISO]
            t = np.min([h[0] for h in hits], 0)
            which = np.argmin([h[0] for h in hits], 0)
            n = np.stack([h[1] for h in hits])[which, np.arange(k)]
            norm = np.linalg.norm(n, axis=1)
            lambert = np.abs(np.einsum("kj,kj->k", n, d)) / np.where(norm > 0, norm, 1.0)
            color = tf_color_at(params, np.array(ISO)[which]) * lambert[:, None]
        else:
            value, met = reference_slice(V, T, scalar, o, d, *PLANE)
            t = np.where(met, (np.array(PLANE[0]) - o) @ np.array(PLANE[1])
                         / (d @ np.array(PLANE[1])), np.inf)
            t = np.where(t > start, t, np.inf)
            color = tf_color_at(params, np.nan_to_num(value))
        met = go & np.isfinite(t)
        C, Tv = vol(start, np.where(met, t, np.inf))
        C, Tv = np.where(go[:, None], C, 0), np.where(go, Tv, 1)
        L += W[:, None] * C
        W *= Tv
        L += np.where(met[:, None], W[:, None] * opacity * color, 0)
        W = np.where(met, W * (1 - opacity), W)
        start = np.where(met, t + eps, start)
        go = met & (W > 1e-4)
    C, Tv = vol(start, np.full(k, np.inf))
    L += np.where(go[:, None], W[:, None] * C, 0)
    return L


@pytest.mark.parametrize("mode, opacity, volume", [
    ("iso", 1.0, True), ("iso", 0.45, True), ("slice", 1.0, True), ("slice", 0.45, True),
    ("iso", 0.45, False)])
def test_overlay_against_the_reference(mode, opacity, volume):
    overlay = overlay_of(mode, opacity)
    scene = scene_of({"type": "tetvr", "overlay": overlay} if volume else overlay)
    params = mi.traverse(scene)
    o, d = rays_at(np.random.default_rng(11), 160, radius=4.0, target_extent=0.7)
    with dr.suspend_grad():
        L, _, _, _ = scene.integrator().sample(dr.ADMode.Primal, scene, None, make_rays(o, d),
                                                None, None, True)
    got = np.array(L, np.float64).T
    want = reference_layers(params, mode, opacity, o, d, volume)
    # Rays that meet a surface edge-on are left out: a grazing crossing is
    # ill-conditioned in either precision (the normal's |n.d| near 0).
    err = np.abs(got - want).max(1)
    assert np.abs(want).max() > 0.1
    assert np.quantile(err, 0.97) < 2e-3 and np.median(err) < 2e-4, (np.quantile(err, 0.97),
                                                                       np.median(err))


def test_translucent_layers_show_what_lies_behind():
    """A translucent isosurface lets the volume behind it through: the
    composite differs from the opaque one exactly where a surface is met,
    and with opacity 1 the layered composite equals one surface."""
    o, d = rays_at(np.random.default_rng(12), 64, radius=4.0, target_extent=1.4)
    out = {}
    for a in (1.0, 0.45):
        scene = scene_of({"type": "tetvr", "overlay": overlay_of("iso", a)})
        with dr.suspend_grad():
            L, _, _, _ = scene.integrator().sample(dr.ADMode.Primal, scene, None,
                                                    make_rays(o, d), None, None, True)
        out[a] = np.array(L, np.float64).T
    t, _ = reference_isosurface(*MESH, grid_field()[2], o, d, ISO[0])
    t2, _ = reference_isosurface(*MESH, grid_field()[2], o, d, ISO[1])
    met = np.isfinite(t) | np.isfinite(t2)
    assert met.sum() > 10 and (~met).sum() > 5
    differs = np.abs(out[1.0] - out[0.45]).max(1) > 1e-5
    assert np.array_equal(differs, met)


def iso_volume_scene(opacity):
    return scene_of({"type": "tetvr", "overlay": overlay_of("iso", opacity)})


@pytest.fixture(scope="module", params=[1.0, 0.45], ids=["opaque", "translucent"])
def composite(request):
    """``(scene, opacity)``: the volume and its isosurfaces of that opacity."""
    return iso_volume_scene(request.param), request.param


def test_overlay_gradients(composite):
    """W.r.t. the scalars (they move the isosurfaces, whose depths end and
    start the volume's intervals, and classify the volume: both terms), the
    isovalues, the transfer function and (the translucent composite) the
    positions."""
    scene, opacity = composite
    params = mi.traverse(scene)
    rng = np.random.default_rng(1)
    checks = {"m.vertex_scalar": (rng.normal(size=len(np.array(params["m.vertex_scalar"]))),
                                  2e-3, 0.7),
              "integrator.overlay.iso": ([1.0, 0.5], 2e-3, 0.7)}
    for key in ("m.tf_color", "m.tf_opacity"):
        checks[key] = (rng.normal(size=len(np.array(params[key]))), 1e-2, 0.9)
    if opacity < 1.0:
        V, T = MESH
        checks["m.vertex_positions"] = (rng.normal(size=3 * len(V)) * interior_positions(V, T),
                                        2e-3, 0.6)
    check_derivatives(scene, checks)


def test_slice_in_the_volume_gradient_wrt_scalars():
    scene = scene_of({"type": "tetvr", "overlay": overlay_of("slice", 0.45)})
    n = len(np.array(mi.traverse(scene)["m.vertex_scalar"]))
    check_derivatives(scene, {"m.vertex_scalar": (np.random.default_rng(5).normal(size=n),
                                                  2e-3, 0.7)})


def test_overlay_refusals():
    # (Mitsuba's loader passes the plugins' ValueErrors on as RuntimeErrors)
    with pytest.raises(Exception, match="overlay is a tetproj"):
        mi.load_dict({"type": "tetvr", "overlay": {"type": "tetproj", "mode": "max"}})
    with pytest.raises(Exception, match="opacity must be in"):
        mi.load_dict({"type": "tetproj", "mode": "iso", "iso": "0", "opacity": 0.0})
    with pytest.raises(Exception, match="apply to surfaces"):
        mi.load_dict({"type": "tetproj", "mode": "max", "opacity": 0.5})


def test_overlay_refuses_derivatives_it_cannot_take():
    """A pre-integrated volume has no transfer function texels in its walk
    (the isosurface's depth term needs them): said, not a crash."""
    scene = scene_of({"type": "tetvr", "overlay": overlay_of("iso", 1.0)})
    V, T, scalar = grid_field()
    pre = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr",
                                                        "overlay": overlay_of("iso", 1.0)},
                        "sensor": scene.sensors()[0],
                        "m": mi_tetvr.tetmesh_dict(V, T, scalar=scalar,
                                                   transfer_function="viridis",
                                                   value_min=-1.0, value_max=1.0,
                                                   classification="preintegrated")})
    params = mi.traverse(pre)
    dr.enable_grad(params["m.vertex_scalar"])
    with pytest.raises(ValueError, match="classification 'post'"):
        dr.backward(mi.render(pre, params, spp=1))
