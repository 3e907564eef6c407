"""The live viewer's latency and what it costs a fit.

Latency: the time from a camera change reaching the viewer (viser hands it
over from the browser) to its first image (a quarter of the resolution) and
to the refined one (full resolution), at 256x256 and 512x512, on Blunt Fin
(../shared/data/tets, 187k tets, its Density through a transfer function) and
on a fitted mesh of about 2M tets (the default data set fitted on a grid of
that size; made once under --work). The camera orbits 15 degrees between
changes; each change is timed to the end (the viewer's own clock in
``ClientState.latency``), with the frames replaying their recorded kernels
(``frozen``, :mod:`mi_tetvr.apps.frames`, what the viewer does) and traced
anew each time (``traced``). The baseline, in the same run: one plain
``mi.render`` of the same view at full resolution. Not timed: the image's
trip through the websocket and the browser's drawing (a few ms for a JPEG of
64x64 to 512x512 on this machine's loopback).

Fit: steps per second of ``fit`` with and without the viewer attached, the
viewer's camera moving after every step (as a user turning the view), runs
alternating to share the machine's noise; the slowdown against the viewer's
stated share (10 % of the fit's time).

Usage::

    python benchmarks/bench_viewer.py                 # both meshes, 256 and 512, the fit
    python benchmarks/bench_viewer.py --quick         # a small generated mesh, 64 and 128
"""
from __future__ import annotations

import statistics
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from common import header, make_parser, write_json

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "tets"


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=8, quick="a small generated mesh at 64 and 128, a short fit")
    p.add_argument("--work", default=str(ROOT / "out" / "bench_viewer"),
                   help="folder of the fitted mesh (made once; default out/bench_viewer)")
    p.add_argument("--grid", type=int, default=78,
                   help="grid resolution of the fitted mesh (default 78: about 2M tets)")
    p.add_argument("--fit-minutes", type=float, default=3.0,
                   help="time budget of the fitted mesh's fit (default 3)")
    p.add_argument("--steps", type=int, default=40, help="fit steps per timed run (default 40)")
    p.add_argument("--latency-only", action="store_true",
                   help="Blunt Fin's latency alone: no fitted mesh, no fit")
    a = p.parse_args(argv)
    a.sizes = (64, 128) if a.quick else (256, 512)
    if a.quick:
        a.repeat, a.steps = 3, 8
    return a


ARGS = parse_args()

import mitsuba as mi  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402,F401
from mi_tetvr.apps.viewer import (FitViewer, MeshShown, Viewer, browser_camera,  # noqa: E402
                                  camera_pose)
from mi_tetvr.camera import Camera, look_at, orbit_to_world  # noqa: E402


def cli(*args):
    subprocess.run([sys.executable, "-m", "mi_tetvr.cli", *args, "--quiet"], check=True,
                   cwd=ROOT, stdout=subprocess.DEVNULL)


def fitted_mesh(a):
    """The fitted mesh: the default volume's data set (24 views of 64x64) fitted on a
    grid of ``--grid`` for ``--fit-minutes``; made once under ``--work``."""
    work = Path(a.work)
    mesh = work / "fit" / "mesh.vtu"
    if not mesh.is_file():
        print(f"making the fitted mesh: grid {a.grid}, {a.fit_minutes} min (once) ...",
              flush=True)
        cli("make-dataset", "scenes/volumes/default.npy", "--tf", "scenes/tf_default.json",
            "--views", "24", "--test-views", "4", "--res", "64", "--fov", "30", "--out",
            str(work / "data"))
        cli("fit", str(work / "data"), "--out", str(work / "fit"), "--restart",
            "--grid-resolution", str(a.grid), "--time-budget", str(a.fit_minutes))
    return mesh


def small_mesh(a):
    """--quick: a generated mesh with a scalar."""
    from mi_tetvr.mesh.generate import grid_mesh
    from mi_tetvr.mesh.io import write_tetmesh
    from mi_tetvr.mesh.tetmesh import TetMesh
    v, t = grid_mesh(10, jitter=0.1)
    path = Path(a.work) / "small.vtu"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_tetmesh(path, TetMesh(v, t, point_data={"r": np.linalg.norm(v, axis=1)}),
                  color=None, opacity=None)
    return path


def poses(viewer, k):
    """Viser poses orbiting the mesh: 15 degrees of azimuth apart."""
    s = viewer.shown
    position, target, fov = viewer.start_camera()
    distance = float(np.linalg.norm(position - target))
    out = []
    for i in range(k):
        m = np.array(orbit_to_world(45.0 + 15.0 * i, 30.0, distance, target.tolist(),
                                    s.up.tolist()).matrix, np.float64).reshape(4, 4)
        cam = Camera(64, 64, 32.0, 32.0, 32.0, 32.0, look_at(m[:3, 3], target, s.up))
        p, q, _, _ = camera_pose(cam)
        out.append((p, q, fov, 1.0))
    return out


