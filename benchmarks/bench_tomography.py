"""Absorption tomography: ``mi-tetvr fit DATA --model absorption`` (its default
settings) against the classical methods on the same X-ray projections, at
equal numbers of unknowns, every method scored by one function
(:func:`mi_tetvr.recon.metrics.tomography_scores`) on the same arrays.

The data set is what ``mi-tetvr make-dataset VOLUME --xray`` writes:
``--views`` projections (parallel beam over 180 degrees, or ``--beam cone``
over 360; ``--arc`` degrees for a limited-angle scan) and ``--test-views``
held-out ones between them, the exact line integrals of the volume's cubic
B-spline sampled ``--detail`` (2) times finer than its samples, so that no
method's model is the one the data were made with (no "inverse crime"); ``--flux N``
makes the training projections Poisson counts of N photons per
unattenuated pixel (the held-out ones stay noise-free). Methods:

* parallel beam (:mod:`mi_tetvr.grid.slices`, each z slice from its sinogram
  on the detector's pixel grid, whose samples are the volume's):
  scikit-image's filtered back-projection (``iradon``, ramp filter) and SART
  (``iradon_sart``, ``--sart-passes``, values >= 0); and, tuned on views held
  out of the training ones (never on the truth): SART and SIRT (ASTRA's
  projector) at their best pass counts, FISTA-TV (Beck and Teboulle 2009) at
  its best pass count and TV weight (``--no-tuned`` leaves these out);
* cone beam: FDK (:func:`mi_tetvr.grid.xray.fdk`, numpy/scipy) on the
  volume's samples;
* the tets: the fit's tet grid, one vertex per sample (the cells the
  detector's pixels), solved by the fit's default solver (or ``--solver``).

Printed per method, by the one yardstick: the volume PSNR against the true
volume at its samples (values normalised to [0, 1], the reconstruction
clipped to [0, 1]; the tet field sampled there), the mean SSIM of its z
slices, the held-out projection PSNR (transmittance; every reconstruction
projected exactly: grids by their trilinear line integrals, the tets by
their walk) as the mean of the views' PSNRs and over all pixels, the unknowns
and the time.

``--scan FILE.h5`` scores a real scan instead (Data Exchange HDF5, e.g.
TomoPy's tooth): ``mi-tetvr process-xray`` makes its data set (every 8th
angle held out, ``--bin``), there is no truth, so every method is scored by
its held-out projection PSNR; the rotation centre found is compared with
the one whose FBP predicts the held-out angles best (a scan of centres).

Usage::

    python benchmarks/bench_tomography.py                        # head MR, 64 angles
    python benchmarks/bench_tomography.py --volume engine --flux 1e4 --slices out/engine.png
    python benchmarks/bench_tomography.py --beam cone --json out/cone.json
    python benchmarks/bench_tomography.py --views 24 --arc 90 --flux 1e5   # limited angle
    python benchmarks/bench_tomography.py --quick                # a 12^3 phantom
    python benchmarks/bench_tomography.py --scan ../shared/data/tomopy-tooth/tooth.h5 --bin 2 \
        --slices out/tooth.png
"""
from __future__ import annotations

import itertools
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
           "engine": ("engine-ct/engine_256x256x128_uint8.raw.gz", 4),
           "phantom": (None, None),
           # a volume the penalty's weight was never measured on (electron density, smooth)
           "c60": ("c60/C60Large.cvol", 2)}


def scans_arg(text):
    """``--scans``: ``VIEWS[@ARC]`` items, each one of :data:`TABLE_SCANS`."""
    import argparse
    out = []
    for item in text.split(","):
        views, _, arc = item.partition("@")
        try:
            key = (int(views), float(arc or 180))
        except ValueError:
            key = None
        if key not in TABLE_SCANS:
            raise argparse.ArgumentTypeError(
                f"{item!r} is not a table scan; known: "
                + ", ".join(f"{v}" if a == 180 else f"{v}@{a:g}" for v, a in TABLE_SCANS))
        out.append(key)
    return tuple(out)


