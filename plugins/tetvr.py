"""The ``tetvr`` integrator: emission-absorption volume rendering of ``tetmesh``
shapes by walking the tet adjacency.

.. pluginparameters::

 * - n_sub
   - |int|
   - Sub-intervals of the one approximated quantity of a tet segment, its mean
     transmittance (colors and the transmittance are exact; constant extinction at each
     sub-interval's midpoint as in DiffTetVR Alg. 1, extrapolated from n_sub / 2 for even
     n_sub: the error falls as 1/n_sub^4). See :mod:`mi_tetvr.render.segment`. (Default: 4)
 * - min_transmittance
   - |float|
   - Early ray termination once the transmittance falls below this. (Default: 1e-4)
 * - max_steps
   - |int|
   - Safety bound on tets crossed per walk. (Default: 100000)
 * - retrace_epsilon
   - |float|
   - Offset, relative to the scene's bounding-box diagonal, past a boundary
     face before tracing for re-entry. (Default: 1e-5)
 * - reduce_mode
   - |string|
   - How gradients of shared vertices are scatter-added in the derivative
     modes: ``auto`` (plain atomics on the LLVM backend, where they beat
     per-thread copies of the gradient buffers in ``benchmarks/bench_backward.py``;
     Dr.Jit's own choice on CUDA), ``expand`` (per-thread copies up to
     ``dr.expand_threshold()`` entries), ``local`` (pre-reduce within a SIMD
     packet / warp) or ``direct`` (plain atomics). See ``dr.ReduceMode``.
     (Default: ``auto``)
 * - alpha
   - |bool|
   - Add the coverage as an AOV channel named ``alpha``: 1 - T, and 1 where
     a surface is hit. (Default: true)
 * - kept_primals
   - |int|
   - Primal renders kept for the derivative passes that differentiate them (several views
     rendered before one ``dr.backward``); past it the oldest are dropped and their
     derivative pass renders the primal again, with a warning. See
     :mod:`mi_tetvr.render.replay`. (Default: 16)
 * - clip_origin, clip_normal
   - |point|, |vector|
   - A plane that cuts the volume: what lies on the side the normal points to
     is cut away (:mod:`mi_tetvr.render.clipping`; surfaces are not cut).
 * - clip_min, clip_max
   - |point|
   - A box that cuts the volume: what lies outside it is cut away.
 * - overlay
   - |integrator|
   - A ``tetproj`` integrator (named ``overlay``) in mode ``slice`` or
     ``iso``: its surfaces are drawn inside the volume, opaque or
     translucent (its ``opacity``, ``layers``), as ParaView shows a volume
     with a slice or a contour (:mod:`mi_tetvr.render.layers`). The scene's
     one tetmesh must be post-classified (a scalar and a transfer function).
     Derivatives as without it, and through the surfaces' colors and depths
     (not w.r.t. a differentiable camera).
 * - surfaces
   - |integrator|
   - Child integrator (named ``surfaces``) that renders the scene's other
     shapes, seen through the volume in front of them; it sees a scene of
     the surfaces and emitters without the tet meshes. Differentiating the
     surfaces' parameters needs one of Mitsuba's ``ADIntegrator``s (``prb``,
     ``prb_basic``, ``direct_projective``, ...). (Default: ``prb``)

Derivatives: ``mi.render`` with parameters, ``dr.backward`` and ``dr.forward``
reach ``<id>.vertex_color``, ``<id>.vertex_opacity`` and ``<id>.vertex_positions``
(post-classified: ``vertex_scalar``, ``tf_color``, ``tf_opacity``; the ``alpha``
AOV's gradient flows too), and ``dr.backward`` also the sensor's ``to_world``
(:func:`mi_tetvr.camera.orbit_to_world`); through a
differentiable nested integrator, the surfaces' parameters too (their
radiance's adjoint is ``T * δL``). The
adjoint re-walks the rays and records nothing (see
:mod:`mi_tetvr.render.walk`); the silhouettes of the mesh and of the surfaces
(which pixels they cover) have no boundary term.

The pixel value is ``C + T * L_surface`` where ``C`` is the emission
accumulated up to the first hit of another shape (a surface), ``T`` the
transmittance there and ``L_surface`` the nested integrator's radiance along
the ray (the environment where nothing is hit; in a scene of tet meshes
alone, the environment emitter's value, black without one). The
environment's parameters (an ``envmap``'s ``data``) are differentiable too.
Tet meshes of any optical models may share a scene; meshes that overlap in
space are integrated as one medium, their extinctions and emissions added
(:mod:`mi_tetvr.render.surfaces`, :mod:`mi_tetvr.render.merged`).
``sample()`` keeps the ``RBIntegrator`` contract and can be called on any
rays (with a sampler where the scene has surfaces).

.. code-block:: python

    'integrator': {
        'type': 'tetvr',
        'n_sub': 4,
        'surfaces': {'type': 'prb', 'max_depth': 6},
    }
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_tetvr.render.adjoint import Adjoint
from mi_tetvr.render.buffers import index_buffers, model_groups, scene_tetmeshes, tet_scene
from mi_tetvr.render.clipping import Clip
from mi_tetvr.render.linear import TetFrame
from mi_tetvr.render.merged import merged_trace, overlapping
from mi_tetvr.render.optical import PostClassified, Shaded
from mi_tetvr.render.replay import CAPACITY, PrimalStates, derivative_seed
from mi_tetvr.render.surfaces import DEFAULT_SURFACES, NestedIntegrator, SceneParts
from mi_tetvr.render.walk import WalkSettings, trace


class TetVRIntegrator(mi.ad.integrators.common.RBIntegrator):
    __doc__ = __doc__

    def __init__(self, props):
        super().__init__(props)
        n_sub = int(props.get("n_sub", 4))
        if not 1 <= n_sub <= 64:
            raise ValueError(f"tetvr: n_sub must be in [1, 64], got {n_sub}")
        t_min = float(props.get("min_transmittance", 1e-4))
        if not 0.0 <= t_min < 1.0:
            raise ValueError(f"tetvr: min_transmittance must be in [0, 1), got {t_min}")
        max_steps = int(props.get("max_steps", 100_000))
        if max_steps < 1:
            raise ValueError("tetvr: max_steps must be >= 1")
        self.retrace_epsilon = float(props.get("retrace_epsilon", 1e-5))
        llvm = dr.backend_v(mi.Float) == dr.JitBackend.LLVM
        modes = {"auto": dr.ReduceMode.Direct if llvm else dr.ReduceMode.Auto,
                 "expand": dr.ReduceMode.Expand,
                 "local": dr.ReduceMode.Local, "direct": dr.ReduceMode.Direct}
        reduce = str(props.get("reduce_mode", "auto")).lower()
        if reduce not in modes:
            raise ValueError(f"tetvr: reduce_mode must be one of {sorted(modes)}, got {reduce!r}")
        self.n_sub = n_sub
        self.settings = WalkSettings(t_min, max_steps, reduce=modes[reduce])
        self.alpha = bool(props.get("alpha", True))
        self.clip = Clip.from_props(props)
        nested, self.overlay = None, None
        for name, obj in props.objects():
            if name == "surfaces":
                nested = obj
            elif name == "overlay":
                if getattr(obj, "mode", None) not in ("slice", "iso"):
                    raise ValueError("tetvr: the overlay is a tetproj integrator in mode 'slice' "
                                     "or 'iso' (e.g. <integrator type=\"tetproj\" "
                                     "name=\"overlay\"> with <string name=\"mode\" "
                                     "value=\"iso\"/>)")
                self.overlay = obj
            else:
                raise ValueError(f"tetvr: unknown child {name!r} ({type(obj).__name__}); the "
                                 f"children are the integrator of the surfaces, named "
                                 f"'surfaces' (e.g. <integrator type=\"prb\" name=\"surfaces\"/>), "
                                 f"and a tetproj named 'overlay'")
        self.surfaces = NestedIntegrator(nested if nested is not None
                                         else mi.load_dict(DEFAULT_SURFACES))
        self.parts = SceneParts()
        self._index_cache = None
        self._states = PrimalStates(int(props.get("kept_primals", CAPACITY)))
        self._record = None    # (key, inputs) while render() runs with gradients enabled
        self._replay = None    # the kept primal state while a derivative pass runs

    def traverse(self, callback):
        if self.overlay is not None:
            # (its isovalues: overlay.iso)
            callback.put("overlay", self.overlay, mi.ParamFlags.Differentiable)

    def aov_names(self):
        return ["alpha"] if self.alpha else []

    def tet_scenes(self, scene):
        """The :class:`~mi_tetvr.render.buffers.TetScene` of each group of
        tet meshes that one walk renders (an optical model,
        :func:`~mi_tetvr.render.buffers.model_groups`): index buffers cached
        per set of shapes, positions and the optical model's parameters read
        afresh (they change under optimization)."""
        shapes = scene_tetmeshes(scene)
        # Meshes that overlap are walked together, one cursor each.
        groups = [[s] for s in shapes] if overlapping(shapes) else model_groups(shapes)
        key = tuple(tuple(id(s.tet_buffers) for s in g) for g in groups)
        if self._index_cache is None or self._index_cache[0] != key:
            self._index_cache = (key, [index_buffers(g) for g in groups])
        return [tet_scene(g, idx, offsets, n_sub=self.n_sub)
                for g, (idx, offsets) in zip(groups, self._index_cache[1])]

    def tet_scene(self, scene):
        """The one :class:`~mi_tetvr.render.buffers.TetScene` of a scene whose
        tet meshes share one walk (see :meth:`tet_scenes`)."""
        (ts,) = self.tet_scenes(scene)
        return ts

    @staticmethod
    def differentiable_inputs(scene):
        """The scene's arrays that the image depends on differentiably:
        vertex positions, the optical models' vertex buffers and the
        environment's parameters."""
        out = []
        for s in scene_tetmeshes(scene):
            out.append(s.vertex_positions_buffer())
            out += [s.attribute_buffer(name) for name, _ in s.optical_model.vertex_attributes]
            out += s.model_buffers()
        env = scene.environment()
        if env is not None:
            out += [v for _, v in mi.traverse(env).items() if dr.is_array_v(v)]
        return out

    # The derivative passes reuse the primal render's rays and per-ray
    # results instead of rendering it again (see mi_tetvr.render.replay).

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        with dr.resume_grad():
            inputs = self.differentiable_inputs(scene)
            # (with surfaces, the nested integrator samples paths: the derivative
            # pass renders its own primal with its own seed, as Mitsuba does)
            tracked = (any(dr.grad_enabled(x) for x in inputs)
                       and self.parts.split(scene)[2] is None and self.overlay is None)
        if tracked:
            self._record = (PrimalStates.key(scene, sensor, derivative_seed(seed), spp),
                            int(seed), [dr.detach(x) for x in inputs])
        try:
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        finally:
            self._record = None

    def _derivative_pass(self, base, scene, params, sensor, seed, spp, *grad_in):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        kept = self._states.take(PrimalStates.key(scene, sensor, seed, spp),
                                 [dr.detach(x) for x in self.differentiable_inputs(scene)])
        if kept is None:
            return base(scene, params, *grad_in, sensor, seed, spp)
        primal_seed, self._replay = kept
        try:
            return base(scene, params, *grad_in, sensor, primal_seed, spp)
        finally:
            self._replay = None

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        return self._derivative_pass(super().render_backward, scene, params, sensor, seed, spp,
                                     grad_in)

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        return self._derivative_pass(super().render_forward, scene, params, sensor, seed, spp)

    def background(self, scene, d, active):
        env = scene.environment()
        if env is None:
            return mi.Color3f(0.0)
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = -d
        return mi.Color3f(env.eval(si, active))

    def sample_rays(self, scene, sensor, sampler):
        # The sensor weight is a Spectrum; Mitsuba's render_backward and
        # render_forward multiply the AOVs by it, which makes the alpha AOV a
        # Color3f that the image block rejects. RGB sensors weight the three
        # channels equally, so keep one of them.
        # The rays keep their AD graph (to a differentiable sensor) in the
        # derivative passes, which run with AD suspended.
        with dr.resume_grad():
            ray, weight, pos = super().sample_rays(scene, sensor, sampler)
        return ray, mi.Float(dr.detach(weight)[0]), dr.detach(pos)

    def settings_for(self, scene):
        """Walk settings with the re-trace offset scaled to the scene."""
        s = self.settings
        return WalkSettings(s.t_min, s.max_steps,
                            self.retrace_epsilon * float(dr.norm(scene.bbox().extents())),
                            s.reduce)

    def sample(self, mode, scene, sampler, ray, δL, state_in, active, **kwargs):
        primal = mode == dr.ADMode.Primal
        tets, walk_scene, surfaces = self.parts.split(scene)
        # Derivative modes read the parameters with AD resumed (the caller,
        # e.g. render_backward, suspends it): the per-segment recomputation
        # inside the walk needs their AD graph; the walk itself runs detached.
        with dr.resume_grad(when=not primal):
            ts = self.tet_scenes(scene) if tets else None
            # A differentiable camera: rays attached to the sensor's parameters.
            camera = not primal and (dr.grad_enabled(ray.o) or dr.grad_enabled(ray.d))
        settings = self.settings_for(scene)
        ray_ad = ray
        ray = mi.Ray3f(dr.detach(ray))
        ray.d = dr.normalize(ray.d)
        active = mi.Bool(active)
        nested_ray = mi.Ray3f(ray)
        hit = mi.Bool(False)
        if surfaces is not None:
            # The volume is integrated up to the first surface.
            si = surfaces.ray_intersect_preliminary(ray, active=active)
            hit = active & si.is_valid()
            ray.maxt = dr.select(hit, si.t, ray.maxt)
        # The volume's part of the ray (surfaces are not clipped).
        t_start, walking = 0.0, active
        if self.clip is not None:
            t_start, t_end = self.clip.interval(ray.o, ray.d, ray.maxt)
            ray.maxt = dr.minimum(ray.maxt, t_end)
            walking = active & (t_end > t_start)
        if primal:
            # state: (pixel, transmittance, the nested integrator's state, the
            # overlay's layers, what lies behind the volume)
            if self._replay is not None and dr.width(self._replay[1]) == dr.width(ray):
                L, T = self._replay
                state = (L, T, None, None, None)
            else:
                layered = None
                if self.overlay is not None:
                    layered = self.overlay.layered(
                        walk_scene, ray, t_start, walking,
                        lambda r, s, a: self.volume(walk_scene, tets, ts, r, settings, a, s),
                        settings.t_min)
                    C, T = layered.L, layered.W
                else:
                    C, T = self.volume(walk_scene, tets, ts, ray, settings, walking, t_start)
                if surfaces is None:
                    Lb, nested_state = self.background(scene, ray.d, active), None
                else:
                    Lb, nested_state = self.surfaces.primal(surfaces, sampler, nested_ray,
                                                            active)
                L = C + T * Lb
                state = (L, T, nested_state, layered, Lb)
                if surfaces is None and layered is None and self._record is not None:
                    key, primal_seed, inputs = self._record
                    self._states.put(key, primal_seed, (L, T), inputs)
            alpha = dr.select(hit, 1.0, 1.0 - T)
            return L, mi.Bool(True), [alpha] if self.alpha else [], state
        if state_in is None:
            raise ValueError("tetvr: the derivative modes need the primal pass's state_in")
        L_pix, T_fin, layered = state_in[0], state_in[1], state_in[3]
        if layered is not None and camera:
            raise ValueError("tetvr: an overlay's images have no derivatives w.r.t. the camera "
                             "(its surfaces' depths are not differentiated along the rays)")
        δaovs = kwargs.get("δaovs", None)
        δalpha = mi.Float(δaovs[0]) if (self.alpha and δaovs) else mi.Float(0.0)
        # Where a surface is hit, alpha is 1 whatever the volume.
        δalpha = dr.select(hit, 0.0, δalpha)
        zero = mi.Vector3f(0.0)
        if mode == dr.ADMode.Backward:
            adj = Adjoint(mi.Color3f(L_pix), mi.Float(T_fin), mi.Color3f(δL), δalpha, zero, zero)
        else:
            adj = Adjoint(mi.Color3f(L_pix), mi.Float(T_fin), mi.Color3f(0.0), mi.Float(0.0),
                          zero, zero)
        d_seen = 0.0
        if surfaces is None:
            # The background term T * env(d): its derivative w.r.t. the
            # environment's parameters (e.g. a learned envmap's texels), taken
            # before the walk's forward mode consumes the input tangents.
            with dr.resume_grad():
                seen = mi.Float(T_fin) * self.background(scene, ray.d, active)
                if mode == dr.ADMode.Backward and dr.grad_enabled(seen):
                    dr.backward_from(seen * mi.Color3f(δL))
                if mode == dr.ADMode.Forward and dr.grad_enabled(seen):
                    d_seen = dr.forward_to(seen, flags=dr.ADFlag.ClearEdges)
        else:
            # The surfaces seen through the volume: T times their own derivative.
            d_seen = self.surfaces.derivative(
                mode, surfaces, sampler, nested_ray,
                mi.Color3f(δL) * T_fin if mode == dr.ADMode.Backward else None,
                state_in[2], active)
            if mode == dr.ADMode.Forward:
                d_seen = T_fin * d_seen
        if layered is not None:
            dL_layers, dalpha_layers = self.layers_derivative(
                mode, walk_scene, tets, ts, ray, settings, walking, layered, state_in[4],
                mi.Color3f(δL) if mode == dr.ADMode.Backward else None, δalpha)
            if mode == dr.ADMode.Backward:
                return mi.Color3f(0.0), mi.Bool(True), [], None
            dalpha = dr.select(hit, 0.0, dalpha_layers)
            return dL_layers + d_seen, mi.Bool(True), [dalpha] if self.alpha else [], None
        if ts is not None:
            tangent = None
            if camera and mode == dr.ADMode.Forward:
                # The rays' tangents, carried into every crossing's tangent.
                with dr.resume_grad():
                    tangent = tuple(dr.detach(x) for x in dr.forward_to(
                        ray_ad.o, dr.normalize(ray_ad.d),
                        flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad))
            for g in ts:
                g.camera, g.ray_tangent = camera, tangent
            _, _, _, adj = self.walk(mode, walk_scene, tets, [g.detached() for g in ts], ray,
                                     settings, walking, adj, ts, t_start)
        if mode == dr.ADMode.Backward:
            if camera:
                # The ray's gradient into the sensor: the origin's as is, the
                # direction's from the rotation gradient (g_d = g_w x d; the
                # direction is normalized, so its length has none).
                with dr.resume_grad():
                    dr.backward_from(dr.dot(ray_ad.o, adj.g_o) + dr.dot(
                        dr.normalize(ray_ad.d), dr.cross(adj.g_w, ray.d)))
            return mi.Color3f(0.0), mi.Bool(True), [], None
        dL = adj.dL + d_seen
        dalpha = dr.select(hit, 0.0, adj.dalpha)
        return dL, mi.Bool(True), [dalpha] if self.alpha else [], None

    def layers_derivative(self, mode, walk_scene, tets, ts, ray, settings, active, layered,
                          behind, δL, δalpha):
        """The derivative passes with an overlay (:mod:`mi_tetvr.render.layers`):
        the volume's intervals by the walk's adjoint (each with the radiance
        behind it and the transmittance in front), the surfaces' colors and
        (isosurfaces) depths by their closed forms. Backward: accumulates the
        gradients; forward: returns the tangents ``(dL, dalpha)``."""
        backward = mode == dr.ADMode.Backward
        fronts = layered.fronts()
        R = layered.behind(behind)
        zero = mi.Vector3f(0.0)
        dL, dalpha = mi.Color3f(0.0), mi.Float(0.0)
        with dr.resume_grad():
            overlay = self.overlay.tet_scene(walk_scene, differentiable=True)
            (volume,) = ts
            shares = self.overlay.replay_layers(
                overlay, layered, ray.o, ray.d,
                [W * layer.T for layer, W in zip(layered.layers, fronts)])
            total = mi.Color3f(0.0)
            for layer, (share, t, w) in zip(layered.layers, shares):
                total += share
                if self.overlay.mode == "iso":
                    # The surface's depth ends one interval and starts the next.
                    c, sigma = _volume_at(volume, layer.pick, ray.d)
                    rate = layered.alpha * w * sigma * (c - layer.color)
                    total += dr.select(layer.met, dr.detach(rate) * t, 0.0)
            if backward:
                dr.backward_from(δL * total, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
            else:
                # (before the walks' forward mode consumes the input tangents)
                dL += dr.forward_to(total, flags=dr.ADFlag.ClearEdges | dr.ADFlag.AllowNoGrad)
        detached = [g.detached() for g in ts]
        for g in ts:
            g.camera, g.ray_tangent = False, None
        for layer, W, R_k in zip(layered.layers, fronts, R):
            seg = mi.Ray3f(ray)
            seg.maxt = layer.end
            adj = (Adjoint(R_k, layered.W, δL * W, δalpha, zero, zero) if backward else
                   Adjoint(R_k, layered.W, mi.Color3f(0.0), mi.Float(0.0), zero, zero))
            _, _, _, adj = self.walk(mode, walk_scene, tets, detached, seg, settings,
                                     active & layer.active, adj, ts, layer.start)
            if not backward:
                dL += W * adj.dL
                dalpha += adj.dalpha
        return dL, dalpha

    def walk(self, mode, walk_scene, tets, ts, ray, settings, active, adj=None, ts_ad=None,
             t_start=0.0):
        """The walk of :func:`~mi_tetvr.render.walk.trace` through the tet
        meshes ``tets`` (their walks ``ts``, ``ts_ad``) along ``ray`` up to
        ``ray.maxt`` from ``t_start``; meshes that overlap in space take the merged walk
        (:func:`~mi_tetvr.render.merged.merged_trace`), as one medium."""
        if overlapping(tets):
            return merged_trace(mode, self.parts.apart(tets), ts, ray, settings, active, adj,
                                ts_ad, n_sub=self.n_sub, t_start=t_start)
        return trace(mode, walk_scene, ts, ray, settings, active, adj, ts_ad, t_start)

    def volume(self, walk_scene, tets, ts, ray, settings, active, t_start=0.0):
        """``(C, T)``: emission and transmittance of the tet meshes along
        ``ray`` from ``t_start`` (none without tet meshes)."""
        if ts is None:
            return mi.Color3f(0.0), dr.full(mi.Float, 1.0, dr.width(ray.o))
        C, T, _, _ = self.walk(dr.ADMode.Primal, walk_scene, tets, ts, ray, settings, active,
                               t_start=t_start)
        return C, T

    def to_string(self):
        s = self.settings
        return (f"TetVRIntegrator[n_sub={self.n_sub}, min_transmittance={s.t_min}, "
                f"max_steps={s.max_steps}, surfaces={self.surfaces!r}]")


def _volume_at(ts, pick, d):
    """``(color, extinction)`` of a post-classified volume (:class:`PostClassified`
    or :class:`Shaded`) at the pick of an isosurface of its scalar (the
    scalar there is the pick's texel coordinate), detached."""
    model, params = ts.model, ts.params
    if not hasattr(params, "tf_color"):
        raise ValueError("tetvr: the derivatives of an isosurface overlay need the volume's "
                         "transfer function: use classification 'post' (not 'preintegrated')")
    with dr.suspend_grad():
        (c, sigma), _ = PostClassified.classify(model, params, pick.u, pick.u)
        if isinstance(model, Shaded):
            frame = TetFrame(params, pick.tet)
            c = model.lit(c, frame.gradient([dr.gather(mi.Float, params.scalar, i)
                                             for i in frame.ids]), d)
    return dr.detach(c), dr.detach(sigma)


mi.register_integrator("tetvr", lambda props: TetVRIntegrator(props))
