"""Tet volumes beside Mitsuba surfaces: ``L = C_volume[0, t_hit] + T(t_hit) L_surface``.

References the project did not write: the float64 brute-force volume
reference clipped at the surface hit (an analytic ray-sphere / ray-plane
intersection), the closed-form radiance of a diffuse surface under a point
light, and Mitsuba's own ``prb`` rendering the scene without the volume with
the same sampler seed.
"""
import numpy as np
import pytest

import drjit as dr
import mitsuba as mi
import mi_tetvr
from mi_tetvr.mesh.generate import grid_mesh
from tests.helpers import Problem, make_rays, render_rays, seeded_sampler
from tests.reference import reference_render
from tests.render.test_gradients import check_fd, check_forward_reverse

TOL = 3e-3  # as tests/render/test_render.py: default settings against the reference

LIGHT = np.array([1.5, 3.0, 3.0])
INTENSITY = 15.0
SPHERE = (np.array([0.1, -0.1, 0.2]), 0.45, np.array([0.3, 0.6, 0.8]))
FLOOR_Y, FLOOR_RHO = -1.5, np.array([0.7, 0.5, 0.3])
WALL_Z, WALL_RHO = -4.0, np.array([0.4, 0.7, 0.4])
FLOOR_HALF, WALL_HALF = 4.0, 2.0      # half extents


def volume(rng):
    V, T = grid_mesh(3, jitter=0.12, seed=3)
    return V, T, rng.uniform(0, 1, (len(V), 3)), rng.uniform(0, 1.5, len(V))


def surfaces(light=True, env=None, ball=True):
    """The surfaces and lights of the scene (dict entries)."""
    c, r, rho = SPHERE
    d = {
        "ball": {"type": "sphere", "center": c.tolist(), "radius": r,
                 "bsdf": {"type": "diffuse",
                          "reflectance": {"type": "rgb", "value": rho.tolist()}}},
        "floor": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([0, FLOOR_Y, 0])
                  .rotate([1, 0, 0], -90).scale(FLOOR_HALF),
                  "bsdf": {"type": "diffuse",
                           "reflectance": {"type": "rgb", "value": FLOOR_RHO.tolist()}}},
        "wall": {"type": "rectangle",
                 "to_world": mi.ScalarTransform4f().translate([0, 0, WALL_Z]).scale(WALL_HALF),
                 "bsdf": {"type": "diffuse",
                          "reflectance": {"type": "rgb", "value": WALL_RHO.tolist()}}},
    }
    if not ball:
        del d["ball"]
    if light:
        d["light"] = {"type": "point", "position": LIGHT.tolist(),
                      "intensity": {"type": "rgb", "value": INTENSITY}}
    if env is not None:
        d["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": env}}
    return d


def scene_with(mesh, nested=None, with_volume=True, integrator=None, sensor=None, **kw):
    d = {"type": "scene", **surfaces(**kw)}
    if sensor is not None:
        d["sensor"] = sensor
    if integrator is not None:
        d["integrator"] = integrator
    else:
        d["integrator"] = {"type": "tetvr", **({"surfaces": nested} if nested else {})}
    if with_volume:
        d["mesh0"] = mi_tetvr.tetmesh_dict(*mesh)
    return mi.load_dict(d)


def camera_rays(rng, k):
    o = np.tile([0.3, 0.5, 4.5], (k, 1)) + rng.normal(0, 0.05, (k, 3))
    target = np.stack([rng.uniform(-3, 3, k), rng.uniform(-2.2, 2.5, k),
                       rng.uniform(-4.0, 0.5, k)], 1)
    d = target - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def hit_sphere(o, d, c, r):
    """Nearest t > 0 of the rays on the sphere (inf where none)."""
    oc = o - c
    b = np.einsum("ij,ij->i", oc, d)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - r * r)
    s = np.sqrt(np.maximum(disc, 0.0))
    t0, t1 = -b - s, -b + s
    t = np.where(t0 > 1e-9, t0, np.where(t1 > 1e-9, t1, np.inf))
    return np.where(disc > 0, t, np.inf)


