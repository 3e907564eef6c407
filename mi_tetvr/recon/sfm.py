"""Structure from motion with pycolmap: camera poses (and sparse points) from photos or a video.

:func:`run_sfm` turns a folder of photos (or a video, whose frames are extracted evenly) into a
COLMAP model in ``out_dir/sparse/0`` with the pictures in ``out_dir/images``, which
:func:`mi_tetvr.recon.datasets.load_colmap` and :func:`~mi_tetvr.recon.datasets.load_dataset`
read back (``mi-tetvr process-data`` on the command line). :func:`triangulate` adds sparse
points to views whose poses are already known (an instant-ngp ``transforms.json``, a rendered
capture). :func:`align_cameras` compares two sets of cameras of the same pictures up to a
similarity transform (an SfM result against a reference).

Pipeline
--------
Everything runs on the CPU through pycolmap (COLMAP's library, no ``colmap`` executable):
SIFT features (``Device.cpu``), exhaustive matching (all pairs; sequential matching of
neighbouring frames for a video) with geometric verification, COLMAP's incremental mapper,
which starts from the best-connected image pair, registers the other images one at a time
and bundle-adjusts. Its poses and points are in an arbitrary frame and scale (COLMAP
normalizes the model); compare them to other cameras with :func:`align_cameras`.

Small image sets
----------------
COLMAP's defaults are tuned for collections of hundreds of photos. With fewer than
``SMALL_SET`` (30) images, :func:`run_sfm` by default extracts affine-covariant SIFT with
domain-size pooling (``estimate_affine_shape``, ``domain_size_pooling``: about twice the
extraction time, many more matches across wide baselines) and lets the triangulator keep
points seen by two images only (``ignore_two_view_tracks = False``); without both, 4 aerial
photos 20 - 50 degrees apart (``colmap-maupertuis``) do not reconstruct at all.

Conventions
-----------
Camera poses and pixel coordinates are COLMAP's (OpenCV axes, top-left image corner at 0),
converted by :class:`mi_tetvr.camera.Camera` as everywhere in the project; images in
memory are premultiplied linear RGBA (:mod:`mi_tetvr.recon.images`), written for COLMAP as
8-bit sRGB PNG.
"""
from __future__ import annotations

import math
import shutil
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np

from mi_tetvr.extras import MissingExtra, needs

__all__ = ["run_sfm", "triangulate", "align_cameras", "extract_frames", "SMALL_SET",
           "IMAGE_SUFFIXES", "VIDEO_SUFFIXES"]

#: Below this many images :func:`run_sfm` and :func:`triangulate` use affine-covariant SIFT
#: and keep two-view tracks (see the module docstring).
SMALL_SET = 30

#: Photo files :func:`run_sfm` takes from a folder (case-insensitive).
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")

#: Files :func:`run_sfm` reads as a video (frames extracted with :func:`extract_frames`).
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv",
                  ".gif")

#: Inlier matches of a verified image pair (COLMAP's ``min_num_inliers``).
_MIN_INLIERS = 15

#: Fraction of registered images below which :func:`run_sfm` warns.
_WARN_FRACTION = 0.7


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------

@contextmanager
def _quiet_colmap(level: int = 1):
    """COLMAP logs every step at INFO level to stderr: keep warnings and errors only."""
    with needs("sfm", "structure from motion"):
        import pycolmap
    lg = getattr(pycolmap, "logging", None)
    old = getattr(lg, "minloglevel", None) if lg is not None else None
    if old is not None:
        lg.minloglevel = max(int(old), level)
    try:
        yield
    finally:
        if old is not None:
            lg.minloglevel = old


def _progress(total: int, enabled: bool, desc: str):
    from mi_tetvr.progress import progress_bar as tqdm
    return tqdm(total=total, disable=not enabled, desc=desc, unit="step", leave=False,
                dynamic_ncols=True)


def _advance(bar, n: int) -> None:
    """Advance a tqdm bar by ``n`` without passing its total."""
    n = min(n, bar.total - bar.n) if bar.total is not None else n
    if n > 0:
        bar.update(n)


def _extraction_options(max_image_size: int, affine: bool):
    with needs("sfm", "structure from motion"):
        import pycolmap
    eo = pycolmap.FeatureExtractionOptions()
    eo.max_image_size = int(max_image_size)
    eo.use_gpu = False
    if affine:
        eo.sift.estimate_affine_shape = True
        eo.sift.domain_size_pooling = True
    return eo


def _matching_options(seed: int):
    with needs("sfm", "structure from motion"):
        import pycolmap
    mo = pycolmap.FeatureMatchingOptions()
    mo.use_gpu = False
    vo = pycolmap.TwoViewGeometryOptions()
    vo.ransac.random_seed = int(seed)
    return mo, vo


