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

``dC_k`` and ``dtau_k`` are obtained by differentiating the optical model's
segment integral (:meth:`~mi_tetvr.render.optical.OpticalModel.segment`) and
the face crossings with Dr.Jit's AD *locally* inside the loop body; the
gathers' reverse-mode derivative scatter-adds straight into the parameters'
gradients. Memory is therefore O(rays), independent of the number of tets
crossed.

Each segment is a function of the ``(t, attributes)`` of its entry and exit
crossings. A crossing is shared by two consecutive segments, so its gradient
is complete one step later; it then goes to the crossed face's three
vertices. Consecutive faces share two vertices, so reverse mode keeps the
gradients of the current face's vertices in registers (a *window*) and
scatter-adds a vertex only when the walk leaves it behind: one vertex per
step instead of three, the rest after the loop. Forward mode carries the exit
crossing's tangent over as the next entry's.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_tetvr.render.geometry import crossing, face_crossing, project
from mi_tetvr.render.pytree import tree_add, tree_copy, tree_dot, tree_select, weighted_sum
from mi_tetvr.render.segment import clip_segment


class Adjoint:
    """Per-ray inputs and outputs of the derivative modes.

    L_pix, T_fin : the primal pixel value (with background) and transmittance.
    dL, dalpha : the incoming adjoint (backward mode), or the accumulated
        tangent (forward mode, starting at zero).
    """
    DRJIT_STRUCT = {"L_pix": mi.Color3f, "T_fin": mi.Float, "dL": mi.Color3f,
                    "dalpha": mi.Float}

    def __init__(self, L_pix=None, T_fin=None, dL=None, dalpha=None):
        self.L_pix, self.T_fin, self.dL, self.dalpha = L_pix, T_fin, dL, dalpha


_VERTEX_GRAD_TYPES = {}


def vertex_grad_type(model):
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


def start(mode, ts_ad, entry_ids, o, u, v, d, active):
    """The derivative modes' loop state besides the ray's adjoint, at the
    walk's entry face: ``(e, win, win_g)``.

    ``e`` is the gradient (backward) or tangent (forward) of the current
    entry crossing, ``(t, attributes)``; ``win`` the entry face's vertex ids
    and ``win_g`` their pending gradients (backward mode).
    """
    model = ts_ad.model
    e = (mi.Float(0.0), dr.zeros(model.Attributes))
    if mode == dr.ADMode.Forward:
        e = tangent(ts_ad, entry_ids, o, u, v, d, active)
    G = vertex_grad_type(model)
    return e, list(entry_ids), [dr.zeros(G) for _ in range(3)]


def crossing_grads(ts, ids, g, o, u, v, d, active):
    """Gradient of ``g . (t, attributes)`` of the ray's crossing of the
    triangle ``ids`` w.r.t. each vertex's position and attributes (local AD)."""
    G = vertex_grad_type(ts.model)
    with dr.resume_grad():
        P = [ts.buf.position(i, active) for i in ids]
        A = [ts.model.gather(ts.params, i, active) for i in ids]
        dr.enable_grad(P, A)
        p = tuple(project(Pi, o, u, v) for Pi in P)
        t, w = crossing(ids, tuple(P), p, o, d)
        a = weighted_sum(w, A)
        dr.backward_from(t * g[0] + tree_dot(a, g[1]))
        return [G(dr.grad(P[j]), dr.grad(A[j])) for j in range(3)]


def scatter(ts_ad, i, g, active, reduce):
    """Add the pending gradient ``g`` to the parameter gradients of vertex
    ``i`` (through the reverse-mode derivative of a gather: a scatter-add in
    ``reduce`` mode)."""
    with dr.resume_grad():
        P = ts_ad.buf.position(i, active, reduce)
        a = ts_ad.model.gather(ts_ad.params, i, active, reduce)
        dr.backward_from(dr.dot(P, g.p) + tree_dot(a, g.a),
                         flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)