def hit_plane(o, d, axis, value, half):
    """t > 0 of the rays on the square ``x[axis] = value``, |other coordinates| < half."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (value - o[:, axis]) / d[:, axis]
    p = o + t[:, None] * d
    others = [a for a in range(3) if a != axis]
    inside = np.all(np.abs(p[:, others]) < half, 1) & (t > 1e-9)
    return np.where(inside, t, np.inf)


def analytic_surfaces(o, d):
    """``(t_hit, L)``: the first surface hit and its radiance under the point
    light (diffuse: rho / pi * I cos / r^2, zero in the sphere's shadow)."""
    c, r, rho = SPHERE
    ts = np.stack([hit_sphere(o, d, c, r), hit_plane(o, d, 1, FLOOR_Y, FLOOR_HALF),
                   hit_plane(o, d, 2, WALL_Z, WALL_HALF)], 1)
    which = ts.argmin(1)
    t = ts.min(1)
    hit = np.isfinite(t)
    p = o + np.where(hit, t, 0.0)[:, None] * d
    n = np.where((which == 0)[:, None], (p - c) / r,
                 np.where((which == 1)[:, None], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]))
    albedo = np.where((which == 0)[:, None], rho,
                      np.where((which == 1)[:, None], FLOOR_RHO, WALL_RHO))
    to_light = LIGHT - p
    dist = np.linalg.norm(to_light, axis=1)
    l_dir = to_light / dist[:, None]
    cos = np.einsum("ij,ij->i", n, l_dir)
    # the sphere shadows the planes (only the sphere can occlude the light here)
    shadow = (which != 0) & (hit_sphere(p + 1e-6 * l_dir, l_dir, c, r) < dist)
    L = albedo / np.pi * INTENSITY * (np.maximum(cos, 0.0) / dist ** 2)[:, None]
    L[~hit | shadow] = 0.0
    return t, L


@pytest.fixture(scope="module")
def mesh():
    return volume(np.random.default_rng(40))


def test_surfaces_inside_and_behind_against_closed_forms(mesh):
    """A sphere inside the volume, a floor and a wall behind it: every ray is
    the float64 volume clipped at the analytic hit plus its transmittance
    times the closed-form diffuse radiance."""
    rng = np.random.default_rng(41)
    o, d = camera_rays(rng, 512)
    t_hit, L_surf = analytic_surfaces(o, d)
    kinds = {"sphere": np.isfinite(hit_sphere(o, d, SPHERE[0], SPHERE[1])),
             "planes": np.isfinite(t_hit), "nothing": ~np.isfinite(t_hit)}
    assert all(k.sum() > 20 for k in kinds.values()), {k: v.sum() for k, v in kinds.items()}
    scene = scene_with(mesh, nested={"type": "prb", "max_depth": 2})
    rgb, alpha = render_rays(scene, o, d, seeded_sampler(len(o)))
    C, a = reference_render(*mesh, o, d, t_max=np.where(np.isfinite(t_hit), t_hit, np.inf))
    expected = C + (1.0 - a)[:, None] * L_surf
    err = np.abs(rgb - expected).max()
    assert err < TOL, f"max |rgb - reference| = {err:.2e}"
    hit = np.isfinite(t_hit)
    # alpha: the volume's and the surfaces' coverage (1 where a surface is hit)
    np.testing.assert_allclose(alpha[hit], 1.0)
    assert np.abs(alpha[~hit] - a[~hit]).max() < TOL
    # the sphere inside the volume is seen through the volume in front of it only
    assert (a[kinds["sphere"]] > 0.05).mean() > 0.5


def test_default_and_cpp_nested_integrators(mesh):
    """Without a ``surfaces`` child tetvr uses ``prb``; Mitsuba's C++ ``path``
    renders the same deterministic direct light in the primal mode."""
    rng = np.random.default_rng(42)
    o, d = camera_rays(rng, 128)
    scene = scene_with(mesh)
    assert "PRBIntegrator" in str(scene.integrator())
    ref, _ = render_rays(scene_with(mesh, nested={"type": "prb", "max_depth": 2}), o, d,
                         seeded_sampler(len(o)))
    path, _ = render_rays(scene_with(mesh, nested={"type": "path", "max_depth": 2}), o, d,
                          seeded_sampler(len(o)))
    assert np.abs(path - ref).max() < 1e-4


