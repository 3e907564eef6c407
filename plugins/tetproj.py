"""The ``tetproj`` integrator: intensity projections of a ``tetmesh``'s scalar
(the maximum, minimum or mean along each ray), as ParaView's *Maximum /
Minimum / Average Intensity* blend modes show a volume, slices (the scalar on
a plane through the mesh) and isosurfaces.

The scene holds one post-classified ``tetmesh`` (a scalar and a transfer
function) and nothing else. Each ray walks every tet it crosses
(:mod:`mi_tetvr.render.walk`, with the :class:`~mi_tetvr.render.optical.Projection`
model): the scalar is linear in each tet, so the maximum and the minimum of
a segment are at its ends and its mean is the trapezoid's; the projection is
exact. A slice (:class:`~mi_tetvr.render.optical.Slice`) stops each ray
where it first crosses the plane inside the mesh, the scalar there exact too
(the plane's signed distance is linear along the ray in a tet); an
isosurface (:class:`~mi_tetvr.render.optical.Isosurface`) where the scalar
first crosses one of the isovalues. The pixel is the transfer function's color at the projected value
(its opacity is not used), alpha 1 where the ray meets the mesh; the film's
``rgba`` format keeps it. Translucent surfaces (``opacity`` below 1) are
composited front to back over black (the film's alpha still marks where a
surface is met). Nested in ``tetvr`` as its ``overlay``, a slice or
isosurfaces are drawn inside the volume (ParaView's volume with a contour
or a slice).

.. pluginparameters::

 * - mode
   - |string|
   - ``max`` (maximum intensity projection, the default), ``min``, ``mean``
     (average over the length inside the mesh), ``slice`` or ``iso``.
 * - iso
   - |string|
   - ``iso``: the isovalue(s) of the scalar, comma-separated (data units); the
     first one a ray meets is shown, shaded by a headlight (Lambert on the
     normal interpolated from the vertices' gradients).
 * - origin, normal
   - |point|, |vector|
   - ``slice``: a point of the plane (default: the centre of the scene's
     bounding box) and its normal (default: +z).
 * - opacity
   - |float|
   - ``slice``, ``iso``: the surfaces' opacity in (0, 1]; below 1 a ray
     goes on through them, each composited front to back
     (:mod:`mi_tetvr.render.layers`). (Default: 1, opaque)
 * - layers
   - |int|
   - ``slice``, ``iso``: the most surfaces drawn along a ray (further
     ones are not). (Default: 1 when opaque, else 8)
 * - clip_origin, clip_normal, clip_min, clip_max
   - |point|, |vector|
   - A plane and a box that cut the mesh, as ``tetvr``'s.
 * - max_steps
   - |int|
   - Safety bound on tets crossed per walk. (Default: 100000)
 * - retrace_epsilon
   - |float|
   - Offset, relative to the scene's bounding-box diagonal, past a boundary
     face before tracing for re-entry. (Default: 1e-5)

Derivatives (``mi.render`` with parameters, ``dr.backward``, ``dr.forward``)
w.r.t. the tetmesh's ``vertex_scalar``, ``tf_color`` and ``vertex_positions``
and the integrator's ``iso`` (the isovalues, a parameter of
``mi.traverse(integrator)``), in every mode but ``mean``: the point a ray
shows is recomputed in closed form in the tet the primal walk found it in
(:meth:`~mi_tetvr.render.optical.RayValue.replay`), so they are exact where
that point moves smoothly (not across silhouettes or the slice's rim).

.. code-block:: python

    'integrator': {'type': 'tetproj', 'mode': 'max'}
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_tetvr.render.buffers import MeshBuffers, TetScene, index_buffers, scene_tetmeshes
from mi_tetvr.render.clipping import Clip, unit_vector
from mi_tetvr.render.layers import composite
from mi_tetvr.render.optical import (CellClassified, Isosurface, PostClassified, Projection,
                                     Slice)
from mi_tetvr.render.walk import WalkSettings, trace


class TetProjIntegrator(mi.ad.integrators.common.RBIntegrator):
    __doc__ = __doc__

    def __init__(self, props):
        super().__init__(props)
        self.mode = str(props.get("mode", "max")).lower()
        modes = Projection.MODES + ("slice", "iso")
        if self.mode not in modes:
            raise ValueError(f"tetproj: mode must be one of {modes}, got {self.mode!r}")
        iso = [float(v) for v in str(props.get("iso", "")).split(",") if v.strip()]
        if self.mode == "iso" and not iso:
            raise ValueError("tetproj: mode 'iso' needs 'iso', the isovalue(s)")
        self.iso = mi.Float(iso)
        self.origin = list(props["origin"]) if "origin" in props else None
        self.normal = unit_vector(list(props.get("normal", [0.0, 0.0, 1.0])),
                                  "tetproj: the slice's normal").tolist()
        self.opacity = float(props.get("opacity", 1.0))
        if not 0.0 < self.opacity <= 1.0:
            raise ValueError(f"tetproj: opacity must be in (0, 1], got {self.opacity}")
        self.layers = int(props.get("layers", 1 if self.opacity == 1.0 else 8))
        if self.layers < 1:
            raise ValueError(f"tetproj: layers must be >= 1, got {self.layers}")
        if self.mode not in ("slice", "iso") and ("opacity" in props or "layers" in props):
            raise ValueError("tetproj: opacity and layers apply to surfaces (mode slice or "
                             f"iso), not to mode {self.mode!r}")
        self.clip = Clip.from_props(props)
        self.max_steps = int(props.get("max_steps", 100_000))
        self.retrace_epsilon = float(props.get("retrace_epsilon", 1e-5))

    def traverse(self, callback):
        if self.mode == "iso":
            callback.put("iso", self.iso, mi.ParamFlags.Differentiable)

    def tet_scene(self, scene, differentiable=False):
        """The :class:`TetScene` of the scene's one post-classified mesh, walked
        by the mode's model (:class:`Projection`, :class:`Slice` or
        :class:`Isosurface`); ``differentiable``: for the derivative passes."""
        shapes = scene_tetmeshes(scene)
        others = len(scene.shapes()) - len(shapes)
        if len(shapes) != 1 or others:
            raise ValueError(f"tetproj: projects a scene of one tetmesh, got {len(shapes)} "
                             f"tetmesh(es) and {others} other shape(s)")
        if not issubclass(shapes[0].optical_model, PostClassified):
            raise ValueError("tetproj: projects a scalar: give the tetmesh a scalar and a "
                             "transfer_function (classification 'post' or 'preintegrated')")
        if shapes[0].optical_model is CellClassified:
            raise ValueError("tetproj: shows a scalar per vertex, linear in each tet; this "
                             "tetmesh's scalar is cell data: average it onto the vertices "
                             "(cell_to_point) or render it with tetvr")
        if self.mode == "slice":
            box = scene.bbox()
            origin = self.origin if self.origin is not None else list(box.center())
            model = Slice(origin, self.normal)
        elif self.mode == "iso":
            model = Isosurface(self.iso if differentiable else dr.detach(self.iso))
        else:
            model = Projection(self.mode)
        index, offsets = index_buffers(shapes)
        buf = MeshBuffers(**index, positions=shapes[0].vertex_positions_buffer())
        return TetScene(shapes, offsets, buf, model, model.read_params(shapes))

    def settings_for(self, scene):
        return WalkSettings(0.0, self.max_steps,
                            self.retrace_epsilon * float(dr.norm(scene.bbox().extents())))

    def clipped(self, ray, active=True):
        """``(ray, t_start, active)``: the rays cut to this integrator's clip."""
        if self.clip is None:
            return ray, 0.0, active
        ray = mi.Ray3f(ray)
        t_start, t_end = self.clip.interval(ray.o, ray.d, ray.maxt)
        ray.maxt = dr.minimum(ray.maxt, t_end)
        return ray, t_start, active & (t_end > t_start)

    def project(self, scene, ray, active=True, picks=False):
        """``(color, met, scalar)`` of the projection along rays (normalised
        directions); for ``iso``, ``(color, met, hit point)`` of the first
        surface; with ``picks``, also the walk's
        :class:`~mi_tetvr.render.optical.Pick` (for the derivative passes)."""
        ts = self.tet_scene(scene)
        ray, t_start, active = self.clipped(ray, active)
        out, L = self.walk(scene, ts, ray, t_start, active)
        return (*out, L) if picks else out

    def walk(self, scene, ts, ray, start, active):
        """``((color, met, scalar or hit point), pick)`` of the rays walked
        from ``start``."""
        L, _, _, _ = trace(dr.ADMode.Primal, scene, ts, ray, self.settings_for(scene), active,
                           t_start=start)
        if isinstance(ts.model, Isosurface):
            return ts.model.shade(ts.params, L, ray.d), L
        return ts.model.finish(ts.params, L), L

    def find(self, scene, ts, ray, start, active):
        """``(met, color, pick, t)``: the first surface (slice or isosurface)
        along ``ray`` after ``start``."""
        (color, met, _), L = self.walk(scene, ts, ray, start, active)
        return met, color, L, dr.dot(L.p - ray.o, ray.d)

    def layered(self, scene, ray, t_start=0.0, active=True, volume=None, t_min=1e-4):
        """The surfaces along ``ray`` from ``t_start`` to ``ray.maxt`` (both
        cut further by this integrator's clip) composited front to back with
        ``volume`` (:func:`~mi_tetvr.render.layers.composite`)."""
        if self.mode not in ("slice", "iso"):
            raise ValueError(f"tetproj: mode {self.mode!r} shows no surface (slice and iso do)")
        ts = self.tet_scene(scene)
        ray, t_clip, active = self.clipped(ray, active)
        eps = self.settings_for(scene).retrace_eps
        return composite(lambda r, s, a: self.find(scene, ts, r, s, a), volume, ray,
                         dr.maximum(t_start, t_clip), active, self.opacity, self.layers, eps,
                         t_min)

    def replay_layers(self, ts, layered, o, d, weights=None):
        """The layers' share of the pixel, ``sum_k alpha w_k S_k`` with each
        color recomputed with the AD graph from its pick (``weights``: the
        transmittance in front of each surface; default that of the layers
        alone), and each layer's depth ``t_k`` alike: ``[(share, t_k, w_k)]``."""
        out = []
        W = mi.Float(1.0)
        for j, layer in enumerate(layered.layers[:-1]):
            w = W if weights is None else weights[j]
            color, t = ts.model.replay_surface(ts.params, ts.buf, layer.pick, o, d)
            out.append((dr.select(layer.met, layered.alpha * w * color, 0.0), t, w))
            W = dr.select(layer.met, W * (1.0 - layered.alpha), W)
        return out

    def sample(self, mode, scene, sampler, ray, δL, state_in, active, **kwargs):
        ray = mi.Ray3f(dr.detach(ray))
        ray.d = dr.normalize(ray.d)
        layers = self.mode in ("slice", "iso")
        if mode == dr.ADMode.Primal:
            with dr.suspend_grad():
                if layers:
                    rec = self.layered(scene, ray, 0.0, active)
                    return mi.Spectrum(rec.L), rec.met, [], rec
                color, met, _, picks = self.project(scene, ray, active, picks=True)
            return mi.Spectrum(color), met, [], (picks, met)
        # The derivative passes: each ray's pick again, with the AD graph.
        with dr.resume_grad():
            ts = self.tet_scene(scene, differentiable=True)
            if layers:
                color = sum((c for c, _, _ in self.replay_layers(ts, state_in, ray.o, ray.d)),
                            mi.Color3f(0.0))
                met = state_in.met
            else:
                picks, met = state_in
                color = ts.model.replay(ts.params, ts.buf, picks, ray.o, ray.d)
            if mode == dr.ADMode.Backward:
                dr.backward_from(δL * color)
                return mi.Spectrum(0.0), met, [], None
            return mi.Spectrum(dr.forward_to(color)), met, [], None

    def to_string(self):
        plane = (f", origin={self.origin}, normal={self.normal}" if self.mode == "slice"
                 else "")
        return f"TetProjIntegrator[mode={self.mode}{plane}, max_steps={self.max_steps}]"


mi.register_integrator("tetproj", lambda props: TetProjIntegrator(props))