def _extract(database: Path, image_dir: Path, names: Sequence[str], camera_mode, reader,
             extraction, bar, chunk: int) -> None:
    """SIFT of ``names`` in chunks (pycolmap has no progress callback): one bar step per
    image. After the first chunk of a single-camera set the later chunks reuse its camera."""
    with needs("sfm", "structure from motion"):
        import pycolmap
    names = list(names)
    for start in range(0, len(names), chunk):
        part = names[start:start + chunk]
        pycolmap.extract_features(database, image_dir, image_names=part,
                                  camera_mode=camera_mode, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        if camera_mode == pycolmap.CameraMode.SINGLE and reader.existing_camera_id < 0:
            db = pycolmap.Database.open(database)
            try:
                reader.existing_camera_id = int(db.read_image_with_name(part[0]).camera_id)
            finally:
                db.close()
        _advance(bar, len(part))


def _images_in(folder: Path) -> List[Path]:
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                  and not p.name.startswith("."))


def _copy_photos(given: Sequence[Path], image_dir: Path, log: Callable) -> Tuple[list, dict]:
    """Upright copies of the photos in ``image_dir`` (COLMAP reads the pixels as stored, the
    loaders turn them by their EXIF orientation: both must see the same picture). Returns the
    copies and ``{name: why}`` of the photos that could not be read (left out, logged)."""
    from mi_tetvr.recon.images import upright_copy
    files, unreadable, turned = [], {}, 0
    for src in given:
        dst = image_dir / src.name
        if dst.exists():
            dst.unlink()
        try:
            turned += upright_copy(src, dst)
        except (OSError, SyntaxError, ValueError) as e:   # Pillow's errors for damaged files
            if dst.exists():
                dst.unlink()
            unreadable[src.name] = f"cannot be read: {e}"
            log(f"run_sfm: {src.name} cannot be read ({e}); left out")
            continue
        files.append(dst)
    if turned:
        log(f"run_sfm: {turned} of {len(files)} photos turned upright by their EXIF orientation")
    return files, unreadable


def _readable_in_place(given: Sequence[Path], log: Callable) -> Tuple[list, dict]:
    """The photos of a folder that is already the data set's image folder: read, not copied
    (a turned one would be seen sideways by COLMAP and upright by the loaders)."""
    with needs("sfm", "reading photos"):
        from PIL import Image
        from mi_tetvr.recon.images import exif_orientation
    files, unreadable = [], {}
    for p in given:
        try:
            with Image.open(p) as im:
                im.load()
                turned = exif_orientation(im) != 1
        except (OSError, SyntaxError, ValueError) as e:
            unreadable[p.name] = f"cannot be read: {e}"
            log(f"run_sfm: {p.name} cannot be read ({e}); left out")
            continue
        if turned:
            raise ValueError(f"{p} carries an EXIF orientation and lies in the output's own "
                             f"image folder: pass the folder of photos and a different output "
                             f"folder, so that upright copies can be made")
        files.append(p)
    return files, unreadable


def _image_sizes(paths: Sequence[Path]) -> list:
    """The upright ``(width, height)`` of each picture."""
    from mi_tetvr.recon.images import image_size
    return [image_size(p) for p in paths]


def _focal_priors(database: Path, image_dir: Path, log: Callable) -> str:
    """Where the mapper's starting focal length comes from: COLMAP reads it from the EXIF data
    with its camera sensor database; where it found none, the photos' own 35 mm equivalent
    (:func:`mi_tetvr.recon.images.exif_focal_px`) is set as the prior in the database. Returns
    ``"exif"``, ``"exif for some photos"`` or ``"guess"`` (1.2 times the longest side)."""
    with needs("sfm", "structure from motion"):
        import pycolmap
        from mi_tetvr.recon.images import exif_focal_px
    db = pycolmap.Database.open(database)
    try:
        by_camera = {}
        for im in db.read_all_images():
            by_camera.setdefault(int(im.camera_id), []).append(im.name)
        known = 0
        for cam in db.read_all_cameras():
            names = by_camera.get(int(cam.camera_id), [])
            if not cam.has_prior_focal_length:
                f = [x for x in (exif_focal_px(image_dir / n) for n in names) if x]
                if f:
                    params = np.asarray(cam.params, dtype=np.float64).copy()
                    params[list(cam.focal_length_idxs())] = float(np.median(f))
                    cam.params = params
                    cam.has_prior_focal_length = True
                    db.update_camera(cam)
            known += len(names) if cam.has_prior_focal_length else 0
        total = sum(len(v) for v in by_camera.values())
    finally:
        db.close()
    if known < total:
        log(f"run_sfm: {total - known} of {total} photos have no focal length in their EXIF "
            f"data; the mapper starts from 1.2 times the longest side")
    return "exif" if known == total else ("exif for some photos" if known else "guess")


def _why_unregistered(database: Path, names: Sequence[str]) -> dict:
    """``{name: why}`` for photos left out of the model, from the database: too few features,
    no verified match with another photo, or matched but not placed by the mapper."""
    with needs("sfm", "structure from motion"):
        import pycolmap
    db = pycolmap.Database.open(database)
    try:
        ids = {im.name: int(im.image_id) for im in db.read_all_images()}
        pairs, geometries = db.read_two_view_geometries()
        partners, best = {}, {}
        for pid, g in zip(pairs, geometries):
            n = len(g.inlier_matches)
            if n < _MIN_INLIERS:
                continue
            for i in pycolmap.pair_id_to_image_pair(int(pid)):
                partners[int(i)] = partners.get(int(i), 0) + 1
                best[int(i)] = max(best.get(int(i), 0), n)
        out = {}
        for name in names:
            i = ids.get(name)
            k = db.num_keypoints_for_image(i) if i is not None else 0
            if k < 2 * _MIN_INLIERS:
                out[name] = f"too few features ({k}): blurred, dark or without texture"
            elif i not in partners:
                out[name] = f"{k} features but no verified match with any other photo"
            else:
                out[name] = (f"matched with {partners[i]} photo(s) (at most {best[i]} inliers) "
                             f"but not placed: too little overlap or parallax with the "
                             f"registered ones")
    finally:
        db.close()
    return out


