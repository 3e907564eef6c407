"""The ray program: what happens along a camera ray, in one place.

Along each ray, in this order:

1. the first *surface* of the scene (a shape that is not a tet mesh) ends
   the volume's part of the ray (:mod:`~mi_tetvr.render.surfaces`);
2. a *clip* (:mod:`~mi_tetvr.render.clipping`) cuts that part to one
   interval;
3. *probes* (slices, isosurfaces: :class:`Probes`) found one after the other
   along the interval split it into layers, composited front to back with
   the volume between them (:mod:`~mi_tetvr.render.layers`);
4. the *media* (the tet meshes' optical models) are integrated over each
   interval by the walk (:mod:`~mi_tetvr.render.walk`; meshes that overlap
   in space by the merged walk, :mod:`~mi_tetvr.render.merged`, one cursor
   per mesh);
5. what lies *behind* (the nested integrator's radiance at the surface, or
   the environment) is seen through the transmittance left.

A :class:`VolumeProgram` is built from a scene and the ``tetvr`` plugin's
settings each time the plugin samples: the features the scene does not use
(surfaces, clip, probes, overlapping meshes) are not part of it, so their
code is neither traced nor run. The derivative passes get an explicit
context (:class:`~mi_tetvr.render.adjoint.Derivative`: the AD mode, the
camera's tangents) handed down to the walk, and the primal pass's per-ray
state. :class:`Probes` is what ``tetproj`` shows (projections, slices,
isosurfaces) and what ``tetvr`` draws inside its volume (its ``overlay``).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi

from mi_tetvr.render import layers
from mi_tetvr.render.adjoint import Adjoint, Derivative
from mi_tetvr.render.buffers import (MeshBuffers, TetGroup, index_buffers, scene_tetmeshes,
                                     tet_group)
from mi_tetvr.render.clipping import Clip
from mi_tetvr.render.merged import merged_trace, overlapping, walk_groups
from mi_tetvr.render.optical import CellClassified, PostClassified
from mi_tetvr.render.probes import Isosurface, Pick, Projection, Slice, VertexGradients
from mi_tetvr.render.cursor import WalkSettings
from mi_tetvr.render.walk import trace

#: Probe modes that show surfaces (and so layers: slices and isosurfaces).
SURFACE_MODES = ("slice", "iso")


def clipped(clip: Clip | None, ray: mi.Ray3f,
            active: bool | mi.Bool = True) -> tuple[mi.Ray3f, float | mi.Float, bool | mi.Bool]:
    """``(ray, t_start, active)``: the rays cut to ``clip`` (None: as they are)."""
    if clip is None:
        return ray, 0.0, active
    ray = mi.Ray3f(ray)
    t_start, t_end = clip.interval(ray.o, ray.d, ray.maxt)
    ray.maxt = dr.minimum(ray.maxt, t_end)
    return ray, t_start, active & (t_end > t_start)


def scaled_settings(settings: WalkSettings, retrace_epsilon: float,
                    scene: mi.Scene) -> WalkSettings:
    """``settings`` with the re-trace offset scaled to the scene's size."""
    return WalkSettings(settings.t_min, settings.max_steps,
                        retrace_epsilon * float(dr.norm(scene.bbox().extents())),
                        settings.reduce)


