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
theirs. When it stops, the fit also renders whole training photos through their color
transforms (three, ``training.npz``): their PSNR, scored here, is the training PSNR of the
table.

``--runs N`` runs each checkout N times in turn (run k with ``--seed k - 1``) and prints the
means; ``--pairs`` writes held-out photos beside each checkout's renders, ``--tets`` where
each checkout's tets ended up (a histogram of tet size against distance from the point the
cameras look at). LPIPS is not computed: its networks' weights are downloaded at run time.
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
            t0 = time.perf_counter()
            training_renders(self.trainer, dataset, Path(a.out) / "training.npz")
            paused[0] += time.perf_counter() - t0

    run(dataset, a.out, config, resume=False, progress=False, log=lambda *x: None, now=now,
        viewer=Probe)


#: The training photos a fit's training PSNR is scored on: this many, spread evenly.
TRAINING_VIEWS = 3


def training_views(n):
    return np.unique(np.linspace(0, n - 1, min(TRAINING_VIEWS, n)).round().astype(int))


def training_renders(trainer, dataset, path):
    """Renders of a few whole training photos (:func:`training_views`) through their color
    transforms, as the held-out ones are rendered (16 jittered samples per pixel, or one at
    each pixel centre), to ``path`` (``.npz``)."""
    import drjit as dr
    pick = training_views(len(dataset.train))
    out = {}
    with dr.suspend_grad():
        for i in pick:
            v = dataset.train[i]
            image = trainer.render(v, None, seed=int(i), spp=16 if trainer.jitter else 1)
            out[f"render{i}"] = np.array(trainer.apply_appearance(image, v))
    bg = trainer.background
    np.savez(path, **out, index=pick,
             background=np.zeros(0) if bg is None else np.asarray(bg, np.float64))


def training_psnr(out, dataset):
    """The PSNR of a fit's renders of whole training photos (:func:`training_renders`)
    against the photos as loaded here (one sRGB MSE over all of them)."""
    from mi_tetvr.recon.metrics import display_rgb, psnr
    d = np.load(Path(out) / "training.npz")
    bg = None if d["background"].size == 0 else d["background"]
    mse = [np.mean((display_rgb(d[f"render{i}"], bg) - display_rgb(dataset.train[i].image, bg))
                   ** 2) for i in d["index"]]
    return psnr(float(np.mean(mse)))


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


def run_name(name, k, runs):
    """The folder of run ``k`` of checkout ``name`` (``this``, ``code``; ``this_2``...)."""
    return name if runs == 1 else f"{name}_{k + 1}"


def label(a, run):
    name = run.split("_")[0]
    tail = run[len(name):].replace("_", " run ")
    return ("this checkout" if name == "this" else _commit(a.code)) + tail


def one_fit(a, name, k, cmd, extra, dataset):
    """Run (or with ``--reuse`` read) one fit and score it here."""
    out = Path(a.out) / run_name(name, k, a.runs)
    if a.reuse and (out / "test").is_dir():
        seconds = float("nan")
    else:
        seconds = fit(cmd, a.data, out, a.downscale, a.time_budget, a.variant,
                      extra + (["--seed", str(k)] if k else []), a.every)
    metrics = json.loads((out / "metrics.json").read_text())
    r = {**score(out, dataset), "training_psnr": training_psnr(out, dataset),
         "seconds": seconds, "steps": metrics["step"], "tets": metrics["tets"],
         "steps_per_second": metrics["step"] / metrics["optimization_seconds"],
         "curve": curve_scores(out, dataset)}
    print(f"{out.name:>7s}: PSNR {r['psnr']:.2f} dB, SSIM {r['ssim']:.4f}, training PSNR "
          f"{r['training_psnr']:.2f} dB; {r['steps']} steps ({r['steps_per_second']:.2f}/s), "
          f"{r['tets']:,} tets ({seconds:.0f} s){'  ' + ' '.join(extra) if extra else ''}")
    print("         held-out PSNR at " + ", ".join(f"{t:.0f} s: {q:.2f}"
                                                 for t, _, q in r["curve"]))
    return r


def table(results, runs, n):
    """Each checkout's mean over its runs, and this checkout's difference."""
    mean = {name: {k: float(np.mean([results[run_name(name, i, n)][k] for i in range(n)]))
                   for k in ("psnr", "ssim", "training_psnr", "steps", "tets")}
            for name in runs}
    for name, m in mean.items():
        print(f"{name:>5s} (mean of {n}): PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}, "
              f"training PSNR {m['training_psnr']:.2f} dB, {m['steps']:.0f} steps, "
              f"{m['tets']:,.0f} tets")
    if "code" in mean:
        t, c = mean["this"], mean["code"]
        print(f"this - code: {t['psnr'] - c['psnr']:+.2f} dB, SSIM {t['ssim'] - c['ssim']:+.4f}, "
              f"training PSNR {t['training_psnr'] - c['training_psnr']:+.2f} dB")


