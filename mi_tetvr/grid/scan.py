"""Real scanner projections in: Data Exchange HDF5 to the project's X-ray data set.

Data Exchange (the HDF5 layout of TomoPy and of the Advanced Photon Source:
``exchange/data`` (angles, rows, columns) raw counts, ``exchange/data_white``
flat fields, ``exchange/data_dark`` dark fields, ``exchange/theta`` angles)
is read (:func:`read_data_exchange`), flat/dark corrected to transmittance
``T = (data - dark) / (flat - dark)`` (:func:`transmittance`), its rings
optionally removed (Vo's sorting-based stripe filter, algotom), its rotation
centre found (Vo's Fourier method, algotom's ``find_center_vo``:
:func:`find_center`); the cameras of the geometry (:func:`scan_cameras`), the
held-out angles (:func:`held_out_split`) and the reconstruction grid on the
detector's pixels (:func:`scan_grid`) are what ``mi-tetvr process-xray``
writes as the data set that ``make-dataset --xray`` writes.

Geometry, as TIGRE and ASTRA describe a circular scan about the world z axis:

* parallel beam (``parallel``): detector pixels of ``pixel_size`` world
  units; the rotation axis falls on column ``center`` (a detector shift of
  ``center - (width - 1) / 2`` pixels);
* cone beam (``cone``): a source at ``source_distance`` from the axis, a flat
  detector at ``detector_distance`` from the source (TIGRE's DSO and DSD,
  ASTRA's ``source_origin`` and ``source_origin + origin_det``), pixels of
  ``pixel_size`` on the detector, the central ray through column ``center``.

Angles are the object's rotation in degrees; the camera at angle ``a`` looks
along ``-(cos a, sin a, 0)`` (as :func:`mi_tetvr.grid.xray.xray_cameras`).
World units: those of ``pixel_size`` (default: the detector is 2 wide).
"""
from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np

from mi_tetvr.camera import Camera, look_at
from mi_tetvr.extras import needs

__all__ = ["Scan", "read_data_exchange", "transmittance", "find_center", "remove_rings",
           "estimate_flux", "scan_cameras", "scan_grid", "bin_pixels",
           "held_out_split"]


@dataclasses.dataclass
class Scan:
    """Projections as read: ``data`` (angles, rows, columns) raw counts,
    ``flats`` / ``darks`` (k, rows, columns) or ``None``, ``angles`` in
    degrees, and what was said while reading (``notes``)."""
    data: np.ndarray
    flats: np.ndarray | None
    darks: np.ndarray | None
    angles: np.ndarray
    source: str = ""
    notes: list = dataclasses.field(default_factory=list)


def _angles_in_degrees(theta, units, notes):
    """Degrees from ``theta``: by its ``units`` attribute, else by its size
    (a scan whose angles all lie within 2 pi + 1 % is read as radians, since a
    scan in degrees over less than 6.3 degrees is no tomography)."""
    theta = np.asarray(theta, np.float64).ravel()
    if units:
        u = units.lower()
        if u.startswith("rad"):
            notes.append(f"angles in radians (units attribute {units!r})")
            return np.degrees(theta)
        if u.startswith("deg"):
            notes.append(f"angles in degrees (units attribute {units!r})")
            return theta
        raise ValueError(f"angles have units {units!r}: expected degrees or radians")
    span = float(np.ptp(theta)) if len(theta) > 1 else 0.0
    if np.max(np.abs(theta)) <= 2 * np.pi * 1.01:
        notes.append(f"angles read as radians (no units attribute; they span {span:.4g}, "
                     f"at most 2 pi)")
        return np.degrees(theta)
    notes.append(f"angles read as degrees (no units attribute; they span {span:.4g})")
    return theta


