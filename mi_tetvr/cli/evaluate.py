"""``mi-tetvr eval RESULT DATA``: PSNR and SSIM of a fit (what it fitted, with its own
settings) or of a colored mesh file on a data set's views, scored as the fit scores
itself."""
from __future__ import annotations

import json
from pathlib import Path

from mi_tetvr.cli import flags
from mi_tetvr.cli.common import load_data, set_variant
from mi_tetvr.extras import require

NAME = "eval"
HELP = ("PSNR/SSIM of a fit (or a colored mesh) on a data set's views, scored as the fit "
        "scores itself")


def add_arguments(p):
    p.add_argument("result", help="a fit's output folder (scores what it fitted: colors, an "
                   "attenuation, a scalar or a transfer function, with its background), or "
                   "a mesh file with color and opacity arrays")
    p.add_argument("data", help="the data set")
    flags.out(p, "also write the metrics to this JSON file", required=False)
    p.add_argument("--background", help="a mesh file's background: none (default), white, "
                   "black or r,g,b (a fit folder uses its own)")
    p.add_argument("--downscale", type=int, help="shrink images by this factor (default: the "
                   "fit's, else 1)")
    p.add_argument("--holdout", type=int, default=8,
                   help="with a train split only: every N-th view is a test view (default 8)")
    p.add_argument("--split", choices=["test", "train"], default="test")
    p.add_argument("--images", metavar="DIR", help="a fit folder: write a PNG per view to DIR, "
                   "the render | the view's image | each value's uncertainty (its maximum "
                   "along the rays, where mi-tetvr uncertainty wrote it)")
    flags.mesh_flags(p)
    flags.variant(p)


def run(a):
    require("recon", "mi-tetvr eval", "scipy", "skimage", "PIL")
    from mi_tetvr.recon.config import parse_background
    result = Path(a.result)
    if not result.exists():
        raise FileNotFoundError(f"not found: {result}")
    background = parse_background(a.background) if a.background else None
    set_variant(a.variant)
    from mi_tetvr.recon.pipeline import evaluate_fit, evaluate_mesh
    if result.is_dir():
        if a.background or a.repair or a.cell_to_point:
            raise ValueError("--background, --repair and --cell-to-point apply to a mesh "
                             "file; a fit folder is scored with its own settings")
        metrics = evaluate_fit(result, a.data, split=a.split, downscale=a.downscale,
                               holdout=a.holdout, images=a.images)
    else:
        if a.images:
            raise ValueError("--images applies to a fit folder (its render, and its "
                             "uncertainty where mi-tetvr uncertainty wrote it)")
        if background == "learn":
            raise ValueError("a learned background is in the fit's folder: eval that "
                             "folder (mi-tetvr eval FIT_DIR DATA)")
        data = load_data(a.data, a.downscale, a.holdout)
        metrics = evaluate_mesh(result, data, background=background, split=a.split,
                                repair=a.repair, cell_to_point=a.cell_to_point)
    for name, m in metrics["views"].items():
        print(f"  {name:<24s} PSNR {m['psnr']:6.2f} dB  SSIM {m['ssim']:.4f}")
    m = metrics["mean"]
    what = metrics.get("scored", "sRGB")
    linear = f"; linear PSNR {m['psnr_linear']:.2f} dB" if what == "sRGB" else ""
    print(f"mean PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f} ({what}{linear}) "
          f"({len(metrics['views'])} views)")
    if a.images:
        print(f"render | image | uncertainty per view -> {a.images}")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(metrics, indent=2))
