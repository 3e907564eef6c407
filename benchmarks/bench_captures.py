"""Photo captures: the default ``mi-tetvr fit`` of this checkout against
another checkout's (``--code DIR``), each with the same time budget on the
same data set, scored by one function on the same arrays.

Each fit writes ``test/<view>.png`` (its render | the photo, 8-bit sRGB);
this script reads the render half of every one and scores it against the
held-out photo as it loads it itself (:func:`mi_tetvr.recon.metrics
.image_metrics`: PSNR and SSIM of sRGB pictures in [0, 1]), so neither
fit's own ``metrics.json`` is compared with the other's. The fits run one
after the other, never at once::

    python benchmarks/bench_captures.py ROOM --downscale 2 --time-budget 10 \\
        --code ../before --code-args="--background learn" --json room.json
    python benchmarks/bench_captures.py ../shared/data/colmap-maupertuis --downscale 4 \\
        --time-budget 10 --code ../before --code-args="--background learn"

``--code-args`` are extra options of the other checkout's fit (e.g. the
learned background, which the earlier code did not choose by itself).
"""
from __future__ import annotations

import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from common import header_info, make_parser, write_json


def fit(command, data, out, downscale, budget, variant, extra):
    t0 = time.perf_counter()
    cmd = command + ["fit", str(data), "--out", str(out), "--downscale", str(downscale),
                     "--time-budget", str(budget), "--restart", "--variant", variant, *extra]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{r.stderr[-3000:]}")
    return time.perf_counter() - t0


def score(out, dataset):
    """Mean PSNR / SSIM of the renders in ``out/test`` against the held-out photos."""
    from PIL import Image

    from mi_tetvr.color import srgb_to_linear
    from mi_tetvr.recon.metrics import image_metrics
    per = []
    for v in dataset.test:
        png = np.asarray(Image.open(Path(out) / "test" / f"{v.name}.png"), np.float64) / 255
        render = srgb_to_linear(png[:, : v.camera.width, :3])
        rgba = np.concatenate([render, np.ones_like(render[..., :1])], -1)
        per.append(image_metrics(rgba, v.image, None))
    return {k: float(np.mean([m[k] for m in per])) for k in ("psnr", "ssim")}


def main():
    p = make_parser(__doc__, repeat=None, quick="colmap-maupertuis at 1/16 for half a minute")
    p.add_argument("data", nargs="?", help="a photo capture (transforms.json or a COLMAP "
                   "model)")
    p.add_argument("--downscale", type=int, default=2)
    p.add_argument("--time-budget", type=float, default=10.0, help="minutes per fit")
    p.add_argument("--out", default="out/captures", help="where the fits are written "
                   "(default out/captures)")
    p.add_argument("--code", help="another checkout whose default fit is run too")
    p.add_argument("--code-args", default="", help="extra fit options of --code's run")
    p.add_argument("--reuse", action="store_true", help="score the fits already in --out "
                   "(OUT/this, OUT/code) instead of running them again")
    a = p.parse_args()
    if a.quick:
        a.data = a.data or str(Path(__file__).resolve().parents[2] / "shared" / "data" /
                               "colmap-maupertuis")
        a.downscale, a.time_budget = 16, 0.5
        if not Path(a.data).is_dir():
            print(f"{a.data} absent: nothing to run")
            return
    if a.data is None:
        p.error("the data set is required (or --quick)")
    info = header_info("photo captures: default fit, held-out sRGB PSNR / SSIM")
    print(f"# mi_tetvr {info['title']} (mitsuba {info['mitsuba']}, {info['device']}, "
          f"{info['cpu_count']} CPU cores)")
    from mi_tetvr.recon.datasets import load_dataset
    try:
        dataset = load_dataset(a.data, downscale=a.downscale)
    except (ValueError, FileNotFoundError) as e:
        p.error(str(e))
    print(f"{a.data}: {len(dataset.train)} training, {len(dataset.test)} held-out photos "
          f"({dataset.test[0].camera.width}x{dataset.test[0].camera.height}); "
          f"{dataset.protocol}")
    runs = {"this": [sys.executable, "-m", "mi_tetvr.cli"]}
    extra = {"this": []}
    if a.code:
        from checkout_cli import command
        runs["code"] = command(a.code)
        extra["code"] = shlex.split(a.code_args)
    results = {}
    for name, cmd in runs.items():
        out = Path(a.out) / name
        if a.reuse and (out / "test").is_dir():
            seconds = float("nan")
        else:
            seconds = fit(cmd, a.data, out, a.downscale, a.time_budget, a.variant, extra[name])
        results[name] = {**score(out, dataset), "seconds": seconds}
        r = results[name]
        print(f"{name:>5s}: PSNR {r['psnr']:.2f} dB, SSIM {r['ssim']:.4f} "
              f"({seconds:.0f} s){'  ' + a.code_args if name == 'code' and a.code_args else ''}")
    if a.code:
        print(f"this - code: {results['this']['psnr'] - results['code']['psnr']:+.2f} dB, "
              f"SSIM {results['this']['ssim'] - results['code']['ssim']:+.4f}")
    write_json(a, info, results)


if __name__ == "__main__":
    main()
