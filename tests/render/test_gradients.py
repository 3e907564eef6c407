"""Derivatives of tetvr: the adjoint (inversion trick) against central finite
differences of the primal, forward mode against reverse mode, and against
Dr.Jit's AD through a recorded (evaluated) loop of the primal renderer."""
import warnings

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi
import mi_tetvr
from tests.helpers import Problem, make_scene, rays_at, render_rays
from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.topology import build_topology

KEYS = ("mesh0.vertex_color", "mesh0.vertex_opacity", "mesh0.vertex_positions")


def attributes(n, rng, max_opacity=2.0):
    return rng.uniform(0, 1, (n, 3)), rng.uniform(0, max_opacity, n)


def ushape(rng):
    """Non-convex: a U of two arms (rays leave one arm and re-enter the other)."""
    V, T = grid_mesh((6, 4, 3), jitter=0.1, seed=5)
    centroid = V[T].mean(1)
    T = T[~((np.abs(centroid[:, 0]) < 0.34) & (centroid[:, 1] > -0.5))]
    return (V, T, *attributes(len(V), rng))


def jittered(rng, max_opacity=2.0):
    V, T = grid_mesh(3, jitter=0.12, seed=3)
    return (V, T, *attributes(len(V), rng, max_opacity))


def interior_position_entries(V, T):
    """Flat indices (3 i + axis) of the positions of vertices off the boundary."""
    boundary = np.unique(build_topology(V, T).boundary_faces)
    inner = np.setdiff1d(np.arange(len(V)), boundary)
    return (3 * inner[:, None] + np.arange(3)).ravel()


def check_fd(problem, rng, keys=KEYS, n=10, tol=0.05):
    grads = problem.backward()
    V, T = problem.mesh[0], problem.mesh[1]
    for key in keys:
        g = grads[key]
        if key.endswith("positions"):
            candidates = interior_position_entries(V, T)
            h = 1e-3
        else:
            candidates = np.arange(len(g))
            h = 1e-3
        # Entries with a sizeable gradient, so that the relative error means something.
        candidates = candidates[np.abs(g[candidates]) > 1e-3 * np.abs(g).max()]
        assert len(candidates) > 0
        idx = rng.choice(candidates, min(n, len(candidates)), replace=False)
        fd = np.array([problem.finite_difference(key, i, h) for i in idx])
        err = np.linalg.norm(g[idx] - fd) / np.linalg.norm(fd)
        assert err < tol, f"{key}: relative L2 error {err:.3g} (adjoint {g[idx]}, FD {fd})"
    return grads


def test_adjoint_matches_finite_differences_jittered():
    rng = np.random.default_rng(20)
    check_fd(Problem(jittered(rng), *rays_at(rng, 64), rng), rng)


def test_adjoint_matches_finite_differences_nonconvex():
    rng = np.random.default_rng(21)
    k = 64
    o = np.stack([np.full(k, -3.0), rng.uniform(-0.3, 0.9, k), rng.uniform(-0.9, 0.9, k)], 1)
    d = np.stack([np.ones(k), rng.uniform(-0.1, 0.1, k), rng.uniform(-0.1, 0.1, k)], 1)
    problem = Problem(ushape(rng), o, d, rng)
    check_fd(problem, rng)


def check_forward_reverse(problem, grads, rng, trials=2, tol=0.01):
    """Forward mode along random directions against the reverse-mode
    gradients ``grads`` (key -> array) of ``problem``: relative ``tol``."""
    for _ in range(trials):
        directions = {k: rng.normal(size=len(g)) for k, g in grads.items()}
        reverse = sum((directions[k] * grads[k]).sum() for k in grads)
        forward = problem.forward(directions)
        assert abs(forward - reverse) < tol * abs(reverse), (forward, reverse)


def test_forward_matches_reverse():
    rng = np.random.default_rng(22)
    problem = Problem(jittered(rng), *rays_at(rng, 64), rng)
    check_forward_reverse(problem, problem.backward(), rng)


