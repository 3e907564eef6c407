"""Tutorial: a CFD scalar field with a transfer function that has a thin peak,
classified before and after interpolation, side by side.

Most tet meshes people look at carry a scalar per vertex (density, pressure)
that a 1D transfer function maps to color and opacity. ``tetmesh`` does it in
one of two ways (its ``classification`` property):

* ``pre``: the vertices are shaded at load and the *colors* are interpolated
  inside each tet. A narrow feature of the transfer function (an
  isosurface-like peak) that falls between two vertex values is missed or
  smeared: a tet shows it only if one of its vertices happens to hit it.
* ``post`` (the default): the *scalar* is interpolated along the ray and
  classified there; the walk cuts each tet's segment where the scalar crosses
  one of the transfer function's texels, so the peak appears wherever the
  field passes through its value, as a thin shell.

The mesh is NASA's Blunt Fin (``../shared/data/tets/bluntfin``, 40,960
vertices, ``Density``); the transfer function is a faint ramp with one narrow
opacity peak at a density chosen from the field. The script renders both
classifications from the same camera and writes ``classify.png`` (pre | post)
to ``--out``, and prints how much of the image differs.

Run it with::

    python tutorials/classify_scalar.py                    # 384x384
    python tutorials/classify_scalar.py --res 128 --out out/classify
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
MESH = ROOT.parent / "shared" / "data" / "tets" / "bluntfin" / "bluntfin_tets.vtu"


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--mesh", default=str(MESH), help="tet mesh with a scalar point array")
    p.add_argument("--scalar", default="Density", help="the scalar array (default Density)")
    p.add_argument("--res", type=int, default=384, help="image size (default 384)")
    p.add_argument("--spp", type=int, default=1, help="samples per pixel (default 1)")
    p.add_argument("--peak", type=float, default=0.2,
                   help="where the opacity peak sits, as a fraction of the scalar range "
                        "(default 0.2)")
    p.add_argument("--width", type=float, default=0.006,
                   help="half width of the peak, as a fraction of the range (default 0.006)")
    p.add_argument("--out", default="out/classify", help="output folder")
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def peaked_tf(path, peak, width):
    """A faint blue ramp and one narrow, opaque orange peak."""
    path.write_text(json.dumps({
        "color": [[0.0, 0.05, 0.15, 0.6], [peak - width, 0.1, 0.3, 0.8],
                  [peak, 1.0, 0.45, 0.05], [peak + width, 0.1, 0.3, 0.8],
                  [1.0, 0.3, 0.5, 0.9]],
        "opacity": [[0.0, 0.0], [peak - width, 0.02], [peak, 4.0], [peak + width, 0.02],
                    [1.0, 0.05]],
        "colorspace": "linear"}))
    return path


def scene_dict(mesh_path, tf_path, scalar, bounds, res, spp, classification):
    lo, hi = bounds
    centre, diag = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    eye = centre + diag * np.array([0.55, -0.9, 0.6])
    return {
        "type": "scene", "integrator": {"type": "tetvr"},
        "sensor": {"type": "perspective", "fov": 35.0,
                   "to_world": mi.ScalarTransform4f().look_at(
                       origin=eye.tolist(), target=centre.tolist(), up=[0, 0, 1]),
                   "sampler": {"type": "independent", "sample_count": spp},
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}}},
        "emitter": {"type": "constant", "radiance": {"type": "rgb", "value": 0.02}},
        "volume": {"type": "tetmesh", "filename": str(mesh_path),
                   "transfer_function": str(tf_path), "scalar_attribute": scalar,
                   # the peak's extinction: about 12 per the mesh's diagonal
                   "opacity_scale": 3.0 / diag, "classification": classification},
    }


def main(argv=None):
    a = parse_args(argv)
    mi.set_variant(a.variant)
    import mi_tetvr
    from mi_tetvr.color import linear_to_srgb as to_srgb
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = mi_tetvr.read_tetmesh(a.mesh)
    values = np.asarray(mesh.point_data[a.scalar]).reshape(-1)
    vmin, vmax = float(values.min()), float(values.max())
    tf_path = peaked_tf(out / "peaked_tf.json", a.peak, a.width)
    images, seconds = {}, {}
    for mode in ("pre", "post"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene = mi.load_dict(scene_dict(a.mesh, tf_path, a.scalar, mesh.bounds, a.res,
                                            a.spp, mode))
        mi.render(scene, spp=a.spp)                                  # compile
        t0 = time.perf_counter()
        images[mode] = np.array(mi.render(scene, spp=a.spp))[..., :3]
        seconds[mode] = time.perf_counter() - t0
    pre, post = (to_srgb(np.clip(images[k], 0, None)) for k in ("pre", "post"))
    diff = np.abs(post - pre).max(-1)
    side = np.concatenate([pre, np.ones((a.res, 4, 3)), post], 1)
    from PIL import Image
    Image.fromarray((np.clip(side, 0, 1) * 255 + 0.5).astype(np.uint8)).save(
        out / "classify.png")
    result = {"differs": float((diff > 0.05).mean()), "mean_abs_diff": float(diff.mean()),
              "seconds": seconds, "scalar_range": (vmin, vmax),
              "files": {"comparison": str(out / "classify.png"), "tf": str(tf_path)},
              "images": images}
    if not a.quiet:
        print(f"{a.mesh}: {len(mesh.tets):,} tets, '{a.scalar}' in [{vmin:.4g}, {vmax:.4g}], "
              f"peak at {vmin + a.peak * (vmax - vmin):.4g}")
        print(f"render {a.res}x{a.res}: pre {seconds['pre']:.2f} s, post {seconds['post']:.2f} s")
        print(f"pixels whose sRGB differs by more than 0.05: {100 * result['differs']:.1f} % "
              f"(mean |difference| {result['mean_abs_diff']:.3f}) -> {out / 'classify.png'}")
    return result


if __name__ == "__main__":
    main()
