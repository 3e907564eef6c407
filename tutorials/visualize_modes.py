"""Tutorial: one CFD field shown the ways ParaView users look at it: volume
rendering, maximum and mean intensity projections, a slice, isosurfaces and a
clipped volume, from Python dictionaries.

Each view is a Mitsuba scene of the same ``tetmesh`` (NASA's Blunt Fin,
``../shared/data/tets/bluntfin``, its ``Density`` through matplotlib's
``viridis``) and one integrator:

* ``tetvr``: emission-absorption volume rendering (the transfer function's
  opacity per mesh radius scaled by ``opacity_scale``);
* ``tetproj`` with ``mode`` ``max`` / ``mean``: the maximum and the mean of the
  density along each ray (exact: the field is linear in each tet);
* ``tetproj`` with ``mode`` ``slice``: the density on a plane (``origin``,
  ``normal``);
* ``tetproj`` with ``mode`` ``iso``: the first of the isosurfaces ``iso``
  (comma-separated values) each ray meets, lit by a headlight;
* ``tetvr`` with ``clip_origin`` / ``clip_normal``: the volume cut by a
  plane;
* ``tetvr`` with an ``overlay`` (a ``tetproj`` in mode ``iso`` or ``slice``):
  a translucent isosurface (``opacity`` 0.5) or a slice drawn inside the
  volume, as ParaView shows a volume with a contour or a slice.

The script writes ``modes.png`` (the eight side by side) to ``--out`` and
prints each view's time. The command line does the same one view at a time:
``mi-tetvr render bluntfin_tets.vtu --scalar Density --tf viridis --mode max``.

Run it with::

    python tutorials/visualize_modes.py                 # 320x240 per view
    python tutorials/visualize_modes.py --res 160 --out out/modes
"""
from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

import mitsuba as mi

ROOT = Path(__file__).resolve().parents[1]
MESH = ROOT.parent / "shared" / "data" / "tets" / "bluntfin" / "bluntfin_tets.vtu"


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--mesh", default=str(MESH), help="tet mesh with a scalar point array")
    p.add_argument("--scalar", default="Density", help="the scalar array (default Density)")
    p.add_argument("--res", type=int, default=320, help="image width (default 320)")
    p.add_argument("--out", default="out/modes", help="output folder")
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def views(lo, hi, values):
    """The eight integrators: name -> integrator dict."""
    centre = ((lo + hi) / 2).tolist()
    q = np.quantile(values, [0.5, 0.97])
    return {
        "volume (tetvr)": {"type": "tetvr"},
        "maximum (tetproj max)": {"type": "tetproj", "mode": "max"},
        "mean (tetproj mean)": {"type": "tetproj", "mode": "mean"},
        "slice z = centre (tetproj slice)": {"type": "tetproj", "mode": "slice",
                                             "origin": centre, "normal": [0.0, 0.0, 1.0]},
        f"isosurfaces {q[0]:.3g}, {q[1]:.3g} (tetproj iso)": {
            "type": "tetproj", "mode": "iso", "iso": f"{q[0]},{q[1]}"},
        "volume clipped at y = centre (tetvr)": {"type": "tetvr", "clip_origin": centre,
                                                 "clip_normal": [0.0, 1.0, 0.0]},
        f"volume + isosurface {q[0]:.3g}, opacity 0.5 (tetvr overlay)": {
            "type": "tetvr", "overlay": {"type": "tetproj", "mode": "iso", "iso": f"{q[0]}",
                                         "opacity": 0.5}},
        "volume + slice y = centre (tetvr overlay)": {
            "type": "tetvr", "overlay": {"type": "tetproj", "mode": "slice", "origin": centre,
                                         "normal": [0.0, 1.0, 0.0]}},
    }


def main(argv=None):
    a = parse_args(argv)
    mi.set_variant(a.variant)
    import mi_tetvr
    from mi_tetvr.camera import framing_distance, orbit_to_world
    from mi_tetvr.mesh.topology import bounding_radius
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = mi_tetvr.read_tetmesh(a.mesh, color=None, opacity=None)
    values = np.asarray(mesh.point_data[a.scalar], np.float64)
    lo, hi = mesh.bounds
    radius = bounding_radius(mesh.vertices)
    width, height = a.res, a.res * 3 // 4
    fov = 40.0
    distance = framing_distance(radius, fov, (width, height))
    to_world = orbit_to_world(30.0, 25.0, distance, (lo + hi) / 2, (0.0, 0.0, 1.0))
    sensor = {"type": "perspective", "fov": fov,
              "to_world": mi.ScalarTransform4f(np.array(to_world.matrix).reshape(4, 4)),
              "film": {"type": "hdrfilm", "width": width, "height": height,
                       "rfilter": {"type": "box"}},
              "sampler": {"type": "stratified", "sample_count": 1, "jitter": False}}
    shape = {"type": "tetmesh", "filename": str(a.mesh), "scalar_attribute": a.scalar,
             "transfer_function": "viridis", "opacity_scale": 2.0 / radius}
    images, coverage, seconds = {}, {}, {}
    for name, integrator in views(lo, hi, values).items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene = mi.load_dict({"type": "scene", "integrator": integrator,
                                  "sensor": sensor, "volume": shape})
        t0 = time.perf_counter()
        img = np.array(mi.render(scene, spp=1))
        seconds[name] = time.perf_counter() - t0
        images[name] = img[..., :3]
        # tetvr: its alpha AOV (the last channel); tetproj: the film's alpha
        coverage[name] = img[..., -1]
        if not a.quiet:
            print(f"{name:<42} {seconds[name]:.2f} s")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "modes.png"
    plot(path, images)
    if not a.quiet:
        print(f"-> {path}")
    return {"images": images, "coverage": coverage, "seconds": seconds,
            "files": {"modes": str(path)}}


def plot(path, images):
    from matplotlib.figure import Figure
    from mi_tetvr.color import linear_to_srgb
    fig = Figure(figsize=(16, 6.2))
    for k, (name, img) in enumerate(images.items()):
        ax = fig.add_subplot(2, 4, k + 1)
        ax.imshow(linear_to_srgb(np.clip(img, 0, 1)))
        ax.set_title(name, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    main()
