"""The ray cursor: the one traversal of tet meshes, written once.

For each ray, repeat from ``start`` (the span's beginning, or where a block
enters its piece):

1. Mitsuba's ray tracer (its BVH over the meshes' boundary faces) finds the
   next boundary face after ``start``.
2. If the ray *enters* through it, the walk starts in the tet behind it. If
   the ray *leaves* through it, the point at ``start`` is inside a mesh (a
   camera inside, or just past a seam of coincident but unconnected faces):
   :func:`locate` walks back from that face along the reversed ray to the tet
   containing the start point (point location by walking, Aman et al.
   Sec. 4.2). A ray that starts inside a known tet (a path's scattered ray)
   starts there, through the face its line enters by.
3. :func:`walk` goes front to back, tet to tet through the neighbour links,
   handing each piece (clipped by the client to the span) to a *client*,
   until the ray leaves the mesh, reaches the span's end, or the client is
   done; then ``start`` moves just past the exit face and the loop traces
   again (non-convex meshes, disjoint parts, several meshes).

The cursor knows nothing of what a vertex carries or what a piece adds up
to. A *client* says it (:class:`Client`): what a crossing interpolates
(``gather``), where a piece ends inside a tet (``cut``, for models that
classify a scalar nonlinearly), and what to do with each piece. Its clients
are ``tetvr``'s emission-absorption and probes
(:mod:`~mi_tetvr.render.walk`), their adjoint
(:mod:`~mi_tetvr.render.adjoint`), and ``tetpath``'s optical depth up to a
target (free flights, shadow transmittance:
:mod:`~mi_tetvr.render.transport`). Meshes that overlap in space are walked
with one :class:`Cursor` each (:func:`traverse_merged`, :mod:`~mi_tetvr.render.merged`),
entered by the same :func:`enter` and :func:`locate` and stepped by the single
walk's own step (:func:`advance`, :func:`moved`); its client gets each mesh's
:class:`Piece`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import drjit as dr
import mitsuba as mi

from mi_tetvr.render.buffers import MeshBuffers, TetGroup, unpack_link
from mi_tetvr.render.geometry import (RayFrame, Step, crossing_at, entry_carry, face_entry,
                                      inside_face, walk_step)
from mi_tetvr.render.pytree import tree_lerp, tree_select, weighted_sum


class WalkSettings:
    """Python-level settings of the walk (not traced).

    ``t_min``: a ray stops when its transmittance falls below it;
    ``max_steps``: the most tets (or pieces) one walk crosses;
    ``retrace_eps``: how far past a mesh's exit face the ray tracer looks for
    the next boundary; ``reduce``: the scatter strategy (``dr.ReduceMode``)
    of the gradient accumulation into shared vertices, or None (the
    default) for the walk's own choice (:meth:`sums_mode`; plain atomics on
    the LLVM backend and Dr.Jit's ``Auto`` on CUDA where gradients go to a
    parameter directly, :attr:`atomics`).
    """

    def __init__(self, t_min: float = 1e-4, max_steps: int = 100_000,
                 retrace_eps: float = 1e-5, reduce: dr.ReduceMode | None = None) -> None:
        self.t_min = float(t_min)
        self.max_steps = int(max_steps)
        self.retrace_eps = float(retrace_eps)
        self.reduce = reduce

    @property
    def atomics(self) -> dr.ReduceMode:
        """The scatter strategy of a gather's reverse-mode derivative (a
        vertex's gradient added to a parameter at once): ``reduce``, or by
        default plain atomics on the LLVM backend (where they beat Dr.Jit's
        per-thread copies of a parameter's gradient, ``benchmarks/bench_backward.py``)
        and Dr.Jit's own choice on CUDA."""
        if self.reduce is not None:
            return self.reduce
        llvm = dr.backend_v(mi.Float) == dr.JitBackend.LLVM
        return dr.ReduceMode.Direct if llvm else dr.ReduceMode.Auto

    def sums_mode(self, nbytes: int) -> dr.ReduceMode:
        """The scatter strategy of the adjoint's per-vertex sums of
        ``nbytes`` (:class:`~mi_tetvr.render.adjoint.VertexSums`): ``reduce``,
        or by default per-thread copies on the LLVM backend where they take
        at most :data:`EXPAND_BYTES` (no atomics: one read-modify-write of a
        vertex's packet of gradients per lane), else :attr:`atomics`."""
        if self.reduce is None and dr.backend_v(mi.Float) == dr.JitBackend.LLVM \
                and dr.thread_count() * nbytes <= EXPAND_BYTES:
            return dr.ReduceMode.Expand
        return self.atomics


#: The most memory (bytes) the per-thread copies of the adjoint's vertex
#: gradients may take (:meth:`WalkSettings.sums_mode`).
EXPAND_BYTES = 1 << 30


@dataclass
class Span:
    """The interval ``[begin, end]`` of ray parameters a walk integrates."""
    begin: mi.Float
    end: mi.Float


@dataclass
class Entry:
    """Where a traversal starts, when not at its span's beginning: ``t``,
    where the search for the meshes' boundary starts (a block of a
    partitioned mesh enters its piece before the span); ``tet``, the tet a
    ray starts inside of, where ``inside`` (a scattered ray)."""
    t: Any = None
    tet: mi.UInt32 = None
    inside: mi.Bool = None


@dataclass
class Cursor:
    """Where a walk stands: in ``tet``, entered through its local face
    ``f_in``, whose corners, their values and edge functions are ``carry``
    (:func:`~mi_tetvr.render.geometry.entry_carry`), at the ray parameter
    ``t`` with the values ``a`` interpolated there."""
    tet: mi.UInt32
    f_in: mi.UInt32
    carry: tuple
    t: mi.Float
    a: Any

    @staticmethod
    def at(client: Client, tet: mi.UInt32, f_in: mi.UInt32, fr: RayFrame,
           active: bool | mi.Bool) -> Cursor:
        """The cursor entering ``tet`` through its face ``f_in``."""
        tet, f_in = mi.UInt32(tet), mi.UInt32(f_in)
        carry = entry_carry(client.ts.buf, tet, f_in, fr, active, client.gather)
        t, w = crossing_at(carry[0], carry[2])
        return Cursor(tet, f_in, carry, t, weighted_sum(w, carry[1]))


@dataclass
class Piece:
    """What a walk hands its client per step: the piece of the ray in
    ``cur.tet`` from the cursor (``cur.t``, ``cur.a``) to ``(t1, a1)``,
    found by the step ``st``; ``stay``: the piece ends inside the tet, ``f``
    of the way to its exit crossing (models that cut tets)."""
    cur: Cursor
    st: Step
    t1: mi.Float
    a1: Any
    stay: mi.Bool
    f: mi.Float = None


class Client(Protocol):
    """What a walk does along a ray (see the module docstring). ``acc`` is
    the client's per-ray state, carried through the walk's loop."""
    ts: TetGroup          # the buffers walked (``ts.buf``) and the optical model
    cuts: bool            # whether pieces end inside tets (``cut``)
    label: str            # the walk loop's name in Dr.Jit's kernels

    def gather(self, i: mi.UInt32, active: bool | mi.Bool) -> Any: ...
    def cut(self, a0: Any, a1: Any) -> mi.Float: ...
    def begin(self, acc: Any, cur: Cursor, fr: RayFrame, active: mi.Bool) -> Any: ...
    def piece(self, acc: Any, p: Piece, span: Span, fr: RayFrame,
              active: mi.Bool) -> tuple[Any, mi.Bool]: ...
    def end(self, acc: Any, cur: Cursor, stay: mi.Bool, walked: mi.Bool,
            fr: RayFrame) -> Any: ...
    def alive(self, acc: Any) -> mi.Bool: ...


@dr.syntax
def locate(buf: MeshBuffers, tet: mi.UInt32, f_out: mi.UInt32, fr: RayFrame, t_start: mi.Float,
           max_steps: int, active: bool | mi.Bool) -> tuple[mi.UInt32, mi.UInt32]:
    """Walk back from the boundary face ``f_out`` of ``tet`` (where the ray
    leaves a mesh) along the reversed ray to the tet that contains the point
    at ``t_start``.

    Returns ``(tet, f_in)``: the tet and the face through which the forward
    ray enters it (at or before ``t_start``; after it when the reversed ray
    left the mesh first).
    """
    back = fr.reversed()
    tet = mi.UInt32(tet)
    f_in = mi.UInt32(f_out)
    steps = mi.UInt32(0)
    active = mi.Bool(active)
    # (the face walked in by, carried from step to step as the walk does)
    carry = entry_carry(buf, tet, f_in, back, active)
    while dr.hint(active, label="tetvr_locate"):
        st = walk_step(buf, tet, f_in, back, active, carry)
        found = -st.t <= t_start
        go = ~found & (st.link >= 0)
        nxt_tet, nxt_f = unpack_link(st.link)
        tet = dr.select(go, nxt_tet, tet)
        f_in = dr.select(go, nxt_f, st.f_out)
        carry = tree_select(go, st.carry, carry)
        steps += 1
        active &= go & (steps < max_steps)
    return tet, f_in


def enter(buf: MeshBuffers, face: mi.UInt32, fr: RayFrame, t_start: mi.Float, max_steps: int,
          active: bool | mi.Bool) -> tuple[mi.UInt32, mi.UInt32, mi.Bool]:
    """Where a ray that hits the boundary face ``face`` (global index, from
    Mitsuba's ray tracer) walks from: ``(tet, f_in, outward)``. A ray that
    enters through the face starts in the tet behind it; one that leaves
    through it (``outward``) is inside the mesh at ``t_start`` and is
    :func:`locate` d there."""
    tet, f, outward = face_entry(buf, face, fr, active)
    tet, f = locate(buf, tet, f, fr, t_start, max_steps, active & outward)
    return tet, f, outward


def advance(client: Client, cur: Cursor, fr: RayFrame, active: bool | mi.Bool) -> Piece:
    """One step of a walk: the piece of the ray in the cursor's tet from the cursor to
    the tet's exit crossing or (clients that cut tets) to the next knot of the
    client's ``cut`` (``stay``: it ends inside the tet)."""
    st = walk_step(client.ts.buf, cur.tet, cur.f_in, fr, active, cur.carry, client.gather)
    a1 = weighted_sum(st.w, st.carry[1])
    t1 = dr.maximum(st.t, cur.t)
    stay = mi.Bool(False)
    f = None
    if client.cuts:
        # The client's nonlinearity: end the piece at the next knot.
        f = client.cut(cur.a, a1)
        stay = f < 1.0
        t1 = dr.select(stay, dr.lerp(cur.t, t1, f), t1)
        a1 = tree_select(stay, tree_lerp(cur.a, a1, f), a1)
    return Piece(cur, st, t1, a1, stay, f)


def moved(p: Piece, cuts: bool) -> Cursor:
    """The cursor after the piece ``p``: in the next tet, entered through the face the
    ray leaves by, or (``p.stay``) in the same tet at the piece's end."""
    nxt_tet, nxt_f = unpack_link(p.st.link)
    cur, st = p.cur, p.st
    if not cuts:
        return Cursor(nxt_tet, nxt_f, st.carry, p.t1, p.a1)
    return Cursor(dr.select(p.stay, cur.tet, nxt_tet), dr.select(p.stay, cur.f_in, nxt_f),
                  tree_select(p.stay, cur.carry, st.carry), p.t1, p.a1)


@dr.syntax
def walk(client: Client, fr: RayFrame, cur: Cursor, acc: Any, span: Span, settings: WalkSettings,
         active: bool | mi.Bool) -> tuple[Any, mi.Float, mi.UInt32]:
    """Walk front to back from the cursor ``cur``, handing each piece to
    ``client``, until the ray leaves the mesh, reaches ``span.end``, crosses
    ``settings.max_steps`` tets (pieces), or the client says stop.

    Returns ``(acc, t, steps)``: the client's state, where the walk ended
    and the number of tets crossed.
    """
    cuts = client.cuts
    active = mi.Bool(active)
    acc = client.begin(acc, cur, fr, active)
    steps = mi.UInt32(0)
    pieces = mi.UInt32(0)
    stay = mi.Bool(False)     # (clients that cut tets) the last piece ended inside its tet
    while dr.hint(active, label=client.label):
        p = advance(client, cur, fr, active)
        stay = p.stay
        acc, go = client.piece(acc, p, span, fr, active)
        # Stay in the tet for the next piece (a knot), else move on.
        cur = moved(p, cuts)
        if dr.hint(cuts, mode="scalar"):
            steps += dr.select(stay, 0, 1)
            pieces += 1
            active &= (stay | (p.st.link >= 0)) & (p.t1 < span.end) & \
                (pieces < settings.max_steps)
        else:
            steps += 1
            active &= (p.st.link >= 0) & (p.t1 < span.end) & (steps < settings.max_steps)
        active &= go
    # (a walk that stopped inside its first tet left none: count its pieces)
    acc = client.end(acc, cur, stay, (pieces > 0) if cuts else (steps > 0), fr)
    return acc, cur.t, steps


@dr.syntax
def traverse(scene: mi.Scene, clients: list, fr: RayFrame, acc: Any, span: Span,
             settings: WalkSettings, active: bool | mi.Bool,
             entry: Entry = None) -> tuple[Any, mi.UInt32]:
    """Walk rays through the tet meshes whose boundaries are ``scene``'s
    shapes, over ``span`` (see the module docstring).

    ``clients`` has one :class:`Client` per group of shapes that one walk
    renders (their :class:`~mi_tetvr.render.buffers.TetGroup`): each
    boundary hit is walked by its own group's client, all sharing ``acc``;
    the first client's ``alive(acc)`` says whether a ray goes on.
    ``entry``: where to start, when not at ``span.begin`` (:class:`Entry`).

    Returns ``(acc, steps)``: the clients' state and the tets crossed.
    """
    entry = entry if entry is not None else Entry()
    inside = entry.tet is not None
    if inside and len(clients) != 1:
        raise ValueError("a ray that starts inside a tet walks one group of meshes")
    if dr.hint(not inside and entry.t is None and len(clients) == 1 and convex_scene(scene),
               mode="scalar"):
        return traverse_convex(scene, clients[0], fr, acc, span, settings, active)
    t_max = mi.Float(span.end)
    start = mi.Float(span.begin if entry.t is None else entry.t)
    active = mi.Bool(active)
    first = mi.Bool(entry.inside) & active if inside else mi.Bool(False)
    steps = mi.UInt32(0)
    while dr.hint(active, label=clients[0].label + "_trace"):
        tracing = active & ~first
        # (unbounded: a ray that starts inside a mesh finds the face it
        # leaves by even past the span's end, and walks back to its start)
        si = scene.ray_intersect_preliminary(mi.Ray3f(fr.at(start), fr.d), active=tracing)
        hit = tracing & si.is_valid()
        t_end = mi.Float(start)
        for c in clients:
            # The hit face's own group walks it (all of them with one group).
            mine = hit if len(clients) == 1 else hit & c.ts.owns(si)
            tet, f, _ = enter(c.ts.buf, c.ts.boundary_face(si), fr, start, settings.max_steps,
                              mine)
            if dr.hint(inside, mode="scalar"):
                tet = dr.select(first, entry.tet, tet)
                f = dr.select(first, inside_face(c.ts.buf, entry.tet, fr, first), f)
                mine = mine | first
            cur = Cursor.at(c, tet, f, fr, mine)
            acc, t_c, n = walk(c, fr, cur, acc, Span(dr.maximum(start, span.begin), t_max),
                               settings, mine)
            t_end = dr.select(mine, t_c, t_end)
            steps += dr.select(mine, n, 0)
        start = dr.maximum(t_end, start) + settings.retrace_eps
        active = (hit | first) & clients[0].alive(acc) & (start < t_max)
        first = mi.Bool(False)
    return acc, steps


def convex_scene(scene: mi.Scene) -> bool:
    """Whether ``scene`` is one tet mesh's boundary, and that mesh is convex
    (its shape's ``convex()``): a line meets it in one interval."""
    shapes = scene.shapes()
    return len(shapes) == 1 and bool(getattr(shapes[0], "convex", lambda: False)())


def traverse_convex(scene: mi.Scene, client: Client, fr: RayFrame, acc: Any, span: Span,
                    settings: WalkSettings, active: bool | mi.Bool) -> tuple[Any, mi.UInt32]:
    """:func:`traverse` where ``scene`` is one convex mesh
    (:func:`convex_scene`): a ray that leaves it never comes back, so the
    ray tracer is asked once, and there is no loop around the walk. A ray
    that starts inside the mesh (its first boundary face is one it leaves
    by) enters it where its line does, behind the start: the first face
    found from a point beyond the mesh's bounds, back along the ray; the
    walk's pieces before ``span.begin`` are clipped away, as the general
    traverse clips the piece it locates the start in. (No walk back to the
    start, :func:`locate`, and none of its code.)"""
    buf = client.ts.buf
    start = mi.Float(span.begin)
    active = mi.Bool(active)
    si = scene.ray_intersect_preliminary(mi.Ray3f(fr.at(start), fr.d), active=active)
    hit = active & si.is_valid()
    tet, f, outward = face_entry(buf, client.ts.boundary_face(si), fr, hit)
    behind = hit & outward
    # (a point a bounding box's diagonal beyond the box's sphere is outside the mesh)
    box = scene.bbox()
    far = dr.norm(fr.at(start) - box.center()) + dr.norm(box.extents())
    si = scene.ray_intersect_preliminary(mi.Ray3f(fr.at(start - far), fr.d), active=behind)
    tet_b, f_b, _ = face_entry(buf, client.ts.boundary_face(si), fr, behind)
    # (a line through the mesh is found from behind; where round-off says
    # otherwise, the ray is not walked rather than walked from a face it leaves by)
    hit &= ~behind | si.is_valid()
    tet = dr.select(behind, tet_b, tet)
    f = dr.select(behind, f_b, f)
    cur = Cursor.at(client, tet, f, fr, hit)
    acc, _, steps = walk(client, fr, cur, acc, Span(start, mi.Float(span.end)), settings, hit)
    return acc, dr.select(hit, steps, 0)


# ----------------------------------------------------------------------------
# Several meshes that overlap in space: one cursor per mesh
# ----------------------------------------------------------------------------

@dataclass
class Pieces:
    """What the walk over overlapping meshes (:func:`traverse_merged`) hands its client
    per piece ``[t0, t1]`` of the ray (``length``): per mesh ``k``, whether the ray is
    ``inside[k]`` it and there the single walk's :class:`Piece` of that mesh over
    ``[t0, t1]`` (``parts[k]``: its cursor at ``t0`` with the mesh's values there, the
    step in its tet, the values at ``t1``), and (clients that ask, ``boundary_terms``)
    whether the piece starts where the ray crossed the mesh's boundary
    (``from_bnd[k]``), ends where it enters or leaves it (``to_bnd[k]``), and the next
    boundary face (``f_next[k]``)."""
    t0: mi.Float
    t1: mi.Float
    length: mi.Float
    inside: list
    parts: list
    from_bnd: list = None
    to_bnd: list = None
    f_next: list = None


class MergedClient(Protocol):
    """What a walk over overlapping meshes does along a ray: ``members``,
    one :class:`Client` per mesh (its ``ts``, ``cuts``, ``gather``,
    ``cut``); ``piece`` takes each :class:`Pieces` and returns ``(acc,
    go)``."""
    members: list
    boundary_terms: bool
    label: str

    def piece(self, acc: Any, pc: Pieces, fr: RayFrame,
              active: mi.Bool) -> tuple[Any, mi.Bool]: ...


def entry_of(p: Piece) -> tuple[mi.Float, Any, mi.Float]:
    """``(te, we, 1 / (tx - te))`` of a piece's tet: the ray parameter and the
    face-vertex weights where the ray entered it, and the inverse of its span up to the
    exit crossing (0 for none): the tet's linear field along the ray."""
    te, we = crossing_at(p.cur.carry[0], p.cur.carry[2])
    span = dr.maximum(p.st.t, te) - te
    return te, we, dr.select(span > 0, dr.rcp(dr.select(span > 0, span, 1.0)), 0.0)


def _clipped(p: Piece, t0: mi.Float, t1: mi.Float, whole: mi.Bool) -> Piece:
    """The piece ``p`` (from its cursor) over ``[t0, t1]`` within it: the values at
    each end on its line; where ``whole`` (``t1`` is its end) the end as it is."""
    cur = p.cur
    span = p.t1 - cur.t
    inv = dr.select(span > 0, dr.rcp(dr.select(span > 0, span, 1.0)), 0.0)
    a0 = tree_lerp(cur.a, p.a1, dr.clip((t0 - cur.t) * inv, 0.0, 1.0))
    a1 = tree_select(whole, p.a1, tree_lerp(cur.a, p.a1, dr.clip((t1 - cur.t) * inv,
                                                                   0.0, 1.0)))
    return Piece(Cursor(cur.tet, cur.f_in, cur.carry, t0, a0), p.st, t1, a1,
                 p.stay & whole, p.f)


@dr.syntax
def traverse_merged(scenes: list, client: MergedClient, fr: RayFrame, acc: Any, span: Span,
                    settings: WalkSettings, active: bool | mi.Bool) -> tuple[Any, mi.UInt32]:
    """Walk rays through tet meshes that may overlap in space, one cursor
    per mesh (``scenes[k]``: a scene of mesh ``k``'s boundary alone, so that
    coincident faces of two meshes are both found), over ``span``.

    Each mesh's cursor is inside it (a :class:`Cursor`, stepped by the single walk's
    :func:`advance` and :func:`moved`) or outside, holding the next boundary face of
    that mesh along the ray. Each iteration hands the client the piece up to the
    nearest event of any cursor (the end of its piece: its tet's exit or a knot of its
    member's ``cut``; or entering its mesh) and moves on the cursor whose event it is;
    the others stay where they are. A ray that starts inside a mesh (a camera inside,
    or a first face it leaves by) is located in it by walking back (:func:`enter`).
    Returns ``(acc, steps)``.
    """
    members = client.members
    K = len(members)
    t_max = mi.Float(span.end)
    active = mi.Bool(active)
    inside = [mi.Bool(False) for _ in range(K)]
    cur = [Cursor.at(m, mi.UInt32(0), mi.UInt32(0), fr, mi.Bool(False)) for m in members]
    # Outside a mesh: where to trace its boundary from, and its next face.
    need = [mi.Bool(active) for _ in range(K)]
    t_trace = [mi.Float(span.begin) for _ in range(K)]
    t_next = [mi.Float(dr.inf) for _ in range(K)]
    f_next = [mi.UInt32(0) for _ in range(K)]
    # The piece starts where the ray crossed mesh k's boundary (its cursor's face).
    from_bnd = [mi.Bool(False) for _ in range(K)]
    # Outside mesh k, its cursor already at the tet the ray enters next (a face the ray
    # leaves by was found from outside: the ray grazed the mesh, round-off put the face
    # first; its entry crossing lies ahead, at ``t_next``).
    waiting = [mi.Bool(False) for _ in range(K)]
    t = mi.Float(span.begin)
    steps = mi.UInt32(0)
    inf = mi.Float(dr.inf)
    while dr.hint(active, label=client.label):
        inside, cur, need, t_trace = list(inside), list(cur), list(need), list(t_trace)
        t_next, f_next, from_bnd, waiting = list(t_next), list(f_next), list(from_bnd), \
            list(waiting)
        # Each mesh the ray is outside of: its next boundary face, where needed;
        # a face the ray leaves by: it is inside, walk back to where it is now.
        for k in range(K):
            m = members[k]
            cur_k, in_k, tn_k, fn_k = cur[k], inside[k], t_next[k], f_next[k]
            need_k, wait_k = need[k] & active, waiting[k]
            if need_k:
                # (a branch: most iterations trace nothing)
                si = scenes[k].ray_intersect_preliminary(mi.Ray3f(fr.at(t_trace[k]), fr.d),
                                                         active=need_k)
                hit = need_k & si.is_valid()
                tt, ff, out = enter(m.ts.buf, si.prim_index, fr, t, settings.max_steps, hit)
                here = hit & out
                # (located: the cursor at the tet's entry crossing, before t)
                cur_k = tree_select(here, Cursor.at(m, tt, ff, fr, here), cur_k)
                # (walked back, the ray left the mesh before t: it enters ahead, not here)
                wait_k = here & (cur_k.t > t)
                in_k = in_k | (here & ~wait_k)
                tn_k = dr.select(hit & ~out, t_trace[k] + si.t, dr.select(wait_k, cur_k.t, inf))
                fn_k = mi.UInt32(si.prim_index)
            cur[k], inside[k], t_next[k], f_next[k] = cur_k, in_k, tn_k, fn_k
            need[k], waiting[k] = mi.Bool(False), wait_k
        # Every cursor's next event: the end of its piece (its tet's exit or a knot),
        # or (outside its mesh) its next boundary face.
        pend, evs = [], []
        t_ev = mi.Float(t_max)
        for k in range(K):
            pend.append(advance(members[k], cur[k], fr, inside[k]))
            evs.append(dr.select(inside[k], pend[k].t1, t_next[k]))
            t_ev = dr.minimum(t_ev, evs[k])
        t_ev = dr.maximum(t_ev, t)
        # The cursor whose event it is (the first of equal ones) moves on.
        go = []
        moved_one = mi.Bool(False)
        for k in range(K):
            go.append(active & ~moved_one & (evs[k] <= t_ev) & (evs[k] < t_max))
            moved_one |= go[k]
        # The piece [t, t_ev] (none inside: an empty piece, which may reach to
        # an infinite t_max, whose length times a zero extinction would be NaN).
        any_in = mi.Bool(False)
        for k in range(K):
            any_in |= inside[k]
        t_end = dr.select(any_in, t_ev, t)
        parts = [_clipped(pend[k], t, t_ev, go[k]) for k in range(K)]
        pc = Pieces(t, t_end, t_end - t, list(inside), parts)
        if dr.hint(client.boundary_terms, mode="scalar"):
            # The piece ends where the ray enters or leaves mesh k.
            pc.from_bnd, pc.f_next = list(from_bnd), list(f_next)
            pc.to_bnd = [go[k] & (~inside[k] | (~pend[k].stay & (pend[k].st.link < 0)))
                         for k in range(K)]
        acc, more = client.piece(acc, pc, fr, active)
        for k in range(K):
            m = members[k]
            p = pend[k]
            # Inside: the next tet (or the knot, staying); leaving the mesh,
            # trace its boundary again past the exit.
            adv = go[k] & inside[k]
            cur_k = tree_select(adv, moved(p, m.cuts), cur[k])
            left = adv & ~p.stay & (p.st.link < 0)
            inside[k] = inside[k] & ~left
            from_bnd[k] = left
            t_trace[k] = dr.select(left, p.t1 + settings.retrace_eps, t_trace[k])
            need[k] = need[k] | left
            # Outside: enter the mesh through its next boundary face.
            entering = go[k] & ~inside[k] & ~left
            # (a waiting cursor is at its tet already)
            fresh = entering & ~waiting[k]
            if fresh:
                tt, ff, _ = face_entry(m.ts.buf, f_next[k], fr, fresh)
                cur_k = tree_select(fresh, Cursor.at(m, tt, ff, fr, fresh), cur_k)
            cur[k] = cur_k
            waiting[k] = waiting[k] & ~entering
            inside[k] = inside[k] | entering
            from_bnd[k] = from_bnd[k] | entering
            t_next[k] = dr.select(entering, inf, t_next[k])
        t = t_ev
        steps += 1
        pending = mi.Bool(False)
        for k in range(K):
            pending |= inside[k] | need[k] | (t_next[k] < t_max)
        active &= pending & (t < t_max) & more & (steps < settings.max_steps)
    return acc, steps