class Probes:
    """What a ``tetproj`` picks along rays through a scene's one
    post-classified tet mesh: the maximum, minimum or mean of its scalar
    (``mode`` ``max``, ``min``, ``mean``), the scalar on a plane (``slice``:
    ``plane = (origin, normal)``) or the first of its isosurfaces (``iso``:
    ``iso``, the values, a differentiable ``Float``). Surfaces are drawn with
    ``opacity``, at most ``count`` of them along a ray (:mod:`~mi_tetvr.render.layers`);
    ``clip`` cuts the mesh."""
    #: (the arrays Dr.Jit reaches through the integrator that holds the
    #: probes, e.g. as a frozen render's input: the isovalues, the kept
    #: vertex gradients)
    DRJIT_STRUCT = {"iso": mi.Float, "gradients": VertexGradients}

    def __init__(self, mode: str, iso: mi.Float, plane: tuple, opacity: float, count: int,
                 clip: Clip | None, settings: WalkSettings, retrace_epsilon: float) -> None:
        self.mode, self.iso, (self.origin, self.normal) = mode, iso, plane
        self.opacity, self.count, self.clip = opacity, count, clip
        self.settings, self.retrace_epsilon = settings, retrace_epsilon
        #: The isosurfaces' vertex gradients, kept between renders.
        self.gradients = VertexGradients()

    @property
    def surfaces(self) -> bool:
        """Whether the probes are surfaces (slices, isosurfaces)."""
        return self.mode in SURFACE_MODES

    def tet_group(self, scene: mi.Scene, differentiable: bool = False) -> TetGroup:
        """The :class:`TetGroup` of the scene's one post-classified mesh,
        walked by the mode's model (:class:`Projection`, :class:`Slice` or
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
            origin = self.origin if self.origin is not None else list(scene.bbox().center())
            model = Slice(origin, self.normal)
        elif self.mode == "iso":
            model = Isosurface(self.iso if differentiable else dr.detach(self.iso),
                               self.gradients)
        else:
            model = Projection(self.mode)
        index, offsets = index_buffers(shapes)
        buf = MeshBuffers(**index, positions=shapes[0].vertex_positions_buffer())
        return TetGroup(shapes, offsets, buf, model, model.read_params(shapes))

    def walk(self, scene: mi.Scene, ts: TetGroup, ray: mi.Ray3f, start: float | mi.Float,
             active: bool | mi.Bool
             ) -> tuple[tuple[mi.Color3f, mi.Bool, mi.Float | mi.Point3f], Pick | mi.Color3f]:
        """``((color, met, scalar or hit point), pick)`` of the rays walked
        from ``start``."""
        L, _, _, _ = trace(scene, ts, ray, scaled_settings(self.settings, self.retrace_epsilon,
                                                           scene), active, start)
        if isinstance(ts.model, Isosurface):
            return ts.model.shade(ts.params, L, ray.d), L
        return ts.model.finish(ts.params, L), L

    def project(self, scene: mi.Scene, ray: mi.Ray3f, active: bool | mi.Bool = True
                ) -> tuple[mi.Color3f, mi.Bool, mi.Float | mi.Point3f, Pick | mi.Color3f]:
        """``(color, met, scalar or hit point, pick)`` of the first probe
        along rays (normalised directions)."""
        ts = self.tet_group(scene)
        ray, t_start, active = clipped(self.clip, ray, active)
        out, L = self.walk(scene, ts, ray, t_start, active)
        return (*out, L)

    def layered(self, scene: mi.Scene, ray: mi.Ray3f, t_start: float | mi.Float = 0.0,
                active: bool | mi.Bool = True,
                volume: Callable[[mi.Ray3f, mi.Float, mi.Bool],
                                 tuple[mi.Color3f, mi.Float]] | None = None,
                t_min: float = 1e-4) -> layers.Layered:
        """The surfaces along ``ray`` from ``t_start`` to ``ray.maxt`` (both
        cut further by the clip) composited front to back with ``volume``
        (:func:`~mi_tetvr.render.layers.composite`)."""
        if not self.surfaces:
            raise ValueError(f"tetproj: mode {self.mode!r} shows no surface (slice and iso do)")
        # (laid out for the walk once: each layer walks it again)
        ts = self.tet_group(scene).walked()
        ray, t_clip, active = clipped(self.clip, ray, active)
        eps = self.retrace_epsilon * float(dr.norm(scene.bbox().extents()))

        def find(r, start, go):
            (color, met, _), L = self.walk(scene, ts, r, start, go)
            return met, color, L, dr.dot(L.p - r.o, r.d)
        return layers.composite(find, volume, ray, dr.maximum(t_start, t_clip), active,
                                layers.Drawing(self.opacity, self.count, eps, t_min))

    def replay(self, scene: mi.Scene, state: layers.Layered | Pick, o: mi.Point3f,
               d: mi.Vector3f) -> mi.Color3f:
        """A pixel's color recomputed with the parameters' AD graph from the
        primal pass's ``state`` (a :class:`~mi_tetvr.render.layers.Layered`
        for surfaces, else the rays' picks)."""
        ts = self.tet_group(scene, differentiable=True)
        if self.surfaces:
            return sum((c for c, _, _ in layers.replay(ts, state, o, d)), mi.Color3f(0.0))
        return ts.model.replay(ts.params, ts.buf, state, o, d)

    def __repr__(self):
        plane = (f", origin={self.origin}, normal={self.normal}" if self.mode == "slice"
                 else "")
        return f"Probes[mode={self.mode}{plane}, max_steps={self.settings.max_steps}]"


