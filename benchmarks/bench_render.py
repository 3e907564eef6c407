"""Render benchmark: the ``tetvr`` tet walk against a plain walk.

Scene: a jittered regular tet grid (``cells^3`` cells, 6 Kuhn tets each; 64^3
= 1.57M tets) over [-1, 1]^3 carrying :func:`mi_tetvr.mesh.generate.blob_field`,
seen by a perspective camera, one ray per pixel through the pixel center,
no early ray termination (``min_transmittance = 0``), so every ray crosses the
whole mesh.

Methods, each timed warm (one run to compile, then the median of
``--repeat`` runs), all on the same pixel-center rays:

1. **tetvr**: ``mi.render`` with the ``tetvr`` integrator (stratified sampler
   without jitter: its rays are the pixel-center rays), and
   :func:`mi_tetvr.render.walk.trace` called directly (which gives the number
   of tets crossed).
2. **plain walk** (:mod:`plain_walk`): Weiler-style: every step reads all
   four vertices of the tet, intersects the four face planes, interpolates
   at the exit point. Once with tetvr's own segment integral at the same
   ``n_sub`` (the walks alone compared), once with the integral tetvr used
   before (DiffTetVR Alg. 1, ``--baseline-n-sub`` = 8 plain sub-intervals):
   what a first implementation of DiffTetVR's renderer does.

Accuracy: every image is compared with tetvr's at ``n_sub`` = 32 on the same
rays (the extrapolated integral's error falls as 1/n^4: converged to float
precision), so a faster integral is seen not to be a coarser one.

Usage::

    python benchmarks/bench_render.py            # 64^3 cells, 384x384
    python benchmarks/bench_render.py --quick    # 16^3 cells, 96x96 smoke run
    python benchmarks/bench_render.py --shuffle  # vertices and tets in random order
    python benchmarks/bench_render.py --code ../before --rounds 3   # against another checkout

With ``--code DIR`` the script runs in turns with this checkout's package and
with ``DIR``'s (each run in a process of its own, ``--rounds`` times) and
prints, per round and over the rounds, each checkout's ``trace()`` and the
plain walk beside it: plain / ``tetvr`` for both, and this / ``--code``.
"""
from __future__ import annotations

import sys

import numpy as np

from common import (add_code_options, alternate, check_code, grid_scene, header, make_parser,
                    pixel_rays, spread, timed, write_json)


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=3, quick="--cells 16 --res 96")
    p.add_argument("--cells", type=int, default=64, help="grid cells per axis (default 64)")
    p.add_argument("--res", type=int, default=384, help="image width = height (default 384)")
    p.add_argument("--jitter", type=float, default=0.15,
                   help="vertex jitter in cell sizes (default 0.15; > ~0.2 inverts Kuhn tets)")
    p.add_argument("--scale", type=float, default=1.0, help="blob_field opacity scale (default 1)")
    p.add_argument("--n-sub", type=int, default=None,
                   help="tetvr's n_sub (default: the integrator's default)")
    p.add_argument("--shuffle", action="store_true",
                   help="list the grid's vertices and tets in random order (as a mesh file "
                        "may); adds tetvr on the tets in that order (without the Morton order "
                        "the tetmesh shape gives them)")
    p.add_argument("--baseline-n-sub", type=int, default=8,
                   help="sub-intervals of the plain walk's Alg. 1 integral (default 8, the "
                        "n_sub tetvr used with it)")
    add_code_options(p)
    a = p.parse_args(argv)
    check_code(p, a)
    if a.quick:
        a.cells, a.res = 16, 96
    return a


ARGS = parse_args()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant(ARGS.variant)

import mi_tetvr  # noqa: E402,F401
from mi_tetvr.mesh.topology import build_topology  # noqa: E402
from mi_tetvr.render.buffers import MeshBuffers, TetGroup, shape_index_arrays  # noqa: E402
from mi_tetvr.render.cursor import WalkSettings  # noqa: E402
from mi_tetvr.render.walk import trace  # noqa: E402
from plain_walk import PlainBuffers, plain_trace  # noqa: E402

#: n_sub of the reference image (error ~1/n^4: below float precision).
REFERENCE_N_SUB = 32


def total(x):
    return int(np.asarray(x, dtype=np.uint64).sum())


