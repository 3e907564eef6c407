"""The ``tetproj`` integrator: intensity projections of a ``tetmesh``'s scalar
(the maximum, minimum or mean along each ray), as ParaView's *Maximum /
Minimum / Average Intensity* blend modes show a volume, slices (the scalar on
a plane through the mesh) and isosurfaces.

The scene holds one post-classified ``tetmesh`` (a scalar and a transfer
function) and nothing else. Each ray walks every tet it crosses
(:mod:`mi_tetvr.render.walk`, with the :class:`~mi_tetvr.render.probes.Projection`
model): the scalar is linear in each tet, so the maximum and the minimum of
a segment are at its ends and its mean is the trapezoid's; the projection is
exact. A slice (:class:`~mi_tetvr.render.probes.Slice`) stops each ray
where it first crosses the plane inside the mesh, the scalar there exact too
(the plane's signed distance is linear along the ray in a tet); an
isosurface (:class:`~mi_tetvr.render.probes.Isosurface`) where the scalar
first crosses one of the isovalues. The pixel is the transfer function's color at the projected
value (its opacity is not used), alpha 1 where the ray meets the mesh; the film's
``rgba`` format keeps it. Translucent surfaces (``opacity`` below 1) are
composited front to back over black (the film's alpha still marks where a
surface is met). Nested in ``tetvr`` as its ``overlay``, a slice or
isosurfaces are drawn inside the volume (ParaView's volume with a contour
or a slice).

.. pluginparameters::

 * - mode
   - |string|
   - ``max`` (maximum intensity projection), ``min``, ``mean`` (average over
     the length inside the mesh), ``slice`` or ``iso``. (Default: ``max``)
 * - iso
   - |string|
   - ``iso``: the isovalue(s) of the scalar, comma-separated (data units); the
     first one a ray meets is shown, shaded by a headlight (Lambert on the
     normal interpolated from the vertices' gradients). Required in mode
     ``iso``. (Default: none)
 * - origin, normal
   - |point|, |vector|
   - ``slice``: a point of the plane and its normal. (Default: the centre of
     the scene's bounding box, +z)
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
   - A plane and a box that cut the mesh, as ``tetvr``'s. (Default: none)
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
(:meth:`~mi_tetvr.render.probes.Probe.replay`), so they are exact where
that point moves smoothly (not across silhouettes or the slice's rim).

.. code-block:: python

    'integrator': {'type': 'tetproj', 'mode': 'max'}
"""
from __future__ import annotations

from typing import Any

import drjit as dr
import mitsuba as mi

from mi_tetvr.plugins import constructor
from mi_tetvr.render.buffers import TetGroup
from mi_tetvr.render.clipping import Clip, unit_vector
from mi_tetvr.render.layers import Layered
from mi_tetvr.render.probes import Pick, Projection
from mi_tetvr.render.program import SURFACE_MODES, Probes
from mi_tetvr.render.cursor import WalkSettings


class TetProjIntegrator(mi.ad.integrators.common.RBIntegrator):
    __doc__ = __doc__

    def __init__(self, props: mi.Properties) -> None:
        super().__init__(props)
        mode = str(props.get("mode", "max")).lower()
        modes = Projection.MODES + SURFACE_MODES
        if mode not in modes:
            raise ValueError(f"tetproj: mode must be one of {modes}, got {mode!r}")
        iso = [float(v) for v in str(props.get("iso", "")).split(",") if v.strip()]
        if mode == "iso" and not iso:
            raise ValueError("tetproj: mode 'iso' needs 'iso', the isovalue(s)")
        self.iso = mi.Float(iso)
        origin = list(props["origin"]) if "origin" in props else None
        normal = unit_vector(list(props.get("normal", [0.0, 0.0, 1.0])),
                             "tetproj: the slice's normal").tolist()
        opacity = float(props.get("opacity", 1.0))
        if not 0.0 < opacity <= 1.0:
            raise ValueError(f"tetproj: opacity must be in (0, 1], got {opacity}")
        count = int(props.get("layers", 1 if opacity == 1.0 else 8))
        if count < 1:
            raise ValueError(f"tetproj: layers must be >= 1, got {count}")
        if mode not in SURFACE_MODES and ("opacity" in props or "layers" in props):
            raise ValueError("tetproj: opacity and layers apply to surfaces (mode slice or "
                             f"iso), not to mode {mode!r}")
        #: What this integrator shows (:class:`~mi_tetvr.render.program.Probes`).
        self.probes = Probes(mode, self.iso, (origin, normal), opacity, count,
                             Clip.from_props(props),
                             WalkSettings(0.0, int(props.get("max_steps", 100_000))),
                             float(props.get("retrace_epsilon", 1e-5)))

    @property
    def mode(self) -> str:
        return self.probes.mode

    def traverse(self, callback: mi.TraversalCallback) -> None:
        if self.mode == "iso":
            callback.put("iso", self.iso, mi.ParamFlags.Differentiable)

    def tet_group(self, scene: mi.Scene, differentiable: bool = False) -> TetGroup:
        """The :class:`~mi_tetvr.render.buffers.TetGroup` the probes walk
        (:meth:`~mi_tetvr.render.program.Probes.tet_group`)."""
        return self.probes.tet_group(scene, differentiable)

    def project(self, scene: mi.Scene, ray: mi.Ray3f, active: bool | mi.Bool = True
                ) -> tuple[mi.Color3f, mi.Bool, mi.Float | mi.Point3f]:
        """``(color, met, scalar)`` of the projection along rays (normalised
        directions); for ``iso``, ``(color, met, hit point)`` of the first
        surface."""
        return self.probes.project(scene, ray, active)[:3]

    def sample(self, mode: dr.ADMode, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f,
               δL: mi.Spectrum | None,
               state_in: Layered | tuple[Pick | mi.Color3f, mi.Bool] | None, active: mi.Bool,
               **kwargs: Any
               ) -> tuple[mi.Spectrum, mi.Bool, list[mi.Float],
                          Layered | tuple[Pick | mi.Color3f, mi.Bool] | None]:
        ray = mi.Ray3f(dr.detach(ray))
        ray.d = dr.normalize(ray.d)
        if mode == dr.ADMode.Primal:
            with dr.suspend_grad():
                if self.probes.surfaces:
                    rec = self.probes.layered(scene, ray, 0.0, active)
                    return mi.Spectrum(rec.L), rec.met, [], rec
                color, met, _, picks = self.probes.project(scene, ray, active)
            return mi.Spectrum(color), met, [], (picks, met)
        # The derivative passes: each ray's pick again, with the AD graph.
        state, met = (state_in, state_in.met) if self.probes.surfaces else state_in
        with dr.resume_grad():
            color = self.probes.replay(scene, state, ray.o, ray.d)
            if mode == dr.ADMode.Backward:
                dr.backward_from(δL * color)
                return mi.Spectrum(0.0), met, [], None
            return mi.Spectrum(dr.forward_to(color)), met, [], None

    def to_string(self) -> str:
        return "TetProjIntegrator[" + repr(self.probes)[len("Probes["):]


mi.register_integrator("tetproj", constructor(TetProjIntegrator, "tetproj"))
