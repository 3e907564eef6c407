"""Multi-view image data sets with known cameras, converted exactly to Mitsuba sensors.

A :class:`Dataset` holds posed :class:`View` s (a name, a pinhole
:class:`~mi_tetvr.camera.Camera` and its image) split into ``train`` and ``test``,
optionally with COLMAP's sparse points and a scene box. Loaders:
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
Cameras
    Pixel coordinates, camera frames, the conversion of NeRF (OpenGL) and COLMAP (OpenCV)
    poses and the exact Mitsuba sensor are those of :mod:`mi_tetvr.camera`. NeRF's
    ``transform_matrix`` is an OpenGL camera-to-world (:meth:`Camera.from_opengl
    <mi_tetvr.camera.Camera.from_opengl>`); COLMAP's pose is a world-to-camera
    ``[R | t]`` in OpenCV axes (:meth:`Camera.from_colmap
    <mi_tetvr.camera.Camera.from_colmap>`); both are refused unless rigid.
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
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

import numpy as np

from mi_tetvr.camera import OPENGL_TO_MITSUBA, Camera, as_rigid
from mi_tetvr.extras import needs
from mi_tetvr.recon.hull import frusta_bounds
from mi_tetvr.recon.images import (check_factor, downscale_image, image_size, read_image,
                                   write_image)
from mi_tetvr.recon.undistort import Lens, nerf_lens

__all__ = ["View", "Dataset", "load_dataset", "load_nerf", "load_colmap", "write_nerf"]

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".PNG", ".JPG", ".JPEG", ".EXR", ".npy")

Holdout = Union[int, Sequence[int], None]


# --------------------------------------------------------------------------------------------
# View and Dataset
# --------------------------------------------------------------------------------------------

@dataclass
class View:
    """One posed image: a name, a pinhole camera and (optionally) its picture.

    Attributes
    ----------
    name : str
    camera : Camera
        Intrinsics and pose (:mod:`mi_tetvr.camera`).
    image : (camera.height, camera.width, 4) float32 or None
        Premultiplied linear RGB and alpha (what ``tetvr`` renders over black, with its
        ``alpha`` AOV). ``None`` for a camera without picture (e.g. to render one).
    """
    name: str
    camera: Camera
    image: Optional[np.ndarray] = None

    def __post_init__(self):
        if self.image is not None:
            self.image = np.asarray(self.image, dtype=np.float32)
            shape = (self.camera.height, self.camera.width, 4)
            if self.image.shape != shape:
                raise ValueError(f"view '{self.name}': image shape {self.image.shape} != "
                                 f"(height, width, 4) = {shape}")

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
        from mi_tetvr.recon.metrics import composite
        return composite(self.image, np.asarray(background, np.float32))

    def downscaled(self, factor: int) -> "View":
        """This view with its image area-averaged by ``factor`` and its camera downscaled
        accordingly (:meth:`Camera.downscaled <mi_tetvr.camera.Camera.downscaled>`)."""
        factor = check_factor(factor)
        img = None if self.image is None else downscale_image(self.image, factor)
        return View(self.name, self.camera.downscaled(factor), img)


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
    protocol : str
        How the test views were chosen (recorded in a fit's ``metrics.json``).
    pixel_sampling : str
        What a pixel is, as the data set records it (NeRF json key ``pixel_sampling``):
        ``"centers"`` (rendered through pixel centres: point samples, as ``mi-tetvr
        make-dataset`` writes them) or ``"area"`` (averages over the pixel, as photos
        and path-traced renders are); ``""`` when it does not say.
    xray_flux : float or None
        X-ray projections with Poisson noise: photons per pixel of the unattenuated
        beam (NeRF json key ``xray_flux``); ``None`` for noise-free projections.
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
    protocol: str = ""
    pixel_sampling: str = ""
    xray_flux: Optional[float] = None

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
        3. the camera frusta: the bounding box of what every camera sees,
           :func:`mi_tetvr.recon.hull.frusta_bounds` (``far`` caps the depth of unbounded
           intersections, e.g. forward-facing captures).

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
        return frusta_bounds([v.camera for v in views], far)


# --------------------------------------------------------------------------------------------
# NeRF / instant-ngp
# --------------------------------------------------------------------------------------------

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


def _image_file_size(path: Path):
    """``(width, height)`` of an image file without decoding it (None for EXR)."""
    if path.suffix.lower() == ".exr":
        return None
    return image_size(path)


def holdout_protocol(holdout: Holdout, order: str) -> str:
    """Words for a held-out split made by :func:`_holdout_split`."""
    if holdout is None or (isinstance(holdout, (int, np.integer)) and holdout == 0):
        return "no held-out views"
    if isinstance(holdout, (int, np.integer)):
        return (f"every {int(holdout)}th image held out ({order}, from the first)"
                + (" as in LLFF and Mip-NeRF 360" if int(holdout) == 8 else ""))
    return f"the images at {sorted(int(i) for i in holdout)} held out ({order})"


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
    path = _resolve_image(root, frame["file_path"])
    image = read_image(path) if load_images else None
    if image is not None:
        img_h, img_w = image.shape[:2]
    else:
        size = _image_file_size(path) if ("w" not in m or "h" not in m) else None
        img_w, img_h = size if size is not None else (None, None)
    w = float(m["w"]) if "w" in m else img_w
    h = float(m["h"]) if "h" in m else img_h
    if w is None or h is None:
        raise ValueError(f"{what}: cannot tell the size of '{path}' (give 'w' and 'h')")
    if str(m.get("camera_model", "")).lower() == "orthographic":
        return _orthographic_view(m, frame, path, image, w, h, downscale, what)
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
        fx, fy, cx, cy, w, h = fx * sx, fy * sy, cx * sx, cy * sy, img_w, img_h
    width, height = int(round(w)), int(round(h))
    lens = nerf_lens(m, width, height, fx, fy, cx, cy, f"{what}: frame '{frame['file_path']}'")
    if lens is not None:                      # distortion or non-square pixels: resample
        fx, fy, cx, cy = lens.pinhole()
        image = None if image is None else lens.undistort(image)
    elif fx != fy:                            # square within SQUARE_RTOL
        fx = fy = math.sqrt(fx * fy)
    c2w = as_rigid(frame["transform_matrix"], f"{what}: frame '{frame['file_path']}'")
    camera = Camera.from_opengl(c2w, width, height, fx, fy, cx, cy)
    view = View(Path(frame["file_path"]).stem if Path(frame["file_path"]).suffix.lower()
                in _IMAGE_SUFFIXES_LOWER else Path(frame["file_path"]).name, camera, image)
    return view.downscaled(downscale) if downscale != 1 else view


def _orthographic_view(m, frame, path, image, w, h, downscale, what) -> View:
    """A parallel-beam frame: ``ortho_width`` x ``ortho_height`` world units
    on ``w`` x ``h`` pixels (square), centred on the camera's axis unless
    ``cx, cy`` say otherwise."""
    where = f"{what}: frame '{frame['file_path']}'"
    try:
        ow, oh = float(m["ortho_width"]), float(m["ortho_height"])
    except KeyError:
        raise ValueError(f"{where}: camera_model orthographic needs 'ortho_width' and "
                         f"'ortho_height' (world units)") from None
    if image is not None and image.shape[:2] != (int(round(h)), int(round(w))):
        raise ValueError(f"{where}: image of {image.shape[1]}x{image.shape[0]} pixels, the "
                         f"frame says {w:g}x{h:g}")
    # pixel_size (written beside ortho_width) keeps the camera bit for bit
    s = float(m.get("pixel_size", ow / w))
    if not s > 0 or abs(ow / w - s) > 1e-6 * s or abs(oh / h - s) > 1e-6 * s:
        raise ValueError(f"{where}: orthographic pixels must be square and positive "
                         f"(ortho_width / w = {ow / w:g}, ortho_height / h = {oh / h:g})")
    c2w = as_rigid(frame["transform_matrix"], where)
    camera = Camera(int(round(w)), int(round(h)), 1.0, 1.0, float(m.get("cx", w / 2)),
                    float(m.get("cy", h / 2)), c2w @ OPENGL_TO_MITSUBA, s)
    view = View(Path(frame["file_path"]).stem, camera, image)
    return view.downscaled(downscale) if downscale != 1 else view


_IMAGE_SUFFIXES_LOWER = {s.lower() for s in _IMAGE_SUFFIXES}


def load_nerf(path, downscale: int = 1, holdout: Holdout = 8, *, load_images: bool = True,
              splits: Optional[Dict[str, str]] = None) -> Dataset:
    """Load a NeRF-convention data set.

    Reads ``transforms_train.json`` and ``transforms_test.json`` (or, without it,
    ``transforms_val.json`` as the test split), or a single ``transforms.json`` (instant-ngp /
    nerfstudio), or the json file ``path`` itself. Intrinsics come from ``fl_x, fl_y, cx, cy,
    w, h`` or ``camera_angle_x`` (``camera_angle_y``), per frame or top-level (a frame's keys
    win); missing ``cx, cy`` = image center, missing ``fl_y`` = ``fl_x``, missing ``w, h`` = the
    image size. Intrinsics given for another size than the stored image are rescaled to it.
    Lens distortion (``camera_model`` ``OPENCV`` with ``k1, k2, p1, p2`` (``k3 .. k6``),
    ``OPENCV_FISHEYE`` with ``k1 .. k4``) and focal lengths ``fl_x, fl_y`` more than 0.1 %
    apart are resampled away at load into square-pixel pinhole images
    (:mod:`mi_tetvr.recon.undistort`); closer focal lengths become their geometric mean.
    Frames whose image is missing are skipped with a warning. ``transform_matrix`` is
    camera-to-world in OpenGL axes (looks along -z, y up; :meth:`Camera.from_opengl
    <mi_tetvr.camera.Camera.from_opengl>`). A top-level ``aabb`` ``[[x0, y0, z0], [x1, y1,
    z1]]`` becomes ``Dataset.bbox``.

    Parameters
    ----------
    path : str or Path
        The data set folder or a json file (any name: the frames of that file are the
        training views, split by ``holdout``).
    downscale : int
        Integer area-averaging factor applied to each image as it is decoded (intrinsics divided
        exactly, see :meth:`Camera.downscaled <mi_tetvr.camera.Camera.downscaled>`).
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
    bbox, sampling, flux = None, "", None
    for split, name in files.items():
        fpath = root / name
        with open(fpath) as f:
            meta = json.load(f)
        sampling = sampling or str(meta.get("pixel_sampling", ""))
        if meta.get("xray_flux") is not None:
            flux = float(meta["xray_flux"])
        if bbox is None and "aabb" in meta and np.size(meta["aabb"]) == 6:
            bbox = np.asarray(meta["aabb"], np.float64).reshape(2, 3)
        frames = meta.get("frames", [])

        def frame_view(fr):
            try:
                return _nerf_frame_view(root, meta, fr, downscale, load_images, str(fpath))
            except FileNotFoundError as e:    # listed but not on disk: skipped
                return e

        views = _pool_map(frame_view, frames)
        missing = [str(v).split("'")[1] for v in views if isinstance(v, FileNotFoundError)]
        if missing:
            warnings.warn(f"{fpath}: {len(missing)} of {len(frames)} frames have no image on "
                          f"disk and are skipped ({', '.join(missing[:5])}"
                          f"{', ...' if len(missing) > 5 else ''})", stacklevel=2)
            if len(missing) == len(frames):
                raise FileNotFoundError(f"{fpath}: none of its {len(frames)} frames has an "
                                        f"image under {root}")
        out[split] = [v for v in views if not isinstance(v, FileNotFoundError)]
    train, test = out.get("train", []), out.get("test")
    protocol = "the data set's own test split"
    if test is None:
        train, test = _holdout_split(train, holdout)
        protocol = holdout_protocol(holdout, "in file order")
    return Dataset(train=train, test=test, points=None, bbox=bbox, name=root.name, root=root,
                   protocol=protocol, pixel_sampling=sampling, xray_flux=flux)