def _summary_of(rec) -> dict:
    return {"images_registered": int(rec.num_reg_images()),
            "points": int(rec.num_points3D()),
            "mean_reprojection_error": float(rec.compute_mean_reprojection_error())
            if rec.num_points3D() else float("nan"),
            "mean_track_length": float(rec.compute_mean_track_length())
            if rec.num_points3D() else float("nan")}


# --------------------------------------------------------------------------------------------
# video
# --------------------------------------------------------------------------------------------

def _video_backend(path: Path):
    """``(name, count(), frames())`` of the first video reader that is installed
    (PyAV, OpenCV, imageio-ffmpeg; Pillow for a GIF); ``frames()`` yields (H, W, 3)
    uint8 RGB."""
    for backend in (_pyav, _opencv, _imageio_ffmpeg):
        found = backend(str(path))
        if found is not None:
            return found
    if path.suffix.lower() == ".gif":
        return _pillow(str(path))
    raise MissingExtra(f"reading the video {path} needs a video decoder, and none is "
                       f"installed: pip install \"mi_tetvr[sfm]\" (imageio-ffmpeg; or PyAV or "
                       f"OpenCV), or extract the frames yourself and pass their folder",
                       name="imageio_ffmpeg")


def _pyav(p):
    try:
        import av
    except ImportError:
        return None

    def count():
        with av.open(p) as c:
            s = c.streams.video[0]
            return int(s.frames) or sum(1 for pk in c.demux(s) if pk.size)

    def frames():
        with av.open(p) as c:
            for f in c.decode(video=0):
                yield f.to_ndarray(format="rgb24")
    return "PyAV", count, frames


def _opencv(p):
    try:
        import cv2
    except ImportError:
        return None

    def count():
        cap = cv2.VideoCapture(p)
        try:
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            if n <= 0:
                n = 0
                while cap.grab():
                    n += 1
            return n
        finally:
            cap.release()

    def frames():
        cap = cv2.VideoCapture(p)
        try:
            while True:
                ok, f = cap.read()
                if not ok:
                    break
                yield np.ascontiguousarray(f[..., ::-1])
        finally:
            cap.release()
    return "OpenCV", count, frames


def _imageio_ffmpeg(p):
    try:
        import imageio_ffmpeg
    except ImportError:
        return None

    def count():
        return int(imageio_ffmpeg.count_frames_and_secs(p)[0])

    def frames():
        gen = imageio_ffmpeg.read_frames(p)
        meta = next(gen)
        w, h = meta["size"]
        for buf in gen:
            yield np.frombuffer(buf, np.uint8).reshape(h, w, 3)
    return "imageio-ffmpeg", count, frames


def _pillow(p):
    with needs("sfm", "reading a GIF"):
        from PIL import Image, ImageSequence

    def count():
        with Image.open(p) as im:
            return int(getattr(im, "n_frames", 1))

    def frames():
        with Image.open(p) as im:
            for f in ImageSequence.Iterator(im):
                yield np.asarray(f.convert("RGB"))
    return "Pillow", count, frames



def extract_frames(video, out_dir, max_frames: int = 100, *, log: Callable = print
                   ) -> List[Path]:
    """Extract at most ``max_frames`` frames of a video, evenly spaced, as JPEG files.

    The decoder is the first installed of PyAV (``av``), OpenCV (``cv2``) and
    ``imageio-ffmpeg``; a ``.gif`` also reads with Pillow.

    Parameters
    ----------
    video : str or Path
    out_dir : str or Path
        Folder for ``frame_00000.jpg``, ``frame_00001.jpg``, ... (quality 95), numbered in
        time order (COLMAP's sequential matcher orders images by name).
    max_frames : int
    log : callable
        Receives one line about the extraction.

    Returns
    -------
    list of Path
        The files written.

    Raises
    ------
    ValueError
        No decoder installed, or no frame in the file.
    """
    with needs("sfm", "reading photos"):
        from PIL import Image
    video, out_dir = Path(video), Path(out_dir)
    if max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    name, count, frames = _video_backend(video)
    n = count()
    if n <= 0:
        raise ValueError(f"{video}: no video frames found")
    keep = np.unique(np.round(np.linspace(0, n - 1, min(n, int(max_frames)))).astype(int))
    wanted = set(keep.tolist())
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for i, frame in enumerate(frames()):
        if i in wanted:
            path = out_dir / f"frame_{len(written):05d}.jpg"
            Image.fromarray(np.asarray(frame, np.uint8)).save(path, quality=95)
            written.append(path)
        if i >= keep[-1]:
            break
    if not written:
        raise ValueError(f"{video}: no video frames could be decoded")
    log(f"{video.name}: {len(written)} of {n} frames extracted ({name})")
    return written


