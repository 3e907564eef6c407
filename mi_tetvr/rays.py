"""Rays in, colors out: any batch of rays rendered through a scene's tet meshes.

:func:`render_rays` renders rays given by their origins and directions (and,
optionally, the stretch of each that counts) with the scene's ``tetvr``
integrator, and returns RGBA per ray. It runs the integrator's own ray
program, so a ray through a pixel centre gets the value ``mi.render`` gives
that pixel (with one sample per pixel at its centre), and it is an operation
of Dr.Jit's AD graph as ``mi.render`` is: ``dr.backward`` and ``dr.forward``
reach every scene parameter the integrator differentiates (vertex colors,
opacities, positions, scalars, transfer functions, the environment) and the
rays themselves. The derivative passes walk the rays again and record
nothing, so their memory does not grow with the tets a ray crosses.

This is what renders a random batch of pixels from many photos in one step
of a fit, rays from a camera model Mitsuba does not have, and what
:mod:`mi_tetvr.interop` hands to PyTorch and JAX.

Needs a Mitsuba variant (``llvm_ad_rgb`` or ``cuda_ad_rgb``).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

__all__ = ["render_rays", "ray_arrays"]


def _integrator(scene, integrator):
    """The ``tetvr`` integrator that renders the rays."""
    from mi_tetvr.render.buffers import scene_tetmeshes
    if not isinstance(scene, mi.Scene):
        raise TypeError(f"render_rays: scene must be a mitsuba Scene, got {type(scene).__name__}")
    if not scene_tetmeshes(scene):
        raise ValueError("render_rays: the scene has no tetmesh shape (nothing to render the "
                         "rays through)")
    integrator = scene.integrator() if integrator is None else integrator
    # (a tetvr integrator is the one whose ray program a scene builds)
    if not callable(getattr(integrator, "program", None)):
        name = type(integrator).__name__ if integrator is not None else "none"
        raise ValueError(f"render_rays: renders with a tetvr integrator, and the scene's is "
                         f"{name}: pass integrator=mi.load_dict({{'type': 'tetvr'}})")
    return integrator


def _vectors(x, cls, what: str):
    """``x`` as a Dr.Jit 3-vector array of type ``cls`` (AD graph kept): a
    Dr.Jit 3-vector, a ``TensorXf`` or an array of shape (k, 3)."""
    if isinstance(x, mi.TensorXf):
        if x.ndim != 2 or x.shape[1] != 3:
            raise ValueError(f"render_rays: {what} must have shape (k, 3), got {x.shape}")
        return dr.unravel(cls, x.array)
    if dr.is_array_v(x):
        if dr.size_v(x) != 3 or not dr.is_float_v(x):
            raise ValueError(f"render_rays: {what} must be a 3-vector array (mi.Point3f, "
                             f"mi.Vector3f) or of shape (k, 3), got {type(x).__name__}")
        return cls(x)
    a = np.asarray(x, np.float32)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"render_rays: {what} must have shape (k, 3), got {a.shape}")
    from mi_tetvr.render.buffers import owned
    return cls(*(owned(mi.Float, np.ascontiguousarray(c)) for c in a.T))


def _extents(x, k: int):
    """``(near, far)`` Floats of ray extents: None (0 to infinity), a number
    or ``(k,)`` (the far end), or ``(k, 2)`` (near and far)."""
    inf = dr.full(mi.Float, dr.inf, k)
    if x is None:
        return dr.zeros(mi.Float, k), inf
    if isinstance(x, (int, float)):
        return dr.zeros(mi.Float, k), dr.full(mi.Float, float(x), k)
    if isinstance(x, mi.TensorXf):
        shape, flat = tuple(x.shape), dr.detach(x.array)
    elif dr.is_array_v(x):
        shape, flat = (dr.width(x),), dr.detach(mi.Float(x))
    else:
        a = np.asarray(x, np.float32)
        shape, flat = a.shape, mi.Float(a.ravel())
    if shape == (k,):
        return dr.zeros(mi.Float, k), flat
    if shape == (k, 2):
        near, far = dr.unravel(mi.Point2f, flat)
        return near, far
    raise ValueError(f"render_rays: extents must be a number, of shape ({k},) (the far end) "
                     f"or ({k}, 2) (near and far), got shape {shape}")


def ray_arrays(origins, directions, extents=None):
    """``(o, d, near, far)``: rays as Dr.Jit arrays (``mi.Point3f``,
    ``mi.Vector3f`` and two ``mi.Float``), checked: the same count of
    origins, directions and extents, all finite (a far end may be infinite),
    no zero direction, ``0 <= near < far``. The origins and directions keep
    their AD graph; the extents are constants.

    Raises
    ------
    ValueError
        Naming the first thing wrong.
    """
    o = _vectors(origins, mi.Point3f, "origins")
    d = _vectors(directions, mi.Vector3f, "directions")
    k = dr.width(o)
    if dr.width(d) != k:
        raise ValueError(f"render_rays: {k} origins and {dr.width(d)} directions")
    if k == 0:
        raise ValueError("render_rays: no rays")
    near, far = _extents(extents, k)
    # (one reduction, read at once: what is wrong, in one number each)
    od = dr.detach(o), dr.detach(d)
    bad = mi.Vector4u(
        dr.count(~(dr.isfinite(od[0].x) & dr.isfinite(od[0].y) & dr.isfinite(od[0].z))),
        dr.count(~(dr.isfinite(od[1].x) & dr.isfinite(od[1].y) & dr.isfinite(od[1].z))),
        dr.count(dr.squared_norm(od[1]) == 0.0),
        dr.count(~(dr.isfinite(near) & (near >= 0.0) & (far > near) & ~dr.isnan(far))))
    n_o, n_d, n_zero, n_ext = (int(v[0]) for v in bad)
    for n, what in ((n_o, "origins are not finite (NaN or infinite)"),
                    (n_d, "directions are not finite (NaN or infinite)"),
                    (n_zero, "directions are zero"),
                    (n_ext, "extents are not 0 <= near < far (or are NaN)")):
        if n:
            raise ValueError(f"render_rays: {n} of {k} rays' {what}")
    return o, d, near, far


class _RaysOp(dr.CustomOp):
    """``render_rays`` in the AD graph: the primal evaluates the rays with AD
    suspended; the derivative passes run the integrator's ray program's
    derivative over them (rays attached to leaves of their own where their
    derivatives are asked for), as ``mi.render`` runs ``render_forward`` and
    ``render_backward``."""

    def eval(self, o, d, near, far, _, params, scene, integrator, seed, camera):
        # (``_``: the parameters as a dict, the op's inputs in the AD graph;
        # ``params`` the SceneParameters they come from, as mi.render passes them)
        self.o, self.d, self.near, self.far = o, d, near, far
        self.seed, self.camera = seed, camera
        self.program = integrator.program(scene)
        self.k = dr.width(o)
        with dr.suspend_grad():
            L, T, hit, state = self.program.primal(self._ray(o, d), self._sampler(seed), True)
            # (the derivative passes reuse the primal's values where nothing
            # behind the volume samples paths; else they render their own, as
            # mi.render's do, with a seed of their own)
            self.state = state if self.program.keeps_primal() else None
            # (the walk's values as arrays of their own: the derivative passes
            # read them, and must not hold the walk that computed them)
            dr.eval(L, T, hit)
            return self._tensor(L, dr.select(hit, 1.0, 1.0 - T))

    def _ray(self, o, d) -> mi.Ray3f:
        """Rays from ``o`` along ``d`` over the extents (the near end as the
        origin: a start point inside a mesh is walked from there)."""
        return mi.Ray3f(o + self.near * dr.normalize(d), d, self.far - self.near, 0.0,
                        mi.Color0f())

    def _sampler(self, seed: int):
        """A sampler for what lies behind the volume (None where nothing
        samples)."""
        if self.program.surfaces is None:
            return None
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(seed, self.k)
        return sampler

    def _tensor(self, L, alpha) -> mi.TensorXf:
        return mi.TensorXf(dr.ravel(mi.Vector4f(L.x, L.y, L.z, alpha)), shape=(self.k, 4))

    def _derivative_inputs(self, mode):
        """``(ray, state, sampler, leaves)`` for a derivative pass: the rays
        (attached to fresh leaves where the camera is differentiated; forward
        mode: carrying the input tangents) and the primal state."""
        leaves = None
        o, d = self.o, self.d
        if self.camera:
            leaves = (mi.Point3f(o), mi.Vector3f(d))
            dr.enable_grad(leaves)
            if mode == dr.ADMode.Forward:
                dr.set_grad(leaves[0], self.grad_in("o"))
                dr.set_grad(leaves[1], self.grad_in("d"))
            with dr.resume_grad():
                ray = self._ray(*leaves)
        else:
            ray = self._ray(o, d)
        state = self.state
        seed = int(mi.sample_tea_32(int(self.seed), 1)[0])
        if state is None:
            with dr.suspend_grad():
                *_, state = self.program.primal(self._ray(o, d), self._sampler(seed), True)
        return ray, state, self._sampler(seed), leaves

    def forward(self):
        ray, state, sampler, _ = self._derivative_inputs(dr.ADMode.Forward)
        with dr.suspend_grad():
            out = self.program.derivative(dr.ADMode.Forward, ray, sampler, None, mi.Float(0.0),
                                          state, True)
        dL, dalpha = out if out is not None else (mi.Color3f(0.0), mi.Float(0.0))
        self.set_grad_out(self._tensor(dL, dalpha))

    def backward(self):
        g = dr.unravel(mi.Vector4f, self.grad_out().array)
        ray, state, sampler, leaves = self._derivative_inputs(dr.ADMode.Backward)
        with dr.suspend_grad():
            self.program.derivative(dr.ADMode.Backward, ray, sampler, mi.Color3f(g.x, g.y, g.z),
                                    mi.Float(g.w), state, True)
        if leaves is not None:
            self.set_grad_in("o", dr.grad(leaves[0]))
            self.set_grad_in("d", dr.grad(leaves[1]))

    def name(self):
        return "RenderRays"


def render_rays(scene: mi.Scene, origins, directions, extents=None, *,
                params: mi.SceneParameters | None = None,
                integrator: mi.Integrator | None = None, seed: int = 0) -> mi.TensorXf:
    """RGBA of rays through the scene's tet meshes (and what lies behind
    them), as the scene's ``tetvr`` integrator renders a pixel.

    Parameters
    ----------
    scene : mi.Scene
        A scene with at least one ``tetmesh``.
    origins, directions : mi.Point3f, mi.Vector3f, mi.TensorXf (k, 3) or (k, 3) array
        The rays (directions of any length: they are normalized, and the
        extents are distances). Dr.Jit arrays keep their AD graph: the result
        is differentiable w.r.t. them (``dr.backward`` gives their gradients,
        ``dr.forward`` takes their tangents).
    extents : float, (k,) or (k, 2), optional
        Where along each ray the volume counts: its far end, or near and far
        ends (``0 <= near < far``; a near end inside a mesh starts the walk
        there). Constants (no derivative). Default: from the origin to
        infinity.
    params : mi.SceneParameters, optional
        The parameters whose derivatives the result carries, as for
        ``mi.render`` (default: all of ``mi.traverse(scene)``; only those
        with gradients enabled count).
    integrator : mi.Integrator, optional
        A ``tetvr`` integrator (default: the scene's).
    seed : int, optional
        Seeds the paths the integrator's nested integrator samples behind the
        volume (a scene with surfaces). Default 0.

    Returns
    -------
    mi.TensorXf
        Shape ``(k, 4)``: linear RGB and alpha (coverage: 1 minus the
        transmittance; 1 where a surface is hit) of each ray.

    Raises
    ------
    ValueError
        For rays of the wrong shape, NaN or infinite rays, zero directions,
        bad extents, a scene without a ``tetmesh`` or an integrator that is
        not ``tetvr``.

    Examples
    --------
    >>> rgba = render_rays(scene, origins, directions)              # doctest: +SKIP
    >>> dr.backward(dr.mean(dr.square(rgba - target), axis=None))   # doctest: +SKIP
    """
    integrator = _integrator(scene, integrator)
    o, d, near, far = ray_arrays(origins, directions, extents)
    camera = dr.grad_enabled(o) or dr.grad_enabled(d)
    if params is None:
        params = mi.traverse(scene)
    elif not isinstance(params, mi.SceneParameters):
        raise TypeError("render_rays: params must be mi.SceneParameters (mi.traverse(scene))")
    return dr.custom(_RaysOp, o, d, near, far, dict(params), params, scene, integrator,
                     int(seed), camera)
