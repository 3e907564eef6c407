"""Tutorial: where a CT reconstruction is unsure, beside where it is wrong.

A reconstruction from 24 noisy X-ray projections returns one attenuation per
vertex; :func:`mi_tetvr.recon.uncertainty.laplace` gives each a standard
deviation: the Laplace approximation of the fit's weighted least squares, its
information ``sum_r w_r A_ri^2`` (the rays' Poisson counts as weights) probed
exactly through the walk's adjoint, plus a floor (the values' own spread). The
command line does the same (``mi-tetvr uncertainty FIT DATA``) and writes it into
the fit's mesh as the point array ``attenuation_std``.

Steps: project the project's default volume (a ring, blobs and a shell) into 24
parallel-beam views at 10^4 photons per pixel, fit the attenuation (the default
absorption fit), compute its uncertainty, and compare it with the true error of
each vertex: their Spearman rank correlation, beside the baseline of how many
training rays cross the vertex. Writes ``uncertainty.png``: the reconstruction, its
uncertainty and its true error, as maximum-intensity projections (``tetproj``)
from one camera and on the middle slice.

Run it with::

    python tutorials/ct_uncertainty.py
    python tutorials/ct_uncertainty.py --volume ../shared/data/headmr/HeadMRVolume.mhd
"""
from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

import mitsuba as mi


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--volume", help="grid volume file (default: the project's own)")
    p.add_argument("--size", type=int, default=32, help="samples per axis of the default "
                   "volume (default 32)")
    p.add_argument("--views", type=int, default=24, help="projections (default 24)")
    p.add_argument("--flux", type=float, default=1e4, help="photons per pixel (default 1e4)")
    p.add_argument("--passes", type=int, help="the fit's passes (default: the fit's, 24)")
    p.add_argument("--res", type=int, default=200, help="the projections' size (default 200)")
    p.add_argument("--out", default="out/ct_uncertainty")
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def main(argv=None):
    a = parse_args(argv)
    mi.set_variant(a.variant)
    from scipy.stats import spearmanr

    from mi_tetvr.camera import Camera
    from mi_tetvr.grid import load_volume, make_volume
    from mi_tetvr.mesh.sample import sample_field
    from mi_tetvr.mesh.scenes import default_volume
    from mi_tetvr.recon.checkpoint import load_checkpoint
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.pipeline import run
    from mi_tetvr.recon.plan import fit_settings
    from mi_tetvr.recon.synthetic import make_xray_dataset
    from mi_tetvr.recon.uncertainty import fit_penalty, laplace, projection
    out = Path(a.out)
    try:
        volume = load_volume(a.volume) if a.volume else make_volume(default_volume(a.size))
    except (OSError, ValueError) as e:
        raise SystemExit(f"ct_uncertainty.py: {e}") from None
    # 1. noisy projections (Poisson counts of `flux` photons per unattenuated pixel)
    made = make_xray_dataset(volume, out / "data", views=a.views, test_views=8, flux=a.flux,
                             progress=not a.quiet)
    volume, scale = made["volume"], made["info"]["attenuation_scale"]
    data = load_dataset(out / "data")
    # 2. the default absorption fit (penalized weighted least squares on tets)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run(data, out / "fit", FitConfig(model="absorption", passes=a.passes), resume=False,
            progress=not a.quiet, log=lambda *x: None)
    trainer = load_checkpoint(out / "fit" / "checkpoint.npz", data, fit_settings(out / "fit"))
    # 3. each vertex's standard deviation: the rays' counts weigh the information, the
    #    fit's total variation (its weight and corner in metrics.json) is the prior
    u = laplace(trainer, penalty=fit_penalty(out / "fit"), progress=not a.quiet)
    std = u.std()["attenuation_std"]
    vertices, tets, values = trainer.arrays()
    fitted = values["attenuation"]
    error = np.abs(fitted - volume.sample(vertices) * scale)
    rho = float(spearmanr(std, error).statistic)
    base = float(spearmanr(-u.information.crossings, error).statistic)
    # 4. pictures: from a camera above the scan's plane, and the middle slice
    lo, hi = (np.asarray(b, np.float64) for b in volume.bounds())
    centre, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    cam = Camera.look_at(centre + radius * np.array([1.6, -2.2, 1.5]), centre, (0, 0, 1),
                         a.res, a.res, fov_x=40.0)
    top = max(float(np.percentile(error, 99.5)), float(std.max()))
    panels = [projection(vertices, tets, fitted, cam, "max", (0.0, float(fitted.max())), "gray"),
              projection(vertices, tets, std, cam, "max", (0.0, top)),
              projection(vertices, tets, error, cam, "max", (0.0, top))]
    points = volume.sample_points()
    slices = [sample_field(vertices, tets, v, points).reshape(volume.values.shape)
              for v in (fitted, std, error)]
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mi_tetvr.color import linear_to_srgb
    fig, axes = plt.subplots(2, 3, figsize=(9.6, 6.4))
    titles = ("reconstruction", "its uncertainty (std)", "its true error")
    for k in range(3):
        axes[0, k].imshow(np.clip(linear_to_srgb(np.clip(panels[k], 0, 1)), 0, 1))
        axes[0, k].set_title(f"{titles[k]}, max projection", fontsize=9)
        s = slices[k][len(slices[k]) // 2]
        axes[1, k].imshow(s, cmap="gray" if k == 0 else "viridis", origin="lower", vmin=0,
                          vmax=float(fitted.max()) if k == 0 else top)
        axes[1, k].set_title(f"{titles[k]}, middle slice", fontsize=9)
    for ax in axes.ravel():
        ax.axis("off")
    fig.suptitle(f"{a.views} projections at {a.flux:g} photons: Spearman(std, |error|) "
                 f"{rho:.2f} per vertex (rays crossing: {base:.2f})", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "uncertainty.png", dpi=110)
    plt.close(fig)
    result = {"spearman_std": rho, "spearman_crossings": base, "vertices": len(vertices),
              "renders": u.information.renders, "exact": u.information.exact,
              "files": {"figure": str(out / "uncertainty.png")}}
    if not a.quiet:
        print(f"{len(vertices):,} vertices: Spearman(std, |error|) {rho:.3f}, rays crossing "
              f"{base:.3f}; probing {u.information.renders:.0f} renders' work "
              f"({'exact' if u.information.exact else 'estimated'}) -> {out / 'uncertainty.png'}")
    return result


if __name__ == "__main__":
    main()
