"""``mi-tetvr process-xray SCAN.h5 -o DIR``: measured X-ray projections (Data Exchange
HDF5: counts, flat and dark fields, angles) as the X-ray data set ``fit --model
absorption`` reads: flat/dark corrected, rings optionally removed, the rotation centre
found, every k-th angle held out for scoring."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from mi_tetvr.cli import flags
from mi_tetvr.cli.common import CommandError
from mi_tetvr.extras import require

NAME = "process-xray"
HELP = ("measured X-ray projections (Data Exchange HDF5) as an X-ray data set for fit: "
        "flat/dark correction, rotation centre, rings, held-out angles")


def _pair(text):
    parts = [float(x) for x in text.split(",")]
    if len(parts) != 2:
        raise ValueError(f"expected FIRST,LAST, got {text!r}")
    return tuple(parts)


def add_arguments(p):
    p.add_argument("scan", help="Data Exchange HDF5 file (exchange/data, exchange/data_white, "
                   "exchange/data_dark, exchange/theta), as TomoPy and the APS write them")
    flags.out(p, "data set folder (transforms_*.json, train/ and test/ .npy transmittance, "
                 "xray_info.json)")
    p.add_argument("--center", default="auto",
                   help="rotation axis's detector column (0: the first pixel's centre), or "
                   "auto (default: Vo's Fourier method, parallel beam over 180 degrees)")
    p.add_argument("--hold-out", type=int, default=8,
                   help="every K-th angle is held out for scoring (default 8; 0: none)")
    p.add_argument("--rings", action="store_true",
                   help="remove ring artefacts (Vo's sorting-based stripe filter)")
    p.add_argument("--bin", type=int, default=1,
                   help="average BxB detector pixels (default 1: none)")
    p.add_argument("--rows", help="detector rows FIRST,LAST to keep (default: all)")
    p.add_argument("--pixel-size", type=float,
                   help="detector pixel in world units (default: the detector is 2 wide)")
    p.add_argument("--flux", default="auto",
                   help="photons per unattenuated pixel, weighting the fit's rays: a number, "
                   "auto (default: estimated from the noise of the projections) or none")
    p.add_argument("--angles", type=flags.argument_type(_pair, "angles"),
                   help="FIRST,LAST angle in degrees, evenly between (when the file has none)")
    p.add_argument("--normalized", action="store_true",
                   help="exchange/data holds transmittance already (no flat fields)")
    p.add_argument("--beam", choices=("parallel", "cone"), default="parallel",
                   help="parallel beam (default) or cone beam (--source-distance, "
                   "--detector-distance)")
    p.add_argument("--source-distance", type=float,
                   help="cone beam: source to rotation axis (world units; TIGRE's DSO)")
    p.add_argument("--detector-distance", type=float,
                   help="cone beam: source to detector (world units; TIGRE's DSD)")
    flags.quiet(p)


def run(a):
    require("tomo", "mi-tetvr process-xray", "h5py", "algotom", "skimage")
    from mi_tetvr.grid.scan import (bin_pixels, estimate_flux, find_center, read_data_exchange,
                                    remove_rings, transmittance)
    try:
        scan = read_data_exchange(a.scan, angles=a.angles, normalized=a.normalized)
    except (ValueError, FileNotFoundError) as e:
        raise CommandError(str(e)) from None
    for note in scan.notes:
        print(f"{a.scan}: {note}")
    if a.bin < 1:
        raise ValueError(f"--bin must be >= 1, got {a.bin}")
    if a.beam == "cone" and (a.source_distance is None or a.detector_distance is None):
        raise ValueError("--beam cone needs --source-distance and --detector-distance")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t = transmittance(scan)
    for w in caught:
        print(f"{a.scan}: {w.message}")
    if a.rows:
        first, last = (int(v) for v in _pair(a.rows))
        if not 0 <= first <= last < t.shape[1]:
            raise ValueError(f"--rows {a.rows}: the detector has rows 0 to {t.shape[1] - 1}")
        t = t[:, first:last + 1]
    t = bin_pixels(t, a.bin)
    n, h, w = t.shape
    low = float(np.mean(t <= 0))
    if low > 0.01:
        print(f"warning: {100 * low:.1f} % of the pixels have no signal left (transmittance "
              f"<= 0): their optical depth is clipped")
    if a.flux == "auto":
        flux = estimate_flux(t)
        flux_said = f"{flux:.4g} photons (estimated from the projections' noise)"
    elif a.flux == "none":
        flux, flux_said = None, "none (rays alike)"
    else:
        flux = float(a.flux)
        flux_said = f"{flux:g} photons (given)"
    depth = -np.log(np.clip(t, 1e-6, None))
    if a.rings:
        depth = remove_rings(depth)
        t = np.exp(-depth)
    if a.center == "auto":
        if a.beam != "parallel":
            raise ValueError("the centre is found for a parallel beam: give --center")
        center = find_center(depth, scan.angles)
        center_said = f"{center:.2f} (found: Vo's method)"
    else:
        center = (float(a.center) + 0.5) / a.bin - 0.5
        center_said = f"{center:.2f} (given)"
    pixel = a.pixel_size if a.pixel_size else 2.0 / w
    info = write_scan_dataset(
        t, scan.angles, a.out, pixel_size=pixel, center=center, hold_out=a.hold_out,
        beam=a.beam, source_distance=a.source_distance, detector_distance=a.detector_distance,
        flux=flux, info={"source": str(a.scan), "bin": a.bin, "rings_removed": bool(a.rings),
                         "notes": scan.notes, "flux_estimated": a.flux == "auto"})
    print(f"{a.out}: {len(info['angles_train_deg'])} training and "
          f"{len(info['angles_test_deg'])} held-out projections of {w}x{h} ({a.beam} beam), "
          f"angles {scan.angles.min():.4g} to {scan.angles.max():.4g} degrees, rotation "
          f"centre at column {center_said}, detector shift {info['detector_shift_px']:+.2f} px, "
          f"flux {flux_said}")
    print(f"next: mi-tetvr fit {a.out} --model absorption -o {a.out.rstrip('/')}_fit")


def write_scan_dataset(t: np.ndarray, angles, out_dir, *, pixel_size: float, center: float,
                       hold_out: int = 8, beam: str = "parallel", source_distance=None,
                       detector_distance=None, flux=None, info=None):
    """Write transmittance projections ``t`` (angles, rows, columns) as the
    project's X-ray data set (what ``make-dataset --xray`` writes and ``fit
    --model absorption`` reads): ``transforms_{train,test}.json`` (every
    ``hold_out``-th angle in test), ``{train,test}/p_NNN.npy``, the
    reconstruction grid's box as ``aabb`` and ``xray_info.json``. Returns the
    info written."""
    from mi_tetvr.grid.scan import held_out_split, scan_cameras, scan_grid
    from mi_tetvr.recon.datasets import Dataset, View, write_nerf
    n, h, w = t.shape
    cams = scan_cameras(angles, w, h, pixel_size, center, beam, source_distance,
                        detector_distance)
    train, test = held_out_split(n, hold_out)
    shape, origin = scan_grid(w, h, pixel_size, center)
    lo = origin.copy()
    hi = origin + (np.array(shape) - 1) * pixel_size
    if h == 1:
        # one row: a slab one pixel thick about it
        lo[2], hi[2] = -0.5 * pixel_size, 0.5 * pixel_size
    if beam == "cone":
        # magnified: the detector's pixels are pixel_size * DSO / DSD at the axis
        cell = pixel_size * source_distance / detector_distance
        m = int(np.ceil(0.5 * w)) + 1
        lo = np.array([-m * cell, -m * cell, -0.5 * h * cell])
        hi = -lo
    views = {}
    for split, idx in (("train", train), ("test", test)):
        views[split] = []
        for i in idx:
            img = np.zeros((h, w, 4), np.float32)
            img[..., 3] = 1.0 - t[i]
            views[split].append(View(f"p_{i:03d}", cams[i], img))
    write_nerf(Dataset(views["train"], views["test"], bbox=np.stack([lo, hi]),
                       pixel_sampling="area", xray_flux=flux,
                       protocol=f"every {hold_out}-th angle held out"), out_dir,
               image_format="npy")
    record = {"beam": beam, "attenuation_scale": 1.0, "detector": [w, h],
              "pixel_size": float(pixel_size), "center": float(center),
              "detector_shift_px": float(center - (w - 1) / 2),
              "source_distance": source_distance, "detector_distance": detector_distance,
              "angles_train_deg": np.asarray(angles)[train].tolist(),
              "angles_test_deg": np.asarray(angles)[test].tolist(),
              "hold_out": int(hold_out), "xray_flux": None if flux is None else float(flux),
              "grid": {"shape_xyz": [int(s) for s in shape], "spacing": float(pixel_size),
                       "origin": [float(v) for v in origin]},
              "model": "absorption: measured transmittance (flat/dark corrected), "
                       "attenuation per world unit",
              **(info or {})}
    (Path(out_dir) / "xray_info.json").write_text(json.dumps(record, indent=1) + "\n")
    return record
