"""Tet meshes that overlap in space, composited as one medium (extinctions
and emissions add), against the float64 reference of several meshes
(``tests.reference.reference_render_meshes``: every mesh's pieces merged in
depth order), and their derivatives against finite differences."""
import json

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi
import mi_tetvr
from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.render.merged import overlapping
from mi_tetvr.transfer import read_transfer_function
from tests.helpers import Problem, make_rays, rays_at, render_rays, seeded_sampler
from tests.reference import reference_render_meshes
from tests.render.test_gradients import check_fd, check_forward_reverse
from tests.render.test_surfaces import camera_rays, surfaces

TOL = 3e-3
RESOLUTION = 32
RANGE = (-1.0, 1.5)


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    """name -> (dict entry, mesh for the reference): a color mesh, a scalar
    mesh under a peaked transfer function overlapping it, an absorption mesh
    nested inside the color mesh."""
    rng = np.random.default_rng(70)
    out = {}
    VA, TA = grid_mesh(3, lo=(-1, -1, -1), hi=(0.6, 1, 1), jitter=0.1, seed=1)
    cA, oA = rng.uniform(0, 1, (len(VA), 3)), rng.uniform(0, 1.5, len(VA))
    out["color"] = (mi_tetvr.tetmesh_dict(VA, TA, cA, oA),
                    dict(vertices=VA, tets=TA, color=cA, opacity=oA))
    VB, TB = grid_mesh(3, lo=(-0.5, -0.8, -0.7), hi=(1.2, 0.7, 0.9), jitter=0.1, seed=2)
    path = tmp_path_factory.mktemp("tf") / "peaks.json"
    path.write_text(json.dumps({
        "color": [[0.0, 0.9, 0.2, 0.1], [0.5, 0.1, 0.8, 0.3], [1.0, 0.2, 0.3, 0.9]],
        "opacity": [[0.0, 0.2], [0.48, 0.3], [0.5, 5.0], [0.52, 0.3], [1.0, 1.0]],
        "colorspace": "linear"}))
    scalar = np.sin(2.0 * VB[:, 0] + VB[:, 1]) + 0.4 * VB[:, 2]
    tc, to = read_transfer_function(path).texels(RESOLUTION)
    out["scalar"] = (mi_tetvr.tetmesh_dict(VB, TB, scalar=scalar, transfer_function=str(path),
                                           value_min=RANGE[0], value_max=RANGE[1],
                                           tf_resolution=RESOLUTION),
                     dict(vertices=VB, tets=TB, scalar=scalar, tf_color=tc, tf_opacity=to,
                          value_range=RANGE))
    VC, TC = grid_mesh(2, lo=(-0.7, -0.5, -0.5), hi=(0.1, 0.4, 0.5), jitter=0.1, seed=3)
    oC = rng.uniform(0.5, 2.5, len(VC))
    out["xray"] = (mi_tetvr.tetmesh_dict(VC, TC, None, oC, model="absorption"),
                   dict(vertices=VC, tets=TC, color=np.zeros((len(VC), 3)), opacity=oC))
    return out


def scene_of(meshes, names, **extra):
    return mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                         **{n: meshes[n][0] for n in names}, **extra})


def reference(meshes, names, o, d, **kw):
    return reference_render_meshes([meshes[n][1] for n in names], o, d, **kw)