# --------------------------------------------------------------------------------------------
# structure from motion
# --------------------------------------------------------------------------------------------

def run_sfm(images, out_dir, *, matcher: Optional[str] = None, max_image_size: int = 1600,
            camera_model: str = "SIMPLE_RADIAL", single_camera: bool = True,
            camera_params: Optional[Sequence[float]] = None, max_frames: int = 100,
            affine_features: Optional[bool] = None, seed: int = 0, progress: bool = True,
            log: Callable = print) -> dict:
    """Recover the cameras of a set of photos (or a video's frames) with COLMAP.

    The pictures are copied to ``out_dir/images``, SIFT features extracted on the
    CPU into ``out_dir/database.db``, matched and geometrically verified, and COLMAP's
    incremental mapper run; its largest model is written (binary) to ``out_dir/sparse/0``,
    which :func:`mi_tetvr.recon.datasets.load_colmap` reads (``load_dataset(out_dir)``).
    A run replaces an earlier database and model in ``out_dir`` (and, for a video, the
    ``frame_*.jpg`` extracted by an earlier run).

    Parameters
    ----------
    images : str or Path
        A folder of photos (``.jpg``, ``.png``, ``.tif``, ``.bmp``; not its subfolders; of
        any sizes; copied upright by their EXIF orientation; a photo that cannot be read is
        left out and reported), or a video file (``.mp4``, ``.mov``, ... ``.gif``), whose
        frames are extracted evenly (:func:`extract_frames`, at most ``max_frames``).
    out_dir : str or Path
    matcher : {"exhaustive", "sequential"}, optional
        Which image pairs are matched: all of them (the default for photos), or each image with
        its neighbours in name order (the default for a video; COLMAP's quadratic overlap of
        10).
    max_image_size : int
        Images are downsized to this longest side for feature extraction (keypoints are
        scaled back to full resolution).
    camera_model : str
        COLMAP camera model fitted by the mapper (``SIMPLE_PINHOLE``, ``PINHOLE``,
        ``SIMPLE_RADIAL`` (default), ``RADIAL``, ``OPENCV``, ...); the loaders resample
        distorted images into pinholes.
    single_camera : bool
        One shared camera for all pictures of a size (the same camera and zoom: a phone's
        portrait photos share one, its landscape ones another); False, or pictures of
        different sizes with ``camera_params`` given, give each picture its own.
    camera_params : sequence of float, optional
        Starting intrinsics in pycolmap's order for ``camera_model`` (``SIMPLE_RADIAL``:
        ``f, cx, cy, k``; ``PINHOLE``: ``fx, fy, cx, cy``); the mapper refines them. Default:
        the focal length from the photos' EXIF data, else ``1.2 * max(width, height)``
        (COLMAP's guess, fine for ordinary photos, far off for wide lenses).
    max_frames : int
        Frames taken from a video.
    affine_features : bool, optional
        Affine-covariant SIFT with domain-size pooling (more matches across wide baselines,
        slower); default: with fewer than :data:`SMALL_SET` images.
    seed : int
        Seed of COLMAP's random number generator and RANSAC (repeatable runs).
    progress : bool
        A tqdm progress bar over the stages (features per image, matching, mapping per
        registered image).
    log : callable
        Receives the lines reported (warnings included); ``print`` by default.

    Returns
    -------
    dict
        ``images_given`` (int), ``images_registered`` (int), ``points`` (int),
        ``mean_reprojection_error`` (pixels), ``mean_track_length`` (images per point),
        ``seconds`` (wall time), ``stage_seconds`` (dict: ``frames``, ``features``,
        ``matching``, ``mapping``), ``camera`` (model name and parameters of the first camera),
        ``registered`` / ``unregistered`` (lists of image names), ``why_unregistered``
        (``{name: reason}`` read from the matches), ``unreadable`` (``{name: reason}`` of photos
        left out), ``focal_prior`` (``"exif"``, ``"exif for some photos"``, ``"guess"`` or
        ``"given"``), ``models`` (the sizes of all
        models found), ``model`` (path of ``sparse/0``), ``images`` (path of the image folder),
        ``matcher``.

    Raises
    ------
    ValueError
        Fewer than 2 pictures, a path that is neither a folder nor a video, no decoder for a
        video, or a model with fewer than 3 registered images (or none); the message says how
        many images were given and how many registered.
    FileNotFoundError
        ``images`` does not exist.
    """
    with needs("sfm", "structure from motion"):
        import pycolmap
    t0 = time.perf_counter()
    src, out_dir = Path(images), Path(out_dir)
    _check_sfm_args(src, matcher, camera_model)
    out_dir.mkdir(parents=True, exist_ok=True)
    image_dir = out_dir / "images"
    stages = {}
    t = time.perf_counter()
    files, unreadable, matcher = _pictures(src, image_dir, matcher, max_frames, log)
    stages["frames"] = time.perf_counter() - t
    n = len(files)
    if n < 2:
        raise ValueError(f"structure from motion needs at least 2 images, got {n}"
                         + (f" ({len(unreadable)} could not be read: "
                            f"{', '.join(sorted(unreadable)[:5])})" if unreadable else ""))
    names = [f.name for f in files]
    database = _fresh_database(out_dir)
    shutil.rmtree(out_dir / "sparse", ignore_errors=True)
    mapping_dir = out_dir / "sparse" / "_models"
    single, groups = _camera_groups(files, bool(single_camera), camera_params, log)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    if camera_params is not None:
        reader.camera_params = ",".join(repr(float(x)) for x in camera_params)
    pycolmap.set_random_seed(int(seed))
    options = _extraction_options(
        max_image_size, n < SMALL_SET if affine_features is None else bool(affine_features))
    mode = pycolmap.CameraMode.SINGLE if single else pycolmap.CameraMode.PER_IMAGE
    bar = _progress(2 * n + 1, progress, "features")
    try:
        with _quiet_colmap():
            t = time.perf_counter()
            for group in groups:
                reader.existing_camera_id = -1
                _extract(database, image_dir, group, mode, reader, options, bar,
                         chunk=max(2, math.ceil(n / 20)))
            focal_prior = "given" if camera_params is not None else \
                _focal_priors(database, image_dir, log)
            stages["features"] = time.perf_counter() - t
            t = time.perf_counter()
            _match(database, matcher, seed, bar)
            stages["matching"] = time.perf_counter() - t
            t = time.perf_counter()
            recs = _map(database, image_dir, mapping_dir, n, seed, bar)
            stages["mapping"] = time.perf_counter() - t
    finally:
        bar.close()
    best, sizes = _best_model(recs, database, names, mapping_dir, max_image_size, log)
    model_dir = out_dir / "sparse" / "0"
    model_dir.mkdir(parents=True, exist_ok=True)
    best.write(model_dir)
    shutil.rmtree(mapping_dir, ignore_errors=True)
    summary = {**_run_summary(best, names, database), "seconds": time.perf_counter() - t0,
               "stage_seconds": stages, "unreadable": unreadable, "focal_prior": focal_prior,
               "models": sizes, "model": str(model_dir), "images": str(image_dir),
               "matcher": matcher}
    _report(summary, recs, best, log)
    return summary


