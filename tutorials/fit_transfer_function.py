"""Tutorial: recover a transfer function from images of a scalar tet mesh
(DiffDVR Sec. 5.2, on tets).

The scalar field and the cameras are known; the transfer function that
colored the images is not. ``optimize="tf"`` makes its R texels (linear RGB
and extinction at the texel centres, piecewise linear between them) the
unknowns of the usual fit: ``mi.traverse`` exposes them as
``volume.tf_color`` and ``volume.tf_opacity``, ``tetvr`` post-classifies the
scalar along every ray and differentiates the texel reads, and DiffDVR's
smoothing prior (Eq. 12, weight ``tf_smoothing``) keeps texels that no image
shows from wandering.

Steps: render a data set of the mesh under the true function
(:func:`mi_tetvr.recon.synthetic.make_mesh_dataset`), fit from a flat grey
start (:func:`mi_tetvr.recon.pipeline.run`), score held-out views, and plot
the true and fitted functions (``transfer_functions.png``). The fitted one is
``fit/transfer_function.json``. The default mesh is the project's own
(``scenes/meshes/radial_scalar.vtu``, ``scenes/tf_radial.json``); e.g.
``--mesh ../shared/data/tets/bluntfin/bluntfin_tets.vtu --scalar Density
--tf scenes/tf_bluntfin.json`` runs it on real CFD data.

Run it with::

    python tutorials/fit_transfer_function.py
    python tutorials/fit_transfer_function.py --res 128 --steps 300 --out out/tf
"""
from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import mitsuba as mi

ROOT = Path(__file__).resolve().parents[1]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--mesh", help="scalar tet mesh (default: scenes/meshes/radial_scalar.vtu)")
    p.add_argument("--scalar", help="its scalar point array (default: the only one)")
    p.add_argument("--tf", default=str(ROOT / "scenes" / "tf_radial.json"),
                   help="the true transfer function")
    p.add_argument("--views", type=int, default=8, help="training views (default 8)")
    p.add_argument("--res", type=int, default=64, help="image size (default 64)")
    p.add_argument("--texels", type=int, default=64, help="R (default 64)")
    p.add_argument("--steps", type=int, default=200, help="optimizer steps (default 200)")
    p.add_argument("--out", default="out/fit_tf")
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def main(argv=None):
    a = parse_args(argv)
    mi.set_variant(a.variant)
    import mi_tetvr  # noqa: F401  (registers the plugins)
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.pipeline import run
    from mi_tetvr.recon.plots import plot_transfer_functions
    from mi_tetvr.recon.synthetic import make_mesh_dataset
    from mi_tetvr.transfer import TransferFunction, read_transfer_function
    out = Path(a.out)
    from mi_tetvr.mesh.scenes import scalar_mesh
    mesh = Path(a.mesh) if a.mesh else scalar_mesh()
    # 1. the images: the mesh post-classified by the true function (opacity per mesh radius)
    info = make_mesh_dataset(mesh, a.tf, out / "data", views=a.views, test_views=4, res=a.res,
                             scalar=a.scalar, opacity_scale=4.0, progress=not a.quiet)
    data = load_dataset(out / "data")
    # 2. the fit: only the texels move; the mesh and its scalar are the init file's
    cfg = FitConfig(init=str(mesh), optimize="tf", scalar=info["scalar"],
                    tf_resolution=a.texels, iterations=a.steps)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        metrics = run(data, out / "fit", cfg, resume=False, progress=not a.quiet,
                      log=lambda *x: None)
    seconds = time.perf_counter() - t0
    # 3. the true function in the fit's units (extinction per world unit) beside the fitted
    given = read_transfer_function(a.tf)
    truth = TransferFunction(given.color_positions, given.colors, given.opacity_positions,
                             given.opacities * info["extinction_scale"])
    fitted = read_transfer_function(out / "fit" / "transfer_function.json")
    plot_transfer_functions(out / "transfer_functions.png", {"true": truth, "fitted": fitted},
                            info["value_range"])
    result = {"psnr": metrics["mean"]["psnr"], "ssim": metrics["mean"]["ssim"],
              "seconds": seconds, "steps": metrics["step"], "truth": truth, "fitted": fitted,
              "files": {"tf": str(out / "fit" / "transfer_function.json"),
                        "plot": str(out / "transfer_functions.png")}}
    if not a.quiet:
        print(f"{mesh.name} '{info['scalar']}': {a.texels} texels fitted in {seconds:.0f} s "
              f"({metrics['step']} steps): held-out PSNR {result['psnr']:.2f} dB, SSIM "
              f"{result['ssim']:.4f} (sRGB) -> {out / 'transfer_functions.png'}")
    return result


if __name__ == "__main__":
    main()
