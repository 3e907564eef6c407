"""Rays in, colors out: ``render_rays`` against ``mi.render`` on the same rays.

Scene: the jittered ``cells^3`` grid with the blob field of ``bench_render.py``,
one ray per pixel through the pixel centre (``res x res``), no early ray
termination. Both render the same rays: ``mi.render`` with a stratified sampler
without jitter (its rays are the pixel-centre rays), ``render_rays`` the rays of
the sensor at the pixel centres, given as arrays. Each is timed warm (one run to
compile, then the median of ``--repeat`` runs), in turns, for

1. the primal: the RGBA of every ray;
2. the primal and ``dr.backward`` of an L2 loss w.r.t. the vertex colors,
   opacities and positions.

Then the memory of ``dr.backward`` through ``render_rays`` (the peak of
Dr.Jit's allocations above what was allocated before it) on the same rays at
two opacity scales: the blob field as is (every ray crosses the grid) and an
opaque one (early termination after a few tets), as ``bench_memory.py``
measures ``mi.render``: flat in the tets a ray crosses.

Usage::

    python benchmarks/bench_rays.py            # 64^3 cells, 256x256
    python benchmarks/bench_rays.py --quick    # 16^3 cells, 64x64
"""
from __future__ import annotations

from common import grid_scene, header, make_parser, pixel_rays, spread, timed, write_json


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=5, quick="--cells 16 --res 64")
    p.add_argument("--cells", type=int, default=64, help="grid cells per axis (default 64)")
    p.add_argument("--res", type=int, default=256, help="image width = height (default 256)")
    p.add_argument("--opaque", type=float, default=200.0,
                   help="opacity of the opaque case, per unit length (default 200)")
    a = p.parse_args(argv)
    if a.quick:
        a.cells, a.res = 16, 64
    return a


ARGS = parse_args()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402,F401
from mi_tetvr.rays import render_rays  # noqa: E402
from mi_tetvr.render.walk import trace  # noqa: E402

KEYS = ("volume.vertex_color", "volume.vertex_opacity", "volume.vertex_positions")
MB = 1024.0 ** 2


def main(a):
    info = header("rays in, colors out: render_rays against mi.render")
    scene, v, tets, color, opacity = grid_scene(a.cells, a.res, min_transmittance=0.0)
    params = mi.traverse(scene)
    ray = pixel_rays(scene.sensors()[0], a.res)
    n = a.res * a.res
    target = mi.TensorXf(dr.zeros(mi.Float, n * 4), (a.res, a.res, 4))
    flat_target = mi.TensorXf(dr.zeros(mi.Float, n * 4), (n, 4))
    print(f"mesh: {a.cells}^3 cells, {len(tets):,} tets; {n:,} pixel-centre rays")

    def image():
        img = mi.render(scene, spp=1)
        dr.eval(img)
        return img

    def rays():
        out = render_rays(scene, ray.o, ray.d)
        dr.eval(out)
        return out

    def with_gradients(render, tgt):
        def run():
            for k in KEYS:
                dr.enable_grad(params[k])
            dr.backward(dr.mean(dr.square(render() - tgt), axis=None))
            grads = [dr.grad(params[k]) for k in KEYS]
            dr.eval(grads)
            for k in KEYS:
                dr.disable_grad(params[k])
            return grads
        return run

    a_img, b_img = image(), rays()
    diff = float(np.abs(np.array(a_img).reshape(-1, 4) - np.array(b_img)).max())
    print(f"render_rays vs mi.render on the pixel-centre rays: max |diff| = {diff:.1e}")
    cases = [("primal", image, rays),
             ("primal + dr.backward", with_gradients(lambda: mi.render(scene, params, spp=1),
                                                     target),
              with_gradients(lambda: render_rays(scene, ray.o, ray.d, params=params),
                             flat_target))]
    results = {"tets": len(tets), "rays": n, "max_diff": diff, "cases": []}
    print(f"\n{'case':<22}{'mi.render [s]':>14}{'render_rays [s]':>16}{'ratio':>8}   "
          f"ratio per turn")
    for name, f_img, f_rays in cases:
        ratios, t_img, t_rays = [], [], []
        for _ in range(3):      # in turns: the drift of the machine falls on both
            t_img.append(timed(f_img, a.repeat)[1])
            t_rays.append(timed(f_rays, a.repeat)[1])
            ratios.append(t_rays[-1] / t_img[-1])
        print(f"{name:<22}{np.median(t_img):>14.3f}{np.median(t_rays):>16.3f}"
              f"{np.median(ratios):>8.2f}   {spread(ratios)}")
        results["cases"].append(dict(case=name, mi_render_s=t_img, render_rays_s=t_rays,
                                     ratios=ratios))

    print(f"\n{'opacity':<22}{'tets per ray':>14}{'backward [MB]':>16}")
    results["memory"] = []
    for label, sigma in (("blob field", None), (f"opaque ({a.opaque:g})", a.opaque)):
        if sigma is not None:
            params["volume.vertex_opacity"] = dr.full(mi.Float, sigma, len(v))
            params.update()
        integrator = scene.integrator()
        with dr.suspend_grad():
            _, _, steps, _ = trace(scene, integrator.tet_group(scene), ray,
                                   integrator.settings_for(scene), True)
        steps = np.asarray(steps)
        per_ray = float(steps[steps > 0].mean())
        for k in KEYS:
            dr.enable_grad(params[k])
        loss = dr.mean(dr.square(render_rays(scene, ray.o, ray.d, params=params)
                                 - flat_target), axis=None)
        dr.eval(loss)
        dr.sync_thread()
        dr.flush_malloc_cache()
        dr.detail.malloc_clear_statistics()
        backend = dr.backend_v(mi.Float)
        base = dr.detail.malloc_watermark(backend)
        dr.backward(loss)
        dr.eval([dr.grad(params[k]) for k in KEYS])
        dr.sync_thread()
        extra = (dr.detail.malloc_watermark(backend) - base) / MB
        for k in KEYS:
            dr.disable_grad(params[k])
        print(f"{label:<22}{per_ray:>14.1f}{extra:>16.1f}")
        results["memory"].append(dict(opacity=label, tets_per_ray=per_ray, backward_mb=extra))
    write_json(a, info, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(ARGS))