@dataclass
class ProgramOptions:
    """What a ``tetvr`` integrator builds its ray programs from.

    parts : mi_tetvr.render.surfaces.SceneParts
        The plugin's split of scenes into tet meshes and surfaces (cached).
    nested : mi_tetvr.render.surfaces.NestedIntegrator
        Renders the surfaces.
    settings : WalkSettings
        The walk's settings, scaled to the scene (:func:`scaled_settings`).
    n_sub : int
        The segment integrals' sub-intervals.
    clip : mi_tetvr.render.clipping.Clip or None
    probes : Probes or None
        Surfaces drawn inside the volume (``tetvr``'s overlay).
    index_cache : callable
        ``index_cache(groups)``: the index buffers of each group of shapes.
    remote : object or None
        A medium rendered elsewhere, in place of the scene's tet meshes (a
        partitioned mesh over workers, :mod:`mi_tetvr.distributed`): its
        ``primal(ray, t_start, active) -> (C, T)`` and ``backward(ray,
        t_start, active, adj, behind)``.
    """
    parts: Any
    nested: Any
    settings: WalkSettings
    n_sub: int
    clip: Any
    probes: Any
    index_cache: Any
    remote: Any = None


class VolumeProgram:
    """``tetvr``'s ray program for one scene (see the module docstring),
    built from the integrator's :class:`ProgramOptions`."""

    def __init__(self, scene: mi.Scene, options: ProgramOptions) -> None:
        self.scene = scene
        self.tets, self.boundaries, self.surfaces = options.parts.split(scene)
        self.parts, self.nested, self.n_sub = options.parts, options.nested, options.n_sub
        self.settings = options.settings
        self.clip, self.probes = options.clip, options.probes
        self.index_cache, self.remote = options.index_cache, options.remote
        if self.remote is not None and (self.tets or self.probes is not None):
            raise ValueError("tetvr: a partitioned mesh is rendered alone (no other tet mesh "
                             "in the scene, no overlay)")
        #: Meshes that overlap in space take the merged walk.
        self.merged = overlapping(self.tets)

    # -- the media ------------------------------------------------------------

    def media(self, differentiable: bool = False) -> list[TetGroup] | None:
        """The :class:`TetGroup` of each group of tet meshes that one walk
        renders (per mesh where they overlap; else per optical model,
        :func:`~mi_tetvr.render.buffers.model_groups`), None without tet
        meshes; ``differentiable``: read with AD resumed (the derivative
        passes run with it suspended), attached to the parameters."""
        if not self.tets:
            return None
        groups = walk_groups(self.tets, "tetvr")
        with dr.resume_grad(when=differentiable):
            return [tet_group(g, idx, offsets, n_sub=self.n_sub)
                    for g, (idx, offsets) in zip(groups, self.index_cache(groups))]

    def walk(self, media: list[TetGroup], ray: mi.Ray3f, t_start: float | mi.Float,
             active: bool | mi.Bool, grad: tuple[Derivative, Adjoint] | None = None,
             t_enter: float | mi.Float | None = None
             ) -> tuple[mi.Color3f, mi.Float, mi.UInt32, Adjoint | None]:
        """``(C, T, steps, adj)`` of the media along ``ray`` from ``t_start``
        to ``ray.maxt`` (a derivative pass: ``grad = (deriv, adj)``, its
        context and the rays' adjoint; ``media`` then detached; ``t_enter``:
        see :func:`~mi_tetvr.render.walk.trace`)."""
        if self.merged:
            return merged_trace(self.parts.apart(self.tets), media, ray, self.settings, active,
                                t_start, grad, n_sub=self.n_sub)
        return trace(self.boundaries, media, ray, self.settings, active, t_start, grad, t_enter)

    def volume(self, media: list[TetGroup] | None, ray: mi.Ray3f, t_start: float | mi.Float,
               active: bool | mi.Bool,
               t_enter: float | mi.Float | None = None) -> tuple[mi.Color3f, mi.Float]:
        """``(C, T)`` of the media along ``ray`` from ``t_start``."""
        if media is None:
            if self.remote is not None:
                return self.remote.primal(ray, t_start, active)
            return mi.Color3f(0.0), dr.full(mi.Float, 1.0, dr.width(ray.o))
        C, T, _, _ = self.walk(media, ray, t_start, active, t_enter=t_enter)
        return C, T

    # -- the ray's parts ------------------------------------------------------

    def background(self, d: mi.Vector3f, active: bool | mi.Bool) -> mi.Color3f:
        """The environment's radiance along directions ``d`` (black without one)."""
        env = self.scene.environment()
        if env is None:
            return mi.Color3f(0.0)
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = -d
        return mi.Color3f(env.eval(si, active))

    def interval(self, ray: mi.Ray3f, active: bool | mi.Bool
                 ) -> tuple[mi.Ray3f, mi.Ray3f, mi.Bool, float | mi.Float, mi.Bool]:
        """``(ray, nested_ray, hit, t_start, walking)``: the volume's part of
        the rays (up to the first surface, cut by the clip; ``ray.maxt`` its
        end, ``t_start`` its start, ``walking`` where it is not empty), the
        rays the nested integrator follows, and where a surface is hit."""
        ray = mi.Ray3f(dr.detach(ray))
        ray.d = dr.normalize(ray.d)
        active = mi.Bool(active)
        nested_ray = mi.Ray3f(ray)
        hit = mi.Bool(False)
        if self.surfaces is not None:
            si = self.surfaces.ray_intersect_preliminary(ray, active=active)
            hit = active & si.is_valid()
            ray.maxt = dr.select(hit, si.t, ray.maxt)
        # (surfaces are not clipped)
        ray, t_start, walking = clipped(self.clip, ray, active)
        # The rays as a kernel of their own: the walk's kernels then hold no
        # code of the sensor or the sampler (a camera pose given as literal
        # values made every pose compile the walk again).
        layers.own_kernel(ray, t_start, walking, hit)
        return ray, nested_ray, hit, t_start, walking

    # -- the passes -----------------------------------------------------------

    def primal(self, ray: mi.Ray3f, sampler: mi.Sampler | None,
               active: mi.Bool) -> tuple[mi.Color3f, mi.Float, mi.Bool, tuple]:
        """``(L, T, hit, state)``: the pixel value, the transmittance in
        front of what lies behind the volume, where a surface is hit, and
        what the derivative passes need (``(L, T, nested state, layers,
        radiance behind)``)."""
        ray, nested_ray, hit, t_start, walking = self.interval(ray, active)
        media = self.media()
        layered = None
        if self.probes is not None:
            layered = self.probes.layered(
                self.boundaries, ray, t_start, walking,
                lambda r, s, a: self.volume(media, r, s, a), self.settings.t_min)
            C, T = layered.L, layered.W
        else:
            C, T = self.volume(media, ray, t_start, walking)
        if self.surfaces is None:
            Lb, nested_state = self.background(ray.d, active), None
        else:
            Lb, nested_state = self.nested.primal(self.surfaces, sampler, nested_ray, active)
        L = C + T * Lb
        return L, T, hit, (L, T, nested_state, layered, Lb)

    def keeps_primal(self) -> bool:
        """Whether the derivative passes need only the primal's pixel value
        and transmittance (no nested integrator's paths, no layers): then a
        kept primal replaces the primal pass (:mod:`~mi_tetvr.render.replay`)."""
        return self.surfaces is None and self.probes is None

    def derivative(self, mode: dr.ADMode, ray_ad: mi.Ray3f, sampler: mi.Sampler,
                   δL: mi.Spectrum | None, δalpha: mi.Float, state: tuple,
                   active: mi.Bool) -> tuple[mi.Color3f, mi.Float] | None:
        """A derivative pass over the rays ``ray_ad`` (attached to a
        differentiable sensor, if any) given the primal ``state``: backward
        mode propagates ``δL`` (and the alpha AOV's ``δalpha``) into the
        parameters and returns None; forward mode returns the tangents
        ``(dL, dalpha)``."""
        backward = mode == dr.ADMode.Backward
        ray, nested_ray, hit, t_start, walking = self.interval(ray_ad, active)
        with dr.resume_grad():
            camera = dr.grad_enabled(ray_ad.o) or dr.grad_enabled(ray_ad.d)
        L_pix, T_fin, nested_state, layered, behind = state
        if layered is not None and camera:
            raise ValueError("tetvr: an overlay's images have no derivatives w.r.t. the camera "
                             "(its surfaces' depths are not differentiated along the rays)")
        # Where a surface is hit, alpha is 1 whatever the volume.
        δalpha = dr.select(hit, 0.0, mi.Float(δalpha))
        seen = self.behind_derivative(mode, ray, nested_ray, sampler, δL, T_fin, nested_state,
                                      active)
        media_ad = self.media(differentiable=True)
        if layered is not None:
            dL, dalpha = self.layers_derivative(mode, media_ad, ray, walking, layered, behind,
                                                δL, δalpha)
            return None if backward else (dL + seen, dr.select(hit, 0.0, dalpha))
        zero = mi.Vector3f(0.0)
        adj = Adjoint(mi.Color3f(L_pix), mi.Float(T_fin),
                      mi.Color3f(δL) if backward else mi.Color3f(0.0),
                      δalpha if backward else mi.Float(0.0), zero, zero)
        if media_ad is not None:
            tangent = None
            if camera and not backward:
                # The rays' tangents, carried into every crossing's tangent.
                with dr.resume_grad():
                    tangent = tuple(dr.detach(x) for x in dr.forward_to(
                        ray_ad.o, dr.normalize(ray_ad.d),
                        flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad))
                layers.own_kernel(tangent)          # (the pose's code out of the walk)
            deriv = Derivative(mode, media_ad, camera, tangent)
            _, _, _, adj = self.walk([g.detached() for g in media_ad], ray, t_start, walking,
                                     (deriv, adj))
        elif self.remote is not None:
            if camera or not backward:
                raise ValueError("tetvr: a partitioned mesh has reverse-mode derivatives "
                                 "w.r.t. its own parameters only (not forward mode, not "
                                 "w.r.t. the camera)")
            self.remote.backward(ray, t_start, walking, adj, behind)
        if backward:
            if camera:
                layers.own_kernel(adj.g_o, adj.g_w)   # (the pose's code out of the walk)
                # The ray's gradient into the sensor: the origin's as is, the
                # direction's from the rotation gradient (g_d = g_w x d; the
                # direction is normalized, so its length has none).
                with dr.resume_grad():
                    dr.backward_from(dr.dot(ray_ad.o, adj.g_o) + dr.dot(
                        dr.normalize(ray_ad.d), dr.cross(adj.g_w, ray.d)))
            return None
        return adj.dL + seen, dr.select(hit, 0.0, adj.dalpha)

    def behind_derivative(self, mode: dr.ADMode, ray: mi.Ray3f, nested_ray: mi.Ray3f,
                          sampler: mi.Sampler, δL: mi.Spectrum | None, T_fin: mi.Float,
                          nested_state: Any, active: mi.Bool) -> float | mi.Color3f:
        """The derivative of ``T L_behind`` w.r.t. what lies behind (the
        environment's parameters, or the surfaces' through the nested
        integrator), taken before the walk's forward mode consumes the input
        tangents: forward mode returns its tangent (else 0)."""
        backward = mode == dr.ADMode.Backward
        if self.surfaces is not None:
            d_seen = self.nested.derivative(mode, self.surfaces, sampler, nested_ray,
                                            mi.Color3f(δL) * T_fin if backward else None,
                                            nested_state, active)
            return 0.0 if backward else T_fin * d_seen
        with dr.resume_grad():
            seen = mi.Float(T_fin) * self.background(ray.d, active)
            if not dr.grad_enabled(seen):
                return 0.0
            if backward:
                dr.backward_from(seen * mi.Color3f(δL))
                return 0.0
            return dr.forward_to(seen, flags=dr.ADFlag.ClearEdges)

    def layers_derivative(self, mode: dr.ADMode, media_ad: list[TetGroup], ray: mi.Ray3f,
                          active: mi.Bool, layered: layers.Layered, behind: mi.Color3f,
                          δL: mi.Spectrum | None,
                          δalpha: mi.Float) -> tuple[mi.Color3f, mi.Float]:
        """The derivative passes with surfaces in the volume
        (:mod:`~mi_tetvr.render.layers`): the volume's intervals by the walk's
        adjoint (each with the radiance behind it and the transmittance in
        front), the surfaces' colors and (isosurfaces) depths by their closed
        forms. Backward: accumulates the gradients; forward: returns the
        tangents ``(dL, dalpha)``."""
        backward = mode == dr.ADMode.Backward
        fronts = layered.fronts()
        R = layered.behind(behind)
        zero = mi.Vector3f(0.0)
        dL, dalpha = mi.Color3f(0.0), mi.Float(0.0)
        with dr.resume_grad():
            probes = self.probes.tet_group(self.boundaries, differentiable=True)
            (volume,) = media_ad
            shares = layers.replay(probes, layered, ray.o, ray.d,
                                   [W * layer.T for layer, W in zip(layered.layers, fronts)])
            total = mi.Color3f(0.0)
            for layer, (share, t, w) in zip(layered.layers, shares):
                total += share
                if self.probes.mode == "iso":
                    # The surface's depth ends one interval and starts the next.
                    c, sigma = layers.volume_at(volume, layer.pick, ray.d)
                    rate = layered.alpha * w * sigma * (c - layer.color)
                    total += dr.select(layer.met, dr.detach(rate) * t, 0.0)
            if backward:
                dr.backward_from(mi.Color3f(δL) * total,
                                 flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
            else:
                # (before the walks' forward mode consumes the input tangents)
                dL += dr.forward_to(total, flags=dr.ADFlag.ClearEdges | dr.ADFlag.AllowNoGrad)
        detached = [g.detached().walked() for g in media_ad]
        deriv = Derivative(mode, media_ad)
        for layer, W, R_k in zip(layered.layers, fronts, R):
            seg = mi.Ray3f(ray)
            seg.maxt = layer.end
            adj = (Adjoint(R_k, layered.W, mi.Color3f(δL) * W, δalpha, zero, zero) if backward
                   else Adjoint(R_k, layered.W, mi.Color3f(0.0), mi.Float(0.0), zero, zero))
            _, _, _, adj = self.walk(detached, seg, layer.start, active & layer.active,
                                     (deriv, adj))
            if not backward:
                dL += W * adj.dL
                dalpha += adj.dalpha
            layers.own_kernel(dL, dalpha)
        return dL, dalpha
