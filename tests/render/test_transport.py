"""Light transport in scattering tet media (``tetpath``,
:mod:`mi_tetvr.render.transport`).

References the project did not write: Mitsuba's own ``volpath`` (a
``homogeneous`` medium in a ``cube``; a ``heterogeneous`` medium on a
``gridvolume`` holding a field linear in space, which a tet mesh and a
trilinear grid both represent exactly) and ``prbvolpath``'s gradients; the
closed-form optical depth of a linear extinction; finite differences.
Monte Carlo images are compared by z-tests of their difference (independent
pixels), block by block.
"""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy import stats

import mi_tetvr
from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.render.buffers import tets_of
from mi_tetvr.render.cursor import Entry
from mi_tetvr.render.transport import flight, solve_depth

RES = 20
ALBEDO, G = 0.7, 0.5
#: The linear field: extinction A + B x over the cube [-1, 1]^3.
A, B = 1.0, 0.8
#: Bound on the z-scores of image differences (16 blocks and the image).
Z = 4.5


@pytest.fixture(scope="module")
def cube():
    return grid_mesh((4, 4, 4))


def camera(spp=64):
    return {"type": "perspective", "fov": 40,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0.5, 0.8, 5], target=[0, 0, 0],
                                                       up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": RES, "height": RES,
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": spp}}


LIGHTS = {
    "point": {"type": "point", "position": [2.0, 2.5, 3.0],
              "intensity": {"type": "rgb", "value": 20.0}},
    "area": {"type": "rectangle",
             "to_world": mi.ScalarTransform4f().translate([0, 3, 0]).rotate([1, 0, 0], 90),
             "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 5.0}}},
    "envmap": {"type": "envmap", "bitmap": mi.Bitmap(np.concatenate(
        [np.linspace(0.2, 2.0, 32 * 16).reshape(16, 32, 1) * np.array([1.0, 0.8, 0.6])],
        axis=2).astype(np.float32))},
}


def linear_grid(n=8):
    """Mitsuba's ``gridvolume`` of ``A + B x`` on the cube: its samples sit at
    the voxel centres, so the grid spans half a voxel beyond the cube on each
    side and its outermost centres lie on the cube's faces."""
    x = -1.0 + 2.0 * np.arange(n) / (n - 1)
    data = np.broadcast_to((A + B * x)[None, None, :, None], (n, n, n, 1))
    h = 2.0 / (n - 1)
    return {"type": "gridvolume", "data": mi.TensorXf(np.ascontiguousarray(data, np.float32)),
            "filter_type": "trilinear",
            "to_world": mi.ScalarTransform4f().translate([-1 - h / 2] * 3).scale([2 + h] * 3)}


def scenes(cube, light, field, integrator, max_depth, spp=64, reference="volpath"):
    """The tet scene and Mitsuba's scene of the same medium."""
    V, T = cube
    phase = {"type": "hg", "g": G}
    if field == "constant":
        sigma = np.full(len(V), 1.5)
        medium = {"type": "homogeneous", "sigma_t": 1.5, "albedo": ALBEDO, "phase": phase}
    else:
        sigma = A + B * V[:, 0]
        medium = {"type": "heterogeneous", "sigma_t": linear_grid(), "albedo": ALBEDO,
                  "phase": phase}
    common = {"type": "scene", "sensor": camera(spp), "light": LIGHTS[light]}
    tet = mi.load_dict({**common, "integrator": {"type": integrator, "max_depth": max_depth},
                        "vol": mi_tetvr.tetmesh_dict(V, T, opacity=sigma, albedo=ALBEDO,
                                                     phase=phase)})
    ref = mi.load_dict({**common, "integrator": {"type": reference, "max_depth": max_depth},
                        "cube": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium}})
    return tet, ref


def z_scores(a, b, block=5):
    """z-scores of the mean difference of two independent Monte Carlo images,
    per block of pixels and over the whole image."""
    d = (np.asarray(a)[..., :3] - np.asarray(b)[..., :3]).mean(axis=2)
    z = []
    for blk in [d[i:i + block, j:j + block] for i in range(0, d.shape[0], block)
                for j in range(0, d.shape[1], block)] + [d]:
        x = blk.ravel()
        z.append(x.mean() / (x.std(ddof=1) / np.sqrt(x.size)))
    return np.abs(np.array(z))


