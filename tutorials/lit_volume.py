"""Tutorial: a scattering volume lit by the scene, and its extinction and
albedo learned from images under known lighting.

A tet volume becomes a participating medium when its ``tetmesh`` has an
``albedo``: its opacity is then its extinction, it scatters light by a
phase function (a Mitsuba phase plugin, here ``hg``), and the ``tetpath``
integrator traces paths through it and the scene's surfaces: the volume is
lit by the scene's emitters, shadows itself and casts a shadow on the floor.

1. The *target* is a smoke-like volume (a few soft blobs, their albedo
   going from warm to cool across it) above a floor, under a point light
   and a dim sky, rendered by ``tetpath`` from a few cameras.
2. The fit starts from a coarse grid of constant extinction and grey albedo
   and learns ``volume.vertex_opacity`` (the extinction) and
   ``volume.vertex_albedo`` with ``mi.ad.Adam``: each step renders a view
   with ``mi.render(scene, params)`` and back-propagates an L2 loss with
   ``dr.backward``; ``tetpath``'s derivative pass replays the paths
   (constant memory per path). Half way, the mesh is refined where the
   extinction is largest (``split_vertices``: every edge at those vertices
   split, the values interpolated) and the fit goes on, as Mitsuba's volume
   tutorial upsamples its grid.
3. ``--out`` gets the loss curve, a target / start / fit comparison and the
   fitted mesh (``.vtu`` with its extinction and albedo, opens in ParaView).

Run it with::

    python tutorials/lit_volume.py
    python tutorials/lit_volume.py --iters 400 --res 64 --views 8
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import drjit as dr
import mitsuba as mi


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cells", type=int, default=5, help="the fit's first grid (default 5^3)")
    p.add_argument("--views", type=int, default=6, help="training views (default 6)")
    p.add_argument("--res", type=int, default=40, help="image side (default 40)")
    p.add_argument("--spp", type=int, default=8, help="samples per pixel in the fit")
    p.add_argument("--target-spp", type=int, default=256, help="samples of the targets")
    p.add_argument("--iters", type=int, default=200, help="Adam steps (default 200)")
    p.add_argument("--lr", type=float, default=0.05, help="Adam learning rate")
    p.add_argument("--fraction", type=float, default=0.2,
                   help="fraction of the vertices split at the refinement (default 0.2)")
    p.add_argument("--out", default="out/lit_volume")
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


CENTERS = np.array([[0.3, 0.05, 0.0], [-0.3, 0.25, 0.15], [0.0, -0.3, -0.2]])


def true_extinction(p):
    """The smoke: three soft blobs (peak extinction about 8 per unit length)."""
    return 8.0 * np.exp(-np.sum((p[:, None, :] - CENTERS[None]) ** 2, -1) / 0.06).sum(1)


def true_albedo(p):
    t = np.clip(0.5 + 0.5 * p[:, 0:1], 0.0, 1.0)
    return (1 - t) * np.array([0.95, 0.85, 0.55]) + t * np.array([0.5, 0.75, 0.95])


def make_scene(V, T, sigma, albedo):
    """The volume (extinction ``sigma``, ``albedo`` per vertex, ``hg`` phase)
    above a floor, a point light, a sky; ``tetpath`` renders it."""
    import mi_tetvr
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "tetpath", "max_depth": 6},
        "volume": mi_tetvr.tetmesh_dict(V, T, opacity=sigma, albedo=albedo,
                                        phase={"type": "hg", "g": 0.3}),
        "floor": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([0, -1.2, 0]).rotate(
                      [1, 0, 0], -90).scale(4.0),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}},
        "light": {"type": "point", "position": [1.5, 3.0, 1.0],
                  "intensity": {"type": "rgb", "value": 25.0}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.06, 0.08, 0.1]}},
    })


def make_sensor(origin, res):
    return mi.load_dict({
        "type": "perspective", "fov": 45,
        "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=[0, -0.3, 0],
                                                   up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
        "sampler": {"type": "independent"}})


def camera_origins(n, radius=3.5):
    """``n`` cameras around the volume, slightly above it."""
    az = 2 * np.pi * np.arange(n) / n
    return [[radius * np.cos(a), 1.0 + 0.4 * np.sin(2 * a), radius * np.sin(a)] for a in az]


def extinction_error(V, T, sigma, probe):
    """RMSE of the fitted extinction at ``probe`` points against the truth."""
    from mi_tetvr.mesh.sample import sample_field
    return float(np.sqrt(np.mean((sample_field(V, T, sigma, probe) - true_extinction(probe))
                                 ** 2)))


def albedo_error(V, T, albedo, start):
    """Mean absolute error of the fitted albedo (the start's, a constant
    ``start``) at the vertices where the true extinction exceeds 0.5 per
    cell: ``(start's, fit's)``."""
    from mi_tetvr.mesh.topology import mean_edge_length
    dense = true_extinction(V) * mean_edge_length(V, T) > 0.5
    truth = true_albedo(V[dense])
    return (float(np.abs(start - truth).mean()), float(np.abs(albedo[dense] - truth).mean()))


def save_outputs(out, history, images, mesh):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import mi_tetvr
    files = {"loss_plot": out / "loss.png", "comparison": out / "comparison.png",
             "mesh": out / "volume.vtu"}
    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=120)
    ax.semilogy(history)
    ax.set_xlabel("Adam step")
    ax.set_ylabel("L2 loss of the step's view")
    ax.set_title("extinction and albedo under known lights")
    fig.tight_layout()
    fig.savefig(files["loss_plot"])
    plt.close(fig)
    srgb = [np.clip(np.array(mi.Bitmap(np.asarray(im)[..., :3]).convert(
        mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, True)), 0, 1) for im in images]
    fig, axes = plt.subplots(1, 3, figsize=(9, 3.2), dpi=120)
    for a, im, title in zip(axes, srgb, ("target", "start", "fit")):
        a.imshow(im)
        a.set_title(title)
        a.axis("off")
    fig.tight_layout()
    fig.savefig(files["comparison"])
    plt.close(fig)
    V, T, sigma, albedo = mesh
    mi_tetvr.write_tetmesh(str(files["mesh"]), mi_tetvr.TetMesh(
        V, T, albedo, sigma, point_data={"albedo": albedo, "extinction": sigma}))
    return {k: str(v) for k, v in files.items()}


def main(argv=None):
    a = parse_args(argv)
    mi.set_variant(a.variant)
    import mi_tetvr  # noqa: F401  (registers the plugins)
    from mi_tetvr.mesh.generate import grid_mesh
    from mi_tetvr.mesh.refine import split_vertices
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    # The target: a finer mesh holding the true fields.
    Vt, Tt = grid_mesh(16)
    target_scene = make_scene(Vt, Tt, true_extinction(Vt), true_albedo(Vt))
    sensors = [make_sensor(o, a.res) for o in camera_origins(a.views)]
    targets = [mi.TensorXf(np.ascontiguousarray(np.asarray(
        mi.render(target_scene, sensor=s, spp=a.target_spp, seed=7 + i))[..., :3]))
        for i, s in enumerate(sensors)]

    V, T = grid_mesh(a.cells)
    sigma, albedo = np.full(len(V), 0.5), np.full((len(V), 3), 0.5)
    probe = np.random.default_rng(0).uniform(-0.9, 0.9, (4000, 3))
    error_start = extinction_error(V, T, sigma, probe)
    keys = ["volume.vertex_opacity", "volume.vertex_albedo"]

    def adam(params):
        opt = mi.ad.Adam(lr=a.lr)
        for k in keys:
            opt[k] = params[k]
        params.update(opt)
        return opt

    scene = make_scene(V, T, sigma, albedo)
    params = mi.traverse(scene)
    opt = adam(params)
    start = mi.render(scene, sensor=sensors[0], spp=a.target_spp, seed=1)
    history, t0 = [], time.time()
    for it in range(a.iters):
        if it == a.iters // 2:
            # Coarse to fine: split the edges at the densest vertices.
            sigma = np.asarray(params[keys[0]], np.float64)
            albedo = np.asarray(params[keys[1]], np.float64).reshape(-1, 3)
            top = np.argsort(-sigma)[:max(1, int(a.fraction * len(sigma)))]
            res = split_vertices(V, T, top, {"sigma": sigma, "albedo": albedo})
            V, T = res.vertices, res.tets
            # The refined mesh goes into the same shape (a new scene would
            # compile its kernels again); Adam starts afresh on it.
            volume = next(s for s in scene.shapes() if s.id() == "volume")
            volume.set_mesh(params, V, T, {
                "vertex_opacity": res.point_data["sigma"],
                "vertex_albedo": res.point_data["albedo"],
                "vertex_emission": np.zeros((len(V), 3))})
            params.update()
            opt = adam(params)
            if not a.quiet:
                print(f"refined: {len(V):,} vertices, {len(T):,} tets")
        i = it % len(sensors)
        img = mi.render(scene, params, sensor=sensors[i], spp=a.spp, seed=it)
        loss = dr.mean(dr.square(img[..., :3] - targets[i]), axis=None)
        dr.backward(loss)
        opt.step()
        opt[keys[0]] = dr.maximum(opt[keys[0]], 0.0)
        opt[keys[1]] = dr.clip(opt[keys[1]], 0.0, 1.0)
        params.update(opt)
        history.append(float(loss.array[0]))
        if not a.quiet and (it % 20 == 0 or it == a.iters - 1):
            print(f"step {it:4d}  loss {history[-1]:.3e}  ({time.time() - t0:.1f} s)")

    sigma = np.asarray(params[keys[0]], np.float64)
    albedo = np.asarray(params[keys[1]], np.float64).reshape(-1, 3)
    fit = mi.render(scene, sensor=sensors[0], spp=a.target_spp, seed=1)
    files = save_outputs(out, history, [targets[0], start, fit], (V, T, sigma, albedo))
    result = {"loss": history, "vertices": len(V),
              "extinction_rmse": (error_start, extinction_error(V, T, sigma, probe)),
              # (where the medium is dense enough to be seen: optical depth 0.5 a cell)
              "albedo_error": albedo_error(V, T, albedo, start=0.5),
              "files": files, "seconds": time.time() - t0}
    if not a.quiet:
        print(f"extinction RMSE {result['extinction_rmse'][0]:.3f} -> "
              f"{result['extinction_rmse'][1]:.3f}; albedo error "
              f"{result['albedo_error'][0]:.3f} -> {result['albedo_error'][1]:.3f}; "
              f"{len(V):,} vertices; outputs in {out}")
    return result


if __name__ == "__main__":
    main()
