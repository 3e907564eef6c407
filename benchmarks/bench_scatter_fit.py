"""Inverse rendering of a scattering volume: a tet mesh (``tetpath``, refined
where the density is) against Mitsuba's own ``prbvolpath`` on a grid with as
many unknowns, in equal time.

The data: a smoke-like density (a few soft blobs, peak extinction
``--peak``) with an albedo that varies across the volume, rendered by
Mitsuba's ``volpath`` on a fine ``gridvolume`` (``--truth-res``^3, an
independent renderer), under a point light and a dim sky, from ``--views``
cameras around it; every fourth view is held out. As Mitsuba's volume
optimization tutorial, both methods start from a constant medium and learn
the extinction and the albedo (RGB) from the images by Adam on an L2 image
loss, coarse to fine:

* tets: a grid of ``--cells``^3 cells, then, at a third and at two thirds of
  the time, its vertices of the largest extinction (``--fraction``) split
  (:func:`mi_tetvr.mesh.refine.split_vertices`, values interpolated, put
  into the same shape by ``set_mesh``: no kernel compiled again; Adam
  starts afresh, as Mitsuba's tutorial does when it upsamples its grid);
* grid: ``N / 2``^3 voxels, upsampled to ``N``^3 at a third of the time,
  where ``N^3`` is the tet mesh's final vertex count (the same unknowns).

Scores, by one function on the same arrays: PSNR and SSIM of the held-out
views (sRGB in [0, 1]; each method's result rendered by its own renderer at
``--eval-spp``), and the extinction's error at a lattice of points inside
the volume (RMSE, and PSNR over the true range).

Usage::

    python benchmarks/bench_scatter_fit.py                 # 60 s each
    python benchmarks/bench_scatter_fit.py --quick         # a smoke run
"""
from __future__ import annotations

import time

from common import header, make_parser, write_json


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=None, quick="--budget 6 --res 16 --views 8")
    p.add_argument("--budget", type=float, default=60.0,
                   help="seconds of optimization per method (default 60)")
    p.add_argument("--res", type=int, default=40, help="image width = height (default 40)")
    p.add_argument("--views", type=int, default=16, help="cameras (default 16; 1 in 4 held out)")
    p.add_argument("--cells", type=int, default=6, help="the tet grid's cells at first (6)")
    p.add_argument("--fraction", type=float, default=0.15,
                   help="fraction of the vertices split at each refinement (default 0.15)")
    p.add_argument("--spp", type=int, default=4, help="samples per pixel in a step (4)")
    p.add_argument("--lr", type=float, default=0.05, help="Adam's learning rate (0.05)")
    p.add_argument("--peak", type=float, default=8.0, help="peak extinction (default 8)")
    p.add_argument("--truth-res", type=int, default=48, help="the true grid's size (48)")
    p.add_argument("--eval-spp", type=int, default=256, help="samples of the scored renders")
    p.add_argument("--out", default=None, help="write the held-out renders here (PNG)")
    a = p.parse_args(argv)
    if a.quick:
        a.budget, a.res, a.views, a.eval_spp, a.truth_res = 6.0, 16, 8, 32, 24
    return a


ARGS = parse_args()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402
from mi_tetvr.mesh.generate import grid_mesh  # noqa: E402
from mi_tetvr.mesh.refine import split_vertices  # noqa: E402
from mi_tetvr.mesh.sample import sample_field  # noqa: E402
from mi_tetvr.color import linear_to_srgb  # noqa: E402
from mi_tetvr.recon.metrics import psnr, ssim  # noqa: E402

CENTERS = np.array([[0.35, 0.05, 0.0], [-0.3, 0.3, 0.15], [0.0, -0.35, -0.2]])


def true_extinction(p, peak):
    w = np.exp(-np.sum((p[:, None, :] - CENTERS[None]) ** 2, -1) / 0.06)
    return peak * w.sum(1)