# -- the walk's sampling and transmittance against closed forms ---------------

@pytest.fixture(scope="module")
def linear_walk(cube):
    V, T = cube
    scene = mi.load_dict({"type": "scene", "vol": mi_tetvr.tetmesh_dict(
        V, T, opacity=A + B * V[:, 0], albedo=0.5)})
    return mi.load_dict({"type": "tetpath"}).path_inputs(scene)


def rays(o, d, t_max):
    """Rays from the rows of ``o`` along the rows of ``d`` up to ``t_max``."""
    ray = mi.Ray3f(mi.Point3f(o.T), mi.Vector3f(d.T))
    ray.maxt = mi.Float(t_max)
    return ray


def optical_depth(o, d, s):
    """float64 closed form: the optical depth of ``A + B x`` from ``o`` over
    a distance ``s`` along ``d`` (a linear field: length times the midpoint's value)."""
    mid = o + d * (s / 2)[:, None]
    return s * (A + B * mid[:, 0])


def test_free_flight_distances_invert_the_optical_depth(linear_walk):
    """Rays along x through the cube: each sampled distance solves the
    closed-form optical depth of its target, and the distances follow the
    free-flight density (Kolmogorov-Smirnov against the closed-form CDF)."""
    ps = linear_walk
    n = 20000
    rng = np.random.default_rng(1)
    yz = rng.uniform(-0.9, 0.9, (n, 2))
    o = np.column_stack([np.full(n, -3.0), yz])
    d = np.tile([1.0, 0.0, 0.0], (n, 1))
    total = 2.0 * A                                   # the depth of the whole chord
    u = rng.uniform(0.0, 1.0 - np.exp(-total), n)     # (every sample collides)
    target = -np.log1p(-u)
    fl = flight(ps, rays(o, d, 10.0), mi.Float(target), None, mi.Bool(True))
    assert np.all(np.array(fl.hit))
    s = np.array(fl.t, np.float64) - 2.0               # the distance inside the cube
    # s solves (A - B) s + B s^2 / 2 = target
    s_ref = (-(A - B) + np.sqrt((A - B) ** 2 + 2 * B * target)) / B
    assert np.abs(s - s_ref).max() < 2e-5
    assert np.abs(np.array(fl.tau) - target).max() < 1e-5

    def cdf(x):
        return -np.expm1(-((A - B) * x + B * x * x / 2)) / -np.expm1(-total)
    assert stats.kstest(s, cdf).pvalue > 1e-3
    # The collision's attributes are the field there.
    x = -1.0 + s
    assert np.abs(np.array(fl.s) - (A + B * x)).max() < 1e-4
    # The root of a piece's depth, in the form without cancellation.
    r = solve_depth(mi.Float(2.0), mi.Float(0.0), mi.Float(1.0), mi.Float(0.75))
    assert abs(r[0] - 0.5) < 1e-6


def test_transmittance_from_outside_and_from_inside_a_tet(linear_walk, cube):
    """Optical depth to the end of the ray (``target = inf``) against the float64
    closed form: oblique rays from outside, and rays that start at a point
    inside a known tet in any direction (a scattered ray: the walk finds the
    face its line enters the tet by)."""
    ps = linear_walk
    V, T = cube
    rng = np.random.default_rng(2)
    n = 4000
    # From outside, through the cube: aim at points inside.
    target = rng.uniform(-0.8, 0.8, (n, 3))
    o = target + rng.normal(size=(n, 3)) * 3.0
    d = target - o
    d /= np.linalg.norm(d, axis=1)[:, None]
    fl = flight(ps, rays(o, d, dr.inf), mi.Float(dr.inf), None, mi.Bool(True))
    t0, t1 = box_chord(o, d)
    ref = optical_depth(o + d * t0[:, None], d, t1 - t0)
    assert np.abs(np.array(fl.tau) - ref).max() < 1e-5 * max(1.0, ref.max())
    # From inside a tet (its tets in the walk's order), to the cube's side.
    tets = tets_of(np.asarray(ps.ts.buf.cells))
    k = rng.integers(0, len(tets), n)
    w = rng.dirichlet(np.ones(4), n)
    p = np.einsum("nk,nkj->nj", w, V[tets[k]])
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    fl = flight(ps, rays(p, d, dr.inf), mi.Float(dr.inf),
                Entry(tet=mi.UInt32(k), inside=mi.Bool(True)), mi.Bool(True))
    _, t1 = box_chord(p, d)
    ref = optical_depth(p, d, t1)
    assert np.abs(np.array(fl.tau) - ref).max() < 1e-5 * max(1.0, ref.max())


