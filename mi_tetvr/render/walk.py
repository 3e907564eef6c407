"""Ray traversal of tet meshes: entry through the boundary, the tet walk,
re-entry, a start point inside a mesh, and the derivative modes.

For each ray, repeat from ``start = 0``:

1. Mitsuba's ray tracer (its BVH over the meshes' boundary faces) finds the
   next boundary face after ``start``.
2. If the ray *enters* through it, the walk starts in the tet behind it. If
   the ray *leaves* through it, the point at ``start`` is inside a mesh (a
   camera inside, or just past a seam of coincident but unconnected faces):
   :func:`locate` walks back from that face along the reversed ray to the tet
   containing the start point (point location by walking, Aman et al.
   Sec. 4.2).
3. :func:`walk` goes front to back, tet to tet through the neighbour links,
   integrating each segment (clipped to ``[start, ray.maxt]``), until the ray
   leaves the mesh or is nearly opaque; then ``start`` moves just past the
   exit face and the loop traces again (non-convex meshes, disjoint parts,
   several meshes).

Derivatives (the inversion trick)
---------------------------------
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
gradient stays at float precision. ``dC_k`` and ``dtau_k`` are obtained by
differentiating the segment integral (:mod:`mi_tetvr.render.segment`) and the face
crossings with Dr.Jit's AD *locally* inside the loop body; the gathers'
reverse-mode derivative scatter-adds straight into the parameters' gradients.
Memory is therefore O(rays), independent of the number of tets crossed.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_tetvr.render.geometry import (_PERM, crossing, face_entry, face_point, project, ray_frame,
                                     tet_face, walk_step)
from mi_tetvr.render.segment import clip_segment, segment_integral


class WalkSettings:
    """Python-level settings of the walk (not traced).

    ``reduce`` is the scatter strategy (``dr.ReduceMode``) of the gradient
    accumulation into shared vertices: ``Auto`` expands the gradient buffers
    per CPU thread on the LLVM backend (no atomics; up to
    ``dr.expand_threshold()`` entries) and uses atomics on CUDA.
    """

    def __init__(self, n_sub=8, t_min=1e-4, max_steps=100_000, retrace_eps=1e-5,
                 reduce=dr.ReduceMode.Auto):
        self.n_sub = int(n_sub)
        self.t_min = float(t_min)
        self.max_steps = int(max_steps)
        self.retrace_eps = float(retrace_eps)
        self.reduce = reduce


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


def boundary_face_index(si, shapes, face_offsets):
    """Global boundary face index of a preliminary intersection."""
    if len(shapes) == 1:
        return mi.UInt32(si.prim_index)
    idx = mi.UInt32(si.prim_index)
    off = mi.UInt32(0)
    for shape, offset in zip(shapes, face_offsets):
        off = dr.select(si.shape == mi.ShapePtr(shape), offset, off)
    return idx + off


@dr.syntax
def locate(buf, tet, f_out, o, u, v, d, t_start, max_steps: int, active):
    """Walk back from the boundary face ``f_out`` of ``tet`` (where the ray
    leaves a mesh) along the reversed ray to the tet that contains the point
    at ``t_start``.

    Returns ``(tet, f_in)``: the tet and the face through which the forward
    ray enters it (at or before ``t_start``; after it when the reversed ray
    left the mesh first).
    """
    perm = mi.UInt32(_PERM)
    tet = mi.UInt32(tet)
    f_in = mi.UInt32(f_out)
    steps = mi.UInt32(0)
    active = mi.Bool(active)
    while dr.hint(active, label="tetvr_locate"):
        # The reversed ray in the mirrored frame: its parameter is -t.
        st = walk_step(buf, perm, tet, f_in, o, u, -v, -d, active)
        found = -st.t <= t_start
        f_in = mi.UInt32(st.f_out)
        go = ~found & (st.nbr >= 0)
        tet = dr.select(go, mi.UInt32(st.nbr >> 2), tet)
        f_in = dr.select(go, mi.UInt32(st.nbr & 3), f_in)
        steps += 1
        active &= go & (steps < max_steps)
    return tet, f_in


def _vertex_grads(buf, ids, g, o, u, v, d, active):
    """Gradient of ``g . (t, c, s)`` of the ray's crossing of the triangle
    ``ids`` w.r.t. each vertex's position, color and opacity (local AD)."""
    with dr.resume_grad():
        P = [buf.position(i, active) for i in ids]
        A = [buf.attributes(i, active) for i in ids]
        dr.enable_grad(P, A)
        p = tuple(project(Pi, o, u, v) for Pi in P)
        t, w = crossing(ids, tuple(P), p, o, d)
        c = w[0] * A[0][0] + w[1] * A[1][0] + w[2] * A[2][0]
        s = w[0] * A[0][1] + w[1] * A[1][1] + w[2] * A[2][1]
        dr.backward_from(t * g[0] + dr.dot(c, g[1]) + s * g[2])
        return [VertexGrad(dr.grad(P[j]), *dr.grad(A[j])) for j in range(3)]