def _run_summary(best, names, database):
    """What :func:`run_sfm` reports of the kept model ``best`` of the pictures ``names``."""
    registered = sorted(best.images[i].name for i in best.reg_image_ids())
    cam = next(iter(best.cameras.values()))
    return {"images_given": len(names), **_summary_of(best),
            "camera": {"model": cam.model_name,
                       "params": [float(x) for x in np.asarray(cam.params)]},
            "registered": registered, "unregistered": sorted(set(names) - set(registered)),
            "why_unregistered": _why_unregistered(database,
                                                  sorted(set(names) - set(registered)))}


def _check_sfm_args(src, matcher, camera_model):
    with needs("sfm", "structure from motion"):
        import pycolmap
    if not src.exists():
        raise FileNotFoundError(f"{src}: no such folder or video")
    if matcher is not None and matcher not in ("exhaustive", "sequential"):
        raise ValueError(f"matcher must be 'exhaustive' or 'sequential', got {matcher!r}")
    if camera_model not in pycolmap.CameraModelId.__members__ or camera_model == "INVALID":
        models = [m for m in pycolmap.CameraModelId.__members__ if m != "INVALID"]
        raise ValueError(f"unknown camera model {camera_model!r} (one of {', '.join(models)})")


def _fresh_database(folder):
    """``folder/database.db``, an earlier run's removed (with its write-ahead log)."""
    database = Path(folder) / "database.db"
    for stale in (database, Path(str(database) + "-wal"), Path(str(database) + "-shm")):
        if stale.exists():
            stale.unlink()
    return database


def _pictures(src, image_dir, matcher, max_frames, log):
    """The pictures of a run in ``image_dir``: a video's frames extracted (those of an
    earlier run removed), or the photos copied upright; those that cannot be read and
    the matcher (default: sequential for a video, exhaustive for photos)."""
    if src.is_file():
        if src.suffix.lower() not in VIDEO_SUFFIXES:
            raise ValueError(f"{src}: neither a folder of images nor a video "
                             f"({', '.join(VIDEO_SUFFIXES)})")
        _video_backend(src)                    # no decoder: fail before touching out_dir
        for old in image_dir.glob("frame_*.jpg") if image_dir.is_dir() else ():
            old.unlink()
        return extract_frames(src, image_dir, max_frames, log=log), {}, \
            matcher or "sequential"
    given = _images_in(src)
    if len(given) < 2:
        raise ValueError(f"structure from motion needs at least 2 images, {src} has "
                         f"{len(given)} ({', '.join(IMAGE_SUFFIXES)})")
    image_dir.mkdir(exist_ok=True)
    if image_dir.resolve() == src.resolve():
        files, unreadable = _readable_in_place(given, log)
    else:
        files, unreadable = _copy_photos(given, image_dir, log)
    return files, unreadable, matcher or "exhaustive"


def _camera_groups(files, single, camera_params, log):
    """Whether pictures share cameras, and the groups of names that share one: all of
    them, or (a phone's portrait and landscape photos) one camera per picture size."""
    names = [f.name for f in files]
    sizes = _image_sizes(files)
    if not single or len(set(sizes)) == 1:
        return single, [names]
    if camera_params is not None:
        log("run_sfm: the pictures have different sizes; each gets its own camera")
        return False, [names]
    groups = [[f.name for f, s in zip(files, sizes) if s == size] for size in sorted(set(sizes))]
    log(f"run_sfm: the pictures have {len(groups)} sizes ("
        + ", ".join(f"{len(g)} of {w}x{h}" for g, (w, h) in zip(groups, sorted(set(sizes))))
        + "); one camera for each size")
    return True, groups