def box_chord(o, d):
    """float64 ray parameters where rays enter and leave the cube [-1, 1]^3."""
    with np.errstate(divide="ignore"):
        inv = 1.0 / d
    a, b = (-1.0 - o) * inv, (1.0 - o) * inv
    return np.maximum(np.minimum(a, b).max(1), 0.0), np.maximum(a, b).min(1)


# -- images against Mitsuba's volpath ------------------------------------------

@pytest.mark.parametrize("light, field, max_depth", [
    ("point", "constant", 2), ("point", "constant", -1),
    ("area", "constant", 2), ("area", "constant", -1),
    ("envmap", "constant", 2), ("envmap", "constant", -1),
    ("area", "linear", -1), ("envmap", "linear", 2), ("point", "linear", -1)])
def test_matches_mitsuba_volpath(cube, light, field, max_depth):
    """Single (``max_depth = 2``) and multiple scattering in a constant
    medium (Mitsuba: ``homogeneous``) and in a medium linear in space
    (Mitsuba: ``heterogeneous`` on a trilinear ``gridvolume``), lit by a
    point light, an area light and an environment map."""
    tet, ref = scenes(cube, light, field, "tetpath", max_depth)
    a = mi.render(tet, spp=256, seed=1)
    b = mi.render(ref, spp=256, seed=2)
    assert np.asarray(b).mean() > 1e-3
    z = z_scores(a, b)
    assert z.max() < Z, z


# -- derivatives ----------------------------------------------------------------

def weighted_loss(weights):
    """A loss whose gradient differs per pixel and channel."""
    def loss(img):
        return dr.sum(img[:, :, :3] * weights, axis=None) / RES ** 2
    return loss


def backward(scene, keys, loss, spp, seed):
    """Gradients of ``loss`` w.r.t. the parameters ``keys`` (numpy) of the
    image rendered with ``seed`` (Mitsuba's derivative pass renders its own
    primal with ``seed_grad``)."""
    params = mi.traverse(scene)
    for k in keys:
        dr.enable_grad(params[k])
    params.update()
    dr.backward(loss(mi.render(scene, params, spp=spp, seed=seed + 1, seed_grad=seed)))
    out = {k: np.array(dr.grad(params[k]), np.float64) for k in keys}
    for k in keys:
        dr.disable_grad(params[k])
    return out


def forward(scene, directions, loss, spp, seed):
    """The derivative of ``loss`` along ``directions`` (``{key: tangent}``:
    all at once) of the image rendered with ``seed``, in forward mode."""
    params = mi.traverse(scene)
    for key, direction in directions.items():
        dr.enable_grad(params[key])
        dr.set_grad(params[key], mi.Float(np.asarray(direction, np.float32)))
    params.update()
    out = dr.forward_to(loss(mi.render(scene, params, spp=spp, seed=seed + 1, seed_grad=seed)))
    for key in directions:
        dr.disable_grad(params[key])
    return float(out.array[0])


