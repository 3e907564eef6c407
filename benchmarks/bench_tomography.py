"""Absorption-only tomography: ``mi-tetvr fit DATA --model absorption`` against
scikit-image's filtered back-projection (``iradon``) and SART (``iradon_sart``,
several passes) on the same parallel-beam projections of a real CT volume, at
equal numbers of unknowns.

The data set is ``mi-tetvr make-dataset VOLUME --xray``: ``--views``
projections evenly over 180 degrees (exact line integrals of the volume's
trilinear field, largest optical depth 2.5; the rotation axis and the detector's
pixels on the volume's samples) and ``--test-views`` held-out ones at angles
between them. FBP and SART reconstruct every z slice from its sinogram (one
image row per slice of samples) on the detector's pixel grid, whose voxel
centres inside the box are the volume's own samples; the tets are a grid over
the box (a thousandth of a voxel larger, so that no ray runs along its faces)
with at most as many vertices as the volume has samples, trained coarse to
fine (half the resolution for a quarter of the steps, then the full grid).
Printed per method:

* volume PSNR: the reconstruction against the true volume at its voxel
  centres (values normalised to [0, 1], peak 1; the tet field sampled there
  by VTK's probe, negative FBP values clipped to 0);
* projection PSNR on the held-out angles (transmittance in [0, 1]): each
  reconstruction projected exactly (FBP/SART as trilinear grids, the tets by
  ``tetvr``);
* the unknowns and the time.

``--slices PNG`` writes the middle z slice: truth | FBP | SART | tets.

Usage::

    python benchmarks/bench_tomography.py                       # head MR, 64 angles
    python benchmarks/bench_tomography.py --steps 2000 --slices out/tomo.png --json out/tomo.json
    python benchmarks/bench_tomography.py --quick               # a 12^3 phantom
"""
from __future__ import annotations

import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from common import header, make_parser, write_json

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
VOLUMES = {"headmr": ("headmr/HeadMRVolume.mhd", None),
           "engine": ("engine-ct/engine_256x256x128_uint8.raw.gz", 4)}


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=None, quick="a 12^3 phantom, 16 angles, 60 steps")
    p.add_argument("--volume", choices=tuple(VOLUMES), default="headmr",
                   help="headmr (48x62x42, default) or engine (256x256x128 averaged 4x4x4 "
                   "to 64x64x32)")
    p.add_argument("--views", type=int, default=64, help="training angles (default 64)")
    p.add_argument("--test-views", type=int, default=16, help="held-out angles (default 16)")
    p.add_argument("--steps", type=int, default=1500, help="tet optimizer steps (default 1500)")
    p.add_argument("--sart-passes", type=int, default=30, help="SART passes (default 30)")
    p.add_argument("--lr", type=float, default=0.02,
                   help="attenuation learning rate, optical depth per cell (default 0.02)")
    p.add_argument("--smoothing", type=float, default=0.3,
                   help="weight of the 3D smoothing prior (default 0.3)")
    p.add_argument("--decay", type=float, default=0.1,
                   help="final learning rate over the first (default 0.1)")
    p.add_argument("--views-per-step", type=int, default=8, help="(default 8)")
    p.add_argument("--adaptive", metavar="R,F",
                   help="instead of the uniform grid: a grid of R cells (half of it for a sixth "
                   "of the steps first), the top fraction F of its vertices split by gradient "
                   "after another third")
    p.add_argument("--self-consistent", action="store_true",
                   help="replace the projections by what the tet grid holding the true values "
                   "renders (the tets' own model: isolates its mismatch with the trilinear data)")
    p.add_argument("--slices", help="PNG of the middle slice: truth | FBP | SART | tets")
    p.add_argument("--out", help="folder for the data set and the fit (default: a temp folder)")
    a = p.parse_args(argv)
    if a.quick:
        a.views, a.test_views, a.steps, a.sart_passes = 16, 4, 60, 3
    return a