def test_overlapping_and_nested_meshes_of_three_models(meshes):
    """A color mesh overlapped by a post-classified scalar mesh, with an
    absorption mesh nested inside the color mesh (enter A, enter C, leave C,
    leave A), under an environment: rays from outside and from a camera
    inside all three."""
    names = ["color", "scalar", "xray"]
    scene = scene_of(meshes, names, env={"type": "constant",
                                         "radiance": {"type": "rgb", "value": [0.2, 0.3, 0.4]}})
    assert overlapping(scene.integrator().parts.split(scene)[0])
    rng = np.random.default_rng(71)
    o, d = rays_at(rng, 300, radius=5.0, target_extent=1.2)
    inside = np.tile([-0.3, 0.0, 0.0], (100, 1))      # inside all three meshes
    di = rng.normal(size=(100, 3))
    o, d = np.vstack([o, inside]), np.vstack([d, di / np.linalg.norm(di, axis=1, keepdims=True)])
    rgb, alpha = render_rays(scene, o, d)
    ref, ref_a = reference(meshes, names, o, d, background=(0.2, 0.3, 0.4))
    err = np.abs(rgb - ref).max()
    assert err < TOL, f"max |rgb - reference| = {err:.2e}"
    assert np.abs(alpha - ref_a).max() < TOL
    # The overlap matters: compositing the meshes one after the other differs.
    apart = [reference(meshes, [n], o, d) for n in names]
    assert np.abs(ref_a - (1 - np.prod([1 - a for _, a in apart], 0))).max() < 1e-6
    seq = np.zeros_like(ref)
    T = np.ones(len(o))
    for c, a in apart:        # any fixed order: wrong where the meshes overlap
        seq += T[:, None] * c
        T *= 1 - a
    assert np.abs(seq - ref).max() > 0.05


def test_overlapping_meshes_behind_and_around_surfaces(meshes):
    """Overlapping meshes with the surfaces of tests/render/test_surfaces.py
    (a sphere inside, a floor and a wall behind): the merged volume up to the
    surface hit."""
    names = ["color", "scalar"]
    d = {"type": "scene", "integrator": {"type": "tetvr",
                                         "surfaces": {"type": "prb", "max_depth": 2}},
         **{n: meshes[n][0] for n in names}, **surfaces(ball=False)}
    scene = mi.load_dict(d)
    rng = np.random.default_rng(72)
    o, dirs = camera_rays(rng, 200)
    rays = make_rays(o, dirs)
    nested = {"type": "prb", "max_depth": 2}
    alone = mi.load_dict({"type": "scene", "integrator": nested, **surfaces(ball=False)})
    t_hit = np.array(alone.ray_intersect(rays).t, np.float64)
    L_alone = alone.integrator().sample(dr.ADMode.Primal, alone, seeded_sampler(len(o)), rays,
                                        None, None, True)[0]
    L_alone = np.array(L_alone, np.float64).reshape(3, -1).T
    rgb, _ = render_rays(scene, o, dirs, seeded_sampler(len(o)))
    ref, ref_a = reference(meshes, names, o, dirs, t_max=t_hit)
    expected = ref + (1 - ref_a)[:, None] * L_alone
    assert np.abs(rgb - expected).max() < TOL


def test_gradients_where_meshes_overlap(meshes):
    """Colors, opacities, the scalar, the texels and the vertex positions of
    overlapping meshes: adjoint against finite differences, forward against
    reverse."""
    names = ["color", "scalar", "xray"]
    scene = scene_of(meshes, names)
    keys = ("color.vertex_color", "color.vertex_opacity", "scalar.vertex_scalar",
            "scalar.tf_opacity", "xray.vertex_opacity", "color.vertex_positions")
    rng = np.random.default_rng(73)
    o, d = rays_at(rng, 96, radius=5.0, target_extent=1.0)
    mesh = meshes["color"][1]
    problem = Problem((mesh["vertices"], mesh["tets"]), o, d, rng, scene=scene, keys=keys)
    check_forward_reverse(problem, check_fd(problem, rng, keys=keys), rng, trials=1)


def test_boundary_of_a_nested_mesh_moves(meshes):
    """Moving the boundary vertices of the absorption mesh nested in the
    color mesh moves where the rays enter and leave it inside the color
    medium: the crossings of its boundary carry the positions' derivative
    (against central differences; rays kept away from its silhouette)."""
    names = ["color", "xray"]
    scene = scene_of(meshes, names)
    key = "xray.vertex_positions"
    rng = np.random.default_rng(77)
    k = 64           # rays through the middle of the nested box, along x
    o = np.stack([np.full(k, -3.0), rng.uniform(-0.3, 0.2, k), rng.uniform(-0.3, 0.3, k)], 1)
    d = np.stack([np.ones(k), rng.uniform(-0.05, 0.05, k), rng.uniform(-0.05, 0.05, k)], 1)
    problem = Problem(None, o, d, rng, scene=scene, keys=(key,))
    g = problem.backward()[key]
    V = meshes["xray"][1]["vertices"]
    # the vertices on the faces x = lo and x = hi, away from the box's edges
    lo, hi = V.min(0), V.max(0)
    face = (np.isclose(V[:, 0], lo[0]) | np.isclose(V[:, 0], hi[0])) & np.all(
        (V[:, 1:] > lo[1:] + 1e-6) & (V[:, 1:] < hi[1:] - 1e-6), 1)
    entries = 3 * np.nonzero(face)[0]          # their x coordinates
    assert len(entries) > 0 and np.abs(g[entries]).max() > 1e-3
    fd = np.array([problem.finite_difference(key, i, 1e-3) for i in entries])
    err = np.linalg.norm(g[entries] - fd) / np.linalg.norm(fd)
    assert err < 0.05, (g[entries], fd)


