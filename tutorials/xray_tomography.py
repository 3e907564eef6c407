"""Tutorial: absorption-only tomography on a tet mesh, beside filtered
back-projection (DiffDVR Sec. 5.3, on tets).

An X-ray image holds the transmittance ``I / I0 = exp(-integral of mu)``
along each ray. With ``model="absorption"`` the ``tetmesh`` has a per-vertex
attenuation ``mu`` and no emission; ``tetvr`` renders ``alpha = 1 - T``
exactly (the attenuation is linear inside a tet), and the fit matches the
optical depths ``-log T`` of the projections: a linear problem, solved by
the default absorption fit as penalized weighted least squares (total
variation at a fixed weight relative to the data's curvature).

Steps: project a grid volume into parallel-beam views over 180 degrees
(:func:`mi_tetvr.grid.xray.make_xray_dataset`: exact line integrals of the
trilinear field, ``.npy`` transmittance images, orthographic cameras), fit
the attenuation with one unknown per voxel (the default fit on the data
set's box, :func:`mi_tetvr.recon.pipeline.run`: the grid's trilinear field,
walked on tets of twice its cells per axis), reconstruct
the same slices by scikit-image's filtered back-projection
(:func:`mi_tetvr.grid.slices.reconstruct_slices`), and compare both with the
truth at the voxels. Writes ``slices.png`` (truth | FBP | tets, the middle
slice) and the fitted ``fit/mesh.vtu`` (point data ``attenuation``).

The default volume is the project's own (``default_volume``, a ring, blobs
and a shell) at ``--size`` samples per axis; ``--volume`` takes any grid
file (e.g. ``../shared/data/headmr/HeadMRVolume.mhd``).

Run it with::

    python tutorials/xray_tomography.py
    python tutorials/xray_tomography.py --volume ../shared/data/headmr/HeadMRVolume.mhd \\
        --views 64 --out out/xray
"""
from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

import mitsuba as mi


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--volume", help="grid volume file (default: the project's own)")
    p.add_argument("--size", type=int, default=24, help="samples per axis of the default "
                   "volume (default 24)")
    p.add_argument("--views", type=int, default=32, help="projections (default 32)")
    p.add_argument("--passes", type=int, help="passes over the views of the first penalty "
                   "weight tried (default: the fit's, 24)")
    p.add_argument("--out", default="out/xray")
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def main(argv=None):
    a = parse_args(argv)
    mi.set_variant(a.variant)
    import mi_tetvr
    from mi_tetvr.grid import load_volume, make_volume
    from mi_tetvr.grid.slices import reconstruct_slices
    from mi_tetvr.recon.synthetic import make_xray_dataset
    from mi_tetvr.mesh.sample import sample_field
    from mi_tetvr.mesh.scenes import default_volume
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.pipeline import run
    out = Path(a.out)
    try:
        volume = load_volume(a.volume) if a.volume else make_volume(default_volume(a.size))
    except (OSError, ValueError) as e:
        raise SystemExit(f"xray_tomography.py: {e}") from None
    # 1. X-ray projections (the largest optical depth 2.5 sets the attenuation's scale)
    made = make_xray_dataset(volume, out / "data", views=a.views, test_views=8,
                             progress=not a.quiet)
    scale = made["info"]["attenuation_scale"]
    data = load_dataset(out / "data")
    # 2. the tet fit, as `mi-tetvr fit DATA --model absorption` runs it: an unknown on
    #    every voxel of the data set's box, their trilinear field walked on tets
    cfg = FitConfig(model="absorption", passes=a.passes)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        metrics = run(data, out / "fit", cfg, resume=False, progress=not a.quiet,
                      log=lambda *x: None)
    seconds = time.perf_counter() - t0
    mesh = mi_tetvr.read_tetmesh(out / "fit" / "attenuation.vtu", opacity="attenuation")
    # 3. filtered back-projection of the same projections, slice by slice
    fbp = reconstruct_slices(volume, data.train, scale, "fbp")
    # 4. both against the truth at the voxels (values in [0, 1])
    tets = sample_field(mesh.vertices, mesh.tets, mesh.opacity / scale,
                        volume.sample_points()).reshape(volume.values.shape)
    truth = volume.values

    def psnr(v):
        return float(-10 * np.log10(np.mean((np.clip(v, 0, None) - truth) ** 2)))

    result = {"psnr_tets": psnr(tets), "psnr_fbp": psnr(fbp),
              "projection_psnr": metrics["mean"]["psnr"], "seconds": seconds,
              "unknowns": metrics["unknowns"], "voxels": truth.size,
              "files": {"mesh": str(out / "fit" / "attenuation.vtu"),
                        "slices": str(out / "slices.png")}}
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(9, 3.4))
    for ax, (label, vol) in zip(axes, (("truth", truth),
                                       (f"FBP {result['psnr_fbp']:.2f} dB", fbp),
                                       (f"tets {result['psnr_tets']:.2f} dB", tets))):
        ax.imshow(np.clip(vol[len(vol) // 2], 0, 1), cmap="gray", vmin=0, vmax=1, origin="lower")
        ax.set_title(label, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out / "slices.png", dpi=120)
    plt.close(fig)
    if not a.quiet:
        print(f"{volume.shape} voxels, {a.views} projections: volume PSNR tets "
              f"{result['psnr_tets']:.2f} dB ({result['unknowns']:,} unknowns, {seconds:.0f} s), "
              f"FBP {result['psnr_fbp']:.2f} dB; held-out projections "
              f"{result['projection_psnr']:.2f} dB -> {out / 'slices.png'}")
    return result


if __name__ == "__main__":
    main()
