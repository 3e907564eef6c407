"""tetvr primal rendering against the float64 brute-force reference
(every ray clipped against every tet, Eq. 1 by Gauss-Legendre quadrature)."""
import warnings

import numpy as np
import pytest

from tests.helpers import make_scene, rays_at, render_rays
from mi_tetvr.mesh.generate import grid_mesh
from tests.reference import reference_render

TOL = 3e-3  # default settings against the reference (colors in [0, 1])


def random_attributes(n, rng, max_opacity=3.0):
    return rng.uniform(0, 1, (n, 3)), rng.uniform(0, max_opacity, n)


def check(scene, mesh_arrays, o, d, background=(0, 0, 0), tol=TOL, **ref_kw):
    V, T, C, S = (np.concatenate(x) if isinstance(x, list) else x for x in mesh_arrays)
    rgb, alpha = render_rays(scene, o, d)
    ref_rgb, ref_alpha = reference_render(V, T, C, S, o, d, background=background, **ref_kw)
    err = np.abs(rgb - ref_rgb).max()
    assert err < tol, f"max |rgb - reference| = {err:.2e}"
    assert np.abs(alpha - ref_alpha).max() < tol
    return rgb, alpha


@pytest.fixture(scope="module")
def jittered():
    rng = np.random.default_rng(1)
    V, T = grid_mesh(5, jitter=0.15, seed=1)
    return (V, T, *random_attributes(len(V), rng))


def test_single_tet():
    rng = np.random.default_rng(0)
    V = np.array([[-0.8, -0.7, -0.6], [0.9, -0.5, -0.4], [-0.2, 0.9, -0.3], [0.1, 0.0, 0.8]])
    T = np.array([[0, 1, 2, 3]])
    m = (V, T, *random_attributes(4, rng))
    o, d = rays_at(rng, 128, target_extent=0.4)
    rgb, alpha = check(make_scene(m), m, o, d)
    assert (alpha > 0.05).sum() > 30  # the test sees the tet


def test_jittered_grid(jittered):
    rng = np.random.default_rng(2)
    o, d = rays_at(rng, 256)
    check(make_scene(jittered), jittered, o, d)


def test_background_and_alpha(jittered):
    """pixel = C + T * background with a constant environment."""
    rng = np.random.default_rng(3)
    o, d = rays_at(rng, 64, target_extent=1.5)
    bg = (0.2, 0.5, 0.9)
    rgb, alpha = check(make_scene(jittered, background=bg), jittered, o, d, background=bg)
    assert np.any(alpha < 1e-6)  # some rays miss: they see the background
    np.testing.assert_allclose(rgb[alpha < 1e-6], np.tile(bg, ((alpha < 1e-6).sum(), 1)), atol=1e-6)


def test_n_sub_converges(jittered):
    """More sub-intervals approach the exact integral (error ~ 1/n_sub^2)."""
    rng = np.random.default_rng(4)
    o, d = rays_at(rng, 64)
    ref, _ = reference_render(*jittered, o, d)
    errs = [np.abs(render_rays(make_scene(jittered, n_sub=n), o, d)[0] - ref).max()
            for n in (1, 2, 8)]
    assert errs[0] > errs[1] > errs[2]
    assert errs[2] < 1e-3