def _match(database, matcher, seed, bar):
    """Features matched and geometrically verified: all pairs, or neighbours in name order."""
    with needs("sfm", "structure from motion"):
        import pycolmap
    bar.set_description("matching")
    mo, vo = _matching_options(seed)
    match = pycolmap.match_sequential if matcher == "sequential" else pycolmap.match_exhaustive
    match(database, matching_options=mo, verification_options=vo, device=pycolmap.Device.cpu)
    _advance(bar, 1)


def _map(database, image_dir, mapping_dir, n, seed, bar):
    """COLMAP's incremental mapper, seeded; its models."""
    with needs("sfm", "structure from motion"):
        import pycolmap
    bar.set_description("mapping")
    po = pycolmap.IncrementalPipelineOptions()
    po.min_model_size = 3
    po.random_seed = int(seed)
    po.mapper.random_seed = int(seed)
    po.triangulation.random_seed = int(seed)
    if n < SMALL_SET:
        po.triangulation.ignore_two_view_tracks = False
    mapping_dir.mkdir(parents=True, exist_ok=True)
    recs = pycolmap.incremental_mapping(
        database, image_dir, mapping_dir, options=po,
        initial_image_pair_callback=lambda: _advance(bar, 2),
        next_image_callback=lambda: _advance(bar, 1))
    _advance(bar, bar.total)
    return list(recs.values()) if isinstance(recs, dict) else list(recs or [])


def _best_model(recs, database, names, mapping_dir, max_image_size, log):
    """The model with the most registered images (then points) and the sizes of all;
    fewer than 3 images registered is an error that says why the others were not."""
    sizes = sorted((int(r.num_reg_images()) for r in recs), reverse=True)
    best = max(recs, key=lambda r: (r.num_reg_images(), r.num_points3D())) if recs else None
    k = int(best.num_reg_images()) if best is not None else 0
    if k >= 3:
        return best, sizes
    shutil.rmtree(mapping_dir, ignore_errors=True)
    placed = {best.images[i].name for i in best.reg_image_ids()} if best is not None else set()
    why = _why_unregistered(database, [m for m in names if m not in placed])
    log("run_sfm: not registered: " + "; ".join(f"{m}: {w}" for m, w in why.items()))
    raise ValueError(
        f"structure from motion registered {k} of {len(names)} images: the photos need more "
        f"overlap (each part of the scene seen by 3 or more photos from nearby "
        f"viewpoints), texture and sharpness"
        + ("" if max_image_size >= 1600 else f", or a larger max_image_size "
           f"({max_image_size})") + (f" (models found: {sizes})" if sizes else ""))


def _report(summary, recs, best, log):
    """Warnings about the images the kept model left out."""
    k, n = summary["images_registered"], summary["images_given"]
    if k < _WARN_FRACTION * n:
        log(f"warning: structure from motion registered only {k} of {n} images "
            f"({100 * k / n:.0f} %); the others need more overlap with the rest")
    for name, why in summary["why_unregistered"].items():
        log(f"run_sfm: {name} not registered: {why}")
    elsewhere = sorted({r.images[i].name for r in recs if r is not best
                        for i in r.reg_image_ids()} - set(summary["registered"]))
    if elsewhere:
        log(f"run_sfm: {len(elsewhere)} image(s) registered only in smaller separate models "
            f"(not kept): {', '.join(elsewhere[:5])}{', ...' if len(elsewhere) > 5 else ''}")


# --------------------------------------------------------------------------------------------
# triangulation with known poses
# --------------------------------------------------------------------------------------------

def _cam_from_world(camera) -> np.ndarray:
    """(3, 4) COLMAP world-to-camera ``[R | t]`` of a Camera (the inverse of
    :meth:`Camera.from_colmap <mi_tetvr.camera.Camera.from_colmap>`)."""
    c2w = camera.c2w_opencv
    r = c2w[:3, :3].T
    return np.hstack([r, (-r @ c2w[:3, 3])[:, None]])


