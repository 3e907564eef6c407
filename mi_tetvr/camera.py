"""Pinhole cameras: the one place where the camera convention is written.

A :class:`Camera` is a pinhole camera: image size, focal lengths and principal point in pixels,
and a rigid camera-to-world matrix in Mitsuba's axes. It projects points, generates rays (as
numpy arrays with :meth:`Camera.rays`, as a Dr.Jit ``mi.Ray3f`` with :meth:`Camera.rays_drjit`),
builds the Mitsuba ``perspective`` sensor that reproduces it exactly
(:meth:`Camera.sensor_dict`) and converts from and to the OpenGL (NeRF) and OpenCV (COLMAP)
camera axes. :func:`fibonacci_cameras` and :func:`random_cameras` place cameras on a sphere
around a target, :func:`box_cameras` around a box (at :func:`framing_distance`, the one
distance at which a field of view holds a bounding sphere), :func:`fibonacci_sphere` gives the
spiral's longitudes and latitudes, and :func:`orbit_to_world` a differentiable Dr.Jit pose
by longitude, latitude and distance (camera gradients through ``mi.render``). Everything but
:meth:`Camera.rays_drjit` and :meth:`Camera.sensor_dict` is numpy and works without a Mitsuba
variant.

.. rubric:: Conventions

Camera frame (Mitsuba)
    The camera looks along **+z**, **+y is up** in the image and **+x is to the image's left**;
    this is the frame ``mi.ScalarTransform4f().look_at`` builds and the one of Mitsuba's
    ``perspective`` sensor. ``Camera.to_world`` is the rigid (4, 4) camera-to-world matrix in
    this frame: its columns are the camera's left, up and forward axes and its center.
Other camera frames
    OpenGL / NeRF / instant-ngp cameras look along -z, y up, x right:
    ``to_world = c2w_opengl @ OPENGL_TO_MITSUBA`` with ``OPENGL_TO_MITSUBA = diag(-1, 1, -1, 1)``.
    OpenCV / COLMAP cameras look along +z, y down, x right:
    ``to_world = c2w_opencv @ OPENCV_TO_MITSUBA`` with ``OPENCV_TO_MITSUBA = diag(-1, -1, 1, 1)``;
    COLMAP stores the world-to-camera ``[R | t]``, so ``c2w_opencv = inv([R | t])``. Both
    matrices are involutions: ``c2w_opengl = to_world @ OPENGL_TO_MITSUBA`` (and likewise for
    OpenCV).
Pixel coordinates
    Continuous image coordinates ``(u, v)`` have the **top-left corner of the image at (0, 0)**,
    ``u`` to the right and ``v`` down; the center of pixel ``(i, j)`` (column, row) is at
    ``(i + 0.5, j + 0.5)``. This is COLMAP's convention, the one of instant-ngp / nerfstudio's
    ``cx, cy`` (default ``w / 2``) and the one of Mitsuba's film (pixel ``i`` covers film
    positions ``[i, i + 1) / W``). Hence downscaling by an integer factor ``f`` divides
    ``fx, fy, cx, cy`` by ``f`` exactly (after cropping the right / bottom remainder ``W % f``,
    ``H % f``, which does not move the origin), and an image stored at another size scales
    ``fx, cx`` by the width ratio and ``fy, cy`` by the height ratio.
Projection
    A camera-frame point ``(x, y, z)`` lands at ``u = cx - fx * x / z``, ``v = cy - fy * y / z``;
    ``z`` (> 0 in front of the camera) is its depth. The ray through ``(u, v)`` has the
    camera-frame direction ``((cx - u) / fx, (cy - v) / fy, 1)``, normalized. An OpenCV
    intrinsic matrix ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` projects in the OpenCV
    frame of ``c2w_opencv``.
Rays
    Rays start at the camera center and have unit directions. Without explicit pixel positions
    they go through every pixel center, in row-major order from the top-left pixel
    (``k = row * width + column``), so that ``(k, ...)`` arrays reshape to ``(H, W, ...)``.
Mitsuba sensor
    ``perspective`` with ``fov_axis='x'``, ``fov = 2 atan(W / (2 fx))`` (degrees) and
    ``principal_point_offset_x = 0.5 - cx / W``, ``principal_point_offset_y = 0.5 - cy / H``.
    Mitsuba adds the offsets (in units of the film width / height) to the film position before
    the centered projection, so a film position ``u`` looks where a centered camera's ``u + ox W``
    would (``tests/recon/test_camera.py`` checks this with ``sensor.sample_ray``). Mitsuba's
    perspective camera has square pixels, so ``fx != fy`` is refused (relative tolerance
    ``square_rtol``).
Generated cameras
    :func:`fibonacci_cameras` and :func:`random_cameras` put cameras on a sphere of ``radius``
    around ``target``, looking at it with the image center as principal point;
    :func:`default_fov` is the horizontal field of view that frames the ``[-1, 1]^3`` box
    from distance ``radius``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np

from mi_tetvr.extras import needs


__all__ = ["Camera", "look_at", "as_rigid", "default_fov", "framing_distance", "FRAMING_MARGIN",
           "fibonacci_cameras", "random_cameras", "fibonacci_sphere", "box_cameras",
           "orbit_to_world", "check_factor", "camera_path", "cameras_focus", "drjit_rays",
           "OPENGL_TO_MITSUBA", "OPENCV_TO_MITSUBA"]

#: ``c2w_opengl @ OPENGL_TO_MITSUBA`` is Mitsuba's ``to_world`` (and vice versa: an involution).
OPENGL_TO_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])
#: ``c2w_opencv @ OPENCV_TO_MITSUBA`` is Mitsuba's ``to_world`` (COLMAP cameras).
OPENCV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])


# --------------------------------------------------------------------------------------------
# Poses
# --------------------------------------------------------------------------------------------

def look_at(origin, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world matrix in Mitsuba axes, as ``mi.ScalarTransform4f().look_at``.

    If ``up`` is (nearly) parallel to the view direction, another up vector (the world axis
    least aligned with the view direction) is used.

    Parameters
    ----------
    origin, target, up : (3,) float

    Returns
    -------
    (4, 4) float64
    """
    o = np.asarray(origin, np.float64)
    d = np.asarray(target, np.float64) - o
    d /= np.linalg.norm(d)
    u = np.asarray(up, np.float64)
    u = u / np.linalg.norm(u)
    if abs(np.dot(u, d)) > 0.999:
        u = np.eye(3)[np.argmin(np.abs(d))]
    left = np.cross(u, d)
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
    return m