def test_adjoint_matches_recorded_loop():
    """Dr.Jit's AD through the primal renderer with evaluated (recorded) loops."""
    rng = np.random.default_rng(23)
    problem = Problem(jittered(rng), *rays_at(rng, 64), rng)
    grads = problem.backward()
    for k in KEYS:
        dr.enable_grad(problem.params[k])
    with dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, False):
        L, _, aovs, _ = problem.sample(dr.ADMode.Primal, δL=None, state_in=None)
        loss = dr.sum(dr.sum(L * mi.Color3f(*problem.wL.T)) + aovs[0] * mi.Float(problem.wa))
        dr.backward(loss)
    for k in KEYS:
        ref = np.array(dr.grad(problem.params[k]), np.float64)
        err = np.linalg.norm(grads[k] - ref) / np.linalg.norm(ref)
        assert err < 1e-4, f"{k}: relative error {err:.2e} against the recorded loop"
    problem.disable()


def assert_finite(grads):
    for k, g in grads.items():
        assert np.all(np.isfinite(g)), f"{k}: non-finite gradient entries"


def test_zero_opacity():
    """The x -> 0 limit of the segment integral: finite and exact."""
    rng = np.random.default_rng(24)
    V, T, C, _ = jittered(rng)
    problem = Problem((V, T, C, np.zeros(len(V))), *rays_at(rng, 64), rng)
    grads = check_fd(problem, rng, keys=("mesh0.vertex_opacity",))
    assert_finite(grads)
    # With zero opacity nothing is emitted: colors and positions have no effect.
    assert np.abs(grads["mesh0.vertex_color"]).max() == 0
    assert np.abs(grads["mesh0.vertex_opacity"]).max() > 0


def test_empty_space_skips_the_integral_and_keeps_the_gradients(monkeypatch):
    """A mesh empty (zero opacity) on one side: the branch past empty
    segments renders the very image of the integral it skips, and the
    gradients there (the scheme's derivatives at zero extinction, in the
    adjoint's closed form) are Dr.Jit's AD of the integral without the
    branch, for colors, opacities and positions, within float rounding."""
    from mi_tetvr.render import optical, segment
    rng = np.random.default_rng(31)
    V, T, C, S = jittered(rng)
    S = np.where(V[:, 0] < 0.1, 0.0, S)
    o, d = rays_at(rng, 128)

    def whole(length, c0, c1, s0, s1, n_sub):
        P, Q, T_seg, _ = segment._emission_weights(length, s0, s1, n_sub)
        return c0 * P + c1 * Q, T_seg
    images, grads = [], []
    for skip in (True, False):
        if not skip:
            monkeypatch.setattr(optical, "segment_integral", whole)
            monkeypatch.setattr(optical.EmissionAbsorption, "segment_adjoint",
                                lambda self, *a: None)
        problem = Problem((V, T, C, S), o, d, np.random.default_rng(2))
        images.append(render_rays(problem.scene, o, d)[0])
        grads.append(problem.backward())
    np.testing.assert_array_equal(images[0], images[1])
    for k in KEYS:
        scale = np.abs(grads[1][k]).max()
        assert scale > 0
        np.testing.assert_allclose(grads[0][k], grads[1][k], rtol=1e-4, atol=1e-5 * scale)
    assert np.abs(grads[0]["mesh0.vertex_opacity"][S == 0]).max() > 0


def test_huge_opacity():
    rng = np.random.default_rng(25)
    V, T, C, _ = jittered(rng)
    S = rng.uniform(1e4, 2e4, len(V))
    problem = Problem((V, T, C, S), *rays_at(rng, 64), rng)
    assert_finite(problem.backward())