def _nerf_camera(c) -> dict:
    """A camera's intrinsics as a NeRF ``transforms.json`` holds them (an orthographic
    camera's in this project's own keys)."""
    if c.is_orthographic:
        return {"camera_model": "orthographic", "ortho_width": c.pixel_size * c.width,
                "ortho_height": c.pixel_size * c.height, "pixel_size": c.pixel_size,
                "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height}
    return {"camera_angle_x": 2.0 * math.atan(0.5 * c.width / c.fx),
            "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height}


def write_nerf(dataset_or_views, out_dir, split_names: Sequence[str] = ("train", "test"), *,
               image_format: str = "png") -> Path:
    """Write a NeRF-convention data set that :func:`load_nerf` reads back.

    One ``transforms_<split>.json`` per split, with ``camera_angle_x``, ``fl_x, fl_y, cx, cy, w,
    h`` (top-level when every view of the split shares them, else per frame) and
    ``transform_matrix`` (camera-to-world in OpenGL axes, :attr:`Camera.c2w_opengl
    <mi_tetvr.camera.Camera.c2w_opengl>`); the images go to ``<split>/<name>.<format>``.
    ``png``: 8-bit sRGB RGBA with straight alpha (the premultiplied color is divided by alpha);
    ``exr``: linear premultiplied float32 (exact); ``npy``: X-ray transmittance ``1 - alpha``
    (H, W) float32. Orthographic cameras are written with ``"camera_model": "orthographic"``,
    ``ortho_width``, ``ortho_height`` (world units) and ``pixel_size``.
    A data set ``bbox`` is written as ``aabb``, its ``pixel_sampling`` as ``pixel_sampling``.
    Sparse points are not written.

    Parameters
    ----------
    dataset_or_views : Dataset, list of View, or dict of {split: list of View}
        A Dataset writes ``train`` and ``test`` under ``split_names[0]`` and ``split_names[1]``
        (an empty test split is skipped); a list writes one split ``split_names[0]``.
    out_dir : str or Path
    split_names : sequence of str
    image_format : {"png", "exr", "npy"}

    Returns
    -------
    Path
        ``out_dir``.
    """
    out_dir = Path(out_dir)
    fmt = image_format.lower().lstrip(".")
    if fmt not in ("png", "exr", "npy"):
        raise ValueError(f"image_format must be 'png', 'exr' or 'npy', got {image_format!r}")
    bbox, sampling, flux = None, "", None
    if isinstance(dataset_or_views, Dataset):
        groups = {split_names[0]: dataset_or_views.train}
        if dataset_or_views.test:
            groups[split_names[1]] = dataset_or_views.test
        bbox, sampling = dataset_or_views.bbox, dataset_or_views.pixel_sampling
        flux = dataset_or_views.xray_flux
    elif isinstance(dataset_or_views, dict):
        groups = dict(dataset_or_views)
    else:
        groups = {split_names[0]: list(dataset_or_views)}
    out_dir.mkdir(parents=True, exist_ok=True)

    for split, views in groups.items():
        (out_dir / split).mkdir(exist_ok=True)
        intr = [(c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.pixel_size)
                for c in (v.camera for v in views)]
        shared = len(set(intr)) == 1
        meta: dict = {}

        if shared and views:
            meta.update(_nerf_camera(views[0].camera))
        if bbox is not None:
            meta["aabb"] = np.asarray(bbox, np.float64).reshape(2, 3).tolist()
        if sampling:
            meta["pixel_sampling"] = sampling
        if flux is not None:
            meta["xray_flux"] = float(flux)
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
                  "transform_matrix": v.camera.c2w_opengl.tolist()}
            if not shared:
                fr.update(_nerf_camera(v.camera))
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


def colmap_points(rec):
    """A COLMAP reconstruction's 3D points: positions (k, 3), colors (k, 3) uint8,
    reprojection errors (k,) in pixels and track lengths (k,), by point id; all None
    when it has none."""
    pts = sorted(rec.points3D.items())
    if not pts:
        return None, None, None, None
    return (np.array([p.xyz for _, p in pts], np.float64).reshape(-1, 3),
            np.array([p.color for _, p in pts], np.uint8).reshape(-1, 3),
            np.array([p.error for _, p in pts], np.float64),
            np.array([p.track.length() for _, p in pts], np.int64))


def load_colmap(path, images=None, downscale: int = 1, holdout: Holdout = 8, *,
                load_images: bool = True) -> Dataset:
    """Load a COLMAP sparse reconstruction (binary or text) with pycolmap.

    Distorted cameras (``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``, ``FULL_OPENCV``,
    ``OPENCV_FISHEYE``) and non-square pixels are resampled at load into square-pixel pinhole
    images (:mod:`mi_tetvr.recon.undistort`).
    COLMAP's world-to-camera ``[R | t]`` (camera looks along +z, y down, x right) becomes the
    camera's pose through :meth:`Camera.from_colmap <mi_tetvr.camera.Camera.from_colmap>`.
    COLMAP's pixel convention (top-left corner at 0, pixel centers at +0.5) is the one of
    :mod:`mi_tetvr.camera`, so ``cx, cy`` are kept as they are. Images are sorted by
    name.

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
    with needs("sfm", "reading a COLMAP data set"):
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

    entries, lenses = [], {}
    for img in sorted(rec.images.values(), key=lambda im: im.name):
        has_pose = img.has_pose() if callable(getattr(img, "has_pose", None)) \
            else getattr(img, "has_pose", True)
        if not has_pose:
            continue
        lens = lenses.setdefault(img.camera_id, Lens(rec.cameras[img.camera_id]))
        cfw = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
        entries.append((img.name, lens, np.asarray(cfw.rotation.quat, np.float64),
                        np.asarray(cfw.translation, np.float64)))

    def make(e) -> View:
        name, lens, quat, translation = e
        image = None
        if load_images:
            image = read_image(images / name)
            ih, iw = image.shape[:2]
            if (iw, ih) != (lens.width, lens.height):   # stored at another size
                if abs(iw * lens.height - ih * lens.width) > max(iw, ih, lens.width):
                    raise ValueError(
                        f"{images / name}: the photo is {iw}x{ih} (upright, by its EXIF "
                        f"orientation) but its camera in {model} is {lens.width}x"
                        f"{lens.height}: the model was made from pictures of another shape "
                        f"(turned or cropped); run structure from motion on the photos again "
                        f"(mi-tetvr process-data), which makes upright copies")
                lens = lens.resized(iw, ih)
            image = lens.undistort(image)
        camera = Camera.from_colmap(quat, translation, lens.width, lens.height, *lens.pinhole())
        v = View(Path(name).stem, camera, image)
        return v.downscaled(downscale) if downscale != 1 else v

    views = _pool_map(make, entries)
    train, test = _holdout_split(views, holdout)

    points, colors, errors, tracks = colmap_points(rec)
    name = path.name if path.name not in ("0", "sparse") else model.parent.name
    return Dataset(train=train, test=test, points=points, bbox=None, name=name, root=path,
                   point_colors=colors, point_errors=errors, point_track_lengths=tracks,
                   protocol=holdout_protocol(holdout, "sorted by name"))


def load_dataset(path, downscale: int = 1, holdout: Holdout = 8, **kw) -> Dataset:
    """A NeRF-style folder (``transforms*.json``) or a COLMAP model (``cameras.txt``
    / ``.bin``, also under ``sparse/`` or ``sparse/0``), whichever ``path`` holds."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"data set not found: {p}")
    if p.is_file() and p.suffix == ".json":
        return load_nerf(p, downscale, holdout, **kw)
    if any(p.glob("transforms*.json")):
        return load_nerf(p, downscale, holdout, **kw)
    try:
        _find_colmap_model(p)
    except (FileNotFoundError, ValueError):
        raise ValueError(f"{p} is neither a NeRF-style data set (transforms*.json) nor a "
                         f"COLMAP model (cameras/images/points3D .txt or .bin)") from None
    return load_colmap(p, downscale=downscale, holdout=holdout, **kw)