def test_gradients_match_prbvolpath(cube):
    """Extinction, albedo and the phase function's ``g`` of a constant
    medium under a point light, multiple scattering: the tet mesh's vertex
    gradients, summed, against Mitsuba's ``prbvolpath`` on its
    ``homogeneous`` medium (independent samples: within 5 %)."""
    tet, ref = scenes(cube, "point", "constant", "tetpath", -1, reference="prbvolpath")
    rng = np.random.default_rng(3)
    loss = weighted_loss(mi.TensorXf(rng.uniform(0.5, 1.5, (RES, RES, 3)).astype(np.float32)))
    mine = backward(tet, ["vol.vertex_opacity", "vol.vertex_albedo", "vol.phase.g"], loss,
                    1024, 1)
    theirs = backward(ref, ["cube.interior_medium.sigma_t.value.value",
                            "cube.interior_medium.albedo.value.value",
                            "cube.interior_medium.phase_function.g"], loss, 1024, 2)
    for a, b in zip(mine.values(), theirs.values()):
        assert abs(a.sum() - b.sum()) < 0.05 * abs(b.sum()), (a.sum(), b.sum())


@pytest.fixture(scope="module")
def scattering(cube):
    """A scattering mesh with everything per vertex (extinction, albedo,
    emission) under an area light, and directions in its parameters."""
    V, T = cube
    rng = np.random.default_rng(4)
    scene = mi.load_dict({
        "type": "scene", "sensor": camera(), "light": LIGHTS["area"],
        "integrator": {"type": "tetpath", "max_depth": -1},
        "vol": mi_tetvr.tetmesh_dict(V, T, opacity=0.5 + rng.uniform(0, 1.5, len(V)),
                                     albedo=rng.uniform(0.3, 0.9, (len(V), 3)),
                                     emission=rng.uniform(0, 0.3, (len(V), 3)),
                                     phase={"type": "hg", "g": 0.3})})
    interior = np.all(np.abs(V) < 0.999, axis=1)
    directions = {
        "vol.vertex_opacity": 1.0 + V[:, 0],
        "vol.vertex_albedo": np.repeat(0.1 * (1.0 - V[:, 1]), 3),
        "vol.vertex_emission": rng.normal(size=3 * len(V)),
        "vol.vertex_positions": (np.array([0.2, 0.1, 0.0]) * interior[:, None]).ravel(),
        "vol.phase.g": np.ones(1)}
    loss = weighted_loss(mi.TensorXf(rng.uniform(0.5, 1.5, (RES, RES, 3)).astype(np.float32)))
    return scene, directions, loss


def test_backward_equals_forward(scattering):
    """On the same samples, the reverse-mode gradient along a direction is
    the forward-mode derivative along it: the vertex positions alone, and
    every parameter at once."""
    scene, directions, loss = scattering
    grads = backward(scene, list(directions), loss, 64, 7)
    positions = "vol.vertex_positions"
    for subset in ({positions: directions[positions]}, directions):
        fwd = forward(scene, subset, loss, 64, 7)
        bwd = sum(float(grads[k] @ d) for k, d in subset.items())
        assert abs(fwd - bwd) <= 1e-3 * abs(bwd) + 1e-7, (list(subset), fwd, bwd)


def test_gradients_match_finite_differences(scattering):
    """Extinction, albedo and emission against central differences of the
    image rendered with the same random numbers (the image is linear in the
    emission: there the two are equal up to round-off). The step is not
    small: with the same random numbers, a free flight that reaches a
    mesh's side at one extinction collides at the other, and those jumps
    make the differences' noise grow as 1 / step."""
    scene, directions, loss = scattering
    keys = ["vol.vertex_opacity", "vol.vertex_albedo", "vol.vertex_emission"]
    grads = backward(scene, keys, loss, 1024, 9)
    params = mi.traverse(scene)
    for key in keys:
        base = mi.Float(params[key])
        step = mi.Float(np.asarray(directions[key], np.float32))
        eps = 0.1
        values = []
        for sign in (1, -1):
            params[key] = base + sign * eps * step
            params.update()
            values.append(float(loss(mi.render(scene, spp=1024, seed=9)).array[0]))
        params[key] = base
        params.update()
        fd = (values[0] - values[1]) / (2 * eps)
        bwd = float(grads[key] @ directions[key])
        tol = 1e-3 if key == "vol.vertex_emission" else 0.05
        assert abs(fd - bwd) <= tol * abs(fd), (key, fd, bwd)


