"""The renderer as a differentiable layer of PyTorch and JAX programs.

:func:`ray_renderer` and :func:`camera_renderer` return functions of the
framework's own tensors: vertex values (any of the scene's differentiable
parameters, by their ``mi.traverse`` names), rays or a camera pose in, RGBA
out, with gradients flowing back into the framework's autograd. They wrap
:func:`mi_tetvr.rays.render_rays` with Dr.Jit's :func:`drjit.wrap`, which
hands arrays across without copies where it can (DLPack) and stitches the
render into PyTorch's autograd: ``loss.backward()`` runs the renderer's own
adjoint. Dr.Jit's ``wrap`` calls JAX from Dr.Jit but not the other way round,
so for JAX the same render is a ``jax.custom_vjp`` over ``jax.pure_callback``
(JAX's own way in for foreign functions): ``jax.grad`` and ``jax.vjp`` run
the adjoint (not forward mode; the arrays cross through host memory).

The framework is an extra (``pip install "mi_tetvr[torch]"`` or
``"mi_tetvr[jax]"``). Tensors are float32. With ``llvm_ad_rgb`` the tensors
live on the CPU; with ``cuda_ad_rgb`` on the GPU (PyTorch's ``cuda``, JAX's
GPU device).

Example (PyTorch)::

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import mi_tetvr
    from mi_tetvr.interop import ray_renderer

    scene = mi.load_file("scenes/default.xml")
    render = ray_renderer(scene, ["volume.vertex_color"])
    color = torch.rand(n, 3, requires_grad=True)
    rgba = render(origins, directions, values={"volume.vertex_color": color})
    rgba.square().mean().backward()         # color.grad: the renderer's adjoint
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import drjit as dr
import mitsuba as mi

from mi_tetvr.extras import needs

__all__ = ["FRAMEWORKS", "ray_renderer", "camera_renderer"]

#: The frameworks :func:`drjit.wrap` connects, by the name it takes: the extra
#: that brings each.
FRAMEWORKS = {"torch": "torch", "jax": "jax"}


def _framework(name: str) -> str:
    """Import ``name`` (a key of :data:`FRAMEWORKS`), or one line naming its extra."""
    if name not in FRAMEWORKS:
        raise ValueError(f"framework must be one of {sorted(FRAMEWORKS)}, got {name!r}")
    import importlib
    with needs(FRAMEWORKS[name], f"the {name} interface"):
        importlib.import_module(name)
    return name


class _Values:
    """Writes a dict of framework values into the scene's parameters
    (``mi.traverse`` names, each of its shape flattened), checked."""

    def __init__(self, scene: mi.Scene, keys: Sequence[str]) -> None:
        self.params = mi.traverse(scene)
        self.keys = list(keys)
        for k in self.keys:
            if k not in self.params:
                near = [p for p in self.params.keys() if k.split(".")[-1] in p]
                raise KeyError(f"{k!r} is not a parameter of the scene"
                               + (f" (did you mean {near[0]!r}?)" if near else ""))
        self.sizes = {k: dr.width(self.params[k]) * (dr.size_v(self.params[k])
                                                     if dr.depth_v(self.params[k]) > 1 else 1)
                      for k in self.keys}

    def write(self, values: dict | None) -> mi.SceneParameters:
        for k, x in (values or {}).items():
            if k not in self.sizes:
                raise KeyError(f"{k!r} is not one of this renderer's keys {self.keys}")
            flat = x.array if isinstance(x, mi.TensorXf) else mi.Float(x)
            if dr.width(flat) != self.sizes[k]:
                shape = tuple(x.shape) if isinstance(x, mi.TensorXf) else (dr.width(flat),)
                raise ValueError(f"{k}: {self.sizes[k]} values expected, got shape {shape}")
            self.params[k] = type(self.params[k])(flat) if dr.depth_v(self.params[k]) == 1 \
                else dr.unravel(type(self.params[k]), flat)
        if values:
            self.params.update()
        return self.params


def _torch(render: Callable) -> Callable:
    """``render`` (a function of Dr.Jit arrays) as a function of PyTorch
    tensors, in PyTorch's autograd: :func:`drjit.wrap`."""
    return dr.wrap(source="torch", target="drjit")(render)


