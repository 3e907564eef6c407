"""Tet volumes in an ordinary Mitsuba scene: the scene's parts that ``tetvr``
renders apart, and the nested integrator that renders the surfaces.

A camera ray is integrated through the tet meshes up to the first hit of any
other shape (a *surface*); that surface's radiance, computed by a nested
Mitsuba integrator, is seen through the volume in front of it::

    L = C_volume[0, t_hit] + T(t_hit) L_surface

(without a hit, ``L_surface`` is what the nested integrator returns for a ray
that leaves the scene: the environment). The nested integrator renders a scene
of the surfaces and the emitters alone: its bounces and shadow rays do not see
the tet meshes (light transport through the volume is not modelled), and the
walk traces a scene of the tet meshes alone (:class:`SceneParts`).
"""
from __future__ import annotations

from os import PathLike
from typing import Any

import drjit as dr
import mitsuba as mi


def is_tetmesh(shape: mi.Shape) -> bool:
    """Whether ``shape`` is a ``tetmesh`` (it carries the walk's index arrays)."""
    return hasattr(shape, "tet_buffers")


def split_shapes(scene: mi.Scene) -> tuple[list[mi.Mesh], list[mi.Shape]]:
    """``(tetmeshes, surfaces)``: the scene's ``tetmesh`` shapes and its other
    shapes."""
    tets, surfaces = [], []
    for s in scene.shapes():
        (tets if is_tetmesh(s) else surfaces).append(s)
    return tets, surfaces


def _geometry_key(shape):
    """What identifies a shape's current geometry: its vertex buffer (a mesh:
    a parameter update makes a new array) and its bounding box (any shape)."""
    b = shape.bbox()
    key = (id(shape), tuple(b.min), tuple(b.max))
    if isinstance(shape, mi.Mesh):
        key += (dr.detach(shape.vertex_positions_buffer()).index,)
    return key


def _scene_of(objects):
    """A scene of these shapes and emitters. ``mi.load_dict`` names each
    object after its key: the keys are the objects' own ids, and any id it
    changed anyway is given back (``mi.traverse`` of the user's scene keeps
    its names)."""
    ids = [o.id() for o in objects]
    keys, used = [], {"type"}
    for i, name in enumerate(ids):
        key = name if name and name not in used else f"_tetvr_part_{i}"
        used.add(key)
        keys.append(key)
    scene = mi.load_dict({"type": "scene", **dict(zip(keys, objects))})
    for o, name in zip(objects, ids):
        if o.id() != name:
            o.set_id(name)
    return scene


class SceneParts:
    """The two scenes ``tetvr`` traces in a scene with surfaces, kept until
    the shapes or their geometry change.

    ``walk(scene)`` is the scene whose boundary faces the walk traces: the
    scene itself when it holds only tet meshes, else a scene of its tet
    meshes. ``surfaces(scene)`` is a scene of the other shapes and of the
    emitters that are not area lights of them (area lights come with their
    shapes), or None without other shapes. Both hold the scene's own shape
    and emitter objects, so BSDF and emitter parameters are shared; their
    acceleration structures are rebuilt when a shape's geometry changes
    (a new vertex buffer or bounding box).
    """

    def __init__(self) -> None:
        self._walk = None
        self._surfaces = None
        self._apart = {}

    def apart(self, tets: list[mi.Mesh]) -> list[mi.Scene]:
        """A scene of each tet mesh alone (the merged walk traces each mesh's
        boundary apart: coincident faces of two meshes are then both found)."""
        out, kept = [], {}
        for s in tets:
            key = _geometry_key(s)
            scene = self._apart.get(key) or _scene_of([s])
            kept[key] = scene
            out.append(scene)
        self._apart = kept
        return out

    def split(self, scene: mi.Scene) -> tuple[list[mi.Mesh], mi.Scene, mi.Scene | None]:
        """``(tet meshes, boundaries, surfaces)``: the scene's tet meshes, a
        scene of their boundaries (the scene itself without surfaces) and a
        scene of the other shapes (None without any)."""
        tets, surfaces = split_shapes(scene)
        if not surfaces:
            return tets, scene, None
        key = tuple(_geometry_key(s) for s in tets)
        if self._walk is None or self._walk[0] != key:
            self._walk = (key, _scene_of(tets))
        emitters = [e for e in scene.emitters()
                    if not mi.has_flag(e.flags(), mi.EmitterFlags.Surface)]
        key = (tuple(_geometry_key(s) for s in surfaces), tuple(id(e) for e in emitters))
        if self._surfaces is None or self._surfaces[0] != key:
            self._surfaces = (key, _scene_of(surfaces + emitters))
        return tets, self._walk[1], self._surfaces[1]


