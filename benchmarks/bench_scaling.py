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

Usage::

    python benchmarks/bench_scaling.py --plot out/scaling.png --json out/scaling.json
    python benchmarks/bench_scaling.py --quick
"""
from __future__ import annotations

import sys
import time

import numpy as np

from common import grid_scene, header, make_parser, render_steps, timed, write_json


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
    a = p.parse_args(argv)
    if a.quick:
        a.cells, a.res, a.resolutions, a.image_cells = "8,12", 64, "32,64", 8
    return a


ARGS = parse_args()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402,F401

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
        _, _, steps, _ = trace(dr.ADMode.Primal, scene, integrator.tet_scene(scene), ray,
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


def main(a):
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
