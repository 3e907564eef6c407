"""Transfer-function reconstruction: ``mi-tetvr fit DATA --init MESH
--optimize tf`` recovers the R = 64 texels of a transfer function from
images of a real scalar tet mesh, against the true transfer function.

The data set is Blunt Fin's ``Density`` (187k tets, ``../shared/data``)
post-classified by ``scenes/tf_bluntfin.json`` (opacity scale 4 per mesh
radius), rendered by ``mi-tetvr make-dataset`` into 8 training views (DiffDVR
used 8) and 8 held-out views at random positions. Per start (flat: grey,
one optical depth per 20 cells; random: uniform texels, seeded) it prints the
held-out PSNR and SSIM of the sRGB pictures for the start and the fitted
transfer function, the fit's time, and the texels' RMS error against the
true ones (color, and opacity in optical depth per cell); ``--plot`` draws
the true and fitted functions.

Usage::

    python benchmarks/bench_tf_fit.py                      # 256x256, 300 steps
    python benchmarks/bench_tf_fit.py --smoothing 0.4,0.04,0.01,0 --plot out/tf_fit.png
    python benchmarks/bench_tf_fit.py --quick              # 8^3 grid, 24x24
"""
from __future__ import annotations

import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from common import header, make_parser, write_json

ROOT = Path(__file__).resolve().parents[1]
MESH = ROOT.parent / "shared" / "data" / "tets" / "bluntfin" / "bluntfin_tets.vtu"
TF = ROOT / "scenes" / "tf_bluntfin.json"


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=None, quick="an 8^3 grid, 24x24, 20 steps")
    p.add_argument("--res", type=int, default=256, help="image size (default 256)")
    p.add_argument("--views", type=int, default=8, help="training views (default 8)")
    p.add_argument("--steps", type=int, default=300, help="optimizer steps (default 300)")
    p.add_argument("--texels", type=int, default=64, help="R (default 64)")
    p.add_argument("--smoothing", default="",
                   help="comma-separated prior weights to compare (default: the fit's)")
    p.add_argument("--starts", default="flat,random", help="comma-separated (default both)")
    p.add_argument("--plot", help="PNG of the true and fitted transfer functions")
    p.add_argument("--out", help="folder for the data set and fits (default: a temp folder)")
    a = p.parse_args(argv)
    if a.quick:
        a.res, a.steps, a.views = 24, 20, 4
        a.starts = "flat"
    return a


def quick_mesh(folder):
    """An 8^3 jittered grid with a smooth scalar, written as a .vtu."""
    import mi_tetvr
    from mi_tetvr.mesh.generate import grid_mesh
    V, T = grid_mesh(8, jitter=0.1)
    s = np.sin(2 * V[:, 0]) * np.cos(2 * V[:, 1]) + V[:, 2]
    path = Path(folder) / "grid.vtu"
    mi_tetvr.write_tetmesh(path, mi_tetvr.TetMesh(V, T, point_data={"scalar": s}),
                           color=None, opacity=None)
    return path, "scalar"


def texel_errors(fitted, truth, h, share):
    """RMS texel differences: color (linear RGB) over the texels the images
    show (true opacity above a tenth of its largest and at least 0.5 % of the
    vertices' scalars in the texel: elsewhere the color shows in no image)
    and opacity in optical depth per cell over all."""
    (c0, o0), (c1, o1) = fitted, truth
    seen = (o1 > 0.1 * o1.max()) & (share >= 0.005)
    return (float(np.sqrt(np.mean((c0[seen] - c1[seen]) ** 2))),
            float(np.sqrt(np.mean(((o0 - o1) * h) ** 2))))


def main(a):
    import mitsuba as mi
    mi.set_variant(a.variant)
    from mi_tetvr.mesh.io import read_tetmesh
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.pipeline import run
    from mi_tetvr.recon.synthetic import make_mesh_dataset
    from mi_tetvr.recon.trainer import Trainer
    from mi_tetvr.transfer import TransferFunction, read_transfer_function
    info = header("transfer-function reconstruction benchmark")
    out = Path(a.out or tempfile.mkdtemp())
    if a.quick or not MESH.exists():
        mesh_path, scalar = quick_mesh(out)
        name = "8^3 grid"
    else:
        mesh_path, scalar, name = MESH, "Density", "Blunt Fin"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data_info = make_mesh_dataset(mesh_path, TF, out / "data", views=a.views, test_views=8,
                                      res=a.res, scalar=scalar, opacity_scale=4.0,
                                      progress=False)
        data = load_dataset(out / "data")
        mesh = read_tetmesh(mesh_path, color=None, opacity=None)
    given = read_transfer_function(TF)
    # the true function in the fit's units: extinction per world unit
    truth_tf = TransferFunction(given.color_positions, given.colors, given.opacity_positions,
                                given.opacities * data_info["extinction_scale"])
    truth = truth_tf.texels(a.texels)
    print(f"{name} ({len(mesh.tets):,} tets), '{scalar}', {a.views} training and 8 held-out "
          f"views of {a.res}x{a.res}, R = {a.texels}, {a.steps} steps")
    values = np.asarray(mesh.point_data[scalar], np.float64)
    lo, hi = values.min(), values.max()
    share = np.histogram(values, a.texels, (lo, hi))[0] / len(values)
    rows, tfs = [], {"true": truth_tf}
    weights = [float(x) for x in a.smoothing.split(",") if x] or [FitConfig().field.tf_smoothing]
    for start, lam in ((s, w) for w in weights for s in a.starts.split(",")):
        cfg = FitConfig(init=str(mesh_path), optimize="tf", scalar=scalar,
                        tf_resolution=a.texels, tf_init=start, iterations=a.steps,
                        tf_smoothing=lam)
        label = f"{start} start, lambda {lam:g}"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            first = Trainer(data, mesh.vertices, mesh.tets, cfg, {"scalar": values})
            before = first.evaluate(data.test)["mean"]
            h = first.h
            del first
            t0 = time.perf_counter()
            m = run(data, out / "fit", cfg, resume=False, progress=False, log=lambda *x: None)
            seconds = time.perf_counter() - t0
        fitted_tf = read_transfer_function(out / "fit" / "transfer_function.json")
        fitted = fitted_tf.texels(a.texels)
        e_color, e_depth = texel_errors(fitted, truth, h, share)
        tfs[label] = fitted_tf
        row = dict(start=start, smoothing=lam, psnr=m["mean"]["psnr"], ssim=m["mean"]["ssim"],
                   psnr_start=before["psnr"], seconds=seconds, steps=m["step"],
                   texel_rms_color=e_color, texel_rms_depth_per_cell=e_depth)
        rows.append(row)
        print(f"  {label:<24} {before['psnr']:6.2f} dB -> fitted {row['psnr']:6.2f} dB "
              f"(SSIM {row['ssim']:.4f}) held out, {seconds:5.0f} s; texel RMS error: color "
              f"{e_color:.4f} (texels shown), opacity {e_depth:.4f} optical depth per cell")
    if a.plot:
        from mi_tetvr.recon.plots import plot_transfer_functions
        lo, hi = data_info["value_range"]
        plot_transfer_functions(a.plot, tfs, (lo, hi))
        print(f"plot -> {a.plot}")
    write_json(a, info, {"mesh": name, "tets": len(mesh.tets), "res": a.res, "views": a.views,
                         "texels": a.texels, "steps": a.steps, "data": data_info, "runs": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main(parse_args()))