def latency(shown, size, repeat, freeze=True):
    """Median and range of the first and refined image's latency (seconds) over
    ``repeat`` camera changes, and a plain render's time at full size (one
    ``mi.render`` with a sensor made for the view); ``freeze``: whether the
    viewer's frames replay their recorded kernels (:mod:`mi_tetvr.apps.frames`)."""
    from mi_tetvr.apps.frames import Frames
    shown.freeze, shown._frames = freeze, None
    viewer = Viewer(shown, server=False, resolution=size)
    views = poses(viewer, repeat + 1)
    viewer.add_client("bench", lambda image, final: None, *views[0])
    while viewer.update():                     # compile and warm every level
        pass
    first, refined, plain = [], [], []
    for pose in views[1:]:
        viewer.set_camera("bench", *pose)
        while viewer.update():
            pass
        c = viewer.clients["bench"]
        first.append(c.latency["first"])
        refined.append(c.latency["refined"])
        t0 = time.perf_counter()
        np.array(Frames(shown.scene, freeze=False).render(browser_camera(*pose, size),
                                                          shown.integrator()))
        plain.append(time.perf_counter() - t0)
    return {k: {"median": statistics.median(v), "min": min(v), "max": max(v)}
            for k, v in (("first", first), ("refined", refined), ("plain_render", plain))}


def fit_slowdown(a, data_path, out):
    """Steps per second of a fit with and without the viewer (its camera moving
    after every step), in alternating runs."""
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.pipeline import run
    data = load_dataset(data_path)
    cfg = FitConfig(grid_resolution=8 if a.quick else 32, iterations=a.steps,
                    checkpoint_every=10 ** 6)
    made = {}

    def factory(trainer):
        v = FitViewer(trainer, server=False, resolution=256)
        views = poses(v, 24)
        v.add_client("bench", lambda image, final: None, *views[0])
        after, turn = v.after_step, iter(range(10 ** 9))

        def moving(trainer, *args):
            v.set_camera("bench", *views[next(turn) % len(views)])
            return after(trainer, *args)
        v.after_step = moving
        made["viewer"] = v
        return v
    rates = {"without": [], "with": []}
    shares = []
    for r in range(a.repeat if not a.quick else 1):
        for kind in ("without", "with"):
            t0 = time.perf_counter()
            run(data, out / f"{kind}_{r}", cfg, resume=False, progress=False,
                log=lambda *x: None, viewer=factory if kind == "with" else None)
            rates[kind].append(a.steps / (time.perf_counter() - t0))
            if kind == "with":
                v = made["viewer"]
                shares.append(v.render_seconds / (time.perf_counter() - v.began))
    slow = [w / x - 1.0 for w, x in zip(rates["without"], rates["with"])]
    return {"steps_per_second": rates, "slowdown": slow, "viewer_share": shares}


def main(a):
    info = header("live viewer: camera change -> first and refined image; a fit's slowdown")
    meshes = {}
    if a.quick:
        meshes["small (generated)"] = (small_mesh(a), "r")
    else:
        blunt = DATA / "bluntfin" / "bluntfin_tets.vtu"
        if blunt.is_file():
            meshes["bluntfin (187k tets)"] = (blunt, "Density")
        else:
            print(f"skipped Blunt Fin: {blunt} is absent")
        if not a.latency_only:
            meshes["fitted"] = (fitted_mesh(a), None)
    rows = []
    print(f"{'mesh':<26}{'size':>6}{'frames':>8}{'first (ms)':>22}{'refined (ms)':>24}"
          f"{'plain render (ms)':>20}{'refined/plain':>15}")
    for name, (path, scalar) in meshes.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            shown = MeshShown(path, scalar=scalar)
        tets = shown.mesh.topology.n_tets
        if name == "fitted":
            name = f"fitted ({tets / 1e6:.2f}M tets)"
        for size in a.sizes:
            for freeze in (False, True):
                r = latency(shown, size, a.repeat, freeze)
                f, g, p = r["first"], r["refined"], r["plain_render"]
                ratio = g["median"] / p["median"]
                print(f"{name:<26}{size:>6}{'frozen' if freeze else 'traced':>8}"
                      f"{1e3 * f['median']:>10.0f} [{1e3 * f['min']:.0f}-{1e3 * f['max']:.0f}]"
                      .ljust(62) +
                      f"{1e3 * g['median']:>12.0f} [{1e3 * g['min']:.0f}-{1e3 * g['max']:.0f}]"
                      .ljust(24) + f"{1e3 * p['median']:>12.0f}{ratio:>15.2f}")
                rows.append({"mesh": name, "tets": tets, "size": size, "frozen": freeze, **r,
                             "refined_over_plain": ratio})
    if a.latency_only:
        write_json(a, info, {"latency": rows})
        return
    data = Path(a.work) / ("data" if not a.quick else "quick_data")
    if a.quick and not data.is_dir():
        cli("make-dataset", "scenes/volumes/default.npy", "--tf", "scenes/tf_default.json",
            "--views", "6", "--test-views", "2", "--res", "16", "--fov", "30", "--out",
            str(data))
    fit = fit_slowdown(a, data, Path(a.work) / "slowdown")
    w, x = fit["steps_per_second"]["without"], fit["steps_per_second"]["with"]
    slow = fit["slowdown"]
    print(f"\nfit ({a.steps} steps per run, {len(w)} run(s) each, alternating): "
          f"{statistics.median(w):.2f} steps/s without the viewer, {statistics.median(x):.2f} "
          f"with it (camera moving every step)")
    print(f"slowdown {100 * statistics.median(slow):.1f} % (runs: "
          f"{', '.join(f'{100 * s:.1f}' for s in slow)} %); the viewer rendered in "
          f"{100 * statistics.median(fit['viewer_share']):.1f} % of the fit's time (its share: "
          f"10 %)")
    write_json(a, info, {"latency": rows, "fit": fit})


if __name__ == "__main__":
    main(ARGS)
