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
move only where the ray enters or leaves a mesh) and the camera (the ray's
origin and direction as AD leaves; :func:`_piece_derivative`). Memory stays
O(rays).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi


from mi_tetvr.render import adjoint
from mi_tetvr.render.buffers import model_groups
from mi_tetvr.render.buffers import TetGroup
from mi_tetvr.render.cursor import Pieces, Span, WalkSettings, entry_of, traverse_merged
from mi_tetvr.render.geometry import RayFrame, face_crossing
from mi_tetvr.render.pytree import tree_lerp
from mi_tetvr.render.segment import merged_integral
from mi_tetvr.render.walk import Emission, Radiance

#: Most meshes one merged walk takes (each is a cursor in every iteration).
MAX_MESHES = 8


def overlapping(shapes: list[mi.Shape], rel_eps: float = 1e-6) -> bool:
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


def walk_groups(shapes: list, plugin: str) -> list:
    """The groups of tet meshes that one walk renders: one per mesh where
    meshes overlap in space (the merged walk, at most :data:`MAX_MESHES`),
    else one per optical model (:func:`~mi_tetvr.render.buffers.model_groups`).
    ``plugin`` names the integrator in the error for too many meshes."""
    if not overlapping(shapes):
        return model_groups(shapes)
    if len(shapes) > MAX_MESHES:
        raise ValueError(f"{plugin}: at most {MAX_MESHES} overlapping tet meshes in one scene, "
                         f"got {len(shapes)}; merge some of them into one mesh")
    return [[s] for s in shapes]


class MergedEmission:
    """The client of :func:`~mi_tetvr.render.cursor.traverse_merged` that
    integrates the meshes of ``tss`` (one :class:`~mi_tetvr.render.walk.Emission`
    member each) as one medium, with ``2 n_sub`` sub-intervals per piece; in
    a derivative pass (``deriv``), each piece differentiated by
    :func:`_piece_derivative`."""
    label = "tetvr_merged"

    def __init__(self, tss: list[TetGroup], settings: WalkSettings, n_sub: int,
                 deriv: adjoint.Derivative | None = None) -> None:
        self.members = [Emission(ts, settings) for ts in tss]
        self.tss, self.n_sub, self.deriv = tss, n_sub, deriv
        self.t_min, self.reduce = settings.t_min, settings.atomics
        self.boundary_terms = deriv is not None and any(deriv.geometric(g) for g in deriv.groups)

    def piece(self, acc: Radiance, pc: Pieces, fr: RayFrame,
              active: mi.Bool) -> tuple[Radiance, mi.Bool]:
        media = []
        for k, ts in enumerate(self.tss):
            p = pc.parts[k]
            # (outside its mesh a cursor's tet is stale: past the boundary, no tet)
            lin = ts.model.linear(ts.params, p.cur.a, p.a1,
                                  dr.select(pc.inside[k], p.cur.tet, 0))
            media.append(tuple(dr.select(pc.inside[k], x, 0.0) for x in lin))
        C_seg, T_seg = merged_integral(pc.length, media, 2 * self.n_sub)
        adj = acc.adj
        if self.deriv is not None:
            adj = _piece_derivative(self.deriv, pc, C_seg, acc, fr, self.reduce, self.n_sub)
        T = acc.T * T_seg
        return Radiance(acc.L + acc.T * C_seg, T, adj), T > self.t_min


