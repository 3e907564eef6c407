"""The geometry of the tet walk (pure Dr.Jit): the ray frame, the consistent
edge predicate, face crossings, one step through a tet and the entry through
the boundary surface.

Everything here is a function of Dr.Jit arrays only (no Mitsuba scene, no
Python state), so it runs unchanged on ``llvm_ad_rgb`` and ``cuda_ad_rgb``
and can be differentiated by Dr.Jit's AD.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_tetvr.render.buffers import unpack_link

# ----------------------------------------------------------------------------
# Tet-walk step
# ----------------------------------------------------------------------------
#
# The walk is combinatorial, in the 2D frame of the ray (Aman et al., Alg. 1-7):
# every vertex is projected onto the plane orthogonal to the ray through its
# origin, and the side on which the ray passes each edge is the sign of a 2D
# cross product. Each edge's sign is computed from its two vertices in a
# canonical order (lower global index first), so it is bit-identical in every
# tet that shares the edge; exact zeros are broken by symbolically moving the
# ray by (eps, eps^2) (simulation of simplicity). Every ray therefore passes
# on one definite side of every edge: it can't slip between faces, through
# vertices or along edges, and zero-volume tets are crossed like any other.

def project(p, o, u, v):
    """2D coordinates of point ``p`` in the ray frame ``(o; u, v)``."""
    q = p - o
    return mi.Point2f(dr.dot(q, u), dr.dot(q, v))


def edge_function(i, pi, j, pj):
    """Side of the directed edge ``i -> j`` on which the ray passes.

    Parameters
    ----------
    i, j : UInt32
        Global vertex indices (they fix the canonical evaluation order).
    pi, pj : Point2f
        Their projections in the ray frame.

    Returns
    -------
    (Float, Bool)
        The 2D cross product ``pi x pj`` (twice the signed area of the triangle
        (origin, pi, pj)) and its sign with ties broken consistently
        (``True`` = positive: the ray passes to the left of ``i -> j``).
    """
    swap = i > j
    P = dr.select(swap, pj, pi)
    Q = dr.select(swap, pi, pj)
    e = P.x * Q.y - P.y * Q.x
    tie = dr.select(P.y != Q.y, P.y - Q.y, Q.x - P.x)
    pos = dr.select(e != 0, e > 0, tie > 0)
    return dr.select(swap, -e, e), pos ^ swap


def ray_frame(d):
    """Orthonormal ``u, v`` with ``u x v = d``."""
    u, _ = mi.coordinate_system(d)
    return u, dr.cross(d, u)


def face_weights(e_a, e_b, e_c):
    """Barycentric weights of the ray's crossing point in a triangle from the
    three edge functions opposite each vertex (any common sign); degenerate
    (edge-on) triangles get equal weights."""
    s = e_a + e_b + e_c
    ok = dr.abs(s) > 0
    inv = dr.select(ok, dr.rcp(dr.select(ok, s, 1.0)), 0.0)
    wa = dr.maximum(e_a * inv, 0.0)
    wb = dr.maximum(e_b * inv, 0.0)
    wc = dr.maximum(e_c * inv, 0.0)
    n = wa + wb + wc
    ok &= n > 0
    inv_n = dr.select(ok, dr.rcp(dr.select(ok, n, 1.0)), 0.0)
    third = 1.0 / 3.0
    return (dr.select(ok, wa * inv_n, third), dr.select(ok, wb * inv_n, third),
            dr.select(ok, wc * inv_n, third))


def crossing(ids, P, p, o, d):
    """Where the ray crosses the triangle of vertices ``ids`` (global indices),
    given their positions ``P`` and projections ``p`` in the ray frame.

    Returns the ray parameter ``t`` and the barycentric weights. The weights
    come from the same canonical edge functions as the walk's exit test, so a
    face shared by two tets gives the same crossing from both sides.
    """
    (i0, i1, i2), (P0, P1, P2), (p0, p1, p2) = ids, P, p
    e0, _ = edge_function(i1, p1, i2, p2)
    e1, _ = edge_function(i2, p2, i0, p0)
    e2, _ = edge_function(i0, p0, i1, p1)
    w = face_weights(e0, e1, e2)
    return dr.dot(w[0] * P0 + w[1] * P1 + w[2] * P2 - o, d), w


def face_crossing(buf, ids, o, u, v, d, active=True, reduce=dr.ReduceMode.Auto):
    """``(t, w)`` where the ray crosses the triangle ``ids``: gathers the
    vertices (differentiably, when AD is enabled on the buffers)."""
    P = tuple(buf.position(i, active, reduce) for i in ids)
    p = tuple(project(Pi, o, u, v) for Pi in P)
    return crossing(ids, P, p, o, d)


def tet_face(buf, tet, f, active=True):
    """Global vertex indices ``(apex, a, b, c)`` of ``tet`` for its local face
    ``f`` (the apex is the vertex opposite the face; ``a, b, c`` the face)."""
    base = tet * 4
    k = f * 4
    return tuple(dr.gather(mi.UInt32, buf.tets,
                           base + dr.gather(mi.UInt32, buf.face_order, k + j, active), active)
                 for j in range(4))


def _face_corners(buf, face, o, u, v, active):
    ids = tuple(dr.gather(mi.UInt32, buf.faces, face * 3 + j, active) for j in range(3))
    P = tuple(buf.position(i, active) for i in ids)
    return ids, P, tuple(project(Pi, o, u, v) for Pi in P)


#: Steps of the walk over the boundary surface in :func:`face_entry`. The
#: ray tracer reports a face that contains the hit point up to round-off, so
#: the face the walk wants shares a vertex with it; around a vertex of
#: valence k the walk needs at most k/2 steps (4 were too few for fans of
#: front faces around vertices on a sheared box's edges).
BOUNDARY_WALK_STEPS = 8


def face_entry(buf, face, o, u, v, d, active):
    """The tet behind the boundary face a ray hits.

    The face found by Mitsuba's ray tracer is first moved, over the boundary
    surface, to the face that the ray crosses by the walk's own (consistent)
    edge predicate: a ray hitting a vertex or an edge of the boundary must
    start in the tet the walk agrees with.

    Parameters
    ----------
    buf : mi_tetvr.render.buffers.MeshBuffers
    face : UInt32
        Global boundary face index.

    Returns
    -------
    tet : UInt32, f : UInt32
        Tet behind the face and the face's local index in it.
    outward : Bool
        True when the ray leaves the mesh through this face.
    """
    face = mi.UInt32(face)
    for _ in range(BOUNDARY_WALK_STEPS):
        (ia, ib, ic), _, (pa, pb, pc) = _face_corners(buf, face, o, u, v, active)
        e_bc, s_bc = edge_function(ib, pb, ic, pc)
        e_ca, s_ca = edge_function(ic, pc, ia, pa)
        e_ab, s_ab = edge_function(ia, pa, ib, pb)
        # Front or back facing by the projected area; the ray is inside when
        # every edge sign agrees, else cross the first edge that disagrees.
        back = (e_bc + e_ca + e_ab) > 0
        adj = dr.select(s_bc != back, 0, dr.select(s_ca != back, 1, 2))
        move = active & ((s_bc != back) | (s_ca != back) | (s_ab != back))
        nxt = dr.gather(mi.Int32, buf.face_adj, face * 3 + adj, move)
        face = dr.select(move & (nxt >= 0), mi.UInt32(nxt), face)
    _, (Pa, Pb, Pc), _ = _face_corners(buf, face, o, u, v, active)
    code = dr.gather(mi.UInt32, buf.boundary, face, active)
    outward = dr.dot(dr.cross(Pb - Pa, Pc - Pa), d) > 0
    tet, f = unpack_link(code)
    return tet, f, outward


class Step:
    """Result of :func:`walk_step`: the exit crossing and the faces involved."""

    def __init__(self, t, w, link, f_out, entry, exit):
        self.t = t            # ray parameter of the exit crossing
        self.w = w            # its barycentric weights in the exit face
        self.link = link      # the next tet and its entry face (a link), -1 when leaving the mesh
        self.f_out = f_out    # local index of the exit face
        self.entry = entry    # global vertex ids of the entry face
        self.exit = exit      # global vertex ids of the exit face


def walk_step(buf, tet, f_in, o, u, v, d, active):
    """Cross one tet: find the exit face of a ray entering ``tet`` through its
    local face ``f_in``, and the exit crossing (a :class:`Step`)."""
    ik, ia, ib, ic = tet_face(buf, tet, f_in, active)
    k = f_in * 4
    la = dr.gather(mi.UInt32, buf.face_order, k + 1, active)
    lb = dr.gather(mi.UInt32, buf.face_order, k + 2, active)
    lc = dr.gather(mi.UInt32, buf.face_order, k + 3, active)
    Pk, Pa, Pb, Pc = (buf.position(ik, active), buf.position(ia, active),
                      buf.position(ib, active), buf.position(ic, active))
    pk, pa, pb, pc = (project(Pk, o, u, v), project(Pa, o, u, v),
                      project(Pb, o, u, v), project(Pc, o, u, v))
    ea, sa = edge_function(ik, pk, ia, pa)
    eb, sb = edge_function(ik, pk, ib, pb)
    ec, sc = edge_function(ik, pk, ic, pc)
    # Faces around the apex k, outward: (k,b,a) opposite c, (k,c,b) opposite a,
    # (k,a,c) opposite b. The ray leaves through (k,x,y) when it passes left of
    # k->x and right of k->y.
    opp_c = sb & ~sa
    opp_a = sc & ~sb
    opp_b = sa & ~sc
    # Inconsistent signs (only after round-off in the first entry face): take
    # the candidate whose two edge functions are the most in agreement.
    none = ~(opp_a | opp_b | opp_c)
    s_c = dr.minimum(eb, -ea)
    s_a = dr.minimum(ec, -eb)
    s_b = dr.minimum(ea, -ec)
    best_c = (s_c >= s_a) & (s_c >= s_b)
    best_a = ~best_c & (s_a >= s_b)
    opp_c |= none & best_c
    opp_a |= none & best_a
    opp_b |= none & ~best_c & ~best_a
    # Exit face (k, x, y) and the local index z of the vertex it is opposite.
    ix = dr.select(opp_c, ib, dr.select(opp_a, ic, ia))
    iy = dr.select(opp_c, ia, dr.select(opp_a, ib, ic))
    Px = dr.select(opp_c, Pb, dr.select(opp_a, Pc, Pa))
    Py = dr.select(opp_c, Pa, dr.select(opp_a, Pb, Pc))
    px = dr.select(opp_c, pb, dr.select(opp_a, pc, pa))
    py = dr.select(opp_c, pa, dr.select(opp_a, pb, pc))
    lz = dr.select(opp_c, lc, dr.select(opp_a, la, lb))
    exit_ids = (ik, ix, iy)
    t_out, w = crossing(exit_ids, (Pk, Px, Py), (pk, px, py), o, d)
    link = dr.gather(mi.Int32, buf.nbr, tet * 4 + lz, active)
    return Step(t_out, w, link, lz, (ia, ib, ic), exit_ids)
