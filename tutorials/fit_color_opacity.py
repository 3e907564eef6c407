"""Tutorial: fit the per-vertex color and opacity of a tet mesh to images.

This is inverse volume rendering in the ordinary Mitsuba 3 way, with the
``tetmesh`` shape and the ``tetvr`` integrator of ``mi_tetvr``:

1. A *target* volume (a tet mesh with spatially varying color and opacity) is
   rendered from a few cameras around it. Every image has four channels:
   R, G, B and the integrator's ``alpha`` AOV (accumulated opacity 1 - T).
2. A second scene has the *same* mesh but a constant grey color and a low
   constant opacity: this is where the optimization starts.
3. ``mi.traverse`` exposes ``<id>.vertex_color`` and ``<id>.vertex_opacity``;
   an ``mi.ad.Adam`` optimizer owns them, and each iteration renders every
   view with ``mi.render(scene, params, ...)``, compares it to the target
   (L2 over RGBA), back-propagates with ``dr.backward`` and takes a step.
4. The results go to ``--out``: the loss curve, a target / initial / fitted
   comparison and the fitted mesh as ``.vtu`` (opens in ParaView).

Run it with::

    python tutorials/fit_color_opacity.py                 # defaults below
    python tutorials/fit_color_opacity.py --iters 200 --res 96 --views 8

It prints the initial and final loss and their ratio, and also a *noise floor*:
the loss of the true volume itself against the target images. The fitted loss
cannot go much below it (see "Sampling" below).

Sampling
--------
With a box reconstruction filter and the ``independent`` sampler, each of a
pixel's ``spp`` rays goes through a random point of the pixel, so a pixel is a
Monte Carlo estimate of the pixel's average. The target images are rendered
once with many samples (``--target-spp``, default 16), i.e. close to the
anti-aliased pixel averages. During the fit every render uses few samples
(``--spp``, default 2) and a fresh seed, as usual in Mitsuba optimizations.
``tetvr``'s derivative pass reuses the rays of the image it differentiates,
so each step's gradient is that of the loss of the image just rendered; over
the fresh seeds of the steps the fit minimizes the expected loss of a sampled
image against the target (as NeRF-style training does), which is the loss of
the pixel averages plus the images' sampling variance. The price is a small
noise floor in the measured loss, mostly from pixels on the silhouette of the
mesh, where alpha jumps.

(The ``tetvr`` integrator itself is deterministic: a given ray always gets the
same value. Rendering target and fit with ``spp=1`` and one fixed seed would
let the loss go to ~0, but it would fit 64x64 particular points rather than
pixels.)
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
from tqdm import trange

import drjit as dr
import mitsuba as mi

#: The id of the tet mesh in both scenes; parameters are '<id>.vertex_color' etc.
MESH_ID = "volume"
KEY_COLOR = f"{MESH_ID}.vertex_color"
KEY_OPACITY = f"{MESH_ID}.vertex_opacity"


# ---------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------

def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description="Fit per-vertex color and opacity of a tet mesh to multi-view "
                    "RGBA images (mi_tetvr tutorial).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--cells", type=int, default=8,
                   help="grid cells per axis of the tet mesh (6 tets per cell) over [-1, 1]^3")
    p.add_argument("--jitter", type=float, default=0.25,
                   help="random displacement of interior vertices (fraction of a cell)")
    p.add_argument("--res", type=int, default=64, help="image width and height in pixels")
    p.add_argument("--views", type=int, default=6, help="number of cameras")
    p.add_argument("--spp", type=int, default=2, help="samples per pixel while fitting")
    p.add_argument("--target-spp", type=int, default=16,
                   help="samples per pixel of the target images")
    p.add_argument("--iters", type=int, default=60, help="optimization steps")
    p.add_argument("--lr", type=float, default=0.05, help="Adam learning rate of the color")
    p.add_argument("--lr-opacity", type=float, default=0.15,
                   help="Adam learning rate of the opacity (extinction per unit length, "
                        "which spans a larger range than the color)")
    p.add_argument("--init-color", type=float, default=0.5, help="initial grey level")
    p.add_argument("--init-opacity", type=float, default=0.1, help="initial opacity")
    p.add_argument("--loss", choices=("l2", "l1"), default="l2", help="image loss")
    p.add_argument("--out", type=Path, default=Path("out/tutorial_fit"),
                   help="output folder")
    p.add_argument("--variant", default="llvm_ad_rgb",
                   help="Mitsuba variant (an autodiff RGB one: llvm_ad_rgb or cuda_ad_rgb)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    if args.iters < 1 or args.views < 1 or args.res < 1 or args.spp < 1:
        p.error("--iters, --views, --res and --spp must be >= 1")
    return args


# ---------------------------------------------------------------------------
# The target volume
# ---------------------------------------------------------------------------

def target_field(vertices):
    """Color and opacity of the target volume at the vertices.

    The color varies smoothly everywhere (in [0.1, 0.9], linear RGB); the
    opacity is a low background plus the soft blobs of
    :func:`mi_tetvr.mesh.generate.blob_field`, so that the whole volume is
    semi-transparent and every vertex's color shows in some image.
    """
    from mi_tetvr.mesh.generate import blob_field
    x, y, z = np.asarray(vertices, float).T
    color = 0.5 + 0.4 * np.stack([np.sin(2.0 * x + 1.0),
                                  np.sin(2.0 * y - 0.5) * np.cos(1.5 * z),
                                  np.cos(2.0 * z + x)], axis=1)
    _, blobs = blob_field(vertices, scale=3.0)
    opacity = 0.4 + blobs
    return color, opacity


# ---------------------------------------------------------------------------
# Scenes and cameras
# ---------------------------------------------------------------------------

def camera_origins(n, radius=4.5):
    """``n`` camera positions on a sphere around the origin: evenly spread in
    azimuth, alternately above and below the equator so that the top and the
    bottom of the volume are seen too."""
    out = []
    for i in range(n):
        az = math.radians(15.0 + 360.0 * i / n)
        el = math.radians(30.0 if i % 2 == 0 else -20.0)
        out.append([radius * math.cos(el) * math.sin(az), radius * math.sin(el),
                    radius * math.cos(el) * math.cos(az)])
    return out


def make_sensor(origin, res, spp):
    """A perspective camera looking at the origin.

    The film is an ``hdrfilm`` with a box filter (each ray counts only in its
    own pixel). Its own pixel format is RGB; the ``tetvr`` integrator adds the
    ``alpha`` AOV, so ``mi.render`` returns (res, res, 4) tensors: R, G, B, alpha.
    """
    return mi.load_dict({
        "type": "perspective",
        "fov": 45.0,
        "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=[0, 0, 0],
                                                   up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": res, "height": res,
                 "pixel_format": "rgb", "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": spp},
    })


def make_scene(vertices, tets, color, opacity):
    """A scene with one tet mesh and the ``tetvr`` integrator. No emitter: the
    background is black, so RGB is the emitted light alone and alpha carries
    the opacity. (The sensors are kept outside the scene and passed to
    ``mi.render``; the scene then gets a default sensor we never use.)"""
    import mi_tetvr
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "tetvr"},
        MESH_ID: mi_tetvr.tetmesh_dict(vertices, tets, color, opacity),
    })


# ---------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------

def image_loss(img, ref, kind="l2"):
    """Mean over pixels and the four channels (R, G, B, alpha)."""
    diff = img - ref
    return dr.mean(dr.square(diff) if kind == "l2" else dr.abs(diff), axis=None)


def to_srgb(img):
    """(H, W, 4) linear RGBA tensor -> (H, W, 3) uint8 sRGB array (RGB only)."""
    rgb = mi.TensorXf(np.ascontiguousarray(np.array(img)[..., :3]))
    return np.array(mi.util.convert_to_bitmap(rgb))


def save_loss_plot(path, history, noise_floor):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=120)
    ax.semilogy(np.arange(len(history)), history, label="loss (fit)")
    ax.axhline(noise_floor, color="grey", ls="--", lw=1,
               label="noise floor (true volume)")
    ax.set_xlabel("iteration")
    ax.set_ylabel("image loss (RGBA)")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def save_comparison(path, target, initial, fitted):
    """Target / initial / fitted of one view: sRGB color on top, alpha below."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 3, figsize=(7.5, 5.2), dpi=120)
    for col, (title, img) in enumerate((("target", target), ("initial", initial),
                                        ("fitted", fitted))):
        axes[0, col].imshow(to_srgb(img), interpolation="nearest")
        axes[0, col].set_title(title)
        axes[1, col].imshow(np.array(img)[..., 3], cmap="gray", vmin=0, vmax=1,
                            interpolation="nearest")
    axes[0, 0].set_ylabel("color (sRGB)")
    axes[1, 0].set_ylabel("alpha")
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# ---------------------------------------------------------------------------
# The tutorial
# ---------------------------------------------------------------------------