def merged_trace(scenes: list, tss: list, ray: mi.Ray3f, settings: WalkSettings,
                 active: bool | mi.Bool, t_start: float | mi.Float = 0.0, grad: tuple = None,
                 n_sub: int = 4) -> tuple[mi.Color3f, mi.Float, mi.UInt32, adjoint.Adjoint | None]:
    """Emission and transmittance along rays through tet meshes that may
    overlap: per mesh a scene of it alone (``scenes``, whose boundary faces
    are traced) and its :class:`~mi_tetvr.render.buffers.TetGroup` (``tss``;
    a derivative pass, ``grad = (deriv, adj)``: its context, whose ``deriv.groups``
    are the same attached to the AD graph, and the rays' adjoint).
    Same results as :func:`~mi_tetvr.render.walk.trace`; pieces are
    integrated with ``2 n_sub`` sub-intervals (the merged integral's error at
    ``2 n`` is about the single medium's at ``n``); the integral starts at
    ``t_start`` (a clip)."""
    deriv, adj = (None, None) if grad is None else grad
    fr = RayFrame.of(ray.o, ray.d)
    d = dr.detach(fr.d)
    tss = [g.for_ray(d) for g in tss]
    if deriv is not None:
        deriv = adjoint.Derivative(deriv.mode, [g.for_ray(d) for g in deriv.groups],
                                   deriv.camera, deriv.ray_tangent)
    client = MergedEmission(tss, settings, n_sub, deriv)
    acc = Radiance(mi.Color3f(0.0), mi.Float(1.0), adj)
    acc, steps = traverse_merged(scenes, client, fr, acc,
                                 Span(mi.Float(t_start), mi.Float(ray.maxt)), settings, active)
    return acc.L, acc.T, steps, acc.adj


def _piece_derivative(deriv: adjoint.Derivative, pc: Pieces, C_seg, acc: Radiance,
                      fr: RayFrame, reduce, n_sub: int):
    """One piece in a derivative mode: its emission and optical depth
    recomputed with the AD graph through the gathers of each mesh's entry
    and exit face vertices, and ``d L_pix = T dC - R dtau`` with ``R`` the
    radiance from behind (:mod:`mi_tetvr.render.adjoint`).

    The piece's ends are fixed ray parameters where the integrand is
    continuous (a tet face or a knot of one mesh: the integral does not
    depend on where it is split), and the crossings of a mesh's boundary
    where it enters or leaves that mesh (``pc.from_bnd``, ``pc.to_bnd``,
    when vertex positions or the camera are differentiated):
    those move with the boundary, and every mesh's attributes at the ends
    follow through their own crossings, recomputed from the positions and,
    for the camera, on a ray whose origin and direction are AD leaves
    (:func:`~mi_tetvr.render.adjoint.ray_leaves`)."""
    backward = deriv.backward
    tss_ad = deriv.groups
    parts, inside = pc.parts, pc.inside
    length = pc.length
    geo = pc.to_bnd is not None
    with dr.resume_grad():
        t0, t1 = mi.Float(pc.t0), mi.Float(pc.t1)
        # (the camera: the ray's origin and direction as leaves)
        leaves = adjoint.ray_leaves(deriv, fr) if geo and deriv.camera else None

        def crossing_of(ts, ids, act):
            """A face crossing from the positions (attached), on the ray
            (attached where ``act`` when the camera is differentiated)."""
            return face_crossing(ts.buf, ids, fr if leaves is None
                                 else adjoint.leaf_frame(leaves, act), act, reduce)
        crossings = []
        for k, ts in enumerate(tss_ad):
            te, we, inv = entry_of(parts[k])
            st = parts[k].st
            ids_e = tuple(c.i for c in parts[k].cur.carry[0])
            if geo:
                from_bnd, to_bnd, f_next = pc.from_bnd, pc.to_bnd, pc.f_next
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
        if geo:
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
                                  dr.select(inside[k], parts[k].cur.tet, 0))
            lin = tuple(dr.select(inside[k], x, 0.0) for x in lin)
            media.append(lin)
            tau += length * (lin[2] + lin[3]) * 0.5
        C_d, _ = merged_integral(length, media, 2 * n_sub)
        adj = adjoint.inversion(deriv, acc.adj, acc.L, acc.T, C_seg, C_d, tau)
        if backward and leaves is not None:
            adj = adjoint.leaf_grads(adj, leaves)
    return adj
