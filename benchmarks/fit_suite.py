"""Reconstruction suite: the default ``mi-tetvr fit DATA --time-budget B`` on data
sets the defaults were never tuned on, scored as NeRF, 3DGS and DiffTetVR score.

Per data set it prints the PSNR and SSIM of the sRGB pictures of held-out views
(RGB over the data set's background, see ``mi_tetvr.recon.metrics``), the mesh's
vertices and tets, the optimizer steps and the wall time of the ``fit`` command.
For the volumes it also scores the *no-fitting* baseline: a regular tet grid
over the volume with as many vertices as the fitted mesh, pre-shaded from the
true volume by the same transfer function (what one gets without optimizing).

Data sets (``../shared/data``): ``engine`` (CT, 256x256x128), ``c60`` (electron
density, 128^3), ``headmr`` (MR, 48x62x42), rendered by the grid ray marcher
with the transfer functions ``scenes/tf_{engine,c60,headmr}.json`` into 48
training and 8 test views of 128x128; ``lego`` (NeRF-synthetic, 80 views at
800x800, ``--downscale 4``: 200x200, every 8th view held out, scored over white).
``default`` is the project's own volume (no shared data needed).

    python benchmarks/fit_suite.py                               # 4 sets x 10 min
    python benchmarks/fit_suite.py --sets engine,lego --budget 5 --json out/suite.json
    python benchmarks/fit_suite.py --code DIR --out out/suite_old   # DIR's fit, scored here

``--code DIR`` runs the fit of another checkout (``benchmarks/checkout_cli.py``)
and scores its meshes with this checkout's metrics, so that two versions'
defaults compare on one scale.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from checkout_cli import command as checkout_command  # noqa: E402
from common import header, make_parser, write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"

#: The data sets: a volume (file, value range, transfer function) or a NeRF folder.
SETS = {
    "engine": dict(volume="engine-ct/engine_256x256x128_uint8.raw.gz", value_range=(0, 255),
                   tf="tf_engine.json"),
    "c60": dict(volume="c60/C60Large.cvol", tf="tf_c60.json"),
    "headmr": dict(volume="headmr/HeadMRVolume.mhd", tf="tf_headmr.json"),
    "lego": dict(nerf="nerf-lego", downscale=4, background=[1.0, 1.0, 1.0]),
    "default": dict(volume=None, tf="tf_default.json"),
}
#: The views a volume is rendered into.
VOLUME_VIEWS = dict(views=48, test_views=8, res=128, fov=40.0)
QUICK_VIEWS = dict(views=6, test_views=2, res=24, fov=40.0)


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=None,
                    quick="--sets default --budget 0.3, 6 views of 24x24")
    p.add_argument("--sets", default="engine,c60,headmr,lego",
                   help=f"comma-separated, of {', '.join(SETS)} (default engine,c60,headmr,lego)")
    p.add_argument("--budget", type=float, default=10.0,
                   help="--time-budget of each fit, minutes (default 10)")
    p.add_argument("--out", default="out/suite", help="data sets and fits (default out/suite)")
    p.add_argument("--code", help="checkout whose fit to run (default: this one)")
    p.add_argument("--fit-args", default="", help="extra arguments of every fit command")
    a = p.parse_args(argv)
    if a.quick:
        a.sets, a.budget = "default", 0.3
    a.sets = [s for s in a.sets.split(",") if s]
    bad = [s for s in a.sets if s not in SETS]
    if bad:
        p.error(f"unknown data sets {bad}; known: {', '.join(SETS)}")
    return a


def load_set_volume(spec):
    """(Volume, TransferFunction) of a volume data set."""
    from mi_tetvr import read_transfer_function
    from mi_tetvr.grid import load_volume, make_volume
    from mi_tetvr.mesh.scenes import default_volume
    tf = read_transfer_function(ROOT / "scenes" / spec["tf"])
    if spec["volume"] is None:
        return make_volume(default_volume()), tf
    return load_volume(DATA / spec["volume"], value_range=spec.get("value_range")), tf


def prepare(name, spec, out, quick):
    """The data folder of a set (rendered once and kept) and how to load it."""
    from mi_tetvr.recon.synthetic import make_dataset
    if "nerf" in spec:
        return DATA / spec["nerf"]
    folder = out / f"{name}_data"
    if not (folder / "transforms_train.json").is_file():
        volume, tf = load_set_volume(spec)
        make_dataset(volume, tf, out_dir=folder, progress=False,
                     **(QUICK_VIEWS if quick else VOLUME_VIEWS))
    return folder


def no_fitting(spec, n_vertices, dataset, path):
    """Metrics of a tet grid over the volume with about ``n_vertices``
    vertices, pre-shaded from the true volume; returns (metrics, vertices)."""
    import numpy as np

    from mi_tetvr.mesh import TetMesh, write_tetmesh
    from mi_tetvr.mesh.initial import grid_init
    from mi_tetvr.recon.pipeline import evaluate_mesh
    volume, tf = load_set_volume(spec)
    lo, hi = volume.bounds()
    ext = hi - lo

    def count(r):
        return int(np.prod([max(1, round(r * e / ext.max())) + 1 for e in ext]))

    r = min(range(1, 400), key=lambda q: abs(count(q) - n_vertices))
    vertices, tets = grid_init(np.stack([lo, hi]), r)
    color, opacity = tf.shade(volume.sample(vertices), value_range=(0.0, 1.0))
    write_tetmesh(path, TetMesh(vertices, tets, color, opacity))
    return evaluate_mesh(path, dataset)["mean"], len(vertices)


def fit(data, out, budget, spec, code, extra, variant):
    """Run the fit command; returns (its metrics.json, wall seconds)."""
    cmd = (checkout_command(code) if code else [sys.executable, "-m", "mi_tetvr.cli"]) + [
        "fit", str(Path(data).resolve()), "--out", str(Path(out).resolve()), "--restart",
        "--time-budget", str(budget), "--variant", variant]
    if "downscale" in spec:
        cmd += ["--downscale", str(spec["downscale"])]
    cmd += extra.split()
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    (out / "fit.log").parent.mkdir(parents=True, exist_ok=True)
    (out / "fit.log").write_text(r.stdout + r.stderr)
    if r.returncode != 0:
        raise RuntimeError(f"fit failed ({r.returncode}): {r.stderr[-2000:]}")
    return json.loads((out / "metrics.json").read_text()), wall


def main(argv=None):
    a = parse_args(argv)
    import mitsuba as mi
    mi.set_variant(a.variant)
    import mi_tetvr  # noqa: F401
    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.pipeline import evaluate_mesh
    info = header("reconstruction suite")
    print(f"fit --time-budget {a.budget} min per data set; "
          f"code: {a.code or 'this checkout'}; PSNR/SSIM of sRGB pictures of held-out views\n")
    out = Path(a.out).resolve()
    results = {}
    row = "{:8s} {:>9s} {:>7s} {:>9s} {:>9s} {:>7s} {:>7s} {:>14s}"
    print(row.format("set", "PSNR", "SSIM", "vertices", "tets", "steps", "time", "no fitting"))
    for name in a.sets:
        spec = SETS[name]
        if ("nerf" in spec or spec["volume"]) and not DATA.is_dir():
            print(f"{name:8s} skipped: {DATA} is absent")
            continue
        data = prepare(name, spec, out, a.quick)
        metrics, wall = fit(data, out / f"{name}_fit", a.budget, spec, a.code, a.fit_args,
                            a.variant)
        dataset = load_dataset(data, downscale=spec.get("downscale", 1))
        score = evaluate_mesh(out / f"{name}_fit" / "mesh.vtu", dataset,
                              background=spec.get("background"))["mean"]
        res = {"psnr": score["psnr"], "ssim": score["ssim"], "psnr_linear": score["psnr_linear"],
               "vertices": metrics["vertices"], "tets": metrics["tets"],
               "steps": metrics["step"], "wall_seconds": wall,
               "optimization_seconds": metrics.get("optimization_seconds"),
               "budget_seconds": 60.0 * a.budget, "test_views": len(dataset.test)}
        base = ""
        if "volume" in spec:
            b, nv = no_fitting(spec, metrics["vertices"], dataset, out / f"{name}_nofit.vtu")
            res["no_fitting"] = {"psnr": b["psnr"], "ssim": b["ssim"], "vertices": nv}
            base = f"{b['psnr']:.2f} dB"
        results[name] = res
        print(row.format(name, f"{res['psnr']:.2f} dB", f"{res['ssim']:.3f}",
                         f"{res['vertices']:,}", f"{res['tets']:,}", f"{res['steps']:,}",
                         f"{wall:.0f} s", base), flush=True)
    write_json(a, info, results)
    return results


if __name__ == "__main__":
    main()
