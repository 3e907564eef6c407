"""Tutorial: the camera position that shows most of a volume, found by
gradient ascent of the image's opacity entropy (DiffDVR Sec. 5.1).

The camera orbits the mesh (longitude, latitude, a fixed distance, always
looking at its centre). The *opacity entropy* of a render is the entropy of
its alpha channel read as a distribution over the pixels (normalized to
[0, 1]); it is high when the opaque parts spread over the picture instead of
hiding behind each other. Its derivatives with respect to longitude and
latitude come from ``tetvr``'s forward mode (camera gradients through
``mi.traverse``'s ``sensor.to_world``), so every start climbs in a few
renders; the best of the starts is compared with the best of many views
sampled evenly on the sphere.

The default mesh is the project's own scalar mesh
(``scenes/meshes/radial_scalar.vtu``, an ellipsoidal shell pattern, made by
``mi-tetvr make-scenes``) post-classified by ``scenes/tf_radial.json``;
``--mesh`` takes any scalar tet mesh (e.g. ``../shared/data/tets/spx/spx.vtk``)
with ``--scalar`` and ``--tf``. Writes ``view.png`` (the chosen view), ``viewpoint.png``
(entropy over the sphere with the paths) and ``viewpoint.json`` to ``--out``.

Run it with::

    python tutorials/best_viewpoint.py
    python tutorials/best_viewpoint.py --mesh ../shared/data/tets/spx/spx.vtk --out out/vp
"""
from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

import mitsuba as mi

ROOT = Path(__file__).resolve().parents[1]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--mesh", help="scalar tet mesh (default: one made here)")
    p.add_argument("--scalar", help="its scalar point array (default: the only one)")
    p.add_argument("--tf", default=str(ROOT / "scenes" / "tf_radial.json"))
    p.add_argument("--res", type=int, default=96, help="image size (default 96)")
    p.add_argument("--starts", type=int, default=8, help="ascent starts (default 8)")
    p.add_argument("--iterations", type=int, default=20, help="steps per start (default 20)")
    p.add_argument("--samples", type=int, default=256, help="sampled views (default 256)")
    p.add_argument("--out", default="out/viewpoint")
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def main(argv=None):
    a = parse_args(argv)
    mi.set_variant(a.variant)
    import mi_tetvr  # noqa: F401  (registers the plugins)
    from mi_tetvr.mesh.topology import bounding_radius
    from mi_tetvr.apps.viewpoint import (ViewpointSearch, best_viewpoint, default_starts,
                                           orbit_scene, plot_viewpoints)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    from mi_tetvr.mesh.scenes import scalar_mesh
    mesh_path = Path(a.mesh) if a.mesh else scalar_mesh()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = mi_tetvr.read_tetmesh(mesh_path, color=None, opacity=None)
    lo, hi = mesh.bounds
    shape = {"type": "tetmesh", "filename": str(mesh_path.resolve()),
             "transfer_function": str(Path(a.tf).resolve()),
             "opacity_scale": 4.0 / bounding_radius(mesh.vertices)}   # per mesh radius
    if a.scalar:
        shape["scalar_attribute"] = a.scalar
    scene, centre, distance = orbit_scene(shape, (lo, hi), a.res)
    # the search moves the sensor's to_world; its derivative is tetvr's forward mode
    search = ViewpointSearch(scene, centre.tolist(), distance, up=(0.0, 0.0, 1.0))
    t0 = time.perf_counter()
    result = best_viewpoint(search, default_starts(a.starts), a.iterations, a.samples)
    result["seconds"] = time.perf_counter() - t0
    image = search.image(result["longitude"], result["latitude"])
    from mi_tetvr.color import linear_to_srgb
    from PIL import Image
    Image.fromarray((np.clip(linear_to_srgb(np.clip(image[..., :3], 0, 1)), 0, 1) * 255
                     + 0.5).astype(np.uint8)).save(out / "view.png")
    plot_viewpoints(result, out / "viewpoint.png")
    (out / "viewpoint.json").write_text(json.dumps(result, indent=1) + "\n")
    result["files"] = {k: str(out / f) for k, f in (("view", "view.png"),
                                                     ("plot", "viewpoint.png"),
                                                     ("json", "viewpoint.json"))}
    if not a.quiet:
        b = result["best_sampled"]
        print(f"{mesh_path}: best view at longitude {result['longitude']:.1f}, latitude "
              f"{result['latitude']:.1f} deg, opacity entropy {result['entropy']:.4f} = "
              f"{100 * result['ratio_to_best_sampled']:.1f} % of the best of {b['samples']} "
              f"sampled views ({b['entropy']:.4f}); {result['seconds']:.0f} s -> {out}")
    return result


if __name__ == "__main__":
    main()
