"""Real lenses in, pinholes out: images of distorted or non-square-pixel
cameras are resampled at load into square-pixel pinhole images, which is what
Mitsuba's ``perspective`` sensor renders.

The lens models are COLMAP's, evaluated by pycolmap (``OPENCV``:
``k1, k2, p1, p2``; ``FULL_OPENCV``: also ``k3 .. k6``; ``OPENCV_FISHEYE``:
``k1 .. k4``; ``SIMPLE_RADIAL``, ``RADIAL``; ``PINHOLE`` with ``fx != fy``).
The pinhole keeps the image size and principal point; its focal length is
the larger of ``fx, fy`` times the smallest zoom at which every pixel of the
new image sees a point of the old one (the widest view without invented
borders, as COLMAP's undistorter with ``blank_pixels = 0``). Resampling is bilinear on the
premultiplied linear RGBA (:func:`scipy.ndimage.map_coordinates`). Pixel
coordinates are those of :mod:`mi_tetvr.camera` (and COLMAP): the
top-left corner at 0, centres at +0.5.
"""
from __future__ import annotations

import numpy as np

from mi_tetvr.extras import needs

__all__ = ["Lens", "SQUARE_RTOL", "nerf_lens"]

#: Focal lengths ``fx, fy`` this close (relative) count as square pixels and
#: become their geometric mean without resampling (a real calibration's
#: 0.075 % moves a border pixel of a 1000-pixel image by 0.4 pixels; 0.1 %
#: by at most 0.5).
SQUARE_RTOL = 1e-3

#: transforms.json distortion keys, per COLMAP model, in pycolmap's order.
_NERF_MODELS = {
    "OPENCV": ("k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4"),
}


class Lens:
    """A camera's intrinsics as COLMAP models them, and the pinhole its
    images are resampled to.

    Parameters
    ----------
    camera : pycolmap.Camera
        The model, image size and parameters (focal lengths, principal
        point, distortion); :meth:`from_params` makes one.
    """

    def __init__(self, camera):
        self.camera = camera
        self.width, self.height = int(camera.width), int(camera.height)
        fx, fy = camera.focal_length_x, camera.focal_length_y
        self.cx, self.cy = camera.principal_point_x, camera.principal_point_y
        extra = np.asarray(camera.params)[list(camera.extra_params_idxs())]
        square = abs(fx - fy) <= SQUARE_RTOL * max(fx, fy)
        #: Whether the images need resampling (distortion, or pixels not square).
        self.resample = bool(np.any(extra != 0) or not square)
        self.f = max(fx, fy) * self._zoom() if self.resample else float(np.sqrt(fx * fy))

    @classmethod
    def from_params(cls, model, width, height, params):
        """The lens of a COLMAP ``model`` with pycolmap's ``params``."""
        with needs("sfm", "undistorting photos"):
            import pycolmap
        return cls(pycolmap.Camera(model=model, width=int(width), height=int(height),
                                   params=[float(p) for p in params]))

    def resized(self, width, height):
        """The lens of the same pictures stored at ``width x height``."""
        with needs("sfm", "undistorting photos"):
            import pycolmap
        camera = pycolmap.Camera(model=self.camera.model, width=self.width, height=self.height,
                                 params=self.camera.params)
        camera.rescale(int(width), int(height))
        return Lens(camera)

    def pinhole(self):
        """``(fx, fy, cx, cy)`` of the square-pixel pinhole of the images."""
        return self.f, self.f, self.cx, self.cy

    def _source(self, x, y, f):
        """Pixel positions in the original image seen by pixel positions
        ``x, y`` of a pinhole with focal length ``f``."""
        rays = np.stack([(x - self.cx) / f, (y - self.cy) / f, np.ones_like(x)], -1)
        return self.camera.img_from_cam(rays.reshape(-1, 3).astype(np.float64))

    def _zoom(self):
        """The smallest zoom of the larger focal length (in [0.5, 4]) at
        which the border of the pinhole image maps inside the original one:
        above 1 for pincushion distortion, below for barrel distortion."""
        t = np.linspace(0.0, 1.0, 129)
        w, h = self.width, self.height
        x = np.concatenate([t * w, t * w, np.zeros_like(t), np.full_like(t, w)])
        y = np.concatenate([np.zeros_like(t), np.full_like(t, h), t * h, t * h])
        f0 = max(self.camera.focal_length_x, self.camera.focal_length_y)

        def inside(zoom):
            uv = self._source(x, y, f0 * zoom)
            return np.all(np.isfinite(uv)) and np.all(uv >= -1e-6) and \
                np.all(uv[:, 0] <= w + 1e-6) and np.all(uv[:, 1] <= h + 1e-6)

        lo, hi = 0.5, 4.0
        if inside(lo):
            return lo
        if not inside(hi):
            raise ValueError(f"lens {self.camera}: even 4x zoomed in, the undistorted image "
                             f"would leave the original (the distortion looks wrong)")
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if inside(mid) else (mid, hi)
        return hi

    def undistort(self, image):
        """The (h, w, c) image (float) as the pinhole sees it (a copy)."""
        with needs("recon", "undistorting photos"):
            from scipy.ndimage import map_coordinates
        image = np.asarray(image, np.float32)
        h, w = image.shape[:2]
        if (w, h) != (self.width, self.height):
            raise ValueError(f"image of {w}x{h} for a lens of {self.width}x{self.height}")
        if not self.resample:
            return image.copy()
        y, x = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
        uv = self._source(x.ravel(), y.ravel(), self.f)
        coords = [uv[:, 1] - 0.5, uv[:, 0] - 0.5]            # array rows, columns
        out = np.empty_like(image)
        for c in range(image.shape[2]):
            out[..., c] = map_coordinates(image[..., c], coords, order=1,
                                          mode="nearest").reshape(h, w)
        return out


def nerf_lens(meta, width, height, fx, fy, cx, cy, what=""):
    """The :class:`Lens` of a transforms.json frame (its keys merged over the
    file's), or ``None`` for a square-pixel pinhole without distortion.

    ``camera_model`` (default ``OPENCV``) names the distortion keys read:
    ``k1, k2, p1, p2`` (and ``k3 .. k6``, which make it ``FULL_OPENCV``) or,
    for ``OPENCV_FISHEYE``, ``k1 .. k4``.
    """
    model = str(meta.get("camera_model", "OPENCV")).upper()
    if model in ("PINHOLE", "SIMPLE_PINHOLE"):
        model = "OPENCV"
    if model not in _NERF_MODELS:
        raise ValueError(f"{what}: camera_model {meta.get('camera_model')!r} is not supported "
                         f"(use one of {', '.join(['PINHOLE', *_NERF_MODELS])}, or undistort "
                         f"the images first)")
    if model == "OPENCV" and any(float(meta.get(k, 0.0)) for k in ("k3", "k4", "k5", "k6")):
        model = "FULL_OPENCV"
    keys = _NERF_MODELS[model]
    extra = sorted(k for k in ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")
                   if k not in keys and float(meta.get(k, 0.0)))
    if extra:
        raise ValueError(f"{what}: distortion keys {extra} do not belong to camera_model "
                         f"{model}")
    dist = [float(meta.get(k, 0.0)) for k in keys]
    if not any(dist) and abs(fx - fy) <= SQUARE_RTOL * max(fx, fy):
        return None
    return Lens.from_params(model, width, height, [fx, fy, cx, cy, *dist])