class VertexGrad:
    """Pending gradient of one vertex's position, color and opacity."""
    DRJIT_STRUCT = {"p": mi.Vector3f, "c": mi.Color3f, "s": mi.Float}

    def __init__(self, p=None, c=None, s=None):
        self.p = None if p is None else mi.Vector3f(p)
        self.c = None if c is None else mi.Color3f(c)
        self.s = None if s is None else mi.Float(s)

    @staticmethod
    def zero():
        return VertexGrad(mi.Vector3f(0.0), mi.Color3f(0.0), mi.Float(0.0))


def _add(a: VertexGrad, b: VertexGrad):
    return VertexGrad(a.p + b.p, a.c + b.c, a.s + b.s)


def _scatter(buf_ad, i, g: VertexGrad, active, reduce):
    """Add ``g`` to the parameter gradients of vertex ``i`` (through the
    reverse-mode derivative of a gather: a scatter-add in ``reduce`` mode)."""
    with dr.resume_grad():
        P = buf_ad.position(i, active, reduce)
        c, s = buf_ad.attributes(i, active, reduce)
        dr.backward_from(dr.dot(P, g.p) + dr.dot(c, g.c) + s * g.s,
                         flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)


def _tangent(buf_ad, ids, o, u, v, d, active):
    """Forward mode: the tangent of a face crossing's ``(t, c, s)``."""
    with dr.resume_grad():
        return dr.forward_to(*face_point(buf_ad, ids, o, u, v, d, active))


@dr.syntax
def walk(mode, buf, tet, f_in, L, T, o, u, v, d, t_begin, t_stop,
         settings: WalkSettings, active, adj: Adjoint = None, buf_ad=None):
    """Walk front to back from ``tet`` (entered through its local face
    ``f_in``), integrating over ``[t_begin, t_stop]``, until the ray leaves
    the mesh, reaches ``t_stop`` or becomes nearly opaque.

    ``L, T`` are the emission and transmittance accumulated in front; returns
    their updated values, where the walk ended, the number of tets crossed and
    (forward mode) the updated ``adj``. ``buf_ad``: the buffers attached to
    the parameters' AD graph (derivative modes; ``buf`` may be detached).

    Derivative modes: each segment is a function of the ``(t, c, s)`` of its
    entry and exit crossings; its local derivatives come from Dr.Jit's AD on
    just the clipped segment integral. A crossing is shared by two consecutive
    segments, so its gradient is complete one step later; it then goes to the
    crossed face's three vertices. Consecutive faces share two vertices, so
    reverse mode keeps the gradients of the current face's vertices in
    registers and scatter-adds a vertex only when the walk leaves it behind:
    one vertex (7 values) per step instead of three, the rest after the loop.
    Forward mode carries the exit crossing's tangent over as the next entry's.
    """
    primal = mode == dr.ADMode.Primal
    backward = mode == dr.ADMode.Backward
    perm = mi.UInt32(_PERM)
    tet = mi.UInt32(tet)
    f_in = mi.UInt32(f_in)
    L = mi.Color3f(L)
    T = mi.Float(T)
    active = mi.Bool(active)
    entry_ids = tet_face(buf, perm, tet, f_in, active)[1:]
    t, c, s = face_point(buf, entry_ids, o, u, v, d, active)
    steps = mi.UInt32(0)
    # Gradient (backward) or tangent (forward) of the entry crossing.
    e_t, e_c, e_s = mi.Float(0.0), mi.Color3f(0.0), mi.Float(0.0)
    win = list(entry_ids)  # the entry face's vertices and their pending gradients
    win_g = [VertexGrad.zero() for _ in range(3)]
    if dr.hint(not primal and not backward, mode="scalar"):
        e_t, e_c, e_s = _tangent(buf_ad, entry_ids, o, u, v, d, active)
    while dr.hint(active, label="tetvr_walk"):
        st = walk_step(buf, perm, tet, f_in, o, u, v, d, active)
        t_out = dr.maximum(st.t, t)
        if dr.hint(primal, mode="scalar"):
            seg = clip_segment(t, c, s, t_out, st.c, st.s, t_begin, t_stop)
            C_seg, T_seg = segment_integral(*seg, n_sub=settings.n_sub)
        else:
            with dr.resume_grad():
                x = (mi.Float(t), mi.Color3f(c), mi.Float(s),
                     mi.Float(t_out), mi.Color3f(st.c), mi.Float(st.s))
                dr.enable_grad(x)
                if dr.hint(not backward, mode="scalar"):
                    x_t = _tangent(buf_ad, st.exit, o, u, v, d, active)
                    dr.set_grad(x, (e_t, e_c, e_s, *x_t))
                length, c0, c1, s0, s1 = clip_segment(*x, t_begin, t_stop)
                C_d, T_d = segment_integral(length, c0, c1, s0, s1, settings.n_sub)
                C_seg = dr.detach(C_d)
                T_seg = dr.detach(T_d)
                # Radiance reaching the pixel from behind this segment.
                R = adj.L_pix - (L + T * C_seg)
                tau = length * (s0 + s1) * 0.5  # the midpoint sums, exact
                Lo = T * C_d - tau * R
                Lo_alpha = tau * adj.T_fin
                if dr.hint(backward, mode="scalar"):
                    dr.backward_from(dr.dot(adj.dL, Lo) + adj.dalpha * Lo_alpha)
                    g = dr.grad(x)
                else:
                    dLo, dLo_alpha = dr.forward_to(Lo, Lo_alpha)
                    adj.dL += dLo
                    adj.dalpha += dLo_alpha
            if dr.hint(backward, mode="scalar"):
                vg = _vertex_grads(buf, st.entry, (e_t + g[0], e_c + g[1], e_s + g[2]),
                                   o, u, v, d, active)
                e_t, e_c, e_s = mi.Float(g[3]), mi.Color3f(g[4]), mi.Float(g[5])
                # Into the window (the entry face is the window's vertex set),
                # then scatter the vertex the exit face leaves behind.
                ik, ix, iy = st.exit
                drop = mi.UInt32(0)
                drop_g = VertexGrad.zero()
                new_win, new_g = [], []
                for j in range(3):
                    gj = win_g[j]
                    for m in range(3):
                        gj = dr.select(win[j] == st.entry[m], _add(gj, vg[m]), gj)
                    out = (win[j] != ix) & (win[j] != iy)
                    drop = dr.select(out, win[j], drop)
                    drop_g = dr.select(out, gj, drop_g)
                    new_g.append(dr.select(out, VertexGrad.zero(), gj))
                    new_win.append(dr.select(out, ik, win[j]))
                win, win_g = new_win, new_g
                _scatter(buf_ad, drop, drop_g, active, settings.reduce)
            else:
                e_t, e_c, e_s = x_t
        L += T * C_seg
        T *= T_seg
        t = t_out
        c = mi.Color3f(st.c)
        s = mi.Float(st.s)
        steps += 1
        tet = mi.UInt32(st.nbr >> 2)
        f_in = mi.UInt32(st.nbr & 3)
        active &= (st.nbr >= 0) & (t_out < t_stop) & (steps < settings.max_steps)
        active &= T > settings.t_min
    if dr.hint(backward, mode="scalar"):
        # The last exit crossing, and the vertices still in the window.
        walked = steps > 0
        vg = _vertex_grads(buf, win, (e_t, e_c, e_s), o, u, v, d, walked)
        for j in range(3):
            _scatter(buf_ad, win[j], _add(win_g[j], vg[j]), walked, settings.reduce)
    return L, T, t, steps, adj


