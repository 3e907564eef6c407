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
differentiating the segment integral (:mod:`mi_tetvr.kernels`) and the face
crossings with Dr.Jit's AD *locally* inside the loop body; the gathers'
reverse-mode derivative scatter-adds straight into the parameters' gradients.
Memory is therefore O(rays), independent of the number of tets crossed.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .kernels import (_PERM, clip_segment, face_entry, face_point, ray_frame,
                      segment_integral, tet_face, walk_step)


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
    """
    primal = mode == dr.ADMode.Primal
    perm = mi.UInt32(_PERM)
    tet = mi.UInt32(tet)
    f_in = mi.UInt32(f_in)
    L = mi.Color3f(L)
    T = mi.Float(T)
    active = mi.Bool(active)
    t, c, s = face_point(buf, tet_face(buf, perm, tet, f_in, active)[1:], o, u, v, d, active)
    steps = mi.UInt32(0)
    while dr.hint(active, label="tetvr_walk"):
        st = walk_step(buf, perm, tet, f_in, o, u, v, d, active)
        t_out = dr.maximum(st.t, t)
        seg = clip_segment(t, c, s, t_out, st.c, st.s, t_begin, t_stop)
        C_seg, T_seg = segment_integral(*seg, n_sub=settings.n_sub)
        if dr.hint(not primal, mode="scalar"):
            # Radiance reaching the pixel from behind this segment.
            R = adj.L_pix - (L + T * C_seg)
            with dr.resume_grad():
                # The segment again, as a differentiable function of its four
                # vertices (the entry and exit faces).
                r = settings.reduce
                ta, ca, sa = face_point(buf_ad, st.entry, o, u, v, d, active, r)
                tb, cb, sb = face_point(buf_ad, st.exit, o, u, v, d, active, r)
                length, c0, c1, s0, s1 = clip_segment(ta, ca, sa, dr.maximum(tb, ta), cb, sb,
                                                      t_begin, t_stop)
                C_d, _ = segment_integral(length, c0, c1, s0, s1, settings.n_sub)
                tau = length * (s0 + s1) * 0.5  # the midpoint sums, exact
                Lo = T * C_d - tau * R
                Lo_alpha = tau * adj.T_fin
                if dr.hint(mode == dr.ADMode.Backward, mode="scalar"):
                    dr.backward_from(dr.dot(adj.dL, Lo) + adj.dalpha * Lo_alpha)
                else:
                    dLo, dLo_alpha = dr.forward_to(Lo, Lo_alpha)
                    adj.dL += dLo
                    adj.dalpha += dLo_alpha
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
