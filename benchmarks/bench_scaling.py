"""Scaling benchmark: how the cost of loading, rendering and differentiating
grows with the number of tets and with the image size.

Scene: the jittered ``cells^3`` grid over [-1, 1]^3 with the blob field
(6 tets per cell: ``--cells 12,...,100`` gives 10k to 6M tets), the default
``tetvr`` settings, one pixel-center ray per pixel. Per mesh size, at
``--res``^2 pixels: the time to load the scene (topology, boundary BVH,
buffers), a primal ``mi.render`` and ``mi.render`` + ``dr.backward`` of an
L2 image loss with gradients on colors, opacities and positions (warm,
median of ``--repeat``), the tets crossed per ray and the tet steps per
second. Per image size (``--resolutions``, at ``--image-cells``): the same
render timings.

Writes a table, and with ``--plot PATH`` a PNG of both sweeps (log-log),
with ``--json PATH`` the numbers.

``--load`` measures big meshes instead, each size in a fresh process (the
``--load-cells`` grids: 100k to 35M tets): the time of ``mi.load_dict`` and
of its ``build_topology``, the peak resident memory during the load (the
process's high-water mark, reset before it) and over the memory held before
it, the memory the loaded scene keeps per tet, the walk's own index buffers
per tet, and the first (compiling) and a warm render at 256^2 and 512^2.
``--baseline REV`` measures the project at git revision REV the same way,
in the same run (up to ``--baseline-max`` tets), and prints the ratios.

Usage::

    python benchmarks/bench_scaling.py --plot out/scaling.png --json out/scaling.json
    python benchmarks/bench_scaling.py --load --baseline 982827a --plot out/load.png
    python benchmarks/bench_scaling.py --quick
    python benchmarks/bench_scaling.py --load --quick
"""
from __future__ import annotations