def load(a):
    """The volume (normalised to [0, 1], isotropic) and its name."""
    from mi_tetvr.grid.volume import load_volume, make_volume
    if a.quick or not (DATA / VOLUMES[a.volume][0]).exists():
        g = np.linspace(-1, 1, 12)
        z, y, x = np.meshgrid(g, g, g, indexing="ij")
        phantom = ((x ** 2 + y ** 2 + z ** 2 < 0.7) * 0.6
                   + ((x - 0.3) ** 2 + y ** 2 + z ** 2 < 0.1) * 0.4)
        return make_volume(phantom), "12^3 phantom"
    path, factor = VOLUMES[a.volume]
    v = load_volume(DATA / path, value_range=(0, 255) if a.volume == "engine" else None)
    if factor:
        nz, ny, nx = v.values.shape
        f = factor
        avg = v.values[:nz // f * f, :ny // f * f, :nx // f * f].reshape(
            nz // f, f, ny // f, f, nx // f, f).mean((1, 3, 5))
        v = make_volume(avg, spacing=v.source_spacing, value_range=(0.0, 1.0),
                        source=f"{path} averaged {f}x{f}x{f}")
    return v, a.volume


def volume_psnr(pred, truth):
    mse = float(np.mean((np.clip(pred, 0, None) - truth) ** 2))
    return -10 * np.log10(mse)


def projection_psnr(volume, views, scale):
    from mi_tetvr.grid.xray import project_volume
    mse = np.mean([np.mean((project_volume(volume, v.camera, scale)
                            - (1.0 - v.image[..., 3])) ** 2) for v in views])
    return -10 * np.log10(mse)


def tet_model_projections(volume, data, scale):
    """Replace every view's image by the render of the tet grid (one vertex per
    sample, the box a thousandth of a voxel larger) holding the true
    attenuation: projections the tets' own model makes exactly. Returns the
    largest transmittance difference to the trilinear projections."""
    import mitsuba as mi

    import mi_tetvr
    from mi_tetvr.mesh.initial import grid_init
    lo, hi = volume.bounds()
    s = float(volume.spacing[0])
    bounds = np.stack([lo - 1e-3 * s, hi + 1e-3 * s])
    V, T = grid_init(bounds, equal_resolution(bounds, volume.values.size))
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "v": mi_tetvr.tetmesh_dict(V, T, model="absorption",
                                                     opacity=scale * volume.sample(
                                                         np.clip(V, lo, hi)))})
    largest = 0.0
    for view in data.train + data.test:
        d = view.camera.sensor_dict(sampler="stratified")
        d["sampler"]["jitter"] = False
        image = np.array(mi.render(scene, sensor=mi.load_dict(d), spp=1), np.float32)
        largest = max(largest, float(np.abs(image[..., 3] - view.image[..., 3]).max()))
        view.image = image
    return largest


def equal_resolution(bounds, unknowns):
    """The finest tet grid over ``bounds`` with at most ``unknowns`` vertices."""
    from mi_tetvr.mesh.initial import grid_shape
    r = 2
    while np.prod(np.add(grid_shape(bounds, r + 1), 1)) <= unknowns:
        r += 1
    return r