def _halves(out, view):
    """The render and the photo of a fit's ``test/<view>.png`` (render | photo), 8-bit."""
    from PIL import Image
    png = np.asarray(Image.open(Path(out) / "test" / f"{view.name}.png"))[..., :3]
    w = view.camera.width
    return png[:, :w], png[:, w:2 * w]


def plot_pairs(path, fits, dataset, views=3):
    """Held-out photos beside each fit's render of them: a row per photo (at most ``views``,
    spread over the held-out ones), the photo first."""
    from matplotlib.figure import Figure
    pick = np.unique(np.linspace(0, len(dataset.test) - 1, min(views, len(dataset.test)))
                     .round().astype(int))
    fig = Figure(figsize=(3.2 * (len(fits) + 1), 2.6 * len(pick)))
    axes = fig.subplots(len(pick), len(fits) + 1, squeeze=False)
    for row, i in zip(axes, pick):
        v = dataset.test[i]
        row[0].imshow(_halves(next(iter(fits.values())), v)[1])
        row[0].set_title(f"photo {v.name}", fontsize=8)
        for ax, (name, out) in zip(row[1:], fits.items()):
            ax.imshow(_halves(out, v)[0])
            ax.set_title(name, fontsize=8)
        for ax in row:
            ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def plot_tet_sizes(path, fits, dataset):
    """Where each fit's tets ended up: a 2D histogram of tet size (the cube root of six
    times the volume: a cube's edge) against distance from the point the cameras look
    at, both in units of the cameras' median distance from it, and each fit's tets
    against distance (cumulative)."""
    from matplotlib.colors import LogNorm
    from matplotlib.figure import Figure

    from mi_tetvr.camera import cameras_focus
    from mi_tetvr.mesh.io import read_tetmesh
    from mi_tetvr.mesh.topology import signed_volumes
    cams = [v.camera for v in dataset.train]
    focus = cameras_focus(cams)
    unit = float(np.median([np.linalg.norm(c.center - focus) for c in cams]))
    fig = Figure(figsize=(4.2 * (len(fits) + 1), 3.6))
    axes = fig.subplots(1, len(fits) + 1)
    bins = (np.geomspace(1e-2, 1e2, 41), np.geomspace(1e-4, 1e2, 41))
    for ax, (name, out) in zip(axes, fits.items()):
        mesh = read_tetmesh(out / "mesh.vtu", color=None, opacity=None)
        centre = mesh.vertices[mesh.tets].mean(1)
        dist = np.linalg.norm(centre - focus, axis=1) / unit
        size = np.cbrt(6 * np.abs(signed_volumes(mesh.vertices, mesh.tets))) / unit
        ax.hist2d(np.clip(dist, *bins[0][[0, -1]]), np.clip(size, *bins[1][[0, -1]]), bins=bins,
                  norm=LogNorm(), cmap="viridis")
        ax.set(xscale="log", yscale="log", xlabel="distance from the cameras' focus",
               ylabel="tet size")
        ax.set_title(f"{name}: {len(mesh.tets):,} tets", fontsize=8)
        order = np.sort(dist)
        axes[-1].plot(order, np.arange(1, len(order) + 1) / len(order), label=name)
    axes[-1].set(xscale="log", xlabel="distance from the cameras' focus",
                 ylabel="share of the tets within")
    axes[-1].axvline(1.0, color="gray", lw=0.8, ls="--")
    axes[-1].legend(fontsize=8)
    fig.suptitle("units: the cameras' median distance from their focus", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


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
    p.add_argument("--runs", type=int, default=1, help="fits of each checkout, one after the "
                   "other in turn (run k > 1 with --seed k - 1; default 1)")
    p.add_argument("--pairs", help="held-out photos beside the first run's renders of each "
                   "checkout (PNG)")
    p.add_argument("--tets", help="the first run's tet sizes against distance from the "
                   "cameras' focus, per checkout (PNG)")
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
    for k in range(a.runs):
        for name, cmd in runs.items():
            results[run_name(name, k, a.runs)] = one_fit(a, name, k, cmd, extra[name], dataset)
    table(results, runs, a.runs)
    if a.plot:
        plot_curves(a.plot, {label(a, r): results[r]["curve"] for r in results},
                    f"{Path(a.data).name} at 1/{a.downscale}, {a.time_budget:g} min budget")
        print(f"# curves written to {a.plot}")
    firsts = {label(a, name): Path(a.out) / run_name(name, 0, a.runs) for name in runs}
    if a.pairs:
        plot_pairs(a.pairs, firsts, dataset)
        print(f"# held-out photo | renders written to {a.pairs}")
    if a.tets:
        plot_tet_sizes(a.tets, firsts, dataset)
        print(f"# tet sizes against distance written to {a.tets}")
    write_json(a, info, results)


if __name__ == "__main__":
    main()
