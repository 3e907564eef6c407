"""Ray traversal of tet meshes: entry through the boundary, the tet walk,
re-entry, and a camera inside a mesh.

For each ray:

1. Mitsuba's ray tracer (its BVH over the meshes' boundary faces) finds the
   first boundary face. If the ray *leaves* through it, the origin is inside a
   mesh: the part from the origin to that face is walked backwards (from the
   face towards the origin, the same walk on the reversed ray) and composited
   back to front. This is point location by walking (Aman et al. Sec. 4.2)
   fused with the integral, so an inside camera costs no extra walk.
2. Front to back: enter through a boundary face, walk tet to tet through the
   neighbour links integrating each segment, leave through a boundary face,
   and trace again for re-entry (non-convex meshes, disjoint parts, several
   meshes), until the ray leaves the scene, the transmittance drops below the
   termination threshold, or ``ray.maxt`` is reached.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .kernels import _PERM, face_entry, ray_frame, segment_integral, walk_step


class WalkSettings:
    """Python-level settings of the walk (not traced)."""

    def __init__(self, n_sub=8, t_min=1e-4, max_steps=100_000, retrace_eps=1e-5):
        self.n_sub = int(n_sub)
        self.t_min = float(t_min)
        self.max_steps = int(max_steps)
        self.retrace_eps = float(retrace_eps)


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
def walk(buf, tet, f_in, t, c, s, o, u, v, d, t_stop, settings: WalkSettings,
         active, back_to_front: bool):
    """Walk from ``tet`` (entered through local face ``f_in`` at ``t`` with
    color ``c`` and opacity ``s``) until the ray leaves the mesh, reaches
    ``t_stop``, or (front to back only) becomes nearly opaque.

    Returns
    -------
    L : Color3f
        Emission, as seen from the ray's origin side when ``back_to_front`` is
        False; as seen from the *far* side looking back (i.e. the part of the
        original ray's emission) when True.
    T : Float
        Transmittance of the walked part.
    t : Float
        Where the walk ended.
    steps : UInt32
        Tets crossed.
    """
    perm = mi.UInt32(_PERM)
    L = mi.Color3f(0.0)
    T = mi.Float(1.0)
    tet = mi.UInt32(tet)
    f_in = mi.UInt32(f_in)
    t = mi.Float(t)
    c = mi.Color3f(c)
    s = mi.Float(s)
    steps = mi.UInt32(0)
    active = mi.Bool(active)
    while dr.hint(active, label="tetvr_walk_back" if back_to_front else "tetvr_walk"):
        t_out, c_out, s_out, nbr = walk_step(buf, perm, tet, f_in, o, u, v, d, active)
        t_out = dr.maximum(t_out, t)
        # Stop inside this tet at t_stop: attributes are linear along the segment.
        clip = t_out > t_stop
        if clip:
            w = dr.select(t_out > t, (t_stop - t) / (t_out - t), 1.0)
            c_out = dr.lerp(c, c_out, w)
            s_out = dr.lerp(s, s_out, w)
            t_out = mi.Float(t_stop)
        if dr.hint(back_to_front, mode="scalar"):
            C_seg, T_seg = segment_integral(t_out - t, c_out, c, s_out, s, settings.n_sub)
            L = C_seg + T_seg * L
        else:
            C_seg, T_seg = segment_integral(t_out - t, c, c_out, s, s_out, settings.n_sub)
            L += T * C_seg
        T *= T_seg
        t = t_out
        c = c_out
        s = s_out
        steps += 1
        inside = nbr >= 0
        tet = mi.UInt32(nbr >> 2)
        f_in = mi.UInt32(nbr & 3)
        active &= inside & ~clip & (steps < settings.max_steps)
        if dr.hint(not back_to_front, mode="scalar"):
            active &= T > settings.t_min
    return L, T, t, steps


@dr.syntax
def render_rays(scene, buf, shapes, face_offsets, ray, settings: WalkSettings, active):
    """Emission and transmittance along rays through the tet meshes.

    Parameters
    ----------
    scene : mi.Scene
        Its shapes must be exactly ``shapes`` (the tet meshes' boundaries).
    buf : MeshBuffers
    shapes : list of tetmesh shapes, face_offsets : list of int
        For mapping Mitsuba's intersections to global boundary faces.
    ray : mi.Ray3f
        Normalized direction; ``ray.maxt`` bounds the integral.

    Returns
    -------
    (Color3f, Float, UInt32)
        Accumulated emission ``C``, transmittance ``T`` (pixel = C + T bg) and
        the number of tets crossed.
    """
    o = mi.Point3f(ray.o)
    d = mi.Vector3f(ray.d)
    t_max = mi.Float(ray.maxt)
    u, v = ray_frame(d)
    active = mi.Bool(active)

    # -- 1. Origin inside a mesh: walk back from the first (outgoing) face. --
    si = scene.ray_intersect_preliminary(mi.Ray3f(o, d, t_max), active=active)
    hit = active & si.is_valid()
    face = boundary_face_index(si, shapes, face_offsets)
    tet, f_in, t_hit, c, s, outward = face_entry(buf, face, o, u, v, d, hit)
    inside = hit & outward
    L_in = mi.Color3f(0.0)
    T_in = mi.Float(1.0)
    # Reversed ray from the exit point; its parameter is t_hit - t.
    L_in, T_in, _, steps = walk(buf, tet, f_in, 0.0, c, s, o + d * t_hit, u, -v, -d,
                         t_hit, settings, inside, back_to_front=True)

    # -- 2. Front to back, with re-entry. --
    eps = settings.retrace_eps
    L = mi.Color3f(L_in)
    T = mi.Float(T_in)
    t = dr.select(inside, t_hit, 0.0)
    first = mi.Bool(True)
    active &= T > settings.t_min
    while dr.hint(active, label="tetvr_reenter"):
        start = dr.select(first, t, t + eps)
        first = mi.Bool(False)
        o_r = o + d * start
        si = scene.ray_intersect_preliminary(mi.Ray3f(o_r, d, t_max - start),
                                             active=active)
        # Only boundary faces the ray enters through start a walk.
        face = boundary_face_index(si, shapes, face_offsets)
        entering = active & si.is_valid()
        tet, f_in, t_e, c, s, outward = face_entry(buf, face, o, u, v, d, entering)
        entering &= ~outward
        L_seg, T_seg, t_end, n = walk(buf, tet, f_in, dr.maximum(t_e, start), c, s,
                                   o, u, v, d, t_max, settings, entering,
                                   back_to_front=False)
        L += T * L_seg
        T *= T_seg
        steps += n
        # An outgoing face here means the ray is on a face the walk just left
        # (round-off): step past it.
        t = dr.select(entering, t_end,
                      dr.select(si.is_valid(), start + si.t, t_max))
        active &= si.is_valid() & (T > settings.t_min) & (t < t_max)
    return L, T, steps