def test_grazing_rays_and_camera_inside():
    rng = np.random.default_rng(26)
    V, T = grid_mesh(3, jitter=0.0)
    mesh = (V, T, *attributes(len(V), rng))
    k = 32
    # Along the boundary faces' planes and through boundary edges/vertices.
    y = rng.choice([-1.0, 1.0], k)
    z = rng.choice(np.linspace(-1, 1, 4), k)
    o_graze = np.stack([np.full(k, -3.0), y, z], 1)
    d_graze = np.tile([1.0, 0.0, 0.0], (k, 1))
    # Inside the mesh, in random directions.
    o_in = rng.uniform(-0.8, 0.8, (k, 3))
    d_in = rng.normal(size=(k, 3))
    problem = Problem(mesh, np.concatenate([o_graze, o_in]), np.concatenate([d_graze, d_in]),
                      rng)
    assert_finite(problem.backward())
    # Inside: a starting point that moves with its tet's vertices.
    inside = Problem(jittered(rng), o_in, d_in, rng)
    check_fd(inside, rng)


def camera_scene(mesh, size, fov, **extra):
    """A scene of one mesh seen by a square pixel-centred camera."""
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "tetvr"},
        "sensor": {"type": "perspective", "fov": fov,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[2.5, 1.5, 3.0],
                                                              target=[0, 0, 0], up=[0, 1, 0]),
                   "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
                   "film": {"type": "hdrfilm", "width": size, "height": size,
                            "rfilter": {"type": "box"}}},
        "mesh0": mi_tetvr.tetmesh_dict(*mesh), **extra})


def loss_difference(params, key, direction, loss, h=1e-3):
    """Central difference of ``loss()`` (a scalar Dr.Jit value) along
    ``direction`` in the parameter ``key``."""
    base = np.array(params[key])
    vals = []
    for sign in (1, -1):
        params[key] = mi.Float(base + sign * h * direction)
        params.update()
        vals.append(float(np.array(loss()).ravel()[0]))
    params[key] = mi.Float(base)
    params.update()
    return (vals[0] - vals[1]) / (2 * h)


def test_mi_render_workflow_forward_backward_and_fd():
    """Through mi.render: dr.backward and dr.forward of an RGBA image loss
    agree with each other and with finite differences of the rendered loss."""
    rng = np.random.default_rng(27)
    V, T, C, S = jittered(rng)
    scene = camera_scene((V, T, C, S), 16, 40)
    params = mi.traverse(scene)
    w = mi.TensorXf(rng.normal(size=(16, 16, 4)).astype(np.float32))  # RGB and the alpha AOV

    def loss(p):
        return dr.sum(mi.render(scene, p, spp=1) * w, axis=None)

    key = "mesh0.vertex_opacity"
    dr.enable_grad(params[key])
    dr.backward(loss(params))
    g = np.array(dr.grad(params[key]), np.float64)
    direction = rng.normal(size=len(g))
    dr.set_grad(params[key], mi.Float(direction))
    fwd = float(np.array(dr.forward_to(loss(params))).ravel()[0])
    dr.disable_grad(params[key])
    reverse = float(direction @ g)
    assert abs(fwd - reverse) < 0.01 * abs(reverse), (fwd, reverse)
    fd = loss_difference(params, key, direction, lambda: loss(None))
    assert abs(fd - reverse) < 0.02 * abs(reverse), (fd, reverse)


