"""The derivative modes of the walk (the inversion trick).

The derivative modes run the same traversal again with the pixel's final
value ``L_pix`` (color + T * background) and transmittance ``T_fin`` from the
primal pass; nothing per segment is stored. Front to back, the walk knows the
accumulated emission ``L`` and transmittance ``T`` in front of each segment
(recomputed, not recorded), so the radiance that reaches the pixel from
*behind* the segment is recovered as ``R = L_pix - (L + T C_k)``. With the
segment's emission ``C_k`` and optical depth ``tau_k`` (transmittance
``exp(-tau_k)``)::

    d L_pix = T dC_k - R dtau_k        d alpha = T_fin dtau_k

(``alpha = 1 - T_fin``). This is Mitsuba's PRB-style front-to-back form
rather than DiffTetVR's back-to-front inversion: it never divides by a
transmittance, so it stays exact as the accumulated opacity approaches 1 (the
back-to-front inversion divides by ``1 - alpha`` of each segment, and early
ray termination would make that inversion start from an unknown state). ``R``
is a difference of two accumulated values, so its absolute error is a few
float ulps of ``L_pix``; it multiplies ``dtau_k``, so the relative error of a
gradient stays at float precision.

In backward mode ``dC_k`` and ``dtau_k`` are the optical model's
closed form where it has one
(:meth:`~mi_tetvr.render.optical.OpticalModel.segment_adjoint`, with the
clip's, :func:`~mi_tetvr.render.segment.clip_segment_vjp`), else (and in
forward mode) Dr.Jit's AD of its segment integral
(:meth:`~mi_tetvr.render.optical.OpticalModel.segment`) taken *locally*
inside the loop body; the face crossings are differentiated in closed form
(:func:`~mi_tetvr.render.geometry.crossing_vjp`). Each vertex's gradient goes
to per-vertex sums (:class:`VertexSums`), passed to the parameters after the
walk. Memory is therefore O(rays + vertices), independent of the number of
tets crossed.

Each segment is a function of the ``(t, attributes)`` of its entry and exit
crossings. A crossing is shared by two consecutive segments, so its gradient
is complete one step later; it then goes to the crossed face's three
vertices. The walk carries that face's corners (index, projection, depth,
attributes: :func:`mi_tetvr.render.geometry.walk_step`), so the crossing's
derivative is taken from them without reading the vertices again
(:func:`crossing_grads`), and reverse mode keeps each corner's pending
gradient beside it: when a step replaces a corner by the tet's apex, the
vertex left behind is complete and added to the sums (one vertex per step),
the three last ones after the loop. Forward mode carries the exit crossing's
tangent over as the next entry's.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import drjit as dr
import mitsuba as mi

from mi_tetvr.render.buffers import TetGroup, _packet_type
from mi_tetvr.render.cursor import Piece, Span, WalkSettings
from mi_tetvr.render.geometry import RayFrame, crossing_vjp, face_crossing, face_weights
from mi_tetvr.render.optical import OpticalModel
from mi_tetvr.render.pytree import (scalar_leaves, tree_add, tree_copy, tree_dot, tree_lerp,
                                     tree_map, tree_select)
from mi_tetvr.render.segment import clip_segment, clip_segment_vjp

if TYPE_CHECKING:
    from mi_tetvr.render.walk import EmissionDerivative, Radiance


class Derivative:
    """The context of a derivative pass, handed down the walk explicitly (never
    set on the data it reads).

    mode : dr.ADMode
        ``Backward`` or ``Forward``.
    groups : list of :class:`~mi_tetvr.render.buffers.TetGroup`
        Per walk group, its buffers attached to the parameters' AD graph
        (the walk itself reads detached copies).
    camera : bool
        Whether the rays are differentiated (a differentiable sensor).
    ray_tangent : (Vector3f, Vector3f) or None
        Forward mode with a moving camera: the rays' tangents (origin,
        direction).
    """

    def __init__(self, mode: dr.ADMode, groups: list, camera: bool = False,
                 ray_tangent: tuple[mi.Vector3f, mi.Vector3f] | None = None) -> None:
        self.mode = mode
        self.backward = mode == dr.ADMode.Backward
        self.groups = list(groups)
        self.camera = bool(camera)
        self.ray_tangent = ray_tangent

    def geometric(self, ts_ad: TetGroup) -> bool:
        """Whether the pass needs the geometry of ``ts_ad``'s walk: vertices
        that move, or a differentiable camera."""
        return self.camera or moves_vertices(ts_ad)


class Adjoint:
    """Per-ray inputs and outputs of the derivative modes.

    L_pix, T_fin : the primal pixel value (with background) and transmittance.
    dL, dalpha : the incoming adjoint (backward mode), or the accumulated
        tangent (forward mode, starting at zero).
    g_o, g_w : (backward mode, a differentiable camera) the gradient w.r.t.
        the ray's origin and w.r.t. a rotation of its direction about the
        origin: moving the ray by ``delta`` is moving every vertex by
        ``-delta``, turning it by ``w`` turns every vertex by ``-w`` about
        ``o``, so both are sums over the crossings' vertex gradients
        (:func:`camera_grads`).
    """
    DRJIT_STRUCT = {"L_pix": mi.Color3f, "T_fin": mi.Float, "dL": mi.Color3f,
                    "dalpha": mi.Float, "g_o": mi.Vector3f, "g_w": mi.Vector3f}

    def __init__(self, L_pix: mi.Color3f | None = None, T_fin: mi.Float | None = None,
                 dL: mi.Color3f | None = None, dalpha: mi.Float | None = None,
                 g_o: mi.Vector3f | None = None, g_w: mi.Vector3f | None = None) -> None:
        self.L_pix, self.T_fin, self.dL, self.dalpha = L_pix, T_fin, dL, dalpha
        self.g_o, self.g_w = g_o, g_w


_VERTEX_GRAD_TYPES = {}


def vertex_grad_type(model: OpticalModel) -> type:
    """The ``DRJIT_STRUCT`` class of a pending vertex gradient under
    ``model``: position ``p`` and the model's attributes ``a``."""
    A = model.Attributes
    if A not in _VERTEX_GRAD_TYPES:
        def init(self, p=None, a=None):
            self.p, self.a = p, a
        _VERTEX_GRAD_TYPES[A] = type("VertexGrad", (), {
            "DRJIT_STRUCT": {"p": mi.Vector3f, "a": A}, "__init__": init,
            "__doc__": "Pending gradient of one vertex's position and attributes."})
    return _VERTEX_GRAD_TYPES[A]