def test_non_convex_reentry():
    """A U-shaped mesh: rays leave through one arm and re-enter the other."""
    rng = np.random.default_rng(5)
    V, T = grid_mesh((6, 6, 2), jitter=0.1, seed=5)
    centroid = V[T].mean(1)
    keep = ~((np.abs(centroid[:, 0]) < 0.34) & (centroid[:, 1] > -0.3))
    T = T[keep]
    m = (V, T, *random_attributes(len(V), rng))
    # Rays along x through both arms (they cross the notch).
    k = 128
    o = np.stack([np.full(k, -3.0), rng.uniform(-0.2, 0.9, k), rng.uniform(-0.9, 0.9, k)], 1)
    d = np.stack([np.ones(k), rng.uniform(-0.05, 0.05, k), rng.uniform(-0.05, 0.05, k)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    check(make_scene(m), m, o, d)


def test_two_disjoint_parts_and_two_shapes():
    rng = np.random.default_rng(6)
    V1, T1 = grid_mesh(3, lo=(-1, -1, -1), hi=(-0.2, 1, 1), jitter=0.1, seed=1)
    V2, T2 = grid_mesh(3, lo=(0.2, -1, -1), hi=(1, 1, 1), jitter=0.1, seed=2)
    a1, a2 = random_attributes(len(V1), rng), random_attributes(len(V2), rng)
    one = (np.concatenate([V1, V2]), np.concatenate([T1, T2 + len(V1)]),
           np.concatenate([a1[0], a2[0]]), np.concatenate([a1[1], a2[1]]))
    k = 128
    o = np.stack([np.full(k, -3.0), rng.uniform(-0.9, 0.9, k), rng.uniform(-0.9, 0.9, k)], 1)
    d = np.stack([np.ones(k), rng.uniform(-0.1, 0.1, k), rng.uniform(-0.1, 0.1, k)], 1)
    rgb1, _ = check(make_scene(one), one, o, d)
    rgb2, _ = render_rays(make_scene((V1, T1, *a1), (V2, T2, *a2)), o, d)
    np.testing.assert_allclose(rgb2, rgb1, atol=1e-5)


def test_camera_inside(jittered):
    """Origins inside the mesh (and inside its tets): integration starts at t=0."""
    rng = np.random.default_rng(7)
    k = 256
    o = rng.uniform(-0.7, 0.7, (k, 3))
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    check(make_scene(jittered), jittered, o, d)


def test_rays_through_vertices_edges_and_faces():
    """Unjittered grid: rays exactly along grid edges, through vertices and
    inside faces must neither leak nor double count."""
    rng = np.random.default_rng(8)
    V, T = grid_mesh(4)  # vertices at multiples of 0.5
    m = (V, T, *random_attributes(len(V), rng, max_opacity=2.0))
    g = np.array([-0.5, 0.0, 0.5])  # interior grid lines (a ray lying in the
    # boundary surface is inside or outside only by convention)
    a, b = np.meshgrid(g, g)
    a, b = a.ravel(), b.ravel()
    n = len(a)
    o_list = [np.stack([np.full(n, -3.0), a, b], 1),             # along x edges
              np.stack([a, np.full(n, -3.0), b], 1),             # along y edges
              np.stack([a, b, np.full(n, 3.0)], 1),              # along -z edges
              np.stack([np.full(n, -3.0), a, b + 0.25], 1)]      # inside x-y faces
    d_list = [np.tile([1.0, 0, 0], (n, 1)), np.tile([0, 1.0, 0], (n, 1)),
              np.tile([0, 0, -1.0], (n, 1)), np.tile([1.0, 0, 0], (n, 1))]
    # Through the main diagonals of cells (the shared edge of the Kuhn split)
    # and through vertices.
    o_list.append(np.array([[-3.0, -3.0, -3.0], [-2.5, -3.0, -3.0], [-3.0, -2.5, -3.5]]))
    d_list.append(np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]))
    o = np.concatenate(o_list)
    d = np.concatenate(d_list)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rgb, alpha = check(make_scene(m), m, o, d)
    assert np.all(alpha[:n] > 0)  # all rays along grid edges see the volume


def test_zero_volume_tets():
    """A layer of cells collapsed to zero thickness: 6 flat tets per cell that
    the walk must step over without leaking."""
    rng = np.random.default_rng(9)
    V, T = grid_mesh(4)
    V = V.copy()
    V[np.isclose(V[:, 0], 0.5), 0] = 0.0  # collapse the layer 0 < x < 0.5
    m = (V, T, *random_attributes(len(V), rng))
    with pytest.warns(UserWarning, match="zero-volume"):
        scene = make_scene(m)
    o, d = rays_at(rng, 256)
    check(scene, m, o, d)
    # Rays along x cross the collapsed layer exactly perpendicular.
    k = 64
    o = np.stack([np.full(k, -3.0), rng.uniform(-0.9, 0.9, k), rng.uniform(-0.9, 0.9, k)], 1)
    d = np.tile([1.0, 0.0, 0.0], (k, 1))
    check(scene, m, o, d)


def test_early_termination_threshold(jittered):
    V, T, C, S = jittered
    m = (V, T, C, S * 20)
    rng = np.random.default_rng(10)
    o, d = rays_at(rng, 64)
    ref, _ = reference_render(*m, o, d)
    rgb, _ = render_rays(make_scene(m, min_transmittance=0.05), o, d)
    # Stopping at T < 0.05 loses at most 0.05 of emission in [0, 1].
    assert np.abs(rgb - ref).max() < 0.05 + TOL


@pytest.mark.parametrize("name", [
    "spx/spx.vtk", "a-grid/a_grid.vtk",
    "post/post.vtk", "sfepy/elbow.mesh", "bluntfin/bluntfin_tets.vtu"])