def test_reduce_modes_agree_and_bad_mode_is_refused(monkeypatch):
    """Every scatter strategy gives the same gradients, and so do the
    per-vertex sums passed on after the walk and the gather's derivative at
    every vertex (what a model whose values depend on the ray takes)."""
    from mi_tetvr.render.optical import EmissionAbsorption
    rng = np.random.default_rng(28)
    mesh = jittered(rng)
    o, d = rays_at(rng, 64)
    grads = []
    # (auto: the walk's choice, per-thread copies of the vertices' sums on LLVM)
    for mode in ("auto", "direct", "local", "expand", "per vertex"):
        problem = Problem(mesh, o, d, np.random.default_rng(1))
        problem.integrator.settings.reduce = {"auto": None, "direct": dr.ReduceMode.Direct,
                                              "local": dr.ReduceMode.Local,
                                              "expand": dr.ReduceMode.Expand,
                                              "per vertex": None}[mode]
        if mode == "per vertex":
            monkeypatch.setattr(EmissionAbsorption, "per_ray_values", True)
        grads.append(problem.backward())
    for other in grads[1:]:
        for k in KEYS:
            np.testing.assert_allclose(other[k], grads[0][k], rtol=1e-4,
                                       atol=1e-6 * np.abs(grads[0][k]).max())
    with np.testing.assert_raises_regex(Exception, "reduce_mode"):
        make_scene(mesh, reduce_mode="sometimes")


def test_environment_gradient_through_mi_render():
    """A learnable background: the loss is linear in an envmap's texels
    (``C + T * env(d)``), so finite differences are exact up to rounding;
    reverse and forward mode agree with them."""
    rng = np.random.default_rng(29)
    V, T, C, S = jittered(rng, max_opacity=0.7)
    env = mi.Bitmap(rng.uniform(0.2, 1.0, (4, 8, 3)).astype(np.float32))
    scene = camera_scene((V, T, C, S), 12, 60, emitter={"type": "envmap", "bitmap": env})
    params = mi.traverse(scene)
    w = mi.TensorXf(rng.normal(size=(12, 12, 4)).astype(np.float32))

    def loss(p):
        return dr.sum(mi.render(scene, p, spp=1) * w, axis=None)

    key = "emitter.data"
    data = mi.TensorXf(params[key])       # the envmap keeps its own copy of the texels:
    dr.enable_grad(data)                  # give it a differentiable one
    params[key] = data
    params.update()
    direction = rng.normal(size=dr.width(data))
    # forward mode through the integrator (mi.render's forward mode does not
    # pass an envmap's tangents on in this Mitsuba, for prb neither)
    dr.set_grad(data, mi.TensorXf(direction.astype(np.float32), dr.shape(data)))
    image_tangent = scene.integrator().render_forward(scene, params, spp=1)
    fwd = float(np.sum(np.array(image_tangent, np.float64) * np.array(w)))
    dr.set_grad(data, 0.0)
    params[key] = data                    # as an optimizer's update() does every step
    params.update()
    dr.backward(loss(params))
    g = np.array(dr.grad(data), np.float64).ravel()
    dr.disable_grad(data)
    reverse = float(direction @ g)
    assert abs(fwd - reverse) < 1e-3 * abs(reverse), (fwd, reverse)
    base = np.array(params[key])
    vals = []
    for sign in (1, -1):
        params[key] = mi.TensorXf((base + sign * 0.05 * direction.reshape(base.shape))
                                  .astype(np.float32))
        params.update()
        vals.append(float(np.array(loss(None)).ravel()[0]))
    params[key] = mi.TensorXf(base)
    params.update()
    fd = (vals[0] - vals[1]) / 0.1
    assert abs(fd - reverse) < 2e-3 * abs(reverse), (fd, reverse)