def start(deriv: Derivative, ts_ad: TetGroup, carry: tuple, fr: RayFrame,
          active: mi.Bool) -> tuple:
    """The derivative modes' loop state besides the ray's adjoint, at the
    walk's entry face (``carry``, as the walk carries it): ``(e, pend, w)``.

    ``e`` is the gradient (backward) or tangent (forward) of the current
    entry crossing, ``(t, attributes)``; ``pend`` the pending gradients of
    the entry face's corners (backward mode), in the walk's corner order;
    ``w`` the crossing's weights (each step's exit weights, kept for the
    next step, which would compute them again from the same edge functions).
    """
    model = ts_ad.model
    e = (mi.Float(0.0), dr.zeros(model.Attributes))
    if not deriv.backward:
        e = tangent(deriv, ts_ad, tuple(c.i for c in carry[0]), fr, active)
    G = vertex_grad_type(model)
    pend = tuple(dr.zeros(G) for _ in range(3))
    if model.cuts:
        # Pieces of a tet: the exit crossing's gradient so far and where
        # along the tet's segment the current piece starts.
        return e, (mi.Float(0.0), dr.zeros(model.Attributes)), mi.Float(0.0), pend
    return e, pend, face_weights(*carry[2])


def moves_vertices(ts_ad: TetGroup) -> bool:
    """Whether vertex positions receive gradients (else the derivative
    modes leave out everything geometric: crossings' ray parameters and
    position scatters)."""
    with dr.resume_grad():     # the derivative passes run with AD suspended
        return dr.grad_enabled(ts_ad.buf.positions)


def ray_grads(adj: Adjoint, r: mi.Vector3f, g: mi.Vector3f, mask: bool | mi.Bool) -> Adjoint:
    """Add the gradient ``g`` of a vertex at offset ``r`` from the ray's
    origin to the ray's origin and direction gradients (see
    :class:`Adjoint`): moving the ray is moving the vertex the other way."""
    adj.g_o = dr.select(mask, adj.g_o - g, adj.g_o)
    adj.g_w = dr.select(mask, adj.g_w - dr.cross(r, g), adj.g_w)
    return adj