@dr.syntax
def trace(mode, scene, buf, shapes, face_offsets, ray, settings: WalkSettings, active,
          adj: Adjoint = None, buf_ad=None):
    """Emission and transmittance along rays through the tet meshes.

    Parameters
    ----------
    mode : dr.ADMode
        ``Primal``, or ``Backward`` / ``Forward`` with ``adj`` and ``buf_ad``
        (the parameter buffers attached to the AD graph) set.
    scene : mi.Scene
        Its shapes must be exactly ``shapes`` (the tet meshes' boundaries).
    buf : MeshBuffers
    shapes : list of tetmesh shapes, face_offsets : list of int
        For mapping Mitsuba's intersections to global boundary faces.
    ray : mi.Ray3f
        Normalized direction; ``ray.maxt`` bounds the integral.

    Returns
    -------
    (Color3f, Float, UInt32, Adjoint)
        Accumulated emission ``C``, transmittance ``T`` (pixel = C + T bg),
        the number of tets crossed, and ``adj`` (forward mode: with the
        tangents accumulated).
    """
    o = mi.Point3f(ray.o)
    d = mi.Vector3f(ray.d)
    t_max = mi.Float(ray.maxt)
    u, v = ray_frame(d)
    L = mi.Color3f(0.0)
    T = mi.Float(1.0)
    steps = mi.UInt32(0)
    start = mi.Float(0.0)
    active = mi.Bool(active)
    while dr.hint(active, label="tetvr_trace"):
        si = scene.ray_intersect_preliminary(mi.Ray3f(o + d * start, d, t_max - start),
                                             active=active)
        hit = active & si.is_valid()
        tet, f, outward = face_entry(buf, boundary_face_index(si, shapes, face_offsets),
                                     o, u, v, d, hit)
        # Leaving through the face: the start point is inside; locate it.
        tet, f = locate(buf, tet, f, o, u, v, d, start, settings.max_steps, hit & outward)
        L, T, t_end, n, adj = walk(mode, buf, tet, f, L, T, o, u, v, d, start, t_max,
                                   settings, hit, adj, buf_ad)
        steps += n
        start = dr.maximum(t_end, start) + settings.retrace_eps
        active = hit & (T > settings.t_min) & (start < t_max)
    return L, T, steps, adj