def test_derivative_pass_reuses_the_primal_render():
    """mi.render's derivative pass reuses the rays and per-ray results of
    the render it differentiates: with jittered rays, dr.backward gives the
    derivative of the very image returned (finite differences at the same
    seed agree), the kept state is used once, and a parameter update between
    render and backward falls back to rendering the primal anew."""
    rng = np.random.default_rng(31)
    V, T, C, S = jittered(rng)
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "tetvr"},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[2.5, 1.5, 3.0],
                                                              target=[0, 0, 0], up=[0, 1, 0]),
                   "sampler": {"type": "independent", "sample_count": 2},
                   "film": {"type": "hdrfilm", "width": 12, "height": 12,
                            "rfilter": {"type": "box"}}},
        "mesh0": mi_tetvr.tetmesh_dict(V, T, C, S)})
    integrator = scene.integrator()
    params = mi.traverse(scene)
    w = mi.TensorXf(rng.normal(size=(12, 12, 4)).astype(np.float32))
    key = "mesh0.vertex_opacity"
    base = np.array(params[key])
    direction = rng.normal(size=len(base))

    def loss(seed, **kw):
        return dr.sum(mi.render(scene, params, seed=seed, spp=2, **kw) * w, axis=None)

    def reverse(seed, **kw):
        dr.enable_grad(params[key])
        dr.backward(loss(seed, **kw))
        g = np.array(dr.grad(params[key]), np.float64)
        dr.disable_grad(params[key])
        return float(direction @ g)

    def fd(seed):
        return loss_difference(params, key, direction, lambda: loss(seed))

    replayed = reverse(7)
    assert len(integrator.kept_primals) == 0            # kept once, used once
    exact = fd(7)
    assert abs(replayed - exact) < 0.01 * abs(exact), (replayed, exact)
    # Mitsuba's own derivative pass (any explicit seed_grad) renders other
    # rays: the derivative of another image.
    other = reverse(7, seed_grad=12345)
    assert abs(other - exact) > 0.02 * abs(exact), (other, exact)
    assert abs(other - fd(12345)) < 0.01 * abs(other)
    # Forward mode reuses the primal too and agrees with reverse mode.
    dr.enable_grad(params[key])
    dr.set_grad(params[key], mi.Float(direction))
    fwd = float(np.array(dr.forward_to(loss(7))).ravel()[0])
    dr.disable_grad(params[key])
    assert abs(fwd - replayed) < 1e-3 * abs(replayed)
    # An update between render and backward: the kept state (of the old
    # values) is dropped unused and the derivative pass renders the primal
    # itself, at the new values, on the rays of Mitsuba's derivative seed:
    # the gradient equals that of a render at the new values on those rays.
    from mi_tetvr.render.replay import derivative_seed
    dr.enable_grad(params[key])
    image = loss(7)
    assert len(integrator.kept_primals) == 1
    params[key] = mi.Float(base * 1.5)
    dr.enable_grad(params[key])
    params.update()
    dr.backward(image)
    assert len(integrator.kept_primals) == 0
    after_update = np.array(dr.grad(params[key]), np.float64)
    dr.disable_grad(params[key])
    dr.enable_grad(params[key])
    dr.backward(loss(derivative_seed(7)))
    fresh = np.array(dr.grad(params[key]), np.float64)
    dr.disable_grad(params[key])
    np.testing.assert_allclose(after_update, fresh, rtol=1e-5, atol=1e-6 * np.abs(fresh).max())
    params[key] = mi.Float(base)
    params.update()


def test_primal_states_guard_and_capacity():
    """A kept state is returned only for the very same input arrays, once;
    the oldest go first beyond the capacity."""
    from mi_tetvr.render.replay import PrimalStates
    states = PrimalStates(capacity=2)
    a, b = mi.Float(np.array([1.0, 2.0])), mi.Float(np.array([3.0, 4.0]))
    state = (mi.Float([5.0]), mi.Float([0.5]))
    states.put(("k", 1), 3, state, [a, b])
    assert states.take(("k", 1), [a, mi.Float(np.array([3.0, 4.0]))]) is None  # a copy
    assert states.take(("k", 1), [a, b]) is None                    # already dropped
    states.put(("k", 1), 3, state, [a, b])
    seed, kept = states.take(("k", 1), [a, b])
    assert seed == 3 and kept is state and len(states) == 0
    for i in range(3):
        states.put(("k", i), i, state, [a])
    # a dropped render's derivative pass is told it renders the primal again
    with pytest.warns(RuntimeWarning, match="more than 2 primal renders.*kept_primals"):
        assert len(states) == 2 and states.take(("k", 0), [a]) is None
    assert states.take(("k", 2), [a])[0] == 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")              # never kept: nothing to say
        assert states.take(("never", 0), [a]) is None
    with pytest.raises(ValueError, match="kept_primals"):
        PrimalStates(capacity=0)


