"""``tetvr``'s walk: emission-absorption and probes along rays, and their
derivative modes, as clients of the ray cursor
(:mod:`~mi_tetvr.render.cursor`).

The walk knows nothing of what a vertex carries: an optical model
(:mod:`mi_tetvr.render.optical`) interpolates the vertex values at each
crossing and integrates each segment. A model whose values map to color and
extinction nonlinearly (a scalar and a transfer function) sets ``cuts``: the
cursor then ends a piece where the model's :meth:`cut` says and stays in the
tet for the next piece. The derivative modes re-walk the rays
(:mod:`mi_tetvr.render.adjoint`), recording nothing.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi

from mi_tetvr.render import adjoint
from mi_tetvr.render.buffers import TetGroup
from mi_tetvr.render.cursor import Cursor, Entry, Piece, Span, WalkSettings, traverse
from mi_tetvr.render.geometry import RayFrame, walk_step
from mi_tetvr.render.probes import Pick, Probe
from mi_tetvr.render.segment import clip_segment


@dataclass
class Radiance:
    """What lies in front along a ray: emission ``L`` (a probe's
    accumulator, for a probe) and transmittance ``T``; in a derivative
    pass, the rays' ``adj`` and the ``pending`` crossing gradients
    (:func:`~mi_tetvr.render.adjoint.start`)."""
    L: Any
    T: mi.Float
    adj: adjoint.Adjoint = None
    pending: Any = None


class Emission:
    """The cursor's client that integrates an optical model (or picks with a
    probe) along rays through the meshes of ``ts``."""
    label = "tetvr_walk"

    def __init__(self, ts: TetGroup, settings: WalkSettings) -> None:
        self.ts, self.model, self.params = ts, ts.model, ts.params
        self.cuts = ts.model.cuts
        self.probe = isinstance(ts.model, Probe)
        self.t_min = settings.t_min

    def gather(self, i: mi.UInt32, active: bool | mi.Bool) -> Any:
        return self.ts.values(i, active)

    def cut(self, a0: Any, a1: Any) -> mi.Float:
        return self.model.cut(a0, a1)

    def begin(self, acc: Radiance, cur: Cursor, fr: RayFrame, active: mi.Bool) -> Radiance:
        return acc

    def piece(self, acc: Radiance, p: Piece, span: Span, fr: RayFrame,
              active: mi.Bool) -> tuple[Radiance, mi.Bool]:
        length, a0, a1 = clip_segment(p.cur.t, p.cur.a, p.t1, p.a1, span.begin, span.end)
        if self.probe:
            # (a probe picks: the ray goes on, T = 1, until it stops, T = 0)
            L, stop = self.model.visit(self.params, acc.L, length, a0, a1, p.cur.tet)
            T = dr.select(stop, 0.0, acc.T)
        else:
            C_seg, T_seg, _ = self.model.segment(self.params, length, a0, a1,
                                                 *((p.cur.tet,) if self.model.per_tet else ()))
            L, T = acc.L + acc.T * C_seg, acc.T * T_seg
        return Radiance(L, T), T > self.t_min

    def end(self, acc: Radiance, cur: Cursor, stay: mi.Bool, walked: mi.Bool,
            fr: RayFrame) -> Radiance:
        return acc

    def alive(self, acc: Radiance) -> mi.Bool:
        return acc.T > self.t_min


class EmissionDerivative(Emission):
    """:class:`Emission` in a derivative pass (``deriv``): the same walk over
    the detached buffers ``ts``, each segment differentiated through
    ``ts_ad`` (attached) by :func:`~mi_tetvr.render.adjoint.segment`."""

    def __init__(self, ts: TetGroup, ts_ad: TetGroup, deriv: adjoint.Derivative,
                 settings: WalkSettings) -> None:
        super().__init__(ts, settings)
        self.ts_ad, self.deriv = ts_ad, deriv
        #: The vertices' gradients (backward mode), passed on after the walk.
        self.sums = adjoint.VertexSums(ts_ad, settings) if deriv.backward else None

    def begin(self, acc: Radiance, cur: Cursor, fr: RayFrame, active: mi.Bool) -> Radiance:
        pending = adjoint.start(self.deriv, self.ts_ad, cur.carry, fr, active)
        return Radiance(acc.L, acc.T, acc.adj, pending)

    def piece(self, acc: Radiance, p: Piece, span: Span, fr: RayFrame,
              active: mi.Bool) -> tuple[Radiance, mi.Bool]:
        C_seg, T_seg, adj, pending = adjoint.segment(self.deriv, self, p, acc, span, fr, active)
        T = acc.T * T_seg
        return Radiance(acc.L + acc.T * C_seg, T, adj, pending), T > self.t_min

    def end(self, acc: Radiance, cur: Cursor, stay: mi.Bool, walked: mi.Bool,
            fr: RayFrame) -> Radiance:
        if not self.deriv.backward:
            return Radiance(acc.L, acc.T, acc.adj)
        exit_face = None
        if self.cuts:
            # Stopped inside a tet (early termination): its exit face.
            exit_face = (walk_step(self.ts.buf, cur.tet, cur.f_in, fr, stay, cur.carry,
                                   self.gather).carry, stay)
        adj = adjoint.finish(self.deriv, self, acc, cur.carry, walked, fr, exit_face)
        return Radiance(acc.L, acc.T, adj)


def trace(scene: mi.Scene, ts: TetGroup | list[TetGroup], ray: mi.Ray3f,
          settings: WalkSettings, active: bool | mi.Bool, t_start: float | mi.Float = 0.0,
          grad: tuple = None, t_enter: float | mi.Float | None = None
          ) -> tuple[mi.Color3f | Pick, mi.Float, mi.UInt32, adjoint.Adjoint | None]:
    """Emission and transmittance along rays through the tet meshes.

    Parameters
    ----------
    scene : mi.Scene
        Its shapes must be exactly the tet meshes of ``ts`` (their boundaries).
    ts : mi_tetvr.render.buffers.TetGroup, or a list of them
        One per group of shapes that one walk renders (an optical model:
        :func:`~mi_tetvr.render.buffers.model_groups`). Each boundary hit is
        walked in its own group's mesh.
    ray : mi.Ray3f
        Normalized direction; ``ray.maxt`` bounds the integral.
    t_start : float or mi.Float
        Where the integral starts along the ray (a clip, :mod:`mi_tetvr.render.clipping`).
    grad : (adjoint.Derivative, adjoint.Adjoint), optional
        A derivative pass's context (its ``scenes`` pair with ``ts``, which is
        then detached) and the rays' adjoint.
    t_enter : float or mi.Float, optional
        Where the search for the mesh's boundary starts, before ``t_start``
        (default: at it). A block of a partitioned mesh integrates from
        inside its piece: entered through the piece's near side, its walk
        does not have to walk back from the far side to the start point.

    Returns
    -------
    (Color3f, Float, UInt32, Adjoint)
        Accumulated emission ``C``, transmittance ``T`` (pixel = C + T bg),
        the number of tets crossed, and the adjoint (forward mode: with the
        tangents accumulated; None in the primal pass).
    """
    fr = RayFrame.of(ray.o, ray.d)
    d = dr.detach(fr.d)
    groups = [g.for_ray(d).walked() for g in (ts if isinstance(ts, (list, tuple)) else [ts])]
    if grad is None:
        clients, adj = [Emission(g, settings) for g in groups], None
    else:
        deriv, adj = grad
        clients = [EmissionDerivative(g, g_ad.for_ray(d), deriv, settings)
                   for g, g_ad in zip(groups, deriv.groups)]
    model = groups[0].model
    L = model.start() if isinstance(model, Probe) else mi.Color3f(0.0)
    acc = Radiance(L, dr.full(mi.Float, 1.0, dr.width(ray.o)), adj)
    acc, steps = traverse(scene, clients, fr, acc, Span(mi.Float(t_start), mi.Float(ray.maxt)),
                          settings, active, Entry(t=t_enter) if t_enter is not None else None)
    for c in clients:
        if getattr(c, "sums", None) is not None:
            c.sums.flush()
    return acc.L, acc.T, steps, acc.adj
