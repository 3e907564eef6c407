"""The grid ray marcher: a regular-grid volume rendered in Dr.Jit under a transfer function.

The grid baseline for comparisons with the tet renderer, and the renderer of the ground-truth
images of :func:`mi_tetvr.recon.synthetic.make_dataset`. Needs a Mitsuba variant when called
(not at import).

Conventions
-----------
Rendering model (post-classification emission-absorption)
    Along a ray the volume's box (:meth:`Volume.bounds <mi_tetvr.grid.volume.Volume.bounds>`)
    is entered at ``t0`` and left at ``t1`` (slab test); the marcher takes steps of
    ``dt = step * min(spacing)`` (``step`` in voxels, default 0.25; the last step is shortened
    to end exactly at ``t1``) and samples the **midpoint** of each step: the scalar is
    interpolated trilinearly, *then* the transfer function gives the linear-RGB color ``c``
    and the extinction ``sigma`` (``TransferFunction`` opacity times ``opacity_scale``, per
    unit length in the world units of the ``[-1, 1]`` placement).  Per step
    ``a = exp(-sigma * h)``, ``C += T * c * (1 - a)``, ``T *= a`` (the exact integral for ``c``
    and ``sigma`` held constant over the step, as in the tet renderer's sub-intervals).  The
    output is premultiplied linear RGB over black plus ``alpha = 1 - T``.  Rays stop early
    once ``T < min_transmittance`` (default 1e-4, the tet integrator's default).  The midpoint
    rule makes the transmittance exact for an extinction linear along the step; the error is
    O(dt^2) in general.
Transfer function
    Evaluated exactly inside Dr.Jit from its piecewise-linear control points (no lookup
    table): ``t = (s - lo) / (hi - lo)`` with ``value_range=(lo, hi)`` (default ``(0, 1)``,
    i.e. the normalised scalar), clamped like :meth:`TransferFunction.__call__`.
Cameras
    :class:`mi_tetvr.camera.Camera` (rays through the pixel centers, see
    :mod:`mi_tetvr.camera`) or a Mitsuba sensor.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_tetvr.grid.volume import Volume
from mi_tetvr.camera import Camera
from mi_tetvr.transfer import TransferFunction

__all__ = ["TFEval", "GridField", "render_rays", "render_volume", "camera_rays"]


def _check_variant():
    if mi.variant() is None:
        raise RuntimeError("mi_tetvr.grid.marcher: call mitsuba.set_variant(...) first "
                           "(e.g. 'llvm_ad_rgb' or 'cuda_ad_rgb')")


class TFEval:
    """A :class:`TransferFunction` evaluated exactly inside Dr.Jit.

    The piecewise-linear function with non-decreasing positions ``p`` and values ``v`` is
    written as the telescoping sum ``v_0 + sum_i (v_{i+1} - v_i) w_i(t)`` with
    ``w_i = clamp((t - p_i) / (p_{i+1} - p_i), 0, 1)`` (a step ``t >= p_i`` at a jump), which
    equals ``numpy.interp`` with clamping and the after-jump value at a jump.

    Parameters
    ----------
    tf : TransferFunction
    value_range : (lo, hi)
        Scalar values mapped to the TF's 0 and 1 (default ``(0, 1)``).
    opacity_scale : float
        Factor on the TF opacity (extinction per unit world length).
    """

    def __init__(self, tf: TransferFunction, value_range=(0.0, 1.0), opacity_scale=1.0):
        lo, hi = (float(x) for x in value_range)
        if not (np.isfinite(lo) and np.isfinite(hi)) or hi < lo:
            raise ValueError(f"value_range must be finite with lo <= hi, got {value_range!r}")
        s = float(opacity_scale)
        if not np.isfinite(s) or s < 0:
            raise ValueError(f"opacity_scale must be finite and >= 0, got {opacity_scale!r}")
        self.tf, self.lo, self.hi, self.opacity_scale = tf, lo, hi, s

    @staticmethod
    def _pl(t, pos, vals):
        out = float(vals[0])
        for i in range(len(pos) - 1):
            dv = float(vals[i + 1] - vals[i])
            if dv == 0.0:
                continue
            p0, p1 = float(pos[i]), float(pos[i + 1])
            if p1 > p0:
                w = dr.clip((t - p0) * (1.0 / (p1 - p0)), 0.0, 1.0)
            else:
                w = dr.select(t >= p0, 1.0, 0.0)
            out = out + dv * w
        return out

    def __call__(self, s):
        """Color (Color3f, linear RGB) and extinction (Float) for scalar values ``s`` (Float)."""
        t = (s - self.lo) * (1.0 / (self.hi - self.lo)) if self.hi > self.lo else s * 0.0
        t = dr.clip(t, 0.0, 1.0)
        tf = self.tf
        c = mi.Color3f(*[mi.Float(0.0) + self._pl(t, tf.color_positions, tf.colors[:, k])
                         for k in range(3)])
        sigma = mi.Float(0.0) + self._pl(t, tf.opacity_positions, tf.opacities)
        return c, sigma * self.opacity_scale


class GridField:
    """A :class:`Volume`'s samples in a flat Dr.Jit buffer, with trilinear lookup.

    ``buffer`` (``mi.Float``, x fastest) may be replaced by a differentiable array.
    """

    def __init__(self, volume: Volume):
        _check_variant()
        nx, ny, nz = volume.shape
        self.shape = (nx, ny, nz)
        self.buffer = mi.Float(np.ascontiguousarray(volume.values, np.float32).ravel())
        self.origin = [float(v) for v in volume.origin]
        self.inv_spacing = [1.0 / float(v) for v in volume.spacing]
        lo, hi = volume.bounds()
        self.bbox = mi.ScalarBoundingBox3f(lo.tolist(), hi.tolist())

    def eval(self, p):
        """Trilinear interpolation at world points ``p`` (Point3f); clamps outside the box."""
        nx, ny, nz = self.shape
        g = [(p[a] - self.origin[a]) * self.inv_spacing[a] for a in range(3)]
        g = [dr.clip(g[a], 0.0, float(self.shape[a] - 1)) for a in range(3)]
        i0 = [dr.minimum(mi.Int32(dr.floor(g[a])), self.shape[a] - 2) for a in range(3)]
        f = [g[a] - mi.Float(i0[a]) for a in range(3)]
        base = i0[0] + nx * (i0[1] + ny * i0[2])
        sx, sy, sz = 1, nx, nx * ny
        b = self.buffer

        def v(o):
            return dr.gather(mi.Float, b, base + o)

        c00 = dr.lerp(v(0), v(sx), f[0])
        c10 = dr.lerp(v(sy), v(sy + sx), f[0])
        c01 = dr.lerp(v(sz), v(sz + sx), f[0])
        c11 = dr.lerp(v(sz + sy), v(sz + sy + sx), f[0])
        return dr.lerp(dr.lerp(c00, c10, f[1]), dr.lerp(c01, c11, f[1]), f[2])


@dr.syntax
def _march(field: GridField, tfe: TFEval, o, d, dt: float, min_transmittance: float):
    """The marching loop (see the module docstring for the model)."""
    bbox = mi.BoundingBox3f(mi.Point3f(field.bbox.min), mi.Point3f(field.bbox.max))
    hit, t0, t1 = bbox.ray_intersect(mi.Ray3f(o, d))
    t = dr.maximum(t0, 0.0)
    active = mi.Bool(hit) & (t1 > t)
    T = mi.Float(1.0)
    C = mi.Color3f(0.0)
    while dr.hint(active, label="volume_march"):
        h = dr.minimum(dt, t1 - t)
        s = field.eval(o + d * (t + 0.5 * h))
        c, sigma = tfe(s)
        a = dr.exp(-sigma * h)
        C += T * (1.0 - a) * c
        T *= a
        t += dt
        active &= (t < t1) & (T > min_transmittance)
    return C, 1.0 - T


def render_rays(field, tf, origins, directions, step: float = 0.25, value_range=(0.0, 1.0),
                opacity_scale: float = 1.0, min_transmittance: float = 1e-4):
    """March rays through a grid volume (the Dr.Jit core).

    Parameters
    ----------
    field : Volume or GridField
    tf : TransferFunction or TFEval
    origins, directions : Point3f / Vector3f, or (k, 3) arrays
        Ray origins and directions (normalised here).
    step : float
        Step length in voxels (times the smallest world spacing).
    value_range, opacity_scale
        See :class:`TFEval` (ignored when ``tf`` is already a ``TFEval``).
    min_transmittance : float
        Early termination threshold.

    Returns
    -------
    (Color3f, Float)
        Premultiplied linear RGB and alpha ``= 1 - T`` per ray.
    """
    _check_variant()
    if isinstance(field, Volume):
        field = GridField(field)
    if not isinstance(tf, TFEval):
        tf = TFEval(tf, value_range, opacity_scale)
    if step <= 0:
        raise ValueError(f"step must be > 0, got {step}")
    if not isinstance(origins, mi.Point3f):
        origins = mi.Point3f(*np.asarray(origins, np.float32).reshape(-1, 3).T)
    if not isinstance(directions, mi.Vector3f):
        directions = mi.Vector3f(*np.asarray(directions, np.float32).reshape(-1, 3).T)
    directions = dr.normalize(directions)
    dt = float(step) / max(field.inv_spacing)
    return _march(field, tf, origins, directions, dt, float(min_transmittance))


def camera_rays(camera):
    """Rays through the pixel centers of a :class:`~mi_tetvr.camera.Camera` or a
    Mitsuba sensor.

    Parameters
    ----------
    camera : Camera or mitsuba Sensor
        A camera's rays are :meth:`Camera.rays_drjit
        <mi_tetvr.camera.Camera.rays_drjit>`; a sensor's come from its ``sample_ray`` at
        the film positions of the pixel centers.

    Returns
    -------
    (Point3f, Vector3f, int, int)
        Origins, unit directions, width and height; pixels in row-major order from the
        top-left.
    """
    _check_variant()
    if isinstance(camera, Camera):
        ray = camera.rays_drjit()
        return mi.Point3f(ray.o), mi.Vector3f(ray.d), camera.width, camera.height
    sensor = camera
    w, h = (int(v) for v in sensor.film().size())
    idx = dr.arange(mi.UInt32, w * h)
    uv = mi.Point2f((mi.Float(idx % w) + 0.5) / w, (mi.Float(idx // w) + 0.5) / h)
    ray, _ = sensor.sample_ray(0.0, 0.0, uv, mi.Point2f(0.5, 0.5))
    return mi.Point3f(ray.o), mi.Vector3f(ray.d), w, h


def render_volume(volume, tf, camera, step: float = 0.25, value_range=(0.0, 1.0),
                  opacity_scale: float = 1.0, min_transmittance: float = 1e-4) -> np.ndarray:
    """Render a grid volume from one view.

    Parameters
    ----------
    volume : Volume or GridField
    tf : TransferFunction or TFEval
    camera : Camera or mitsuba Sensor (e.g. ``mi.load_dict(camera.sensor_dict())``)
    step, value_range, opacity_scale, min_transmittance
        See :func:`render_rays`.

    Returns
    -------
    (height, width, 4) float32
        Premultiplied linear RGB and alpha.
    """
    o, d, w, h = camera_rays(camera)
    C, alpha = render_rays(volume, tf, o, d, step=step, value_range=value_range,
                           opacity_scale=opacity_scale, min_transmittance=min_transmittance)
    out = np.stack([np.asarray(C[0]), np.asarray(C[1]), np.asarray(C[2]),
                    np.asarray(alpha)], axis=-1)
    return out.reshape(h, w, 4).astype(np.float32)