def true_albedo(p):
    t = np.clip(0.5 + 0.5 * p[:, 0:1], 0.0, 1.0)
    return (1 - t) * np.array([0.95, 0.9, 0.6]) + t * np.array([0.5, 0.75, 0.95])


def lattice(n):
    """Mitsuba's voxel centres of an ``n^3`` grid on the cube, (n^3, 3) in
    its (z, y, x) storage order."""
    c = -1.0 + (np.arange(n) + 0.5) * 2.0 / n
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()])


def grid_medium(sigma, albedo, n):
    def volume(values, channels):
        data = np.asarray(values, np.float32).reshape(n, n, n, channels)
        return {"type": "gridvolume", "data": mi.TensorXf(np.ascontiguousarray(data)),
                "filter_type": "trilinear",
                "to_world": mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)}
    return {"type": "heterogeneous", "sigma_t": volume(sigma, 1), "albedo": volume(albedo, 3)}


def sensors(a):
    out = []
    for k in range(a.views):
        phi = 2 * np.pi * k / a.views
        elev = 0.6 * np.sin(3 * phi)
        eye = 4.0 * np.array([np.cos(phi) * np.cos(elev), np.sin(elev), np.sin(phi) * np.cos(elev)])
        out.append(mi.load_dict({
            "type": "perspective", "fov": 40,
            "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(), target=[0, 0, 0],
                                                       up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": a.res, "height": a.res,
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent"}}))
    return out


LIGHTS = {"light": {"type": "point", "position": [2.5, 3.0, 1.5],
                    "intensity": {"type": "rgb", "value": 30.0}},
          "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.08, 0.1, 0.14]}}}


def grid_scene(sigma, albedo, n, integrator):
    return mi.load_dict({"type": "scene", **LIGHTS,
                         "integrator": {"type": integrator, "max_depth": 8},
                         "cube": {"type": "cube", "bsdf": {"type": "null"},
                                  "interior": grid_medium(sigma, albedo, n)}})


def tet_group(V, T, sigma, albedo, integrator="tetpath"):
    return mi.load_dict({"type": "scene", **LIGHTS,
                         "integrator": {"type": integrator, "max_depth": 8},
                         "vol": mi_tetvr.tetmesh_dict(V, T, opacity=sigma, albedo=albedo)})


def adam(scene, keys, lr):
    """Mitsuba's Adam on ``keys`` of ``scene`` (a fresh state)."""
    params = mi.traverse(scene)
    opt = mi.ad.Adam(lr=lr)
    for k in keys:
        opt[k] = params[k]
    params.update(opt)
    return params, opt


def fit(scene, keys, train, targets, a, budget, refine):
    """Adam on ``keys`` of ``scene`` for ``budget`` seconds; at a third and
    at two thirds, ``refine(stage, scene, values)`` (``values``: the
    parameters as numpy) returns the next stage's ``(scene, keys)`` (Adam
    then starts afresh)."""
    params, opt = adam(scene, keys, a.lr)
    start, step, stage = time.perf_counter(), 0, 0
    losses = []
    while (elapsed := time.perf_counter() - start) < budget:
        if stage < 2 and elapsed > budget * (stage + 1) / 3:
            stage += 1
            values = {k: np.asarray(params[k], np.float64) for k in keys}
            del params, opt
            scene, keys = refine(stage, scene, values)
            params, opt = adam(scene, keys, a.lr)
        i = step % len(train)
        img = mi.render(scene, params, sensor=train[i], spp=a.spp, seed=step)
        loss = dr.mean(dr.square(img[..., :3] - targets[i]), axis=None)
        dr.backward(loss)
        opt.step()
        for k in keys:
            opt[k] = dr.clip(opt[k], 0.0, 1.0) if "albedo" in k else dr.maximum(opt[k], 0.0)
        params.update(opt)
        losses.append(float(loss.array[0]))
        step += 1
    return scene, step, losses


def picture(rgb):
    """sRGB in [0, 1] of a linear RGB render (what the scores compare)."""
    return linear_to_srgb(np.clip(np.asarray(rgb, np.float64), 0.0, 1.0))


def scores(renders, truth):
    out = {"psnr": [], "ssim": []}
    for x, y in zip(renders, truth):
        x, y = picture(x), picture(y)
        out["psnr"].append(psnr(float(np.mean((x - y) ** 2))))
        out["ssim"].append(ssim(x, y))
    return {k: float(np.mean(v)) for k, v in out.items()}


def main(a):
    info = header("scattering inverse rendering: tet mesh (tetpath) vs grid (prbvolpath)")
    cams = sensors(a)
    test = [c for k, c in enumerate(cams) if k % 4 == 3]
    train = [c for k, c in enumerate(cams) if k % 4 != 3]
    P = lattice(a.truth_res)
    truth_scene = grid_scene(true_extinction(P, a.peak), true_albedo(P), a.truth_res, "volpath")
    t0 = time.perf_counter()
    targets = [mi.TensorXf(np.ascontiguousarray(np.asarray(mi.render(
        truth_scene, sensor=c, spp=4 * a.eval_spp, seed=100 + k))[..., :3]))
               for k, c in enumerate(train)]
    truth_test = [np.asarray(mi.render(truth_scene, sensor=c, spp=4 * a.eval_spp,
                                       seed=200 + k))[..., :3] for k, c in enumerate(test)]
    print(f"data: {len(train)} training and {len(test)} held-out views at {a.res}x{a.res} "
          f"(volpath on a {a.truth_res}^3 grid, {time.perf_counter() - t0:.1f} s)")
    results = {}

    # -- tets, refined where the extinction is largest ----------------------
    V, T = grid_mesh((a.cells,) * 3)
    n0 = len(V)
    keys = ["vol.vertex_opacity", "vol.vertex_albedo"]
    mesh = {"V": V, "T": T}
    scene = tet_group(V, T, np.full(len(V), 0.5), np.full((len(V), 3), 0.5))

    def refine(stage, scene, values):
        sigma = values[keys[0]]
        albedo = values[keys[1]].reshape(-1, 3)
        sel = np.argsort(-sigma)[:max(1, int(a.fraction * len(sigma)))]
        res = split_vertices(mesh["V"], mesh["T"], sel, {"sigma": sigma, "albedo": albedo})
        mesh["V"], mesh["T"] = res.vertices, res.tets
        print(f"  refined: {len(res.vertices):,} vertices, {len(res.tets):,} tets")
        # the refined mesh in the same shape: the kernels compiled already serve it
        params = mi.traverse(scene)
        next(s for s in scene.shapes() if s.id() == "vol").set_mesh(
            params, res.vertices, res.tets, {"vertex_opacity": res.point_data["sigma"],
                                             "vertex_albedo": res.point_data["albedo"],
                                             "vertex_emission": np.zeros((len(res.vertices), 3))})
        params.update()
        return scene, keys

    scene, steps, losses = fit(scene, keys, train, targets, a, a.budget, refine)
    params = mi.traverse(scene)
    sigma_t = np.asarray(params[keys[0]], np.float64)
    n_tet = len(mesh["V"])
    print(f"tets: {steps} steps in {a.budget:.0f} s; {n0} -> {n_tet:,} vertices "
          f"({len(mesh['T']):,} tets); last loss {np.mean(losses[-10:]):.3e}")
    renders = [np.asarray(mi.render(scene, sensor=c, spp=a.eval_spp, seed=300 + k))[..., :3]
               for k, c in enumerate(test)]
    results["tets"] = {"steps": steps, "vertices": n_tet, "unknowns": 4 * n_tet,
                       **scores(renders, truth_test)}
    tet_renders = renders

    # -- Mitsuba's grid, the same unknowns ----------------------------------
    N = max(2, int(round(n_tet ** (1 / 3))))
    half = max(2, N // 2)
    keys_g = ["cube.interior_medium.sigma_t.data", "cube.interior_medium.albedo.data"]
    scene_g = grid_scene(np.full(half ** 3, 0.5), np.full((half ** 3, 3), 0.5), half,
                         "prbvolpath")

    def upsample(stage, scene, values):
        # Mitsuba's tutorial: the grid's data upsampled in place, the same scene
        if stage == 1:
            from scipy.ndimage import zoom
            params = mi.traverse(scene)
            for k, c in zip(keys_g, (1, 3)):
                up = zoom(values[k].reshape(half, half, half, c), (N / half,) * 3 + (1,),
                          order=1, mode="nearest")
                params[k] = mi.TensorXf(np.ascontiguousarray(up, np.float32))
            params.update()
            print(f"  upsampled: {N}^3 voxels")
        return scene, keys_g

    scene_g, steps_g, losses_g = fit(scene_g, keys_g, train, targets, a, a.budget, upsample)
    params = mi.traverse(scene_g)
    sigma_g = np.asarray(params[keys_g[0]], np.float64).reshape(N, N, N)
    albedo_g = np.asarray(params[keys_g[1]], np.float64).reshape(-1, 3)
    print(f"grid: {steps_g} steps in {a.budget:.0f} s; {N}^3 = {N ** 3:,} voxels; "
          f"last loss {np.mean(losses_g[-10:]):.3e}")
    eval_g = grid_scene(sigma_g, albedo_g, N, "volpath")
    renders_g = [np.asarray(mi.render(eval_g, sensor=c, spp=a.eval_spp, seed=300 + k))[..., :3]
                 for k, c in enumerate(test)]
    results["grid"] = {"steps": steps_g, "voxels": N ** 3, "unknowns": 4 * N ** 3,
                       **scores(renders_g, truth_test)}

    # -- the extinction's error inside the volume ---------------------------
    probe = lattice(24) * 0.95
    truth = true_extinction(probe, a.peak)
    est_t = sample_field(mesh["V"], mesh["T"], sigma_t, probe)
    from scipy.interpolate import RegularGridInterpolator
    c = -1.0 + (np.arange(N) + 0.5) * 2.0 / N
    est_g = RegularGridInterpolator((c, c, c), sigma_g, bounds_error=False, fill_value=None)(
        np.clip(probe[:, ::-1], c[0], c[-1]))
    rng_ = truth.max() - truth.min()
    for name, est in (("tets", est_t), ("grid", est_g)):
        rmse = float(np.sqrt(np.mean((est - truth) ** 2)))
        results[name]["volume_rmse"] = rmse
        results[name]["volume_psnr"] = float(20 * np.log10(rng_ / rmse))
    print(f"\n{'method':>6} {'unknowns':>9} {'steps':>6} {'held-out PSNR':>14} {'SSIM':>6} "
          f"{'extinction RMSE':>16} {'volume PSNR':>12}")
    for name in ("tets", "grid"):
        r = results[name]
        print(f"{name:>6} {r['unknowns']:>9,} {r['steps']:>6} {r['psnr']:>14.2f} "
              f"{r['ssim']:>6.3f} {r['volume_rmse']:>16.3f} {r['volume_psnr']:>12.2f}")
    if a.out:
        from pathlib import Path
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        for k, (x, y, z) in enumerate(zip(truth_test, tet_renders, renders_g)):
            row = np.concatenate([np.clip(v, 0, 1) for v in (x, y, z)], axis=1)
            mi.util.write_bitmap(str(out / f"heldout_{k}.png"), row.astype(np.float32),
                                 write_async=False)
        print(f"held-out views (truth | tets | grid) in {out}")
    write_json(a, info, results)


if __name__ == "__main__":
    main(ARGS)
