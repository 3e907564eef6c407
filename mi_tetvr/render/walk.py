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

The walk knows nothing of what a vertex carries: an optical model
(:mod:`mi_tetvr.render.optical`) interpolates the vertex values at each
crossing and integrates each segment. A model whose values map to color and
extinction nonlinearly (a scalar and a transfer function) sets ``cuts``: the
walk then ends a piece where the model's :meth:`cut` says and stays in the
tet for the next piece. The derivative modes re-walk the rays
(:mod:`mi_tetvr.render.adjoint`), recording nothing.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_tetvr.render import adjoint
from mi_tetvr.render.buffers import unpack_link
from mi_tetvr.render.geometry import crossing_at, entry_carry, face_entry, ray_frame, walk_step
from mi_tetvr.render.probes import Probe
from mi_tetvr.render.pytree import tree_copy, tree_lerp, tree_select, weighted_sum
from mi_tetvr.render.segment import clip_segment


class WalkSettings:
    """Python-level settings of the walk (not traced).

    ``reduce`` is the scatter strategy (``dr.ReduceMode``) of the gradient
    accumulation into shared vertices: ``Auto`` expands the gradient buffers
    per CPU thread on the LLVM backend (no atomics; up to
    ``dr.expand_threshold()`` entries) and uses atomics on CUDA.
    """

    def __init__(self, t_min=1e-4, max_steps=100_000, retrace_eps=1e-5,
                 reduce=dr.ReduceMode.Auto):
        self.t_min = float(t_min)
        self.max_steps = int(max_steps)
        self.retrace_eps = float(retrace_eps)
        self.reduce = reduce


@dr.syntax
def locate(buf, tet, f_out, o, u, v, d, t_start, max_steps: int, active):
    """Walk back from the boundary face ``f_out`` of ``tet`` (where the ray
    leaves a mesh) along the reversed ray to the tet that contains the point
    at ``t_start``.

    Returns ``(tet, f_in)``: the tet and the face through which the forward
    ray enters it (at or before ``t_start``; after it when the reversed ray
    left the mesh first).
    """
    tet = mi.UInt32(tet)
    f_in = mi.UInt32(f_out)
    steps = mi.UInt32(0)
    active = mi.Bool(active)
    while dr.hint(active, label="tetvr_locate"):
        # The reversed ray in the mirrored frame: its parameter is -t.
        st = walk_step(buf, tet, f_in, o, u, -v, -d, active)
        found = -st.t <= t_start
        f_in = mi.UInt32(st.f_out)
        go = ~found & (st.link >= 0)
        nxt_tet, nxt_f = unpack_link(st.link)
        tet = dr.select(go, nxt_tet, tet)
        f_in = dr.select(go, nxt_f, f_in)
        steps += 1
        active &= go & (steps < max_steps)
    return tet, f_in


def enter(buf, face, o, u, v, d, t_start, max_steps: int, active):
    """Where a ray that hits the boundary face ``face`` (global index, from
    Mitsuba's ray tracer) walks from: ``(tet, f_in, outward)``. A ray that
    enters through the face starts in the tet behind it; one that leaves
    through it (``outward``) is inside the mesh at ``t_start`` and is
    :func:`locate` d there."""
    tet, f, outward = face_entry(buf, face, o, u, v, d, active)
    tet, f = locate(buf, tet, f, o, u, v, d, t_start, max_steps, active & outward)
    return tet, f, outward