def camera_grads(adj: Adjoint, carry: tuple, vg: list[Any], fr: RayFrame,
                 mask: mi.Bool) -> Adjoint:
    """:func:`ray_grads` of one crossing's vertex-position gradients ``vg``
    (of the corners ``carry``); a corner's offset from the origin is ``p.x u
    + p.y v + z d``. The single walk's backward mode, whose crossings are
    differentiated in closed form; where a crossing is differentiated by
    Dr.Jit's AD (forward mode, the merged walk), the ray is a leaf of the
    graph instead (:func:`ray_leaves`)."""
    for c, g in zip(carry[0], vg):
        adj = ray_grads(adj, c.p.x * fr.u + c.p.y * fr.v + c.z * fr.d, g.p, mask)
    return adj


def inversion(deriv: Derivative, adj: Adjoint, L: mi.Color3f, T: mi.Float, C_seg: mi.Color3f,
              C_d: mi.Color3f, tau: mi.Float) -> Adjoint:
    """The inversion trick, for one segment or piece: with ``L, T`` the
    emission and transmittance in front of it, ``C_seg`` its emission (as the
    primal computed it) and ``C_d``, ``tau`` its emission and optical depth
    attached to the AD graph, the radiance reaching the pixel from behind it
    is ``R = L_pix - (L + T C_seg)``, and ``d L_pix = T dC - R dtau``, ``d
    alpha = T_fin dtau``. Backward mode propagates the ray's adjoint through
    them; forward mode returns ``adj`` with their tangents added."""
    R = adj.L_pix - (L + T * C_seg)
    Lo = T * C_d - tau * R
    Lo_alpha = tau * adj.T_fin
    flags = dr.ADFlag.Default | dr.ADFlag.AllowNoGrad
    if deriv.backward:
        dr.backward_from(dr.dot(adj.dL, Lo) + adj.dalpha * Lo_alpha, flags=flags)
    else:
        dLo, dLo_alpha = dr.forward_to(Lo, Lo_alpha, flags=flags)
        adj.dL = adj.dL + dLo
        adj.dalpha = adj.dalpha + dLo_alpha
    return adj


def crossing_grads(deriv: Derivative, ts_ad: TetGroup, carry: tuple, g: tuple[mi.Float, Any],
                   fr: RayFrame, w: tuple | None = None) -> list[Any]:
    """Gradient of ``g . (t, attributes)`` of the ray's crossing of the face
    the walk carries (``carry``: corners, their attributes, edge functions;
    ``w``: the crossing's weights, where known) w.r.t. each corner's
    position and attributes (:func:`~mi_tetvr.render.geometry.crossing_vjp`).
    A corner's projection is ``((P - o) . u, (P - o) . v)`` and its depth
    ``(P - o) . d``, so ``dP = dp.x u + dp.y v + dz d``."""
    G = vertex_grad_type(ts_ad.model)
    corners, values, edges = carry
    if not deriv.geometric(ts_ad):
        w = face_weights(*edges) if w is None else w
        return [G(mi.Vector3f(0.0), tree_map(lambda x: w[j] * x, g[1])) for j in range(3)]
    return [G(dp.x * fr.u + dp.y * fr.v + dz * fr.d, da)
            for dp, dz, da in crossing_vjp(corners, edges, values, g[0], g[1], w)]


def scatter(ts_ad: TetGroup, i: mi.UInt32, g: Any, active: mi.Bool,
            reduce: dr.ReduceMode) -> None:
    """Add the pending gradient ``g`` to the parameter gradients of vertex
    ``i`` (through the reverse-mode derivative of a gather: a scatter-add in
    ``reduce`` mode)."""
    with dr.resume_grad():
        a = ts_ad.model.gather(ts_ad.params, i, active, reduce)
        y = tree_dot(a, g.a)
        if moves_vertices(ts_ad):
            y += dr.dot(ts_ad.buf.position(i, active, reduce), g.p)
        dr.backward_from(y, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)