def tangent(ts_ad, ids, o, u, v, d, active):
    """Forward mode: the tangent of a face crossing's ``(t, attributes)``."""
    with dr.resume_grad():
        t, w = face_crossing(ts_ad.buf, ids, o, u, v, d, active)
        a = ts_ad.model.interpolate(ts_ad.params, ids, w, active)
        # AllowNoGrad: the tangents may all be elsewhere (e.g. the environment's)
        return dr.forward_to(t, a, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)


def segment(mode, ts, ts_ad, st, entry, exit, L, T, t_begin, t_stop, adj, pending,
            o, u, v, d, active, reduce):
    """One segment in a derivative mode.

    ``entry`` and ``exit`` are the ``(t, attributes)`` of the segment's
    crossings, ``st`` the walk step that found the exit, ``L, T`` what lies in
    front. Returns ``(C_seg, T_seg, adj, pending)``: the segment's emission and
    transmittance (as the primal computes them), the adjoint with this
    segment's tangent added (forward mode), and the pending gradients moved
    one crossing on (backward mode: the entry crossing's gradient is complete
    and goes to the window, the vertex the exit face leaves behind is
    scattered).
    """
    backward = mode == dr.ADMode.Backward
    model = ts.model
    e, win, win_g = pending
    with dr.resume_grad():
        x = tree_copy((entry, exit))
        dr.enable_grad(x)
        if dr.hint(not backward, mode="scalar"):
            x_t = tangent(ts_ad, st.exit, o, u, v, d, active)
            dr.set_grad(x, (e, x_t))
        (t0, a0), (t1, a1) = x
        length, b0, b1 = clip_segment(t0, a0, t1, a1, t_begin, t_stop)
        C_d, T_d, tau = model.segment(ts_ad.params, length, b0, b1)
        C_seg = dr.detach(C_d)
        T_seg = dr.detach(T_d)
        # Radiance reaching the pixel from behind this segment.
        R = adj.L_pix - (L + T * C_seg)
        Lo = T * C_d - tau * R
        Lo_alpha = tau * adj.T_fin
        if dr.hint(backward, mode="scalar"):
            dr.backward_from(dr.dot(adj.dL, Lo) + adj.dalpha * Lo_alpha)
            g_entry, g_exit = dr.grad(x)
        else:
            dLo, dLo_alpha = dr.forward_to(Lo, Lo_alpha)
            adj.dL += dLo
            adj.dalpha += dLo_alpha
    if dr.hint(not backward, mode="scalar"):
        return C_seg, T_seg, adj, (x_t, win, win_g)
    vg = crossing_grads(ts, st.entry, tree_add(e, g_entry), o, u, v, d, active)
    # Into the window (the entry face is the window's vertex set), then
    # scatter the vertex the exit face leaves behind.
    G = vertex_grad_type(model)
    drop = mi.UInt32(0)
    drop_g = dr.zeros(G)
    new_win, new_g = [], []
    for j in range(3):
        gj = win_g[j]
        for m in range(3):
            gj = tree_select(win[j] == st.entry[m], tree_add(gj, vg[m]), gj)
        out = (win[j] != st.exit[0]) & (win[j] != st.exit[1]) & (win[j] != st.exit[2])
        drop = dr.select(out, win[j], drop)
        drop_g = tree_select(out, gj, drop_g)
        new_g.append(tree_select(out, dr.zeros(G), gj))
        new_win.append(dr.select(out, st.apex, win[j]))
    scatter(ts_ad, drop, drop_g, active, reduce)
    return C_seg, T_seg, adj, (g_exit, new_win, new_g)


def finish(ts, ts_ad, pending, steps, o, u, v, d, reduce):
    """Backward mode, after the walk: the last exit crossing's gradient and
    the vertices still in the window."""
    e, win, win_g = pending
    walked = steps > 0
    vg = crossing_grads(ts, win, e, o, u, v, d, walked)
    for j in range(3):
        scatter(ts_ad, win[j], tree_add(win_g[j], vg[j]), walked, reduce)
