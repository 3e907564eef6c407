"""Linear functions inside one tet (pure Dr.Jit, differentiable).

A per-vertex value is linear inside a tet: ``u(x) = sum_k lambda_k(x) u_k``
with the barycentric coordinates ``lambda_k``, themselves affine in ``x``
(extended outside the tet by the same formula). Everything here is a closed
form of the tet's four corners, so Dr.Jit's AD differentiates it w.r.t. the
values and the positions: the derivative passes of the models that show one
point per ray (isosurfaces, slices, extreme values:
:meth:`~mi_tetvr.render.probes.Probe.replay`) recompute that point here,
in the tet the walk found it in, instead of re-walking the ray.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import drjit as dr
import mitsuba as mi

from mi_tetvr.render.buffers import MeshBuffers

if TYPE_CHECKING:
    from mi_tetvr.render.optical import Shaded


class TetFrame:
    """A tet's corners and barycentric frame.

    ids : 4 UInt32 (global vertex indices), X : 4 Point3f (positions),
    B : Matrix3f with ``(lambda_1, lambda_2, lambda_3)(x) = B (x - X[0])``
    (the inverse of the matrix whose columns are the edges ``X[k] - X[0]``),
    det : Float (six times the signed volume).

    ``reduce`` is the scatter strategy of the position gathers' derivative
    (default: the buffers' own).
    """

    def __init__(self, buf: MeshBuffers | Shaded.Params, tet: mi.UInt32,
                 active: bool | mi.Bool = True, reduce: dr.ReduceMode | None = None) -> None:
        rec = buf.corners(tet, active)
        self.ids = [rec.x, rec.y, rec.z, rec.w]
        self.X = [buf.position(i, active) if reduce is None else buf.position(i, active, reduce)
                  for i in self.ids]
        e = [self.X[k] - self.X[0] for k in (1, 2, 3)]
        M = mi.Matrix3f(e[0].x, e[1].x, e[2].x,
                        e[0].y, e[1].y, e[2].y,
                        e[0].z, e[1].z, e[2].z)
        self.det = dr.det(M)
        self.B = dr.rcp(M)

    def weights(self, x: mi.Point3f) -> list[mi.Float]:
        """The four barycentric coordinates of point ``x``."""
        lam = self.B @ mi.Vector3f(x - self.X[0])
        return [1.0 - lam.x - lam.y - lam.z, lam.x, lam.y, lam.z]

    def weight_gradients(self) -> list[mi.Vector3f]:
        """The (constant) gradients of the four barycentric coordinates."""
        rows = [mi.Vector3f(self.B[k]) for k in range(3)]
        return [-(rows[0] + rows[1] + rows[2])] + rows

    def gradient(self, values: Sequence[mi.Float]) -> mi.Vector3f:
        """The gradient of the linear function with ``values`` at the corners."""
        du = mi.Vector3f(values[1] - values[0], values[2] - values[0], values[3] - values[0])
        return self.B.T @ du

    def at(self, values: Sequence[mi.Float], x: mi.Point3f) -> mi.Float:
        """The linear function with ``values`` at the corners, at point ``x``."""
        return sum(w * v for w, v in zip(self.weights(x), values))


def vertex_gradients(buf: MeshBuffers, scalar: mi.Float) -> mi.Float:
    """Flat ``Float`` (3 n): each vertex's gradient of a per-vertex ``scalar``
    (``Float``, n), the gradients of the tets around it (constant in each)
    averaged by volume; flat and folded tets are left out. Differentiable
    w.r.t. the scalar and the positions."""
    n = dr.width(scalar)
    frame = TetFrame(buf, dr.arange(mi.UInt32, buf.n_tets))
    g = frame.gradient([dr.gather(mi.Float, scalar, i) for i in frame.ids])
    vol = dr.abs(frame.det)
    ok = (vol > 0.0) & dr.all(dr.isfinite(g))
    vol = dr.select(ok, vol, 0.0)
    g = dr.select(ok, g, 0.0)
    total = dr.zeros(mi.Float, 3 * n)
    weight = dr.zeros(mi.Float, n)
    for i in frame.ids:
        dr.scatter_reduce(dr.ReduceOp.Add, total, g * vol, i)
        dr.scatter_reduce(dr.ReduceOp.Add, weight, vol, i)
    v = dr.arange(mi.UInt32, n)
    w = dr.gather(mi.Float, weight, v)
    mean = dr.select(w > 0.0, dr.gather(mi.Vector3f, total, v) / dr.select(w > 0.0, w, 1.0), 0.0)
    return dr.ravel(mean)