def lights_scene(path: str | PathLike) -> dict[str, mi.Shape | mi.Emitter]:
    """``{name: object}`` of a Mitsuba scene file's emitters and shapes (the
    known lighting of a scattering fit, the lights of a lit render), for a
    scene dict."""
    lights = mi.load_file(str(path))
    tets, surfaces = split_shapes(lights)
    if tets:
        raise ValueError(f"{path}: the lights' scene holds a tetmesh; it is the volume's "
                         f"surroundings (emitters, surfaces)")
    emitters = [e for e in lights.emitters()
                if not mi.has_flag(e.flags(), mi.EmitterFlags.Surface)]
    if not emitters and not any(s.is_emitter() for s in surfaces):
        raise ValueError(f"{path}: the lights' scene has no emitter")
    return {f"_light_{i}": o for i, o in enumerate(surfaces + emitters)}


#: The nested integrator of a ``tetvr`` without a ``surfaces`` child.
DEFAULT_SURFACES = {"type": "prb"}


class NestedIntegrator:
    """The integrator that renders the surfaces (``tetvr``'s ``surfaces``
    child): a Mitsuba ``SamplingIntegrator``. Python integrators derived from
    Mitsuba's ``ADIntegrator`` (``prb``, ``prb_basic``, ``direct_projective``,
    ``prb_projective``, ...) run in all three modes; others (``path``,
    ``direct``, ...) in the primal mode only."""

    def __init__(self, integrator: mi.Object) -> None:
        if not isinstance(integrator, mi.SamplingIntegrator):
            raise ValueError(f"tetvr: the 'surfaces' child must be a sampling integrator "
                             f"(e.g. prb, path, direct), got {type(integrator).__name__}")
        self.integrator = integrator
        self.differentiable = isinstance(integrator, mi.ad.integrators.common.ADIntegrator)

    def __repr__(self):
        return repr(self.integrator)

    def primal(self, scene: mi.Scene, sampler: mi.Sampler | None, ray: mi.Ray3f,
               active: mi.Bool) -> tuple[mi.Color3f, Any]:
        """``(L, state)``: the surfaces' radiance along ``ray`` and what the
        derivative modes need of it."""
        if sampler is None:
            raise ValueError("tetvr: a scene with surfaces needs a sampler (the nested "
                             "integrator samples paths)")
        if self.differentiable:
            L, _, _, state = self.integrator.sample(dr.ADMode.Primal, scene, sampler, ray,
                                                    None, None, active)
            return mi.Color3f(L), state
        L, _, _ = self.integrator.sample(scene, sampler, ray, None, active)
        return mi.Color3f(L), None

    def derivative(self, mode: dr.ADMode, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f,
                   δL: mi.Spectrum | None, state: Any, active: mi.Bool) -> mi.Color3f | None:
        """Backward mode: propagate ``δL`` (the adjoint of the surfaces'
        radiance) into the surfaces' parameters; forward mode: return the
        radiance's tangent (0 where no parameter of the surfaces scene, its
        shapes, BSDFs and emitters, has gradients enabled)."""
        with dr.resume_grad():      # (the derivative passes run with AD suspended)
            tracked = any(dr.grad_enabled(v) for _, v in mi.traverse(scene).items()
                          if dr.is_array_v(v))
        if not tracked:
            return mi.Color3f(0.0) if mode == dr.ADMode.Forward else None
        if not self.differentiable:
            raise ValueError(f"tetvr: the nested 'surfaces' integrator "
                             f"{type(self.integrator).__name__} has no derivative modes; "
                             f"use a differentiable one (prb, prb_basic, direct_projective, "
                             f"prb_projective) to differentiate a scene with surfaces")
        out = self.integrator.sample(mode, scene, sampler, ray, δL, state, active)
        return mi.Color3f(out[0]) if mode == dr.ADMode.Forward else None
