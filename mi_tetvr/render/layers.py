"""Surfaces inside a volume, front to back: isosurfaces and slices drawn in
(or without) the emission-absorption volume, opaque or translucent, as
ParaView shows a volume with a contour or a slice.

Along a ray the surfaces (the layers) are found one after the other, each
from just past the previous one (:meth:`~mi_tetvr.render.program.Probes.layered`);
the volume is integrated over the interval in front of each, and after the
last. With the layers' opacity ``alpha``, colors ``S_k``, the volume's
emission ``C_k`` and transmittance ``T_k`` over the interval in front of
layer ``k`` and ``W_k`` the transmittance in front of that interval::

    L = sum_k W_k (C_k + T_k alpha S_k) + W_tail C_tail + W_final L_behind,
    W_{k+1} = W_k T_k (1 - alpha)

Derivatives. The volume's intervals are differentiated by the walk's
adjoint with the interval's own end points held (``R_k``, the radiance that
reaches the interval's start from behind, is what the adjoint needs as its
pixel value), the layers' colors by their closed forms
(:meth:`~mi_tetvr.render.probes.Probe.replay`). A layer that moves
(an isosurface: its depth ``t_k`` depends on the scalars, the positions and
the isovalue) ends one interval and starts the next; the volume being
continuous there, the two ends' terms add up to::

    dL/dt_k = alpha W_k T_k sigma_k (c_k - S_k)

with ``c_k``, ``sigma_k`` the volume's color and extinction at the layer
point (the derivative of the emission lost in front, the transmittance
gained and the surface's share of what lies behind).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi

from mi_tetvr.render.buffers import TetGroup
from mi_tetvr.render.probes import Pick


class Layer:
    """The interval ``[start, end]`` of the volume in front of a surface
    (emission ``C``, transmittance ``T``; ``active`` where the ray got that
    far) and the surface at ``end``: where it
    is met (``met``), its color and the walk's pick
    (:class:`~mi_tetvr.render.probes.Pick`). The tail after the last
    surface is a layer that meets none."""

    def __init__(self, start: mi.Float, end: mi.Float, active: mi.Bool, C: mi.Color3f,
                 T: mi.Float, met: mi.Bool, color: mi.Color3f | None = None,
                 pick: Pick | None = None) -> None:
        self.start, self.end, self.active, self.C, self.T = start, end, active, C, T
        self.met, self.color, self.pick = met, color, pick


class Layered:
    """What :func:`composite` found along each ray: its ``layers`` (the
    tail last), the composite ``L`` without what lies behind and the final
    transmittance ``W``; ``alpha`` the layers' opacity."""

    def __init__(self, layers: list[Layer], L: mi.Color3f, W: mi.Float, alpha: float) -> None:
        self.layers, self.L, self.W, self.alpha = layers, L, W, alpha

    @property
    def met(self) -> mi.Bool:
        """Whether any surface was met."""
        met = mi.Bool(False)
        for layer in self.layers:
            met |= layer.met
        return met

    def fronts(self) -> list[mi.Float]:
        """The transmittance in front of each layer's interval."""
        W, out = mi.Float(1.0), []
        for layer in self.layers:
            out.append(W)
            W = W * layer.T * dr.select(layer.met, 1.0 - self.alpha, 1.0)
        return out

    def behind(self, background: mi.Color3f) -> list[mi.Color3f]:
        """``R_k``: the radiance reaching each interval's start from behind it,
        ``background`` behind the tail."""
        R, out = mi.Color3f(background), []
        for layer in reversed(self.layers):
            if layer.color is not None:
                R = dr.select(layer.met, self.alpha * layer.color + (1.0 - self.alpha) * R, R)
            R = layer.C + layer.T * R
            out.append(R)
        return out[::-1]


def own_kernel(*values: Any) -> None:
    """Evaluates ``values`` (and the scatters queued with them) unless traced in
    a symbolic loop or call: each layer's walks then run as kernels of their
    own, whose code is the same from one layer to the next (compiled once, not
    once per layer inside one kernel LLVM takes many minutes to compile)."""
    if not dr.flag(dr.JitFlag.SymbolicScope):
        dr.eval(*values)


