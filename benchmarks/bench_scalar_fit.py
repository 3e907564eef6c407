"""Density under a transfer function: ``mi-tetvr fit DATA --init MESH
--optimize scalar --tf TF`` reconstructs the per-vertex scalar of a real tet
mesh from color images, the transfer function known (DiffDVR Sec. 5.4).

The data set is Blunt Fin's ``Density`` (187k tets) post-classified by
``scenes/tf_bluntfin.json`` (peaks: not monotonic), rendered by ``mi-tetvr
make-dataset`` into ``--views`` training views and 8 held-out ones. The mesh's
geometry is given; its scalar is not used except for the scoring. Two starts:

* ``constant``: every vertex at mid-range, then the scalar fit (where
  non-convexity bites: DiffDVR's Fig. 12);
* ``colors``: DiffDVR's remedy: per-vertex colors and opacities fitted first,
  scalars matched to them (Eq. 13), then the scalar fit.

Printed per start: held-out PSNR/SSIM of the sRGB pictures at the start and
after the fit, the scalar error against the true field (RMS over the range,
and over the vertices whose true value the transfer function shows, opacity
above a tenth of its largest), and the time.

Usage::

    python benchmarks/bench_scalar_fit.py                   # 16 views of 256x256
    python benchmarks/bench_scalar_fit.py --quick           # 8^3 grid, 24x24
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
    p.add_argument("--views", type=int, default=16, help="training views (default 16)")
    p.add_argument("--steps", type=int, default=400,
                   help="steps of each fit (colors, scalar; default 400)")
    p.add_argument("--starts", default="constant,colors", help="comma-separated (default both)")
    p.add_argument("--out", help="folder for the data set and fits (default: a temp folder)")
    a = p.parse_args(argv)
    if a.quick:
        a.res, a.steps, a.views = 24, 20, 4
    return a


def main(a):
    import mitsuba as mi
    mi.set_variant(a.variant)
    from bench_tf_fit import quick_mesh

    from mi_tetvr.mesh import TetMesh
    from mi_tetvr.mesh.io import read_tetmesh, write_tetmesh
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.pipeline import run, scalar_from_colors
    from mi_tetvr.recon.synthetic import make_mesh_dataset
    from mi_tetvr.recon.trainer import Trainer
    from mi_tetvr.transfer import read_transfer_function
    info = header("scalar reconstruction benchmark")
    out = Path(a.out or tempfile.mkdtemp())
    if a.quick or not MESH.exists():
        mesh_path, scalar = quick_mesh(out)
        name = "8^3 grid"
    else:
        mesh_path, scalar, name = MESH, "Density", "Blunt Fin"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        made = make_mesh_dataset(mesh_path, TF, out / "data", views=a.views, test_views=8,
                                 res=a.res, scalar=scalar, opacity_scale=4.0, progress=False)
        data = load_dataset(out / "data")
        mesh = read_tetmesh(mesh_path, color=None, opacity=None)
    truth = np.asarray(mesh.point_data[scalar], np.float64)
    lo, hi = made["value_range"]
    tf = read_transfer_function(TF)
    shown = tf((truth - lo) / (hi - lo))[1] > 0.1 * tf.opacities.max()
    print(f"{name} ({len(mesh.tets):,} tets), '{scalar}' under {TF.name}, {a.views} training "
          f"and 8 held-out views of {a.res}x{a.res}, {a.steps} steps per fit; "
          f"{int(shown.sum()):,} of {len(truth):,} vertices where the function shows")

    def errors(s):
        e = (np.asarray(s) - truth) / (hi - lo)
        return float(np.sqrt(np.mean(e ** 2))), float(np.sqrt(np.mean(e[shown] ** 2)))

    rows = []
    for start in a.starts.split(","):
        cfg = FitConfig(init=str(mesh_path), optimize="scalar", transfer_function=str(TF),
                        opacity_scale=4.0, value_range=[lo, hi], iterations=a.steps,
                        scalar_init="colors" if start == "colors" else "mesh")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t0 = time.perf_counter()
            if start == "colors":
                s0 = scalar_from_colors(cfg, data, mesh.vertices, mesh.tets, progress=False,
                                        log=lambda *x: None)
            else:
                s0 = np.full(len(truth), 0.5 * (lo + hi))
            t_start = time.perf_counter() - t0
            first = Trainer(data, mesh.vertices, mesh.tets, cfg, {"scalar": s0})
            before = first.evaluate(data.test)["mean"]
            del first
            # the scalar fit starts from a mesh holding the start's scalars
            start_mesh = out / f"start_{start}.vtu"
            write_tetmesh(start_mesh, TetMesh(mesh.vertices, mesh.tets,
                                              point_data={"scalar": s0}),
                          color=None, opacity=None)
            t0 = time.perf_counter()
            m = run(data, out / f"fit_{start}", cfg.updated(init=str(start_mesh), scalar="scalar",
                                                             scalar_init="mesh"),
                    resume=False, progress=False, log=lambda *x: None)
            seconds = t_start + time.perf_counter() - t0
            fitted = read_tetmesh(out / f"fit_{start}" / "scalar.vtu", color=None, opacity=None)
        e0, e0_shown = errors(s0)
        e1, e1_shown = errors(fitted.point_data["scalar"])
        row = dict(start=start, psnr_start=before["psnr"], psnr=m["mean"]["psnr"],
                   ssim=m["mean"]["ssim"], scalar_rms_start=e0, scalar_rms=e1,
                   scalar_rms_shown_start=e0_shown, scalar_rms_shown=e1_shown,
                   seconds=seconds)
        rows.append(row)
        print(f"  {start:<9} start {before['psnr']:6.2f} dB -> fitted {row['psnr']:6.2f} dB "
              f"(SSIM {row['ssim']:.4f}) held out; scalar RMS error / range {e0:.4f} -> "
              f"{e1:.4f} (where shown {e0_shown:.4f} -> {e1_shown:.4f}); {seconds:.0f} s")
    write_json(a, info, {"mesh": name, "res": a.res, "views": a.views, "steps": a.steps,
                         "runs": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main(parse_args()))