def read_data_exchange(path, angles=None, normalized: bool = False) -> Scan:
    """Read a Data Exchange HDF5 file.

    Parameters
    ----------
    path : path
    angles : (first, last), optional
        Degrees of the first and the last projection, evenly between, when the
        file has no ``exchange/theta`` (or to override it).
    normalized : bool
        The data are transmittance already (no flats needed).

    Raises
    ------
    ValueError
        Not an HDF5 file, no ``exchange/data``, no flat fields (unless
        ``normalized``), no angles, angles whose count differs from the
        projections', or fields of another detector size.
    """
    with needs("tomo", "reading an HDF5 scan"):
        import h5py
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise ValueError(f"{path} is not an HDF5 file ({e})") from None
    notes = []
    with f:
        if "exchange/data" not in f:
            raise ValueError(f"{path} has no exchange/data: not a Data Exchange file "
                             f"(it holds {sorted(f.keys())})")
        data = np.asarray(f["exchange/data"], np.float64)
        if data.ndim == 2:
            data = data[:, None, :]
        if data.ndim != 3 or min(data.shape) < 1:
            raise ValueError(f"exchange/data has shape {data.shape}: expected (angles, rows, "
                             f"columns)")
        fields = {}
        for key, name in (("data_white", "flat"), ("data_dark", "dark")):
            if f"exchange/{key}" in f:
                a = np.asarray(f[f"exchange/{key}"], np.float64)
                a = a[None] if a.ndim == 2 else a
                if a.shape[1:] != data.shape[1:]:
                    raise ValueError(f"exchange/{key} has {name} fields of {a.shape[1:]} "
                                     f"pixels, the projections {data.shape[1:]}")
                fields[name] = a
        theta, units = None, None
        if "exchange/theta" in f:
            theta = np.asarray(f["exchange/theta"], np.float64)
            units = f["exchange/theta"].attrs.get("units")
            units = units.decode() if isinstance(units, bytes) else units
    if not normalized and "flat" not in fields:
        raise ValueError(f"{path} has no flat fields (exchange/data_white): the counts cannot "
                         f"be turned into transmittance. If exchange/data holds transmittance "
                         f"already, say so (--normalized)")
    if normalized:
        fields = {}
        notes.append("data read as transmittance (no flat/dark correction)")
    elif "dark" not in fields:
        notes.append("no dark fields (exchange/data_dark): dark current taken as 0")
    if angles is not None:
        first, last = (float(a) for a in angles)
        theta = np.linspace(first, last, len(data))
        notes.append(f"angles {first:g} to {last:g} degrees as given")
    elif theta is None:
        raise ValueError(f"{path} has no angles (exchange/theta): give the first and the last "
                         f"(--angles FIRST,LAST in degrees)")
    else:
        if theta.size != len(data):
            raise ValueError(f"exchange/theta holds {theta.size} angles for {len(data)} "
                             f"projections in exchange/data")
        theta = _angles_in_degrees(theta, units, notes)
    return Scan(data, fields.get("flat"), fields.get("dark"), np.asarray(theta, np.float64),
                str(path), notes)


def transmittance(scan: Scan) -> np.ndarray:
    """``(data - dark) / (flat - dark)`` with the mean flat and dark fields
    (float64, (angles, rows, columns)); detector pixels whose flat is not
    above their dark are dead: their values are interpolated from the
    neighbouring columns (with a warning)."""
    if scan.flats is None:
        return scan.data.copy()
    dark = np.zeros(scan.data.shape[1:]) if scan.darks is None else scan.darks.mean(0)
    gain = scan.flats.mean(0) - dark
    dead = gain <= 0
    t = (scan.data - dark) / np.where(dead, 1.0, gain)
    if dead.any():
        warnings.warn(f"{int(dead.sum())} detector pixels have a flat field not above their "
                      f"dark field: interpolated from their neighbours", stacklevel=2)
        cols = np.arange(t.shape[2])
        for r in range(t.shape[1]):
            bad = dead[r]
            if bad.all():
                raise ValueError(f"detector row {r} has no live pixel (flat <= dark)")
            for a in range(len(t)):
                t[a, r, bad] = np.interp(cols[bad], cols[~bad], t[a, r, ~bad])
    return t


