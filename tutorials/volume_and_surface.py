"""Tutorial: fit a volume's colors and the texture of a wall behind it, together.

A tet volume stands in front of a textured wall, lit by a point light. The
``tetvr`` integrator integrates the volume along each camera ray up to the
wall and adds the wall's radiance, rendered by its nested integrator
(``prb``, named ``surfaces``), seen through the volume's transmittance::

    L = C_volume[0, t_wall] + T(t_wall) L_wall

1. The *target* scene has colored blobs in the volume and a checkerboard
   texture (a ``bitmap`` reflectance) on the wall; it is rendered from a few
   cameras in front of the wall.
2. The fit starts from a grey volume and a grey wall (the volume's opacity
   is known and kept), and optimizes ``volume.vertex_color`` and
   ``wall.bsdf.reflectance.data`` with one ``mi.ad.Adam``: each step renders
   the views with ``mi.render(scene, params)`` and back-propagates an L2
   loss with ``dr.backward``. The volume's gradients come from ``tetvr``'s
   adjoint, the wall's from ``prb`` through the volume (``T`` times its own).
3. ``--out`` gets the loss curve, a target / start / fit comparison, the
   fitted texture and the fitted mesh (``.vtu``, opens in ParaView).

The light is a point light and ``prb`` runs with ``max_depth=2`` (direct
light): the wall's radiance is then exact per ray, so the loss can fall to
the pixel-sampling noise. The volume casts no shadow on the wall (light
transport through the volume is not modelled).

Run it with::

    python tutorials/volume_and_surface.py
    python tutorials/volume_and_surface.py --iters 200 --res 96 --views 6
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
    p.add_argument("--cells", type=int, default=8, help="grid cells per axis (default 8)")
    p.add_argument("--texels", type=int, default=16, help="texture side (default 16)")
    p.add_argument("--views", type=int, default=4, help="training views (default 4)")
    p.add_argument("--res", type=int, default=64, help="image side (default 64)")
    p.add_argument("--spp", type=int, default=2, help="samples per pixel in the fit")
    p.add_argument("--target-spp", type=int, default=16, help="samples of the targets")
    p.add_argument("--iters", type=int, default=120, help="Adam steps (default 120)")
    p.add_argument("--lr", type=float, default=0.05, help="Adam learning rate")
    p.add_argument("--out", default="out/volume_and_surface")
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


WALL_Z = -1.5


def checkerboard(n, squares=4):
    """(n, n, 3) texture: two colors in ``squares`` x ``squares`` squares."""
    i = (np.arange(n) * squares // n)
    mask = (i[:, None] + i[None, :]) % 2 == 0
    return np.where(mask[..., None], [0.85, 0.75, 0.2], [0.15, 0.3, 0.7]).astype(np.float32)


def make_scene(mesh, texture):
    """The volume (arrays of ``mesh``) before the textured wall, a point
    light, ``tetvr`` with ``prb`` for the wall."""
    import mi_tetvr
    V, T, color, opacity = mesh
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "tetvr", "surfaces": {"type": "prb", "max_depth": 2}},
        "volume": mi_tetvr.tetmesh_dict(V, T, color, opacity),
        "wall": {"type": "rectangle",
                 "to_world": mi.ScalarTransform4f().translate([0, 0, WALL_Z]).scale(1.8),
                 "bsdf": {"type": "diffuse", "reflectance": {
                     "type": "bitmap", "data": mi.TensorXf(texture), "raw": True,
                     "filter_type": "nearest"}}},
        "light": {"type": "point", "position": [0.5, 1.5, 3.0],
                  "intensity": {"type": "rgb", "value": 14.0}},
    })


def make_sensor(origin, res, spp):
    return mi.load_dict({
        "type": "perspective", "fov": 40,
        "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=[0, 0, -0.4],
                                                   up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": spp}})


def camera_origins(n, radius=4.0):
    """``n`` cameras in front of the wall, spread over +-35 degrees."""
    az = np.radians(np.linspace(-35, 35, n)) if n > 1 else np.zeros(1)
    el = np.radians(np.where(np.arange(n) % 2 == 0, 12.0, -8.0))
    return [[radius * np.sin(a) * np.cos(e), radius * np.sin(e), radius * np.cos(a) * np.cos(e)]
            for a, e in zip(az, el)]


def save_outputs(out, history, noise_floor, images, texture, mesh):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import mi_tetvr
    files = {"loss_plot": out / "loss.png", "comparison": out / "comparison.png",
             "texture": out / "texture.png", "mesh": out / "volume.vtu"}
    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=120)
    ax.semilogy(history, label="fit")
    ax.axhline(noise_floor, color="grey", ls="--", label="true scene (sampling noise)")
    ax.legend()
    ax.set_xlabel("Adam step")
    ax.set_ylabel("L2 loss over the views")
    ax.set_title("volume colors and wall texture, fitted together")
    fig.tight_layout()
    fig.savefig(files["loss_plot"])
    plt.close(fig)
    srgb = [np.clip(np.array(mi.Bitmap(im).convert(mi.Bitmap.PixelFormat.RGB,
                                                     mi.Struct.Type.Float32, True)), 0, 1)
            for im in images]
    fig, axes = plt.subplots(1, 3, figsize=(9, 3.2), dpi=120)
    for a, im, title in zip(axes, srgb, ("target", "start", "fit")):
        a.imshow(im)
        a.set_title(title)
        a.axis("off")
    fig.tight_layout()
    fig.savefig(files["comparison"])
    plt.close(fig)
    mi.util.write_bitmap(str(files["texture"]), np.clip(texture, 0, 1),
                         write_async=False)   # (written when the function returns)
    V, T, color, opacity = mesh
    mi_tetvr.write_tetmesh(str(files["mesh"]), mi_tetvr.TetMesh(V, T, color, opacity))
    return {k: str(v) for k, v in files.items()}


def main(argv=None):
    a = parse_args(argv)
    mi.set_variant(a.variant)
    import mi_tetvr  # noqa: F401  (registers the plugins)
    from mi_tetvr.mesh.generate import blob_field, grid_mesh
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    V, T = grid_mesh(a.cells, lo=(-0.8, -0.8, -0.8), hi=(0.8, 0.8, 0.8), jitter=0.1)
    color_ref, opacity = blob_field(V / 0.8, scale=1.5)
    tex_ref = checkerboard(a.texels)
    grey_color = np.full_like(color_ref, 0.5)
    grey_tex = np.full_like(tex_ref, 0.5)

    origins = camera_origins(a.views)
    target_scene = make_scene((V, T, color_ref, opacity), tex_ref)
    targets = [mi.render(target_scene, sensor=make_sensor(o, a.res, a.target_spp), seed=7 + i)
               for i, o in enumerate(origins)]
    sensors = [make_sensor(o, a.res, a.spp) for o in origins]

    def loss_of(img, ref):
        return dr.mean(dr.square(img[..., :3] - ref[..., :3]), axis=None)
    # The loss of the true scene itself at the fit's samples per pixel: the
    # pixel-sampling noise (silhouettes, texture edges) the fit cannot go below.
    noise_floor = float(np.mean([loss_of(mi.render(target_scene, sensor=s, seed=1000 + i), ref)
                                 .array[0] for i, (s, ref) in enumerate(zip(sensors, targets))]))

    scene = make_scene((V, T, grey_color, opacity), grey_tex)
    params = mi.traverse(scene)
    keys = ["volume.vertex_color", "wall.bsdf.reflectance.data"]
    opt = mi.ad.Adam(lr=a.lr)
    for k in keys:
        opt[k] = params[k]
    params.update(opt)
    start = mi.render(scene, sensor=sensors[0], spp=a.target_spp, seed=1)

    history, t0 = [], time.time()
    for it in range(a.iters):
        total = 0.0
        for i, (sensor, ref) in enumerate(zip(sensors, targets)):
            img = mi.render(scene, params, sensor=sensor, seed=it * len(sensors) + i)
            loss = loss_of(img, ref)
            dr.backward(loss)
            total += float(loss.array[0])
        opt.step()
        for k in keys:
            opt[k] = dr.clip(opt[k], 0.0, 1.0)
        params.update(opt)
        history.append(total / len(sensors))
        if not a.quiet and (it % 20 == 0 or it == a.iters - 1):
            print(f"step {it:4d}  loss {history[-1]:.3e}  ({time.time() - t0:.1f} s)")

    fit = mi.render(scene, sensor=sensors[0], spp=a.target_spp, seed=1)
    color_fit = np.array(params["volume.vertex_color"], np.float64).reshape(-1, 3)
    tex_fit = np.array(params["wall.bsdf.reflectance.data"], np.float64)
    files = save_outputs(out, history, noise_floor, [targets[0], start, fit], tex_fit,
                         (V, T, color_fit, opacity))
    result = {
        "loss": history, "initial_loss": history[0], "final_loss": history[-1],
        "noise_floor": noise_floor,
        "color_ref": color_ref, "color_fit": color_fit, "opacity": opacity,
        "texture_error": (float(np.abs(grey_tex - tex_ref).mean()),
                          float(np.abs(tex_fit - tex_ref).mean())),
        # weighted by the opacity: where a vertex's color shows
        "color_error": (float(np.average(np.abs(grey_color - color_ref).mean(1), weights=opacity)),
                        float(np.average(np.abs(color_fit - color_ref).mean(1), weights=opacity))),
        "files": files,
    }
    if not a.quiet:
        (t0, t1), (c0, c1) = result["texture_error"], result["color_error"]
        print(f"loss {history[0]:.3e} -> {history[-1]:.3e} "
              f"({history[-1] / history[0]:.3f} of the start, {history[-1] / noise_floor:.2f}x "
              f"the true scene's sampling noise); texture mean |error| "
              f"{t0:.3f} -> {t1:.3f}; volume color mean |error| (opacity-weighted) "
              f"{c0:.3f} -> {c1:.3f}; outputs in {out}")
    return result


if __name__ == "__main__":
    main()