def _jax(render: Callable, out_shape: Callable) -> Callable:
    """``render`` (a function of Dr.Jit arrays) as a function of JAX arrays
    with a vector-Jacobian product (``jax.grad``, ``jax.vjp``; not forward
    mode): JAX's own ``custom_vjp`` over ``pure_callback``, since
    :func:`drjit.wrap` (Dr.Jit 1.5) calls JAX from Dr.Jit but not Dr.Jit from
    JAX. The arrays cross through host memory; the derivative renders the
    primal again (the callback keeps no state between the passes)."""
    import numpy as np
    with needs("jax", "the jax interface"):
        import jax
        import jax.numpy as jnp

    def _to_drjit(tree):
        return jax.tree_util.tree_map(lambda a: mi.TensorXf(np.asarray(a, np.float32)), tree)

    def primal(*args):
        return np.asarray(render(*_to_drjit(args)), np.float32)

    def vjp(cot, *args):
        xs = _to_drjit(args)
        leaves = jax.tree_util.tree_leaves(xs)
        dr.enable_grad(leaves)
        dr.backward(dr.sum(render(*xs) * mi.TensorXf(np.asarray(cot, np.float32)), axis=None))
        return jax.tree_util.tree_map(lambda x: np.asarray(dr.grad(x), np.float32), xs)

    @jax.custom_vjp
    def f(*args):
        return jax.pure_callback(primal, jax.ShapeDtypeStruct(out_shape(*args), jnp.float32),
                                 *args)

    def f_fwd(*args):
        return f(*args), args

    def f_bwd(args, cot):
        shapes = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, jnp.float32),
                                        args)
        return tuple(jax.pure_callback(vjp, shapes, cot, *args))

    f.defvjp(f_fwd, f_bwd)
    return f


def _adapt(framework: str, render: Callable, out_shape: Callable) -> Callable:
    """``render`` as a function of the framework's arrays (:func:`_torch`, :func:`_jax`)."""
    return _torch(render) if framework == "torch" else _jax(render, out_shape)


def ray_renderer(scene: mi.Scene, keys: Sequence[str] = (), framework: str = "torch", *,
                 integrator: mi.Integrator | None = None) -> Callable:
    """A function of PyTorch or JAX tensors that renders rays through ``scene``.

    Parameters
    ----------
    scene : mi.Scene
        A scene with a ``tetmesh`` (and a ``tetvr`` integrator, or ``integrator``).
    keys : sequence of str
        The parameters (``mi.traverse`` names, e.g. ``"volume.vertex_color"``)
        the function takes values for.
    framework : str
        ``"torch"`` or ``"jax"``.
    integrator : mi.Integrator, optional
        A ``tetvr`` integrator (default: the scene's).

    Returns
    -------
    callable
        ``f(origins, directions, extents=None, values=None) -> rgba``:
        origins and directions ``(k, 3)``, extents ``(k,)`` or ``(k, 2)``
        (see :func:`~mi_tetvr.rays.render_rays`), ``values`` a dict of
        ``keys`` to tensors of each parameter's size (``(n, 3)`` colors,
        ``(n,)`` opacities, ...); returns ``(k, 4)`` RGBA. Differentiable
        w.r.t. the origins, directions and values. The values stay in the
        scene after the call.
    """
    values_of = _Values(scene, keys)
    fw = _framework(framework)
    from mi_tetvr.rays import render_rays

    def render(origins, directions, extents, values):
        params = values_of.write(values)
        return render_rays(scene, origins, directions, extents, params=params,
                           integrator=integrator)
    render = _adapt(fw, render, lambda o, *_: (o.shape[0], 4))

    def f(origins, directions, extents=None, values=None):
        return render(origins, directions, extents, dict(values or {}))
    return f


def camera_renderer(scene: mi.Scene, camera, keys: Sequence[str] = (),
                    framework: str = "torch", *,
                    integrator: mi.Integrator | None = None) -> Callable:
    """A function of PyTorch or JAX tensors that renders ``camera``'s image of
    ``scene`` from a given pose.

    Parameters
    ----------
    scene : mi.Scene
    camera : mi_tetvr.camera.Camera
        The camera model (size, intrinsics); its pose is the function's
        argument.
    keys, framework, integrator
        As for :func:`ray_renderer`.

    Returns
    -------
    callable
        ``f(to_world, values=None) -> image``: ``to_world`` the ``(4, 4)``
        camera-to-world matrix (Mitsuba's convention, as
        :attr:`Camera.to_world <mi_tetvr.camera.Camera.to_world>`),
        ``values`` as for :func:`ray_renderer`; returns the ``(height,
        width, 4)`` RGBA image (one ray through each pixel centre: the image
        ``mi.render`` gives with one sample there). Differentiable w.r.t. the
        pose and the values.
    """
    values_of = _Values(scene, keys)
    fw = _framework(framework)
    from mi_tetvr.rays import render_rays

    def render(to_world, values):
        if tuple(to_world.shape) != (4, 4):
            raise ValueError(f"to_world must have shape (4, 4), got {tuple(to_world.shape)}")
        params = values_of.write(values)
        m = [[dr.gather(mi.Float, to_world.array, 4 * i + j) for j in range(4)]
             for i in range(4)]
        ray = camera.rays_drjit(to_world=m)
        rgba = render_rays(scene, ray.o, ray.d, params=params, integrator=integrator)
        return mi.TensorXf(rgba.array, (camera.height, camera.width, 4))
    render = _adapt(fw, render, lambda *_: (camera.height, camera.width, 4))

    def f(to_world, values=None):
        return render(to_world, dict(values or {}))
    return f
