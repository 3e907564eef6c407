"""Multi-view image data sets with known cameras, converted exactly to Mitsuba sensors.

A :class:`Dataset` holds posed :class:`View` s (an image plus a pinhole camera) split into
``train`` and ``test``, optionally with COLMAP's sparse points and a scene box. Loaders:
:func:`load_nerf` (NeRF / instant-ngp ``transforms*.json``) and :func:`load_colmap` (a COLMAP
sparse model through pycolmap); :func:`write_nerf` writes a NeRF-convention data set that
:func:`load_nerf` reads back.

Conventions
-----------
Images
    ``View.image`` is ``(H, W, 4) float32`` **premultiplied linear RGB and alpha**: exactly what
    the ``tetvr`` integrator renders over a black background (RGB = accumulated emission, AOV
    ``alpha`` = 1 - transmittance). PNG/JPEG files are sRGB with straight alpha: they are decoded
    to linear with :func:`mi_tetvr.color.srgb_to_linear` and then premultiplied. EXR files are
    linear and, following the OpenEXR convention, already premultiplied (read and written as is).
    A file without alpha gets alpha = 1. ``View.composite(bg)`` gives the picture over a constant
    background (NeRF-synthetic's white background: ``composite(1.0)``).
Pixel coordinates
    Continuous image coordinates have the **top-left corner of the image at (0, 0)**; the centre of
    pixel ``(i, j)`` (column, row) is at ``(i + 0.5, j + 0.5)``. This is COLMAP's convention, the
    one of instant-ngp/nerfstudio's ``cx, cy`` (default ``w / 2``), and the one of Mitsuba's film
    (pixel ``i`` covers film positions ``[i, i + 1) / W``). With it, downscaling by an integer
    factor ``f`` divides ``fx, fy, cx, cy`` by ``f`` exactly (after cropping the right/bottom
    remainder ``W % f``, ``H % f``, which does not move the origin).
Projection
    A camera-frame point ``(x, y, z)`` (Mitsuba camera frame: looks along +z, y up, x to the
    image's *left*) lands at ``u = cx - fx * x / z``, ``v = cy - fy * y / z`` (``v`` down).
Camera frames
    ``View.to_world`` is a rigid (4, 4) Mitsuba camera-to-world matrix. NeRF/OpenGL cameras
    (look along -z, y up, x right): ``to_world = c2w @ diag(-1, 1, -1, 1)``. COLMAP/OpenCV cameras
    (look along +z, y down, x right), world-to-camera ``[R | t]``:
    ``to_world = inv([R | t]) @ diag(-1, -1, 1, 1)``.
Mitsuba sensor
    ``perspective`` with ``fov_axis='x'``, ``fov = 2 atan(W / (2 fx))`` (degrees) and
    ``principal_point_offset_x = 0.5 - cx / W``, ``principal_point_offset_y = 0.5 - cy / H``.
    Mitsuba adds the offsets (in units of the film width / height) to the film position before
    the centred projection, so a film position ``u`` looks where a centred camera's ``u + ox W``
    would: the tests check this with ``sensor.sample_ray`` against the pinhole formula above.
    Mitsuba's perspective camera has square pixels, so ``fx != fy`` is refused (relative
    tolerance ``square_rtol``).
Held-out views
    When a data set has no test split (NeRF without ``transforms_test.json`` /
    ``transforms_val.json``, instant-ngp's single ``transforms.json``, every COLMAP model), the
    views whose index (in file order for NeRF, sorted by image name for COLMAP) is a multiple of
    ``holdout`` (default 8, the LLFF / Mip-NeRF 360 convention) form the test split.
    ``holdout=None`` (or 0) keeps every view for training; a sequence gives the test indices.
"""
from __future__ import annotations

import json
import math
import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

import numpy as np

from mi_tetvr.recon.images import check_factor, downscale_image, read_image, write_image

__all__ = ["View", "Dataset", "look_at", "load_dataset", "load_nerf", "load_colmap", "write_nerf",
           "read_image", "write_image", "downscale_image", "OPENGL_TO_MITSUBA",
           "OPENCV_TO_MITSUBA"]

#: ``c2w_opengl @ OPENGL_TO_MITSUBA`` is Mitsuba's ``to_world`` (and vice versa: it is an involution).
OPENGL_TO_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])
#: ``c2w_opencv @ OPENCV_TO_MITSUBA`` is Mitsuba's ``to_world`` (COLMAP cameras).
OPENCV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".PNG", ".JPG", ".JPEG", ".EXR")