def rgb_np(C):
    return np.stack([np.asarray(C.x), np.asarray(C.y), np.asarray(C.z)], -1)


def compare(a):
    """This checkout against ``--code``, in turns (see the module docstring)."""
    argv = ["--cells", str(a.cells), "--res", str(a.res), "--jitter", str(a.jitter),
            "--scale", str(a.scale), "--repeat", str(a.repeat), "--variant", a.variant,
            "--baseline-n-sub", str(a.baseline_n_sub)]
    argv += ["--n-sub", str(a.n_sub)] if a.n_sub is not None else []
    info = header("render benchmark, this checkout against --code " + str(a.code))
    rounds = alternate(__file__, argv, a.code, a.rounds)

    def medians(res):
        return {m["method"]: m["median_s"] for m in res["methods"]}
    trace, plain = "tetvr trace()", [m["method"] for m in rounds[0]["this"]["methods"]][2]
    rows = []
    print(f"{'round':<7}{'trace() this':>14}{'trace() --code':>16}{'plain walk':>12}"
          f"{'plain/this':>12}{'plain/--code':>14}{'this/--code':>13}")
    for r, row in enumerate(rounds):
        t, o = medians(row["this"]), medians(row["other"])
        # (the plain walk timed beside each: the mean of its two runs)
        pl = 0.5 * (t[plain] + o[plain])
        rows.append(dict(this_s=t[trace], other_s=o[trace], plain_s=pl,
                         plain_over_this=t[plain] / t[trace], plain_over_other=o[plain] / o[trace],
                         this_over_other=t[trace] / o[trace]))
        x = rows[-1]
        print(f"{r + 1:<7}{x['this_s']:>13.3f}s{x['other_s']:>15.3f}s{pl:>11.3f}s"
              f"{x['plain_over_this']:>11.2f}x{x['plain_over_other']:>13.2f}x"
              f"{x['this_over_other']:>12.2f}x")
    print()
    for k, what in (("plain_over_this", "plain walk / tetvr, this checkout"),
                    ("plain_over_other", "plain walk / tetvr, --code"),
                    ("this_over_other", "tetvr this / --code (below 1: faster)")):
        print(f"{what}: {spread([x[k] for x in rows])}x (median [range] of {len(rows)} rounds)")
    write_json(a, info, {"code": a.code, "rounds": rows, "runs": rounds})
    return 0


