"""The geometry of the tet walk (pure Dr.Jit): the ray frame, the consistent
edge predicate, face crossings, one step through a tet and the entry through
the boundary surface.

Everything here is a function of Dr.Jit arrays only (no Mitsuba scene, no
Python state), so it runs unchanged on ``llvm_ad_rgb`` and ``cuda_ad_rgb``
and can be differentiated by Dr.Jit's AD.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi

from mi_tetvr.mesh.topology import FACES
from mi_tetvr.render.buffers import MeshBuffers, unpack_link
from mi_tetvr.render.pytree import tree_dot, tree_map, tree_select

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

def project(p: mi.Point3f, o: mi.Point3f, u: mi.Vector3f, v: mi.Vector3f) -> mi.Point2f:
    """2D coordinates of point ``p`` in the ray frame ``(o; u, v)``."""
    q = p - o
    return mi.Point2f(dr.dot(q, u), dr.dot(q, v))


def edge_function(i: mi.UInt32, pi: mi.Point2f, j: mi.UInt32,
                  pj: mi.Point2f) -> tuple[mi.Float, mi.Bool]:
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


def ray_frame(d: mi.Vector3f) -> tuple[mi.Vector3f, mi.Vector3f]:
    """Orthonormal ``u, v`` with ``u x v = d``."""
    u, _ = mi.coordinate_system(d)
    return u, dr.cross(d, u)


@dataclass
class RayFrame:
    """A ray and its 2D frame, the walk's view of a ray: origin ``o``,
    normalized direction ``d`` and ``u, v`` (:func:`ray_frame`). Every
    vertex is seen as its projection ``((P - o) . u, (P - o) . v)`` and its
    depth ``(P - o) . d``."""
    o: mi.Point3f
    d: mi.Vector3f
    u: mi.Vector3f
    v: mi.Vector3f

    @staticmethod
    def of(o: mi.Point3f, d: mi.Vector3f) -> RayFrame:
        """The frame of the ray from ``o`` along the normalized ``d``."""
        d = mi.Vector3f(d)
        u, v = ray_frame(d)
        return RayFrame(mi.Point3f(o), d, u, v)

    def reversed(self) -> RayFrame:
        """The reversed ray in the mirrored frame ``(u, -v)``, whose
        parameter is ``-t`` (``u x -v = -d``)."""
        return RayFrame(self.o, -self.d, self.u, -self.v)

    def at(self, t: float | mi.Float) -> mi.Point3f:
        """The point at ray parameter ``t``."""
        return self.o + self.d * t


def face_weights(e_a: mi.Float, e_b: mi.Float,
                 e_c: mi.Float) -> tuple[mi.Float, mi.Float, mi.Float]:
    """Barycentric weights of the ray's crossing point in a triangle from the
    three edge functions opposite each vertex (any common sign); degenerate
    (edge-on) triangles get equal weights. An edge function of the other
    sign than their sum (round-off, a ray on an edge) counts as zero: the
    weights ``max(e_j / S, 0)``, normalised, are ``max(e_j sign(S), 0)``
    over their sum (one division)."""
    s = e_a + e_b + e_c
    sign = dr.select(s < 0, -1.0, 1.0)
    wa = dr.maximum(e_a * sign, 0.0)
    wb = dr.maximum(e_b * sign, 0.0)
    wc = dr.maximum(e_c * sign, 0.0)
    n = wa + wb + wc
    ok = (s != 0) & (n > 0)
    inv_n = dr.rcp(dr.select(ok, n, 1.0))
    third = 1.0 / 3.0
    return (dr.select(ok, wa * inv_n, third), dr.select(ok, wb * inv_n, third),
            dr.select(ok, wc * inv_n, third))


class Corner:
    """A vertex of the face a ray crosses, as the walk sees it: its global
    index ``i`` (which fixes the canonical edge order), its projection ``p``
    in the ray frame and its depth ``z = (P - o) . d`` along the ray.

    The walk carries the three corners of the face it entered through from
    one tet to the next, so that a step reads only the one new vertex."""
    DRJIT_STRUCT = {"i": mi.UInt32, "p": mi.Point2f, "z": mi.Float}

    def __init__(self, i: mi.UInt32 | None = None, p: mi.Point2f | None = None,
                 z: mi.Float | None = None) -> None:
        self.i, self.p, self.z = i, p, z


def corner(i: mi.UInt32, P: mi.Point3f, fr: RayFrame) -> Corner:
    """The :class:`Corner` of vertex ``i`` at position ``P``."""
    return Corner(i, project(P, fr.o, fr.u, fr.v), dr.dot(P - fr.o, fr.d))


def face_edges(c: Sequence[Corner]) -> tuple[mi.Float, mi.Float, mi.Float]:
    """The canonical edge functions of the triangle of :class:`Corner` s
    ``c``, each of the edge opposite a corner: ``e(c1, c2), e(c2, c0), e(c0,
    c1)``."""
    return (edge_function(c[1].i, c[1].p, c[2].i, c[2].p)[0],
            edge_function(c[2].i, c[2].p, c[0].i, c[0].p)[0],
            edge_function(c[0].i, c[0].p, c[1].i, c[1].p)[0])


def crossing_at(c: Sequence[Corner],
                edges: Sequence[mi.Float] | None = None) -> tuple[mi.Float, tuple[mi.Float, ...]]:
    """Where the ray crosses the triangle of the :class:`Corner` s ``c``: the
    ray parameter ``t`` and the barycentric weights. The weights come from
    the same canonical edge functions as the walk's exit test
    (:func:`face_edges`, or ``edges`` when known), so a face shared by two
    tets gives the same crossing from both sides."""
    w = face_weights(*(face_edges(c) if edges is None else edges))
    return w[0] * c[0].z + w[1] * c[1].z + w[2] * c[2].z, w


def crossing_vjp(c: Sequence[Corner], edges: Sequence[mi.Float], values: Sequence[Any],
                 g_t: mi.Float, g_a: Any,
                 w: Sequence[mi.Float] | None = None) -> list[tuple[mi.Point2f, mi.Float, Any]]:
    """Reverse-mode derivative of a crossing (:func:`crossing_at`) and of
    the values interpolated there: given the gradient ``(g_t, g_a)`` of the
    ray parameter and of ``sum_j w_j values[j]``, the gradients of each
    corner's projection ``p``, depth ``z`` and value, in closed form.

    With ``e_j`` the edge function opposite corner ``j`` (``edges``), ``S =
    sum e_j`` and ``w_j = e_j / S``: ``q_j = g_t z_j + g_a . values[j]``
    is the gradient of ``w_j``, ``r_k = (q_k - sum_j w_j q_j) / S`` that of
    ``e_k``, and ``e_0 = p_1 x p_2`` (cyclically) passes it to the
    projections. Where the weights are clamped (a ray exactly on an edge)
    or degenerate (``S = 0``, equal weights) it is the derivative of the
    unclamped weights, resp. zero.

    ``w``: the weights, where known (:func:`face_weights` of ``edges``).

    Returns ``[(dp_j, dz_j, dvalue_j) for j in 0, 1, 2]``.
    """
    w = face_weights(*edges) if w is None else w
    S = edges[0] + edges[1] + edges[2]
    ok = dr.abs(S) > 0
    inv = dr.select(ok, dr.rcp(dr.select(ok, S, 1.0)), 0.0)
    q = [g_t * c[j].z + tree_dot(g_a, values[j]) for j in range(3)]
    mean_q = w[0] * q[0] + w[1] * q[1] + w[2] * q[2]
    r = [(q[k] - mean_q) * inv for k in range(3)]
    out = []
    for j in range(3):
        n1, n2 = c[(j + 1) % 3].p, c[(j + 2) % 3].p
        # e_{j+1} = p_{j+2} x p_j and e_{j+2} = p_j x p_{j+1}
        r1, r2 = r[(j + 1) % 3], r[(j + 2) % 3]
        dp = mi.Point2f(r1 * -n2.y + r2 * n1.y, r1 * n2.x - r2 * n1.x)
        out.append((dp, g_t * w[j], tree_map(lambda x: w[j] * x, g_a)))
    return out


def crossing(ids: Sequence[mi.UInt32], P: Sequence[mi.Point3f], p: Sequence[mi.Point2f],
             o: mi.Point3f, d: mi.Vector3f) -> tuple[mi.Float, tuple[mi.Float, ...]]:
    """:func:`crossing_at` of the triangle of vertices ``ids`` (global
    indices), given their positions ``P`` and projections ``p`` in the ray
    frame."""
    return crossing_at(tuple(Corner(i, pi, dr.dot(Pi - o, d)) for i, Pi, pi in zip(ids, P, p)))


def face_corners(buf: MeshBuffers, ids: Sequence[mi.UInt32], fr: RayFrame,
                 active: bool | mi.Bool = True,
                 reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> tuple[Corner, ...]:
    """The :class:`Corner` s of the vertices ``ids``, gathered
    (differentiably, when AD is enabled on the buffers)."""
    return tuple(corner(i, buf.position(i, active, reduce), fr) for i in ids)


def face_crossing(buf: MeshBuffers, ids: Sequence[mi.UInt32], fr: RayFrame,
                  active: bool | mi.Bool = True, reduce: dr.ReduceMode = dr.ReduceMode.Auto
                  ) -> tuple[mi.Float, tuple[mi.Float, ...]]:
    """``(t, w)`` where the ray crosses the triangle ``ids`` (gathered)."""
    return crossing_at(face_corners(buf, ids, fr, active, reduce))


def _pick(f, x):
    """``x[f]`` for a ``UInt32`` ``f`` in 0..3 and a 4-tuple ``x``."""
    return dr.select(f < 2, dr.select(f == 0, x[0], x[1]), dr.select(f == 2, x[2], x[3]))


#: FACES as constants per position in the face: _FACE_LOCAL[j][f].
_FACE_LOCAL = tuple(tuple(int(FACES[f][j]) for f in range(4)) for j in range(3))


def tet_face(buf: MeshBuffers, tet: mi.UInt32, f: mi.UInt32,
             active: bool | mi.Bool = True) -> tuple[mi.UInt32, mi.UInt32, mi.UInt32, mi.UInt32]:
    """Global vertex indices ``(apex, a, b, c)`` of ``tet`` for its local face
    ``f`` (the apex is the vertex opposite the face, local vertex ``f``;
    ``a, b, c`` the face in the outward order of
    :data:`~mi_tetvr.mesh.topology.FACES`), read from the tet's record."""
    rec = buf.corners(tet, active)
    r = (rec.x, rec.y, rec.z, rec.w)
    local = (_pick(f, tuple(mi.UInt32(x) for x in _FACE_LOCAL[j])) for j in range(3))
    return (_pick(f, r), *(_pick(lj, r) for lj in local))


