"""Render benchmark: the ``tetvr`` tet walk against a Mitsuba-native baseline.

Scene: a jittered regular tet grid (``cells^3`` cells, 6 Kuhn tets each; 64^3
= 1.57M tets) over [-1, 1]^3 carrying :func:`mi_tetvr.mesh.generate.blob_field`,
seen by a perspective camera, one ray per pixel through the pixel center,
no early ray termination (``min_transmittance = 0``), so every ray crosses the
whole mesh.

1. **tetvr**: ``mi.render`` with the ``tetvr`` integrator (stratified sampler
   without jitter, so its rays are the pixel-center rays), and
   :func:`mi_tetvr.render.walk.trace` called directly on the same rays
   (which gives the number of tets crossed). Both are timed warm (one run to
   compile, then the median of ``--repeat`` runs).
2. **baseline**: every tet face (each unique triangle once) in one ordinary
   Mitsuba ``mesh`` in a separate scene. The ray is advanced hit by hit with
   ``scene.ray_intersect_preliminary`` (Embree BVH, origin moved just past each
   hit) inside a Dr.Jit symbolic loop; between two consecutive hits the ray is
   inside one tet, color and opacity at each hit come from the hit triangle's
   vertices with the barycentrics in ``si.prim_uv``, and the segment is
   integrated with the same :func:`mi_tetvr.render.segment.segment_integral`. (The
   baseline assumes a convex mesh: everything between the first and the last
   hit is inside; the grid is a box.)

Usage::

    python benchmarks/bench_render.py            # 64^3 cells, 512x512
    python benchmarks/bench_render.py --quick    # 16^3 cells, 128x128 smoke run
"""
from __future__ import annotations

import sys
import time

import numpy as np

from common import grid_scene, header, make_parser, timed, write_json


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=3, quick="--cells 16 --res 128")
    p.add_argument("--cells", type=int, default=64, help="grid cells per axis (default 64)")
    p.add_argument("--res", type=int, default=512, help="image width = height (default 512)")
    p.add_argument("--jitter", type=float, default=0.15,
                   help="vertex jitter in cell sizes (default 0.15; > ~0.2 inverts Kuhn tets)")
    p.add_argument("--scale", type=float, default=1.0, help="blob_field opacity scale (default 1)")
    p.add_argument("--n-sub", type=int, default=8, help="sub-intervals per segment (default 8, as tetvr)")
    p.add_argument("--eps", type=float, default=1e-5,
                   help="baseline: offset past each hit, relative to the bbox diagonal "
                        "(default 1e-5, like tetvr's retrace_epsilon)")
    a = p.parse_args(argv)
    if a.quick:
        a.cells, a.res = 16, 128
    return a


ARGS = parse_args()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant(ARGS.variant)

import mi_tetvr  # noqa: E402
from mi_tetvr.render.segment import segment_integral  # noqa: E402
from mi_tetvr.mesh.topology import FACES  # noqa: E402
from mi_tetvr.render.walk import WalkSettings, trace  # noqa: E402

mi_tetvr.register()
from mi_tetvr.render.buffers import scene_tetmeshes  # noqa: E402


# ----------------------------------------------------------------------------
# Scene
# ----------------------------------------------------------------------------

def pixel_rays(sensor, res):
    """One normalized ray through each pixel center (row-major, like the film)."""
    idx = dr.arange(mi.UInt32, res * res)
    x = mi.Float(idx % res) + 0.5
    y = mi.Float(idx // res) + 0.5
    ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5),
                               mi.Point2f(x / res, y / res), mi.Point2f(0.5))
    ray = mi.Ray3f(ray.o, dr.normalize(ray.d))
    dr.eval(ray)
    return ray


def unique_faces(tets, neighbors):
    """Each triangle of the tet mesh once: face (t, i) is kept when it is on the
    boundary or t is the smaller of the two tets sharing it."""
    m = len(tets)
    keep = (neighbors < 0) | (np.arange(m)[:, None] < neighbors)
    return tets[:, FACES][keep]  # (f, 3)


def baseline_scene(vertices, faces):
    mesh = mi.Mesh("all_tet_faces", len(vertices), len(faces))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.asarray(vertices, np.float32).ravel())
    params["faces"] = mi.UInt32(np.asarray(faces, np.uint32).ravel())
    params.update()
    return mi.load_dict({"type": "scene", "faces": mesh})


# ----------------------------------------------------------------------------
# Baseline: multi-hit BVH traversal
# ----------------------------------------------------------------------------

