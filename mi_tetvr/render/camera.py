"""Differentiable camera poses for ``tetvr``.

The derivative passes of ``tetvr`` differentiate the image w.r.t. the rays
when the sensor's ``to_world`` carries gradients (reverse and forward mode
through ``mi.render``; :mod:`mi_tetvr.render.adjoint`): move or turn the
camera and the image changes as if the mesh had moved the other way. What is left out
is the silhouette: which pixels see the mesh at all has no boundary term, so
a camera gradient is exact for a volume whose boundary is transparent and
misses the edge term where the boundary is opaque.

:func:`orbit_to_world` parameterizes a camera by longitude, latitude and
distance around a target (what viewpoint optimization searches over); its
result is a Dr.Jit ``AffineTransform4f`` that stays attached to its inputs,
to assign to ``params["<sensor id>.to_world"]``.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi


def orbit_to_world(longitude, latitude, distance, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)):
    """The ``to_world`` of a camera at ``distance`` from ``target``, at
    ``longitude`` and ``latitude`` (degrees; Dr.Jit values keep their
    gradients) about the ``up`` axis, looking at the target.

    Latitude 0 is the plane through the target orthogonal to ``up``, +90 the
    pole along ``up`` (avoid it: the view's up vector degenerates there).
    Longitude 0 lies along the first axis of ``mi.coordinate_system(up)``.
    """
    up = dr.normalize(mi.Vector3f(up))
    e1, e2 = mi.coordinate_system(up)
    lon = dr.deg2rad(mi.Float(longitude))
    lat = dr.deg2rad(mi.Float(latitude))
    direction = dr.cos(lat) * (dr.cos(lon) * e1 + dr.sin(lon) * e2) + dr.sin(lat) * up
    target = mi.Point3f(target)
    return mi.AffineTransform4f().look_at(origin=target + mi.Float(distance) * direction,
                                          target=target, up=up)