def triangulate(dataset_or_views, work_dir, *, max_image_size: int = 1600,
                affine_features: Optional[bool] = None, min_points: int = 20, seed: int = 0,
                progress: bool = True, log: Callable = print
                ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sparse 3D points of posed views: features matched across the images and triangulated
    with the cameras held fixed.

    The images are written as sRGB PNG (composited over black) to ``work_dir/images``, SIFT
    features extracted and matched (all pairs) into ``work_dir/database.db``, and a
    ``pycolmap.Reconstruction`` built with one ``PINHOLE`` camera per view (``fx, fy, cx,
    cy``) and the views' poses (``cam_from_world`` = the inverse of ``camera.c2w_opencv``);
    ``pycolmap.triangulate_points`` triangulates the verified matches and refines the points
    by bundle adjustment with the poses and intrinsics fixed, so the points are in the data
    set's own world frame. The model is written to ``work_dir/sparse``.

    Parameters
    ----------
    dataset_or_views : Dataset or sequence of View
        Pinhole views with images (``View.image``, premultiplied linear RGBA); a Dataset's
        ``train + test``.
    work_dir : str or Path
    max_image_size : int
        Longest image side for feature extraction.
    affine_features : bool, optional
        Affine-covariant SIFT (default: with fewer than :data:`SMALL_SET` views).
    min_points : int
        Fewer triangulated points raise ``ValueError``.
    seed : int
    progress : bool
        A tqdm bar over the stages.
    log : callable
        Receives one summary line.

    Returns
    -------
    points : (k, 3) float64
        World positions.
    colors : (k, 3) uint8
        sRGB colors sampled from the images.
    errors : (k,) float64
        Mean reprojection error of each point in pixels.
    track_lengths : (k,) int64
        Number of images that observe each point.

    Raises
    ------
    ValueError
        Fewer than 2 views, a view without image or an orthographic camera, or fewer than
        ``min_points`` points.
    """
    with needs("sfm", "structure from motion"):
        import pycolmap
        from mi_tetvr.recon.images import write_image
    views = list(dataset_or_views.views if hasattr(dataset_or_views, "views")
                 else dataset_or_views)
    if len(views) < 2:
        raise ValueError(f"triangulate needs at least 2 posed views, got {len(views)}")
    for v in views:
        if v.image is None:
            raise ValueError(f"triangulate: view '{v.name}' has no image")
        if v.camera.pixel_size is not None:
            raise ValueError(f"triangulate: view '{v.name}' is orthographic (pinholes only)")
    work_dir = Path(work_dir)
    image_dir = work_dir / "images"
    shutil.rmtree(image_dir, ignore_errors=True)
    shutil.rmtree(work_dir / "sparse", ignore_errors=True)
    image_dir.mkdir(parents=True)
    database = _fresh_database(work_dir)
    n = len(views)
    names = [f"{i:05d}.png" for i in range(n)]
    affine = n < SMALL_SET if affine_features is None else bool(affine_features)
    pycolmap.set_random_seed(int(seed))

    bar = _progress(2 * n + 2, progress, "images")
    try:
        with _quiet_colmap():
            for name, v in zip(names, views):
                write_image(image_dir / name, v.image[..., :3])     # premultiplied = over black
                _advance(bar, 1)
            bar.set_description("features")
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = "PINHOLE"
            _extract(database, image_dir, names, pycolmap.CameraMode.PER_IMAGE, reader,
                     _extraction_options(max_image_size, affine), bar,
                     chunk=max(2, math.ceil(n / 20)))

            rec = _posed_reconstruction(database, names, views)
            _match(database, "exhaustive", seed, bar)
            bar.set_description("triangulation")
            po = pycolmap.IncrementalPipelineOptions()
            po.random_seed = int(seed)
            po.triangulation.random_seed = int(seed)
            if n < SMALL_SET:
                po.triangulation.ignore_two_view_tracks = False
            out = work_dir / "sparse"
            out.mkdir(parents=True, exist_ok=True)
            rec = pycolmap.triangulate_points(rec, database, image_dir, out, clear_points=True,
                                              options=po, refine_intrinsics=False)
            _advance(bar, 1)
    finally:
        bar.close()

    return _points_of(rec, n, min_points, log)


def _posed_reconstruction(database, names, views):
    """A reconstruction of the known cameras: the database's cameras become the views'
    pinholes (verification uses them) and the reconstruction reuses the database's
    camera and image ids."""
    with needs("sfm", "structure from motion"):
        import pycolmap
    db = pycolmap.Database.open(database)
    try:
        by_name = {im.name: im for im in db.read_all_images()}
        rec = pycolmap.Reconstruction()
        for name, v in zip(names, views):
            im = by_name[name]
            c = v.camera
            cam = pycolmap.Camera(camera_id=im.camera_id, model="PINHOLE",
                                  width=c.width, height=c.height,
                                  params=[c.fx, c.fy, c.cx, c.cy])
            cam.has_prior_focal_length = True
            db.update_camera(cam)
            rec.add_camera_with_trivial_rig(cam)
            rec.add_image_with_trivial_frame(
                pycolmap.Image(name=name, camera_id=im.camera_id, image_id=im.image_id),
                pycolmap.Rigid3d(_cam_from_world(c)))
    finally:
        db.close()
    return rec


def _points_of(rec, n, min_points, log):
    """The triangulated points' positions, colors, errors and track lengths; fewer than
    ``min_points`` is an error."""
    from mi_tetvr.recon.datasets import colmap_points
    points, colors, errors, tracks = colmap_points(rec)
    k = 0 if points is None else len(points)
    if k < min_points:
        raise ValueError(f"triangulation with the known poses gave {k} points from {n} views "
                         f"(fewer than {min_points}): the images need more overlap and texture "
                         f"(or the poses do not fit the images)")
    log(f"triangulated {k} points from {n} views (mean reprojection error "
        f"{errors.mean():.2f} px, mean track length {tracks.mean():.2f})")
    return points, colors, errors, tracks


# --------------------------------------------------------------------------------------------
# comparing cameras
# --------------------------------------------------------------------------------------------

def _rotation_angle_deg(r: np.ndarray) -> np.ndarray:
    """Angles (degrees) of (..., 3, 3) rotation matrices, from the trace (clipped)."""
    c = np.clip((np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(c))


def align_cameras(estimated: Sequence, reference: Sequence, *, robust: bool = False) -> dict:
    """Compare cameras of the same pictures (matched by order) up to a similarity transform.

    The similarity ``x -> s R x + t`` that maps the estimated camera centers onto the
    reference ones in the least-squares sense (Umeyama's closed form, by
    ``pycolmap.estimate_sim3d``; LO-RANSAC with ``pycolmap.estimate_sim3d_robust`` when
    ``robust``, inlier threshold 5 % of the scene size) is applied to the estimated poses;
    then, per camera, the rotation error is the angle of ``R_ref^T R_aligned`` (camera-to-world
    rotations) and the position error is the distance between the aligned and the reference
    center divided by the scene size: the diagonal of the reference centers' bounding box.
    The similarity comes from the centers alone, so when they lie nearly on a line its
    rotation about that line is poorly determined and shows in every camera's rotation error;
    the relative rotation errors (the angle between ``R_i^T R_j`` of the two sets, for every
    pair ``i < j``) do not depend on the alignment.

    Parameters
    ----------
    estimated, reference : sequence of Camera
        Same length, at least 3, same pictures in the same order; the reference centers must
        not all lie on one line.
    robust : bool
        Ignore outlier cameras while estimating the similarity.

    Returns
    -------
    dict
        ``scale`` (float), ``rotation`` ((3, 3) float64), ``translation`` ((3,) float64): the
        similarity (reference from estimated); ``aligned``: list of Camera (the estimated
        ones moved by it, their intrinsics unchanged); ``rotation_errors_deg`` ((n,)
        float64); ``position_errors`` ((n,) float64, relative to ``scene_size``);
        ``scene_size`` (float); ``relative_rotation_errors_deg`` ((n (n - 1) / 2,) float64,
        pairs in ``numpy.triu_indices`` order); ``rotation_error_deg_mean`` / ``_median`` /
        ``_max``, ``position_error_mean`` / ``_median`` / ``_max`` and
        ``relative_rotation_error_deg_mean`` / ``_median`` / ``_max``.

    Raises
    ------
    ValueError
        Different lengths, fewer than 3 cameras, or a degenerate configuration (no
        similarity found).
    """
    with needs("sfm", "structure from motion"):
        import pycolmap
        from mi_tetvr.camera import Camera
    est, ref = list(estimated), list(reference)
    if len(est) != len(ref):
        raise ValueError(f"align_cameras: {len(est)} estimated and {len(ref)} reference "
                         f"cameras (they must be the same pictures, in the same order)")
    if len(est) < 3:
        raise ValueError(f"align_cameras needs at least 3 cameras, got {len(est)}")
    src = np.array([c.center for c in est], np.float64)
    dst = np.array([c.center for c in ref], np.float64)
    scene = float(np.linalg.norm(dst.max(0) - dst.min(0)))
    if not scene > 0:
        raise ValueError("align_cameras: the reference cameras all sit at one point")
    if robust:
        ro = pycolmap.RANSACOptions()
        ro.max_error = 0.05 * scene
        ro.random_seed = 0
        sim = pycolmap.estimate_sim3d_robust(src, dst, ro)
        sim = sim.get("tgt_from_src") if isinstance(sim, dict) else sim
    else:
        sim = pycolmap.estimate_sim3d(src, dst)
    if sim is None:
        raise ValueError("align_cameras: no similarity found (are the camera centers "
                         "collinear or coincident?)")
    s = float(sim.scale)
    r = np.asarray(sim.rotation.matrix(), np.float64)
    t = np.asarray(sim.translation, np.float64).reshape(3)
    aligned = []
    for c in est:
        m = np.eye(4)
        m[:3, :3] = r @ c.to_world[:3, :3]
        m[:3, 3] = s * r @ c.to_world[:3, 3] + t
        aligned.append(Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, m, c.pixel_size))
    ra = np.array([a.to_world[:3, :3] for a in aligned])
    rr = np.array([c.to_world[:3, :3] for c in ref])
    rot = _rotation_angle_deg(np.transpose(rr, (0, 2, 1)) @ ra)
    pos = np.linalg.norm(np.array([a.center for a in aligned]) - dst, axis=1) / scene
    re = np.array([c.to_world[:3, :3] for c in est])
    i, j = np.triu_indices(len(est), 1)
    rel_ref = np.transpose(rr[i], (0, 2, 1)) @ rr[j]
    rel_est = np.transpose(re[i], (0, 2, 1)) @ re[j]
    rel = _rotation_angle_deg(np.transpose(rel_ref, (0, 2, 1)) @ rel_est)
    out = {"scale": s, "rotation": r, "translation": t, "aligned": aligned,
           "rotation_errors_deg": rot, "position_errors": pos, "scene_size": scene,
           "relative_rotation_errors_deg": rel}
    for key, v in (("rotation_error_deg", rot), ("position_error", pos),
                   ("relative_rotation_error_deg", rel)):
        out[f"{key}_mean"] = float(v.mean())
        out[f"{key}_median"] = float(np.median(v))
        out[f"{key}_max"] = float(v.max())
    return out
