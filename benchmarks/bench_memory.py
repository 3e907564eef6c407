"""Memory benchmark of the derivative pass: constant in the number of tets a
ray crosses (the adjoint re-walks the rays and records nothing), against
Dr.Jit's AD through a recorded (evaluated) loop, which stores every step.

One mesh (the jittered ``cells^3`` grid with the blob field) and one image
(``res x res`` pixel-center rays), two opacity scales:

- *transparent*: the blob field as is; rays cross the whole grid (~100 tets
  at 64^3) with no early termination;
- *opaque*: a constant opacity of ``--opaque`` per unit length (optical
  depth ~6 per tet at 64^3); rays stop after a few tets (early ray
  termination at the default transmittance 1e-4).

For each, the peak Dr.Jit memory (``dr.detail.malloc_watermark``) above what
was allocated before is measured for

1. ``tetvr``'s adjoint: ``dr.backward`` of an L2 image loss through
   ``mi.render`` with gradients on colors, opacities and positions (this
   includes the primal pass's kept per-ray values and the gradient buffers);
2. the fit's distortion regularizer (a render of the disparity moments, the same adjoint);
3. the recorded-loop reference: the same primal renderer run with
   ``dr.JitFlag.SymbolicLoops`` off and AD on, then ``dr.backward`` (done on
   ``--ref-res``^2 rays, a smaller image, since its memory grows with the
   number of steps: it is reported also per ray and per step; an evaluated
   loop runs all rays until the longest one ends, so it grows with the
   *maximum* number of tets crossed).

Usage::

    python benchmarks/bench_memory.py            # 64^3 cells, 128x128
    python benchmarks/bench_memory.py --quick    # 16^3 cells, 32x32 (reference 16x16)
"""
from __future__ import annotations

from common import grid_scene, header, make_parser, write_json


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=None, quick="--cells 16 --res 32 --ref-res 16")
    p.add_argument("--cells", type=int, default=64, help="grid cells per axis (default 64)")
    p.add_argument("--res", type=int, default=128, help="image width = height (default 128)")
    p.add_argument("--ref-res", type=int, default=128,
                   help="image size for the recorded-loop reference (default 128: the same rays)")
    p.add_argument("--opaque", type=float, default=200.0,
                   help="opacity of the opaque case, per unit length (default 200)")
    a = p.parse_args(argv)
    if a.quick:
        a.cells, a.res, a.ref_res = 16, 32, 16
    return a


ARGS = parse_args()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402,F401
from mi_tetvr.render.walk import trace  # noqa: E402

KEYS = ("volume.vertex_color", "volume.vertex_opacity", "volume.vertex_positions")
MB = 1024.0 ** 2


def backend():
    return dr.backend_v(mi.Float)


def start_measure():
    dr.eval()
    dr.sync_thread()
    dr.flush_malloc_cache()
    dr.detail.malloc_clear_statistics()
    return dr.detail.malloc_watermark(backend())


def peak_since(base):
    dr.sync_thread()
    return (dr.detail.malloc_watermark(backend()) - base) / MB


def pixel_rays(scene, res):
    integrator, sensor = scene.integrator(), scene.sensors()[0]
    with dr.suspend_grad():
        sampler, _ = integrator.prepare(sensor, 0, 1, integrator.aov_names())
        ray, _, _ = integrator.sample_rays(scene, sensor, sampler)
    ray = mi.Ray3f(ray)
    ray.d = dr.normalize(ray.d)
    dr.eval(ray)
    return ray


def tets_per_ray(scene, ray):
    integrator = scene.integrator()
    with dr.suspend_grad():
        _, _, steps, _ = trace(scene, integrator.tet_group(scene), ray,
                               integrator.settings_for(scene), True)
    steps = np.asarray(steps)
    hit = steps > 0
    return steps[hit].mean(), steps.max(), hit.sum()


def backward_memory(scene, params, keys, loss_of):
    """Peak memory of ``dr.backward`` of ``loss_of(image)`` through ``mi.render`` with
    gradients on ``keys``."""
    for k in keys:
        dr.enable_grad(params[k])
    loss = loss_of(mi.render(scene, params, spp=1))
    dr.eval(loss)
    base = start_measure()
    dr.backward(loss)
    dr.eval([dr.grad(params[k]) for k in keys])
    extra = peak_since(base)
    for k in keys:
        dr.disable_grad(params[k])
    return extra


def adjoint_memory(scene, params, res):
    target = mi.TensorXf(dr.zeros(mi.Float, res * res * 4), (res, res, 4))
    return backward_memory(scene, params, KEYS,
                           lambda img: dr.mean(dr.square(img - target), axis=None))