def test_against_mitsuba_without_the_volume(mesh):
    """Lit by an environment (random paths): each ray equals the float64
    volume up to Mitsuba's own hit plus its transmittance times Mitsuba's
    ``prb`` on the scene without the volume, with the same sampler seed."""
    rng = np.random.default_rng(43)
    o, d = camera_rays(rng, 512)
    nested = {"type": "prb", "max_depth": 4}
    scene = scene_with(mesh, nested=nested, env=[0.3, 0.4, 0.5])
    alone = scene_with(mesh, with_volume=False, integrator=nested, env=[0.3, 0.4, 0.5])
    rgb, alpha = render_rays(scene, o, d, seeded_sampler(len(o), seed=5))
    ray = make_rays(o, d)
    L_alone, _, _, _ = alone.integrator().sample(dr.ADMode.Primal, alone, seeded_sampler(
        len(o), seed=5), ray, None, None, True)
    L_alone = np.array(L_alone, np.float64).reshape(3, -1).T
    t_hit = np.array(alone.ray_intersect(ray).t, np.float64)
    assert np.isfinite(t_hit).sum() > 100 and (~np.isfinite(t_hit)).sum() > 20
    C, a = reference_render(*mesh, o, d, t_max=t_hit)
    expected = C + (1.0 - a)[:, None] * L_alone
    err = np.abs(rgb - expected)
    assert err.max() < TOL, f"max |rgb - reference| = {err.max():.2e}"


def test_mi_render_pixels_against_mitsuba(mesh):
    """mi.render at one sample per pixel (box filter), surfaces behind the
    volume: the image is the volume-only image plus its transmittance times
    Mitsuba's ``prb`` image of the scene without the volume, with the same
    seed (the same camera rays and the same paths)."""
    sensor = {"type": "perspective", "fov": 45,
              "to_world": mi.ScalarTransform4f().look_at(origin=[0.3, 0.5, 4.5],
                                                         target=[0, -0.3, 0], up=[0, 1, 0]),
              "film": {"type": "hdrfilm", "width": 24, "height": 24,
                       "rfilter": {"type": "box"}},
              "sampler": {"type": "independent", "sample_count": 1}}
    nested = {"type": "prb", "max_depth": 3}
    env = [0.3, 0.4, 0.5]

    def render(**kw):
        d = {"type": "scene", "sensor": sensor, **surfaces(env=env, ball=False)}
        d.update(kw)
        return np.array(mi.render(mi.load_dict(d), seed=3), np.float64)
    mixed = render(integrator={"type": "tetvr", "surfaces": nested},
                   mesh0=mi_tetvr.tetmesh_dict(*mesh))
    alone = render(integrator=nested)
    vol = np.array(mi.render(mi.load_dict({
        "type": "scene", "sensor": sensor, "integrator": {"type": "tetvr"},
        "mesh0": mi_tetvr.tetmesh_dict(*mesh)}), seed=3), np.float64)
    T = 1.0 - vol[..., 3]
    assert (T < 0.9).mean() > 0.2       # the volume covers part of the image
    expected = vol[..., :3] + T[..., None] * alone[..., :3]
    assert np.abs(mixed[..., :3] - expected).max() < 1e-4
    # alpha: 1 where a surface is hit, the volume's own elsewhere (sky above the wall)
    surface = np.abs(mixed[..., 3] - 1.0) < 1e-6
    assert 0.2 < surface.mean() < 0.9
    assert np.abs(mixed[..., 3] - vol[..., 3])[~surface].max() < 1e-6


KEYS = ("mesh0.vertex_color", "mesh0.vertex_opacity", "mesh0.vertex_positions")
SURFACE_KEYS = ("floor.bsdf.reflectance.value", "ball.bsdf.reflectance.value")