def test_nonconvex_mesh_overlapped_by_a_mesh_of_the_same_model():
    """A U-shaped mesh (rays leave one arm and re-enter the other) with a
    box of the same model over one arm: re-entry and overlap in one walk."""
    from tests.render.test_gradients import ushape
    rng = np.random.default_rng(74)
    U = ushape(rng)
    VB, TB = grid_mesh(3, lo=(0.2, -0.2, -0.8), hi=(1.3, 1.3, 0.8), jitter=0.1, seed=2)
    B = (VB, TB, rng.uniform(0, 1, (len(VB), 3)), rng.uniform(0, 2, len(VB)))
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "u": mi_tetvr.tetmesh_dict(*U), "b": mi_tetvr.tetmesh_dict(*B)})
    k = 200
    o = np.stack([np.full(k, -3.0), rng.uniform(-0.3, 0.9, k), rng.uniform(-0.9, 0.9, k)], 1)
    d = np.stack([np.ones(k), rng.uniform(-0.1, 0.1, k), rng.uniform(-0.1, 0.1, k)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rgb, alpha = render_rays(scene, o, d)
    ref, ref_a = reference_render_meshes(
        [dict(vertices=m[0], tets=m[1], color=m[2], opacity=m[3]) for m in (U, B)], o, d)
    assert np.abs(rgb - ref).max() < TOL
    assert np.abs(alpha - ref_a).max() < TOL


def test_merged_walk_moves_on_at_every_knot(meshes, tmp_path):
    """Each iteration of the merged walk ends at a crossing, a knot or a
    boundary face, and a cursor that stopped at its own knot keeps the
    attributes there: recomputed from t they can fall short of the knot by
    more than the knot tolerance (256 texels, a camera 20 away: float32 t),
    and the walk would cut there again and again (it ran to max_steps)."""
    from mi_tetvr.render.merged import merged_trace
    from tests.helpers import make_rays
    path = tmp_path / "ramp.json"
    path.write_text(json.dumps({"color": [[0, 0.9, 0.2, 0.1], [1, 0.1, 0.3, 0.9]],
                                "opacity": [[0, 0.2], [1, 1.0]], "colorspace": "linear"}))
    VB, TB = (meshes["scalar"][1][k] for k in ("vertices", "tets"))
    scene = scene_of(meshes, ["color"], fine=mi_tetvr.tetmesh_dict(
        VB, TB, scalar=meshes["scalar"][1]["scalar"], transfer_function=str(path),
        tf_resolution=256))
    integrator = scene.integrator()
    ray = make_rays(*rays_at(np.random.default_rng(75), 256, radius=20.0, target_extent=1.0))
    tets = integrator.parts.split(scene)[0]
    _, _, steps, _ = merged_trace(integrator.parts.apart(tets),
                                  integrator.tet_groups(scene), ray,
                                  integrator.settings_for(scene), True)
    steps = np.array(steps)
    # Measured: at most 299 iterations (tets of both meshes, the ramp's knots, boundary faces).
    assert 50 < steps.max() < 1000, steps.max()


def test_overlapping_meshes_with_coincident_boundary_faces():
    """Two copies of a grid shifted by two cells: their boundary faces on
    four sides coincide exactly where they overlap. Each mesh's boundary is
    traced apart, so a ray entering both through one plane enters both."""
    from mi_tetvr.mesh.generate import blob_field
    from tests.reference import reference_render_meshes
    V, T = grid_mesh(4, jitter=0.15)          # unjittered boundary: faces coincide
    c, o = blob_field(V, 3.0)
    moved = V + [1.0, 0.0, 0.0]
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "a": mi_tetvr.tetmesh_dict(V, T, c, o),
                          "b": mi_tetvr.tetmesh_dict(moved, T, c[:, ::-1].copy(), o)})
    rng = np.random.default_rng(76)
    o_, d_ = rays_at(rng, 300, radius=5.0, target_extent=1.0)
    rgb, alpha = render_rays(scene, o_, d_)
    ref, ref_a = reference_render_meshes(
        [dict(vertices=V, tets=T, color=c, opacity=o),
         dict(vertices=moved, tets=T, color=c[:, ::-1].copy(), opacity=o)], o_, d_)
    assert np.abs(rgb - ref).max() < TOL
    assert np.abs(alpha - ref_a).max() < TOL