def _boundary_corners(buf, face, fr: RayFrame, active):
    ids = tuple(dr.gather(mi.UInt32, buf.faces, face * 3 + j, active) for j in range(3))
    P = tuple(buf.position(i, active) for i in ids)
    return ids, P, tuple(project(Pi, fr.o, fr.u, fr.v) for Pi in P)


#: Steps of the walk over the boundary surface in :func:`face_entry`. The
#: ray tracer reports a face that contains the hit point up to round-off, so
#: the face the walk wants shares a vertex with it; around a vertex of
#: valence k the walk needs at most k/2 steps (4 were too few for fans of
#: front faces around vertices on a sheared box's edges).
BOUNDARY_WALK_STEPS = 8


@dr.syntax
def face_entry(buf: MeshBuffers, face: mi.UInt32, fr: RayFrame,
               active: bool | mi.Bool) -> tuple[mi.UInt32, mi.UInt32, mi.Bool]:
    """The tet behind the boundary face a ray hits.

    The face found by Mitsuba's ray tracer is first moved, over the boundary
    surface, to the face that the ray crosses by the walk's own (consistent)
    edge predicate: a ray hitting a vertex or an edge of the boundary must
    start in the tet the walk agrees with. (A loop that lanes leave as soon
    as their face is the one: most rays stay on the ray tracer's face.)

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
    move = mi.Bool(active)
    steps = mi.UInt32(0)
    while dr.hint(move, label="tetvr_entry_face"):
        (ia, ib, ic), _, (pa, pb, pc) = _boundary_corners(buf, face, fr, move)
        e_bc, s_bc = edge_function(ib, pb, ic, pc)
        e_ca, s_ca = edge_function(ic, pc, ia, pa)
        e_ab, s_ab = edge_function(ia, pa, ib, pb)
        # Front or back facing by the projected area; the ray is inside when
        # every edge sign agrees, else cross the first edge that disagrees.
        back = (e_bc + e_ca + e_ab) > 0
        adj = dr.select(s_bc != back, 0, dr.select(s_ca != back, 1, 2))
        move &= (s_bc != back) | (s_ca != back) | (s_ab != back)
        nxt = dr.gather(mi.Int32, buf.face_adj, face * 3 + adj, move)
        move &= nxt >= 0
        face = dr.select(move, mi.UInt32(nxt), face)
        steps += 1
        move &= steps < BOUNDARY_WALK_STEPS
    _, (Pa, Pb, Pc), _ = _boundary_corners(buf, face, fr, active)
    code = dr.gather(mi.UInt32, buf.boundary, face, active)
    outward = dr.dot(dr.cross(Pb - Pa, Pc - Pa), fr.d) > 0
    tet, f = unpack_link(code)
    return tet, f, outward


@dataclass
class Step:
    """Result of :func:`walk_step`: the exit crossing and the faces involved."""
    t: mi.Float           # ray parameter of the exit crossing
    w: tuple              # its barycentric weights in the exit face (order of ``exit``)
    link: mi.Int32        # the next tet and its entry face (a link), -1 when leaving the mesh
    f_out: mi.UInt32      # local index of the exit face
    entry: tuple          # global vertex ids of the entry face
    exit: tuple           # global vertex ids of the exit face
    apex: mi.UInt32       # the vertex the exit face has and the entry face has not
    slot: tuple           # per corner of the entry face: is it the one the apex replaces
    carry: tuple          # the exit face for the next step (see walk_step)


def entry_carry(buf: MeshBuffers, tet: mi.UInt32, f_in: mi.UInt32, fr: RayFrame,
                active: bool | mi.Bool,
                gather: Callable[[mi.UInt32, bool | mi.Bool], Any] | None = None) -> tuple:
    """What :func:`walk_step` carries, for the face ``f_in`` of ``tet`` read
    from the buffers: the three :class:`Corner` s in the outward order of
    ``tet``, their values ``gather(i, active)`` and the face's edge
    functions (:func:`face_edges`)."""
    ids = tet_face(buf, tet, f_in, active)[1:]
    corners = face_corners(buf, ids, fr, active)
    values = tuple(gather(i, active) for i in ids) if gather else ((), (), ())
    return corners, values, face_edges(corners)


def walk_step(buf: MeshBuffers, tet: mi.UInt32, f_in: mi.UInt32, fr: RayFrame,
              active: bool | mi.Bool, carry: tuple | None = None,
              gather: Callable[[mi.UInt32, bool | mi.Bool], Any] | None = None) -> Step:
    """Cross one tet: find the exit face of a ray entering ``tet`` through its
    local face ``f_in``, and the exit crossing (a :class:`Step`).

    ``carry`` is the entry face as the previous step left it (``st.carry``,
    or :func:`entry_carry`): its corners in the outward order of ``tet``,
    per corner the values ``gather(i, active)`` returns (e.g. an optical
    model's attributes) and its edge functions. A step reads the tet's
    vertex indices, the one vertex it does not share with the entry face
    (the apex) and one neighbour link; the exit face is the entry face with
    the corner it leaves behind replaced by the apex, which keeps its corners
    in the outward order of the next tet (the topology orients every tet
    consistently), so ``st.carry`` serves the next step as it is.
    """
    if carry is None:
        carry = entry_carry(buf, tet, f_in, fr, active, gather)
    (ca, cb, cc), (xa, xb, xc), (Ea, Eb, Ec) = carry
    ia, ib, ic = ca.i, cb.i, cc.i
    rec = buf.corners(tet, active)
    # The apex: the one index of the tet's record not on the entry face.
    ik = rec.x ^ rec.y ^ rec.z ^ rec.w ^ ia ^ ib ^ ic
    ck = corner(ik, buf.position(ik, active), fr)
    xk = gather(ik, active) if gather else ()
    pk = ck.p
    ea, sa = edge_function(ik, pk, ia, ca.p)
    eb, sb = edge_function(ik, pk, ib, cb.p)
    ec, sc = edge_function(ik, pk, ic, cc.p)
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
    opp_a = ~opp_c & (opp_a | (none & best_a))
    opp_b = ~opp_c & ~opp_a
    # The exit face: the entry face with the corner z opposite it replaced by k.
    exit_c = (tree_select(opp_a, ck, ca), tree_select(opp_b, ck, cb), tree_select(opp_c, ck, cc))
    exit_x = (tree_select(opp_a, xk, xa), tree_select(opp_b, xk, xb), tree_select(opp_c, xk, xc))
    # Its edge functions: the edge opposite z is an entry-face edge, the two
    # others are edges of k (the canonical values are exactly antisymmetric).
    exit_e = (dr.select(opp_a, Ea, dr.select(opp_b, ec, -eb)),
              dr.select(opp_b, Eb, dr.select(opp_c, ea, -ec)),
              dr.select(opp_c, Ec, dr.select(opp_a, eb, -ea)))
    t_out, w = crossing_at(exit_c, exit_e)
    iz = dr.select(opp_c, ic, dr.select(opp_a, ia, ib))
    lz = dr.select(iz == rec.x, 0, dr.select(iz == rec.y, 1, dr.select(iz == rec.z, 2, 3)))
    lz = mi.UInt32(lz)
    link = buf.link(tet, lz, active)
    return Step(t_out, w, link, lz, (ia, ib, ic), tuple(c.i for c in exit_c), ik,
                (opp_a, opp_b, opp_c), (exit_c, exit_x, exit_e))


def inside_face(buf: MeshBuffers, tet: mi.UInt32, fr: RayFrame,
                active: bool | mi.Bool = True) -> mi.UInt32:
    """The local face through which the line of a ray from ``o`` (a point of
    ``tet``) in direction ``d`` enters ``tet``: the face the line passes
    through (its three canonical edge functions agree) that faces the ray
    (projected clockwise in the ray frame: an outward normal against ``d``).
    Where round-off puts ``o`` just outside and the line misses the tet, the
    face closest to being crossed."""
    rec = buf.corners(tet, active)
    ids = (rec.x, rec.y, rec.z, rec.w)
    p = [project(buf.position(i, active), fr.o, fr.u, fr.v) for i in ids]
    best = mi.UInt32(0)
    best_score = mi.Float(-dr.inf)
    for f in range(4):
        a, b, c = (int(k) for k in FACES[f])
        e_bc, s_bc = edge_function(ids[b], p[b], ids[c], p[c])
        e_ca, s_ca = edge_function(ids[c], p[c], ids[a], p[a])
        e_ab, s_ab = edge_function(ids[a], p[a], ids[b], p[b])
        entry = ~s_bc & ~s_ca & ~s_ab
        # How far from passing through it as an entry face (0 or more when it does).
        score = dr.select(entry, dr.inf, -dr.maximum(dr.maximum(e_bc, e_ca), e_ab))
        take = score > best_score
        best = dr.select(take, f, best)
        best_score = dr.select(take, score, best_score)
    return best
