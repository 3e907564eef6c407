"""X-ray projections of a grid volume: exact line integrals of its trilinear field.

The attenuation is ``mu(p) = scale * v(p)`` with ``v`` the volume's trilinear
interpolant (normalised to [0, 1]) inside its box and 0 outside. Along a ray
``v`` is a cubic polynomial between two crossings of grid planes, so two-point
Gauss-Legendre quadrature on every such interval integrates it exactly
(:func:`line_integrals`). An image holds the transmittance ``I / I0 =
exp(-integral of mu)``.

:func:`xray_cameras` places parallel-beam (orthographic) or cone-beam
(perspective) cameras on a circle around the volume's z axis, the geometry of
a CT scanner, so that image row ``j`` of a parallel-beam view is the
projection of one z slice of samples;
:func:`mi_tetvr.recon.synthetic.make_xray_dataset` writes a NeRF-style data
set of such images (``.npy`` transmittance) that ``mi-tetvr fit --model
absorption`` reads.
"""
from __future__ import annotations

import numpy as np

from mi_tetvr.camera import Camera
from mi_tetvr.extras import needs
from mi_tetvr.grid.volume import Volume, trilinear_numpy

__all__ = ["line_integrals", "xray_cameras", "rotation_axis", "project_volume",
           "parallel_angles", "fdk", "MAX_DEPTH", "FACE_TOLERANCE"]

#: Default largest optical depth of a data set's rays (transmittance e^-2.5 = 8 %):
#: the attenuation scale is chosen for it.
MAX_DEPTH = 2.5
#: A ray parallel to an axis this fraction of a sample spacing outside a face
#: of the box runs along the face (:func:`line_integrals`).
FACE_TOLERANCE = 1e-6
_GL = 0.5 / np.sqrt(3.0)     # two-point Gauss-Legendre nodes at 1/2 -+ this