def test_camera_gradients_where_meshes_overlap():
    """Reverse mode through mi.render w.r.t. the sensor's to_world (a
    translation and a rotation) with two overlapping meshes whose boundaries
    are transparent (no silhouette term), against central differences of the
    rendered loss (5 %); forward against reverse (1 %). As
    tests/render/test_gradients.py does for one mesh."""
    from tests.render.test_gradients import camera_scene, check_camera_poses
    V, T = grid_mesh(5, jitter=0.1, seed=2)

    def field(P, shift):
        Q = P - [shift, 0.0, 0.0]
        C = np.clip(np.stack([0.5 + 0.4 * Q[:, 0], 0.5 - 0.4 * Q[:, 1], 0.6 - 0.3 * Q[:, 2]],
                             1), 0, 1)
        return C, 2.5 * np.exp(-3 * (Q ** 2).sum(1)) * (np.abs(Q).max(1) < 0.99)
    V2 = V + [0.6, 0.1, 0.0]
    scene = camera_scene((V, T, *field(V, 0.0)), 24, 50,
                         mesh1=mi_tetvr.tetmesh_dict(V2, T, *field(V2, 0.6)))
    base = mi.AffineTransform4f(mi.traverse(scene)["sensor.to_world"])

    def pose(x):    # a translation along x, a rotation about y (degrees)
        return (mi.AffineTransform4f().translate(mi.Vector3f(x[0], 0, 0)) @ base
                @ mi.AffineTransform4f().rotate(mi.Vector3f(0, 1, 0), x[1]))
    check_camera_poses(scene, pose, {"translate x": 1e-3, "rotate about y (degrees)": 0.05}, 78)


def test_camera_gradients_of_overlapping_meshes_read_only_their_own_vertices(capfd):
    """The merged walk's camera derivative gathers each crossing's corners only where that
    face exists: under Dr.Jit's debug mode (which checks every gather's index) no read
    falls outside a mesh's vertices. (Such reads returned whatever memory followed the
    positions: a NaN rotation gradient in a few rays, now and then.) The merged adjoint's
    kernel with debug checks compiles in about 6 s cold on two cores (it took over 20
    minutes while the adjoint scattered seven atomics a step)."""
    from tests.render.test_gradients import camera_scene
    V, T = grid_mesh(5, jitter=0.1, seed=2)
    C = np.full((len(V), 3), 0.5)
    S = 2.5 * np.exp(-3 * (V ** 2).sum(1)) * (np.abs(V).max(1) < 0.99)
    V2 = V + [0.6, 0.1, 0.0]
    with dr.scoped_set_flag(dr.JitFlag.Debug, True):
        scene = camera_scene((V, T, C, S), 24, 50, mesh1=mi_tetvr.tetmesh_dict(V2, T, C, S))
        params = mi.traverse(scene)
        base = mi.AffineTransform4f(params["sensor.to_world"])
        x = mi.Float(0.0)
        dr.enable_grad(x)
        params["sensor.to_world"] = base @ mi.AffineTransform4f().rotate(mi.Vector3f(0, 1, 0), x)
        params.update()
        dr.backward(dr.sum(mi.render(scene, params, spp=1), axis=None))
        g = float(dr.grad(x)[0])
    err = capfd.readouterr().err
    assert "out-of-bounds" not in err, err[:500]
    assert np.isfinite(g) and g != 0.0
