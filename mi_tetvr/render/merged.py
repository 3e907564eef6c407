"""Tet meshes that overlap in space, integrated as one medium.

Where a ray is inside several meshes at once, their extinctions add and so do
their emissions (each with its own color): the ray is cut at every crossing
of every mesh (and at every knot of a model that cuts, such as a transfer
function's texel centres), and on each piece between two cuts every mesh's
color and extinction are linear, so the piece is integrated as one medium by
:func:`~mi_tetvr.render.segment.merged_integral`. Disjoint and nested meshes
along one ray (enter A, enter B, leave B, leave A) are the same walk.

The walk keeps a *cursor* per mesh: whether the ray is inside it, the tet it
is in and the face it entered through (with the face's corners, as
:func:`~mi_tetvr.render.geometry.walk_step` carries them), or, outside it,
the next boundary face of that mesh along the ray (Mitsuba's ray tracer on a
scene of that mesh alone, so that coincident faces of two meshes are both
found). Each iteration integrates the piece up to the nearest event of any
cursor (the exit of its tet, a knot, or entering its mesh) and moves on the
cursor whose event it is. A ray that starts inside a mesh (a camera inside,
or a first face it leaves by) is located in it by walking back
(:func:`~mi_tetvr.render.cursor.locate`).

Derivatives use the same inversion as the single walk
(:mod:`mi_tetvr.render.adjoint`): the radiance behind each piece is
recovered from the pixel's value, and the piece is differentiated with
Dr.Jit's AD locally, through the gathers of its tets' face vertices (their
reverse mode scatter-adds into the parameters): the optical models'
parameters, vertex positions (through the face crossings; a piece's ends
move only where the ray enters or leaves a mesh) and the camera (every
crossed vertex moved the other way; :func:`_piece_derivative`). Memory stays
O(rays).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from dataclasses import dataclass

from mi_tetvr.render import adjoint
from mi_tetvr.render.buffers import unpack_link
from mi_tetvr.render.cursor import WalkSettings, enter
from mi_tetvr.render.geometry import (RayFrame, corner, crossing_at, entry_carry,
                                      face_crossing, face_entry, walk_step)
from mi_tetvr.render.pytree import tree_lerp, tree_select, weighted_sum
from mi_tetvr.render.segment import merged_integral
from mi_tetvr.render.walk import Radiance

#: Most meshes one merged walk takes (each is a cursor in every iteration).
MAX_MESHES = 8


def overlapping(shapes, rel_eps=1e-6):
    """Whether any two shapes' bounding boxes overlap with a positive volume
    (boxes that only touch, such as blocks sharing an interface, do not)."""
    boxes = [s.bbox() for s in shapes]
    if len(boxes) < 2:
        return False
    lo = [min(b.min[i] for b in boxes) for i in range(3)]
    hi = [max(b.max[i] for b in boxes) for i in range(3)]
    eps = rel_eps * max(max(h - lw for lw, h in zip(lo, hi)), 1e-30)
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            a, b = boxes[i], boxes[j]
            if all(min(a.max[x], b.max[x]) - max(a.min[x], b.min[x]) > eps for x in range(3)):
                return True
    return False


def _check(tss):
    if len(tss) > MAX_MESHES:
        raise ValueError(f"tetvr: at most {MAX_MESHES} overlapping tet meshes in one scene, got "
                         f"{len(tss)}; merge some of them into one mesh")


def _carry_like(ts, fr):
    """A cursor's carry, zero (its structure and types)."""
    return entry_carry(ts.buf, mi.UInt32(0), mi.UInt32(0), fr, mi.Bool(False), _gather(ts))


def _gather(ts):
    return lambda i, active: ts.model.gather(ts.params, i, active)