def as_rigid(m, what: str = "camera", tol: float = 1e-3) -> np.ndarray:
    """Check that a camera-to-world matrix is rigid and snap its rotation to SO(3).

    Parameters
    ----------
    m : (4, 4) or (3, 4) float
    what : str
        Names the matrix in the error message.
    tol : float
        Largest accepted deviation of ``R^T R`` from the identity and of the last row from
        ``(0, 0, 0, 1)``.

    Returns
    -------
    (4, 4) float64
        The nearest rotation (polar decomposition) and the same translation; a
        matrix that is a rotation to float64 precision is returned unchanged.

    Raises
    ------
    ValueError
        Wrong shape, or scale, shear or reflection beyond ``tol`` (Mitsuba sensors must be
        rigid).
    """
    m = np.asarray(m, np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    if m.shape != (4, 4):
        raise ValueError(f"{what}: expected a 4x4 (or 3x4) matrix, got shape {m.shape}")
    r = m[:3, :3]
    if np.abs(r.T @ r - np.eye(3)).max() > tol or np.linalg.det(r) < 0 \
            or np.abs(m[3] - [0, 0, 0, 1]).max() > tol:
        raise ValueError(f"{what}: camera-to-world matrix is not a rotation + translation "
                         f"(scale, shear or reflection); Mitsuba sensors must be rigid")
    out = np.eye(4)
    out[:3, 3] = m[:3, 3]
    if np.abs(r.T @ r - np.eye(3)).max() <= 8 * np.finfo(np.float64).eps:
        out[:3, :3] = r              # a rotation to float64 precision: kept bit for bit
    else:
        u, _, vt = np.linalg.svd(r)
        out[:3, :3] = u @ vt
    return out


def _quat_xyzw_to_matrix(q) -> np.ndarray:
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


# --------------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------------

@dataclass
class Camera:
    """A pinhole camera (see the module docstring for the convention).

    Attributes
    ----------
    width, height : int
        Image size in pixels.
    fx, fy : float
        Focal lengths in pixels.
    cx, cy : float
        Principal point in pixels, top-left image corner at (0, 0), pixel centers at +0.5.
    to_world : (4, 4) float64
        Rigid Mitsuba camera-to-world matrix (camera looks along +z, y up, x to the left).
    pixel_size : float or None
        ``None`` for a pinhole camera; for an orthographic (parallel-beam) one
        the world size of a pixel (square pixels): the ray through pixel
        position ``(u, v)`` starts at ``to_world (s (cx - u), s (cy - v), 0)``
        and runs along the camera's +z; ``fx, fy`` are then unused.
    """
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    to_world: np.ndarray
    pixel_size: Optional[float] = None

    def __post_init__(self):
        self.width, self.height = int(self.width), int(self.height)
        self.fx, self.fy = float(self.fx), float(self.fy)
        self.cx, self.cy = float(self.cx), float(self.cy)
        self.to_world = np.asarray(self.to_world, dtype=np.float64).reshape(4, 4)
        if self.pixel_size is not None:
            self.pixel_size = float(self.pixel_size)
            if not self.pixel_size > 0:
                raise ValueError(f"an orthographic camera needs pixel_size > 0, got "
                                 f"{self.pixel_size}")

    @classmethod
    def orthographic(cls, origin, target, up, width: int, height: int,
                     pixel_size: float) -> "Camera":
        """A parallel-beam camera looking from ``origin`` towards ``target``:
        ``width x height`` pixels of ``pixel_size`` world units, centred on the
        axis through ``origin``."""
        return cls(width, height, 1.0, 1.0, width / 2, height / 2, look_at(origin, target, up),
                   pixel_size)

    @property
    def is_orthographic(self) -> bool:
        """Whether this is a parallel-beam camera (:attr:`pixel_size` set)."""
        return self.pixel_size is not None

    # -- constructors -----------------------------------------------------------------------
    @classmethod
    def look_at(cls, origin, target, up, width: int, height: int, *,
                fov_x: Optional[float] = None, fx: Optional[float] = None,
                cx: Optional[float] = None, cy: Optional[float] = None) -> "Camera":
        """A camera at ``origin`` looking at ``target`` (:func:`look_at`), square pixels.

        Parameters
        ----------
        origin, target, up : (3,) float
        width, height : int
        fov_x : float, optional
            Horizontal field of view in degrees (give this or ``fx``).
        fx : float, optional
            Focal length in pixels (``fy = fx``).
        cx, cy : float, optional
            Principal point (default: the image center ``width / 2, height / 2``).
        """
        if (fov_x is None) == (fx is None):
            raise ValueError("give exactly one of fov_x (degrees) and fx (pixels)")
        if fx is None:
            fx = 0.5 * width / math.tan(math.radians(fov_x) / 2)
        return cls(width, height, fx, fx, width / 2 if cx is None else cx,
                   height / 2 if cy is None else cy, look_at(origin, target, up))

    @classmethod
    def from_opengl(cls, c2w, width: int, height: int, fx: float, fy: float, cx: float,
                    cy: float) -> "Camera":
        """A camera from an OpenGL camera-to-world matrix (NeRF, instant-ngp: looks along -z,
        y up, x right): ``to_world = c2w @ OPENGL_TO_MITSUBA``.

        Parameters
        ----------
        c2w : (4, 4) float
        width, height : int
        fx, fy, cx, cy : float
        """
        return cls(width, height, fx, fy, cx, cy,
                   np.asarray(c2w, np.float64).reshape(4, 4) @ OPENGL_TO_MITSUBA)

    @classmethod
    def from_opencv(cls, c2w, width: int, height: int, fx: float, fy: float, cx: float,
                    cy: float) -> "Camera":
        """A camera from an OpenCV camera-to-world matrix (looks along +z, y down, x right):
        ``to_world = c2w @ OPENCV_TO_MITSUBA``.

        Parameters
        ----------
        c2w : (4, 4) float
        width, height : int
        fx, fy, cx, cy : float
        """
        return cls(width, height, fx, fy, cx, cy,
                   np.asarray(c2w, np.float64).reshape(4, 4) @ OPENCV_TO_MITSUBA)

    @classmethod
    def from_colmap(cls, quat_xyzw, translation, width: int, height: int, fx: float,
                    fy: float, cx: float, cy: float) -> "Camera":
        """A camera from COLMAP's world-to-camera pose (OpenCV axes).

        The quaternion is normalized first (COLMAP's text format stores rounded ones), so the
        pose is exactly rigid, and inverted as a rigid transform:
        ``c2w_opencv = [[R^T, -R^T t], [0, 1]]``.

        Parameters
        ----------
        quat_xyzw : (4,) float
            Rotation as a quaternion in pycolmap's ``(x, y, z, w)`` order
            (``image.cam_from_world.rotation.quat``; COLMAP's ``images.txt`` writes
            ``QW QX QY QZ``).
        translation : (3,) float
        width, height : int
        fx, fy, cx, cy : float
        """
        r = _quat_xyzw_to_matrix(quat_xyzw)
        t = np.asarray(translation, np.float64).reshape(3)
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = r.T, -r.T @ t
        return cls.from_opencv(c2w, width, height, fx, fy, cx, cy)

    # -- other axes and intrinsics ---------------------------------------------------------
    @property
    def c2w_opengl(self) -> np.ndarray:
        """(4, 4) float64: camera-to-world in OpenGL axes (NeRF's ``transform_matrix``)."""
        return self.to_world @ OPENGL_TO_MITSUBA

    @property
    def c2w_opencv(self) -> np.ndarray:
        """(4, 4) float64: camera-to-world in OpenCV axes (COLMAP's, inverted)."""
        return self.to_world @ OPENCV_TO_MITSUBA

    @property
    def center(self) -> np.ndarray:
        """(3,) float64: camera position in world space."""
        return self.to_world[:3, 3].copy()

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64: OpenCV intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``
        (for the OpenCV camera frame of :attr:`c2w_opencv`)."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def fov_x(self) -> float:
        """Horizontal field of view in degrees, ``2 atan(width / (2 fx))``."""
        return math.degrees(2.0 * math.atan(0.5 * self.width / self.fx))

    def downscaled(self, factor: int) -> "Camera":
        """The camera of the image area-averaged by an integer ``factor``.

        The right / bottom remainder (``width % factor`` etc.) is cropped, which keeps the
        top-left origin, so ``fx, fy, cx, cy`` scale by ``1 / factor`` exactly.
        """
        f = check_factor(factor)
        return Camera(self.width // f, self.height // f, self.fx / f, self.fy / f, self.cx / f,
                      self.cy / f, self.to_world.copy(),
                      None if self.pixel_size is None else self.pixel_size * f)

    def resized(self, width: int, height: int) -> "Camera":
        """The camera of the same picture stored at ``width x height`` pixels: ``fx, cx``
        scale by ``width / self.width``, ``fy, cy`` by ``height / self.height``."""
        sx, sy = width / self.width, height / self.height
        if self.pixel_size is not None and abs(sx - sy) > 1e-9 * sx:
            raise ValueError("an orthographic camera keeps square pixels: resize both axes "
                             "by the same factor")
        return Camera(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
                      self.to_world.copy(),
                      None if self.pixel_size is None else self.pixel_size / sx)

    # -- projection and rays ----------------------------------------------------------------
    def project(self, points) -> Tuple[np.ndarray, np.ndarray]:
        """Project world points with the pinhole model.

        Parameters
        ----------
        points : (k, 3) float

        Returns
        -------
        uv : (k, 2) float64
            Continuous pixel coordinates (top-left corner at 0, pixel centers at +0.5).
            NaN-free; meaningless where ``depth <= 0``.
        depth : (k,) float64
            ``z`` in the camera frame (> 0 in front of the camera).
        """
        p = np.asarray(points, np.float64).reshape(-1, 3)
        r, c = self.to_world[:3, :3], self.to_world[:3, 3]
        q = (p - c) @ r          # rows: R^T (p - c), the camera frame
        z = q[:, 2]
        if self.pixel_size is not None:
            s = self.pixel_size
            return np.stack([self.cx - q[:, 0] / s, self.cy - q[:, 1] / s], 1), z
        safe = np.where(np.abs(z) > 1e-300, z, 1e-300)
        uv = np.stack([self.cx - self.fx * q[:, 0] / safe, self.cy - self.fy * q[:, 1] / safe], 1)
        return uv, z

    def pixel_centers(self) -> np.ndarray:
        """(height * width, 2) float64: the centers ``(column + 0.5, row + 0.5)`` of all
        pixels, row-major from the top-left pixel."""
        j, i = np.divmod(np.arange(self.width * self.height), self.width)
        return np.stack([i + 0.5, j + 0.5], 1)

    def rays(self, uv=None) -> Tuple[np.ndarray, np.ndarray]:
        """Rays through pixel positions, as numpy arrays.

        Parameters
        ----------
        uv : (k, 2) float, optional
            Continuous pixel coordinates; default :meth:`pixel_centers`.

        Returns
        -------
        origins : (k, 3) float64
            The camera center (orthographic: the pixel's point of the image plane).
        directions : (k, 3) float64
            Unit world-space directions.
        """
        uv = self.pixel_centers() if uv is None else np.asarray(uv, np.float64).reshape(-1, 2)
        if self.pixel_size is not None:
            s, r = self.pixel_size, self.to_world[:3, :3]
            q = np.stack([s * (self.cx - uv[:, 0]), s * (self.cy - uv[:, 1]),
                          np.zeros(len(uv))], 1)
            o = q @ r.T + self.to_world[:3, 3]
            return o, np.broadcast_to(r[:, 2], o.shape).copy()
        d = np.stack([(self.cx - uv[:, 0]) / self.fx, (self.cy - uv[:, 1]) / self.fy,
                      np.ones(len(uv))], 1)
        d = d @ self.to_world[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.broadcast_to(self.to_world[:3, 3], d.shape).copy(), d

    def rays_drjit(self, uv=None, to_world=None):
        """Rays through pixel positions, as a Dr.Jit ``mi.Ray3f`` (needs a Mitsuba variant).

        Parameters
        ----------
        uv : mi.Point2f or (k, 2) float, optional
            Continuous pixel coordinates; default: every pixel center, in the order of
            :meth:`pixel_centers`.
        to_world : mi.Matrix4f, optional
            The camera-to-world matrix in place of :attr:`to_world`, as Dr.Jit values:
            the rays then carry its AD graph (derivatives w.r.t. the pose).

        Returns
        -------
        mi.Ray3f
            Origins at the camera center, unit directions.
        """
        import drjit as dr
        import mitsuba as mi
        if mi.variant() is None:
            raise RuntimeError("Camera.rays_drjit: call mitsuba.set_variant(...) first "
                               "(e.g. 'llvm_ad_rgb' or 'cuda_ad_rgb')")
        if uv is None:
            idx = dr.arange(mi.UInt32, self.width * self.height)
            u, v = mi.Float(idx % self.width) + 0.5, mi.Float(idx // self.width) + 0.5
        else:
            if not isinstance(uv, mi.Point2f):
                uv = mi.Point2f(*np.asarray(uv, np.float32).reshape(-1, 2).T)
            u, v = uv.x, uv.y
        m = ([[float(x) for x in row] for row in self.to_world] if to_world is None
             else to_world)
        return drjit_rays(u, v, (self.fx, self.fy, self.cx, self.cy), m, self.pixel_size)

    # -- Mitsuba ----------------------------------------------------------------------------
    def sensor_dict(self, spp: int = 1, sampler: str = "independent", *,
                    jitter: Optional[bool] = None, near_clip: Optional[float] = None,
                    far_clip: Optional[float] = None, square_rtol: float = 1e-6) -> dict:
        """A Mitsuba ``perspective`` sensor that reproduces this camera exactly.

        ``fov_axis='x'``, ``fov = 2 atan(width / (2 fx))`` in degrees,
        ``principal_point_offset_x = 0.5 - cx / width``,
        ``principal_point_offset_y = 0.5 - cy / height``, an ``hdrfilm`` of ``width x height``
        with a ``box`` filter and ``pixel_format='rgb'`` (the integrator's AOVs, e.g. ``alpha``,
        are appended by ``mi.render``).

        Parameters
        ----------
        spp : int
            Samples per pixel of the sampler.
        sampler : str
            Mitsuba sampler plugin name.
        jitter : bool, optional
            The sampler's ``jitter`` (``stratified``, ``multijitter``): False puts one sample
            at each pixel centre; None leaves the sampler's default.
        near_clip, far_clip : float, optional
            Passed to the sensor when given.
        square_rtol : float
            Mitsuba's perspective camera has square pixels: ``|fx - fy| > square_rtol * fx``
            raises ``ValueError``.

        Returns
        -------
        dict
            For ``mi.load_dict`` (needs a Mitsuba variant to be set).
        """
        import mitsuba as mi
        if self.pixel_size is not None:
            d = self._orthographic_dict(spp, sampler, near_clip, far_clip)
            if jitter is not None:
                d["sampler"]["jitter"] = bool(jitter)
            return d
        if abs(self.fx - self.fy) > square_rtol * abs(self.fx):
            raise ValueError(
                f"non-square pixels (fx={self.fx}, fy={self.fy}) cannot be represented by "
                f"Mitsuba's perspective sensor; resample the image so that fx == fy, or raise "
                f"square_rtol to accept fy := fx")
        d = {
            "type": "perspective",
            "fov_axis": "x",
            "fov": self.fov_x,
            "principal_point_offset_x": 0.5 - self.cx / self.width,
            "principal_point_offset_y": 0.5 - self.cy / self.height,
            "to_world": mi.ScalarTransform4f(self.to_world.tolist()),
            "sampler": {"type": sampler, "sample_count": int(spp)},
            "film": {"type": "hdrfilm", "width": self.width, "height": self.height,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        }
        if jitter is not None:
            d["sampler"]["jitter"] = bool(jitter)
        if near_clip is not None:
            d["near_clip"] = float(near_clip)
        if far_clip is not None:
            d["far_clip"] = float(far_clip)
        return d

    def _orthographic_dict(self, spp, sampler, near_clip, far_clip):
        """Mitsuba's ``orthographic`` sensor for a parallel-beam camera: it
        maps x in [-1, 1] (y in [-h/w, h/w]) of the camera frame onto the
        film, so ``to_world`` is scaled by half the image's world width and
        shifted to the principal point."""
        import mitsuba as mi
        s = self.pixel_size
        shift = np.eye(4)
        shift[0, 3] = s * (self.cx - self.width / 2)
        shift[1, 3] = s * (self.cy - self.height / 2)
        half = 0.5 * s * self.width
        m = self.to_world @ shift @ np.diag([half, half, 1.0, 1.0])
        d = {"type": "orthographic", "to_world": mi.ScalarTransform4f(m.tolist()),
             "sampler": {"type": sampler, "sample_count": int(spp)},
             "film": {"type": "hdrfilm", "width": self.width, "height": self.height,
                      "rfilter": {"type": "box"}, "pixel_format": "rgb"}}
        if near_clip is not None:
            d["near_clip"] = float(near_clip)
        if far_clip is not None:
            d["far_clip"] = float(far_clip)
        return d


# --------------------------------------------------------------------------------------------
# Generated cameras
# --------------------------------------------------------------------------------------------

#: How much larger than a bounding sphere the sphere is that a framing camera's view holds.
FRAMING_MARGIN = 1.05


def drjit_rays(u, v, intrinsics, to_world, pixel_size=None):
    """Dr.Jit rays through pixel positions ``(u, v)`` of pinhole (or orthographic)
    cameras: the formula of :meth:`Camera.rays_drjit`, for one camera or for each
    ray its own (every argument a number or a Dr.Jit ``Float`` per ray).

    Parameters
    ----------
    u, v : mi.Float
        Continuous pixel coordinates (top-left corner at (0, 0)).
    intrinsics : (fx, fy, cx, cy)
        Focal lengths and principal point in pixels.
    to_world : 4x4 (or 3x4) nested sequence
        The camera-to-world matrix, indexed ``[row][column]``.
    pixel_size : float, optional
        An orthographic camera's pixel size (``fx, fy`` unused).

    Returns
    -------
    mi.Ray3f
        Origins at the camera centre (orthographic: on the image plane), unit
        directions.
    """
    import drjit as dr
    import mitsuba as mi
    fx, fy, cx, cy = intrinsics
    m = to_world
    r = [[m[i][j] for j in range(3)] for i in range(3)]
    width = max(dr.width(u), dr.width(v))
    if pixel_size is not None:
        x, y = (cx - u) * pixel_size, (cy - v) * pixel_size
        o = mi.Point3f(*[r[i][0] * x + r[i][1] * y + m[i][3] for i in range(3)])
        d = dr.zeros(mi.Vector3f, dr.width(o)) + mi.Vector3f(r[0][2], r[1][2], r[2][2])
        return mi.Ray3f(o, d)
    x = (cx - u) / fx
    y = (cy - v) / fy
    d = mi.Vector3f(r[0][0] * x + r[0][1] * y + r[0][2],
                    r[1][0] * x + r[1][1] * y + r[1][2],
                    r[2][0] * x + r[2][1] * y + r[2][2])
    o = dr.zeros(mi.Point3f, width) + mi.Point3f(*[m[i][3] for i in range(3)])
    return mi.Ray3f(o, dr.normalize(d))


def cameras_focus(cameras: Sequence[Camera]) -> np.ndarray:
    """(3,) the point the cameras look at: the least-squares point nearest to their view
    axes (their centers' mean where the axes are near parallel, as a forward-facing
    capture's: a small pull towards it keeps the system well posed)."""
    c = np.array([cam.center for cam in cameras], np.float64).reshape(-1, 3)
    f = np.array([cam.to_world[:3, 2] for cam in cameras], np.float64).reshape(-1, 3)
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    proj = np.eye(3)[None] - f[:, :, None] * f[:, None, :]     # onto each axis's normal plane
    a, b = proj.sum(0), np.einsum("kij,kj->i", proj, c)
    eps = 1e-3 * len(c)
    return np.linalg.solve(a + eps * np.eye(3), b + eps * c.mean(0))


def camera_path(cameras: Sequence[Camera], frames: int) -> List[Camera]:
    """``frames`` cameras along the path of ``cameras``, in their order (a capture's, as the
    photos were taken): the centers interpolated linearly and the orientations spherically
    (slerp) by the distance travelled (by the index where the cameras do not move), with the
    intrinsics of the cameras' most common image size (the median focal length and principal
    point of those): a fly-through of the capture."""
    with needs("recon", "a camera path"):
        from scipy.spatial.transform import Rotation, Slerp
    cameras = list(cameras)
    if len(cameras) < 2 or frames < 2:
        raise ValueError(f"a camera path needs 2 or more cameras and frames, got "
                         f"{len(cameras)} cameras and {frames} frames")
    if any(c.pixel_size is not None for c in cameras):
        raise ValueError("a camera path is made of pinhole cameras")
    sizes = [(c.width, c.height) for c in cameras]
    size = max(set(sizes), key=sizes.count)
    same = [c for c in cameras if (c.width, c.height) == size]
    fx, fy, cx, cy = (float(np.median([getattr(c, k) for c in same]))
                      for k in ("fx", "fy", "cx", "cy"))
    centers = np.array([c.center for c in cameras])
    step = np.linalg.norm(np.diff(centers, axis=0), axis=1)
    key = np.concatenate([[0.0], np.cumsum(step)])
    if key[-1] <= 1e-12 * max(1.0, float(np.abs(centers).max())):
        key = np.arange(len(cameras), dtype=np.float64)
    key = key / key[-1]
    # (cameras at the same place: their times a little apart, in order)
    key = np.maximum.accumulate(key + 1e-9 * np.arange(len(key)))
    t = np.linspace(key[0], key[-1], frames)
    rotations = Slerp(key, Rotation.from_matrix([c.to_world[:3, :3] for c in cameras]))(t)
    path = []
    for r, x in zip(rotations.as_matrix(), np.stack([np.interp(t, key, centers[:, k])
                                                    for k in range(3)], 1)):
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = r, x
        path.append(Camera(size[0], size[1], fx, fy, cx, cy, m))
    return path


def framing_distance(radius: float, fov: float, res=None,
                     margin: float = FRAMING_MARGIN) -> float:
    """The distance from a sphere's centre at which a camera's field of view holds the
    sphere ``margin`` times its ``radius``: ``margin * radius / sin(fov' / 2)``.

    Parameters
    ----------
    radius : float
        The bounding sphere's radius.
    fov : float
        The camera's horizontal field of view in degrees.
    res : (width, height), optional
        The image size: on an image taller than it is wide ``fov'`` is ``fov``; on a
        wider one the narrower ``fov * height / width`` (a little less than the vertical
        field, ``2 atan(tan(fov / 2) height / width)``, so the sphere stays inside).
        Without it, ``fov'`` is ``fov``.
    margin : float

    Returns
    -------
    float
    """
    if res is not None:
        width, height = res
        fov = min(fov, fov * height / width)
    return margin * radius / math.sin(math.radians(fov) / 2)


def default_fov(radius: float, margin: float = FRAMING_MARGIN) -> float:
    """Horizontal field of view (degrees) whose cone at distance ``radius`` holds the sphere
    of radius ``margin * sqrt(3)`` around the origin (the ``[-1, 1]^3`` box): the inverse
    of :func:`framing_distance`."""
    r = min(margin * math.sqrt(3.0) / radius, 1.0)
    return math.degrees(2.0 * math.asin(r))


def check_factor(factor) -> int:
    """A downscale factor as an int (a positive integer), else ``ValueError``."""
    if int(factor) != factor or factor < 1:
        raise ValueError(f"downscale factor must be a positive integer, got {factor!r}")
    return int(factor)


def _resolution(res) -> Tuple[int, int]:
    if isinstance(res, (int, np.integer)):
        return int(res), int(res)
    w, h = res
    return int(w), int(h)


def _frame(up):
    u = np.asarray(up, np.float64)
    u = u / np.linalg.norm(u)
    a = np.eye(3)[np.argmin(np.abs(u))]
    e1 = np.cross(u, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1), u


def _spiral(n: int, hemisphere: bool = False):
    """The Fibonacci (golden-angle) spiral of ``n`` points evenly over the unit sphere (or
    its ``z >= 0`` half): their heights ``z`` and azimuths ``phi`` (radians)."""
    i = np.arange(n) + 0.5
    z = 1.0 - i / n if hemisphere else 1.0 - 2.0 * i / n
    return z, math.pi * (3.0 - math.sqrt(5.0)) * i


def fibonacci_sphere(n: int):
    """``(longitude, latitude)`` in degrees of ``n`` points spread evenly over the sphere:
    the spiral :func:`fibonacci_cameras` places its cameras on (pole along ``z``)."""
    z, phi = _spiral(n)
    return np.degrees(phi) % 360.0, np.degrees(np.arcsin(z))


def fibonacci_cameras(n: int, radius: float = 4.0, res=256, fov: Optional[float] = None,
                      up=(0.0, 0.0, 1.0), target=(0.0, 0.0, 0.0),
                      hemisphere: bool = False) -> List[Camera]:
    """``n`` cameras on a Fibonacci sphere of ``radius`` around ``target``, looking at it.

    Parameters
    ----------
    n : int
    radius : float
    res : int or (width, height)
    fov : float, optional
        Horizontal field of view in degrees; default :func:`default_fov` (frames
        ``[-1, 1]^3``).
    up : (3,) float
        The sphere's pole and the cameras' up vector (at the poles another one is chosen, see
        :func:`look_at`).
    target : (3,) float
    hemisphere : bool
        Keep to the ``up`` side.

    Returns
    -------
    list of Camera
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    w, h = _resolution(res)
    fov = default_fov(radius) if fov is None else float(fov)
    z, phi = _spiral(n, hemisphere)
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    e1, e2, e3 = _frame(up)
    dirs = (r * np.cos(phi))[:, None] * e1 + (r * np.sin(phi))[:, None] * e2 + z[:, None] * e3
    t = np.asarray(target, np.float64)
    return [Camera.look_at(t + radius * d, t, up, w, h, fov_x=fov) for d in dirs]


def random_cameras(n: int, radius: float = 4.0, res=256, fov: Optional[float] = None,
                   seed: int = 0, up=(0.0, 0.0, 1.0), target=(0.0, 0.0, 0.0),
                   hemisphere: bool = False) -> List[Camera]:
    """``n`` cameras at uniformly random points of a sphere (``numpy.random.default_rng(seed)``),
    looking at ``target``; the other arguments as :func:`fibonacci_cameras`.

    Returns
    -------
    list of Camera
    """
    w, h = _resolution(res)
    fov = default_fov(radius) if fov is None else float(fov)
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    if hemisphere:
        d = np.where((d @ u)[:, None] < 0, d - 2 * (d @ u)[:, None] * u, d)
    t = np.asarray(target, np.float64)
    return [Camera.look_at(t + radius * x, t, up, w, h, fov_x=fov) for x in d]


def box_cameras(bounds, views: int, test_views: int, res=256, fov: float = 40.0, seed: int = 0,
                up=(0.0, 0.0, 1.0)):
    """Cameras around the box ``bounds`` (2, 3), at the distance where its bounding sphere
    fills ``fov`` (degrees): ``views`` on a Fibonacci sphere (:func:`fibonacci_cameras`) and
    ``test_views`` at random (:func:`random_cameras` with ``seed``). Returns
    ``(train, test)`` lists of Camera."""
    lo, hi = np.asarray(bounds, np.float64).reshape(2, 3)
    centre = (lo + hi) / 2
    distance = framing_distance(np.linalg.norm(hi - lo) / 2, fov)
    train = fibonacci_cameras(views, distance, res, fov, up=up, target=centre)
    test = random_cameras(test_views, distance, res, fov, seed=seed, up=up, target=centre) \
        if test_views else []
    return train, test


def orbit_to_world(longitude, latitude, distance, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)):
    """The ``to_world`` of a camera at ``distance`` from ``target``, at
    ``longitude`` and ``latitude`` (degrees; Dr.Jit values keep their
    gradients) about the ``up`` axis, looking at the target.

    Latitude 0 is the plane through the target orthogonal to ``up``, +90 the
    pole along ``up`` (avoid it: the view's up vector degenerates there).
    Longitude 0 lies along the first axis of ``mi.coordinate_system(up)``. Needs a Mitsuba
    variant. The derivative passes of ``tetvr`` differentiate the image w.r.t. the rays when
    the sensor's ``to_world`` carries gradients (:mod:`mi_tetvr.render.adjoint`), except the
    silhouette: which pixels see the mesh has no boundary term, so a camera gradient is
    exact for a volume whose boundary is transparent.
    """
    import drjit as dr
    import mitsuba as mi
    up = dr.normalize(mi.Vector3f(up))
    e1, e2 = mi.coordinate_system(up)
    lon = dr.deg2rad(mi.Float(longitude))
    lat = dr.deg2rad(mi.Float(latitude))
    direction = dr.cos(lat) * (dr.cos(lon) * e1 + dr.sin(lon) * e2) + dr.sin(lat) * up
    target = mi.Point3f(target)
    return mi.AffineTransform4f().look_at(origin=target + mi.Float(distance) * direction,
                                          target=target, up=up)
