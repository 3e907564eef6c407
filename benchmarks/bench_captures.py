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
learned background, which the earlier code did not choose by itself), ``--args``
this checkout's: ``--args="--sh-degree 2" --code . --code-args="--sh-degree 0"``
compares two settings of one checkout.

The held-out photos are also rendered every ``--every`` seconds of the fit and when it
stops training, by each checkout's own trainer, and scored here the same way: a curve of
held-out PSNR against the seconds of both versions (``--plot``). The fit's clock stops while
it renders them (they cost the fit no training time), so a fit's wall time is its budget plus
theirs.
"""
from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import time
from pathlib import Path

import numpy as np

from common import header_info, make_parser, write_json


def fit(command, data, out, downscale, budget, variant, extra, every):
    """Run one checkout's default fit (``command``: the argv that runs this script with
    that checkout's ``mi_tetvr``) in a process of its own; returns its wall seconds."""
    t0 = time.perf_counter()
    cmd = command + [str(Path(__file__).resolve()), "--worker", str(data), "--out", str(out),
                     "--downscale", str(downscale), "--time-budget", str(budget),
                     "--every", str(every), "--variant", variant,
                     "--code-args=" + shlex.join(extra)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{r.stderr[-3000:]}")
    return time.perf_counter() - t0


def worker(a):
    """The fit of ``mi-tetvr fit DATA --out OUT --downscale D --time-budget T EXTRA``
    through the fit's own viewer hook: every ``--every`` seconds of the fit, and when its
    training ends, the held-out photos are rendered (``OUT/curve/<seconds>.npz``) while the
    fit's clock stands still."""
    import mitsuba as mi
    mi.set_variant(a.variant)
    from mi_tetvr.cli.fit import add_arguments, fit_config
    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.pipeline import run
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    f = parser.parse_args([a.data, "--out", a.out, "--downscale", str(a.downscale),
                           "--time-budget", str(a.time_budget), *shlex.split(a.code_args)])
    config = fit_config(f)
    dataset = load_dataset(a.data, downscale=a.downscale)
    curve = Path(a.out) / "curve"
    curve.mkdir(parents=True, exist_ok=True)
    for old in curve.glob("*.npz"):
        old.unlink()
    paused = [0.0]

    def now():
        return time.perf_counter() - paused[0]

    start = now()

    class Probe:
        """The fit's viewer hook: renders the held-out photos when due and at the end."""

        def __init__(self, trainer):
            self.trainer, self.next = trainer, 0.0

        def set_trainer(self, trainer):
            self.trainer = trainer

        def after_step(self, trainer, *_):
            if now() - start >= self.next:
                self.record(trainer)

        def record(self, trainer):
            seconds = now() - start          # since the fit began, setup and stages included
            t0 = time.perf_counter()
            # (photos of several sizes: one array each)
            renders = {f"render{i}": trainer.render_view(v) for i, v in enumerate(dataset.test)}
            bg = trainer.background
            np.savez(curve / f"{seconds:09.2f}.npz", **renders, seconds=seconds,
                     step=trainer.state.step, tets=len(trainer.tets),
                     background=np.zeros(0) if bg is None else np.asarray(bg, np.float64))
            self.next = seconds + a.every
            paused[0] += time.perf_counter() - t0

        def stop(self):
            self.record(self.trainer)

    run(dataset, a.out, config, resume=False, progress=False, log=lambda *x: None, now=now,
        viewer=Probe)


def curve_scores(out, dataset):
    """``[(seconds of the fit, step, mean held-out PSNR)]`` of the renders in ``out/curve``,
    scored against the held-out photos as loaded here."""
    from mi_tetvr.recon.metrics import image_metrics
    points = []
    for f in sorted((Path(out) / "curve").glob("*.npz")):
        d = np.load(f)
        bg = None if d["background"].size == 0 else d["background"]
        psnr = np.mean([image_metrics(d[f"render{i}"], v.image, bg)["psnr"]
                        for i, v in enumerate(dataset.test)])
        points.append((float(d["seconds"]), int(d["step"]), float(psnr)))
    return points


def _commit(code):
    """``commit 1234abc`` of the checkout ``code`` (its folder's name when it is not one)."""
    r = subprocess.run(["git", "-C", str(code), "rev-parse", "--short", "HEAD"],
                       capture_output=True, text=True)
    return f"commit {r.stdout.strip()}" if r.returncode == 0 else Path(code).name


def plot_curves(path, curves, title):
    from matplotlib.figure import Figure
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    for name, points in curves.items():
        if points:
            t, _, p = zip(*points)
            ax.plot(np.asarray(t) / 60, p, marker="o", ms=3, label=name)
    ax.set_xlabel("time since the fit began [min] (its budget's clock)")
    ax.set_ylabel("held-out PSNR [dB] (sRGB)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


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
    p.add_argument("--args", default="", help="extra fit options of this checkout's run "
                   "(e.g. --args=\"--sh-degree 2\" --code . --code-args=\"--sh-degree 0\": "
                   "one setting against another)")
    p.add_argument("--reuse", action="store_true", help="score the fits already in --out "
                   "(OUT/this, OUT/code) instead of running them again")
    p.add_argument("--every", type=float, default=60.0, help="seconds of the fit between two "
                   "renders of the held-out photos (the curve; default 60)")
    p.add_argument("--plot", help="the curves of held-out PSNR against training time (PNG)")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.worker:
        return worker(a)
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
    # this checkout: the one this script is in (whatever the interpreter imports)
    from checkout_cli import command
    runs = {"this": command(Path(__file__).resolve().parents[1])}
    extra = {"this": shlex.split(a.args)}
    if a.code:
        runs["code"] = command(a.code)
        extra["code"] = shlex.split(a.code_args)
    results = {}
    for name, cmd in runs.items():
        out = Path(a.out) / name
        if a.reuse and (out / "test").is_dir():
            seconds = float("nan")
        else:
            seconds = fit(cmd, a.data, out, a.downscale, a.time_budget, a.variant,
                          extra[name], a.every)
        metrics = json.loads((out / "metrics.json").read_text())
        results[name] = {**score(out, dataset), "seconds": seconds,
                         "steps": metrics["step"], "tets": metrics["tets"],
                         "steps_per_second": metrics["step"] / metrics["optimization_seconds"],
                         "curve": curve_scores(out, dataset)}
        r = results[name]
        print(f"{name:>5s}: PSNR {r['psnr']:.2f} dB, SSIM {r['ssim']:.4f}; {r['steps']} steps "
              f"({r['steps_per_second']:.2f}/s), {r['tets']:,} tets ({seconds:.0f} s)"
              f"{'  ' + ' '.join(extra[name]) if extra[name] else ''}")
        print("       held-out PSNR at " + ", ".join(f"{t:.0f} s: {q:.2f}"
                                                   for t, _, q in r["curve"]))
    if a.code:
        print(f"this - code: {results['this']['psnr'] - results['code']['psnr']:+.2f} dB, "
              f"SSIM {results['this']['ssim'] - results['code']['ssim']:+.4f}")
    if a.plot:
        plot_curves(a.plot, {("this checkout" if k == "this" else _commit(a.code)): r["curve"]
                             for k, r in results.items()},
                    f"{Path(a.data).name} at 1/{a.downscale}, {a.time_budget:g} min budget")
        print(f"# curves written to {a.plot}")
    write_json(a, info, results)


if __name__ == "__main__":
    main()
