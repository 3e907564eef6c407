"""Benchmark of mesh refinement (mi_tetvr.mesh.refine) on a ~1M-tet jittered grid.

Prints the time of :func:`mi_tetvr.mesh.refine.split_vertices` with 5 % of the
vertices selected (DiffTetVR's setting), for both global bisection orders and
for everything selected, next to the baseline measured in the same run:
:func:`mi_tetvr.mesh.build_topology` on the refined mesh, which every
refinement is followed by anyway. Also times :func:`prune_empty`.

    python benchmarks/bench_refine.py [--cells 56] [--fraction 0.05] [--repeat 3] [--all]
    python benchmarks/bench_refine.py --quick    # 12^3 cells smoke run
"""
from __future__ import annotations

import os
import platform
import time

import numpy as np

from common import header_info, make_parser, timed, write_json
from mi_tetvr.mesh.generate import blob_field, grid_mesh
from mi_tetvr.mesh.topology import build_topology, quality
from mi_tetvr.mesh.refine import prune_empty, select_top_fraction, split_vertices


def main():
    ap = make_parser(__doc__, variant=False, repeat=3, quick="--cells 12")
    ap.add_argument("--cells", type=int, default=56, help="grid cells per axis (56: ~1M tets)")
    ap.add_argument("--fraction", type=float, default=0.05)
    ap.add_argument("--all", action="store_true",
                    help="also refine with every vertex selected (8x the tets; slow, ~3 GB)")
    args = ap.parse_args()
    if args.quick:
        args.cells = 12
    info = header_info("refinement benchmark")
    results = {"rows": []}

    print(f"# mi_tetvr refinement benchmark (numpy {np.__version__}, python "
          f"{platform.python_version()}, {os.cpu_count()} CPU cores)")
    v, t = grid_mesh(args.cells, jitter=0.15)
    color, opacity = blob_field(v)
    pd = {"color": color, "opacity": opacity}
    print(f"# mesh: grid_mesh({args.cells}, jitter=0.15): {len(v)} vertices, {len(t)} tets")
    results["mesh"] = dict(cells=args.cells, jitter=0.15, vertices=len(v), tets=len(t))

    # scores as from accumulated absolute gradients: random, with zeros
    rng = np.random.default_rng(0)
    scores = rng.random(len(v)) * (rng.random(len(v)) < 0.9)
    _, t_sel, _, sel = timed(lambda: select_top_fraction(scores, args.fraction), args.repeat,
                             warmup=False)
    print(f"select_top_fraction({args.fraction}): {len(sel)} vertices in {t_sel * 1e3:.1f} ms")
    results["select_top_fraction"] = dict(fraction=args.fraction, vertices=len(sel),
                                          median_s=t_sel)

    cases = [(f"{args.fraction:.0%} selected, longest-first", sel, "longest"),
             (f"{args.fraction:.0%} selected, hash order", sel, "hash")]
    if args.all:
        cases.append(("all selected, longest-first", np.arange(len(v)), "longest"))
    for label, selection, order in cases:
        reps = args.repeat if len(selection) < len(v) else 1
        _, dt, _, res = timed(lambda: split_vertices(v, t, selection, pd, order=order), reps,
                              warmup=False)
        t0 = time.perf_counter()
        topo = build_topology(res.vertices, res.tets, warn=False)
        dt_topo = time.perf_counter() - t0
        q = quality(res.vertices, res.tets)
        kids = q[np.bincount(res.parent)[res.parent] > 1]
        print(f"split_vertices [{label}]: {dt:.3f} s  ({len(t)} -> {len(res.tets)} tets, "
              f"+{res.n_new_vertices} vertices, {res.n_rounds} rounds); "
              f"build_topology of the result {dt_topo:.3f} s, ratio refine/topology "
              f"{dt / dt_topo:.2f}; quality of refined tets min {kids.min():.3f} "
              f"mean {kids.mean():.3f}; flipped {topo.n_flipped}")
        results["rows"].append(dict(
            case=label, order=order, selected=len(selection), median_s=dt, tets_in=len(t),
            tets_out=len(res.tets), new_vertices=res.n_new_vertices, rounds=res.n_rounds,
            build_topology_s=dt_topo, refine_over_topology=dt / dt_topo,
            quality_min=float(kids.min()), quality_mean=float(kids.mean()),
            flipped=topo.n_flipped))

    thr = np.percentile(opacity, 50)
    _, dt, _, pr = timed(lambda: prune_empty(v, t, opacity, thr, pd), args.repeat,
                         warmup=False)
    print(f"prune_empty(threshold=median opacity): {dt:.3f} s  ({len(t)} -> {len(pr.tets)} tets, "
          f"{pr.n_nonmanifold_edges} non-manifold boundary edges)")
    results["prune_empty"] = dict(threshold=float(thr), median_s=dt, tets_in=len(t),
                                  tets_out=len(pr.tets),
                                  nonmanifold_edges=pr.n_nonmanifold_edges)
    write_json(args, info, results)


if __name__ == "__main__":
    main()