def test_emission_only_is_tetvr_in_expectation(cube):
    """With albedo 0 the path tracer is a Monte Carlo estimate of the
    emission-absorption integral that ``tetvr`` computes exactly: the images
    agree within their noise, and so do the gradients w.r.t. extinction,
    emission and (interior) vertex positions."""
    V, T = cube
    rng = np.random.default_rng(5)
    sigma, color = 0.3 + rng.uniform(0, 2.0, len(V)), rng.uniform(0, 1, (len(V), 3))
    mc = mi.load_dict({"type": "scene", "sensor": camera(),
                       "integrator": {"type": "tetpath", "max_depth": -1},
                       "vol": mi_tetvr.tetmesh_dict(V, T, opacity=sigma, albedo=0.0,
                                                    emission=color)})
    exact = mi.load_dict({"type": "scene", "sensor": camera(),
                          "integrator": {"type": "tetvr", "min_transmittance": 0.0},
                          "vol": mi_tetvr.tetmesh_dict(V, T, color=color, opacity=sigma)})
    a = np.asarray(mi.render(mc, spp=256, seed=1))
    b = np.asarray(mi.render(exact, spp=256, seed=2))[..., :3]
    assert z_scores(a, b).max() < Z
    interior = np.all(np.abs(V) < 0.999, axis=1)
    loss = weighted_loss(mi.TensorXf(rng.uniform(0.5, 1.5, (RES, RES, 3)).astype(np.float32)))
    g_mc = backward(mc, ["vol.vertex_opacity", "vol.vertex_emission", "vol.vertex_positions"],
                    loss, 4096, 3)
    g_ex = backward(exact, ["vol.vertex_opacity", "vol.vertex_color", "vol.vertex_positions"],
                    loss, 64, 4)
    # Along the exact gradient (moving interior vertices only: the mesh's
    # sides, where the extinction jumps, stay where they are).
    g_ex["vol.vertex_positions"] *= np.repeat(interior, 3)
    for x, y in zip(g_mc.values(), g_ex.values()):
        assert abs(x @ y - y @ y) < 0.05 * (y @ y), (x @ y, y @ y)


# -- meshes that overlap in space: the summed medium ---------------------------

#: A second linear field over the cube, on another tessellation of it.
C, D = 0.6, -0.4


def cube_pair(cube, first, second, *singles):
    """Two meshes of the cube that overlap (4^3 and 3^3 cells: their tets
    and inner faces differ, their boundaries coincide) and single meshes of
    it (4^3 cells), each medium given as ``(opacity(V), albedo)``; one phase
    function, an area light. Returns ``(the pair's scene, [the singles'])``."""
    V, T = cube
    V2, T2 = grid_mesh((3, 3, 3))
    phase = mi.load_dict({"type": "hg", "g": G})
    common = {"type": "scene", "sensor": camera(128), "light": LIGHTS["area"],
              "integrator": {"type": "tetpath", "max_depth": 4}}

    def mesh(V, T, medium):
        return mi_tetvr.tetmesh_dict(V, T, opacity=medium[0](V), albedo=medium[1], phase=phase)
    two = mi.load_dict({**common, "a": mesh(V, T, first), "b": mesh(V2, T2, second)})
    return two, [mi.load_dict({**common, "a": mesh(V, T, m)}) for m in singles]


@pytest.fixture(scope="module")
def overlapping(cube):
    """The pair of meshes of the cube with linear extinctions ``A + B x``
    and ``C + D y``, and the one mesh whose extinction is their sum (linear
    fields are exact on any tessellation), all with one albedo: the same
    medium, walked with a cursor per mesh or with one."""
    two, (one,) = cube_pair(cube, (lambda V: A + B * V[:, 0], ALBEDO),
                            (lambda V: C + D * V[:, 1], ALBEDO),
                            (lambda V: A + B * V[:, 0] + C + D * V[:, 1], ALBEDO))
    return two, one


def chords(n, seed):
    """Rays from outside the cube through random points inside it."""
    rng = np.random.default_rng(seed)
    target = rng.uniform(-0.9, 0.9, (n, 3))
    o = target + rng.normal(size=(n, 3)) * 3.0
    d = target - o
    return o, d / np.linalg.norm(d, axis=1)[:, None]