@dr.syntax
def walk(ts, tet, f_in, L, T, o, u, v, d, t_begin, t_stop, settings: WalkSettings, active,
         deriv: adjoint.Derivative = None, ts_ad=None, adj: adjoint.Adjoint = None):
    """Walk front to back from ``tet`` (entered through its local face
    ``f_in``), integrating over ``[t_begin, t_stop]``, until the ray leaves
    the mesh, reaches ``t_stop`` or becomes nearly opaque.

    ``ts`` is the :class:`~mi_tetvr.render.buffers.TetScene` (detached in
    the derivative modes); a derivative pass gives its context ``deriv``,
    ``ts_ad`` (``ts`` attached to the parameters' AD graph) and the rays'
    ``adj``. ``L, T`` are the emission and transmittance accumulated in
    front; returns their updated values, where the walk ended, the number of
    tets crossed and (forward mode) the updated ``adj``.
    """
    primal = deriv is None
    backward = not primal and deriv.backward
    buf, model, params = ts.buf, ts.model, ts.params
    probe = isinstance(model, Probe)
    tet = mi.UInt32(tet)
    f_in = mi.UInt32(f_in)
    L = tree_copy(L)           # (Color3f, or a probe's accumulator)
    T = mi.Float(T)
    active = mi.Bool(active)

    def gather(i, active):
        return model.gather(params, i, active)

    # The entry face's corners and attributes; each step reads only its apex.
    carry = entry_carry(buf, tet, f_in, o, u, v, d, active, gather)
    entry_ids = tuple(c.i for c in carry[0])
    t, w = crossing_at(carry[0], carry[2])
    a = weighted_sum(w, carry[1])
    steps = mi.UInt32(0)
    pending = None
    if dr.hint(not primal, mode="scalar"):
        pending = adjoint.start(deriv, ts_ad, entry_ids, o, u, v, d, active)
    cuts = model.cuts
    pieces = mi.UInt32(0)
    stay = mi.Bool(False)     # (models that cut tets) the last piece ended inside its tet
    while dr.hint(active, label="tetvr_walk"):
        st = walk_step(buf, tet, f_in, o, u, v, d, active, carry, gather)
        a_out = weighted_sum(st.w, st.carry[1])
        t_out = dr.maximum(st.t, t)
        stay = mi.Bool(False)
        if dr.hint(cuts, mode="scalar"):
            # The model's nonlinearity: end the piece at the next knot.
            f = model.cut(a, a_out)
            stay = f < 1.0
            t_out = dr.select(stay, dr.lerp(t, t_out, f), t_out)
            a_out = tree_select(stay, tree_lerp(a, a_out, f), a_out)
        if dr.hint(probe, mode="scalar"):
            # (a probe picks: the ray goes on, T = 1, until it stops, T = 0)
            length, a0, a1 = clip_segment(t, a, t_out, a_out, t_begin, t_stop)
            L, stop = model.visit(params, L, length, a0, a1, tet)
            T = dr.select(stop, 0.0, T)
        elif dr.hint(primal, mode="scalar"):
            length, a0, a1 = clip_segment(t, a, t_out, a_out, t_begin, t_stop)
            C_seg, T_seg, _ = model.segment(params, length, a0, a1,
                                            *((tet,) if model.per_tet else ()))
        else:
            C_seg, T_seg, adj, pending = adjoint.segment(
                deriv, ts, ts_ad, st, carry, (t, a), (t_out, a_out), L, T, t_begin, t_stop,
                adj, pending, o, u, v, d, active, settings.reduce, *((stay, f) if cuts else ()),
                tet=tet)
        if dr.hint(not probe, mode="scalar"):
            L = L + T * C_seg
            T = T * T_seg
        t = t_out
        a = a_out
        if dr.hint(cuts, mode="scalar"):
            # Stay in the tet for the next piece, else move on.
            carry = tree_select(stay, carry, st.carry)
            nxt_tet, nxt_f = unpack_link(st.link)
            tet = dr.select(stay, tet, nxt_tet)
            f_in = dr.select(stay, f_in, nxt_f)
            steps += dr.select(stay, 0, 1)
            pieces += 1
            active &= (stay | (st.link >= 0)) & (t_out < t_stop) & (pieces < settings.max_steps)
        else:
            carry = st.carry
            steps += 1
            tet, f_in = unpack_link(st.link)
            active &= (st.link >= 0) & (t_out < t_stop) & (steps < settings.max_steps)
        active &= T > settings.t_min
    if dr.hint(backward, mode="scalar"):
        exit_carry = None
        if dr.hint(cuts, mode="scalar"):
            # Stopped inside a tet (early termination): its exit face.
            exit_carry = walk_step(buf, tet, f_in, o, u, v, d, stay, carry, gather).carry
        # (a walk that stopped inside its first tet left none: count its pieces)
        walked = (pieces > 0) if cuts else (steps > 0)
        adj = adjoint.finish(deriv, ts_ad, pending, carry, walked, u, v, d, settings.reduce, adj,
                             exit_carry, stay)
    return L, T, t, steps, adj


