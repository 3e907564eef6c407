"""Optical models: what a vertex carries and how one segment is integrated.

The walk (:mod:`mi_tetvr.render.walk`) crosses faces; at each crossing it
asks the model for the per-vertex values interpolated there, and for each
segment (entry and exit values, length) it asks the model for the emission
and the transmittance. It never looks inside either. The adjoint
(:mod:`mi_tetvr.render.adjoint`) obtains the local derivatives of a segment by
Dr.Jit's AD of :meth:`OpticalModel.segment` and of :meth:`OpticalModel.gather`,
so a model only writes its forward formulas.

A model defines:

* ``Attributes``: a ``DRJIT_STRUCT`` class of the values interpolated at a
  crossing (barycentric in the crossed face, hence linear along the ray
  inside a tet); the walk adds, lerps and selects them field by field.
* ``Params``: a ``DRJIT_STRUCT`` class of the parameter buffers (Mitsuba
  scene parameters, differentiable), read from the shapes by
  :meth:`OpticalModel.read_params`.
* :meth:`OpticalModel.gather`: the attributes of a vertex from ``Params``.
* :meth:`OpticalModel.segment`: ``(C, T, tau)`` of a segment: the emission
  seen from its front, its transmittance and its optical depth
  (``T = exp(-tau)`` mathematically; ``tau`` is what the adjoint
  differentiates, ``T`` what the primal multiplies).

A model whose attributes map to color and extinction nonlinearly sets
``cuts`` and defines :meth:`cut` (the fraction of a segment at which the
walk ends a piece, so that each piece is integrated by :meth:`segment` with
linear color and extinction).

Models here: :class:`EmissionAbsorption` (what ``tetmesh`` shapes use),
:class:`Absorption` (extinction only), :class:`PostClassified` (a scalar and
a transfer function), :class:`PreIntegrated` (the same by a table),
:class:`CellClassified` (a scalar per tet and a transfer function),
:class:`Shaded` (post-classified and lit by a headlight), and the
models that show one point per ray, each accumulated by its own
:meth:`~OpticalModel.accumulate`: :class:`Projection` (the maximum, minimum
or mean of the scalar along the ray), :class:`Slice` (the scalar where the
ray crosses a plane) and :class:`Isosurface`. To add a model, subclass :class:`OpticalModel`, and let the
``tetmesh`` shape name it (``shape.optical_model``) and carry its
``vertex_attributes``; the walk and the adjoint stay as they are.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_tetvr.render.buffers import MeshBuffers, concat
from mi_tetvr.render.clipping import unit_vector
from mi_tetvr.render.linear import TetFrame, vertex_gradients
from mi_tetvr.render.pytree import tree_select, weighted_sum
from mi_tetvr.render.segment import segment_integral


class OpticalModel:
    """Interface of an optical model (see the module docstring).

    Parameters
    ----------
    n_sub : int
        Sub-intervals per segment, for models whose segment integral has no
        closed form (a Python int: the loop is unrolled).
    """
    Attributes = None
    Params = None
    #: ``(shape attribute name, channels)`` of the per-vertex buffers the
    #: ``tetmesh`` shape carries for this model (Mitsuba mesh attributes,
    #: exposed by ``mi.traverse`` as ``<id>.<name>``).
    vertex_attributes = ()
    #: Whether the walk cuts a tet's segment into pieces where :meth:`cut`
    #: says (models whose attributes map to color and extinction nonlinearly).
    cuts = False
    #: Whether the model takes settings from its shape (then each shape is
    #: walked apart; else the shapes of one model share a walk).
    per_shape = False
    #: The accumulated value before the first segment (every channel).
    initial = 0.0
    #: Whether :meth:`segment` takes the index of the segment's tet (in the
    #: walk's buffers) as a fifth argument.
    per_tet = False

    def __init__(self, n_sub: int = 4):
        self.n_sub = int(n_sub)

    @staticmethod
    def vertex_values(mesh):
        """``{name: (n, channels) array}`` of :attr:`vertex_attributes` from a
        :class:`~mi_tetvr.mesh.TetMesh` (the shape's initial values)."""
        raise NotImplementedError

    def read_params(self, shapes):
        """The model's parameter buffers, concatenated over ``shapes`` in the
        order of their vertices (attached to the shapes' AD graph)."""
        raise NotImplementedError

    def gather(self, params, i, active=True, reduce=dr.ReduceMode.Auto):
        """``Attributes`` of vertex ``i``; ``reduce`` is the scatter strategy
        of the gather's reverse-mode derivative."""
        raise NotImplementedError

    def interpolate(self, params, ids, w, active=True, reduce=dr.ReduceMode.Auto):
        """``Attributes`` at barycentric weights ``w`` of the vertices ``ids``."""
        return weighted_sum(w, [self.gather(params, i, active, reduce) for i in ids])

    def start(self):
        """The accumulator ``L`` before the first segment (a ``Color3f`` of
        :attr:`initial`; a model with its own accumulator returns that)."""
        return mi.Color3f(self.initial)

    def accumulate(self, L, T, C, T_seg):
        """``(L, T)`` after a segment ``(C, T_seg)`` behind what was
        accumulated: front-to-back compositing."""
        return L + T * C, T * T_seg

    def segment(self, params, length, a0, a1):
        """``(C : Color3f, T : Float, tau : Float)`` of a segment of
        ``length`` whose attributes go linearly from ``a0`` to ``a1``."""
        raise NotImplementedError

    def linear(self, params, a0, a1):
        """``(c0, c1, s0, s1)``: color and extinction at the ends of a piece
        whose attributes go linearly from ``a0`` to ``a1`` (between the
        model's knots: color and extinction are linear on it). Where meshes
        overlap, the pieces of all of them are integrated as one medium from
        these (:func:`~mi_tetvr.render.segment.merged_integral`)."""
        raise NotImplementedError(f"{type(self).__name__} cannot overlap other meshes")


class EmissionAbsorption(OpticalModel):
    """Per-vertex color ``c`` (linear RGB, emission per unit extinction) and
    extinction ``s`` (per unit length), both linear inside a tet; the segment
    integral of :func:`mi_tetvr.render.segment.segment_integral`."""

    class Attributes:
        DRJIT_STRUCT = {"c": mi.Color3f, "s": mi.Float}

        def __init__(self, c=None, s=None):
            self.c, self.s = c, s

    class Params:
        DRJIT_STRUCT = {"color": mi.Float, "opacity": mi.Float}

        def __init__(self, color=None, opacity=None):
            self.color, self.opacity = color, opacity

    vertex_attributes = (("vertex_color", 3), ("vertex_opacity", 1))

    @staticmethod
    def vertex_values(mesh):
        return {"vertex_color": mesh.color, "vertex_opacity": mesh.opacity}

    def read_params(self, shapes):
        return self.Params(concat([s.attribute_buffer("vertex_color") for s in shapes]),
                           concat([s.attribute_buffer("vertex_opacity") for s in shapes]))

    def gather(self, params, i, active=True, reduce=dr.ReduceMode.Auto):
        return self.Attributes(dr.gather(mi.Color3f, params.color, i, active, mode=reduce),
                               dr.gather(mi.Float, params.opacity, i, active, mode=reduce))

    def segment(self, params, length, a0, a1):
        C, T = segment_integral(length, a0.c, a1.c, a0.s, a1.s, self.n_sub)
        # The midpoint sums of the sub-intervals: exact for a linear extinction.
        tau = length * (a0.s + a1.s) * 0.5
        return C, T, tau

    def linear(self, params, a0, a1):
        return a0.c, a1.c, a0.s, a1.s


class Absorption(OpticalModel):
    """Extinction only (X-ray attenuation): per-vertex extinction ``s``, linear
    inside a tet, no emission. A segment's transmittance is exact:
    ``exp(-length (s0 + s1) / 2)``; the image is the transmittance (its
    ``alpha`` is ``1 - T``)."""

    class Attributes:
        DRJIT_STRUCT = {"s": mi.Float}

        def __init__(self, s=None):
            self.s = s

    class Params:
        DRJIT_STRUCT = {"opacity": mi.Float}

        def __init__(self, opacity=None):
            self.opacity = opacity

    vertex_attributes = (("vertex_opacity", 1),)

    @staticmethod
    def vertex_values(mesh):
        return {"vertex_opacity": mesh.opacity}

    def read_params(self, shapes):
        return self.Params(concat([s.attribute_buffer("vertex_opacity") for s in shapes]))

    def gather(self, params, i, active=True, reduce=dr.ReduceMode.Auto):
        return self.Attributes(dr.gather(mi.Float, params.opacity, i, active, mode=reduce))

    def segment(self, params, length, a0, a1):
        tau = length * (a0.s + a1.s) * 0.5
        return dr.zeros(mi.Color3f, dr.width(length)), dr.exp(-tau), tau

    def linear(self, params, a0, a1):
        zero = dr.zeros(mi.Color3f, dr.width(a0.s))
        return zero, zero, a0.s, a1.s


#: Scatter strategy of the texel reads' reverse-mode derivative (many rays
#: write into few texels). On the 2-core CPU all strategies were within
#: 10 % of each other (``benchmarks/bench_tf_gradients.py``), so Dr.Jit
#: chooses.
TEXEL_REDUCE = dr.ReduceMode.Auto

#: A knot of the transfer function closer than this (in texels) to a
#: segment's start counts as crossed (the walk then never cuts twice at one).
KNOT_EPSILON = 1e-4


class PostClassified(OpticalModel):
    """A per-vertex scalar, linear inside a tet, classified *after*
    interpolation by a transfer function held as ``R`` texels (linear RGB
    color ``tf_color`` (R, 3) and extinction ``tf_opacity`` (R,) at the texel
    centres of ``value_range``, linear between centres, constant outside).

    A crossing carries the scalar as a texel coordinate ``u = (v - lo) R /
    (hi - lo) - 0.5`` (the knots are the integers ``0 .. R-1``). The walk
    cuts a tet's segment where ``u`` crosses a knot (:meth:`cut`); on each
    piece color and extinction are linear along the ray, and the piece is
    integrated like :class:`EmissionAbsorption`'s segments, so the integral
    is exact but for the mean transmittance's sub-intervals.
    """

    class Attributes:
        DRJIT_STRUCT = {"u": mi.Float}

        def __init__(self, u=None):
            self.u = u

    class Params:
        DRJIT_STRUCT = {"scalar": mi.Float, "tf_color": mi.Float, "tf_opacity": mi.Float}

        def __init__(self, scalar=None, tf_color=None, tf_opacity=None):
            self.scalar, self.tf_color, self.tf_opacity = scalar, tf_color, tf_opacity

    vertex_attributes = (("vertex_scalar", 1),)
    #: The walk asks :meth:`cut` where to end each piece.
    cuts = True
    #: Each shape has its own value range and texels.
    per_shape = True

    def __init__(self, n_sub: int = 4, resolution: int = 256, value_range=(0.0, 1.0)):
        super().__init__(n_sub)
        self.resolution = int(resolution)
        self.value_range = tuple(float(x) for x in value_range)

    @staticmethod
    def vertex_values(mesh):
        raise NotImplementedError("post-classified meshes take their scalar from the shape")

    def the_shape(self, shapes):
        """The one shape of a walk of a post-classified model (its value
        range and texel count set on the model)."""
        if len(shapes) != 1:
            raise ValueError("tetvr: a post-classified walk renders one tetmesh, got "
                             f"{len(shapes)} (see model_groups)")
        s = shapes[0]
        self.value_range, self.resolution = s.value_range, s.tf_resolution
        return s

    def read_params(self, shapes):
        s = self.the_shape(shapes)
        return self.Params(s.attribute_buffer("vertex_scalar"), s.tf_color, s.tf_opacity)

    def texel(self, v):
        """The texel coordinate of scalar value ``v``."""
        lo, hi = self.value_range
        return (v - lo) * (self.resolution / (hi - lo)) - 0.5

    def gather(self, params, i, active=True, reduce=dr.ReduceMode.Auto):
        # Gathered from the parameter itself (so that its reverse-mode
        # derivative is a scatter-add into it), then mapped to texels.
        return self.Attributes(self.texel(dr.gather(mi.Float, params.scalar, i, active,
                                                    mode=reduce)))

    def classify(self, params, u0, u1):
        """Color and extinction at the texel coordinates ``u0`` and ``u1`` of
        a piece's ends. The piece lies between two knots, so both ends are
        read from the one linear part of the transfer function that holds
        the piece's middle (or its constant part below the first texel
        centre / above the last): a value a hair beyond a knot (round-off
        at a cut) keeps the piece's own slope, and so does its derivative."""
        last = float(self.resolution - 1)
        mid = 0.5 * (u0 + u1)
        below, above = mid < 0.0, mid > last
        k = mi.UInt32(dr.clip(dr.floor(mid), 0.0, last - 1.0))
        mode = TEXEL_REDUCE
        c0 = dr.gather(mi.Color3f, params.tf_color, k, mode=mode)
        c1 = dr.gather(mi.Color3f, params.tf_color, k + 1, mode=mode)
        s0 = dr.gather(mi.Float, params.tf_opacity, k, mode=mode)
        s1 = dr.gather(mi.Float, params.tf_opacity, k + 1, mode=mode)
        out = []
        for u in (u0, u1):
            w = dr.select(below, 0.0, dr.select(above, 1.0, u - mi.Float(k)))
            out.append((dr.lerp(c0, c1, w), dr.lerp(s0, s1, w)))
        return out

    def cut(self, a0, a1):
        """Fraction ``f`` in (0, 1] of the way from ``a0`` to ``a1`` where
        the scalar reaches the next knot (1: none before ``a1``)."""
        u0, u1 = a0.u, a1.u
        last = float(self.resolution - 1)
        up = u1 > u0
        k = dr.select(up, dr.maximum(dr.floor(u0 + KNOT_EPSILON) + 1.0, 0.0),
                      dr.minimum(dr.ceil(u0 - KNOT_EPSILON) - 1.0, last))
        inside = dr.select(up, (k < u1) & (k <= last), (k > u1) & (k >= 0.0)) & (u1 != u0)
        du = dr.select(u1 != u0, u1 - u0, 1.0)
        return dr.select(inside, dr.clip((k - u0) / du, 0.0, 1.0), 1.0)

    def segment(self, params, length, a0, a1):
        (c0, s0), (c1, s1) = self.classify(params, a0.u, a1.u)
        C, T = segment_integral(length, c0, c1, s0, s1, self.n_sub)
        return C, T, length * (s0 + s1) * 0.5

    def linear(self, params, a0, a1):
        (c0, s0), (c1, s1) = self.classify(params, a0.u, a1.u)
        return c0, c1, s0, s1


class CellClassified(PostClassified):
    """A per-tet scalar (cell data) classified by a transfer function, as it
    is: constant in each tet, so each tet's segment has one color ``c`` and
    extinction ``s``, integrated exactly (``C = c (1 - exp(-s l))``); nothing
    is averaged onto the vertices. The walk hands each segment its tet
    (:attr:`per_tet`); the shape's ``cell_scalar`` (in the mesh's tet order)
    is read in the walk's order (``shape.cell_order``, where the shape
    stores its tets reordered). Its derivatives w.r.t. the cell values, the
    texels and the positions (the segments' lengths) are the adjoint's, as
    for every model."""

    class Params:
        DRJIT_STRUCT = {"cells": mi.Float, "order": mi.UInt32, "tf_color": mi.Float,
                        "tf_opacity": mi.Float}

        def __init__(self, cells=None, order=None, tf_color=None, tf_opacity=None):
            self.cells, self.order = cells, order
            self.tf_color, self.tf_opacity = tf_color, tf_opacity

    vertex_attributes = ()
    cuts = False
    per_tet = True
    #: Whether the shape stores its tets reordered (``order`` maps them).
    reordered = False

    def read_params(self, shapes):
        # (the cells are read through the order inside the walk: the
        # parameter itself is gathered, so forward mode needs no tangent
        # of a derived buffer)
        s = self.the_shape(shapes)
        self.reordered = s.cell_order is not None
        order = s.cell_order if self.reordered else mi.UInt32(0)
        return self.Params(s.cell_scalar, order, s.tf_color, s.tf_opacity)

    def gather(self, params, i, active=True, reduce=dr.ReduceMode.Auto):
        # Nothing varies inside a tet (the walk still carries an attribute).
        return self.Attributes(mi.Float(0.0))

    def segment(self, params, length, a0, a1, tet):
        cell = dr.gather(mi.UInt32, params.order, tet) if self.reordered else tet
        # (inside the adjoint's loop: plain atomics; Auto's per-thread
        # copies raced there)
        u = self.texel(dr.gather(mi.Float, params.cells, cell, mode=dr.ReduceMode.Direct))
        (c, s), _ = self.classify(params, u, u)
        tau = s * length
        T = dr.exp(-tau)
        return c * (1.0 - T), T, tau

    def linear(self, params, a0, a1):
        raise ValueError("tetvr: a tetmesh of cell data cannot overlap another tetmesh "
                         "(its segments need their tet)")


#: The last vertex gradients computed without derivatives:
#: ``(inputs, buffer)``, the inputs the arrays they were computed from (held,
#: so that their Dr.Jit variables stay theirs).
_GRADIENTS = [(), None]


def shape_vertex_gradients(shape):
    """The vertex gradients of a post-classified shape's scalar
    (:func:`~mi_tetvr.render.linear.vertex_gradients`): attached to the AD
    graph where the scalar or the positions track gradients, else the
    last ones computed while the scalar, the positions and the tets are the
    same arrays."""
    scalar, positions = shape.attribute_buffer("vertex_scalar"), shape.vertex_positions_buffer()
    buf = MeshBuffers(tets=shape.tet_buffers["tets"], positions=positions)
    if dr.grad_enabled(scalar) or dr.grad_enabled(positions):
        return vertex_gradients(buf, scalar)
    inputs = (positions, scalar, buf.tets)
    kept, gradients = _GRADIENTS
    if len(kept) != 3 or any(a.index != b.index for a, b in zip(kept, inputs)):
        gradients = vertex_gradients(buf, scalar)
        dr.eval(gradients)
        _GRADIENTS[:] = [inputs, gradients]
    return gradients


class ScalarPoint:
    """A crossing's attributes for the models that need its point: the
    scalar's texel coordinate ``u`` and the point ``p``."""
    DRJIT_STRUCT = {"u": mi.Float, "p": mi.Point3f}

    def __init__(self, u=None, p=None):
        self.u, self.p = u, p

    @staticmethod
    def gather(model, params, i, active=True, reduce=dr.ReduceMode.Auto):
        """The attributes of vertex ``i`` (``params.scalar``, ``params.positions``)."""
        u = PostClassified.gather(model, params, i, active, reduce).u
        return ScalarPoint(u, dr.gather(mi.Point3f, params.positions, i, active, mode=reduce))


class Shaded(PostClassified):
    """Post-classification lit by a headlight, as ParaView's *Shade* lights a
    volume: the emitted color is ``c (ambient + diffuse |n.d|) + specular
    |n.d|^power`` (Phong with the light at the eye: the half vector is the
    view direction), ``n`` the scalar's gradient, ``d`` the ray's direction;
    where the gradient vanishes the color is unlit. The scalar is linear in
    a tet, so its gradient is the tet's own constant (the walk hands each
    segment its tet, :attr:`per_tet`; :class:`~mi_tetvr.render.linear.TetFrame`):
    the lit color stays linear in the scalar between the transfer
    function's knots and each piece is integrated exactly, its derivatives
    (w.r.t. the scalars and positions through the normal too) those of the
    adjoint. A crossing carries the scalar and its point (a piece's direction
    is that of its end points). The coefficients are the shape's
    (``ambient``, ``diffuse``, ``specular``, ``specular_power``; VTK's
    volume property's defaults)."""

    Attributes = ScalarPoint

    class Params:
        DRJIT_STRUCT = {"scalar": mi.Float, "tf_color": mi.Float, "tf_opacity": mi.Float,
                        "positions": mi.Float, "tets": mi.UInt32}

        def __init__(self, scalar=None, tf_color=None, tf_opacity=None, positions=None,
                     tets=None):
            self.scalar, self.tf_color, self.tf_opacity = scalar, tf_color, tf_opacity
            self.positions, self.tets = positions, tets

        def position(self, i, active=True):
            return dr.gather(mi.Point3f, self.positions, i, active, mode=dr.ReduceMode.Direct)

    per_tet = True
    #: ``(ambient, diffuse, specular, specular_power)``, set from the shape.
    lighting = (0.1, 0.7, 0.2, 10.0)

    def read_params(self, shapes):
        s = self.the_shape(shapes)
        self.lighting = s.lighting
        return self.Params(s.attribute_buffer("vertex_scalar"), s.tf_color, s.tf_opacity,
                           s.vertex_positions_buffer(), s.tet_buffers["tets"])

    def gather(self, params, i, active=True, reduce=dr.ReduceMode.Auto):
        return ScalarPoint.gather(self, params, i, active, reduce)

    def lit(self, c, g, d):
        """The color ``c`` lit at gradient ``g`` seen along ``d`` (unit)."""
        ambient, diffuse, specular, power = self.lighting
        norm = dr.norm(g)
        cos = dr.abs(dr.dot(g, d)) / dr.select(norm > 0.0, norm, 1.0)
        out = c * (ambient + diffuse * cos) + specular * dr.power(cos, power)
        return dr.select(norm > 0.0, out, c)

    def segment(self, params, length, a0, a1, tet):
        frame = TetFrame(params, tet)
        g = frame.gradient([dr.gather(mi.Float, params.scalar, i, mode=dr.ReduceMode.Direct)
                            for i in frame.ids])
        step = a1.p - a0.p
        d = step / dr.select(dr.norm(step) > 0.0, dr.norm(step), 1.0)
        (c0, s0), (c1, s1) = self.classify(params, a0.u, a1.u)
        C, T = segment_integral(length, self.lit(c0, g, d), self.lit(c1, g, d), s0, s1,
                                self.n_sub)
        return C, T, length * (s0 + s1) * 0.5

    def linear(self, params, a0, a1):
        raise ValueError("tetvr: a shaded tetmesh cannot overlap another tetmesh (its "
                         "segments need their tet)")


#: Stands for no value yet in a maximum (its negative in a minimum).
NO_VALUE = 1e30


class Pick:
    """The one point a ray shows (:class:`RayValue`): the scalar's texel
    coordinate ``u`` there (``initial`` while there is none), the point
    ``p``, the tet ``tet`` that holds it and, on an isosurface, the smooth
    normal ``n`` (unnormalised) and the index ``k`` of its isovalue."""
    DRJIT_STRUCT = {"u": mi.Float, "p": mi.Point3f, "n": mi.Vector3f, "tet": mi.UInt32,
                    "k": mi.UInt32}

    def __init__(self, u=None, p=None, n=None, tet=None, k=None):
        self.u, self.p, self.n, self.tet, self.k = u, p, n, tet, k


class RayValue(PostClassified):
    """Base of the models that give each ray one value of a post-classified
    shape's scalar instead of an integral (:class:`Projection`,
    :class:`Slice`, :class:`Isosurface`). The accumulator is a :class:`Pick`
    (the ``mean`` projection: a ``Color3f``, ``L.x`` the scalar's integral
    over the length ``L.y``); :meth:`finish` makes it a pixel.

    Derivatives: the point a ray shows lies in one tet (the walk hands each
    segment its tet, :attr:`per_tet`), where the scalar is linear; its
    value there is a closed form of the tet's corners
    (:class:`~mi_tetvr.render.linear.TetFrame`), which :meth:`replay`
    recomputes with the parameters' AD graph from the primal :class:`Pick`:
    the derivatives w.r.t. the scalars, the transfer function's texels, the
    vertex positions and (isosurfaces) the isovalues are exact wherever the
    pick does not jump to another tet or surface (silhouettes, edges of the
    slice, ties of the maximum)."""
    cuts = False
    per_tet = True
    #: ``L`` holds an integral (``L.x``) over a length (``L.y``).
    mean = False

    Attributes = ScalarPoint

    class Params:
        DRJIT_STRUCT = {"scalar": mi.Float, "tf_color": mi.Float, "tf_opacity": mi.Float,
                        "positions": mi.Float}

        def __init__(self, scalar=None, tf_color=None, tf_opacity=None, positions=None):
            self.scalar, self.tf_color, self.tf_opacity = scalar, tf_color, tf_opacity
            self.positions = positions

    def read_params(self, shapes):
        s = self.the_shape(shapes)
        return self.Params(s.attribute_buffer("vertex_scalar"), s.tf_color, s.tf_opacity,
                           s.vertex_positions_buffer())

    def gather(self, params, i, active=True, reduce=dr.ReduceMode.Auto):
        return ScalarPoint.gather(self, params, i, active, reduce)

    def start(self):
        if self.mean:
            return mi.Color3f(self.initial)
        return Pick(mi.Float(self.initial), mi.Point3f(0.0), mi.Vector3f(0.0), mi.UInt32(0),
                    mi.UInt32(0))

    def value(self, L):
        """``(texel coordinate, met)`` of the accumulated ``L`` of a ray."""
        if self.mean:
            met = L.y > 0.0
            return L.x / dr.select(met, L.y, 1.0), met
        return L.u, dr.abs(L.u) < 0.5 * NO_VALUE

    def scalar(self, u):
        """The scalar (data units) at texel coordinate ``u``."""
        lo, hi = self.value_range
        return lo + (u + 0.5) * ((hi - lo) / self.resolution)

    def color(self, params, u):
        """The transfer function's color at texel coordinate ``u``."""
        (color, _), _ = self.classify(params, u, u)
        return color

    def finish(self, params, L):
        """``(color, met, scalar)`` of a ray's accumulated ``L``: the transfer
        function's color at the value (black where the ray met nothing)."""
        u, met = self.value(L)
        return dr.select(met, self.color(params, u), 0.0), met, self.scalar(u)

    def replay(self, params, buf, L, o, d):
        """The pixel color of a ray ``(o, d)`` (detached) whose primal walk
        picked ``L`` (detached), recomputed in ``L.tet`` from ``params`` and
        ``buf`` (attached to the AD graph)."""
        if self.mean:
            raise NotImplementedError("tetproj: the mean intensity projection is not "
                                      "differentiable (it integrates every tet of a ray); "
                                      "max, min, slice and iso are")
        u, met = self.value(L)
        frame = TetFrame(buf, L.tet, met)
        values = [PostClassified.gather(self, params, i, met).u for i in frame.ids]
        return dr.select(met, self.color(params, self.replay_value(frame, values, L, o, d)),
                         0.0)

    def replay_value(self, frame, values, L, o, d):
        """The texel coordinate at the picked point, from the tet's corner
        ``values`` (:meth:`replay`)."""
        raise NotImplementedError


class Projection(RayValue):
    """Intensity projections of a post-classified shape's scalar along each
    ray, exact per segment (the scalar is linear in a tet): the maximum
    (``max``, MIP) and minimum (``min``) are at a segment's ends, the mean
    over the length inside the meshes (``mean``, average intensity) is the
    trapezoid's. The transmittance stays 1, so every tet on the ray is
    visited."""
    MODES = ("max", "min", "mean")

    def __init__(self, mode: str = "max", **kwargs):
        super().__init__(**kwargs)
        if mode not in self.MODES:
            raise ValueError(f"projection mode must be one of {self.MODES}, got {mode!r}")
        self.mode = mode
        self.mean = mode == "mean"
        self.initial = {"max": -NO_VALUE, "min": NO_VALUE, "mean": 0.0}[mode]

    def better(self, a, b):
        """Whether value ``a`` beats ``b`` (greater for ``max``)."""
        return a > b if self.mode == "max" else a < b

    def segment(self, params, length, a0, a1, tet):
        if self.mean:
            return (mi.Color3f(length * 0.5 * (a0.u + a1.u), length, 0.0), mi.Float(1.0),
                    mi.Float(0.0))
        end = self.better(a1.u, a0.u)
        u = dr.select(length > 0.0, dr.select(end, a1.u, a0.u), self.initial)
        pick = Pick(u, dr.select(end, a1.p, a0.p), mi.Vector3f(0.0), tet, mi.UInt32(0))
        return pick, mi.Float(1.0), mi.Float(0.0)

    def accumulate(self, L, T, C, T_seg):
        if self.mean:
            return L + C, T
        return tree_select(self.better(C.u, L.u), C, L), T

    def replay_value(self, frame, values, L, o, d):
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


class Slice(RayValue):
    """A plane through the mesh showing its scalar: each ray stops where it
    first crosses the plane inside the mesh, and the scalar there is exact.
    The signed distance ``s`` of a crossing's point to the plane is linear
    along the ray in a tet, so a segment meets the plane at the fraction
    ``s0 / (s0 - s1)`` where the scalar is ``lerp(u0, u1, f)``. ``T`` turns
    0 there (the walk stops)."""

    def __init__(self, origin, normal, **kwargs):
        super().__init__(**kwargs)
        self.origin = np.asarray(origin, np.float64).reshape(3)
        self.normal = unit_vector(normal, "a slice's normal")
        self.initial = -NO_VALUE

    def plane(self):
        return mi.Point3f(*self.origin.tolist()), mi.Vector3f(*self.normal.tolist())

    def segment(self, params, length, a0, a1, tet):
        origin, normal = self.plane()
        s0, s1 = dr.dot(a0.p - origin, normal), dr.dot(a1.p - origin, normal)
        meets = ((length > 0.0) & (s0 != s1) & (dr.minimum(s0, s1) <= 0.0)
                 & (dr.maximum(s0, s1) >= 0.0))
        f = dr.clip(s0 / dr.select(s0 != s1, s0 - s1, 1.0), 0.0, 1.0)
        u = dr.select(meets, dr.lerp(a0.u, a1.u, f), self.initial)
        pick = Pick(u, dr.lerp(a0.p, a1.p, f), mi.Vector3f(0.0), tet, mi.UInt32(0))
        return pick, dr.select(meets, 0.0, 1.0), mi.Float(0.0)

    def accumulate(self, L, T, C, T_seg):
        return tree_select(T_seg < 1.0, C, L), T * T_seg

    def depth(self, o, d):
        """Where the rays ``(o, d)`` meet the plane."""
        origin, normal = self.plane()
        slope = dr.dot(d, normal)
        return dr.dot(origin - o, normal) / dr.select(slope != 0.0, slope, 1.0)

    def replay_value(self, frame, values, L, o, d):
        return frame.at(values, o + d * self.depth(o, d))

    def replay_surface(self, params, buf, L, o, d):
        """``(color, t)``: :meth:`replay` and the plane's depth (fixed)."""
        return self.replay(params, buf, L, o, d), self.depth(o, d)


class Isosurface(RayValue):
    """The first isosurface a ray meets, of one or more ``values`` of a
    post-classified shape's scalar, exact: the scalar is linear along the ray
    in a tet, so a segment crosses value ``v`` at ``f = (v - u0) / (u1 -
    u0)``. A crossing carries the scalar's texel coordinate, the position and
    the vertex gradient (the tets' gradients around the vertex averaged by
    volume, :func:`~mi_tetvr.render.linear.vertex_gradients`), all linear
    inside a tet: the hit point and its smooth normal are exact lerps. The
    pixel is the transfer function's color at the isovalue lit by a headlight
    (Lambert, two-sided). ``T`` turns 0 at the hit (the walk stops).

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

    def __init__(self, values, **kwargs):
        super().__init__(**kwargs)
        self.values = mi.Float(values)
        self.count = dr.width(self.values)
        if not self.count:
            raise ValueError("an isosurface needs at least one value")
        self.initial = -NO_VALUE

    def read_params(self, shapes):
        s = self.the_shape(shapes)
        scalar, positions = s.attribute_buffer("vertex_scalar"), s.vertex_positions_buffer()
        return self.Params(scalar, s.tf_color, s.tf_opacity, positions,
                           shape_vertex_gradients(s), self.values)

    def gather(self, params, i, active=True, reduce=dr.ReduceMode.Auto):
        a = RayValue.gather(self, params, i, active, reduce)
        return self.Attributes(a.u, a.p, dr.gather(mi.Vector3f, params.gradients, i, active))

    def segment(self, params, length, a0, a1, tet):
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
        hit = Pick(dr.select(meets, value, self.initial), dr.lerp(a0.p, a1.p, best),
                   dr.lerp(a0.g, a1.g, best), tet, k)
        return hit, dr.select(meets, 0.0, 1.0), mi.Float(0.0)

    def accumulate(self, L, T, C, T_seg):
        return tree_select(T_seg < 1.0, C, L), T * T_seg

    @staticmethod
    def lambert(n, d):
        """The headlight's factor ``|n . d| / |n|`` (1 where ``n`` is 0)."""
        norm = dr.norm(n)
        return dr.select(norm > 0.0, dr.abs(dr.dot(n, d)) / dr.select(norm > 0.0, norm, 1.0),
                         1.0)

    def shade(self, params, L, d):
        """``(color, met, point)``: the transfer function's color at the hit's
        value lit by the headlight."""
        color, met, _ = self.finish(params, L)
        return color * self.lambert(L.n, d), met, L.p

    def replay(self, params, buf, L, o, d):
        return self.replay_surface(params, buf, L, o, d)[0]

    def replay_surface(self, params, buf, L, o, d):
        """``(color, t)``: :meth:`replay` and the hit's depth along the ray,
        both closed forms in the hit's tet (differentiable)."""
        _, met = self.value(L)
        frame = TetFrame(buf, L.tet, met)
        values = [PostClassified.gather(self, params, i, met).u for i in frame.ids]
        w = self.texel(dr.gather(mi.Float, params.values, L.k, met))
        g = frame.gradient(values)
        slope = dr.dot(g, d)
        t = (w - frame.at(values, o)) / dr.select(slope != 0.0, slope, 1.0)
        x = o + d * t
        n = sum((lam * dr.gather(mi.Vector3f, params.gradients, i, met)
                 for lam, i in zip(frame.weights(x), frame.ids)), mi.Vector3f(0.0))
        return dr.select(met, self.color(params, w) * self.lambert(n, d), 0.0), t


#: Samples of the pre-integrated table along the front and back scalar (at
#: most; fewer for a coarser transfer function) and along the segment length.
TABLE_SCALARS = 128
TABLE_LENGTHS = 32


class PreIntegrated(PostClassified):
    """Post-classification by Weiler et al.'s pre-integrated table, a fast
    primal option: the emission and transmittance of a segment are looked up
    (trilinearly) in a table over (front scalar, back scalar, length) that
    :class:`PostClassified`'s exact integral filled for the shape's transfer
    function, instead of cutting the segment at the texels. The transfer
    function's texels get no derivatives (the table would need its own; the
    exact path is the reference); the scalar's and the positions' are those
    of the trilinear lookup.
    """

    class Params:
        DRJIT_STRUCT = {"scalar": mi.Float, "table": mi.Float}

        def __init__(self, scalar=None, table=None):
            self.scalar, self.table = scalar, table

    cuts = False

    def read_params(self, shapes):
        s = self.the_shape(shapes)
        with dr.resume_grad():      # (the primal pass runs with AD suspended)
            tracked = dr.grad_enabled(s.tf_color) or dr.grad_enabled(s.tf_opacity)
        if tracked:
            raise ValueError("tetmesh: classification 'preintegrated' has no derivatives; "
                             "use 'post' to differentiate the transfer function")
        key = (s.tf_color.index, s.tf_opacity.index)
        cached = getattr(s, "_preintegrated", None)
        if cached is None or cached[0] != key:
            s._preintegrated = (key, self.table(s.tf_color, s.tf_opacity, s.longest_edge))
        self.samples, self.max_length, table = s._preintegrated[1]
        return self.Params(s.attribute_buffer("vertex_scalar"), table)

    def table(self, tf_color, tf_opacity, max_length):
        """``(samples, max_length, table)``: RGB emission and transmittance of
        segments from texel coordinate ``u_i`` to ``u_j`` of length ``l_k``,
        flattened ``[(i * S + j) * K + k] * 4 + channel``."""
        S, K = min(TABLE_SCALARS, self.resolution), TABLE_LENGTHS
        last = self.resolution - 1
        i, j, k = np.meshgrid(np.arange(S), np.arange(S), np.arange(K), indexing="ij")
        u = lambda x: mi.Float((x.ravel() * (last / (S - 1))).astype(np.float32))  # noqa: E731
        length = mi.Float((k.ravel() * (max_length / (K - 1))).astype(np.float32))
        C, T = self.exact(PostClassified.Params(None, dr.detach(tf_color),
                                                dr.detach(tf_opacity)), u(i), u(j), length)
        table = np.stack([np.array(C.x), np.array(C.y), np.array(C.z), np.array(T)], -1)
        return S, float(max_length), mi.Float(table.astype(np.float32).ravel())

    @dr.syntax
    def exact(self, params, u0, u1, length):
        """The exact post-classified integral of segments whose texel
        coordinate goes from ``u0`` to ``u1`` over ``length``, piece by piece
        between the knots."""
        C = dr.zeros(mi.Color3f, dr.width(u0))
        T = dr.ones(mi.Float, dr.width(u0))
        a = mi.Float(u0)
        done = mi.Float(0.0)          # fraction of the segment integrated
        active = dr.full(mi.Bool, True, dr.width(u0))
        while active:
            f = self.cut(self.Attributes(a), self.Attributes(u1))
            b = dr.lerp(a, u1, f)
            end = dr.select(f < 1.0, done + (1.0 - done) * f, 1.0)
            (c0, s0), (c1, s1) = self.classify(params, a, b)
            Cp, Tp = segment_integral(length * (end - done), c0, c1, s0, s1, self.n_sub)
            C += T * Cp
            T *= Tp
            a = b
            done = end
            active &= f < 1.0
        return C, T

    def linear(self, params, a0, a1):
        raise ValueError("tetvr: a pre-integrated tetmesh (classification 'preintegrated') "
                         "cannot overlap another tetmesh: its table integrates whole segments "
                         "of its own medium alone; use classification 'post'")

    def segment(self, params, length, a0, a1):
        S, K = self.samples, TABLE_LENGTHS
        last = float(self.resolution - 1)
        scale = (S - 1) / last

        def coord(u, n):
            x = dr.clip(u, 0.0, float(n - 1))
            lo = mi.UInt32(dr.minimum(dr.floor(x), float(n - 2)))
            return lo, x - mi.Float(lo)
        i, wi = coord(dr.clip(a0.u, 0.0, last) * scale, S)
        j, wj = coord(dr.clip(a1.u, 0.0, last) * scale, S)
        k, wk = coord(length * ((K - 1) / self.max_length), K)
        out = dr.zeros(mi.Vector4f, dr.width(length))
        for di, fi in ((0, 1.0 - wi), (1, wi)):
            for dj, fj in ((0, 1.0 - wj), (1, wj)):
                for dk, fk in ((0, 1.0 - wk), (1, wk)):
                    idx = ((i + di) * S + (j + dj)) * K + (k + dk)
                    out += (fi * fj * fk) * dr.gather(mi.Vector4f, params.table, idx)
        tau = -dr.log(dr.maximum(out.w, 1e-30))
        return mi.Color3f(out.x, out.y, out.z), out.w, tau
