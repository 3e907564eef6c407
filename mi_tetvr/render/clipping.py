"""Clipping: a plane and a box that cut the volume away, as ParaView's *Clip*
filter cuts a mesh before it is rendered.

Each kept region is convex, so along a ray it is one interval ``[t0, t1]``
(a slab test); the walk integrates only over it (``trace``'s ``t_start`` and
the ray's ``maxt``). The field is linear in each tet, so integrating the
uncut mesh over the interval equals rendering the mesh cut at the plane or
box (whose new vertices carry the interpolated values): the result is exact.
Surfaces of the scene are not clipped. The cut is fixed in space: its motion
with a differentiable camera has no derivative term (as the silhouettes).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import numpy.typing as npt


def unit_vector(v: npt.ArrayLike, what: str) -> np.ndarray:
    """``v`` (3,) scaled to length 1; ``ValueError`` naming ``what`` unless it
    is a non-zero 3-vector (a plane's normal)."""
    n = np.asarray(v, np.float64).reshape(-1)
    if n.shape != (3,) or not np.linalg.norm(n) > 0:
        raise ValueError(f"{what} must be a non-zero 3-vector, got {np.ravel(v).tolist()}")
    return n / np.linalg.norm(n)


class Clip:
    """A plane (``origin``, ``normal``: the side the normal points to is cut
    away) and/or a box (``box_min``, ``box_max``: what lies outside is cut
    away)."""

    def __init__(self, origin: npt.ArrayLike | None = None, normal: npt.ArrayLike | None = None,
                 box_min: npt.ArrayLike | None = None,
                 box_max: npt.ArrayLike | None = None) -> None:
        self.plane = None
        if (origin is None) != (normal is None):
            raise ValueError("clipping: give both clip_origin and clip_normal (a plane)")
        if normal is not None:
            self.plane = (np.asarray(origin, np.float64).reshape(3),
                          unit_vector(normal, "clipping: clip_normal"))
        self.box = None
        if (box_min is None) != (box_max is None):
            raise ValueError("clipping: give both clip_min and clip_max (a box)")
        if box_min is not None:
            lo, hi = (np.asarray(x, np.float64).reshape(3) for x in (box_min, box_max))
            if not np.all(hi > lo):
                raise ValueError(f"clipping: clip_max must exceed clip_min on every axis, got "
                                 f"{lo.tolist()} and {hi.tolist()}")
            self.box = (lo, hi)

    @classmethod
    def from_props(cls, props: mi.Properties) -> Clip | None:
        """The clip a ``tetvr`` or ``tetproj`` property set describes
        (``clip_origin``, ``clip_normal``, ``clip_min``, ``clip_max``); None
        without any."""
        keys = ("clip_origin", "clip_normal", "clip_min", "clip_max")
        got = {k: list(props[k]) for k in keys if k in props}
        if not got:
            return None
        return cls(got.get("clip_origin"), got.get("clip_normal"), got.get("clip_min"),
                   got.get("clip_max"))

    def interval(self, o: mi.Point3f, d: mi.Vector3f,
                 t_max: float | mi.Float) -> tuple[mi.Float, mi.Float]:
        """``(t0, t1)``: the part of the rays ``o + t d`` (``0 <= t <=
        t_max``) that is kept; empty where ``t1 <= t0``."""
        t0, t1 = mi.Float(0.0), mi.Float(t_max)
        if self.plane is not None:
            p, n = self.plane
            s0 = dr.dot(o - mi.Point3f(*p.tolist()), mi.Vector3f(*n.tolist()))
            dn = dr.dot(d, mi.Vector3f(*n.tolist()))
            # keep s0 + t dn <= 0
            cross = -s0 / dr.select(dn != 0.0, dn, 1.0)
            t1 = dr.select(dn > 0.0, dr.minimum(t1, cross), t1)
            t0 = dr.select(dn < 0.0, dr.maximum(t0, cross), t0)
            t1 = dr.select((dn == 0.0) & (s0 > 0.0), -1.0, t1)
        if self.box is not None:
            lo, hi = self.box
            for axis in range(3):
                oa, da = o[axis], d[axis]
                inv = 1.0 / dr.select(da != 0.0, da, 1.0)
                a, b = (float(lo[axis]) - oa) * inv, (float(hi[axis]) - oa) * inv
                near, far = dr.minimum(a, b), dr.maximum(a, b)
                outside = (da == 0.0) & ((oa < float(lo[axis])) | (oa > float(hi[axis])))
                t0 = dr.select(da != 0.0, dr.maximum(t0, near), t0)
                t1 = dr.select(da != 0.0, dr.minimum(t1, far), dr.select(outside, -1.0, t1))
        return t0, t1

    def __repr__(self):
        parts = []
        if self.plane is not None:
            parts.append(f"plane origin={self.plane[0].tolist()} normal={self.plane[1].tolist()}")
        if self.box is not None:
            parts.append(f"box {self.box[0].tolist()}..{self.box[1].tolist()}")
        return "Clip[" + ", ".join(parts) + "]"
