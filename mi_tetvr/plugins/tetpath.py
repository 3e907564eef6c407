"""The ``tetpath`` integrator: volumetric path tracing of scattering ``tetmesh``
shapes (participating media) among the scene's surfaces and emitters.

.. pluginparameters::

 * - max_depth
   - |int|
   - Longest path depth, as Mitsuba's ``volpath``: 1 shows what emits
     (emitters, and the volume's emission), 2 single scattering (direct
     light at the first collision or surface), -1 no limit. (Default: 6)
 * - rr_depth
   - |int|
   - Depth from which Russian roulette ends paths. (Default: 5)
 * - max_steps
   - |int|
   - Safety bound on tets crossed per walk. (Default: 100000)
 * - retrace_epsilon
   - |float|
   - Offset, relative to the scene's bounding-box diagonal, past a boundary
     face before tracing for re-entry. (Default: 1e-5)

The AOV ``alpha`` is the coverage: 1 for a sample whose camera ray met the
medium (a collision) or a surface, so that its pixel mean is ``1 - T``
through the volume alone, as ``tetvr``'s ``alpha``.

The scene's ``tetmesh`` shapes with an ``albedo`` (see ``tetmesh``) are the
medium: per-vertex extinction (``vertex_opacity``), albedo and emission per
unit extinction, linear in each tet, and a phase function (Mitsuba's phase
plugins). Free-flight distances are sampled exactly, tet by tet (no
majorant, no null collisions), shadow rays are attenuated by the exact
transmittance, and paths scatter in the medium and bounce on the other shapes
with their BSDFs; next-event estimation reaches every Mitsuba emitter
(point, spot, directional, area, ``envmap``, ...) with multiple importance
sampling, as Mitsuba's ``volpath`` and ``prbvolpath``
(:mod:`mi_tetvr.render.transport`).

Derivatives (``dr.backward`` after ``mi.render``, or forward mode) replay
each path (constant memory per path) w.r.t. the meshes' ``vertex_opacity``,
``vertex_albedo``, ``vertex_emission``, ``vertex_positions`` (the
integrand's derivative: no silhouette terms) and the phase function's
parameters. The surfaces' BSDFs and the emitters are sampled but not
differentiated. Meshes may overlap in space (at most 8): their extinctions
add, and a collision is in each with the probability of its share of the
extinction there (derivatives then w.r.t. the media, not the positions).
Surfaces are opaque to shadow rays (a ``null`` or transmissive BSDF still
blocks them).

.. code-block:: python

    'integrator': {'type': 'tetpath', 'max_depth': 8},
    'fog': {'type': 'tetmesh', 'filename': 'fog.vtu', 'albedo': 0.8,
            'phase': {'type': 'hg', 'g': 0.4}},
"""
from __future__ import annotations

from typing import Any

import drjit as dr
import mitsuba as mi

from mi_tetvr.plugins import constructor
from mi_tetvr.render.buffers import index_buffers, tet_group
from mi_tetvr.render.merged import walk_groups
from mi_tetvr.render.optical import Scattering
from mi_tetvr.render.program import scaled_settings
from mi_tetvr.render.surfaces import SceneParts
from mi_tetvr.render.transport import PathInputs, check_derivatives, sample
from mi_tetvr.render.cursor import WalkSettings


class TetPathIntegrator(mi.ad.integrators.common.RBIntegrator):
    __doc__ = __doc__

    def __init__(self, props: mi.Properties) -> None:
        super().__init__(props)
        max_steps = int(props.get("max_steps", 100_000))
        if max_steps < 1:
            raise ValueError("tetpath: max_steps must be >= 1")
        self.retrace_epsilon = float(props.get("retrace_epsilon", 1e-5))
        # (the walk's own scatter strategy: plain atomics on the LLVM backend,
        # as per-thread copies of the gradient buffers are not made inside
        # the path's loop)
        self.settings = WalkSettings(0.0, max_steps)
        self.parts = SceneParts()
        self._empty = None
        self._index = None

    def path_inputs(self, scene: mi.Scene) -> PathInputs:
        """What :func:`~mi_tetvr.render.transport.sample` reads of ``scene``;
        ValueError for a scene it cannot render."""
        tets, boundaries, surfaces = self.parts.split(scene)
        if not tets:
            raise ValueError("tetpath: the scene has no tetmesh")
        plain = [s.id() or "tetmesh" for s in tets if s.optical_model is not Scattering]
        if plain:
            raise ValueError(f"tetpath: tetmesh {', '.join(plain)} has no albedo; tetpath "
                             f"renders scattering media (give each tetmesh an 'albedo', or "
                             f"render emission and absorption with tetvr)")
        phases = {id(s.phase): s.phase for s in tets}
        if len(phases) > 1:
            raise ValueError("tetpath: the scene's scattering tet meshes must share one phase "
                             "function (load it once and hand the same object to each)")
        # Meshes that overlap in space: a cursor each (render.cursor.traverse_merged).
        groups = walk_groups(tets, "tetpath")
        key = tuple(tuple(id(s.tet_buffers) for s in g) for g in groups)
        if self._index is None or self._index[0] != key:
            self._index = (key, [index_buffers(g) for g in groups])
        with dr.resume_grad():
            media = [tet_group(g, index, offsets)
                     for g, (index, offsets) in zip(groups, self._index[1])]
        if surfaces is None:
            if self._empty is None:
                self._empty = mi.load_dict({"type": "scene"})
            surfaces = self._empty
        settings = scaled_settings(self.settings, self.retrace_epsilon, scene)
        meshes = [(ts_ad.detached(), ts_ad) for ts_ad in media]
        apart = self.parts.apart(tets) if len(groups) > 1 else None
        return PathInputs(scene, *meshes[0], boundaries, surfaces, next(iter(phases.values())),
                         settings, self.max_depth, self.rr_depth,
                         meshes if apart is not None else None, apart)

    def aov_names(self) -> list[str]:
        return ["alpha"]

    def sample_rays(self, scene: mi.Scene, sensor: mi.Sensor,
                    sampler: mi.Sampler) -> tuple[mi.RayDifferential3f, mi.Float, mi.Vector2f]:
        # Mitsuba's forward mode multiplies the AOVs by the sensor weight, a
        # Spectrum, which makes the alpha AOV a color the image block refuses;
        # an RGB sensor weights its channels alike: keep one.
        ray, weight, pos = super().sample_rays(scene, sensor, sampler)
        return ray, mi.Float(weight[0]), pos

    def sample(self, mode: dr.ADMode, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f,
               δL: mi.Spectrum | None, state_in: mi.Spectrum | None, active: mi.Bool,
               **kwargs: Any) -> tuple[mi.Spectrum, mi.Bool, list[mi.Float], mi.Spectrum]:
        if mode != dr.ADMode.Primal and state_in is None:
            raise ValueError("tetpath: the derivative modes need the primal pass's state_in")
        ps = self.path_inputs(scene)
        if mode != dr.ADMode.Primal:
            check_derivatives(ps)
        L, valid, alpha, state = sample(mode, ps, sampler, ray, δL, state_in, active)
        # (alpha has no derivative)
        return L, valid, [alpha if mode == dr.ADMode.Primal else mi.Float(0.0)], state

    def to_string(self) -> str:
        return (f"TetPathIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"max_steps={self.settings.max_steps}]")


mi.register_integrator("tetpath", constructor(TetPathIntegrator, "tetpath"))
