"""The renderer as a layer of PyTorch and JAX programs (``mi_tetvr.interop``):
the gradients through each framework equal the gradients Dr.Jit computes
without it (:func:`mi_tetvr.rays.render_rays` and ``dr.backward``, whose own
tests hold them against finite differences), w.r.t. vertex values, rays and a
camera pose; the framework's optimizer lowers a loss through the renderer; a
missing framework is one line naming its extra."""
import sys

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi
from mi_tetvr.camera import Camera
from mi_tetvr.extras import MissingExtra
from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.rays import render_rays
from tests.helpers import make_scene, rays_at

K = 64
KEYS = ("mesh0.vertex_color", "mesh0.vertex_opacity")
CAMERA = Camera.look_at([2.5, 1.5, 3.0], [0, 0, 0], [0, 1, 0], 12, 10, fov_x=40.0)


@pytest.fixture(scope="module")
def problem():
    """A scene, K rays, weights of the RGBA, and the gradients of ``sum(W *
    rgba)`` computed by Dr.Jit alone (colors, opacities, origins, directions;
    the camera's pose through ``Camera.rays_drjit``)."""
    rng = np.random.default_rng(5)
    V, T = grid_mesh(3, jitter=0.1, seed=2)
    C = rng.uniform(0.1, 0.9, (len(V), 3)).astype(np.float32)
    S = (3.0 * np.exp(-3 * (V ** 2).sum(1)) * (np.abs(V).max(1) < 0.99)).astype(np.float32)
    scene = make_scene((V, T, C, S))
    o, d = (x.astype(np.float32) for x in rays_at(rng, K, radius=3.0))
    W = rng.normal(size=(K, 4)).astype(np.float32)
    Wimg = rng.normal(size=(CAMERA.height, CAMERA.width, 4)).astype(np.float32)
    params = mi.traverse(scene)
    O, D = mi.Point3f(*o.T), mi.Vector3f(*d.T)
    dr.enable_grad(O, D, *(params[k] for k in KEYS))
    dr.backward(dr.sum(render_rays(scene, O, D, params=params) * mi.TensorXf(W), axis=None))
    ref = {k: np.array(dr.grad(params[k])).reshape(-1, 3 if k.endswith("color") else 1)
           for k in KEYS}
    ref["o"], ref["d"] = np.array(dr.grad(O)).T, np.array(dr.grad(D)).T
    for k in KEYS:
        dr.disable_grad(params[k])
    m = [[mi.Float(float(CAMERA.to_world[i, j])) for j in range(4)] for i in range(4)]
    dr.enable_grad(m)
    ray = CAMERA.rays_drjit(to_world=m)
    rgba = render_rays(scene, ray.o, ray.d)
    dr.backward(dr.sum(rgba * mi.TensorXf(Wimg.reshape(-1, 4)), axis=None))
    ref["pose"] = np.array([[dr.grad(m[i][j])[0] for j in range(4)] for i in range(4)])
    assert np.abs(ref["pose"][:3]).max() > 1e-2 and np.abs(ref["o"]).max() > 1e-2
    return dict(scene=scene, C=C, S=S, o=o, d=d, W=W, Wimg=Wimg, ref=ref)


def close(a, b, what):
    a, b = np.asarray(a, np.float64).reshape(np.shape(b)), np.asarray(b, np.float64)
    err = np.abs(a - b).max() / np.abs(b).max()
    assert err < 1e-5, (what, err)


def test_torch_gradients_equal_drjit(problem):
    torch = pytest.importorskip("torch")
    from mi_tetvr.interop import camera_renderer, ray_renderer
    p = problem
    render = ray_renderer(p["scene"], KEYS, "torch")
    color = torch.tensor(p["C"], requires_grad=True)
    opacity = torch.tensor(p["S"], requires_grad=True)
    o = torch.tensor(p["o"], requires_grad=True)
    d = torch.tensor(p["d"], requires_grad=True)
    rgba = render(o, d, values={KEYS[0]: color, KEYS[1]: opacity})
    assert isinstance(rgba, torch.Tensor) and rgba.shape == (K, 4)
    (rgba * torch.tensor(p["W"])).sum().backward()
    for name, x in (("mesh0.vertex_color", color), ("mesh0.vertex_opacity", opacity),
                    ("o", o), ("d", d)):
        close(x.grad, p["ref"][name], name)
    pose = torch.tensor(CAMERA.to_world, dtype=torch.float32, requires_grad=True)
    image = camera_renderer(p["scene"], CAMERA, framework="torch")(pose)
    assert image.shape == (CAMERA.height, CAMERA.width, 4)
    (image * torch.tensor(p["Wimg"])).sum().backward()
    close(pose.grad, p["ref"]["pose"], "pose")


def test_jax_gradients_equal_drjit(problem):
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp
    from mi_tetvr.interop import camera_renderer, ray_renderer
    p = problem
    render = ray_renderer(p["scene"], KEYS, "jax")

    def loss(color, opacity, o, d):
        rgba = render(o, d, values={KEYS[0]: color, KEYS[1]: opacity})
        return jnp.sum(rgba * p["W"])
    grads = jax.grad(loss, argnums=(0, 1, 2, 3))(*(jnp.asarray(p[k]) for k in "CSod"))
    for name, g in zip(("mesh0.vertex_color", "mesh0.vertex_opacity", "o", "d"), grads):
        close(g, p["ref"][name], name)
    image = camera_renderer(p["scene"], CAMERA, framework="jax")
    g = jax.grad(lambda m: jnp.sum(image(m) * p["Wimg"]))(jnp.asarray(CAMERA.to_world,
                                                                      jnp.float32))
    close(g, p["ref"]["pose"], "pose")


def test_torch_optimizer_lowers_the_loss(problem):
    """Adam in PyTorch fits the vertex colors, through the renderer, to RGBA
    rendered from the true ones: the loss falls to a hundredth."""
    torch = pytest.importorskip("torch")
    from mi_tetvr.interop import ray_renderer
    p = problem
    render = ray_renderer(p["scene"], KEYS[:1], "torch")
    o, d = torch.tensor(p["o"]), torch.tensor(p["d"])
    target = render(o, d, values={KEYS[0]: torch.tensor(p["C"])}).detach()
    color = torch.full(p["C"].shape, 0.5, requires_grad=True)
    opt = torch.optim.Adam([color], lr=0.05)
    losses = []
    for _ in range(40):
        opt.zero_grad()
        loss = (render(o, d, values={KEYS[0]: color}) - target).square().mean()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.01 * losses[0], losses


def test_missing_framework_is_one_line(problem, monkeypatch):
    from mi_tetvr.interop import ray_renderer
    for name in ("torch", "jax"):
        with monkeypatch.context() as m:
            m.setitem(sys.modules, name, None)              # (import raises)
            with pytest.raises(MissingExtra, match=rf'pip install "mi_tetvr\[{name}\]"'):
                ray_renderer(problem["scene"], KEYS, name)
    with pytest.raises(ValueError, match="framework must be one of"):
        ray_renderer(problem["scene"], KEYS, "tensorflow")
    with pytest.raises(KeyError, match="did you mean 'mesh0.vertex_color'"):
        ray_renderer(problem["scene"], ["mesh.vertex_color"], "torch")
