"""Probes: what picks one value of a post-classified mesh's scalar along
each ray instead of integrating it (ParaView's intensity projections,
slices and contours).

The walk (:mod:`~mi_tetvr.render.walk`) hands a probe each segment of a ray,
with its tet; the probe keeps what it picked so far (its accumulator, a
:class:`Pick` or, for the mean, a ``Color3f``) and says when the ray can
stop. A probe defines:

* ``Attributes``, ``Params``, :meth:`Probe.read_params`,
  :meth:`Probe.gather`: what a crossing interpolates and the buffers it
  reads, as a medium's (:mod:`~mi_tetvr.render.optical`);
* :meth:`Probe.start`: the accumulator before the first segment;
* :meth:`Probe.visit`: the accumulator after a segment, and whether the ray
  stops there;
* :meth:`Probe.finish`: the pixel's color (the transfer function's at the
  value picked), and :meth:`Probe.replay`: the same recomputed with the
  parameters' AD graph from the primal pick (the derivatives).

Probes here: :class:`Projection` (the maximum, minimum or mean along the
ray), :class:`Slice` (the scalar where the ray crosses a plane) and
:class:`Isosurface` (the first crossing of one of the isovalues).

Derivatives: the point a ray shows lies in one tet, where the scalar is
linear; its value there is a closed form of the tet's corners
(:class:`~mi_tetvr.render.linear.TetFrame`), which :meth:`Probe.replay`
recomputes with the parameters' AD graph from the primal :class:`Pick`: the
derivatives w.r.t. the scalars, the transfer function's texels, the vertex
positions and (isosurfaces) the isovalues are exact wherever the pick does
not jump to another tet or surface (silhouettes, edges of the slice, ties of
the maximum).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np
import numpy.typing as npt

from mi_tetvr.render.buffers import MeshBuffers
from mi_tetvr.render.clipping import unit_vector
from mi_tetvr.render.linear import TetFrame, vertex_gradients
from mi_tetvr.render.optical import PostClassified, ScalarPoint
from mi_tetvr.render.pytree import tree_select

#: Stands for no value yet in a maximum (its negative in a minimum).
NO_VALUE = 1e30


class Pick:
    """The one point a ray shows: the scalar's texel coordinate ``u`` there
    (``initial`` while there is none), the point ``p``, the tet ``tet`` that
    holds it and, on an isosurface, the smooth normal ``n`` (unnormalised)
    and the index ``k`` of its isovalue."""
    DRJIT_STRUCT = {"u": mi.Float, "p": mi.Point3f, "n": mi.Vector3f, "tet": mi.UInt32,
                    "k": mi.UInt32}

    def __init__(self, u: mi.Float | None = None, p: mi.Point3f | None = None,
                 n: mi.Vector3f | None = None, tet: mi.UInt32 | None = None,
                 k: mi.UInt32 | None = None) -> None:
        self.u, self.p, self.n, self.tet, self.k = u, p, n, tet, k


class VertexGradients:
    """The vertex gradients of a post-classified shape's scalar
    (:func:`~mi_tetvr.render.linear.vertex_gradients`), kept while the
    scalar, the positions and the tets are the same arrays (held, so that
    their Dr.Jit variables stay theirs); attached to the AD graph, and not
    kept, where the scalar or the positions track gradients. The kept
    buffer is a field Dr.Jit traverses (a frozen render reaches it)."""
    DRJIT_STRUCT = {"kept": mi.Float}

    def __init__(self) -> None:
        self._inputs = ()
        self.kept = mi.Float()

    def __call__(self, shape):
        scalar = shape.attribute_buffer("vertex_scalar")
        positions = shape.vertex_positions_buffer()
        buf = MeshBuffers(cells=shape.tet_buffers["cells"], positions=positions)
        if dr.grad_enabled(scalar) or dr.grad_enabled(positions):
            return vertex_gradients(buf, scalar)
        inputs = (positions, scalar, buf.cells)
        if len(self._inputs) != 3 or any(a.index != b.index
                                         for a, b in zip(self._inputs, inputs)):
            self.kept = vertex_gradients(buf, scalar)
            dr.eval(self.kept)
            self._inputs = inputs
        return self.kept


class Probe:
    """Interface and common part of the probes (see the module docstring):
    each reads a post-classified shape's scalar as texel coordinates of its
    transfer function (:attr:`field`, the shape's
    :class:`~mi_tetvr.render.optical.PostClassified` settings) and shows the
    transfer function's color at the value it picks. The walk hands every
    segment its tet."""
    per_tet = True
    #: (probes are not cut into pieces)
    cuts = False
    #: (a vertex's values are the same for every ray)
    per_ray_values = False
    #: ``L`` holds an integral (``L.x``) over a length (``L.y``).
    mean = False
    #: The accumulator's value before the first pick (every channel).
    initial = -NO_VALUE

    Attributes = ScalarPoint

    class Params:
        DRJIT_STRUCT = {"scalar": mi.Float, "tf_color": mi.Float, "tf_opacity": mi.Float,
                        "positions": mi.Float}

        def __init__(self, scalar=None, tf_color=None, tf_opacity=None, positions=None):
            self.scalar, self.tf_color, self.tf_opacity = scalar, tf_color, tf_opacity
            self.positions = positions

    def __init__(self) -> None:
        #: The scalar's classification (value range and texels of the shape).
        self.field = PostClassified()

    def for_ray(self, params: Probe.Params, d: mi.Vector3f) -> Probe.Params:
        """``params`` as they are: a probe's values do not depend on the rays'
        direction (see :meth:`~mi_tetvr.render.optical.OpticalModel.for_ray`)."""
        return params

    def read_params(self, shapes: list[mi.Mesh]) -> Probe.Params:
        s = self.field.the_shape(shapes)
        return self.Params(s.attribute_buffer("vertex_scalar"), s.tf_color, s.tf_opacity,
                           s.vertex_positions_buffer())

    def texel(self, v: mi.Float) -> mi.Float:
        """The texel coordinate of scalar value ``v``."""
        return self.field.texel(v)

    def vertex_texel(self, params: Any, i: mi.UInt32, active: bool | mi.Bool = True,
                     reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> mi.Float:
        """The texel coordinate of vertex ``i``'s scalar."""
        return self.texel(dr.gather(mi.Float, params.scalar, i, active, mode=reduce))

    def gather(self, params: Any, i: mi.UInt32, active: bool | mi.Bool = True,
               reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> ScalarPoint:
        return ScalarPoint(self.vertex_texel(params, i, active, reduce),
                           dr.gather(mi.Point3f, params.positions, i, active, mode=reduce))

    def start(self) -> Pick | mi.Color3f:
        """The accumulator before the first segment."""
        if self.mean:
            return mi.Color3f(self.initial)
        return Pick(mi.Float(self.initial), mi.Point3f(0.0), mi.Vector3f(0.0), mi.UInt32(0),
                    mi.UInt32(0))

    def visit(self, params: Any, L: Pick | mi.Color3f, length: mi.Float, a0: Any, a1: Any,
              tet: mi.UInt32) -> tuple[Pick | mi.Color3f, mi.Bool]:
        """``(L, stop)``: the accumulator after a segment of ``length`` in
        ``tet`` whose attributes go linearly from ``a0`` to ``a1``, and where
        the ray may stop."""
        raise NotImplementedError

    def value(self, L: Pick | mi.Color3f) -> tuple[mi.Float, mi.Bool]:
        """``(texel coordinate, met)`` of the accumulated ``L`` of a ray."""
        if self.mean:
            met = L.y > 0.0
            return L.x / dr.select(met, L.y, 1.0), met
        return L.u, dr.abs(L.u) < 0.5 * NO_VALUE

    def scalar(self, u: mi.Float) -> mi.Float:
        """The scalar (data units) at texel coordinate ``u``."""
        lo, hi = self.field.value_range
        return lo + (u + 0.5) * ((hi - lo) / self.field.resolution)

    def color(self, params: Any, u: mi.Float) -> mi.Color3f:
        """The transfer function's color at texel coordinate ``u``."""
        (color, _), _ = self.field.classify(params, u, u)
        return color

    def finish(self, params: Any, L: Pick | mi.Color3f) -> tuple[mi.Color3f, mi.Bool, mi.Float]:
        """``(color, met, scalar)`` of a ray's accumulated ``L``: the transfer
        function's color at the value (black where the ray met nothing)."""
        u, met = self.value(L)
        return dr.select(met, self.color(params, u), 0.0), met, self.scalar(u)

    def replay(self, params: Any, buf: MeshBuffers, L: Pick, o: mi.Point3f,
               d: mi.Vector3f) -> mi.Color3f:
        """The pixel color of a ray ``(o, d)`` (detached) whose primal walk
        picked ``L`` (detached), recomputed in ``L.tet`` from ``params`` and
        ``buf`` (attached to the AD graph)."""
        if self.mean:
            raise NotImplementedError("tetproj: the mean intensity projection is not "
                                      "differentiable (it integrates every tet of a ray); "
                                      "max, min, slice and iso are")
        u, met = self.value(L)
        frame = TetFrame(buf, L.tet, met)
        values = [self.vertex_texel(params, i, met) for i in frame.ids]
        return dr.select(met, self.color(params, self.replay_value(frame, values, L, o, d)),
                         0.0)

    def replay_value(self, frame: TetFrame, values: Sequence[mi.Float], L: Pick,
                     o: mi.Point3f, d: mi.Vector3f) -> mi.Float:
        """The texel coordinate at the picked point, from the tet's corner
        ``values`` (:meth:`replay`)."""
        raise NotImplementedError


class Projection(Probe):
    """Intensity projections of a post-classified shape's scalar along each
    ray, exact per segment (the scalar is linear in a tet): the maximum
    (``max``, MIP) and minimum (``min``) are at a segment's ends, the mean
    over the length inside the meshes (``mean``, average intensity) is the
    trapezoid's. The transmittance stays 1, so every tet on the ray is
    visited."""
    MODES = ("max", "min", "mean")

    def __init__(self, mode: str = "max") -> None:
        super().__init__()
        if mode not in self.MODES:
            raise ValueError(f"projection mode must be one of {self.MODES}, got {mode!r}")
        self.mode = mode
        self.mean = mode == "mean"
        self.initial = {"max": -NO_VALUE, "min": NO_VALUE, "mean": 0.0}[mode]

    def better(self, a: mi.Float, b: mi.Float) -> mi.Bool:
        """Whether value ``a`` beats ``b`` (greater for ``max``)."""
        return a > b if self.mode == "max" else a < b

    def visit(self, params: Any, L: Pick | mi.Color3f, length: mi.Float, a0: Any, a1: Any,
              tet: mi.UInt32) -> tuple[Pick | mi.Color3f, mi.Bool]:
        if self.mean:
            return L + mi.Color3f(length * 0.5 * (a0.u + a1.u), length, 0.0), mi.Bool(False)
        end = self.better(a1.u, a0.u)
        u = dr.select(length > 0.0, dr.select(end, a1.u, a0.u), self.initial)
        pick = Pick(u, dr.select(end, a1.p, a0.p), mi.Vector3f(0.0), tet, mi.UInt32(0))
        return tree_select(self.better(pick.u, L.u), pick, L), mi.Bool(False)

    def replay_value(self, frame: TetFrame, values: Sequence[mi.Float], L: Pick,
                     o: mi.Point3f, d: mi.Vector3f) -> mi.Float:
        # The extreme lies on the face of the tet where the ray crosses it
        # (the one of the smallest barycentric coordinate at the primal
        # point), or on a clip plane or the camera's origin (kept where it is).
        lam = frame.weights(L.p)
        grads = frame.weight_gradients()
        k = mi.UInt32(0)
        smallest = dr.abs(lam[0])
        for j in (1, 2, 3):
            less = dr.abs(lam[j]) < smallest
            k = dr.select(less, j, k)
            smallest = dr.select(less, dr.abs(lam[j]), smallest)
        at_o = frame.weights(o)
        lam_o = dr.select(k == 0, at_o[0], dr.select(k == 1, at_o[1],
                          dr.select(k == 2, at_o[2], at_o[3])))
        g = dr.select(k == 0, grads[0], dr.select(k == 1, grads[1],
                      dr.select(k == 2, grads[2], grads[3])))
        slope = dr.dot(g, d)
        on_face = (smallest < 1e-3) & (dr.abs(slope) > 0.0)
        x = dr.select(on_face, o + d * (-lam_o / dr.select(on_face, slope, 1.0)), L.p)
        return frame.at(values, x)


class Slice(Probe):
    """A plane through the mesh showing its scalar: each ray stops where it
    first crosses the plane inside the mesh, and the scalar there is exact.
    The signed distance ``s`` of a crossing's point to the plane is linear
    along the ray in a tet, so a segment meets the plane at the fraction
    ``s0 / (s0 - s1)`` where the scalar is ``lerp(u0, u1, f)``; the walk
    stops there."""

    def __init__(self, origin: npt.ArrayLike, normal: npt.ArrayLike) -> None:
        super().__init__()
        self.origin = np.asarray(origin, np.float64).reshape(3)
        self.normal = unit_vector(normal, "a slice's normal")

    def plane(self) -> tuple[mi.Point3f, mi.Vector3f]:
        return mi.Point3f(*self.origin.tolist()), mi.Vector3f(*self.normal.tolist())

    def visit(self, params: Any, L: Pick | mi.Color3f, length: mi.Float, a0: Any, a1: Any,
              tet: mi.UInt32) -> tuple[Pick | mi.Color3f, mi.Bool]:
        origin, normal = self.plane()
        s0, s1 = dr.dot(a0.p - origin, normal), dr.dot(a1.p - origin, normal)
        meets = ((length > 0.0) & (s0 != s1) & (dr.minimum(s0, s1) <= 0.0)
                 & (dr.maximum(s0, s1) >= 0.0))
        f = dr.clip(s0 / dr.select(s0 != s1, s0 - s1, 1.0), 0.0, 1.0)
        pick = Pick(dr.lerp(a0.u, a1.u, f), dr.lerp(a0.p, a1.p, f), mi.Vector3f(0.0), tet,
                    mi.UInt32(0))
        return tree_select(meets, pick, L), meets

    def depth(self, o: mi.Point3f, d: mi.Vector3f) -> mi.Float:
        """Where the rays ``(o, d)`` meet the plane."""
        origin, normal = self.plane()
        slope = dr.dot(d, normal)
        return dr.dot(origin - o, normal) / dr.select(slope != 0.0, slope, 1.0)

    def replay_value(self, frame: TetFrame, values: Sequence[mi.Float], L: Pick,
                     o: mi.Point3f, d: mi.Vector3f) -> mi.Float:
        return frame.at(values, o + d * self.depth(o, d))

    def replay_surface(self, params: Any, buf: MeshBuffers, L: Pick, o: mi.Point3f,
                       d: mi.Vector3f) -> tuple[mi.Color3f, mi.Float]:
        """``(color, t)``: :meth:`replay` and the plane's depth (fixed)."""
        return self.replay(params, buf, L, o, d), self.depth(o, d)


class Isosurface(Probe):
    """The first isosurface a ray meets, of one or more ``values`` of a
    post-classified shape's scalar, exact: the scalar is linear along the ray
    in a tet, so a segment crosses value ``v`` at ``f = (v - u0) / (u1 -
    u0)``. A crossing carries the scalar's texel coordinate, the position and
    the vertex gradient (the tets' gradients around the vertex averaged by
    volume, :func:`~mi_tetvr.render.linear.vertex_gradients`), all linear
    inside a tet: the hit point and its smooth normal are exact lerps. The
    pixel is the transfer function's color at the isovalue lit by a headlight
    (Lambert, two-sided). The walk stops at the hit.

    ``values`` : Float (the isovalues, data units; differentiable in
    :meth:`replay`)."""

    class Attributes:
        DRJIT_STRUCT = {"u": mi.Float, "p": mi.Point3f, "g": mi.Vector3f}

        def __init__(self, u=None, p=None, g=None):
            self.u, self.p, self.g = u, p, g

    class Params:
        DRJIT_STRUCT = {"scalar": mi.Float, "tf_color": mi.Float, "tf_opacity": mi.Float,
                        "positions": mi.Float, "gradients": mi.Float, "values": mi.Float}

        def __init__(self, scalar=None, tf_color=None, tf_opacity=None, positions=None,
                     gradients=None, values=None):
            self.scalar, self.tf_color, self.tf_opacity = scalar, tf_color, tf_opacity
            self.positions, self.gradients, self.values = positions, gradients, values

    def __init__(self, values: Sequence[float] | mi.Float,
                 gradients: VertexGradients = None) -> None:
        super().__init__()
        self.values = mi.Float(values)
        self.count = dr.width(self.values)
        if not self.count:
            raise ValueError("an isosurface needs at least one value")
        #: Where the shape's vertex gradients are kept between renders.
        self.gradients = gradients if gradients is not None else VertexGradients()

    def read_params(self, shapes: list[mi.Mesh]) -> Isosurface.Params:
        s = self.field.the_shape(shapes)
        scalar, positions = s.attribute_buffer("vertex_scalar"), s.vertex_positions_buffer()
        return self.Params(scalar, s.tf_color, s.tf_opacity, positions, self.gradients(s),
                           self.values)

    def gather(self, params: Any, i: mi.UInt32, active: bool | mi.Bool = True,
               reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> Isosurface.Attributes:
        a = Probe.gather(self, params, i, active, reduce)
        return self.Attributes(a.u, a.p, dr.gather(mi.Vector3f, params.gradients, i, active))

    def visit(self, params: Any, L: Pick | mi.Color3f, length: mi.Float, a0: Any, a1: Any,
              tet: mi.UInt32) -> tuple[Pick | mi.Color3f, mi.Bool]:
        best = mi.Float(2.0)
        value = mi.Float(0.0)
        k = mi.UInt32(0)
        du = a1.u - a0.u
        for j in range(self.count):
            w = self.texel(dr.gather(mi.Float, params.values, mi.UInt32(j)))
            f = (w - a0.u) / dr.select(du != 0.0, du, 1.0)
            ok = (du != 0.0) & (f >= 0.0) & (f <= 1.0) & (f < best)
            best = dr.select(ok, f, best)
            value = dr.select(ok, w, value)
            k = dr.select(ok, j, k)
        meets = (length > 0.0) & (best <= 1.0)
        hit = Pick(value, dr.lerp(a0.p, a1.p, best), dr.lerp(a0.g, a1.g, best), tet, k)
        return tree_select(meets, hit, L), meets

    @staticmethod
    def lambert(n: mi.Vector3f, d: mi.Vector3f) -> mi.Float:
        """The headlight's factor ``|n . d| / |n|`` (1 where ``n`` is 0)."""
        norm = dr.norm(n)
        return dr.select(norm > 0.0, dr.abs(dr.dot(n, d)) / dr.select(norm > 0.0, norm, 1.0),
                         1.0)

    def shade(self, params: Any, L: Pick,
              d: mi.Vector3f) -> tuple[mi.Color3f, mi.Bool, mi.Point3f]:
        """``(color, met, point)``: the transfer function's color at the hit's
        value lit by the headlight."""
        color, met, _ = self.finish(params, L)
        return color * self.lambert(L.n, d), met, L.p

    def replay(self, params: Any, buf: MeshBuffers, L: Pick, o: mi.Point3f,
               d: mi.Vector3f) -> mi.Color3f:
        return self.replay_surface(params, buf, L, o, d)[0]

    def replay_surface(self, params: Any, buf: MeshBuffers, L: Pick, o: mi.Point3f,
                       d: mi.Vector3f) -> tuple[mi.Color3f, mi.Float]:
        """``(color, t)``: :meth:`replay` and the hit's depth along the ray,
        both closed forms in the hit's tet (differentiable)."""
        _, met = self.value(L)
        frame = TetFrame(buf, L.tet, met)
        values = [self.vertex_texel(params, i, met) for i in frame.ids]
        w = self.texel(dr.gather(mi.Float, params.values, L.k, met))
        g = frame.gradient(values)
        slope = dr.dot(g, d)
        t = (w - frame.at(values, o)) / dr.select(slope != 0.0, slope, 1.0)
        x = o + d * t
        n = sum((lam * dr.gather(mi.Vector3f, params.gradients, i, met)
                 for lam, i in zip(frame.weights(x), frame.ids)), mi.Vector3f(0.0))
        return dr.select(met, self.color(params, w) * self.lambert(n, d), 0.0), t