def parse_args(argv=None):
    import argparse

    from mi_tetvr.recon.config import parse_weight
    p = make_parser(__doc__, repeat=None, quick="a 12^3 phantom, 16 angles, 4 passes of the tets")
    p.add_argument("--volume", choices=tuple(VOLUMES), default="headmr",
                   help="headmr (48x62x42, default), engine (256x256x128 averaged 4x4x4 to "
                   "64x64x32), phantom (a 48^3 made here: ellipsoids of several densities) "
                   "or c60 (C60's electron density, 128^3 averaged 2x2x2 to 64^3: smooth)")
    p.add_argument("--views", type=int, default=64, help="training angles (default 64)")
    p.add_argument("--test-views", type=int, default=16, help="held-out angles (default 16)")
    p.add_argument("--beam", choices=("parallel", "cone"), default="parallel")
    p.add_argument("--arc", type=float, help="the degrees the training angles span (default "
                   "180 for a parallel beam, 360 for a cone beam; less: limited angle)")
    p.add_argument("--flux", type=float,
                   help="photons per unattenuated pixel: Poisson noise (default: none)")
    p.add_argument("--detail", type=int, default=2,
                   help="project the volume's cubic B-spline this many times finer than its "
                   "samples (default 2; 1: its trilinear field, nearly the model of SART's "
                   "projector: an inverse crime that favours SART)")
    p.add_argument("--sart-passes", type=int, default=30, help="SART passes (default 30)")
    p.add_argument("--solver", help="the tets' solver (default: the fit's)")
    p.add_argument("--passes", type=int, help="the tets' passes (default: the fit's)")
    def weight(text):
        # the fit's own reading of the setting, its message on argparse's line
        try:
            return parse_weight(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None

    p.add_argument("--tv", type=weight,
                   help="the tets' total-variation weight, or heldout: chosen on held-out "
                   "views (default: the fit's rule)")
    p.add_argument("--basis", choices=("linear", "trilinear"),
                   help="the tets' fit with --basis (default: the fit's)")
    p.add_argument("--adapt", type=float, metavar="SHARE",
                   help="the tets' fit with --adapt SHARE (a coarse grid split where it has "
                   "detail, to SHARE of the grid's unknowns)")
    p.add_argument("--curve", metavar="PNG",
                   help="volume PSNR against unknowns on one data set (--volume, --views, "
                   "--arc, --flux): the tets' default fit on uniform grids of 1/2 to 1 of the "
                   "detector's resolution (1/8 to all of its unknowns) and on adaptive meshes "
                   "(--adapt 0.25 to 1); a table, and the plot to PNG")
    p.add_argument("--time-budget", type=float, default=6.0,
                   help="the fit's --time-budget in minutes (default 6)")
    p.add_argument("--no-tuned", action="store_true",
                   help="leave out the held-out-tuned SART, SIRT and FISTA-TV")
    p.add_argument("--scan", help="a measured scan (Data Exchange HDF5) instead of a volume")
    p.add_argument("--bin", type=int, default=1, help="--scan: average BxB detector pixels")
    p.add_argument("--slices", help="PNG of the middle z slice: truth | classical | tets")
    p.add_argument("--out", help="folder for the data set and the fit (default: a temp folder)")
    p.add_argument("--seed", type=int, default=0, help="seed of the photon noise (default 0)")
    p.add_argument("--table", metavar="VOLUMES",
                   help="the table: VOLUMES (comma-separated, or all: headmr, engine, "
                   "phantom) at 24 and 64 views over 180 degrees and 24 over 120 and 90 "
                   "(limited angle), noise-free and "
                   "at 1e5 and 1e4 photons (noise seeds 0 and 1); goes on from "
                   "OUT/table.json when an earlier run of the same tets settings stopped; "
                   "a case OUT/table.json holds with other tets settings lends its rows "
                   "(the same data set), the tets' fit is added beside them")
    p.add_argument("--scans", type=scans_arg, metavar="VIEWS[@ARC],...",
                   help="--table: these scans only, e.g. 64 or 24@90 (default: all of "
                   "24, 64, 24@120, 24@90)")
    a = p.parse_args(argv)
    full = 180.0 if a.beam == "parallel" else 360.0
    if a.arc is not None and not 0.0 < a.arc <= full:
        p.error(f"--arc must lie in (0, {full:g}] degrees for a {a.beam} beam, got {a.arc:g}")
    for name in ("curve", "slices"):
        # a plot's folder is checked before the fits, not after them
        if getattr(a, name) and not Path(getattr(a, name)).resolve().parent.is_dir():
            p.error(f"--{name}: no folder {Path(getattr(a, name)).resolve().parent}")
    if a.scans and not a.table:
        p.error("--scans chooses the table's scans: give --table too")
    if a.out and Path(a.out).exists() and not Path(a.out).is_dir():
        p.error(f"--out: {a.out} is a file, not a folder")
    if a.table:
        bad = [v for v in a.table.split(",") if v not in VOLUMES] if a.table != "all" else []
        if bad:
            p.error(f"--table: unknown volumes {bad}; known: {', '.join(VOLUMES)} or all")
        table = Path(a.out) / "table.json" if a.out else None
        if table is not None and table.is_file():   # an earlier run's entries, before any fit
            import json
            try:
                entries = json.loads(table.read_text())
            except ValueError:
                entries = None
            if not isinstance(entries, list) or not all(
                    isinstance(e, dict) and isinstance(e.get("rows"), list) for e in entries):
                p.error(f"--table: {table} is not a table this benchmark wrote (a JSON list of "
                        "runs with their rows); move it away to start over")
    if a.quick:
        a.views, a.test_views, a.sart_passes = 16, 4, 3
        a.passes = a.passes or 4
    return a


#: The tuned baselines: method, label, most passes tried.
TUNED = (("sart", "SART tuned", 30), ("sirt", "SIRT tuned", 300),
         ("fista_tv", "FISTA-TV tuned", 100))
#: ``--table all``'s volumes (``c60`` is there to check a rule on a volume it was not made on)
TABLE_VOLUMES = ("headmr", "engine", "phantom")
#: The table's scans: views and the degrees they span (parallel beam); the sparse
#: full scans first, then limited angle.
TABLE_SCANS = ((24, 180.0), (64, 180.0), (24, 120.0), (24, 90.0))


def phantom(n):
    """A 3D Shepp-Logan-like phantom: nested ellipsoids of several densities."""
    g = np.linspace(-1, 1, n)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    v = np.zeros_like(x)
    for c, r, d in (((0, 0, 0), (0.69, 0.92, 0.81), 1.0), ((0, -0.02, 0), (0.66, 0.87, 0.78), -0.6),
                    ((0.22, 0, 0), (0.11, 0.31, 0.22), -0.2),
                    ((-0.22, 0, 0), (0.16, 0.41, 0.28), -0.2),
                    ((0, 0.35, -0.15), (0.21, 0.25, 0.41), 0.15),
                    ((0, 0.1, 0.25), (0.046, 0.046, 0.05), 0.2),
                    ((-0.08, -0.6, 0), (0.046, 0.023, 0.05), 0.15),
                    ((0.06, -0.6, 0), (0.023, 0.046, 0.02), 0.15)):
        v += d * ((((x - c[0]) / r[0]) ** 2 + ((y - c[1]) / r[1]) ** 2
                   + ((z - c[2]) / r[2]) ** 2) <= 1)
    return v


def load(a):
    """The volume (normalised to [0, 1]) and its name."""
    from mi_tetvr.grid.volume import load_volume, make_volume
    path, factor = VOLUMES[a.volume]
    if a.quick:
        return make_volume(phantom(12)), "12^3 phantom"
    if path is None or not (DATA / path).exists():
        return make_volume(phantom(48)), "48^3 phantom"
    v = load_volume(DATA / path, value_range=(0, 255) if a.volume == "engine" else None)
    if factor:
        nz, ny, nx = v.values.shape
        f = factor
        avg = v.values[:nz // f * f, :ny // f * f, :nx // f * f].reshape(
            nz // f, f, ny // f, f, nx // f, f).mean((1, 3, 5))
        v = make_volume(avg, spacing=v.source_spacing, value_range=(0.0, 1.0),
                        source=f"{path} averaged {f}x{f}x{f}")
    return v, a.volume


def grid_projections(values, volume, views, scale):
    """Held-out transmittance images of a reconstruction on the volume's samples
    (its trilinear field's exact line integrals)."""
    from mi_tetvr.grid.volume import Volume
    from mi_tetvr.grid.xray import project_volume
    grid = Volume(np.clip(values, 0, None).astype(np.float32), volume.spacing, volume.origin)
    return [project_volume(grid, v.camera, scale) for v in views]


def tet_projections(mesh, views):
    """Held-out transmittance images of a tet attenuation, walked by ``tetvr``."""
    from mi_tetvr.recon.tomography import Projector
    proj = Projector(mesh.vertices, mesh.tets, [v.camera for v in views])
    depth = proj.forward(np.asarray(mesh.opacity, np.float64))
    return [np.exp(-depth[proj.offsets[i]:proj.offsets[i + 1]]).reshape(
        v.camera.height, v.camera.width) for i, v in enumerate(views)]


def main(a):
    import mitsuba as mi
    mi.set_variant(a.variant)
    info = header("absorption tomography benchmark")
    out = Path(a.out or tempfile.mkdtemp())
    if a.scan:
        return main_scan(a, info, out)
    if a.table:
        return main_table(a, info, out)
    if a.curve:
        return main_curve(a, info, out)
    volume, name = load(a)
    res = run_volume(a, volume, name, a.views, a.flux, a.seed, out, a.arc)
    rows = res["rows"]
    w = max(18, *(len(row["method"]) for row in rows))
    print(f"{'method':<{w}} {'volume PSNR':>11} {'slice SSIM':>10} {'proj. PSNR views':>16} "
          f"{'pixels':>8} {'unknowns':>9} {'time':>8}")
    for row in rows:
        print(f"{row['method']:<{w}} {row['volume_psnr']:8.2f} dB {row['slice_ssim']:10.4f} "
              f"{row['projection_psnr_views']:13.2f} dB {row['projection_psnr_pixels']:5.2f} dB "
              f"{row['unknowns']:>9,} {row['seconds']:7.1f} s")
    # the fit scores itself (metrics.json) by the same function: the same number
    m = res["fit_metrics"]
    print(f"the fit's own metrics.json: held-out projection PSNR {m['mean']['psnr']:.2f} dB "
          f"(views), {m['mean']['psnr_all_pixels']:.2f} dB (pixels)")
    if a.slices:
        plot_slices(a.slices, res["panels"], [None] + [row["volume_psnr"] for row in rows],
                    f"{name}, {a.beam} beam, "
                    + ("noise-free" if a.flux is None else f"{a.flux:g} photons"))
        print(f"slices -> {a.slices}")
    write_json(a, info, {k: v for k, v in res.items() if k not in ("panels", "fit_metrics")})
    return 0


def make_case(a, volume, views, flux, seed, out, arc=None):
    """The data set of one case (``views`` angles over ``arc`` degrees, ``flux``
    photons or noise-free, noise ``seed``) and what scores a reconstruction of it:
    a namespace of ``data``, ``volume`` (what was projected), ``truth``, ``targets``
    (the held-out transmittance images), ``scale`` and ``arc``."""
    from types import SimpleNamespace

    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.synthetic import make_xray_dataset
    made = make_xray_dataset(volume, out / "data", views=views, test_views=a.test_views,
                             beam=a.beam, flux=flux, detail=a.detail, seed=seed,
                             progress=False, arc=arc)
    data = load_dataset(out / "data")
    volume = made["volume"]                      # what was projected (resampled if need be)
    return SimpleNamespace(
        data=data, volume=volume, truth=volume.values.astype(np.float64),
        targets=[1.0 - v.image[..., 3].astype(np.float64) for v in data.test],
        scale=made["info"]["attenuation_scale"], arc=made["info"]["arc_deg"])


def tets_row(case, config, out, progress=False):
    """The tets' fit of ``case`` with ``config``, scored by the one yardstick: the
    row's scores and extras, the field at the samples, and the fit's metrics."""
    from mi_tetvr.mesh.io import read_tetmesh
    from mi_tetvr.mesh.sample import sample_field
    from mi_tetvr.recon.metrics import tomography_scores
    from mi_tetvr.recon.pipeline import run
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = run(case.data, out, config, resume=False, progress=progress, log=lambda *x: None)
    seconds = time.perf_counter() - t0
    mesh = read_tetmesh(out / "attenuation.vtu", opacity="attenuation")
    field = sample_field(mesh.vertices, mesh.tets, mesh.opacity / case.scale,
                         case.volume.sample_points()).reshape(case.truth.shape)
    solver = m.get("solver", {})
    tuning = solver.get("tuning") or {}
    row = dict(**tomography_scores(field, case.truth, tet_projections(mesh, case.data.test),
                                   case.targets),
               unknowns=m["unknowns"], seconds=seconds, tets=len(mesh.tets),
               passes=m["step"], fit_metrics_psnr=m["mean"]["psnr"],
               penalty=solver.get("penalty"),
               tuning={k: v for k, v in tuning.items() if k != "trials"})
    return row, field, m


def run_volume(a, volume, name, views, flux, seed, out, arc=None, log=print, lent=None):
    """One data set of ``volume`` (``views`` angles over ``arc`` degrees,
    ``flux`` photons or noise-free, noise ``seed``) reconstructed by every method and scored by
    the one yardstick. Returns ``rows`` (one per method), the middle-slice
    ``panels`` and what describes the data set. ``lent``: the other methods' rows
    of an earlier run on the same data set, kept instead of computed again (no
    panels then but the tets')."""
    from mi_tetvr.grid.slices import reconstruct_slices, tuned_slices
    from mi_tetvr.grid.xray import fdk
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.metrics import tomography_scores
    case = make_case(a, volume, views, flux, seed, out, arc)
    data, volume, truth, scale, arc = case.data, case.volume, case.truth, case.scale, case.arc
    cam = data.train[0].camera
    log(f"{name} {volume.shape}, {views} {a.beam}-beam projections over {arc:g} degrees of "
        f"{cam.width}x"
        f"{cam.height}, {a.test_views} held out, "
        f"{'noise-free' if flux is None else f'Poisson noise at {flux:g} photons (seed {seed})'}"
        f"; {truth.size:,} samples")
    rows = []

    def score(label, values, projections, unknowns, seconds, **extra):
        rows.append(dict(method=label, **tomography_scores(values, truth, projections,
                                                           case.targets),
                         unknowns=unknowns, seconds=seconds, **extra))

    classical = {}
    methods = ((("FBP", "fbp", 0),) + (() if a.table else
                                       ((f"SART ({a.sart_passes} passes)", "sart",
                                         a.sart_passes),))
               if a.beam == "parallel" else (("FDK", "fdk", 0),))
    for label, method, passes in methods if lent is None else ():
        t0 = time.perf_counter()
        if method == "fdk":
            recon = fdk(volume, data.train, scale)
        else:
            recon = reconstruct_slices(volume, data.train, scale, method, passes)
        seconds = time.perf_counter() - t0
        classical[label] = recon
        score(label, recon, grid_projections(recon, volume, data.test, scale), truth.size,
              seconds)
    rows.extend(lent or [])
    if a.beam == "parallel" and not a.no_tuned and lent is None:
        for method, label, most in TUNED:
            t0 = time.perf_counter()
            recon, chosen = tuned_slices(volume, data.train, scale, method,
                                         3 if a.quick else most, flux=flux)
            classical[label] = recon
            score(label, recon, grid_projections(recon, volume, data.test, scale),
                  truth.size, time.perf_counter() - t0, passes=chosen["passes"],
                  tv=chosen["tv"])
    cfg = FitConfig(model="absorption", time_budget=a.time_budget, adapt=a.adapt,
                    basis=a.basis, **{k: getattr(a, k) for k in ("solver", "passes", "tv")
                                      if getattr(a, k) is not None})
    row, field, m = tets_row(case, cfg, out / "fit", progress=not (a.quick or a.table))
    label = tets_label(m, a.adapt)
    rows[:] = [r for r in rows if r["method"] != label] + [dict(method=label, **row)]
    return {"volume": name, "shape": list(volume.shape), "views": views,
            "test_views": a.test_views, "detail": a.detail, "beam": a.beam, "arc": arc,
            "flux": flux, "seed": seed,
            "attenuation_scale": scale, "detector": [cam.width, cam.height], "rows": rows,
            "panels": {"truth": truth, **classical, "tets": field}, "fit_metrics": m}


def tets_label(m, adapt=None):
    """The tets' row of a fit's ``metrics.json`` ``m``: its solver, the share of an
    adaptive mesh, and the basis when it is trilinear."""
    solver = m.get("solver", {}).get("method", "adam")
    basis = m.get("solver", {}).get("basis")
    return f"tets ({solver}{f', adaptive {adapt:g}' if adapt else ''}" \
        f"{', trilinear' if basis == 'trilinear' else ''})"


#: The curve's meshes: uniform grids at these shares of the detector's resolution
#: (about 1/8, 1/4, 1/2 and all of its unknowns), adaptive ones at these shares of its
#: unknowns.
CURVE_GRIDS = (0.5, 0.63, 0.79, 1.0)
CURVE_SHARES = (0.25, 0.5, 0.75, 1.0)


def main_curve(a, info, out):
    """Volume PSNR against unknowns: the tets' default fit of one data set on
    uniform grids (:data:`CURVE_GRIDS`) and on adaptive meshes
    (:data:`CURVE_SHARES`), every one scored by the one yardstick; the curve
    plotted."""
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.tomography import aligned_resolution, detector_cell
    volume, name = load(a)
    case = make_case(a, volume, a.views, a.flux, a.seed, out, a.arc)
    bbox = np.asarray(case.data.bbox, np.float64)
    fine = aligned_resolution(bbox, detector_cell(case.data, bbox))
    print(f"{name} {case.volume.shape}, {a.views} views over {case.arc:g} degrees, "
          f"{'noise-free' if a.flux is None else f'{a.flux:g} photons (seed {a.seed})'}; "
          f"the detector's grid: resolution {fine}")
    grids, shares = ((0.5, 1.0), (0.5,)) if a.quick else (CURVE_GRIDS, CURVE_SHARES)
    rows = []
    base = dict(model="absorption", time_budget=a.time_budget,
                **{k: getattr(a, k) for k in ("passes", "tv") if getattr(a, k) is not None})
    for kind, values in (("grid", grids), ("adaptive", shares)):
        for f in values:
            r = max(2, int(round(f * fine)))
            cfg = FitConfig(**base, basis=a.basis,
                            **({"grid_resolution": r} if kind == "grid" else {"adapt": f}))
            label = f"grid {r}" if kind == "grid" else f"adaptive {f:g}"
            row, _, m = tets_row(case, cfg, out / label.replace(" ", "_"))
            rows.append(dict(mesh=kind, share=f, method=label, basis=m["solver"]["basis"],
                             **row))
            print(f"{label:<14} {row['unknowns']:>9,} unknowns {row['volume_psnr']:7.2f} dB "
                  f"SSIM {row['slice_ssim']:.4f} {row['seconds']:7.1f} s", flush=True)
    plot_curve(a.curve, rows, f"{name}, {a.views} views over {case.arc:g}°, "
               + ("noise-free" if a.flux is None else f"{a.flux:g} photons"))
    print(f"curve -> {a.curve}")
    write_json(a, info, {"volume": name, "views": a.views, "arc": case.arc, "flux": a.flux,
                         "seed": a.seed, "fine_resolution": fine, "curve": rows})
    return 0


def plot_curve(path, rows, title):
    """Volume PSNR against unknowns, uniform grids and adaptive meshes."""
    from matplotlib.figure import Figure
    fig = Figure(figsize=(5.0, 3.4))
    ax = fig.subplots()
    for kind, style in (("grid", "o-"), ("adaptive", "s-")):
        mine = [r for r in rows if r["mesh"] == kind]
        pts = sorted((r["unknowns"], r["volume_psnr"]) for r in mine)
        basis = f" ({mine[0].get('basis', 'linear')} field)"
        ax.plot(*zip(*pts), style, label=("uniform grid" if kind == "grid" else
                "adaptive (a coarse grid split where it has detail)") + basis)
    ax.set_xscale("log")
    ax.set_xlabel("unknowns (vertices)")
    ax.set_ylabel("volume PSNR (dB)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main_table(a, info, out):
    """Every volume at 24 and 64 views over 180 degrees and 24 over 120 and
    90 (:data:`TABLE_SCANS`), noise-free and at 10^4 and 10^5
    photons (two noise seeds each): the mean volume PSNR and slice SSIM of
    every method, the spread over the seeds, and the tets' margin over the
    best tuned baseline; a markdown table."""
    import json
    volumes = [v for v in a.table.split(",")] if a.table != "all" else list(TABLE_VOLUMES)
    fluxes = [1e4, 1e5, None]
    results = []
    path = out / "table.json"
    # the tets' settings: an entry of other settings (or of an older default, which
    # recorded none) is measured again, not mixed in
    fit = {k: getattr(a, k) for k in ("solver", "passes", "tv", "adapt", "time_budget",
                                      "basis")}
    others = []
    if path.is_file():                 # go on where an earlier run of the table stopped
        for r in json.loads(path.read_text()):
            # entries from before the basis was a setting were of the linear one
            settings = r.get("tets_settings")
            if settings is not None and "basis" not in settings:
                settings = {**settings, "basis": "linear"}
            (results if settings == fit else others).append(r)
    loaded = {}
    # every case with noise seed 0 first, then seed 1 (noise-free data are the same
    # every run: one run), each the sparse noisy cases first: a run stopped early has
    # measured every case once
    scans = a.scans or TABLE_SCANS if not a.quick else ((a.views, a.arc or 180.0),)
    for seed, (views, arc), flux, vol_name in itertools.product((0, 1), scans, fluxes, volumes):
        if seed and flux is None:
            continue
        a.volume = vol_name
        if vol_name not in loaded:
            loaded[vol_name] = load(a)
        volume, name = loaded[vol_name]
        if any(scan(r) == (name, views, arc, flux) and r["seed"] == seed for r in results):
            continue
        d = out / (f"{vol_name}_{views}_{flux or 0:g}_{seed}" if arc == 180 else
                   f"{vol_name}_{views}_{arc:g}deg_{flux or 0:g}_{seed}")
        same = [r for r in others if scan(r) == (name, views, arc, flux) and
                r["seed"] == seed and r["test_views"] == a.test_views and
                r.get("detail", 2) == a.detail and r["beam"] == a.beam]
        res = run_volume(a, volume, name, views, flux, seed, d, arc,
                         lent=[dict(x) for x in same[0]["rows"]] if same else None)
        res.pop("panels"), res.pop("fit_metrics")
        res["tets_settings"] = fit
        results.append(res)
        path.write_text(json.dumps(others + results, indent=1))
        best = max((r for r in res["rows"] if "tuned" in r["method"]),
                   key=lambda r: r["volume_psnr"], default=None)
        margin = "" if best is None else f"; tets - best tuned " \
            f"{res['rows'][-1]['volume_psnr'] - best['volume_psnr']:+.2f} dB"
        print("  " + ", ".join(f"{r['method']} {r['volume_psnr']:.2f}"
                               for r in res["rows"]) + margin, flush=True)
    md = table_markdown(results) + "\n\n" + times_markdown(results)
    print(md)
    (out / "table.md").write_text(md + "\n")
    plot_table(out / "table.png", results)
    print(f"table -> {out / 'table.md'}, {out / 'table.png'}")
    write_json(a, info, {"table": results})
    return 0


def scan(r):
    """A table entry's case: volume, views, arc (degrees) and photons."""
    return r["volume"], r["views"], r.get("arc", 180.0), r["flux"]


def views_label(views, arc):
    return f"{views}" if arc == 180 else f"{views} over {arc:g}°"


def plot_table(path, results):
    """The table as bars, one panel per scan (views and arc): per volume and
    photons, each method's mean volume PSNR, the seeds' range as error bars."""
    from matplotlib.figure import Figure
    methods = table_methods(results)
    keys = table_keys(results)
    scans = list(dict.fromkeys(k[1:3] for k in keys))
    cases = max(sum(k[1:3] == s for k in keys) for s in scans)
    fig = Figure(figsize=(max(6.0, 0.9 * cases + 2), 0.6 + 2.6 * len(scans)))
    axes = fig.subplots(len(scans), 1, squeeze=False)[:, 0]
    # each panel's axis from 1 dB under its worst method but FBP (far below where it is
    # shown at all): the differences between the best methods are a fraction of a dB
    shown = [m for m in methods if m != "FBP"] if len(methods) > 2 else methods
    width = 0.8 / len(methods)
    for ax, (views, arc) in zip(axes, scans):
        ks = [k for k in keys if k[1:3] == (views, arc)]
        psnr = [x["volume_psnr"] for r in results if scan(r) in ks for x in r["rows"]
                if x["method"] in shown]
        low, high = min(psnr) - 1.0, max(psnr) + 0.5
        for j, m in enumerate(methods):
            p = [case_values(results, k, m) for k in ks]
            mean = np.array([np.mean(q) for q in p])
            ax.bar(np.arange(len(ks)) + (j - (len(methods) - 1) / 2) * width, mean, width,
                   yerr=[mean - [min(q) for q in p], [max(q) for q in p] - mean],
                   label=m, capsize=2, color=f"C{j}")
        ax.set_xticks(np.arange(len(ks)))
        ax.set_xticklabels([f"{v}\n{photons_label(f) if f else 'noise-free'}"
                            for v, _, _, f in ks], fontsize=7)
        ax.set_xlim(-0.5, cases - 0.5)
        ax.set_ylim(low, high)
        ax.set_ylabel("volume PSNR (dB)", fontsize=8)
        ax.set_title(f"{views} views over {arc:g}°", fontsize=9)
    axes[0].legend(fontsize=7, ncol=len(methods), loc="lower center",
                   bbox_to_anchor=(0.5, 1.12))
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def table_markdown(results):
    """The table's markdown: one row per volume, views and photons; per method
    the mean volume PSNR / slice SSIM over the seeds (the spread after +-)."""
    methods = table_methods(results)
    tuned = [m for m in methods if "tuned" in m]     # none: no margin column (--no-tuned)
    head = "| volume | views | photons | " + " | ".join(methods) + " |" + (
        " tets - best tuned |" if tuned else "")
    lines = [head, "|" + "---|" * (len(methods) + 3 + bool(tuned))]
    for k in table_keys(results):
        cells, means = [], {}
        for m in methods:
            p, q = case_values(results, k, m), case_values(results, k, m, "slice_ssim")
            means[m] = float(np.mean(p))
            spread = f" ±{(max(p) - min(p)) / 2:.2f}" if len(p) > 1 else ""
            cells.append(f"{np.mean(p):.2f}{spread} / {np.mean(q):.3f}")
        margin = (f" {means[methods[-1]] - max(means[m] for m in tuned):+.2f} dB |"
                  if tuned else "")
        lines.append(f"| {k[0]} | {views_label(k[1], k[2])} | {photons_label(k[3])} | "
                     + " | ".join(cells) + " |" + margin)
    return "\n".join(lines)


def times_markdown(results):
    """Seconds per reconstruction, mean over the seeds, in the order of
    :func:`table_markdown`: the tets' whole fit, the tuned baselines' with their
    held-out tuning."""
    methods = [m for m in (results[0]["rows"][-1]["method"], "FISTA-TV tuned", "SART tuned",
                           "SIRT tuned") if any(x["method"] == m for x in results[0]["rows"])]
    lines = ["| volume | views | photons | " + " | ".join(f"{m} (s)" for m in methods) + " |",
             "|" + "---|" * (len(methods) + 3)]
    for k in table_keys(results):
        secs = [np.mean(case_values(results, k, m, "seconds")) for m in methods]
        lines.append(f"| {k[0]} | {views_label(k[1], k[2])} | {photons_label(k[3])} | "
                     + " | ".join(f"{t:.0f}" for t in secs) + " |")
    return "\n".join(lines)


def table_methods(results):
    """The methods every run of the table has, in the first run's order (the
    tets' fit last)."""
    return [x["method"] for x in results[0]["rows"]
            if all(any(y["method"] == x["method"] for y in r["rows"]) for r in results)]


def case_values(results, key, method, score="volume_psnr"):
    """A method's ``score`` in every run (noise seed) of a table case."""
    return [next(x for x in r["rows"] if x["method"] == method)[score]
            for r in results if scan(r) == key]


def table_keys(results):
    """The table's cases in its order: by scan (full arcs first), then photons
    (fewest first, noise-free last), then volume as first met."""
    names = list(dict.fromkeys(r["volume"] for r in results))
    return sorted({scan(r) for r in results},
                  key=lambda k: (-k[2], k[1], k[3] is None, k[3] or 0, names.index(k[0])))


def photons_label(flux):
    return "none" if flux is None else f"{flux:.0e}".replace("e+0", "e")


def scan_grid_volume(data_dir):
    """The reconstruction grid ``process-xray`` recorded (a zero Volume)."""
    import json
    from mi_tetvr.grid.volume import Volume
    g = json.loads((Path(data_dir) / "xray_info.json").read_text())["grid"]
    nx, ny, nz = g["shape_xyz"]
    return Volume(np.zeros((nz, ny, nx), np.float32), np.full(3, g["spacing"]),
                  np.asarray(g["origin"], np.float64))


def main_scan(a, info, out):
    """A measured scan: held-out projection PSNR of every method, the centre found
    against the centre scan's best."""
    import json
    from mi_tetvr.cli import main as cli
    from mi_tetvr.grid.slices import reconstruct_slices, tuned_slices
    from mi_tetvr.mesh.io import read_tetmesh
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.metrics import tomography_scores
    from mi_tetvr.recon.pipeline import run
    flags = ["--bin", str(a.bin), "-q"]
    if cli(["process-xray", a.scan, "-o", str(out / "data"), *flags]) not in (0, None):
        return 1
    rec = json.loads((out / "data" / "xray_info.json").read_text())
    found = rec["center"]
    data = load_dataset(out / "data")
    grid = scan_grid_volume(out / "data")
    targets = [1.0 - v.image[..., 3].astype(np.float64) for v in data.test]
    print(f"{a.scan}: {len(data.train)} training and {len(data.test)} held-out angles of "
          f"{rec['detector'][0]}x{rec['detector'][1]} (bin {a.bin}), flux "
          f"{rec['xray_flux']:.4g} (estimated), centre found at column {found:.2f}")
    # the centre scan: FBP at each candidate centre, scored on the held-out angles
    scan_rows = []
    for c in found + np.arange(-3.0, 3.01, 0.5):
        d = out / f"centre_{c:.2f}"
        cli(["process-xray", a.scan, "-o", str(d), "--center", f"{(c + 0.5) * a.bin - 0.5}",
             *flags])
        dd = load_dataset(d)
        fbp = reconstruct_slices(grid, dd.train, 1.0, "fbp")
        s = tomography_scores(projections=grid_projections(fbp, grid, dd.test, 1.0),
                              targets=targets)
        scan_rows.append({"center": float(c), "projection_psnr": s["projection_psnr_views"]})
    best = max(scan_rows, key=lambda r: r["projection_psnr"])
    print("centre scan (FBP, held-out projection PSNR): " + ", ".join(
        f"{r['center']:.1f}: {r['projection_psnr']:.2f}" for r in scan_rows))
    print(f"centre found {found:.2f}, best by held-out score {best['center']:.2f} "
          f"(difference {abs(found - best['center']):.2f} px)")
    rows, panels = [], {}

    def score(label, values, projections, unknowns, seconds, **extra):
        rows.append(dict(method=label, **tomography_scores(projections=projections,
                                                           targets=targets),
                         unknowns=unknowns, seconds=seconds, **extra))

    flux = rec["xray_flux"]
    for method, label, most in (("fbp", "FBP", 0),) + TUNED:
        t0 = time.perf_counter()
        if method == "fbp":
            recon, extra = reconstruct_slices(grid, data.train, 1.0, "fbp"), {}
        else:
            recon, chosen = tuned_slices(grid, data.train, 1.0, method,
                                         3 if a.quick else most, flux=flux)
            extra = {"passes": chosen["passes"], "tv": chosen["tv"]}
        panels[label] = recon
        score(label, recon, grid_projections(recon, grid, data.test, 1.0), recon.size,
              time.perf_counter() - t0, **extra)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = run(data, out / "fit", FitConfig(model="absorption", time_budget=a.time_budget),
                resume=False, progress=not a.quick, log=lambda *x: None)
    mesh = read_tetmesh(out / "fit" / "attenuation.vtu", opacity="attenuation")
    from mi_tetvr.mesh.sample import sample_field
    panels["tets"] = sample_field(mesh.vertices, mesh.tets, mesh.opacity,
                                  grid.sample_points()).reshape(grid.values.shape)
    score(tets_label(m), None, tet_projections(mesh, data.test),
          m["unknowns"], time.perf_counter() - t0, passes=m["step"],
          penalty=m["solver"].get("penalty"),
          tuning={k: v for k, v in (m["solver"].get("tuning") or {}).items()
                  if k != "trials"})
    print(f"{'method':<18} {'held-out proj. PSNR views':>25} {'pixels':>9} {'unknowns':>9} "
          f"{'time':>8}")
    for row in rows:
        print(f"{row['method']:<18} {row['projection_psnr_views']:22.2f} dB "
              f"{row['projection_psnr_pixels']:6.2f} dB {row['unknowns']:>9,} "
              f"{row['seconds']:7.1f} s")
    if a.slices:
        top = float(np.percentile(panels["FBP"], 99.9))
        # the object's box (where the tuned SART slice exceeds a tenth of its top), a margin
        ref = panels["SART tuned"][len(panels["SART tuned"]) // 2]
        rows_, cols_ = np.nonzero(ref > 0.1 * np.percentile(ref, 99.9))
        crop = (slice(None),) * 3
        if rows_.size:                 # else (nothing reconstructed) the whole slice
            pad = max(4, int(0.1 * max(np.ptp(rows_), np.ptp(cols_))))
            crop = (slice(None), slice(max(rows_.min() - pad, 0), rows_.max() + pad + 1),
                    slice(max(cols_.min() - pad, 0), cols_.max() + pad + 1))
        plot_slices(a.slices, {k: v[crop] / top for k, v in panels.items()},
                    [r["projection_psnr_views"] for r in rows],
                    f"{Path(a.scan).name}: no truth; held-out projection PSNR")
        print(f"slices -> {a.slices}")
    write_json(a, info, {"scan": a.scan, "bin": a.bin, "center_found": found,
                         "center_best": best["center"], "center_scan": scan_rows,
                         "rows": rows})
    return 0


def plot_slices(path, panels, psnrs, title):
    """The middle z slice of each volume (z, y, x) beside the truth."""
    from matplotlib.figure import Figure
    fig = Figure(figsize=(2.6 * len(panels), 3.0))
    axes = fig.subplots(1, len(panels))
    for ax, (label, vol), p in zip(axes, panels.items(), psnrs):
        ax.imshow(np.clip(vol[len(vol) // 2], 0, 1), cmap="gray", vmin=0, vmax=1,
                  origin="lower")
        ax.set_title(label if p is None else f"{label}\n{p:.2f} dB", fontsize=9)
        ax.axis("off")
    fig.suptitle(f"{title}: middle z slice" + ("" if "held-out" in title else
                                                " (volume PSNR over the whole volume)"),
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    sys.exit(main(parse_args()))