def main(a):
    if a.code:
        return compare(a)
    res, n_rays = a.res, a.res * a.res
    info = header("render benchmark")
    extra = {} if a.n_sub is None else {"n_sub": a.n_sub}
    scene, v, tets, color, opacity = grid_scene(a.cells, res, a.jitter, a.scale, a.shuffle,
                                                min_transmittance=0.0, alpha=False, **extra)
    topo = build_topology(v, tets)          # the shape keeps only the walk's buffers
    integrator = scene.integrator()
    n_sub = integrator.n_sub
    print(f"mesh: {a.cells}^3 cells, jitter {a.jitter}: {len(v):,} vertices, "
          f"{topo.n_tets:,} tets; image {res}x{res} = {n_rays:,} rays, tetvr n_sub = {n_sub}, "
          f"no early termination")
    rays = pixel_rays(scene.sensors()[0], res)
    diag = float(dr.norm(scene.bbox().extents()))
    settings = WalkSettings(0.0, integrator.settings.max_steps,
                            integrator.retrace_epsilon * diag)
    ts = integrator.tet_group(scene)
    dr.eval(ts.buf, ts.params)
    plain = PlainBuffers(ts)

    def run_render():
        img = mi.render(scene, spp=1)
        dr.eval(img)
        return img

    def run_trace():
        C, T, steps, _ = trace(scene, ts, rays, settings, True)
        dr.eval(C, T, steps)
        return C, T, steps

    def run_plain(integral, n):
        def run():
            ts.model.n_sub = n
            C, T, steps = plain_trace(scene, ts, rays, 0.0, settings.max_steps, integral,
                                      plain)
            dr.eval(C, T, steps)
            ts.model.n_sub = n_sub
            return C, T, steps
        return run

    methods = [("tetvr  mi.render", run_render), ("tetvr  trace()", run_trace),
               (f"plain walk, tetvr's integral (n_sub {n_sub})", run_plain("model", n_sub)),
               (f"plain walk, Alg. 1 integral ({a.baseline_n_sub} sub-intervals)",
                run_plain("alg1", a.baseline_n_sub))]
    if a.shuffle:
        # The same walk on the tet records in the file's order.
        unordered = TetGroup(ts.shapes, ts.face_offsets, MeshBuffers(
            **{k: type(getattr(ts.buf, k))(x) for k, x in
               shape_index_arrays(topo, v, reorder=False).items()},
            positions=ts.buf.positions), ts.model, ts.params)

        def run_unordered():
            C, T, steps, _ = trace(scene, unordered, rays, settings, True)
            dr.eval(C, T, steps)
            return C, T, steps
        methods.append(("tetvr  trace(), tets in the file's order", run_unordered))
    timings = {}
    for name, fn in methods:
        first, med, runs, out = timed(fn, a.repeat)
        timings[name] = (first, med, runs, out)
    img = np.asarray(timings["tetvr  mi.render"][3]).reshape(-1, 3)
    C_tv, T_tv, steps = timings["tetvr  trace()"][3]
    steps_np = np.asarray(steps)
    n_steps = total(steps_np)
    # The reference: the same walk, the integral converged.
    ts.model.n_sub = REFERENCE_N_SUB
    C_ref, T_ref, _, _ = trace(scene, ts, rays, settings, True)
    ts.model.n_sub = n_sub
    C_ref = rgb_np(C_ref)

    n_hit = int(np.count_nonzero(steps_np))
    print(f"rays through the mesh: {n_hit:,} of {n_rays:,}; tets per such ray: mean "
          f"{n_steps / max(n_hit, 1):.1f}, max {int(steps_np.max())}; "
          f"{n_steps:,} tet steps per image")
    print(f"mi.render vs trace() on the pixel-center rays: max |diff| = "
          f"{np.abs(img - rgb_np(C_tv)).max():.1e}; tets crossed by the plain walk: "
          f"{total(np.asarray(timings[list(timings)[2]][3][2])) - n_steps:+,}")
    print()
    print(f"{'method':<46}{'1st [s]':>8}{'median [s]':>11}{'Msteps/s':>10}"
          f"{'max err':>9}   runs [s]")
    results = {"mesh": dict(cells=a.cells, jitter=a.jitter, vertices=len(v), tets=topo.n_tets),
               "image": dict(res=res, rays=n_rays, n_sub=n_sub,
                             baseline_n_sub=a.baseline_n_sub),
               "rays": dict(through_mesh=n_hit, tets_per_ray_mean=n_steps / max(n_hit, 1),
                            tets_per_ray_max=int(steps_np.max()), steps=n_steps),
               "methods": []}
    for name, (first, med, runs, out) in timings.items():
        C = img if name == "tetvr  mi.render" else rgb_np(out[0])
        err = float(np.abs(C - C_ref).max())
        print(f"{name:<46}{first:>8.3f}{med:>11.3f}{n_steps / med / 1e6:>10.1f}"
              f"{err:>9.1e}   " + ", ".join(f"{t:.3f}" for t in runs))
        results["methods"].append(dict(method=" ".join(name.split()), first_s=first,
                                       median_s=med, runs_s=runs,
                                       msteps_per_s=n_steps / med / 1e6, max_error=err))
    trace_s = timings["tetvr  trace()"][1]
    names = list(timings)
    same, alg1 = timings[names[2]][1] / trace_s, timings[names[3]][1] / trace_s
    print()
    print(f"plain walk / tetvr walk, same integral: {same:.2f}x; plain walk with the "
          f"Alg. 1 integral ({a.baseline_n_sub} sub-intervals) / tetvr: {alg1:.2f}x")
    print(f"(max err: max |rgb - tetvr at n_sub {REFERENCE_N_SUB}| over all pixels; "
          f"'1st' includes tracing and compilation; median of {a.repeat} warm runs)")
    results["plain_over_tetvr"] = dict(same_integral=same, alg1_integral=alg1)
    if a.shuffle:
        gain = timings[names[4]][1] / trace_s
        print(f"tets in the file's order / in Morton order: {gain:.2f}x")
        results["file_order_over_morton"] = gain
    write_json(a, info, results)
    return 0


if __name__ == "__main__":
    sys.exit(main(ARGS))