def test_camera_gradients_against_finite_differences():
    """Reverse mode through mi.render w.r.t. the sensor: a translation and a
    rotation applied to ``to_world``, and the orbit parameters (longitude,
    latitude, distance) of ``orbit_to_world``, against central differences
    of the rendered loss (5 %), on a volume whose boundary is transparent
    (the silhouette has no boundary term); forward mode against reverse
    (1 %)."""
    from mi_tetvr.camera import orbit_to_world
    V, T = grid_mesh(6, jitter=0.1, seed=2)
    C = np.clip(np.stack([0.5 + 0.4 * V[:, 0], 0.5 + 0.4 * V[:, 1], 0.6 - 0.3 * V[:, 2]], 1),
                0, 1)
    S = 3.0 * np.exp(-3 * (V ** 2).sum(1)) * (np.abs(V).max(1) < 0.99)   # 0 on the boundary
    scene = camera_scene((V, T, C, S), 24, 45)
    # x: a translation along x, a rotation about y (degrees) and the orbit
    # (longitude, latitude, distance), with the steps of their central
    # differences (big enough that float32 round-off of the loss stays
    # below 1 % of the difference)
    steps = {"translate x": 1e-3, "rotate about y (degrees)": 0.05, "longitude": 0.05,
             "latitude": 0.05, "distance": 1e-2}

    def pose(x):
        return (mi.AffineTransform4f().translate(mi.Vector3f(x[0], 0, 0))
                @ orbit_to_world(40.0 + x[2], 25.0 + x[3], 4.2 + x[4])
                @ mi.AffineTransform4f().rotate(mi.Vector3f(0, 1, 0), x[1]))
    check_camera_poses(scene, pose, steps, 32)


def check_camera_poses(scene, pose, steps, seed, size=24):
    """Reverse mode through ``mi.render`` w.r.t. the parameters ``x`` of
    ``sensor.to_world = pose(x)`` (``x`` a list of Floats, named with their
    step of central difference by ``steps``: name -> h) of a random
    weighting of the image, against central differences (5 %); forward
    against reverse (1 %). The parameters are differentiated at once and are
    opaque, so that the scene compiles one kernel per mode and one primal."""
    params = mi.traverse(scene)
    base = mi.AffineTransform4f(params["sensor.to_world"])
    w = mi.TensorXf(np.random.default_rng(seed).normal(size=(size, size, 4)).astype(np.float32))
    names = list(steps)

    def loss(values, tangent=None):
        x = [dr.opaque(mi.Float, v) for v in values]
        if tangent is not None:
            for xi, ti in zip(x, tangent):
                dr.enable_grad(xi)
                dr.set_grad(xi, dr.opaque(mi.Float, ti))
        params["sensor.to_world"] = pose(x)
        params.update()
        return x, dr.sum(mi.render(scene, params, spp=1) * w, axis=None)

    zero = [0.0] * len(names)
    x, value = loss(zero, zero)
    dr.backward(value)
    reverse = [float(dr.grad(xi)[0]) for xi in x]
    for i, name in enumerate(names):
        h = steps[name]
        step = [h if j == i else 0.0 for j in range(len(names))]
        fd = (float(loss(step)[1].array[0])
              - float(loss([-v for v in step])[1].array[0])) / (2 * h)
        assert abs(reverse[i] - fd) < 0.05 * abs(fd), (name, reverse[i], fd)
        assert abs(fd) > 1e-2, (name, fd)
        unit = [1.0 if j == i else 0.0 for j in range(len(names))]
        forward = float(np.array(dr.forward_to(loss(zero, unit)[1])).ravel()[0])
        assert abs(forward - reverse[i]) < 0.01 * abs(reverse[i]), (name, forward, reverse[i])
    params["sensor.to_world"] = base
    params.update()