@dataclass
class Drawing:
    """How surfaces are drawn: with opacity ``alpha``, at most ``count`` of
    them along a ray, the next searched ``eps`` past one, a ray going on
    past a surface while its transmittance exceeds ``t_min``."""
    alpha: float
    count: int
    eps: float
    t_min: float = 1e-4


def composite(find: Callable[[mi.Ray3f, mi.Float, mi.Bool],
                             tuple[mi.Bool, mi.Color3f, Pick, mi.Float]],
              volume: Callable[[mi.Ray3f, mi.Float, mi.Bool],
                               tuple[mi.Color3f, mi.Float]] | None,
              ray: mi.Ray3f, t_start: float | mi.Float, active: bool | mi.Bool,
              drawing: Drawing) -> Layered:
    """Front to back through at most ``drawing.count`` surfaces along
    ``ray`` (unit directions) from ``t_start`` to ``ray.maxt``.

    ``find(ray, start, active)`` gives ``(met, color, pick, t)`` of the first
    surface after ``start``; ``volume(ray, start, active)`` the ``(C, T)`` of
    the volume over ``[start, ray.maxt]`` (None: no volume).
    """
    alpha, count, eps, t_min = drawing.alpha, drawing.count, drawing.eps, drawing.t_min
    start = mi.Float(t_start)
    t_end = mi.Float(ray.maxt)
    go = mi.Bool(active)
    n = dr.width(go)
    L = dr.zeros(mi.Color3f, n)
    W = dr.full(mi.Float, 1.0, n)
    layers = []

    def interval(end, go):
        seg = mi.Ray3f(ray)
        seg.maxt = end
        if volume is None:
            return dr.zeros(mi.Color3f, n), dr.full(mi.Float, 1.0, n)
        C, T = volume(seg, start, go)
        return dr.select(go, C, 0.0), dr.select(go, T, 1.0)

    for _ in range(count):
        met, color, pick, t = find(ray, start, go)
        met &= go
        end = dr.select(met, t, t_end)
        C, T = interval(end, go)
        L += W * C
        W *= T
        L += dr.select(met, W * alpha * color, 0.0)
        layers.append(Layer(mi.Float(start), end, mi.Bool(go), C, T, met, color, pick))
        W = dr.select(met, W * (1.0 - alpha), W)
        start = dr.select(met, end + eps, start)
        go = met & (W > t_min)
        own_kernel(L, W, start, go, end, C, T, met, color, pick)
    go &= start < t_end
    C, T = interval(t_end, go)
    L += W * C
    W *= T
    layers.append(Layer(mi.Float(start), t_end, go, C, T, mi.Bool(False)))
    return Layered(layers, L, W, float(alpha))


def replay(ts: TetGroup, layered: Layered, o: mi.Point3f, d: mi.Vector3f,
           weights: list[mi.Float] | None = None) -> list[tuple[mi.Color3f, mi.Float, mi.Float]]:
    """The layers' share of the pixel, ``sum_k alpha w_k S_k``, with each
    surface's color recomputed with the AD graph from its pick (``ts``: the
    probes' :class:`~mi_tetvr.render.buffers.TetGroup`, attached), and each
    layer's depth ``t_k`` alike: ``[(share, t_k, w_k)]``. ``weights`` are the
    transmittances in front of each surface (default: those of the layers
    alone)."""
    out = []
    W = mi.Float(1.0)
    for j, layer in enumerate(layered.layers[:-1]):
        w = W if weights is None else weights[j]
        color, t = ts.model.replay_surface(ts.params, ts.buf, layer.pick, o, d)
        out.append((dr.select(layer.met, layered.alpha * w * color, 0.0), t, w))
        W = dr.select(layer.met, W * (1.0 - layered.alpha), W)
    return out


def volume_at(ts: TetGroup, pick: Pick, d: mi.Vector3f) -> tuple[mi.Color3f, mi.Float]:
    """``(color, extinction)`` of the volume ``ts`` (a post-classified
    model) at the pick of an isosurface of its scalar, detached
    (:meth:`~mi_tetvr.render.optical.PostClassified.medium_at`)."""
    with dr.suspend_grad():
        c, sigma = ts.model.medium_at(ts.params, pick.u, pick.tet, d)
    return dr.detach(c), dr.detach(sigma)