@dr.syntax
def merged_trace(scenes: list, tss: list, ray: mi.Ray3f, settings: WalkSettings, active,
                 t_start=0.0, grad: tuple = None, n_sub: int = 4):
    """Emission and transmittance along rays through tet meshes that may
    overlap: per mesh a scene of it alone (``scenes``, whose boundary faces
    are traced) and its :class:`~mi_tetvr.render.buffers.TetScene` (``tss``;
    a derivative pass, ``grad = (deriv, adj)``: its context, whose ``deriv.scenes``
    are the same attached to the AD graph, and the rays' adjoint).
    Same results as :func:`~mi_tetvr.render.walk.trace`; pieces are
    integrated with ``2 n_sub`` sub-intervals (the merged integral's error at
    ``2 n`` is about the single medium's at ``n``); the integral starts at
    ``t_start`` (a clip)."""
    _check(tss)
    primal = grad is None
    deriv, adj = (None, None) if primal else grad
    tss_ad = None if primal else deriv.scenes
    K = len(tss)
    fr = RayFrame.of(ray.o, ray.d)
    t_max = mi.Float(ray.maxt)
    active = mi.Bool(active)
    inside = [mi.Bool(False) for _ in range(K)]
    tet = [mi.UInt32(0) for _ in range(K)]
    f_in = [mi.UInt32(0) for _ in range(K)]
    carry = [_carry_like(ts, fr) for ts in tss]
    # Outside a mesh: where to trace its boundary from, and its next face.
    need = [mi.Bool(active) for _ in range(K)]
    t_trace = [mi.Float(t_start) for _ in range(K)]
    t_next = [mi.Float(dr.inf) for _ in range(K)]
    f_next = [mi.UInt32(0) for _ in range(K)]
    # A cursor whose last event was a knot of its own keeps the attributes
    # there (``kept``, ``a_at``): recomputed from t they could fall a hair
    # short of the knot, and the next cut would not move on.
    kept = [mi.Bool(False) for _ in range(K)]
    a_at = [dr.zeros(ts.model.Attributes) for ts in tss]
    # The piece starts where the ray crossed mesh k's boundary (its carried
    # face): that point moves with the boundary (derivative modes).
    from_bnd = [mi.Bool(False) for _ in range(K)]
    geo = not primal and any(deriv.geometric(g) for g in tss_ad)
    L = mi.Color3f(0.0)
    T = mi.Float(1.0)
    t = mi.Float(t_start)
    steps = mi.UInt32(0)
    inf = mi.Float(dr.inf)
    while dr.hint(active, label="tetvr_merged"):
        inside, tet, f_in, carry = list(inside), list(tet), list(f_in), list(carry)
        need, t_trace, t_next, f_next = list(need), list(t_trace), list(t_next), list(f_next)
        kept, a_at, from_bnd = list(kept), list(a_at), list(from_bnd)
        # Each mesh the ray is outside of: its next boundary face, where needed;
        # a face the ray leaves by: it is inside, walk back to where it is now.
        for k in range(K):
            c_k, tet_k, f_k, in_k = carry[k], tet[k], f_in[k], inside[k]
            kept_k, tn_k, fn_k, need_k = kept[k], t_next[k], f_next[k], need[k] & active
            if need_k:
                # (a branch: most iterations trace nothing)
                si = scenes[k].ray_intersect_preliminary(
                    mi.Ray3f(fr.at(t_trace[k]), fr.d, t_max - t_trace[k]), active=need_k)
                hit = need_k & si.is_valid()
                tt, ff, out = enter(tss[k].buf, si.prim_index, fr, t, settings.max_steps, hit)
                here = hit & out
                c_k = tree_select(here, entry_carry(tss[k].buf, tt, ff, fr, here,
                                                    _gather(tss[k])), c_k)
                tet_k = dr.select(here, tt, tet_k)
                f_k = dr.select(here, ff, f_k)
                in_k = in_k | here
                kept_k = kept_k & ~here
                tn_k = dr.select(hit & ~out, t_trace[k] + si.t, inf)
                fn_k = mi.UInt32(si.prim_index)
            carry[k], tet[k], f_in[k], inside[k] = c_k, tet_k, f_k, in_k
            kept[k], t_next[k], f_next[k], need[k] = kept_k, tn_k, fn_k, mi.Bool(False)
        # Every cursor's next event: its tet's exit or a knot inside, or
        # (outside its mesh) its next boundary face.
        sts, ends, nows, knots, evs = [], [], [], [], []
        t_ev = mi.Float(t_max)
        for k in range(K):
            ts = tss[k]
            st = walk_step(ts.buf, tet[k], f_in[k], fr, inside[k], carry[k], _gather(ts))
            te, we = crossing_at(carry[k][0], carry[k][2])
            ae = weighted_sum(we, carry[k][1])
            tx = dr.maximum(st.t, te)
            ax = weighted_sum(st.w, st.carry[1])
            span = tx - te
            inv = dr.select(span > 0, dr.rcp(dr.select(span > 0, span, 1.0)), 0.0)
            a_now = tree_select(kept[k], a_at[k], tree_lerp(ae, ax, dr.clip((t - te) * inv,
                                                                            0.0, 1.0)))
            ev = tx
            knot = (mi.Bool(False), a_now)
            if dr.hint(ts.model.cuts, mode="scalar"):
                f = ts.model.cut(a_now, ax)
                knot = (f < 1.0, tree_lerp(a_now, ax, f))
                ev = dr.select(knot[0], dr.lerp(dr.maximum(t, te), tx, f), tx)
            ev = dr.select(inside[k], ev, t_next[k])
            sts.append(st)
            ends.append((te, we, ae, tx, ax, inv))
            nows.append(a_now)
            knots.append(knot)
            evs.append(ev)
            t_ev = dr.minimum(t_ev, ev)
        t_ev = dr.maximum(t_ev, t)
        # The cursor whose event it is (the first of equal ones) moves on.
        go = []
        moved = mi.Bool(False)
        for k in range(K):
            go.append(active & ~moved & (evs[k] <= t_ev) & (evs[k] < t_max))
            moved |= go[k]
        # The piece [t, t_ev]: every mesh the ray is inside, as one medium
        # (none inside: an empty piece, which may reach to an infinite t_max,
        # whose length times a zero extinction would be NaN).
        any_in = mi.Bool(False)
        for k in range(K):
            any_in |= inside[k]
        t_end = dr.select(any_in, t_ev, t)
        length = t_end - t
        media = []
        for k in range(K):
            te, we, ae, tx, ax, inv = ends[k]
            a1 = tree_select(go[k], tree_select(knots[k][0], knots[k][1], ax),
                             tree_lerp(ae, ax, dr.clip((t_ev - te) * inv, 0.0, 1.0)))
            # (outside its mesh a cursor's tet is stale: past the boundary, no tet)
            lin = tss[k].model.linear(tss[k].params, nows[k], a1,
                                      dr.select(inside[k], tet[k], 0))
            media.append(tuple(dr.select(inside[k], x, 0.0) for x in lin))
            kept[k] = inside[k] & go[k] & knots[k][0]
            a_at[k] = a1
        C_seg, T_seg = merged_integral(length, media, 2 * n_sub)
        if dr.hint(not primal, mode="scalar"):
            # The piece ends where the ray enters or leaves mesh k.
            to_bnd = [go[k] & (~inside[k] | (~knots[k][0] & (sts[k].link < 0)))
                      for k in range(K)]
            adj = _piece_derivative(deriv, Cursors(carry, tet, sts, ends, inside),
                                    MergedPiece(t, t_end, length, C_seg), Radiance(L, T, adj),
                                    (from_bnd, to_bnd, f_next) if geo else None, fr,
                                    settings.reduce, n_sub)
        L += T * C_seg
        T *= T_seg
        for k in range(K):
            ts = tss[k]
            st = sts[k]
            # Inside: the next tet (or the knot, staying); leaving the mesh,
            # trace its boundary again past the exit.
            adv = go[k] & inside[k] & ~knots[k][0]
            nxt_tet, nxt_f = unpack_link(st.link)
            carry[k] = tree_select(adv, st.carry, carry[k])
            tet[k] = dr.select(adv, nxt_tet, tet[k])
            f_in[k] = dr.select(adv, nxt_f, f_in[k])
            left = adv & (st.link < 0)
            inside[k] = inside[k] & ~left
            from_bnd[k] = left
            t_trace[k] = dr.select(left, ends[k][3] + settings.retrace_eps, t_trace[k])
            need[k] = need[k] | left
            # Outside: enter the mesh through its next boundary face.
            entering = go[k] & ~inside[k] & ~left
            c_k, tet_k, f_k = carry[k], tet[k], f_in[k]
            if entering:
                tt, ff, _ = face_entry(ts.buf, f_next[k], fr, entering)
                c_k = entry_carry(ts.buf, tt, ff, fr, entering, _gather(ts))
                tet_k, f_k = tt, ff
            carry[k], tet[k], f_in[k] = c_k, tet_k, f_k
            inside[k] = inside[k] | entering
            kept[k] = kept[k] & ~entering
            from_bnd[k] = from_bnd[k] | entering
            t_next[k] = dr.select(entering, inf, t_next[k])
        t = t_ev
        steps += 1
        pending = mi.Bool(False)
        for k in range(K):
            pending |= inside[k] | need[k] | (t_next[k] < t_max)
        active &= pending & (t < t_max) & (T > settings.t_min) & (steps < settings.max_steps)
    return L, T, steps, adj