def main(a):
    import mitsuba as mi
    mi.set_variant(a.variant)
    from mi_tetvr.grid.volume import Volume
    from mi_tetvr.grid.xray import reconstruct_slices
    from mi_tetvr.recon.synthetic import make_xray_dataset
    from mi_tetvr.mesh.io import read_tetmesh
    from mi_tetvr.mesh.sample import sample_field
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.pipeline import run
    info = header("absorption tomography benchmark")
    out = Path(a.out or tempfile.mkdtemp())
    volume, name = load(a)
    made = make_xray_dataset(volume, out / "data", views=a.views, test_views=a.test_views,
                             progress=False)
    scale = made["info"]["attenuation_scale"]
    data = load_dataset(out / "data")
    if a.self_consistent:
        diff = tet_model_projections(volume, data, scale)
        print(f"projections replaced by the tet model's (the true values on the tet grid): "
              f"they differ from the trilinear ones by at most {diff:.1e} in transmittance")
    cam = data.train[0].camera
    truth = volume.values.astype(np.float64)
    unknowns = truth.size
    print(f"{name} {volume.shape}, {a.views} parallel-beam projections of {cam.width}x"
          f"{cam.height} over 180 deg, {a.test_views} held out; {unknowns:,} voxels")
    recons = {}
    for label, method, passes in (("FBP", "fbp", 0),
                                  (f"SART ({a.sart_passes} passes)", "sart", a.sart_passes)):
        t0 = time.perf_counter()
        recon = reconstruct_slices(volume, data.train, scale, method, passes)
        recons[label] = (recon, time.perf_counter() - t0)
    lo, hi = volume.bounds()
    s = float(volume.spacing[0])
    bounds = np.stack([lo - 1e-3 * s, hi + 1e-3 * s])
    r = equal_resolution(bounds, unknowns)
    stages = [{"iterations": a.steps // 4, "grid": r // 2},
              {"iterations": a.steps - a.steps // 4, "grid": r}]
    if a.adaptive:
        r, fraction = int(a.adaptive.split(",")[0]), float(a.adaptive.split(",")[1])
        stages = [{"iterations": a.steps // 6, "grid": r // 2},
                  {"iterations": a.steps // 3, "grid": r, "split": fraction},
                  {"iterations": a.steps - a.steps // 6 - a.steps // 3}]
    cfg = FitConfig(model="absorption", init="grid", grid_resolution=r, bounds=bounds.tolist(),
                    stages=stages, views_per_step=a.views_per_step, lr_opacity=a.lr,
                    smoothing=a.smoothing, decay=a.decay)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = run(data, out / "fit", cfg, resume=False, progress=not a.quick,
                log=lambda *x: None)
        tets_time = time.perf_counter() - t0
        mesh = read_tetmesh(out / "fit" / "attenuation.vtu", opacity="attenuation")
    nx, ny, nz = volume.shape
    z, y, x = np.meshgrid(*(np.arange(k) for k in (nz, ny, nx)), indexing="ij")
    samples = lo + np.stack([x, y, z], -1).reshape(-1, 3) * volume.spacing
    field = sample_field(mesh.vertices, mesh.tets, mesh.opacity / scale,
                         samples).reshape(truth.shape)
    rows = []
    for label, (recon, seconds) in recons.items():
        grid = Volume(np.clip(recon, 0, None).astype(np.float32), volume.spacing, lo)
        rows.append(dict(method=label, volume_psnr=volume_psnr(recon, truth),
                         projection_psnr=projection_psnr(grid, data.test, scale),
                         unknowns=unknowns, seconds=seconds))
    rows.append(dict(method="tets (mi-tetvr)", volume_psnr=volume_psnr(field, truth),
                     projection_psnr=m["mean"]["psnr"], unknowns=len(mesh.vertices),
                     seconds=tets_time, steps=m["step"], tets=len(mesh.tets)))
    print(f"{'method':<20} {'volume PSNR':>12} {'held-out proj. PSNR':>20} {'unknowns':>10} "
          f"{'time':>8}")
    for row in rows:
        print(f"{row['method']:<20} {row['volume_psnr']:9.2f} dB {row['projection_psnr']:17.2f} dB "
              f"{row['unknowns']:>10,} {row['seconds']:7.1f} s")
    if a.slices:
        panels = {"truth": truth, **{k: v[0] for k, v in recons.items()}, "tets": field}
        plot_slices(a.slices, panels, [None] + [row["volume_psnr"] for row in rows])
        print(f"slices -> {a.slices}")
    write_json(a, info, {"volume": name, "shape": list(volume.shape), "views": a.views,
                         "test_views": a.test_views, "attenuation_scale": scale,
                         "detector": [cam.width, cam.height], "tet_grid": r, "rows": rows})
    return 0


def plot_slices(path, panels, psnrs):
    """The middle z slice of each volume (z, y, x) beside the truth."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(panels), figsize=(3 * len(panels), 3.4))
    for ax, (label, vol), p in zip(axes, panels.items(), psnrs):
        ax.imshow(np.clip(vol[len(vol) // 2], 0, 1), cmap="gray", vmin=0, vmax=1,
                  origin="lower")
        ax.set_title(label if p is None else f"{label}\n{p:.2f} dB", fontsize=9)
        ax.axis("off")
    fig.suptitle("middle z slice (volume PSNR over the whole volume)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main(parse_args()))