import argparse
import gc
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common import grid_scene, header, make_parser, render_steps, sensor_dict, timed, write_json


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=3,
                    quick="--cells 8,12 --res 64 --resolutions 32,64 --image-cells 8")
    p.add_argument("--cells", default="12,16,24,32,48,64,80,100",
                   help="grid cells per axis of the mesh sweep (default 12,...,100: "
                        "10k to 6M tets)")
    p.add_argument("--res", type=int, default=256, help="image size of the mesh sweep (256)")
    p.add_argument("--resolutions", default="64,128,256,512,1024",
                   help="image sizes of the image sweep (default 64,...,1024)")
    p.add_argument("--image-cells", type=int, default=32,
                   help="grid of the image sweep (default 32: 197k tets)")
    p.add_argument("--plot", metavar="PATH", help="write the plot (PNG) to PATH")
    p.add_argument("--load", action="store_true",
                   help="the big-mesh sweep: load time, memory and renders per size")
    p.add_argument("--load-cells", default="26,40,64,96,128,180",
                   help="--load: grid cells per axis (default 26,...,180: 105k to 35M tets)")
    p.add_argument("--baseline", metavar="REV",
                   help="--load: also measure the project at this git revision")
    p.add_argument("--baseline-max", type=float, default=13e6,
                   help="--load: largest mesh (tets) the baseline is given (default 13e6)")
    p.add_argument("--child", type=int, help=argparse.SUPPRESS)
    p.add_argument("--child-root", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.quick:
        a.cells, a.res, a.resolutions, a.image_cells = "8,12", 64, "32,64", 8
        a.load_cells = "8,12"
    return a


ARGS = parse_args()
if ARGS.child_root:          # the project at another revision: its package and plugins
    sys.path.insert(0, ARGS.child_root)
    import mi_tetvr  # noqa: E402  (before a variant is set: registers nothing yet)
    mi_tetvr.__path__.append(ARGS.child_root)

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402,F811
mi_tetvr.register()

KEYS = ("volume.vertex_color", "volume.vertex_opacity", "volume.vertex_positions")


def measure(cells, res, repeat):
    """Load, primal and primal + backward timings of one grid at one size."""
    t0 = time.perf_counter()
    scene, v, tets, _, _ = grid_scene(cells, res)
    load = time.perf_counter() - t0
    primal, backward = render_steps(scene, KEYS)
    _, p_med, p_runs, _ = timed(primal, repeat)
    _, b_med, b_runs, _ = timed(backward, repeat)
    # Tets crossed: the walk's own count on the pixel-center rays.
    from mi_tetvr.render.walk import trace
    integrator = scene.integrator()
    sensor = scene.sensors()[0]
    with dr.suspend_grad():
        sampler, _ = integrator.prepare(sensor, 0, 1, [])
        ray, _, _ = integrator.sample_rays(scene, sensor, sampler)
        ray.d = dr.normalize(ray.d)
        _, _, steps, _ = trace(scene, integrator.tet_group(scene), ray,
                               integrator.settings_for(scene), True)
    steps = np.asarray(steps, np.int64)
    return dict(cells=cells, tets=len(tets), vertices=len(v), res=res, load_s=load,
                primal_s=p_med, primal_runs_s=p_runs, backward_s=b_med, backward_runs_s=b_runs,
                backward_over_primal=b_med / p_med,
                tets_per_ray=float(steps[steps > 0].mean()) if (steps > 0).any() else 0.0,
                msteps_per_s=float(steps.sum()) / p_med / 1e6)


def print_row(r):
    print(f"{r['tets']:>10,} {r['res']:>6} {r['load_s']:>8.1f} {r['primal_s']:>10.3f} "
          f"{r['backward_s']:>12.3f} {r['backward_over_primal']:>8.2f}x "
          f"{r['tets_per_ray']:>8.1f} {r['msteps_per_s']:>9.1f}", flush=True)


def plot(path, mesh_rows, image_rows):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, rows, x, label in ((axes[0], mesh_rows, "tets", "tets"),
                               (axes[1], image_rows, "pixels", "pixels")):
        xs = np.array([r["tets"] if x == "tets" else r["res"] ** 2 for r in rows], float)
        for key, name, style in (("primal_s", "render", "o-"),
                                 ("backward_s", "render + backward", "s-"),
                                 ("load_s", "load", "^--")):
            if key == "load_s" and x != "tets":
                continue
            ax.loglog(xs, [r[key] for r in rows], style, label=name)
        # A ray crosses ~ tets^(1/3) tets; the rays are the pixels.
        power = 1.0 / 3.0 if x == "tets" else 1.0
        ax.loglog(xs, (xs / xs[-1]) ** power * rows[-1]["primal_s"], ":", color="gray",
                  label=f"∝ {label}^{'1/3' if x == 'tets' else '1'} (through the last render)")
        ax.set_xlabel(label)
        ax.set_ylabel("seconds")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_title(f"cost vs mesh size ({mesh_rows[0]['res']}x{mesh_rows[0]['res']} pixels)")
    axes[1].set_title(f"cost vs image size ({image_rows[0]['tets']:,} tets)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"# plot written to {path}")


def _rss(field="VmRSS"):
    """Bytes of this process's resident memory (``VmHWM``: its high-water mark)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    return 0


def load_child(cells, repeat):
    """One size of the load sweep, in this (fresh) process: a JSON line."""
    import mi_tetvr.mesh.tetmesh as tetmesh_module
    from mi_tetvr.mesh.generate import blob_field, grid_mesh
    v, t = grid_mesh(cells, jitter=0.15)
    color, opacity = blob_field(v)
    scene_dict = {"type": "scene", "integrator": {"type": "tetvr"},
                  "volume": mi_tetvr.tetmesh_dict(v, t, color, opacity)}
    n_tets, n_vertices = len(t), len(v)
    del v, t, color, opacity
    gc.collect()
    spent = {"topology_s": 0.0}
    build = tetmesh_module.build_topology

    def timed_build(*args, **kwargs):
        t0 = time.perf_counter()
        out = build(*args, **kwargs)
        spent["topology_s"] += time.perf_counter() - t0
        return out

    tetmesh_module.build_topology = timed_build
    before = _rss()
    Path("/proc/self/clear_refs").write_text("5")      # resets the high-water mark
    t0 = time.perf_counter()
    scene = mi.load_dict(scene_dict)
    load = time.perf_counter() - t0
    peak = _rss("VmHWM")
    gc.collect()
    kept = (_rss() - before) / n_tets        # what the scene holds besides its input arrays
    del scene_dict
    shape = [s for s in scene.shapes() if hasattr(s, "tet_buffers")][0]
    buffers = getattr(shape, "tet_buffers", {})
    index_bytes = sum(np.asarray(b).nbytes for b in buffers.values()) if isinstance(
        buffers, dict) else 0
    row = dict(cells=cells, tets=n_tets, vertices=n_vertices, load_s=load,
               rss_before=before, peak_rss=peak, peak_over_before=peak - before,
               index_bytes_per_tet=index_bytes / n_tets, kept_bytes_per_tet=kept, **spent)
    for res in (256, 512):
        sensor = mi.load_dict(sensor_dict(res))
        t0 = time.perf_counter()
        dr.eval(mi.render(scene, sensor=sensor, spp=1))
        dr.sync_thread()
        row[f"first_render_{res}_s"] = time.perf_counter() - t0
        runs = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            dr.eval(mi.render(scene, sensor=sensor, spp=1))
            dr.sync_thread()
            runs.append(time.perf_counter() - t0)
        row[f"render_{res}_s"] = float(np.median(runs))
    print("RESULT " + json.dumps(row), flush=True)


def run_child(a, cells, root=None):
    """:func:`load_child` in a fresh process (``root``: the project at another
    revision); None when it fails (out of memory)."""
    cmd = [sys.executable, __file__, "--child", str(cells), "--variant", a.variant,
           "--repeat", str(a.repeat)] + (["--child-root", str(root)] if root else [])
    proc = subprocess.run(cmd, capture_output=True, text=True)
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    print(f"# {cells}^3 cells{' (baseline)' if root else ''} failed (exit {proc.returncode}): "
          f"{proc.stderr.strip().splitlines()[-1:] if proc.stderr.strip() else ''}", flush=True)
    return None


def baseline_tree(rev):
    """A git worktree of the project at ``rev`` (a temporary folder)."""
    root = Path(__file__).resolve().parents[1]
    path = Path(tempfile.mkdtemp()) / "baseline"
    subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", str(path), rev],
                   check=True, capture_output=True)
    return path


def print_load_row(r, label=""):
    gb = 1024 ** 3
    print(f"{r['tets']:>11,} {label:>9} {r['load_s']:>8.2f} {r['topology_s']:>9.2f} "
          f"{r['peak_rss'] / gb:>8.2f} {r['peak_over_before'] / r['tets']:>10.0f} "
          f"{r['kept_bytes_per_tet']:>9.0f} {r['index_bytes_per_tet']:>7.0f} "
          f"{r['first_render_256_s']:>8.2f} {r['render_256_s']:>8.3f} "
          f"{r['render_512_s']:>8.3f}", flush=True)


def load_sweep(a, info):
    print(f"load sweep: jittered grids with the blob field, each size in a fresh process "
          f"(renders: median of {a.repeat} warm runs)")
    print(f"{'tets':>11} {'':>9} {'load [s]':>8} {'topo [s]':>9} {'peak GB':>8} "
          f"{'peak B/tet':>10} {'kept B/t':>9} {'index':>7} {'1st 256':>8} {'256 [s]':>8} "
          f"{'512 [s]':>8}")
    tree = baseline_tree(a.baseline) if a.baseline else None
    rows, base = [], []
    try:
        for c in (int(x) for x in a.load_cells.split(",")):
            r = run_child(a, c)
            if r is None:
                break
            rows.append(r)
            print_load_row(r, "")
            if tree and r["tets"] <= a.baseline_max:
                b = run_child(a, c, tree)
                if b is not None:
                    base.append(b)
                    print_load_row(b, a.baseline[:9])
                    print(f"{'':>11} {'ratio':>9} {b['load_s'] / r['load_s']:>7.1f}x "
                          f"{b['topology_s'] / r['topology_s']:>8.1f}x "
                          f"{b['peak_over_before'] / r['peak_over_before']:>7.1f}x "
                          f"(load time, topology time, peak memory over the input: "
                          f"baseline / now)", flush=True)
    finally:
        if tree:
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)],
                           cwd=Path(__file__).resolve().parents[1], capture_output=True)
    if a.plot and rows:
        plot_load(a.plot, rows, base, a.baseline)
    write_json(a, info, {"load_sweep": rows, "baseline": base, "baseline_rev": a.baseline})
    return 0


def plot_load(path, rows, base, rev):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for series, style, label in ((rows, "-", "now"), (base, "--", f"at {rev}")):
        if not series:
            continue
        x = np.array([r["tets"] for r in series], float)
        axes[0].loglog(x, [r["load_s"] for r in series], "o" + style, label=f"load ({label})")
        axes[0].loglog(x, [r["topology_s"] for r in series], "s" + style,
                       label=f"build_topology ({label})")
        axes[1].loglog(x, [r["peak_over_before"] / 1024 ** 3 for r in series], "o" + style,
                       label=f"peak over the input ({label})")
    x = np.array([r["tets"] for r in rows], float)
    axes[0].loglog(x, [r["render_512_s"] for r in rows], "^-", label="render 512² (now)")
    axes[0].loglog(x, x / x[-1] * rows[-1]["load_s"], ":", color="gray", label="∝ tets")
    axes[1].loglog(x, x / x[-1] * rows[-1]["peak_over_before"] / 1024 ** 3, ":", color="gray",
                   label="∝ tets")
    axes[0].set_ylabel("seconds")
    axes[1].set_ylabel("GB")
    for ax, title in zip(axes, ("time", "memory")):
        ax.set_xlabel("tets")
        ax.set_title(f"loading a tet mesh: {title}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"# plot written to {path}")


def main(a):
    if a.child:
        load_child(a.child, a.repeat)
        return 0
    if a.load:
        return load_sweep(a, header("big-mesh load benchmark"))
    info = header("scaling benchmark")
    head = (f"{'tets':>10} {'res':>6} {'load [s]':>8} {'render [s]':>10} "
            f"{'+backward [s]':>12} {'ratio':>9} {'tets/ray':>8} {'Msteps/s':>9}")
    print(f"mesh sweep at {a.res}x{a.res} (median of {a.repeat} warm runs; backward: colors, "
          f"opacities and positions)")
    print(head)
    mesh_rows = []
    for c in (int(x) for x in a.cells.split(",")):
        mesh_rows.append(measure(c, a.res, a.repeat))
        print_row(mesh_rows[-1])
    print(f"\nimage sweep on the {a.image_cells}^3 grid")
    print(head)
    image_rows = []
    for res in (int(x) for x in a.resolutions.split(",")):
        image_rows.append(measure(a.image_cells, res, a.repeat))
        print_row(image_rows[-1])
    if a.plot:
        plot(a.plot, mesh_rows, image_rows)
    write_json(a, info, {"mesh_sweep": mesh_rows, "image_sweep": image_rows})
    return 0


if __name__ == "__main__":
    sys.exit(main(ARGS))
