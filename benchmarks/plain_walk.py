"""The baseline of the render benchmarks: a plain tet walk in Dr.Jit, as one
would first write it (Weiler et al. 2003, "Hardware-based ray casting for
tetrahedral meshes").

Per step it reads the tet's four vertex indices and all four vertex
positions, intersects the ray with the planes of the four faces (normals
from cross products of the edges), leaves through the nearest face whose
plane the ray crosses outwards (other than the entry face), interpolates
the optical model's attributes at the exit point with the barycentric
weights of that point in the exit face (areas of the sub-triangles), reads
the neighbour across and integrates the segment with the *same* segment
integral as ``tetvr`` (``ts.model.segment``: same ``n_sub``). Rays enter the
mesh where ``tetvr``'s rays enter it (the same BVH hit and boundary face),
stop at the same transmittance, and the mesh must be convex (one entry,
one exit: the benchmark grid is a box).

The segment integral is ``tetvr``'s own (``integral="model"``) or the one
``tetvr`` used before (``integral="alg1"``): DiffTetVR's Alg. 1 as printed,
with the corrected Alg. 3 on each of ``n_sub`` sub-intervals of constant
extinction and linear color (:func:`alg1_segment`).

It differs from ``tetvr``'s walk (:mod:`mi_tetvr.render.walk`) only in what
a step reads and computes: ``tetvr`` keeps the entry face's corners from the
previous step and reads one vertex, and decides the exit face with the
consistent edge predicate instead of plane intersections.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_tetvr.mesh.topology import FACES
from mi_tetvr.render.buffers import unpack_link
from mi_tetvr.render.geometry import RayFrame, face_entry, ray_frame
from mi_tetvr.render.pytree import tree_select, weighted_sum
from mi_tetvr.render.segment import interval_terms


def _local(f, j):
    """``FACES[f][j]`` for a ``UInt32`` face ``f``."""
    return mi.UInt32(dr.select(f == 0, int(FACES[0][j]), dr.select(
        f == 1, int(FACES[1][j]), dr.select(f == 2, int(FACES[2][j]), int(FACES[3][j])))))


class PlainBuffers:
    """The plain walk's own tet arrays, as a first implementation keeps them:
    ``tets`` (4 m corners) and ``nbr`` (4 m links), read with one gather per
    corner; the same whatever layout the renderer's own buffers have (a
    32-byte cell of corners and links per tet, or, in checkouts before it,
    these two arrays), so that the baseline stays the same across checkouts."""

    def __init__(self, ts):
        import numpy as np
        buf = ts.buf
        if getattr(buf, "cells", None) is not None:
            c = np.asarray(buf.cells).reshape(-1, 8)
            self.tets = mi.UInt32(np.ascontiguousarray(c[:, :4]).ravel())
            self.nbr = mi.Int32(np.ascontiguousarray(c[:, 4:]).view(np.int32).ravel())
        else:
            self.tets, self.nbr = buf.tets, buf.nbr
        dr.eval(self.tets, self.nbr)


def _exit_point_weights(X, Pa, Pb, Pc, n):
    """Barycentric weights of the point ``X`` of the plane of triangle
    ``(Pa, Pb, Pc)`` with normal ``n`` (sub-triangle areas)."""
    inv = dr.rcp(dr.squared_norm(n))
    wa = dr.dot(dr.cross(Pb - X, Pc - X), n) * inv
    wb = dr.dot(dr.cross(Pc - X, Pa - X), n) * inv
    return wa, wb, 1.0 - wa - wb


def _face_hit(P, f, o, d):
    """Plane of local face ``f`` of the tet with corners ``P``: the ray
    parameter where the ray meets it and whether it leaves through it."""
    a, b, c = (int(x) for x in FACES[f])
    n = dr.cross(P[b] - P[a], P[c] - P[a])
    den = dr.dot(n, d)
    leaving = den > 0
    t = dr.dot(n, P[a] - o) * dr.rcp(dr.select(leaving, den, 1.0))
    return t, leaving, n


def alg1_segment(length, c0, c1, s0, s1, n_sub: int):
    """DiffTetVR Alg. 1: ``n_sub`` sub-intervals of constant extinction (at
    their midpoints) and linear color, each integrated in closed form
    (corrected Alg. 3, series for small optical depth); ``(C, T)``."""
    dt = length * (1.0 / n_sub)
    C = dr.zeros(mi.Color3f, dr.width(length))
    T = dr.ones(mi.Float, dr.width(length))
    for i in range(n_sub):
        x = dt * dr.lerp(s0, s1, (i + 0.5) / n_sub)
        A = dr.exp(-x)
        one_minus_A, h = interval_terms(x, A)
        ci0 = dr.lerp(c0, c1, i / n_sub)
        ci1 = dr.lerp(c0, c1, (i + 1) / n_sub)
        C += T * (one_minus_A * ci0 + h * (ci0 - ci1))
        T *= A
    return C, T


@dr.syntax
def plain_trace(scene, ts, ray, t_min: float, max_steps: int, integral: str = "model",
                plain: PlainBuffers | None = None):
    """Emission, transmittance and tets crossed along ``ray`` (normalized
    directions) through the convex tet mesh of ``scene`` (``ts`` its
    :class:`~mi_tetvr.render.buffers.TetGroup`; ``plain`` its
    :class:`PlainBuffers`, made once)."""
    buf, model, params = ts.buf, ts.model, ts.params
    plain = plain if plain is not None else PlainBuffers(ts)
    o = mi.Point3f(ray.o)
    d = mi.Vector3f(ray.d)
    si = scene.ray_intersect_preliminary(mi.Ray3f(o, d))
    active = mi.Bool(si.is_valid())
    u, v = ray_frame(d)
    tet, f_in, outward = face_entry(buf, ts.boundary_face(si), RayFrame(o, d, u, v), active)
    # Attributes where the ray enters: weights of the hit point in the face.
    t = mi.Float(dr.select(active, si.t, 0.0))
    ids = [dr.gather(mi.UInt32, plain.tets, tet * 4 + _local(f_in, j), active)
           for j in range(3)]
    Pe = [buf.position(i, active) for i in ids]
    we = _exit_point_weights(o + t * d, *Pe, dr.cross(Pe[1] - Pe[0], Pe[2] - Pe[0]))
    a = weighted_sum(we, [model.gather(params, i, active) for i in ids])
    L = mi.Color3f(0.0)
    T = mi.Float(1.0)
    steps = mi.UInt32(0)
    while dr.hint(active, label="plain_walk"):
        vid = [dr.gather(mi.UInt32, plain.tets, tet * 4 + j, active) for j in range(4)]
        P = [buf.position(i, active) for i in vid]
        t_out = mi.Float(dr.inf)
        f_out = mi.UInt32(0)
        n_out = mi.Vector3f(0.0)
        for f in range(4):
            t_f, leaving, n_f = _face_hit(P, f, o, d)
            better = leaving & (f_in != f) & (t_f < t_out)
            t_out = dr.select(better, t_f, t_out)
            f_out = dr.select(better, f, f_out)
            n_out = dr.select(better, n_f, n_out)
        found = dr.isfinite(t_out)       # no outward face only after round-off
        t_out = dr.select(found, dr.maximum(t_out, t), t)
        n_out = dr.select(found, n_out, mi.Vector3f(1.0, 0.0, 0.0))
        # The exit face's corners (FACES[f_out]) and the attributes there.
        corner = []
        for j in range(3):
            loc = _local(f_out, j)
            corner.append((dr.select(loc == 0, vid[0], dr.select(loc == 1, vid[1],
                           dr.select(loc == 2, vid[2], vid[3]))),
                           dr.select(loc == 0, P[0], dr.select(loc == 1, P[1],
                                     dr.select(loc == 2, P[2], P[3])))))
        w = _exit_point_weights(o + t_out * d, *(c[1] for c in corner), n_out)
        a_out = weighted_sum(w, [model.gather(params, c[0], active) for c in corner])
        if dr.hint(integral == "alg1", mode="scalar"):
            C_seg, T_seg = alg1_segment(t_out - t, a.c, a_out.c, a.s, a_out.s, model.n_sub)
        else:
            C_seg, T_seg, _ = model.segment(params, t_out - t, a, a_out)
        L += T * C_seg
        T *= T_seg
        t = t_out
        a = tree_select(active, a_out, a)
        steps += 1
        link = dr.gather(mi.Int32, plain.nbr, tet * 4 + f_out, active)
        tet, f_in = unpack_link(link)
        active &= found & (link >= 0) & (T > t_min) & (steps < max_steps)
    return L, T, steps