@dr.syntax
def trace(scene, ts, ray, settings: WalkSettings, active, t_start=0.0,
          deriv: adjoint.Derivative = None, adj: adjoint.Adjoint = None, t_enter=None):
    """Emission and transmittance along rays through the tet meshes.

    Parameters
    ----------
    scene : mi.Scene
        Its shapes must be exactly the tet meshes of ``ts`` (their boundaries).
    ts : mi_tetvr.render.buffers.TetScene, or a list of them
        One per group of shapes that one walk renders (an optical model:
        :func:`~mi_tetvr.render.buffers.model_groups`). Each boundary hit is
        walked in its own group's mesh.
    ray : mi.Ray3f
        Normalized direction; ``ray.maxt`` bounds the integral.
    t_start : float or mi.Float
        Where the integral starts along the ray (a clip, :mod:`mi_tetvr.render.clipping`).
    deriv : adjoint.Derivative, optional
        A derivative pass's context (its ``scenes`` pair with ``ts``), with
        the rays' adjoint ``adj``.
    t_enter : float or mi.Float, optional
        Where the search for the mesh's boundary starts, before ``t_start``
        (default: at it). A block of a partitioned mesh integrates from
        inside its piece: entered through the piece's near side, its walk
        does not have to walk back from the far side to the start point.

    Returns
    -------
    (Color3f, Float, UInt32, Adjoint)
        Accumulated emission ``C``, transmittance ``T`` (pixel = C + T bg),
        the number of tets crossed, and ``adj`` (forward mode: with the
        tangents accumulated).
    """
    groups = list(ts) if isinstance(ts, (list, tuple)) else [ts]
    groups_ad = deriv.scenes if deriv is not None else [None] * len(groups)
    o = mi.Point3f(ray.o)
    d = mi.Vector3f(ray.d)
    t_max = mi.Float(ray.maxt)
    u, v = ray_frame(d)
    model = groups[0].model
    L = model.start() if isinstance(model, Probe) else mi.Color3f(0.0)
    T = mi.Float(1.0)
    steps = mi.UInt32(0)
    start = mi.Float(t_start if t_enter is None else t_enter)
    active = mi.Bool(active)
    while dr.hint(active, label="tetvr_trace"):
        si = scene.ray_intersect_preliminary(mi.Ray3f(o + d * start, d, t_max - start),
                                             active=active)
        hit = active & si.is_valid()
        t_end = mi.Float(start)
        for g, g_ad in zip(groups, groups_ad):
            # The hit face's own group walks it (all of them with one group).
            mine = hit if len(groups) == 1 else hit & g.owns(si)
            tet, f, _ = enter(g.buf, g.boundary_face(si), o, u, v, d, start, settings.max_steps,
                              mine)
            t_begin = start if t_enter is None else dr.maximum(start, t_start)
            L, T, t_g, n, adj = walk(g, tet, f, L, T, o, u, v, d, t_begin, t_max, settings,
                                     mine, deriv, g_ad, adj)
            t_end = dr.select(mine, t_g, t_end)
            steps += dr.select(mine, n, 0)
        start = dr.maximum(t_end, start) + settings.retrace_eps
        active = hit & (T > settings.t_min) & (start < t_max)
    return L, T, steps, adj