Holdout = Union[int, Sequence[int], None]


# --------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------

def look_at(origin, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world (4, 4) in Mitsuba axes, as ``mi.ScalarTransform4f().look_at``.

    If ``up`` is (nearly) parallel to the view direction, another up vector (the world axis
    least aligned with the view direction) is used.
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


# --------------------------------------------------------------------------------------------
# View and Dataset
# --------------------------------------------------------------------------------------------

@dataclass
class View:
    """One posed image: a pinhole camera and (optionally) its picture.

    Attributes
    ----------
    name : str
    image : (H, W, 4) float32 or None
        Premultiplied linear RGB and alpha (what ``tetvr`` renders over black, with its
        ``alpha`` AOV). ``None`` for a camera without picture (e.g. to render one).
    to_world : (4, 4) float64
        Rigid Mitsuba camera-to-world matrix (camera looks along +z, y up, x to the left).
    fx, fy : float
        Focal lengths in pixels.
    cx, cy : float
        Principal point in pixels, top-left image corner at (0, 0), pixel centres at +0.5.
    width, height : int
        Image size in pixels.
    """
    name: str
    image: Optional[np.ndarray]
    to_world: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        self.to_world = np.asarray(self.to_world, dtype=np.float64).reshape(4, 4)
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in (self.fx, self.fy, self.cx, self.cy))
        self.width, self.height = int(self.width), int(self.height)
        if self.image is not None:
            self.image = np.asarray(self.image, dtype=np.float32)
            if self.image.shape != (self.height, self.width, 4):
                raise ValueError(f"view '{self.name}': image shape {self.image.shape} != "
                                 f"(height, width, 4) = ({self.height}, {self.width}, 4)")

    # -- constructors -----------------------------------------------------------------------
    @classmethod
    def look_at(cls, name: str, origin, target, up, width: int, height: int, *,
                fov_x: Optional[float] = None, fx: Optional[float] = None,
                cx: Optional[float] = None, cy: Optional[float] = None,
                image: Optional[np.ndarray] = None) -> "View":
        """A camera at ``origin`` looking at ``target`` (Mitsuba's ``look_at`` frame).

        Parameters
        ----------
        origin, target, up : (3,) float
        width, height : int
        fov_x : float, optional
            Horizontal field of view in degrees (give this or ``fx``).
        fx : float, optional
            Focal length in pixels (``fy = fx``).
        cx, cy : float, optional
            Principal point (default: the image centre ``width / 2, height / 2``).
        image : (height, width, 4) float, optional
        """
        if (fov_x is None) == (fx is None):
            raise ValueError("give exactly one of fov_x (degrees) and fx (pixels)")
        if fx is None:
            fx = 0.5 * width / math.tan(math.radians(fov_x) / 2)
        return cls(name, image, look_at(origin, target, up), fx, fx, width / 2 if cx is None else cx,
                   height / 2 if cy is None else cy, width, height)

    # -- camera geometry --------------------------------------------------------------------
    @property
    def center(self) -> np.ndarray:
        """(3,) float64: camera position in world space."""
        return self.to_world[:3, 3].copy()

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64: OpenCV/COLMAP intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``
        (for the OpenCV camera frame ``c2w = to_world @ OPENCV_TO_MITSUBA``)."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def fov_x(self) -> float:
        """Horizontal field of view in degrees, ``2 atan(width / (2 fx))``."""
        return math.degrees(2.0 * math.atan(0.5 * self.width / self.fx))

    def project(self, points) -> tuple:
        """Project world points with the pinhole model.

        Parameters
        ----------
        points : (k, 3) float

        Returns
        -------
        uv : (k, 2) float64
            Continuous pixel coordinates (top-left corner at 0, pixel centres at +0.5).
        depth : (k,) float64
            Distance along the viewing axis (> 0 in front of the camera).
        """
        p = np.asarray(points, np.float64).reshape(-1, 3)
        r, c = self.to_world[:3, :3], self.to_world[:3, 3]
        q = (p - c) @ r          # rows: R^T (p - c), Mitsuba camera frame
        z = q[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.cx - self.fx * q[:, 0] / z, self.cy - self.fy * q[:, 1] / z], 1)
        return uv, z

    def ray_directions(self, uv) -> np.ndarray:
        """World-space unit directions of the rays through pixel positions ``uv``.

        Parameters
        ----------
        uv : (k, 2) float
            Continuous pixel coordinates (pixel centres at +0.5).

        Returns
        -------
        (k, 3) float64
        """
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        d = np.stack([-(uv[:, 0] - self.cx) / self.fx, -(uv[:, 1] - self.cy) / self.fy,
                      np.ones(len(uv))], 1)
        d = d @ self.to_world[:3, :3].T
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    # -- Mitsuba ----------------------------------------------------------------------------
    def sensor_dict(self, spp: int = 1, sampler: str = "independent", *,
                    near_clip: Optional[float] = None, far_clip: Optional[float] = None,
                    square_rtol: float = 1e-6) -> dict:
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
        if abs(self.fx - self.fy) > square_rtol * abs(self.fx):
            raise ValueError(
                f"view '{self.name}': non-square pixels (fx={self.fx}, fy={self.fy}) cannot be "
                f"represented by Mitsuba's perspective sensor; resample the image so that "
                f"fx == fy, or raise square_rtol to accept fy := fx")
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
        if near_clip is not None:
            d["near_clip"] = float(near_clip)
        if far_clip is not None:
            d["far_clip"] = float(far_clip)
        return d

    # -- images -----------------------------------------------------------------------------
    def composite(self, background=0.0) -> np.ndarray:
        """The picture over a constant background: ``rgb + (1 - alpha) * background``.

        Parameters
        ----------
        background : float or (3,) float
            Linear RGB (1.0 = NeRF-synthetic's white).

        Returns
        -------
        (H, W, 3) float32, linear RGB
        """
        if self.image is None:
            raise ValueError(f"view '{self.name}' has no image")
        bg = np.broadcast_to(np.asarray(background, np.float32), (3,))
        return self.image[..., :3] + (1.0 - self.image[..., 3:4]) * bg

    def downscaled(self, factor: int) -> "View":
        """This view with its image area-averaged by ``factor`` and intrinsics divided by it.

        The right / bottom remainder (``width % factor`` etc.) is cropped, which keeps the
        top-left origin, so ``fx, fy, cx, cy`` scale by ``1 / factor`` exactly.
        """
        factor = check_factor(factor)
        if factor == 1:
            return replace(self)
        img = None if self.image is None else downscale_image(self.image, factor)
        return View(self.name, img, self.to_world.copy(), self.fx / factor, self.fy / factor,
                    self.cx / factor, self.cy / factor, self.width // factor,
                    self.height // factor)


@dataclass
class Dataset:
    """Posed views split into ``train`` and ``test``.

    Attributes
    ----------
    train, test : list of View
    points : (k, 3) float64 or None
        Sparse 3D points (COLMAP).
    bbox : (2, 3) float64 or None
        Scene box ``[min, max]`` when the data gives one (NeRF json key ``aabb``).
    name : str
    root : Path or None
        Folder the data set was read from.
    point_colors : (k, 3) uint8 or None
    point_errors : (k,) float64 or None
        Mean reprojection error of each point in pixels (COLMAP).
    point_track_lengths : (k,) int64 or None
        Number of images that observe each point (COLMAP).
    """
    train: List[View]
    test: List[View] = field(default_factory=list)
    points: Optional[np.ndarray] = None
    bbox: Optional[np.ndarray] = None
    name: str = ""
    root: Optional[Path] = None
    point_colors: Optional[np.ndarray] = None
    point_errors: Optional[np.ndarray] = None
    point_track_lengths: Optional[np.ndarray] = None

    @property
    def views(self) -> List[View]:
        """``train + test``."""
        return list(self.train) + list(self.test)

    def downscaled(self, factor: int) -> "Dataset":
        """A copy with every view downscaled (see :meth:`View.downscaled`)."""
        factor = check_factor(factor)
        return replace(self, train=[v.downscaled(factor) for v in self.train],
                       test=[v.downscaled(factor) for v in self.test])

    def bounds(self, percentile: float = 0.5, margin: float = 0.05,
               far: Optional[float] = None) -> np.ndarray:
        """A box enclosing the scene.

        In order of preference:

        1. the data set's ``bbox``;
        2. the sparse ``points``: per-axis ``percentile`` .. ``100 - percentile`` percentiles
           (to drop outliers), enlarged by ``margin`` of the extent on each side;
        3. the camera frusta: the bounding box of the intersection of all views' viewing
           pyramids (what every camera sees), found by linear programming. For inward-looking
           captures (NeRF-synthetic) this intersection is bounded; when it is not (forward-facing
           captures), depth along each camera axis is capped at ``far`` (default: twice the spread
           of the camera centres, at least 1). Empty intersections fall back to the box of the
           camera centres.

        Returns
        -------
        (2, 3) float64
            ``[min, max]``.
        """
        if self.bbox is not None:
            return np.asarray(self.bbox, np.float64).reshape(2, 3).copy()
        if self.points is not None and len(self.points) >= 2:
            p = np.asarray(self.points, np.float64)
            lo, hi = np.percentile(p, [percentile, 100 - percentile], axis=0)
            pad = margin * (hi - lo)
            return np.stack([lo - pad, hi + pad])
        views = self.views
        if not views:
            raise ValueError("bounds(): the data set has no views, points or bbox")
        return _frusta_bounds(views, far)


def _frusta_bounds(views: Sequence[View], far: Optional[float]) -> np.ndarray:
    from scipy.optimize import linprog
    centers = np.array([v.center for v in views])
    spread = float(np.linalg.norm(centers.max(0) - centers.min(0)))
    rows, rhs = [], []
    for v in views:
        r, c = v.to_world[:3, :3], v.to_world[:3, 3]
        # Camera frame q = R^T (p - c); each constraint a . q >= 0 (inside the pyramid).
        for a in ([-v.fx, 0, v.cx], [v.fx, 0, v.width - v.cx],
                  [0, -v.fy, v.cy], [0, v.fy, v.height - v.cy]):
            n = r @ np.asarray(a, np.float64)           # world normal: n . (p - c) >= 0
            rows.append(-n)
            rhs.append(-n @ c)

    def solve(a_ub, b_ub):
        out = np.empty((2, 3))
        for k in range(3):
            for s, sign in ((0, 1.0), (1, -1.0)):
                cost = np.zeros(3)
                cost[k] = sign
                res = linprog(cost, A_ub=a_ub, b_ub=b_ub, bounds=[(None, None)] * 3,
                              method="highs")
                if res.status != 0:
                    return res.status
                out[s, k] = res.x[k]
        return out

    a_ub, b_ub = np.array(rows), np.array(rhs)
    out = solve(a_ub, b_ub)
    if isinstance(out, int) and out == 3:                 # unbounded: cap the depth
        far = max(2.0 * spread, 1.0) if far is None else float(far)
        caps = [v.to_world[:3, 2] for v in views]       # z . (p - c) <= far
        a_ub = np.vstack([a_ub, caps])
        b_ub = np.concatenate([b_ub, [z @ v.center + far for z, v in zip(caps, views)]])
        out = solve(a_ub, b_ub)
    if isinstance(out, int):                              # infeasible: no common region
        return np.stack([centers.min(0), centers.max(0)])
    return out


# --------------------------------------------------------------------------------------------
# NeRF / instant-ngp
# --------------------------------------------------------------------------------------------

_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def _resolve_image(root: Path, file_path: str) -> Path:
    p = Path(file_path)
    p = p if p.is_absolute() else root / p
    if p.is_file():
        return p
    for s in _IMAGE_SUFFIXES:
        q = p.with_name(p.name + s)
        if q.is_file():
            return q
    raise FileNotFoundError(f"image '{file_path}' not found under {root} (also tried the "
                            f"extensions {', '.join(_IMAGE_SUFFIXES[:4])})")


def _image_size(path: Path):
    if path.suffix.lower() == ".exr":
        return None
    from PIL import Image
    with Image.open(path) as im:
        return im.size


def _rigid(m: np.ndarray, what: str, tol: float = 1e-3) -> np.ndarray:
    """Check that ``m`` (4, 4) is rigid (up to ``tol``) and snap its rotation to SO(3)."""
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
    u, _, vt = np.linalg.svd(r)
    out = np.eye(4)
    out[:3, :3] = u @ vt
    out[:3, 3] = m[:3, 3]
    return out


def _holdout_split(items: list, holdout: Holdout):
    if holdout is None or (isinstance(holdout, (int, np.integer)) and holdout == 0):
        return list(items), []
    if isinstance(holdout, (int, np.integer)):
        if holdout < 0:
            raise ValueError(f"holdout must be >= 0, got {holdout}")
        test_idx = set(range(0, len(items), int(holdout)))
    else:
        test_idx = {int(i) % len(items) for i in holdout} if items else set()
    train = [x for i, x in enumerate(items) if i not in test_idx]
    test = [x for i, x in enumerate(items) if i in test_idx]
    return train, test


def _pool_map(fn, items):
    items = list(items)
    if len(items) <= 1:
        return [fn(x) for x in items]
    workers = max(1, min(4, os.cpu_count() or 1, len(items)))
    with ThreadPoolExecutor(workers) as ex:
        return list(ex.map(fn, items))


def _nerf_frame_view(root: Path, meta: dict, frame: dict, downscale: int, load_images: bool,
                     what: str) -> View:
    m = {**{k: v for k, v in meta.items() if k != "frames"}, **frame}
    if "file_path" not in frame:
        raise ValueError(f"{what}: frame without 'file_path'")
    if any(float(m.get(k, 0.0)) != 0.0 for k in _DISTORTION_KEYS) or \
            str(m.get("camera_model", "OPENCV")).upper() not in ("OPENCV", "PINHOLE",
                                                                  "SIMPLE_PINHOLE"):
        raise ValueError(f"{what}: frame '{frame['file_path']}' has lens distortion "
                         f"(camera_model={m.get('camera_model')!r}, "
                         f"{ {k: m[k] for k in _DISTORTION_KEYS if k in m} }); only pinhole "
                         f"cameras are supported: undistort the images first")
    path = _resolve_image(root, frame["file_path"])
    image = read_image(path) if load_images else None
    if image is not None:
        img_h, img_w = image.shape[:2]
    else:
        size = _image_size(path) if ("w" not in m or "h" not in m) else None
        img_w, img_h = size if size is not None else (None, None)
    w = float(m["w"]) if "w" in m else img_w
    h = float(m["h"]) if "h" in m else img_h
    if w is None or h is None:
        raise ValueError(f"{what}: cannot tell the size of '{path}' (give 'w' and 'h')")
    if "fl_x" in m:
        fx = float(m["fl_x"])
    elif "camera_angle_x" in m:
        fx = 0.5 * w / math.tan(0.5 * float(m["camera_angle_x"]))
    else:
        raise ValueError(f"{what}: no focal length ('fl_x' or 'camera_angle_x')")
    if "fl_y" in m:
        fy = float(m["fl_y"])
    elif "camera_angle_y" in m:
        fy = 0.5 * h / math.tan(0.5 * float(m["camera_angle_y"]))
    else:
        fy = fx
    cx = float(m.get("cx", w / 2))
    cy = float(m.get("cy", h / 2))
    # Intrinsics refer to (w, h); images stored at another size get them rescaled.
    if img_w is not None and (img_w, img_h) != (w, h):
        sx, sy = img_w / w, img_h / h
        fx, cx, fy, cy = fx * sx, cx * sx, fy * sy, cy * sy
        w, h = img_w, img_h
    c2w = _rigid(np.asarray(frame["transform_matrix"], np.float64),
                 f"{what}: frame '{frame['file_path']}'")
    view = View(Path(frame["file_path"]).stem if Path(frame["file_path"]).suffix.lower()
                in _IMAGE_SUFFIXES_LOWER else Path(frame["file_path"]).name,
                image, c2w @ OPENGL_TO_MITSUBA, fx, fy, cx, cy, int(round(w)), int(round(h)))
    return view.downscaled(downscale) if downscale != 1 else view


_IMAGE_SUFFIXES_LOWER = {s.lower() for s in _IMAGE_SUFFIXES}


def load_nerf(path, downscale: int = 1, holdout: Holdout = 8, *, load_images: bool = True,
              splits: Optional[Dict[str, str]] = None) -> Dataset:
    """Load a NeRF-convention data set.

    Reads ``transforms_train.json`` and ``transforms_test.json`` (or, without it,
    ``transforms_val.json`` as the test split), or a single ``transforms.json`` (instant-ngp /
    nerfstudio), or the json file ``path`` itself. Intrinsics come from ``fl_x, fl_y, cx, cy,
    w, h`` or ``camera_angle_x`` (``camera_angle_y``), per frame or top-level (a frame's keys
    win); missing ``cx, cy`` = image centre, missing ``fl_y`` = ``fl_x``, missing ``w, h`` = the
    image size. Intrinsics given for another size than the stored image are rescaled to it.
    Distortion coefficients (``k1 ... p2`` non-zero) are refused. ``transform_matrix`` is
    camera-to-world in OpenGL axes (looks along -z, y up); ``View.to_world =
    transform_matrix @ diag(-1, 1, -1, 1)``. A top-level ``aabb`` ``[[x0, y0, z0], [x1, y1,
    z1]]`` becomes ``Dataset.bbox``.

    Parameters
    ----------
    path : str or Path
        The data set folder or one of its json files.
    downscale : int
        Integer area-averaging factor applied to each image as it is decoded (intrinsics divided
        exactly, see :meth:`View.downscaled`).
    holdout : int, sequence of int or None
        Used only when there is no test (or val) split: frames whose index in file order is a
        multiple of ``holdout`` (default 8: frames 0, 8, 16, ...) form the test split; a sequence
        lists the test indices; ``None`` / 0 keeps everything for training.
    load_images : bool
        False reads the cameras only (``View.image = None``).
    splits : dict, optional
        ``{"train": file, "test": file}`` json names relative to the folder, overriding the
        discovery above.

    Returns
    -------
    Dataset
    """
    path = Path(path)
    downscale = check_factor(downscale)
    if path.is_file():
        root, files = path.parent, {"train": path.name}
    else:
        root = path
        if splits is not None:
            files = dict(splits)
        elif (root / "transforms_train.json").is_file():
            files = {"train": "transforms_train.json"}
            for key, name in (("test", "transforms_test.json"), ("test", "transforms_val.json")):
                if key not in files and (root / name).is_file():
                    files[key] = name
        elif (root / "transforms.json").is_file():
            files = {"train": "transforms.json"}
        else:
            raise FileNotFoundError(f"{root}: no transforms_train.json or transforms.json")

    out: Dict[str, List[View]] = {}
    bbox = None
    for split, name in files.items():
        fpath = root / name
        with open(fpath) as f:
            meta = json.load(f)
        if bbox is None and "aabb" in meta and np.size(meta["aabb"]) == 6:
            bbox = np.asarray(meta["aabb"], np.float64).reshape(2, 3)
        frames = meta.get("frames", [])
        out[split] = _pool_map(
            lambda fr: _nerf_frame_view(root, meta, fr, downscale, load_images, str(fpath)),
            frames)
    train, test = out.get("train", []), out.get("test")
    if test is None:
        train, test = _holdout_split(train, holdout)
    return Dataset(train=train, test=test, points=None, bbox=bbox, name=root.name, root=root)


def write_nerf(dataset_or_views, out_dir, split_names: Sequence[str] = ("train", "test"), *,
               image_format: str = "png") -> Path:
    """Write a NeRF-convention data set that :func:`load_nerf` reads back.

    One ``transforms_<split>.json`` per split, with ``camera_angle_x``, ``fl_x, fl_y, cx, cy, w,
    h`` (top-level when every view of the split shares them, else per frame) and
    ``transform_matrix`` (camera-to-world, OpenGL axes: ``to_world @ diag(-1, 1, -1, 1)``); the
    images go to ``<split>/<name>.<format>``. ``png``: 8-bit sRGB RGBA with straight alpha (the
    premultiplied colour is divided by alpha); ``exr``: linear premultiplied float32 (exact).
    A data set ``bbox`` is written as ``aabb``. Sparse points are not written.

    Parameters
    ----------
    dataset_or_views : Dataset, list of View, or dict of {split: list of View}
        A Dataset writes ``train`` and ``test`` under ``split_names[0]`` and ``split_names[1]``
        (an empty test split is skipped); a list writes one split ``split_names[0]``.
    out_dir : str or Path
    split_names : sequence of str
    image_format : {"png", "exr"}

    Returns
    -------
    Path
        ``out_dir``.
    """
    out_dir = Path(out_dir)
    fmt = image_format.lower().lstrip(".")
    if fmt not in ("png", "exr"):
        raise ValueError(f"image_format must be 'png' or 'exr', got {image_format!r}")
    bbox = None
    if isinstance(dataset_or_views, Dataset):
        groups = {split_names[0]: dataset_or_views.train}
        if dataset_or_views.test:
            groups[split_names[1]] = dataset_or_views.test
        bbox = dataset_or_views.bbox
    elif isinstance(dataset_or_views, dict):
        groups = dict(dataset_or_views)
    else:
        groups = {split_names[0]: list(dataset_or_views)}
    out_dir.mkdir(parents=True, exist_ok=True)

    for split, views in groups.items():
        (out_dir / split).mkdir(exist_ok=True)
        intr = [(v.fx, v.fy, v.cx, v.cy, v.width, v.height) for v in views]
        shared = len(set(intr)) == 1
        meta: dict = {}

        def cam(v: View) -> dict:
            return {"camera_angle_x": 2.0 * math.atan(0.5 * v.width / v.fx),
                    "fl_x": v.fx, "fl_y": v.fy, "cx": v.cx, "cy": v.cy,
                    "w": v.width, "h": v.height}
        if shared and views:
            meta.update(cam(views[0]))
        if bbox is not None:
            meta["aabb"] = np.asarray(bbox, np.float64).reshape(2, 3).tolist()
        frames, used = [], set()
        for i, v in enumerate(views):
            if v.image is None:
                raise ValueError(f"write_nerf: view '{v.name}' has no image")
            stem = re.sub(r"[^A-Za-z0-9._-]+", "_", v.name) or f"{i:04d}"
            if stem in used:
                stem = f"{stem}_{i:04d}"
            used.add(stem)
            rel = f"{split}/{stem}.{fmt}"
            write_image(out_dir / rel, v.image)
            fr = {"file_path": f"./{rel}",
                  "transform_matrix": (v.to_world @ OPENGL_TO_MITSUBA).tolist()}
            if not shared:
                fr.update(cam(v))
            frames.append(fr)
        meta["frames"] = frames
        with open(out_dir / f"transforms_{split}.json", "w") as f:
            json.dump(meta, f, indent=2)
    return out_dir


# --------------------------------------------------------------------------------------------
# COLMAP
# --------------------------------------------------------------------------------------------

def _find_colmap_model(path: Path) -> Path:
    for cand in (path, path / "sparse" / "0", path / "sparse", path / "colmap" / "sparse" / "0"):
        if (cand / "cameras.bin").is_file() or (cand / "cameras.txt").is_file():
            return cand
    raise FileNotFoundError(f"{path}: no COLMAP model (cameras.bin/.txt) in it, in sparse/0 "
                            f"or in sparse/")


def _pinhole_intrinsics(cam) -> tuple:
    model = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
    p = np.asarray(cam.params, np.float64)
    if model == "PINHOLE":
        return tuple(p[:4])
    if model == "SIMPLE_PINHOLE":
        return p[0], p[0], p[1], p[2]
    # Radial models with all-zero distortion are pinholes in disguise.
    if model in ("SIMPLE_RADIAL", "RADIAL") and np.all(p[3:] == 0):
        return p[0], p[0], p[1], p[2]
    if model in ("OPENCV", "FULL_OPENCV") and np.all(p[4:] == 0):
        return tuple(p[:4])
    raise ValueError(
        f"COLMAP camera {cam.camera_id} uses the {model} model (params {p.tolist()}); only "
        f"PINHOLE and SIMPLE_PINHOLE cameras are supported. Undistort the images first, e.g. "
        f"`colmap image_undistorter --image_path IMAGES --input_path SPARSE --output_path OUT "
        f"--output_type COLMAP` (or pycolmap.undistort_images(OUT, SPARSE, IMAGES)), and load "
        f"OUT, whose sparse model has PINHOLE cameras")


def _quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def load_colmap(path, images=None, downscale: int = 1, holdout: Holdout = 8, *,
                load_images: bool = True) -> Dataset:
    """Load a COLMAP sparse reconstruction (binary or text) with pycolmap.

    Cameras must be PINHOLE or SIMPLE_PINHOLE (radial/OpenCV models with all-zero distortion are
    accepted); other models raise ``ValueError`` telling to run ``colmap image_undistorter``.
    COLMAP's world-to-camera ``[R | t]`` (camera looks along +z, y down, x right) becomes
    ``View.to_world = inv([R | t]) @ diag(-1, -1, 1, 1)``. COLMAP's pixel convention (top-left
    corner at 0, pixel centres at +0.5) is the one of :class:`View`, so ``cx, cy`` are kept as
    they are. Images are sorted by name.

    Parameters
    ----------
    path : str or Path
        The model folder (with ``cameras.bin``/``.txt``), or a folder with ``sparse/0`` or
        ``sparse``.
    images : str or Path, optional
        Image folder; default ``<path>/images`` (or ``images/`` next to / above the model).
    downscale : int
        Integer area-averaging factor applied while loading (intrinsics divided exactly).
    holdout : int, sequence of int or None
        Images (sorted by name) whose index is a multiple of ``holdout`` (default 8) form the
        test split; a sequence lists the test indices; ``None`` / 0 keeps all for training.
    load_images : bool
        False reads the cameras only (``View.image = None``).

    Returns
    -------
    Dataset
        With ``points`` (k, 3), ``point_colors`` (k, 3) uint8, ``point_errors`` (k,) and
        ``point_track_lengths`` (k,) from the sparse points (sorted by point id).
    """
    import pycolmap
    path = Path(path)
    downscale = check_factor(downscale)
    model = _find_colmap_model(path)
    if images is None:
        for cand in (path / "images", model.parent / "images", model.parent.parent / "images"):
            if cand.is_dir():
                images = cand
                break
        else:
            if load_images:
                raise FileNotFoundError(f"{path}: no images/ folder found; pass images=...")
    images = Path(images) if images is not None else None
    rec = pycolmap.Reconstruction(str(model))

    entries = []
    for img in sorted(rec.images.values(), key=lambda im: im.name):
        has_pose = img.has_pose() if callable(getattr(img, "has_pose", None)) \
            else getattr(img, "has_pose", True)
        if not has_pose:
            continue
        cam = rec.cameras[img.camera_id]
        fx, fy, cx, cy = _pinhole_intrinsics(cam)
        cfw = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
        # The text format stores rounded quaternions that pycolmap keeps unnormalized:
        # normalize, so that the pose is exactly rigid, and invert it as a rigid transform.
        r = _quat_xyzw_to_matrix(np.asarray(cfw.rotation.quat, np.float64))
        t = np.asarray(cfw.translation, np.float64)
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = r.T, -r.T @ t
        to_world = c2w @ OPENCV_TO_MITSUBA
        entries.append((img.name, to_world, fx, fy, cx, cy, cam.width, cam.height))

    def make(e) -> View:
        name, to_world, fx, fy, cx, cy, w, h = e
        image = None
        if load_images:
            image = read_image(images / name)
            ih, iw = image.shape[:2]
            if (iw, ih) != (w, h):       # images stored at another size: rescale intrinsics
                sx, sy = iw / w, ih / h
                fx, cx, fy, cy, w, h = fx * sx, cx * sx, fy * sy, cy * sy, iw, ih
        v = View(Path(name).stem, image, to_world, fx, fy, cx, cy, w, h)
        return v.downscaled(downscale) if downscale != 1 else v

    views = _pool_map(make, entries)
    train, test = _holdout_split(views, holdout)

    pts = sorted(rec.points3D.items())
    if pts:
        points = np.array([p.xyz for _, p in pts], np.float64).reshape(-1, 3)
        colors = np.array([p.color for _, p in pts], np.uint8).reshape(-1, 3)
        errors = np.array([p.error for _, p in pts], np.float64)
        tracks = np.array([p.track.length() for _, p in pts], np.int64)
    else:
        points = colors = errors = tracks = None
    name = path.name if path.name not in ("0", "sparse") else model.parent.name
    return Dataset(train=train, test=test, points=points, bbox=None, name=name, root=path,
                   point_colors=colors, point_errors=errors, point_track_lengths=tracks)


def load_dataset(path, downscale: int = 1, holdout: Holdout = 8, **kw) -> Dataset:
    """A NeRF-style folder (``transforms*.json``) or a COLMAP model (``cameras.txt``
    / ``.bin``, also under ``sparse/`` or ``sparse/0``), whichever ``path`` holds."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"data set not found: {p}")
    if p.is_file() and p.suffix == ".json":
        return load_nerf(p.parent, downscale, holdout, **kw)
    if any(p.glob("transforms*.json")):
        return load_nerf(p, downscale, holdout, **kw)
    try:
        _find_colmap_model(p)
    except (FileNotFoundError, ValueError):
        raise ValueError(f"{p} is neither a NeRF-style data set (transforms*.json) nor a "
                         f"COLMAP model (cameras/images/points3D .txt or .bin)") from None
    return load_colmap(p, downscale=downscale, holdout=holdout, **kw)