def bin_pixels(t: np.ndarray, factor: int) -> np.ndarray:
    """Average ``factor x factor`` detector pixels (rows and columns; the
    remainder dropped)."""
    if factor <= 1:
        return t
    n, h, w = t.shape
    hh, ww = max(h // factor, 1), w // factor
    fr = factor if h >= factor else h
    return t[:, :hh * fr, :ww * factor].reshape(n, hh, fr, ww, factor).mean((2, 4))


def remove_rings(depth: np.ndarray, size: int = 21) -> np.ndarray:
    """Ring artefacts removed from optical depths (angles, rows, columns):
    Vo, Atwood and Drakopoulos 2018's sorting-based stripe filter (algotom's
    ``remove_stripe_based_sorting``) on each row's sinogram."""
    with needs("tomo", "ring removal"):
        from algotom.prep.removal import remove_stripe_based_sorting
    out = np.empty_like(depth)
    for r in range(depth.shape[1]):
        out[:, r, :] = remove_stripe_based_sorting(depth[:, r, :], size=size)
    return out


def find_center(depth: np.ndarray, angles) -> float:
    """The rotation axis's detector column (0 the first pixel's centre) of a
    parallel-beam scan over (about) 180 degrees: Vo, Atwood and Drakopoulos
    2014's Fourier-space metric of each row's sinogram joined with its
    mirror (algotom's ``find_center_vo``), the median over the rows."""
    with needs("tomo", "finding a scan's rotation centre"):
        from algotom.prep.calculation import find_center_vo
    span = float(np.ptp(angles))
    if not 150.0 <= span <= 210.0:
        raise ValueError(f"the centre is found on a scan over about 180 degrees; these angles "
                         f"span {span:.1f}: give --center")
    order = np.argsort(angles)
    rows = range(depth.shape[1]) if depth.shape[1] <= 8 else \
        np.linspace(0, depth.shape[1] - 1, 8).round().astype(int)
    return float(np.median([find_center_vo(depth[order, r, :]) for r in rows]))


def estimate_flux(t: np.ndarray) -> float:
    """The photons per unattenuated pixel that Poisson noise of the size
    seen would take: the noise of each projection row estimated by
    scikit-image's ``estimate_sigma`` (the median absolute deviation of the
    finest wavelet coefficients, Donoho and Johnstone), ``var(T) = T / N``,
    so ``N = mean(T) / sigma^2``; the median over the rows."""
    with needs("tomo", "estimating a scan's noise"):
        from skimage.restoration import estimate_sigma
    values = []
    for a in range(t.shape[0]):
        for r in range(t.shape[1]):
            s = float(estimate_sigma(t[a, r]))
            if s > 0:
                values.append(float(np.mean(np.clip(t[a, r], 0, None))) / s ** 2)
    if not values:
        raise ValueError("no noise found in the projections: give the flux (--flux)")
    return float(np.median(values))


def scan_cameras(angles, width: int, height: int, pixel_size: float, center: float,
                 beam: str = "parallel", source_distance: float | None = None,
                 detector_distance: float | None = None, row_center: float | None = None):
    """The cameras of a circular scan about the world z axis (see the module
    docstring). Parallel beam: orthographic, its rays through the pixel
    centres; the rays of column ``center`` meet the axis. Cone beam: a pinhole
    at ``source_distance`` with focal length ``detector_distance /
    pixel_size`` pixels and the principal point on column ``center`` and row
    ``row_center`` (default: the middle)."""
    if pixel_size <= 0:
        raise ValueError(f"pixel size must be > 0, got {pixel_size}")
    rc = (height - 1) / 2 if row_center is None else float(row_center)
    # a parallel beam's detector plane well outside the reach of its pixels
    distance = 2.0 * pixel_size * max(width, height) + 1.0
    cams = []
    for ang in np.radians(np.asarray(angles, np.float64)):
        direction = np.array([np.cos(ang), np.sin(ang), 0.0])
        if beam == "parallel":
            # the ray of pixel centre u = center + 0.5 passes the axis: the camera's
            # x axis (look_at's first column) carries the detector shift
            pose = look_at(direction, np.zeros(3), (0, 0, 1))
            shift = pixel_size * (width / 2 - center - 0.5) * pose[:3, 0] \
                + pixel_size * (height / 2 - rc - 0.5) * pose[:3, 1]
            cams.append(Camera.orthographic(distance * direction - shift, -shift, (0, 0, 1),
                                            width, height, pixel_size))
        elif beam == "cone":
            if not source_distance or not detector_distance or \
                    detector_distance <= source_distance:
                raise ValueError("a cone beam needs a source distance and a larger "
                                 "source-detector distance")
            cams.append(Camera.look_at(source_distance * direction, np.zeros(3), (0, 0, 1),
                                       width, height, fx=detector_distance / pixel_size,
                                       cx=center + 0.5, cy=rc + 0.5))
        else:
            raise ValueError(f"beam must be parallel or cone, got {beam!r}")
    return cams


def scan_grid(width: int, height: int, pixel_size: float, center: float):
    """The reconstruction grid of a parallel-beam scan: samples ``pixel_size``
    apart, one z sample per detector row (on the rows' heights), x and y from
    ``-m`` to ``m`` pixels about the axis with ``m`` the detector's reach
    from it (rounded up), so that a column of samples lies on the axis (as a
    slice reconstruction centres it). Returns ``(shape_xyz, origin)``."""
    m = int(np.ceil(max(center + 0.5, width - center - 0.5)))
    z0 = -pixel_size * (height - 1) / 2
    return (2 * m + 1, 2 * m + 1, height), np.array([-m * pixel_size, -m * pixel_size, z0])


def held_out_split(n: int, every: int):
    """Indices of the training and the held-out angles: every ``every``-th
    angle (from ``every // 2``) held out; none for ``every`` 0."""
    idx = np.arange(n)
    if not every:
        return idx, idx[:0]
    if every < 2 or n // every < 1:
        raise ValueError(f"holding out every {every}-th of {n} angles leaves no training or "
                         f"no held-out angle")
    test = idx[every // 2::every]
    return np.setdiff1d(idx, test), test