class VertexSums:
    """Where the backward mode of a walk adds each vertex's complete
    gradient (:func:`segment`, :func:`finish`): one packet of floats per
    vertex (its attributes' gradients, then its position's, padded to a
    power of two), summed over the rays in one scatter per vertex a ray
    leaves behind, and passed to the parameters once the walk is done
    (:meth:`flush`: the chain rule through the optical model's ``gather``
    of every vertex, which is the same for every ray).

    A packet's scatter-add is one read-modify-write per lane: on the LLVM
    backend into per-thread copies of the sums, without atomics
    (``settings.sums_mode``). The derivative of a gather, which this
    replaces, costs one atomic addition per float and lane (seven per
    vertex with colors, opacities and positions).

    A model whose vertex values depend on the ray (``model.per_ray_values``:
    view-dependent colors) has no such per-vertex sum: its gradients go to
    the parameters at every vertex (:func:`scatter`)."""

    def __init__(self, ts_ad: TetGroup, settings: WalkSettings) -> None:
        self.ts_ad, self.atomics = ts_ad, settings.atomics
        model = ts_ad.model
        self.summed = not model.per_ray_values
        self.geometric = moves_vertices(ts_ad)
        self.sums = None
        if not self.summed:
            return
        self.n = dr.width(ts_ad.buf.positions) // 3
        k = len(scalar_leaves(dr.zeros(model.Attributes))) + (3 if self.geometric else 0)
        self.width = 1 << max(k - 1, 0).bit_length()
        self.sums = dr.zeros(mi.Float, self.width * self.n)
        self.mode = settings.sums_mode(4 * self.width * self.n)

    def add(self, i: mi.UInt32, g: Any, active: mi.Bool) -> None:
        """Add a vertex's gradient ``g`` (of its position ``g.p`` and
        attributes ``g.a``) where ``active``."""
        if not self.summed:
            scatter(self.ts_ad, i, g, active, self.atomics)
            return
        leaves = scalar_leaves(g.a) + (scalar_leaves(g.p) if self.geometric else [])
        leaves += [mi.Float(0.0)] * (self.width - len(leaves))
        packet = leaves[0] if self.width == 1 else _packet_type()(*leaves)
        dr.scatter_add(self.sums, packet, i, active, mode=self.mode)

    def flush(self) -> None:
        """Pass the sums to the parameters' gradients (after the walk)."""
        if self.sums is None:
            return
        ts_ad, n = self.ts_ad, self.n
        with dr.resume_grad():
            idx = dr.arange(mi.UInt32, n)
            a = scalar_leaves(ts_ad.model.gather(ts_ad.params, idx))
            if self.geometric:
                a += scalar_leaves(ts_ad.buf.position(idx))
            y = mi.Float(0.0)
            for j, x in enumerate(a):
                y += x * dr.gather(mi.Float, self.sums, idx * self.width + j)
            dr.backward_from(y, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
        self.sums = None


def ray_leaves(deriv: Derivative, fr: RayFrame) -> tuple[mi.Point3f, mi.Vector3f]:
    """The ray's origin and direction as AD leaves: where the camera enters
    a derivative pass's graph (forward mode: carrying the rays' tangents,
    ``deriv.ray_tangent``). Frames are made of them by :func:`leaf_frame`;
    backward mode reads their gradients with :func:`leaf_grads`."""
    o, d = mi.Point3f(dr.detach(fr.o)), mi.Vector3f(dr.detach(fr.d))
    dr.enable_grad(o, d)
    if deriv.ray_tangent is not None:
        dr.set_grad(o, deriv.ray_tangent[0])
        dr.set_grad(d, deriv.ray_tangent[1])
    return o, d


def leaf_frame(leaves: tuple[mi.Point3f, mi.Vector3f], active: bool | mi.Bool) -> RayFrame:
    """The frame of the ray :func:`ray_leaves` made, attached where
    ``active``: elsewhere (a lane with no crossing there) it adds no
    gradient, rather than the NaN that a degenerate crossing's derivative
    times a zero weight may give."""
    o, d = leaves
    return RayFrame.of(dr.select(active, o, dr.detach(o)), dr.select(active, d, dr.detach(d)))


def leaf_grads(adj: Adjoint, leaves: tuple[mi.Point3f, mi.Vector3f]) -> Adjoint:
    """Add the gradients the leaves of :func:`ray_leaves` received to the
    ray's (see :class:`Adjoint`): turning the direction by ``w`` moves it by
    ``w x d``, so the rotation's gradient is ``d x g_d``."""
    o, d = leaves
    adj.g_o = adj.g_o + mi.Vector3f(dr.grad(o))
    adj.g_w = adj.g_w + dr.cross(dr.detach(d), dr.grad(d))
    return adj


def tangent(deriv: Derivative, ts_ad: TetGroup, ids: Sequence[mi.UInt32], fr: RayFrame,
            active: mi.Bool) -> tuple[mi.Float, Any]:
    """Forward mode: the tangent of a face crossing's ``(t, attributes)``
    (with a moving camera, ``deriv.ray_tangent``, the ray's tangent too)."""
    with dr.resume_grad():
        if deriv.ray_tangent is not None:
            fr = leaf_frame(ray_leaves(deriv, fr), True)
        t, w = face_crossing(ts_ad.buf, ids, fr, active)
        a = ts_ad.model.interpolate(ts_ad.params, ids, w, active)
        # AllowNoGrad: the tangents may all be elsewhere (e.g. the environment's);
        # not ClearInput: the parameters' tangents serve every crossing (a
        # walk's first crossing is taken outside any loop, where clearing them
        # would be for good)
        return dr.forward_to(t, a, flags=dr.ADFlag.ClearEdges | dr.ADFlag.ClearInterior
                             | dr.ADFlag.AllowNoGrad)


def _scaled(g, w):
    return tree_map(lambda x: x * w, g)


def segment(deriv: Derivative, walker: EmissionDerivative, p: Piece, acc: Radiance, span: Span,
            fr: RayFrame, active: mi.Bool) -> tuple[mi.Color3f, mi.Float, Adjoint, tuple]:
    """One segment (or piece) ``p`` (a :class:`~mi_tetvr.render.cursor.Piece`)
    in a derivative mode, walked by ``walker`` (its buffers ``ts``, detached,
    and ``ts_ad``, attached; its scatter strategy ``reduce``); ``acc`` holds
    what lies in front (``L, T``), the rays' ``adj`` and the ``pending``
    gradients (:func:`start`).

    ``p.cur`` is the entry crossing ``(t, a)`` with the entry face as the walk
    carried it into the step ``p.st``, ``(p.t1, p.a1)`` the exit crossing.
    Returns ``(C_seg, T_seg, adj, pending)``: the segment's emission and
    transmittance (as the primal computes them), the adjoint with this
    segment's tangent added (forward mode), and the pending gradients moved
    one crossing on (backward mode: the entry crossing's gradient is
    complete and goes to the entry face's corners; the corner the apex
    replaces is scattered).

    A model that cuts tets into pieces (``model.cuts``) ends a piece ``p.f``
    of the way to the tet's exit crossing where ``p.stay`` (the walk stays
    in the tet). A piece's ends are then fixed blends of the tet's entry and
    exit crossings (the cut points are constants: the integral of a
    continuous integrand does not change where it is split), so their
    gradients go to both crossings, and the tet's entry crossing is complete
    when the walk leaves the tet.
    """
    backward = deriv.backward
    ts, ts_ad = walker.ts, walker.ts_ad
    model = ts.model
    cuts = model.cuts
    carry, st, tet = p.cur.carry, p.st, p.cur.tet
    pending = acc.pending
    w = None
    if cuts:
        e, e_x, F, pend = pending
        F_end = dr.select(p.stay, F + (1.0 - F) * p.f, 1.0)
    else:
        e, pend, w = pending
    extra = (tet,) if model.per_tet else ()
    adj = acc.adj

    def g_tau(C):
        # The inversion's seeds: d L_pix = T dC - R dtau, d alpha = T_fin dtau.
        return adj.dalpha * adj.T_fin - dr.dot(adj.dL, adj.L_pix - (acc.L + acc.T * C))
    closed = None
    if dr.hint(backward, mode="scalar"):
        # The segment's and its clip's derivatives in closed form, where the
        # model has one.
        length, b0, b1, clip_back = clip_segment_vjp(p.cur.t, p.cur.a, p.t1, p.a1, span.begin,
                                                     span.end)
        closed = model.segment_adjoint(ts_ad.params, length, b0, b1, acc.T * adj.dL, g_tau,
                                       *extra)
    if dr.hint(closed is not None, mode="scalar"):
        C_seg, T_seg, g_len, g_b0, g_b1 = closed
        g_t0, g_a0, g_t1, g_a1 = clip_back(g_len, g_b0, g_b1)
        g_entry, g_exit = (g_t0, g_a0), (g_t1, g_a1)
    else:
        with dr.resume_grad():
            x = tree_copy(((p.cur.t, p.cur.a), (p.t1, p.a1)))
            # The crossings' ray parameters matter only when vertices move.
            dr.enable_grad(x if deriv.geometric(ts_ad) else (x[0][1], x[1][1]))
            if dr.hint(not backward, mode="scalar"):
                x_t = tangent(deriv, ts_ad, st.exit, fr, active)
                dr.set_grad(x, (tree_lerp(e, x_t, F), tree_lerp(e, x_t, F_end)) if cuts
                            else (e, x_t))
            (t0, a0), (t1, a1) = x
            length, b0, b1 = clip_segment(t0, a0, t1, a1, span.begin, span.end)
            C_d, T_d, tau = model.segment(ts_ad.params, length, b0, b1, *extra)
            C_seg = dr.detach(C_d)
            T_seg = dr.detach(T_d)
            adj = inversion(deriv, acc.adj, acc.L, acc.T, C_seg, C_d, tau)
            if dr.hint(backward, mode="scalar"):
                g_entry, g_exit = dr.grad(x)
    if dr.hint(not backward, mode="scalar"):
        if cuts:
            return C_seg, T_seg, adj, (tree_select(p.stay, e, x_t), e_x,
                                       dr.select(p.stay, F_end, 0.0), pend)
        return C_seg, T_seg, adj, (x_t, pend, st.w)
    advance = ~p.stay if cuts else True
    if dr.hint(cuts, mode="scalar"):
        e = tree_add(e, tree_add(_scaled(g_entry, 1.0 - F), _scaled(g_exit, 1.0 - F_end)))
        e_x = tree_add(e_x, tree_add(_scaled(g_entry, F), _scaled(g_exit, F_end)))
        g_entry = None
    vg = crossing_grads(deriv, ts_ad, carry, e if cuts else tree_add(e, g_entry), fr, w)
    if deriv.camera:
        adj = camera_grads(adj, carry, vg, fr, active & advance)
    G = vertex_grad_type(model)
    pend = [tree_add(pend[j], vg[j]) for j in range(3)]
    # The corner the apex replaces is complete: scatter it, start afresh.
    ids = [c.i for c in carry[0]]
    replaced = st.slot
    drop = dr.select(replaced[0], ids[0], dr.select(replaced[1], ids[1], ids[2]))
    drop_g = tree_select(replaced[0], pend[0], tree_select(replaced[1], pend[1], pend[2]))
    walker.sums.add(drop, drop_g, active & advance)
    new_pend = tuple(tree_select(replaced[j], dr.zeros(G), pend[j]) for j in range(3))
    if dr.hint(not cuts, mode="scalar"):
        return C_seg, T_seg, adj, (g_exit, new_pend, st.w)
    # Staying in the tet: nothing moves on yet.
    new_pend = tuple(tree_select(advance, new_pend[j], old) for j, old in
                     enumerate(pending[3]))
    zero = _scaled(e_x, 0.0)
    return C_seg, T_seg, adj, (tree_select(advance, e_x, e), tree_select(advance, zero, e_x),
                               dr.select(advance, 0.0, F_end), new_pend)


def finish(deriv: Derivative, walker: EmissionDerivative, acc: Radiance, carry: tuple,
           walked: mi.Bool, fr: RayFrame,
           exit_face: tuple[tuple, mi.Bool] | None = None) -> Adjoint:
    """Backward mode, after the walk: the last exit crossing's gradient and
    the pending ones of its corners (``carry``: the face the walk left by;
    ``walked``: the rays that integrated at least one segment or piece);
    returns ``acc.adj`` (with the camera's gradients).
    A model that cuts tets may have stopped inside one: then ``carry`` is
    that tet's entry face, and ``exit_face = (exit_carry, inside)`` the
    tet's exit face, which takes the exit crossing's gradient so far where
    ``inside``."""
    ts_ad, adj = walker.ts_ad, acc.adj
    w = None
    if ts_ad.model.cuts:
        e, e_x, _, pend = acc.pending
    else:
        e, pend, w = acc.pending
    camera = deriv.camera
    vg = crossing_grads(deriv, ts_ad, carry, e, fr, w)
    if camera:
        adj = camera_grads(adj, carry, vg, fr, walked)
    for j in range(3):
        walker.sums.add(carry[0][j].i, tree_add(pend[j], vg[j]), walked)
    if exit_face is not None:
        exit_carry, inside = exit_face
        vg = crossing_grads(deriv, ts_ad, exit_carry, e_x, fr)
        if camera:
            adj = camera_grads(adj, exit_carry, vg, fr, inside)
        for j in range(3):
            walker.sums.add(exit_carry[0][j].i, vg[j], inside)
    return adj