def test_real_meshes(data_dir, name):
    mesh = mi_tetvr_read(data_dir / "tets" / name)
    lo, hi = mesh.bounds
    diag = np.linalg.norm(hi - lo)
    rng = np.random.default_rng(11)
    c, s = random_attributes(len(mesh.vertices), rng)
    s *= 4.0 / diag  # optical depth O(1) across the mesh
    m = (mesh.vertices, mesh.tets, c, s)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = make_scene(m)
    center = (lo + hi) / 2
    o, d = rays_at(rng, 24, radius=diag)
    o += center
    d = (center + rng.uniform(-0.3, 0.3, (24, 3)) * (hi - lo)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rgb, alpha = check(scene, m, o, d)
    assert alpha.max() > 0.1


def mi_tetvr_read(path):
    from mi_tetvr.mesh.io import read_tetmesh
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_tetmesh(path)


def test_a_scene_built_again_reuses_its_kernels():
    """The same mesh loaded again (and rays made again from the same NumPy
    arrays) renders with the kernels already compiled: the shape's buffers lie
    in memory of Dr.Jit's own, whose alignment does not change the generated
    code (NumPy memory mapped as it is gave loads of another alignment from
    one array to the next, hence other kernels, compiled again in every run)."""
    import drjit as dr
    rng = np.random.default_rng(31)
    V, T = grid_mesh(3, jitter=0.1, seed=5)
    mesh = (V, T, rng.uniform(0, 1, (len(V), 3)), rng.uniform(0, 2, len(V)))
    o, d = rays_at(rng, 64)
    images = []
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for attempt in range(4):
            dr.kernel_history()
            images.append(render_rays(make_scene(mesh), o + 0.0, d + 0.0)[0])
            compiled = [k for k in dr.kernel_history()
                        if not k.get("cache_hit", 1) and not k.get("cache_disk", 1)]
            if attempt > 0:
                assert compiled == [], [k["hash"] for k in compiled]
    assert all(np.array_equal(images[0], im) for im in images[1:])


def test_convex_mesh_walks_as_the_general_traversal(jittered, monkeypatch):
    """A convex mesh is traced once per ray (``traverse_convex``): from
    outside, from inside (entered from behind, its pieces before the start
    clipped), clipped by a box, and along grid edges, the image is the
    general traversal's (one more trace after the exit, a walk back to a
    start inside) and the float64 reference's."""
    import mi_tetvr.render.cursor as cursor
    rng = np.random.default_rng(17)
    k = 128
    inside = rng.uniform(-0.7, 0.7, (k, 3))
    outside, d_out = rays_at(rng, k)
    d_in = rng.normal(size=(k, 3))
    d_in /= np.linalg.norm(d_in, axis=1, keepdims=True)
    o, d = np.concatenate([outside, inside]), np.concatenate([d_out, d_in])
    scene = make_scene(jittered)
    assert [s.convex() for s in scene.shapes()] == [True]
    rgb, alpha = check(scene, jittered, o, d)
    clip = dict(clip_min=[-0.5, -2.0, -0.4], clip_max=[0.6, 2.0, 2.0])
    rgb_clip, _ = render_rays(make_scene(jittered, **clip), o, d)
    monkeypatch.setattr(cursor, "convex_scene", lambda scene: False)
    general = render_rays(make_scene(jittered), o, d)
    np.testing.assert_allclose(rgb, general[0], atol=2e-6)
    np.testing.assert_allclose(alpha, general[1], atol=2e-6)
    np.testing.assert_allclose(rgb_clip, render_rays(make_scene(jittered, **clip), o, d)[0],
                               atol=2e-6)


def test_a_mesh_made_concave_is_walked_again_after_its_exit():
    """Moving boundary vertices inwards (a scene parameter) makes the mesh
    concave: ``convex()`` follows the positions, and rays that leave and
    come back are integrated both times, as the reference says."""
    import mitsuba as mi
    rng = np.random.default_rng(19)
    V, T = grid_mesh((6, 6, 2), jitter=0.0)
    C, S = random_attributes(len(V), rng)
    scene = make_scene((V, T, C, S))
    shape = scene.shapes()[0]
    assert shape.convex()
    # A notch: the +y face's vertices with |x| < 0.5 pushed down to y = 0.8
    # (the top layer of cells is 1/3 deep: its tets stay positive).
    W = V.copy()
    notch = (W[:, 1] > 0.99) & (np.abs(W[:, 0]) < 0.5)
    W[notch, 1] = 0.8
    params = mi.traverse(scene)
    key = [k for k in params.keys() if k.endswith("vertex_positions")][0]
    params[key] = mi.Float(W.astype(np.float32).ravel())
    params.update()
    assert not shape.convex()
    k = 128
    o = np.stack([np.full(k, -3.0), rng.uniform(0.82, 0.98, k), rng.uniform(-0.9, 0.9, k)], 1)
    d = np.stack([np.ones(k), rng.uniform(-0.002, 0.002, k), rng.uniform(-0.05, 0.05, k)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rgb, _ = check(scene, (W, T, C, S), o, d)
    # (the rays that came back: more than the first part of the mesh gives)
    first, _ = reference_render(W, T[W[T].mean(1)[:, 0] < -0.5], C, S, o, d)
    assert (np.abs(rgb - first).max(1) > 0.01).sum() > k // 2