@dr.syntax
def baseline_rays(scene, faces, color, opacity, ray, n_sub: int, eps: float,
                  max_hits: int):
    """Emission, transmittance and hit count along ``ray`` by repeated
    ``ray_intersect_preliminary`` against all tet faces."""
    o = mi.Point3f(ray.o)
    d = mi.Vector3f(ray.d)
    L = mi.Color3f(0.0)
    T = mi.Float(1.0)
    t = mi.Float(0.0)        # ray parameter of the previous hit
    c = mi.Color3f(0.0)      # color and opacity there
    s = mi.Float(0.0)
    start = mi.Float(0.0)    # where the next trace starts
    hits = mi.UInt32(0)
    active = dr.full(mi.Bool, True, dr.width(o))
    while dr.hint(active, label="baseline_multihit"):
        si = scene.ray_intersect_preliminary(mi.Ray3f(o + d * start, d), active=active)
        active &= si.is_valid()
        t_hit = start + si.t
        f = mi.UInt32(si.prim_index)
        i0 = dr.gather(mi.UInt32, faces, f * 3 + 0, active)
        i1 = dr.gather(mi.UInt32, faces, f * 3 + 1, active)
        i2 = dr.gather(mi.UInt32, faces, f * 3 + 2, active)
        b1, b2 = si.prim_uv.x, si.prim_uv.y
        b0 = 1.0 - b1 - b2
        c_hit = (b0 * dr.gather(mi.Color3f, color, i0, active)
                 + b1 * dr.gather(mi.Color3f, color, i1, active)
                 + b2 * dr.gather(mi.Color3f, color, i2, active))
        s_hit = (b0 * dr.gather(mi.Float, opacity, i0, active)
                 + b1 * dr.gather(mi.Float, opacity, i1, active)
                 + b2 * dr.gather(mi.Float, opacity, i2, active))
        # Segment from the previous hit (inside one tet); none before the first.
        length = dr.select(hits > 0, dr.maximum(t_hit - t, 0.0), 0.0)
        C_seg, T_seg = segment_integral(length, c, c_hit, s, s_hit, n_sub)
        L[active] = L + T * C_seg
        T[active] = T * T_seg
        t[active] = t_hit
        c[active] = c_hit
        s[active] = s_hit
        start[active] = t_hit + eps
        hits[active] = hits + 1
        active &= hits < max_hits
    return L, T, hits


# ----------------------------------------------------------------------------
# Timing helpers
# ----------------------------------------------------------------------------

def total(x):
    return int(np.asarray(x, dtype=np.uint64).sum())


def rgb_np(C):
    return np.stack([np.asarray(C.x), np.asarray(C.y), np.asarray(C.z)], -1)


# ----------------------------------------------------------------------------