@pytest.fixture(scope="module")
def problem(mesh):
    rng = np.random.default_rng(44)
    o, d = camera_rays(rng, 96)
    scene = scene_with(mesh, nested={"type": "prb", "max_depth": 2})
    return Problem(mesh, o, d, rng, scene=scene, keys=KEYS + SURFACE_KEYS, sampled=True)


def test_gradients_with_surfaces_against_finite_differences(problem):
    """Volume parameters with surfaces behind and inside, and the surfaces'
    reflectances through ``prb`` (seen through the volume: T times their own
    gradient)."""
    check_fd(problem, np.random.default_rng(45), keys=KEYS + SURFACE_KEYS)


def test_forward_matches_reverse_with_surfaces(problem):
    check_forward_reverse(problem, problem.backward(), np.random.default_rng(46))


def test_mi_render_backward_reaches_volume_and_surfaces(mesh):
    """The usual workflow: mi.render with parameters, a loss, dr.backward:
    both the volume's colors and the floor's reflectance get gradients."""
    scene = scene_with(mesh, nested={"type": "prb", "max_depth": 2}, sensor={
        "type": "perspective", "film": {"type": "hdrfilm", "width": 16, "height": 16},
        "to_world": mi.ScalarTransform4f().look_at(origin=[0.3, 0.5, 4.5], target=[0, -0.3, 0],
                                                   up=[0, 1, 0])})
    params = mi.traverse(scene)
    keys = ["mesh0.vertex_color", "floor.bsdf.reflectance.value", "ball.bsdf.reflectance.value"]
    for k in keys:
        dr.enable_grad(params[k])
    img = mi.render(scene, params, spp=1)
    dr.backward(dr.mean(img, axis=None))
    for k in keys:
        assert np.abs(np.array(dr.grad(params[k]))).max() > 0, k


def test_bad_input_is_refused(mesh):
    with pytest.raises(Exception, match="unknown child 'extra'"):
        mi.load_dict({"type": "tetvr", "extra": {"type": "diffuse"}})
    with pytest.raises(Exception, match="sampling integrator"):
        mi.load_dict({"type": "tetvr", "surfaces": {"type": "ptracer"}})
    # a nested integrator without derivative modes, when the surfaces' gradients are asked
    # (the volume's need only its primal radiance, kept from the primal pass)
    rng = np.random.default_rng(47)
    o, d = camera_rays(rng, 16)
    path = {"type": "path", "max_depth": 2}
    g = Problem(mesh, o, d, np.random.default_rng(1), scene=scene_with(mesh, nested=path),
                keys=KEYS[:1], sampled=True).backward()[KEYS[0]]
    ref = Problem(mesh, o, d, np.random.default_rng(1), keys=KEYS[:1], sampled=True,
                  scene=scene_with(mesh, nested={"type": "prb", "max_depth": 2})).backward()
    assert np.abs(g - ref[KEYS[0]]).max() < 1e-5 * np.abs(g).max()
    with pytest.raises(Exception, match="has no derivative modes"):
        Problem(mesh, o, d, rng, scene=scene_with(mesh, nested=path), keys=SURFACE_KEYS[:1],
                sampled=True).backward()
    # a tetmesh used as an area emitter: refused when the scene is loaded
    with pytest.raises(Exception, match="cannot be an area emitter"):
        mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                      "mesh0": {**mi_tetvr.tetmesh_dict(*mesh), "emitter": {"type": "area"}}})


def test_scene_parameters_keep_their_names(mesh):
    """tetvr renders the surfaces (and overlapping meshes) in scenes of their
    own, which hold the user's objects: their names in ``mi.traverse`` do
    not change by rendering."""
    scene = scene_with(mesh, nested={"type": "prb", "max_depth": 2}, env=[0.1, 0.1, 0.1])
    before = sorted(mi.traverse(scene).keys())
    o, d = camera_rays(np.random.default_rng(48), 8)
    render_rays(scene, o, d, seeded_sampler(len(o)))
    assert sorted(mi.traverse(scene).keys()) == before
    assert "floor.bsdf.reflectance.value" in before and "mesh0.vertex_color" in before