@dataclass
class Cursors:
    """The merged walk's cursors, per mesh, at one piece: the carried entry
    faces, tets, the steps that found their exits, the ends of their
    segments (``(t, weights, attributes)`` at entry, exit ``(t,
    attributes)``, ``1 / span``) and whether the ray is inside."""
    carry: list
    tet: list
    st: list
    ends: list
    inside: list


@dataclass
class MergedPiece:
    """A piece ``[t0, t1]`` of the merged walk, its ``length`` and its
    emission ``C_seg`` as the primal computed it."""
    t0: mi.Float
    t1: mi.Float
    length: mi.Float
    C_seg: mi.Color3f


def _piece_derivative(deriv: adjoint.Derivative, cur: Cursors, piece: MergedPiece,
                      acc: Radiance, geo, fr: RayFrame, reduce, n_sub: int):
    """One piece in a derivative mode: its emission and optical depth
    recomputed with the AD graph through the gathers of each mesh's entry
    and exit face vertices, and ``d L_pix = T dC - R dtau`` with ``R`` the
    radiance from behind (:mod:`mi_tetvr.render.adjoint`).

    The piece's ends are fixed ray parameters where the integrand is
    continuous (a tet face or a knot of one mesh: the integral does not
    depend on where it is split), and the crossings of a mesh's boundary
    where it enters or leaves that mesh (``geo = (from_bnd, to_bnd,
    f_next)``, when vertex positions or the camera are differentiated):
    those move with the boundary, and every mesh's attributes at the ends
    follow through their own crossings, recomputed from the positions (and,
    for the camera, from leaf copies of them)."""
    backward = deriv.backward
    tss_ad = deriv.scenes
    carry, tets, sts, ends, inside = cur.carry, cur.tet, cur.st, cur.ends, cur.inside
    length, o, d = piece.length, fr.o, fr.d
    with dr.resume_grad():
        t0, t1 = mi.Float(piece.t0), mi.Float(piece.t1)
        camera = geo is not None and deriv.camera
        moved = []          # (the camera) each corner's mesh, index, mask, leaf position

        def crossing_of(ts, ids, act):
            """A face crossing from the positions (attached); with a camera,
            from leaf copies of the corners' positions, whose gradients are
            moved onto the ray (moving the ray is moving every vertex the
            other way: the single walk's
            :func:`~mi_tetvr.render.adjoint.camera_grads`) and, where the
            positions are differentiated too, into them."""
            if not camera:
                return face_crossing(ts.buf, ids, fr, act, reduce)
            corners = []
            for i in ids:
                P = mi.Point3f(dr.detach(ts.buf.position(i, act)))
                dr.enable_grad(P)
                if not backward:
                    # the ray's tangent (origin, direction) as the vertex's:
                    # -(do + w x (P - o)) with w = d x dd
                    dP = 0.0
                    if deriv.ray_tangent is not None:
                        do, dd = deriv.ray_tangent
                        dP = -(do + dr.cross(dr.cross(d, dd), P - o))
                    if adjoint.moves_vertices(ts):
                        dP = dP + dr.forward_to(ts.buf.position(i, act),
                                                flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
                    dr.set_grad(P, dP)
                moved.append((ts, i, act, P))
                corners.append(corner(i, P, fr))
            return crossing_at(tuple(corners))
        crossings = []
        for k, ts in enumerate(tss_ad):
            te, we, _, tx, _, inv = ends[k]
            st = sts[k]
            ids_e = tuple(c.i for c in carry[k][0])
            if geo is not None:
                from_bnd, to_bnd, f_next = geo
                # (each crossing only where its face exists: the cursor's entry face
                # inside the mesh or where the piece starts on its boundary, its tet's
                # exit face inside it; elsewhere the cursor's faces are stale and their
                # vertex indices may lie outside the mesh)
                te, we = crossing_of(ts, ids_e, inside[k] | from_bnd[k])
                tx, wx = crossing_of(ts, st.exit, inside[k])
                face = tuple(dr.gather(mi.UInt32, ts.buf.faces, f_next[k] * 3 + j,
                                       to_bnd[k]) for j in range(3))
                tn, _ = crossing_of(ts, face, to_bnd[k])
                t0 = dr.select(from_bnd[k], te, t0)
                t1 = dr.select(to_bnd[k], dr.select(inside[k], tx, tn), t1)
                span = tx - te
                inv = dr.select(span > 0, dr.rcp(dr.select(span > 0, span, 1.0)), 0.0)
            else:
                wx = st.w
            a_e = ts.model.interpolate(ts.params, ids_e, we, inside[k], reduce)
            a_x = ts.model.interpolate(ts.params, st.exit, wx, inside[k], reduce)
            crossings.append((te, a_e, a_x, inv))
        if geo is not None:
            length = t1 - t0
        media = []
        tau = mi.Float(0.0)
        for k, ts in enumerate(tss_ad):
            te, a_e, a_x, inv = crossings[k]
            # (not clipped: a cut held at a fixed t reads the tet's linear
            # field there, continued past a face that moved)
            F0 = (t0 - te) * inv
            F1 = (t1 - te) * inv
            lin = ts.model.linear(ts.params, tree_lerp(a_e, a_x, F0), tree_lerp(a_e, a_x, F1),
                                  dr.select(inside[k], tets[k], 0))
            lin = tuple(dr.select(inside[k], x, 0.0) for x in lin)
            media.append(lin)
            tau += length * (lin[2] + lin[3]) * 0.5
        C_d, _ = merged_integral(length, media, 2 * n_sub)
        adj = adjoint.inversion(deriv, acc.adj, acc.L, acc.T, piece.C_seg, C_d, tau)
        if backward:
            for ts, i, act, P in moved:
                # (a corner that is not there has no gradient: zero, not the NaN that a
                # degenerate crossing's derivative times a zero weight may give)
                g = dr.select(act, mi.Vector3f(dr.grad(P)), 0.0)
                adj = adjoint.ray_grads(adj, dr.detach(P) - o, g, True)
                if adjoint.moves_vertices(ts):
                    dr.backward_from(dr.dot(ts.buf.position(i, act, reduce), dr.detach(g)))
    return adj
