"""Rays drawn at random from all training photos, as nerfstudio's pixel sampler
draws them: each step of a fit renders a batch of rays spread over every photo
instead of two whole photos, so each step's gradient sees many views.

:class:`PixelSampler` holds the photos' pixels and cameras on the device, made
once per stage: a draw picks pixels uniformly over all of them (each photo in
proportion to its pixels), a point in each pixel (jittered, or the centre for
data rendered through pixel centres), the ray through it
(:func:`~mi_tetvr.camera.drjit_rays`, the one pinhole formula) and the photo's
value there. The rays are rendered by :func:`mi_tetvr.rays.render_rays`.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_tetvr.camera import drjit_rays

__all__ = ["PixelSampler"]


class PixelSampler:
    """Random pixels of a list of posed photos (:class:`~mi_tetvr.recon.datasets.View`).

    Parameters
    ----------
    views : list of View
        Photos with images (premultiplied linear RGBA) and pinhole cameras.
    """

    def __init__(self, views) -> None:
        if any(v.camera.pixel_size is not None for v in views):
            raise ValueError("random rays are drawn from pinhole photos (not orthographic "
                             "X-ray projections)")
        cams = [v.camera for v in views]
        sizes = np.array([c.width * c.height for c in cams], np.int64)
        #: Pixels in all photos.
        self.total = int(sizes.sum())
        if self.total >= 2 ** 31:
            raise ValueError(f"{self.total:,} pixels in the photos: at most 2^31 are drawn from")
        self.count = len(views)
        self._first = mi.UInt32(np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.uint32))
        self._pixels = mi.Float(np.concatenate([np.asarray(v.image, np.float32).ravel()
                                                for v in views]))
        per = np.array([[c.width, c.fx, c.fy, c.cx, c.cy, *c.to_world[:3].ravel()]
                        for c in cams], np.float32)
        self._cameras = [mi.Float(np.ascontiguousarray(per[:, j])) for j in range(per.shape[1])]
        self._ends = mi.UInt32(np.cumsum(sizes).astype(np.uint32))
        dr.eval(self._first, self._pixels, self._cameras, self._ends)

    def draw(self, k: int, seed: int, jitter: bool = True):
        """``(ray, target, photo)``: ``k`` rays through pixels drawn uniformly over all
        photos (``mi.Ray3f``), each pixel's value (``mi.TensorXf`` ``(k, 4)``) and the
        index of its photo (``mi.UInt32``). ``seed`` picks them (the same seed, the same
        draw); ``jitter``: a uniform point in each pixel, else its centre."""
        rng = mi.PCG32(size=k, initstate=dr.opaque(mi.UInt64, seed))   # (one kernel)
        flat = dr.minimum(mi.UInt32(rng.next_float32() * self.total), self.total - 1)
        # the photo holding each pixel: the first whose end lies past it
        photo = dr.binary_search(0, self.count - 1,
                                 lambda i: dr.gather(mi.UInt32, self._ends, i) <= flat)
        p = flat - dr.gather(mi.UInt32, self._first, photo)
        c = [dr.gather(mi.Float, a, photo) for a in self._cameras]
        # (in float64: Dr.Jit's LLVM backend faults on an integer division by a
        # per-lane divisor, its unused lanes dividing by zero)
        row = mi.UInt32(dr.floor((mi.Float64(p) + 0.5) / mi.Float64(c[0])))
        col = p - row * mi.UInt32(c[0])
        if jitter:
            du, dv = rng.next_float32(), rng.next_float32()
        else:
            du = dv = 0.5
        ray = drjit_rays(mi.Float(col) + du, mi.Float(row) + dv, c[1:5],
                         [c[5:9], c[9:13], c[13:17]])
        index = 4 * (dr.gather(mi.UInt32, self._first, photo) + p)
        rgba = mi.Vector4f(*(dr.gather(mi.Float, self._pixels, index + j) for j in range(4)))
        target = mi.TensorXf(dr.ravel(rgba), (k, 4))
        return ray, target, photo
