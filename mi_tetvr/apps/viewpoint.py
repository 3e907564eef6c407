"""Best viewpoint by gradient ascent of the opacity entropy (DiffDVR Sec. 5.1).

The camera sits on a sphere around the mesh (:func:`~mi_tetvr.camera.orbit_to_world`:
longitude, latitude, a fixed distance) and looks at its
centre. The objective is the *opacity entropy* of the image: the Shannon
entropy of the alpha channel read as a distribution over the pixels,
normalized by ``log N`` so that it lies in [0, 1] (1: the opacity is spread
evenly over the whole image). (DiffDVR's Eq. 11 as printed lacks the minus
sign.) Several starts (``starts``, default 8: longitudes 45, 135, 225, 315
degrees at latitudes +-45) climb the entropy for ``iterations`` steps with
forward-mode derivatives (two parameters: two forward passes per step); the
best end point is the answer. For comparison, the entropy of ``samples``
views on a Fibonacci sphere.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_tetvr.camera import fibonacci_sphere
from mi_tetvr.camera import orbit_to_world
from mi_tetvr.extras import needs


def _opaque(x):
    """A camera parameter as an evaluated (not literal) value, so that the
    render kernels compiled for one view serve every other."""
    return dr.opaque(mi.Float, float(x))


def opacity_entropy(alpha):
    """Normalized Shannon entropy of a non-negative image (a Dr.Jit array or
    tensor; differentiable): ``-sum p log p / log N`` with ``p = a / sum a``."""
    a = dr.ravel(alpha) if hasattr(alpha, "shape") else alpha
    a = dr.maximum(mi.Float(a), 0.0)
    n = dr.width(a)
    p = a / dr.maximum(dr.sum(a), 1e-30)
    plogp = dr.select(p > 0, p * dr.log(dr.select(p > 0, p, 1.0)), 0.0)
    return -dr.sum(plogp) / math.log(n)


class ViewpointSearch:
    """The entropy of ``scene``'s first sensor placed by longitude and
    latitude around ``target`` at ``distance`` (the sensor's ``to_world`` is
    overwritten), its derivative and the gradient ascent.

    Parameters
    ----------
    scene : mi.Scene
        A ``tetvr`` scene whose integrator writes the ``alpha`` AOV.
    key : str
        The sensor's ``to_world`` in ``mi.traverse(scene)``.
    """

    def __init__(self, scene, target, distance, key="sensor.to_world", up=(0.0, 0.0, 1.0),
                 spp=1):
        self.scene, self.params, self.key = scene, mi.traverse(scene), key
        self.target, self.distance, self.up, self.spp = tuple(target), float(distance), up, spp

    def _entropy(self, lon, lat):
        self.params[self.key] = orbit_to_world(lon, lat, self.distance, self.target, self.up)
        self.params.update()
        image = mi.render(self.scene, self.params, spp=self.spp)
        return opacity_entropy(image[..., 3])

    def entropy(self, lon, lat):
        """The opacity entropy of the view at ``lon, lat`` (degrees)."""
        with dr.suspend_grad():
            return float(self._entropy(_opaque(lon), _opaque(lat)).array[0])

    def image(self, lon, lat):
        """The view at ``lon, lat`` as an (h, w, 4) numpy array."""
        self.params[self.key] = orbit_to_world(_opaque(lon), _opaque(lat), self.distance,
                                               self.target, self.up)
        self.params.update()
        return np.array(mi.render(self.scene, spp=self.spp))

    def gradient(self, lon, lat):
        """``(entropy, d/dlon, d/dlat)`` per degree, by forward mode."""
        out = []
        for which in (0, 1):
            x = [_opaque(lon), _opaque(lat)]
            dr.enable_grad(x[which])
            dr.set_grad(x[which], 1.0)
            h = self._entropy(*x)
            out.append(float(np.array(dr.forward_to(h)).ravel()[0]))
            value = float(dr.detach(h).array[0])
        return value, out[0], out[1]

    def climb(self, lon, lat, iterations=20, step=10.0, final_step=1.0):
        """Gradient ascent from ``lon, lat``: each step moves along the
        gradient's direction on the sphere by a length that falls
        geometrically from ``step`` to ``final_step`` degrees (the entropy
        of a discrete image is bumpy at small scales, so the steps are not
        scaled by the gradient's size). Returns the path ``[(lon, lat,
        entropy), ...]``; the last entry is the best point visited."""
        path = []
        rate = (final_step / step) ** (1.0 / max(iterations - 1, 1))
        for i in range(iterations):
            h, glon, glat = self.gradient(lon, lat)
            path.append((lon, lat, h))
            # the sphere's metric: a degree of longitude is cos(lat) long
            c = max(math.cos(math.radians(lat)), 1e-3)
            norm = math.hypot(glon / c, glat) or 1.0
            length = step * rate ** i
            lon = (lon + length * glon / (c * c) / norm) % 360.0
            lat = float(np.clip(lat + length * glat / norm, -85.0, 85.0))
        path.append(max(path, key=lambda q: q[2]))
        return path


def orbit_scene(shape, bounds, res=128, fov=40.0):
    """A scene to search views of: ``shape`` (a ``tetmesh`` dict), ``tetvr``,
    and a perspective sensor of ``res`` (N for N x N, or (width, height)) pixels
    through pixel centres with ``fov`` (degrees, horizontal). Returns ``(scene, centre, distance)``:
    the box ``bounds``' centre and the distance at which its bounding sphere fills the
    view (what :class:`ViewpointSearch` takes)."""
    from mi_tetvr.camera import framing_distance
    from mi_tetvr.mesh.topology import bounding_radius
    width, height = (int(res), int(res)) if np.isscalar(res) else (int(res[0]), int(res[1]))
    lo, hi = np.asarray(bounds, np.float64)
    centre = (lo + hi) / 2
    distance = framing_distance(bounding_radius(bounds), fov)
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "tetvr"},
        "sensor": {"type": "perspective", "fov": fov,
                   "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
                   "film": {"type": "hdrfilm", "width": width, "height": height,
                            "rfilter": {"type": "box"}}},
        "volume": shape})
    return scene, centre, distance


def default_starts(n=8):
    """DiffDVR's starts: longitudes 45, 135, 225, 315 at latitudes +-45
    (``n`` = 8), or the first ``n`` of them."""
    starts = [(lon, lat) for lat in (45.0, -45.0) for lon in (45.0, 135.0, 225.0, 315.0)]
    return starts[:n]


def best_viewpoint(search, starts, iterations=20, samples=256, progress=None):
    """Climb from every start and sample the Fibonacci sphere; returns a
    dict with the chosen view (``longitude``, ``latitude``, ``entropy``),
    the paths, the best sampled view and the samples."""
    lon_s, lat_s = fibonacci_sphere(samples)
    sampled = []
    for a, b in zip(lon_s, lat_s):
        sampled.append(search.entropy(a, b))
        if progress:
            progress()
    paths = []
    for a, b in starts:
        paths.append(search.climb(a, b, iterations))
        if progress:
            progress()
    end = max((p[-1] for p in paths), key=lambda e: e[2])
    k = int(np.argmax(sampled))
    return {"longitude": end[0], "latitude": end[1], "entropy": end[2],
            "best_sampled": {"longitude": float(lon_s[k]), "latitude": float(lat_s[k]),
                             "entropy": float(sampled[k]), "samples": samples},
            "ratio_to_best_sampled": end[2] / sampled[k] if sampled[k] > 0 else float("inf"),
            "paths": [[list(map(float, q)) for q in p] for p in paths],
            "samples": {"longitude": lon_s.tolist(), "latitude": lat_s.tolist(),
                        "entropy": sampled}}


def plot_viewpoints(result, path):
    """The sampled entropies over the sphere (longitude, latitude) with the
    ascent paths and the chosen view."""
    with needs("vis", "the viewpoint plot"):
        from matplotlib.figure import Figure
    s = result["samples"]
    fig = Figure(figsize=(8, 4.2))
    ax = fig.subplots()
    sc = ax.scatter(s["longitude"], s["latitude"], c=s["entropy"], cmap="viridis", s=18)
    fig.colorbar(sc, ax=ax, label="opacity entropy")
    for p in result["paths"]:
        p = np.array(p)
        ax.plot(p[:-1, 0], p[:-1, 1], ".-", color="black", lw=0.8, ms=3, alpha=0.7)
        ax.plot(p[0, 0], p[0, 1], "o", color="black", ms=5, mfc="none")
    ax.plot(result["longitude"], result["latitude"], "*", color="red", ms=14,
            label=f"chosen ({result['entropy']:.4f})")
    b = result["best_sampled"]
    ax.plot(b["longitude"], b["latitude"], "x", color="orange", ms=10,
            label=f"best of {b['samples']} ({b['entropy']:.4f})")
    ax.set_xlim(0, 360)
    ax.set_ylim(-90, 90)
    ax.set_xlabel("longitude [deg]")
    ax.set_ylabel("latitude [deg]")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