def main(a):
    res, n_rays = a.res, a.res * a.res
    info = header("render benchmark")
    results = {}

    # -- mesh ----------------------------------------------------------------
    t0 = time.perf_counter()
    tv_scene, v, tets, color, opacity = grid_scene(
        a.cells, res, a.jitter, a.scale, n_sub=a.n_sub, min_transmittance=0.0, alpha=False)
    shape = scene_tetmeshes(tv_scene)[0]
    topo = shape.topology
    t_tv_scene = time.perf_counter() - t0
    print(f"mesh: {a.cells}^3 cells, jitter {a.jitter}: {len(v):,} vertices, "
          f"{topo.n_tets:,} tets, {len(topo.boundary_faces):,} boundary faces, "
          f"{topo.n_flipped} flipped, {int(topo.flat.sum())} flat "
          f"(tetmesh scene built in {t_tv_scene:.1f} s)")
    results["mesh"] = dict(cells=a.cells, jitter=a.jitter, vertices=len(v), tets=topo.n_tets,
                           boundary_faces=len(topo.boundary_faces), flipped=topo.n_flipped,
                           flat=int(topo.flat.sum()), scene_s=t_tv_scene)

    t0 = time.perf_counter()
    faces = unique_faces(topo.tets.astype(np.int64), topo.neighbors)
    bl_scene = baseline_scene(v, faces)
    t_bl_scene = time.perf_counter() - t0
    print(f"baseline mesh: {len(faces):,} unique triangles in one Mitsuba mesh "
          f"(scene + BVH built in {t_bl_scene:.1f} s)")
    print(f"image: {res}x{res} = {n_rays:,} rays, n_sub = {a.n_sub}, no early termination")
    results["baseline_mesh"] = dict(triangles=len(faces), scene_s=t_bl_scene)
    results["image"] = dict(res=res, rays=n_rays, n_sub=a.n_sub)
    print()

    sensor = tv_scene.sensors()[0]
    rays = pixel_rays(sensor, res)
    integrator = tv_scene.integrator()
    diag = float(dr.norm(tv_scene.bbox().extents()))
    settings = WalkSettings(0.0, integrator.settings.max_steps,
                            integrator.retrace_epsilon * diag)
    ts = integrator.tet_scene(tv_scene)
    dr.eval(ts.buf, ts.params)

    # -- tetvr through mi.render ----------------------------------------------
    def run_render():
        img = mi.render(tv_scene, spp=1)
        dr.eval(img)
        return img

    r_first, r_med, r_all, img = timed(run_render, a.repeat)
    img = np.asarray(img).reshape(-1, 3)

    # -- tetvr walk on the same rays ------------------------------------------
    def run_walk():
        C, T, steps, _ = trace(dr.ADMode.Primal, tv_scene, ts, rays,
                               settings, True)
        dr.eval(C, T, steps)
        return C, T, steps

    w_first, w_med, w_all, (C_tv, T_tv, steps) = timed(run_walk, a.repeat)
    C_tv = rgb_np(C_tv)
    steps_np = np.asarray(steps)
    n_steps = total(steps_np)

    # -- baseline ---------------------------------------------------------------
    f_buf = mi.UInt32(faces.astype(np.uint32).ravel())
    c_buf = mi.Float(np.asarray(color, np.float32).ravel())
    o_buf = mi.Float(np.asarray(opacity, np.float32).ravel())
    eps = a.eps * diag
    dr.eval(f_buf, c_buf, o_buf)

    def run_baseline():
        L, T, hits = baseline_rays(bl_scene, f_buf, c_buf, o_buf, rays, a.n_sub, eps,
                                   1_000_000)
        dr.eval(L, T, hits)
        return L, T, hits

    b_first, b_med, b_all, (C_bl, T_bl, hits) = timed(run_baseline, a.repeat)
    C_bl = rgb_np(C_bl)
    hits_np = np.asarray(hits)
    n_hits = total(hits_np)
    n_segs = total(np.maximum(hits_np.astype(np.int64) - 1, 0))

    # -- checks -----------------------------------------------------------------
    n_hit_rays = int(np.count_nonzero(steps_np))
    d_img = np.abs(img - C_tv).max()
    diff = np.abs(C_bl - C_tv).max(1)
    dT = np.abs(np.asarray(T_bl) - np.asarray(T_tv))
    bad = diff > 1e-3
    print(f"rays through the mesh: {n_hit_rays:,} of {n_rays:,}; "
          f"tets per such ray: mean {n_steps / max(n_hit_rays, 1):.1f}, "
          f"max {int(steps_np.max())}; mean transmittance {float(np.asarray(T_tv).mean()):.3f}")
    print(f"check mi.render image vs trace() on the pixel-center rays: "
          f"max |diff| = {d_img:.2e}")
    print(f"check baseline vs tetvr: max |dC| = {diff.max():.2e} "
          f"(mean {diff.mean():.1e}, {int(bad.sum())} rays > 1e-3), "
          f"max |dT| = {dT.max():.2e}")
    print(f"check steps: tetvr {n_steps:,} tets crossed; baseline {n_hits:,} hits = "
          f"{n_segs:,} segments ({n_segs - n_steps:+,}; "
          f"rays with a different count: {int(np.count_nonzero(np.maximum(hits_np.astype(np.int64) - 1, 0) != steps_np)):,})")
    print()
    results["rays"] = dict(through_mesh=n_hit_rays, tets_per_ray_mean=n_steps / max(n_hit_rays, 1),
                           tets_per_ray_max=int(steps_np.max()),
                           mean_transmittance=float(np.asarray(T_tv).mean()))
    results["checks"] = dict(
        render_vs_trace_max_diff=float(d_img), baseline_vs_tetvr_max_dC=float(diff.max()),
        baseline_vs_tetvr_mean_dC=float(diff.mean()), rays_dC_over_1e3=int(bad.sum()),
        baseline_vs_tetvr_max_dT=float(dT.max()), tetvr_steps=n_steps, baseline_hits=n_hits,
        baseline_segments=n_segs,
        rays_with_different_count=int(np.count_nonzero(
            np.maximum(hits_np.astype(np.int64) - 1, 0) != steps_np)))

    # -- table ------------------------------------------------------------------
    def fmt_times(ts):
        return ", ".join(f"{t:.3f}" for t in ts)

    rows = [
        ("tetvr  mi.render", r_first, r_med, n_steps, r_all),
        ("tetvr  trace()", w_first, w_med, n_steps, w_all),
        ("baseline multi-hit BVH", b_first, b_med, n_segs, b_all),
    ]
    print(f"{'method':<24}{'1st run [s]':>12}{'median [s]':>12}{'steps':>14}"
          f"{'Msteps/s':>10}{'Mrays/s':>9}   runs [s]")
    for name, first, med, n, ts in rows:
        print(f"{name:<24}{first:>12.3f}{med:>12.3f}{n:>14,}{n / med / 1e6:>10.1f}"
              f"{n_rays / med / 1e6:>9.2f}   {fmt_times(ts)}")
    print()
    print(f"baseline / tetvr time ratio: {b_med / w_med:.2f}x (trace()), "
          f"{b_med / r_med:.2f}x (mi.render)")
    results["methods"] = [dict(method=" ".join(name.split()), first_s=first, median_s=med, steps=n,
                               msteps_per_s=n / med / 1e6, mrays_per_s=n_rays / med / 1e6,
                               runs_s=ts) for name, first, med, n, ts in rows]
    results["baseline_over_tetvr"] = dict(trace=b_med / w_med, render=b_med / r_med)
    print(f"('steps' = tet segments integrated; baseline segments = hits - 1 per ray; "
          f"1st run includes tracing + LLVM compilation; median of {a.repeat} warm runs)")
    write_json(a, info, results)
    return 0


if __name__ == "__main__":
    sys.exit(main(ARGS))