def test_overlapping_meshes_walk_as_their_summed_extinction(overlapping):
    """The optical depth through two overlapping meshes (a cursor each)
    equals the depth through one mesh of the summed extinction, and the
    float64 closed form; so does its derivative w.r.t. the first mesh's
    vertex extinctions (reverse mode, per vertex) against the one mesh's."""
    two, one = overlapping
    o, d = chords(3000, 5)
    t0, t1 = box_chord(o, d)
    ref = (optical_depth(o + d * t0[:, None], d, t1 - t0)
           + (t1 - t0) * (C + D * (o[:, 1] + d[:, 1] * (t0 + t1) / 2)))
    seed = np.random.default_rng(6).uniform(0.5, 1.5, len(o))
    taus, grads = [], []
    for scene in (two, one):
        params = mi.traverse(scene)
        dr.enable_grad(params["a.vertex_opacity"])
        params.update()
        ps = scene.integrator().path_inputs(scene)
        assert (ps.apart is not None) == (scene is two)
        with dr.suspend_grad():
            fl = flight(ps, rays(o, d, dr.inf), mi.Float(dr.inf), None, mi.Bool(True),
                        (dr.ADMode.Backward, mi.Float(seed)))
        taus.append(np.array(fl.tau, np.float64))
        grads.append(np.array(dr.grad(params["a.vertex_opacity"]), np.float64))
        dr.disable_grad(params["a.vertex_opacity"])
    assert np.abs(taus[0] - ref).max() < 2e-5 * ref.max()
    assert np.abs(taus[0] - taus[1]).max() < 2e-5 * ref.max()
    assert np.abs(grads[0] - grads[1]).max() < 1e-4 * np.abs(grads[1]).max()
    # Moving vertices of overlapping meshes: refused in one line, not a wrong gradient.
    params = mi.traverse(two)
    dr.enable_grad(params["b.vertex_positions"])
    params.update()
    with pytest.raises(ValueError, match="overlap.*not w.r.t. their vertex positions"):
        dr.backward(dr.sum(mi.render(two, params, spp=1), axis=None))
    dr.disable_grad(params["b.vertex_positions"])
    params.update()


def test_overlapping_meshes_render_as_their_summed_medium(cube):
    """``tetpath`` on two overlapping meshes of the cube (4^3 and 3^3
    cells), constant extinctions 1 and 0.5 and albedos 0.9 and 0.3, renders
    the image of the one mesh of extinction 1.5 and albedo 0.7 (a collision
    is in each mesh in proportion to its extinction: the mixture's albedo is
    the extinction-weighted mean). Independent samples: z-scores of the
    difference per block and over the image."""
    def constant(value):
        return lambda V: np.full(len(V), value)
    two, (one, wrong) = cube_pair(cube, (constant(1.0), 0.9), (constant(0.5), 0.3),
                                  (constant(1.5), 0.7), (constant(1.5), 0.9))
    a = mi.render(two, seed=1)
    b = mi.render(one, seed=2)
    assert np.array(b)[..., :3].mean() > 0.01            # (the medium is lit and seen)
    assert z_scores(a, b).max() < Z
    # Had every collision taken the first mesh's albedo (0.9), the image would differ.
    assert z_scores(a, mi.render(wrong, seed=3)).max() > Z


# -- the shape's scattering properties, and what tetpath refuses -----------------