def distortion_memory(scene, params, vertices):
    """The derivative pass of the fit's distortion regularizer
    (:meth:`Trainer.distortion <mi_tetvr.recon.trainer.Trainer.distortion>`): a render with
    the disparity moments ``(s, s^2, 0)`` as vertex colors, ``mean(alpha S_2 - S_1^2)``,
    gradients on opacities and positions."""
    sensor = scene.sensors()[0]
    frame = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    z = (vertices - frame[:3, 3]) @ frame[:3, 2]
    near = 0.25 * float(np.median(np.abs(z)))
    s = near / np.maximum(z, near)
    color = params["volume.vertex_color"]
    params["volume.vertex_color"] = mi.Float(np.stack([s, s * s, 0 * s], 1).ravel())
    params.update()
    extra = backward_memory(scene, params, KEYS[1:], lambda img: dr.mean(
        img[..., 3] * img[..., 1] - dr.square(img[..., 0]), axis=None))
    params["volume.vertex_color"] = color
    params.update()
    return extra


def recorded_memory(scene, params, ray):
    integrator = scene.integrator()
    for k in KEYS:
        dr.enable_grad(params[k])
    base = start_measure()
    with dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, False):
        L, _, aovs, _ = integrator.sample(dr.ADMode.Primal, scene, None, ray, None, None, True)
        loss = dr.sum(dr.sum(L) + aovs[0])
        dr.backward(loss)
        dr.eval([dr.grad(params[k]) for k in KEYS])
    extra = peak_since(base)
    for k in KEYS:
        dr.disable_grad(params[k])
    return extra


def main(a):
    info = header("memory benchmark")
    scene, v, tets, color, opacity = grid_scene(a.cells, a.res)
    params = mi.traverse(scene)
    print(f"mesh: {a.cells}^3 cells, {len(tets):,} tets, {len(v):,} vertices; "
          f"image {a.res}x{a.res}; recorded-loop reference on {a.ref_res}x{a.ref_res} rays")
    base_opacity = mi.Float(params["volume.vertex_opacity"])
    rays = pixel_rays(scene, a.res)
    # The reference's rays: a sub-grid of the same image's pixels.
    step = a.res // a.ref_res
    sub = (np.arange(a.ref_res)[:, None] * step * a.res + np.arange(a.ref_res)[None] * step).ravel()
    ref_rays = dr.gather(mi.Ray3f, rays, mi.UInt32(sub.astype(np.uint32)))
    rows = []
    opaque = dr.full(mi.Float, a.opaque, dr.width(base_opacity))
    dr.make_opaque(opaque)  # a real buffer, not a literal
    cases = (("transparent", base_opacity), ("opaque", opaque))
    for name, op in cases:
        params["volume.vertex_opacity"] = op
        params.update()
        mean_tets, max_tets, n_hit = tets_per_ray(scene, rays)
        adj = adjoint_memory(scene, params, a.res)
        dist = distortion_memory(scene, params, v)
        ref = recorded_memory(scene, params, ref_rays)
        rows.append((name, mean_tets, max_tets, adj, ref, dist))
    print()
    print(f"{'case':12s} {'tets/ray':>9s} {'max':>5s} {'adjoint [MB]':>13s} "
          f"{'recorded loop [MB]':>19s} {'per ray per max step [B]':>25s}")
    n_ref = a.ref_res * a.ref_res
    for name, mt, xt, adj, ref, _ in rows:
        print(f"{name:12s} {mt:9.1f} {xt:5d} {adj:13.1f} {ref:19.1f} "
              f"{ref * MB / (n_ref * xt):25.0f}")
    (_, mt0, _, adj0, ref0, dist0), (_, mt1, _, adj1, ref1, dist1) = rows
    print()
    print(f"adjoint: transparent - opaque = {adj0 - adj1:+.1f} MB "
          f"({mt0:.0f} vs {mt1:.1f} tets per ray)")
    print(f"the fit's distortion regularizer (its adjoint): {dist0:.1f} MB transparent, "
          f"{dist1:.1f} MB opaque ({dist0 - dist1:+.1f} MB)")
    scaled = ("" if a.ref_res == a.res else
              f"; ~{(ref0 - ref1) * (a.res / a.ref_res) ** 2:.0f} MB at {a.res}x{a.res}")
    print(f"recorded loop: transparent / opaque = {ref0 / max(ref1, 1e-9):.1f}x "
          f"(+{ref0 - ref1:.1f} MB on {a.ref_res}x{a.ref_res} rays{scaled})")
    write_json(a, info, {
        "mesh": dict(cells=a.cells, tets=len(tets), vertices=len(v)),
        "image": dict(res=a.res, ref_res=a.ref_res),
        "cases": [dict(case=name, tets_per_ray_mean=mt, tets_per_ray_max=xt, adjoint_mb=adj,
                       recorded_loop_mb=ref,
                       recorded_bytes_per_ray_per_max_step=ref * MB / (n_ref * xt),
                       distortion_adjoint_mb=dist)
                  for name, mt, xt, adj, ref, dist in rows],
        "adjoint_transparent_minus_opaque_mb": adj0 - adj1,
        "recorded_transparent_over_opaque": ref0 / max(ref1, 1e-9),
        "recorded_transparent_minus_opaque_mb": ref0 - ref1})


if __name__ == "__main__":
    main(ARGS)
