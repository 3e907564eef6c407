"""Optical models (the media): what a vertex carries and how one segment is
integrated.

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

Where meshes overlap, the walk integrates the pieces of all of them as one
medium from each model's :meth:`OpticalModel.linear` (color and extinction
at a piece's ends).

Models here: :class:`EmissionAbsorption` (what ``tetmesh`` shapes use),
:class:`ViewDependent` (the same with colors that depend on the direction they are
seen from: spherical harmonics per vertex), :class:`Scattering` (extinction, albedo
and emission: a
participating medium), :class:`Absorption` (extinction only), :class:`PostClassified` (a scalar and
a transfer function), :class:`PreIntegrated` (the same by a table),
:class:`CellClassified` (a scalar per tet and a transfer function) and
:class:`Shaded` (post-classified and lit by a headlight). To add a model,
subclass :class:`OpticalModel`, and let the ``tetmesh`` shape name it
(``shape.optical_model``) and carry its ``vertex_attributes``; the walk and
the adjoint stay as they are. What picks one value along a ray instead of
integrating (projections, slices, isosurfaces) is a probe:
:mod:`~mi_tetvr.render.probes`.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_tetvr.mesh import TetMesh
from mi_tetvr.render.buffers import concat
from mi_tetvr.render.linear import TetFrame
from mi_tetvr.render.pytree import weighted_sum
from mi_tetvr.render.segment import (emission_weights_vjp, segment_integral,
                                     zero_opacity_derivatives)


def piece_of(x: mi.Float, n: int) -> mi.UInt32:
    """The linear piece ``k`` in ``[0, n - 2]`` of ``n`` samples at ``0 .. n-1``
    that holds ``x`` (the first or last one beyond them). Written with
    comparisons, false for a NaN: a lane whose coordinate is not a number (an
    inactive one) reads samples 0 and 1, never outside the array."""
    k = dr.floor(x)
    return mi.UInt32(dr.select(k > 0.0, dr.select(k < n - 2.0, k, float(n - 2)), 0.0))


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
    #: Whether :meth:`segment` takes the index of the segment's tet (in the
    #: walk's buffers) as a fifth argument.
    per_tet = False
    #: Whether a vertex's values depend on the ray (:meth:`for_ray`): then the
    #: adjoint passes each vertex's gradient to the parameters ray by ray,
    #: instead of summing it over the rays first.
    per_ray_values = False

    def __init__(self, n_sub: int = 4) -> None:
        self.n_sub = int(n_sub)

    @staticmethod
    def vertex_values(mesh: TetMesh) -> dict[str, np.ndarray]:
        """``{name: (n, channels) array}`` of :attr:`vertex_attributes` from a
        :class:`~mi_tetvr.mesh.TetMesh` (the shape's initial values)."""
        raise NotImplementedError

    def read_params(self, shapes: list[mi.Mesh]) -> Any:
        """The model's parameter buffers, concatenated over ``shapes`` in the
        order of their vertices (attached to the shapes' AD graph)."""
        raise NotImplementedError

    def for_ray(self, params: Any, d: mi.Vector3f) -> Any:
        """``params`` for rays of unit direction ``d`` (a model whose vertices'
        values depend on the direction they are seen from evaluates that once per
        ray here); the walk calls it before it gathers."""
        return params

    def gather(self, params: Any, i: mi.UInt32, active: bool | mi.Bool = True,
               reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> Any:
        """``Attributes`` of vertex ``i``; ``reduce`` is the scatter strategy
        of the gather's reverse-mode derivative."""
        raise NotImplementedError

    def interpolate(self, params: Any, ids: Sequence[mi.UInt32], w: Sequence[mi.Float],
                    active: bool | mi.Bool = True,
                    reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> Any:
        """``Attributes`` at barycentric weights ``w`` of the vertices ``ids``."""
        return weighted_sum(w, [self.gather(params, i, active, reduce) for i in ids])

    def segment(self, params: Any, length: mi.Float, a0: Any,
                a1: Any) -> tuple[mi.Color3f, mi.Float, mi.Float]:
        """``(C : Color3f, T : Float, tau : Float)`` of a segment of
        ``length`` whose attributes go linearly from ``a0`` to ``a1``."""
        raise NotImplementedError

    def segment_adjoint(self, params: Any, length: mi.Float, a0: Any, a1: Any,
                        g_C: mi.Color3f, g_tau: Any, *tet: mi.UInt32) -> tuple | None:
        """A segment's emission and transmittance and their reverse-mode
        derivative in closed form, ``(C, T, g_length, g_a0, g_a1)``: the
        gradients w.r.t. the segment's length and end attributes of ``g_C .
        C + g_tau(C) tau`` (the optical depth's gradient depends on the
        emission: the radiance behind the segment). The backward pass's
        adjoint runs it instead of differentiating :meth:`segment` by
        Dr.Jit's AD. None (the default) for a model without one, or whose
        segment reads differentiable parameters of its own (a transfer
        function)."""
        return None

    def linear(self, params: Any, a0: Any, a1: Any,
               tet: mi.UInt32) -> tuple[mi.Color3f, mi.Color3f, mi.Float, mi.Float]:
        """``(c0, c1, s0, s1)``: color and extinction at the ends of a piece
        of ``tet`` (an index in the walk's buffers) whose attributes go
        linearly from ``a0`` to ``a1`` (between the model's knots: color and
        extinction are linear on it). Where meshes overlap, the pieces of all
        of them are integrated as one medium from these
        (:func:`~mi_tetvr.render.segment.merged_integral`)."""
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
    def vertex_values(mesh: TetMesh) -> dict[str, np.ndarray]:
        return {"vertex_color": mesh.color, "vertex_opacity": mesh.opacity}

    def read_params(self, shapes: list[mi.Mesh]) -> EmissionAbsorption.Params:
        return self.Params(concat([s.attribute_buffer("vertex_color") for s in shapes]),
                           concat([s.attribute_buffer("vertex_opacity") for s in shapes]))

    def gather(self, params: Any, i: mi.UInt32, active: bool | mi.Bool = True,
               reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> EmissionAbsorption.Attributes:
        return self.Attributes(dr.gather(mi.Color3f, params.color, i, active, mode=reduce),
                               dr.gather(mi.Float, params.opacity, i, active, mode=reduce))

    def segment(self, params: Any, length: mi.Float, a0: Any,
                a1: Any) -> tuple[mi.Color3f, mi.Float, mi.Float]:
        C, T = segment_integral(length, a0.c, a1.c, a0.s, a1.s, self.n_sub)
        # The midpoint sums of the sub-intervals: exact for a linear extinction.
        tau = length * (a0.s + a1.s) * 0.5
        return C, T, tau

    def segment_adjoint(self, params: Any, length: mi.Float, a0: Any, a1: Any,
                        g_C: mi.Color3f, g_tau: Any) -> tuple:
        # The integral's weights of the two colors and its transmittance, and
        # their derivative, in a branch that empty segments skip (they take
        # the scheme's derivatives at zero extinction, no exponential); the
        # colors' gradients and the optical depth's (linear) outside it.
        n_sub = self.n_sub
        g_P, g_Q = dr.dot(g_C, a0.c), dr.dot(g_C, a1.c)

        def full():
            P, Q, T, back = emission_weights_vjp(length, a0.s, a1.s, n_sub)
            return (P, Q, T, *back(g_P, g_Q))

        def empty():
            p0, q0, p1, q1 = zero_opacity_derivatives(n_sub)
            zero = mi.Float(0.0)
            return (zero, zero, mi.Float(1.0), zero, length * (g_P * p0 + g_Q * q0),
                    length * (g_P * p1 + g_Q * q1))
        # (zero extinction at both ends, and so all along: C = 0, T = 1 exactly)
        P, Q, T, g_L, g_s0, g_s1 = dr.if_stmt((), (a0.s != 0.0) | (a1.s != 0.0), full, empty,
                                              label="segment_adjoint")
        C = a0.c * P + a1.c * Q
        half = g_tau(C) * 0.5
        return (C, T, g_L + half * (a0.s + a1.s),
                self._attributes_grad(g_C * P, g_s0 + half * length),
                self._attributes_grad(g_C * Q, g_s1 + half * length))

    def _attributes_grad(self, c: mi.Color3f, s: mi.Float) -> Any:
        """Gradients of ``Attributes`` whose color is ``c`` and extinction
        ``s`` (any other field, e.g. an albedo, zero)."""
        g = dr.zeros(self.Attributes, dr.width(s))
        g.c, g.s = c, s
        return g

    def linear(self, params: Any, a0: Any, a1: Any,
               tet: mi.UInt32) -> tuple[mi.Color3f, mi.Color3f, mi.Float, mi.Float]:
        return a0.c, a1.c, a0.s, a1.s


#: Real spherical harmonics' constants up to degree 3 (as 3D Gaussian Splatting's
#: ``sh_utils``: the orthonormal real basis with the Condon-Shortley phase).
_SH_C0 = 0.28209479177387814
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
          -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
          -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(d: Any, degree: int) -> list:
    """The ``(degree + 1)^2`` real spherical harmonics at the unit direction ``d``
    (Dr.Jit or numpy components ``d.x, d.y, d.z`` / ``d[..., 0]``...), in the order
    of 3D Gaussian Splatting (degree by degree, ``m`` from ``-l`` to ``l``)."""
    x, y, z = (d.x, d.y, d.z) if hasattr(d, "x") else (d[..., 0], d[..., 1], d[..., 2])
    out = [_SH_C0 + 0.0 * x]
    if degree >= 1:
        out += [-_SH_C1 * y, _SH_C1 * z, -_SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [_SH_C2[0] * xy, _SH_C2[1] * yz, _SH_C2[2] * (2.0 * zz - xx - yy),
                _SH_C2[3] * xz, _SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [_SH_C3[0] * y * (3.0 * xx - yy), _SH_C3[1] * xy * z,
                _SH_C3[2] * y * (4.0 * zz - xx - yy),
                _SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
                _SH_C3[4] * x * (4.0 * zz - xx - yy), _SH_C3[5] * z * (xx - yy),
                _SH_C3[6] * x * (xx - 3.0 * yy)]
    return out


class ViewDependent(EmissionAbsorption):
    """Emission and absorption whose color depends on the direction it is seen
    from, as 3D Gaussian Splatting's and Radiant Foam's primitives: per vertex, the
    coefficients of real spherical harmonics up to :attr:`degree` per color channel
    (``vertex_sh``: ``(degree + 1)^2`` RGB triples, degree by degree), and an
    extinction. Seen along the unit direction ``d``, a vertex's color is ``max(sum_k
    Y_k(d) k_k + 0.5, 0)`` (3DGS's offset: zero coefficients are a mid gray; the
    degree-0 coefficient of a color ``c`` is ``(c - 0.5) / Y_0``). A ray's direction
    is constant along it, so its basis is evaluated once per ray (:meth:`for_ray`)
    and the colors stay linear inside a tet: each segment is
    :class:`EmissionAbsorption`'s. One class per degree (:func:`view_dependent`),
    so that meshes of one degree share a walk."""

    #: The spherical harmonics' degree (0 to 3).
    degree = 0
    per_ray_values = True

    class Params:
        DRJIT_STRUCT = {"sh": mi.Float, "opacity": mi.Float, "basis": list}

        def __init__(self, sh=None, opacity=None, basis=None):
            self.sh, self.opacity, self.basis = sh, opacity, basis

    @staticmethod
    def vertex_values(mesh: TetMesh) -> dict[str, np.ndarray]:
        raise NotImplementedError("a view-dependent tetmesh reads its coefficients from its "
                                  "properties")

    def read_params(self, shapes: list[mi.Mesh]) -> ViewDependent.Params:
        return self.Params(concat([s.attribute_buffer("vertex_sh") for s in shapes]),
                           concat([s.attribute_buffer("vertex_opacity") for s in shapes]),
                           [])

    def for_ray(self, params: ViewDependent.Params, d: mi.Vector3f) -> ViewDependent.Params:
        """``params`` with the basis at the rays' directions ``d``."""
        return self.Params(params.sh, params.opacity, sh_basis(d, self.degree))

    def gather(self, params: Any, i: mi.UInt32, active: bool | mi.Bool = True,
               reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> EmissionAbsorption.Attributes:
        if not params.basis:
            raise RuntimeError("ViewDependent.gather needs the rays' basis: for_ray(params, d)")
        K = len(params.basis)
        c = mi.Color3f(0.5)
        for k, y in enumerate(params.basis):
            c += y * dr.gather(mi.Color3f, params.sh, i * K + k, active, mode=reduce)
        return self.Attributes(dr.maximum(c, 0.0),
                               dr.gather(mi.Float, params.opacity, i, active, mode=reduce))


_VIEW_DEPENDENT = {}


def view_dependent(degree: int) -> type:
    """The :class:`ViewDependent` model of spherical harmonics up to ``degree``
    (0 to 3), one class per degree."""
    degree = int(degree)
    if not 0 <= degree <= 3:
        raise ValueError(f"the spherical harmonics' degree must be 0 to 3, got {degree}")
    if degree not in _VIEW_DEPENDENT:
        K = (degree + 1) ** 2
        _VIEW_DEPENDENT[degree] = type(f"ViewDependent{degree}", (ViewDependent,), {
            "degree": degree, "vertex_attributes": (("vertex_sh", 3 * K), ("vertex_opacity", 1)),
            "__doc__": f"{ViewDependent.__name__} of degree {degree}."})
    return _VIEW_DEPENDENT[degree]


class Scattering(EmissionAbsorption):
    """A participating medium: per-vertex extinction ``s`` (the opacity),
    single-scattering albedo ``a`` (linear RGB) and emission ``c`` (per unit
    extinction, as :class:`EmissionAbsorption`'s color), all linear inside a
    tet; the phase function is the shape's (``shape.phase``).

    The path tracer (:mod:`mi_tetvr.render.transport`) samples free-flight
    distances in it exactly and lights it by the scene's emitters; the
    emission-absorption walk integrates its emission and extinction as
    :class:`EmissionAbsorption` does (no scattering)."""

    class Attributes:
        DRJIT_STRUCT = {"c": mi.Color3f, "s": mi.Float, "a": mi.Color3f}

        def __init__(self, c=None, s=None, a=None):
            self.c, self.s, self.a = c, s, a

    class Params:
        DRJIT_STRUCT = {"color": mi.Float, "opacity": mi.Float, "albedo": mi.Float}

        def __init__(self, color=None, opacity=None, albedo=None):
            self.color, self.opacity, self.albedo = color, opacity, albedo

    vertex_attributes = (("vertex_emission", 3), ("vertex_opacity", 1), ("vertex_albedo", 3))

    @staticmethod
    def vertex_values(mesh: TetMesh) -> dict[str, np.ndarray]:
        raise NotImplementedError("a scattering tetmesh reads its albedo and emission from "
                                  "its properties")

    def read_params(self, shapes: list[mi.Mesh]) -> Scattering.Params:
        return self.Params(concat([s.attribute_buffer("vertex_emission") for s in shapes]),
                           concat([s.attribute_buffer("vertex_opacity") for s in shapes]),
                           concat([s.attribute_buffer("vertex_albedo") for s in shapes]))

    def gather(self, params: Any, i: mi.UInt32, active: bool | mi.Bool = True,
               reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> Scattering.Attributes:
        return self.Attributes(dr.gather(mi.Color3f, params.color, i, active, mode=reduce),
                               dr.gather(mi.Float, params.opacity, i, active, mode=reduce),
                               dr.gather(mi.Color3f, params.albedo, i, active, mode=reduce))


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
    def vertex_values(mesh: TetMesh) -> dict[str, np.ndarray]:
        return {"vertex_opacity": mesh.opacity}

    def read_params(self, shapes: list[mi.Mesh]) -> Absorption.Params:
        return self.Params(concat([s.attribute_buffer("vertex_opacity") for s in shapes]))

    def gather(self, params: Any, i: mi.UInt32, active: bool | mi.Bool = True,
               reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> Absorption.Attributes:
        return self.Attributes(dr.gather(mi.Float, params.opacity, i, active, mode=reduce))

    def segment(self, params: Any, length: mi.Float, a0: Any,
                a1: Any) -> tuple[mi.Color3f, mi.Float, mi.Float]:
        tau = length * (a0.s + a1.s) * 0.5
        return dr.zeros(mi.Color3f, dr.width(length)), dr.exp(-tau), tau

    def linear(self, params: Any, a0: Any, a1: Any,
               tet: mi.UInt32) -> tuple[mi.Color3f, mi.Color3f, mi.Float, mi.Float]:
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

    def __init__(self, n_sub: int = 4, resolution: int = 256,
                 value_range: tuple[float, float] = (0.0, 1.0)) -> None:
        super().__init__(n_sub)
        self.resolution = int(resolution)
        self.value_range = tuple(float(x) for x in value_range)

    @staticmethod
    def vertex_values(mesh: TetMesh) -> dict[str, np.ndarray]:
        raise NotImplementedError("post-classified meshes take their scalar from the shape")

    def the_shape(self, shapes: list[mi.Mesh]) -> mi.Mesh:
        """The one shape of a walk of a post-classified model (its value
        range and texel count set on the model)."""
        if len(shapes) != 1:
            raise ValueError("tetvr: a post-classified walk renders one tetmesh, got "
                             f"{len(shapes)} (see model_groups)")
        s = shapes[0]
        self.value_range, self.resolution = s.value_range, s.tf_resolution
        return s

    def read_params(self, shapes: list[mi.Mesh]) -> PostClassified.Params:
        s = self.the_shape(shapes)
        return self.Params(s.attribute_buffer("vertex_scalar"), s.tf_color, s.tf_opacity)

    def texel(self, v: mi.Float) -> mi.Float:
        """The texel coordinate of scalar value ``v``."""
        lo, hi = self.value_range
        return (v - lo) * (self.resolution / (hi - lo)) - 0.5

    def gather(self, params: Any, i: mi.UInt32, active: bool | mi.Bool = True,
               reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> PostClassified.Attributes:
        # Gathered from the parameter itself (so that its reverse-mode
        # derivative is a scatter-add into it), then mapped to texels.
        return self.Attributes(self.texel(dr.gather(mi.Float, params.scalar, i, active,
                                                    mode=reduce)))

    def classify(self, params: Any, u0: mi.Float,
                 u1: mi.Float) -> list[tuple[mi.Color3f, mi.Float]]:
        """Color and extinction at the texel coordinates ``u0`` and ``u1`` of
        a piece's ends. The piece lies between two knots, so both ends are
        read from the one linear part of the transfer function that holds
        the piece's middle (or its constant part below the first texel
        centre / above the last): a value a hair beyond a knot (round-off
        at a cut) keeps the piece's own slope, and so does its derivative."""
        last = float(self.resolution - 1)
        mid = 0.5 * (u0 + u1)
        below, above = mid < 0.0, mid > last
        k = piece_of(mid, self.resolution)
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

    def cut(self, a0: Any, a1: Any) -> mi.Float:
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

    def segment(self, params: Any, length: mi.Float, a0: Any,
                a1: Any) -> tuple[mi.Color3f, mi.Float, mi.Float]:
        (c0, s0), (c1, s1) = self.classify(params, a0.u, a1.u)
        C, T = segment_integral(length, c0, c1, s0, s1, self.n_sub)
        return C, T, length * (s0 + s1) * 0.5

    def linear(self, params: Any, a0: Any, a1: Any,
               tet: mi.UInt32) -> tuple[mi.Color3f, mi.Color3f, mi.Float, mi.Float]:
        (c0, s0), (c1, s1) = self.classify(params, a0.u, a1.u)
        return c0, c1, s0, s1

    def medium_at(self, params: Any, u: mi.Float, tet: mi.UInt32,
                  d: mi.Vector3f) -> tuple[mi.Color3f, mi.Float]:
        """``(color, extinction)`` where the scalar's texel coordinate is
        ``u`` in ``tet``, seen along ``d`` (an isosurface drawn in the
        volume: :mod:`~mi_tetvr.render.layers`)."""
        (c, sigma), _ = self.classify(params, u, u)
        return c, sigma


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

    def read_params(self, shapes: list[mi.Mesh]) -> CellClassified.Params:
        # (the cells are read through the order inside the walk: the
        # parameter itself is gathered, so forward mode needs no tangent
        # of a derived buffer)
        s = self.the_shape(shapes)
        self.reordered = s.cell_order is not None
        order = s.cell_order if self.reordered else mi.UInt32(0)
        return self.Params(s.cell_scalar, order, s.tf_color, s.tf_opacity)

    def gather(self, params: Any, i: mi.UInt32, active: bool | mi.Bool = True,
               reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> PostClassified.Attributes:
        # Nothing varies inside a tet (the walk still carries an attribute).
        return self.Attributes(mi.Float(0.0))

    def cell_texel(self, params: Any, tet: mi.UInt32) -> mi.Float:
        """The texel coordinate of the cell value of ``tet`` (the walk's index)."""
        cell = dr.gather(mi.UInt32, params.order, tet) if self.reordered else tet
        # (inside the adjoint's loop: plain atomics; Auto's per-thread
        # copies raced there)
        return self.texel(dr.gather(mi.Float, params.cells, cell, mode=dr.ReduceMode.Direct))

    def segment(self, params: Any, length: mi.Float, a0: Any, a1: Any,
                tet: mi.UInt32) -> tuple[mi.Color3f, mi.Float, mi.Float]:
        u = self.cell_texel(params, tet)
        (c, s), _ = self.classify(params, u, u)
        tau = s * length
        T = dr.exp(-tau)
        return c * (1.0 - T), T, tau

    def linear(self, params: Any, a0: Any, a1: Any,
               tet: mi.UInt32) -> tuple[mi.Color3f, mi.Color3f, mi.Float, mi.Float]:
        u = self.cell_texel(params, tet)
        (c, s), _ = self.classify(params, u, u)
        return c, c, s, s


class ScalarPoint:
    """A crossing's attributes for the models that need its point: the
    scalar's texel coordinate ``u`` and the point ``p``."""
    DRJIT_STRUCT = {"u": mi.Float, "p": mi.Point3f}

    def __init__(self, u: mi.Float | None = None, p: mi.Point3f | None = None) -> None:
        self.u, self.p = u, p

    @staticmethod
    def gather(model: PostClassified, params: Any, i: mi.UInt32,
               active: bool | mi.Bool = True,
               reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> ScalarPoint:
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
                        "positions": mi.Float, "cells": mi.UInt32}

        def __init__(self, scalar=None, tf_color=None, tf_opacity=None, positions=None,
                     cells=None):
            self.scalar, self.tf_color, self.tf_opacity = scalar, tf_color, tf_opacity
            self.positions, self.cells = positions, cells

        def position(self, i, active=True):
            return dr.gather(mi.Point3f, self.positions, i, active, mode=dr.ReduceMode.Direct)

        def corners(self, tet, active=True):
            return dr.gather(mi.Array4u, self.cells, 2 * tet, active)

    per_tet = True
    #: ``(ambient, diffuse, specular, specular_power)``, set from the shape.
    lighting = (0.1, 0.7, 0.2, 10.0)

    def read_params(self, shapes: list[mi.Mesh]) -> Shaded.Params:
        s = self.the_shape(shapes)
        self.lighting = s.lighting
        return self.Params(s.attribute_buffer("vertex_scalar"), s.tf_color, s.tf_opacity,
                           s.vertex_positions_buffer(), s.tet_buffers["cells"])

    def gather(self, params: Any, i: mi.UInt32, active: bool | mi.Bool = True,
               reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> ScalarPoint:
        return ScalarPoint.gather(self, params, i, active, reduce)

    def lit(self, c: mi.Color3f, g: mi.Vector3f, d: mi.Vector3f) -> mi.Color3f:
        """The color ``c`` lit at gradient ``g`` seen along ``d`` (unit)."""
        ambient, diffuse, specular, power = self.lighting
        norm = dr.norm(g)
        cos = dr.abs(dr.dot(g, d)) / dr.select(norm > 0.0, norm, 1.0)
        out = c * (ambient + diffuse * cos) + specular * dr.power(cos, power)
        return dr.select(norm > 0.0, out, c)

    @staticmethod
    def gradient(params: Shaded.Params, tet: mi.UInt32) -> mi.Vector3f:
        """The scalar's gradient in ``tet`` (constant: the scalar is linear)."""
        frame = TetFrame(params, tet)
        return frame.gradient([dr.gather(mi.Float, params.scalar, i, mode=dr.ReduceMode.Direct)
                               for i in frame.ids])

    @staticmethod
    def direction(a0: ScalarPoint, a1: ScalarPoint) -> mi.Vector3f:
        """The unit direction of a piece from its ends' points (0 when empty)."""
        step = a1.p - a0.p
        return step / dr.select(dr.norm(step) > 0.0, dr.norm(step), 1.0)

    def segment(self, params: Any, length: mi.Float, a0: Any, a1: Any,
                tet: mi.UInt32) -> tuple[mi.Color3f, mi.Float, mi.Float]:
        g = self.gradient(params, tet)
        d = self.direction(a0, a1)
        (c0, s0), (c1, s1) = self.classify(params, a0.u, a1.u)
        C, T = segment_integral(length, self.lit(c0, g, d), self.lit(c1, g, d), s0, s1,
                                self.n_sub)
        return C, T, length * (s0 + s1) * 0.5

    def linear(self, params: Any, a0: Any, a1: Any,
               tet: mi.UInt32) -> tuple[mi.Color3f, mi.Color3f, mi.Float, mi.Float]:
        g = self.gradient(params, tet)
        d = self.direction(a0, a1)
        (c0, s0), (c1, s1) = self.classify(params, a0.u, a1.u)
        return self.lit(c0, g, d), self.lit(c1, g, d), s0, s1

    def medium_at(self, params: Any, u: mi.Float, tet: mi.UInt32,
                  d: mi.Vector3f) -> tuple[mi.Color3f, mi.Float]:
        c, sigma = PostClassified.medium_at(self, params, u, tet, d)
        return self.lit(c, self.gradient(params, tet), d), sigma


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

    def read_params(self, shapes: list[mi.Mesh]) -> PreIntegrated.Params:
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

    def table(self, tf_color: mi.Float, tf_opacity: mi.Float,
              max_length: float) -> tuple[int, float, mi.Float]:
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
    def exact(self, params: Any, u0: mi.Float, u1: mi.Float,
              length: mi.Float) -> tuple[mi.Color3f, mi.Float]:
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

    def medium_at(self, params: Any, u: mi.Float, tet: mi.UInt32,
                  d: mi.Vector3f) -> tuple[mi.Color3f, mi.Float]:
        raise ValueError("tetvr: the derivatives of an isosurface overlay need the volume's "
                         "transfer function: use classification 'post' (not 'preintegrated')")

    def linear(self, params: Any, a0: Any, a1: Any,
               tet: mi.UInt32) -> tuple[mi.Color3f, mi.Color3f, mi.Float, mi.Float]:
        raise ValueError("tetvr: a pre-integrated tetmesh (classification 'preintegrated') "
                         "cannot overlap another tetmesh: its table integrates whole segments "
                         "of its own medium alone; use classification 'post'")

    def segment(self, params: Any, length: mi.Float, a0: Any,
                a1: Any) -> tuple[mi.Color3f, mi.Float, mi.Float]:
        S, K = self.samples, TABLE_LENGTHS
        last = float(self.resolution - 1)
        scale = (S - 1) / last

        def coord(u, n):
            x = dr.clip(u, 0.0, float(n - 1))
            lo = piece_of(x, n)
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