def test_scattering_properties_and_refusals(cube):
    V, T = cube
    n = len(V)
    albedo = np.random.default_rng(6).uniform(0, 1, (n, 3))
    shape = mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(V, T, opacity=np.ones(n),
                                                         albedo=albedo))
    params = mi.traverse(shape)
    assert shape.optical_model.__name__ == "Scattering"
    np.testing.assert_allclose(np.array(params["vertex_albedo"]).reshape(n, 3), albedo,
                               atol=1e-6)
    assert np.array(params["vertex_emission"]).max() == 0.0           # no emission by default
    assert "Isotropic" in str(shape.phase)
    grey = mi.traverse(mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(V, T, albedo=0.25)))
    assert np.all(np.array(grey["vertex_albedo"]) == 0.25)
    for props, message in [
            ({"albedo": 1.5}, "albedo must lie in"),
            ({"albedo": "blue"}, "albedo is a number"),
            ({"emission": 1.0}, "give the mesh an 'albedo'"),
            ({"phase": {"type": "hg", "g": 0.2}}, "give the mesh an 'albedo'"),
            ({"albedo": 0.5, "model": "absorption"}, "takes no 'model'"),
            ({"albedo": 0.5, "emission": np.ones(n + 1)}, "per vertex"),
    ]:
        with pytest.raises(ValueError, match=message):
            mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(V, T, **props))
    scalar = V[:, 0]
    tf = {"tf_color": mi.TensorXf(np.ones((4, 3), np.float32)),
          "tf_opacity": mi.TensorXf(np.ones(4, np.float32))}
    with pytest.raises(ValueError, match="classification 'pre'"):
        mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(V, T, scalar=scalar, albedo="color", **tf))
    pre = mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(V, T, scalar=scalar, albedo="color",
                                                       classification="pre", **tf))
    assert pre.optical_model.__name__ == "Scattering"
    # tetpath renders scattering media; tetvr renders their emission and absorption.
    plain = {"type": "scene", "sensor": camera(4), "vol": mi_tetvr.tetmesh_dict(V, T)}
    for scene, message in [({**plain, "integrator": {"type": "tetpath"}}, "has no albedo"),
                            ({"type": "scene", "sensor": camera(4),
                              "integrator": {"type": "tetpath"}}, "no tetmesh")]:
        scene = mi.load_dict(scene)
        with pytest.raises(ValueError, match=message):
            scene.integrator().render(scene, scene.sensors()[0])
    emission = np.random.default_rng(7).uniform(0, 1, (n, 3))
    plain["integrator"] = {"type": "tetvr"}
    a = mi.render(mi.load_dict({**plain, "vol": mi_tetvr.tetmesh_dict(
        V, T, opacity=np.ones(n), albedo=0.5, emission=emission)}), spp=4)
    b = mi.render(mi.load_dict({**plain, "vol": mi_tetvr.tetmesh_dict(
        V, T, color=emission, opacity=np.ones(n))}), spp=4)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_set_mesh_renders_as_a_new_shape(cube):
    """A shape given a refined mesh in place (``set_mesh``) renders and
    differentiates as a shape built from that mesh."""
    from mi_tetvr.mesh.generate import grid_mesh as grid
    V, T = cube
    V2, T2 = grid((5, 5, 5), jitter=0.2, seed=3)
    rng = np.random.default_rng(8)
    sigma, albedo = 0.5 + rng.uniform(0, 1, len(V2)), rng.uniform(0.2, 0.9, (len(V2), 3))
    common = {"type": "scene", "sensor": camera(), "light": LIGHTS["point"],
              "integrator": {"type": "tetpath", "max_depth": 4}}
    fresh = mi.load_dict({**common, "vol": mi_tetvr.tetmesh_dict(V2, T2, opacity=sigma,
                                                                 albedo=albedo)})
    moved = mi.load_dict({**common, "vol": mi_tetvr.tetmesh_dict(V, T, opacity=np.ones(len(V)),
                                                                 albedo=0.5)})
    params = mi.traverse(moved)
    moved.shapes()[0].set_mesh(params, V2, T2, {"vertex_opacity": sigma, "vertex_albedo": albedo,
                                                "vertex_emission": np.zeros((len(V2), 3))})
    params.update()
    np.testing.assert_allclose(np.asarray(mi.render(moved, spp=8, seed=3)),
                               np.asarray(mi.render(fresh, spp=8, seed=3)), atol=1e-5)
    loss = weighted_loss(mi.TensorXf(np.ones((RES, RES, 3), np.float32)))
    g = [backward(s, ["vol.vertex_opacity"], loss, 8, 5)["vol.vertex_opacity"]
         for s in (moved, fresh)]
    np.testing.assert_allclose(g[0], g[1], rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="vertex_albedo needs 3"):
        moved.shapes()[0].set_mesh(params, V2, T2, {"vertex_opacity": sigma,
                                                    "vertex_albedo": sigma,
                                                    "vertex_emission": albedo})