def line_integrals(volume: Volume, origins, directions, chunk: int = 4096) -> np.ndarray:
    """``integral of v(o + t d) dt`` over each ray (``t`` in world units of the
    unit ``d``), exact for the trilinear field (float64).

    Parameters
    ----------
    volume : Volume
    origins, directions : (k, 3) float
        Rays (directions need not be unit: ``t`` is measured along the normalised one).
    chunk : int
        Rays per batch (memory ~ chunk * (nx + ny + nz) * 50 bytes).

    Returns
    -------
    (k,) float64
    """
    o = np.array(origins, np.float64).reshape(-1, 3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    lo, hi = volume.bounds()
    # A ray along a face integrates what lies on it: a ray parallel to an axis
    # (to 1e-12) within FACE_TOLERANCE of a sample spacing outside the box is
    # moved onto its face, so that rounding of a camera's pose never drops it.
    along = np.abs(d) < 1e-12
    d = np.where(along, 0.0, d)
    tol = FACE_TOLERANCE * volume.spacing
    o = np.where(along & (o < lo) & (o >= lo - tol), lo, o)
    o = np.where(along & (o > hi) & (o <= hi + tol), hi, o)
    planes = [lo[a] + np.arange(volume.shape[a]) * volume.spacing[a] for a in range(3)]
    out = np.zeros(len(o))
    for s in range(0, len(o), chunk):
        oc, dc = o[s:s + chunk], d[s:s + chunk]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / dc
            ta, tb = (lo - oc) * inv, (hi - oc) * inv
        t0 = np.nanmax(np.where(np.isfinite(ta), np.minimum(ta, tb), -np.inf), axis=1)
        t1 = np.nanmin(np.where(np.isfinite(ta), np.maximum(ta, tb), np.inf), axis=1)
        # a ray parallel to a slab must lie inside it
        for a in range(3):
            par = dc[:, a] == 0
            outside = par & ((oc[:, a] < lo[a]) | (oc[:, a] > hi[a]))
            t1[outside] = -np.inf
        hit = t1 > t0
        if not hit.any():
            continue
        oc, dc, t0, t1 = oc[hit], dc[hit], t0[hit], t1[hit]
        with np.errstate(divide="ignore", invalid="ignore"):
            ts = [(planes[a][None, :] - oc[:, a:a + 1]) / dc[:, a:a + 1] for a in range(3)]
        t = np.concatenate([t0[:, None], t1[:, None], *ts], axis=1)
        t = np.where(np.isfinite(t), t, t0[:, None])
        t = np.sort(np.clip(t, t0[:, None], t1[:, None]), axis=1)
        a, b = t[:, :-1], t[:, 1:]
        length = b - a
        total = np.zeros(len(oc))
        for node in (0.5 - _GL, 0.5 + _GL):
            p = oc[:, None, :] + (a + node * length)[..., None] * dc[:, None, :]
            total += 0.5 * np.sum(length * trilinear_numpy(volume.values,
                                                           volume.world_to_index(p)), axis=1)
        out[np.flatnonzero(hit) + s] = total
    return out


def parallel_angles(n: int, offset: float = 0.0) -> np.ndarray:
    """``n`` angles in degrees evenly over 180 (a parallel-beam scan), starting
    at ``offset`` times the step (0.5: halfway between those of ``offset=0``)."""
    return (np.arange(n) + offset) * 180.0 / n


def rotation_axis(volume: Volume) -> np.ndarray:
    """The point the parallel-beam cameras of :func:`xray_cameras` turn
    around: x and y of the sample nearest the box's centre (so that the
    detector's pixel grid, and a slice-by-slice reconstruction on it, lie on
    the volume's samples), z of the box's centre."""
    lo, hi = volume.bounds()
    centre = lo + np.floor(np.array(volume.shape) / 2) * volume.spacing
    centre[2] = (lo[2] + hi[2]) / 2
    return centre


def xray_cameras(volume: Volume, angles, beam: str = "parallel", distance: float = 3.0,
                 fov: float = 40.0):
    """Cameras on a circle around the volume's z axis at ``angles`` (degrees,
    counter-clockwise from +x), looking at it, z up.

    ``parallel``: orthographic, pixels of the volume's x spacing, the
    rotation axis through the sample nearest the box's centre and the middle
    pixel's centre, an odd width covering the slice, one row per z sample
    (needs the z spacing equal to x's): every pixel centre lies on a sample
    of the slice. The outermost rows (and, at 0 and 90 degrees, columns) run
    along the box's faces: a tet grid fitted to such data should reach a
    little beyond the box. ``cone``: perspective with ``fov`` (degrees)
    at ``distance`` world units, the same pixel counts.
    """
    lo, hi = volume.bounds()
    s = float(volume.spacing[0])
    if beam == "parallel" and not np.allclose(volume.spacing, s, rtol=1e-6):
        raise ValueError(f"parallel-beam rows on the z samples need isotropic spacing, got "
                         f"{volume.spacing}")
    centre = rotation_axis(volume)
    reach = float(np.max(np.hypot(np.maximum(centre[0] - lo[0], hi[0] - centre[0]),
                                  np.maximum(centre[1] - lo[1], hi[1] - centre[1]))))
    width = 2 * int(np.ceil(reach / s)) + 3               # odd: the axis on a pixel centre
    height = volume.shape[2]                              # one row per z sample
    cams = []
    for ang in np.radians(np.asarray(angles, np.float64)):
        direction = np.array([np.cos(ang), np.sin(ang), 0.0])
        if beam == "parallel":
            cams.append(Camera.orthographic(centre + distance * direction, centre, (0, 0, 1),
                                            width, height, s))
        elif beam == "cone":
            cams.append(Camera.look_at(centre + distance * direction, centre, (0, 0, 1),
                                       width, height, fov_x=fov))
        else:
            raise ValueError(f"beam must be parallel or cone, got {beam!r}")
    return cams


def project_volume(volume: Volume, camera: Camera, scale: float = 1.0) -> np.ndarray:
    """The transmittance image ``exp(-scale * integral of v)`` (height, width)
    of ``camera`` through pixel centres (float64)."""
    o, d = camera.rays()
    depth = scale * line_integrals(volume, o, d)
    return np.exp(-depth).reshape(camera.height, camera.width)


def _ramp(width: int, spacing: float) -> np.ndarray:
    """The band-limited ramp filter's kernel (Kak and Slaney, Eq. 3.61) on
    ``2 width - 1`` taps of ``spacing``: 1/(4 s^2) at 0, -1/(n pi s)^2 at odd n."""
    n = np.arange(-(width - 1), width)
    h = np.zeros(len(n))
    h[n == 0] = 1.0 / (4.0 * spacing ** 2)
    odd = n % 2 == 1
    h[odd] = -1.0 / (np.pi * n[odd] * spacing) ** 2
    return h


def fdk(grid: Volume, views, scale: float) -> np.ndarray:
    """Feldkamp-Davis-Kress cone-beam reconstruction (FDK, 1984) on the
    samples of ``grid`` from cone-beam views on a full circle around its z
    axis (what :func:`xray_cameras` makes with ``beam="cone"``): each
    projection weighted by the cosine of its rays' angle to the central ray,
    ramp-filtered along the detector rows, and back-projected with the
    inverse square of the depth along the central ray.

    Parameters
    ----------
    grid : Volume
        Where to reconstruct (shape, spacing, bounds; its values are not read).
    views : list of View
        Perspective X-ray views evenly over 360 degrees (alpha = 1 - transmittance).
    scale : float
        Attenuation per world unit of a value 1 (the result is in values).

    Returns
    -------
    (nz, ny, nx) float64
    """
    with needs("tomo", "FDK reconstruction"):
        from scipy.ndimage import map_coordinates
        from scipy.signal import fftconvolve
    if not views or any(v.camera.is_orthographic for v in views):
        raise ValueError("fdk needs perspective (cone-beam) views")
    axis = rotation_axis(grid)
    nx, ny, nz = grid.shape
    samples = grid.sample_points()
    out = np.zeros(len(samples))
    for view in views:
        cam = view.camera
        source = cam.to_world[:3, 3]
        radius = float(np.linalg.norm((source - axis)[:2]))
        w, h = cam.width, cam.height
        a = (np.arange(w) + 0.5 - cam.cx) / cam.fx          # tangents of the rays' angles
        b = (np.arange(h) + 0.5 - cam.cy) / cam.fy
        depth = -np.log(np.clip(1.0 - view.image[..., 3].astype(np.float64), 1e-12, None))
        weighted = depth / scale / np.sqrt(1.0 + a[None, :] ** 2 + b[:, None] ** 2)
        # rows filtered in units of the virtual detector through the axis
        step = radius / cam.fx
        q = step * fftconvolve(weighted, _ramp(w, step)[None, :], mode="same", axes=1)
        uv, u_depth = cam.project(samples)
        val = map_coordinates(q, [uv[:, 1] - 0.5, uv[:, 0] - 0.5], order=1, mode="constant",
                              cval=0.0)
        out += (radius / np.maximum(u_depth, 1e-12)) ** 2 * val
    return (out * np.pi / len(views)).reshape(nz, ny, nx)