def main(argv=None):
    args = parse_args(argv)
    t_start = time.perf_counter()

    # The variant must be set before mi_tetvr is imported (importing it
    # registers the plugins with the current variant). Keep an already set
    # variant when it is the requested one (e.g. inside the test suite).
    if mi.variant() != args.variant:
        mi.set_variant(args.variant)
    import mi_tetvr
    from mi_tetvr.mesh.generate import grid_mesh
    mi_tetvr.register()

    # -- 1. The target --------------------------------------------------------
    # A jittered grid of tets over [-1, 1]^3; the geometry is shared by the
    # target and the fit, only color and opacity are unknown.
    vertices, tets = grid_mesh(args.cells, jitter=args.jitter, seed=0)
    color_ref, opacity_ref = target_field(vertices)
    n = len(vertices)
    print(f"mesh: {n} vertices, {len(tets)} tets; {args.views} views of "
          f"{args.res}x{args.res} px")

    sensors = [make_sensor(o, args.res, args.spp) for o in camera_origins(args.views)]
    scene_ref = make_scene(vertices, tets, color_ref, opacity_ref)
    # Seed 0 for the targets; the fit uses seeds >= 1.
    targets = [mi.render(scene_ref, sensor=s, spp=args.target_spp, seed=0) for s in sensors]
    assert targets[0].shape == (args.res, args.res, 4), targets[0].shape

    # The noise floor: the true volume itself, rendered like the fit renders
    # (spp = --spp, other seeds), against the targets.
    noise_floor = float(np.mean([
        image_loss(mi.render(scene_ref, sensor=s, spp=args.spp, seed=10_000 + i), t,
                   args.loss).array[0]
        for i, (s, t) in enumerate(zip(sensors, targets))]))

    # -- 2. The initial scene -------------------------------------------------
    scene = make_scene(vertices, tets, np.full((n, 3), args.init_color),
                       np.full(n, args.init_opacity))
    initial_view = mi.render(scene, sensor=sensors[0], spp=args.target_spp, seed=0)

    # -- 3. The optimization --------------------------------------------------
    params = mi.traverse(scene)
    opt = mi.ad.Adam(lr=args.lr)
    opt[KEY_COLOR] = params[KEY_COLOR]
    opt[KEY_OPACITY] = params[KEY_OPACITY]
    opt.set_learning_rate({KEY_OPACITY: args.lr_opacity})
    params.update(opt)

    history = []
    sensitivity = np.ones(n)
    seen = np.ones(n, bool)
    pbar = trange(args.iters, disable=args.quiet, desc="fit", unit="it")
    for it in pbar:
        total = 0.0
        for v, (sensor, target) in enumerate(zip(sensors, targets)):
            # A fresh seed for every render (see "Sampling" above).
            img = mi.render(scene, params, sensor=sensor, spp=args.spp,
                            seed=1 + it * args.views + v)
            loss = image_loss(img, target, args.loss) / len(sensors)
            # Gradients of all views accumulate on the parameters.
            dr.backward(loss)
            total += float(loss.array[0])
        history.append(total)
        if not math.isfinite(total):
            raise FloatingPointError(f"the loss became {total} at iteration {it}")
        if it == 0:
            # Vertices whose color influences some pixel of some view.
            sensitivity = np.abs(np.array(dr.grad(opt[KEY_COLOR]))).reshape(n, 3).sum(1)
            seen = sensitivity > 0
        opt.step()
        # Keep the parameters physical: color in [0, 1], opacity >= 0.
        opt[KEY_COLOR] = dr.clip(opt[KEY_COLOR], 0.0, 1.0)
        opt[KEY_OPACITY] = dr.maximum(opt[KEY_OPACITY], 0.0)
        params.update(opt)
        pbar.set_postfix(loss=f"{total:.3e}")

    # The loss after the last step, measured like the others.
    with dr.suspend_grad():
        final_loss = float(np.mean([
            image_loss(mi.render(scene, sensor=s, spp=args.spp,
                                 seed=1 + args.iters * args.views + v), t,
                       args.loss).array[0]
            for v, (s, t) in enumerate(zip(sensors, targets))]))
        fitted_view = mi.render(scene, sensor=sensors[0], spp=args.target_spp, seed=0)
    color_fit = np.array(params[KEY_COLOR], np.float64).reshape(n, 3)
    opacity_fit = np.array(params[KEY_OPACITY], np.float64).reshape(n)

    # How far the parameters are from the truth. A vertex's color can only
    # be recovered if some camera sees it (its color got a gradient in the
    # first iteration); the error counts those vertices.
    if seen.any():
        color_err_init = float(np.mean(np.abs(args.init_color - color_ref)[seen]))
        color_err_fit = float(np.mean(np.abs(color_fit - color_ref)[seen]))
    else:
        color_err_init = color_err_fit = float("nan")
    opacity_err_init = float(np.mean(np.abs(args.init_opacity - opacity_ref)))
    opacity_err_fit = float(np.mean(np.abs(opacity_fit - opacity_ref)))

    # -- 4. Outputs -----------------------------------------------------------
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"loss_plot": out / "loss.png", "comparison": out / "comparison.png",
             "mesh": out / "fitted.vtu"}
    save_loss_plot(files["loss_plot"], history + [final_loss], noise_floor)
    save_comparison(files["comparison"], targets[0], initial_view, fitted_view)
    mi_tetvr.write_tetmesh(files["mesh"], mi_tetvr.TetMesh(
        vertices, tets, color_fit, opacity_fit,
        point_data={"target_color": color_ref, "target_opacity": opacity_ref}))

    seconds = time.perf_counter() - t_start
    ratio = final_loss / history[0]
    print(f"initial loss {history[0]:.4e}   final loss {final_loss:.4e}   "
          f"ratio {ratio:.4f}   (noise floor {noise_floor:.2e})")
    print(f"color MAE ({np.count_nonzero(seen)} of {n} vertices seen) "
          f"{color_err_init:.4f} -> {color_err_fit:.4f}; "
          f"opacity MAE {opacity_err_init:.4f} -> {opacity_err_fit:.4f}")
    print(f"wrote {', '.join(str(f) for f in files.values())}  ({seconds:.1f} s)")

    return {
        "loss": history, "initial_loss": history[0], "final_loss": final_loss,
        "ratio": ratio, "noise_floor": noise_floor,
        "color_error": (color_err_init, color_err_fit),
        "opacity_error": (opacity_err_init, opacity_err_fit),
        "seen": seen, "color_sensitivity": sensitivity,
        "color_fit": color_fit, "opacity_fit": opacity_fit,
        "color_ref": color_ref, "opacity_ref": opacity_ref,
        "files": files, "seconds": seconds,
    }


if __name__ == "__main__":
    main()
