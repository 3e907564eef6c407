"""How sure a fit is of each vertex, and which view to take next: measured.

Three parts (``--part``, default all):

``probes``
    The probed ``diag(J^T J)`` of a small color fit (6 views of 16x16 pixels, a
    grid of 2 cells) against its dense value, every column of ``J`` by forward mode
    (one render per value): the relative error (Frobenius, over all values) of
    Hutchinson's plain estimator (stride 1) and of strides 2, 4 and the one that
    separates every vertex star (exact), by sign draws, with the work in renders.
``spearman``
    Does the predicted standard deviation rank the true error? Per vertex, the
    Spearman correlation of the Laplace standard deviation with the absolute error
    against the truth, beside the baseline of how many training rays cross the
    vertex (fewer: less sure), on CT volumes (engine, head MR) from 24 parallel-beam
    projections at 10^4 photons, and on a color volume (the default volume under its
    transfer function) from 8 views.
``nextview``
    From a sparse start (8 of 32 views of the color volume; 12 of 64 X-ray angles of
    the engine CT, drawn at random), the candidate ranked first is added and the fit
    run again with the same settings; the same with random candidates (``--draws`` of
    them, their mean). Held-out PSNR of each. Ranked by FisherRF's trace of the
    information gain on the posterior's diagonal, and (X-ray) on its samples.

Usage::

    python benchmarks/bench_uncertainty.py                  # all parts
    python benchmarks/bench_uncertainty.py --part spearman
    python benchmarks/bench_uncertainty.py --quick          # small cases
"""
from __future__ import annotations

import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from common import header, make_parser, write_json

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=None, quick="small volumes and fits, 2 probed views, 2 random "
                    "draws")
    p.add_argument("--part", choices=("probes", "spearman", "nextview", "all"), default="all")
    p.add_argument("--draws", type=int, default=3, help="random next views averaged (default 3)")
    p.add_argument("--out", help="work folder (default: a temporary one)")
    p.add_argument("--cases", help="spearman: these cases only (engine, headmr, color)")
    a = p.parse_args(argv)
    #: (a smoke run probes and ranks at a fixed small stride, and fewer candidates)
    a.stride = None
    if a.quick:
        a.draws, a.stride = 2, 4
    return a


def log(*_):
    pass


def color_case(out, views, quick, test_views=8):
    """A data set of the default volume under its transfer function (``views``
    Fibonacci views, ``test_views`` random ones) and its truth: ``(dataset, truth)``,
    truth(vertices) -> (color (n, 3), opacity (n,))."""
    from mi_tetvr.grid import make_volume
    from mi_tetvr.mesh.scenes import default_volume
    from mi_tetvr.recon.datasets import load_nerf
    from mi_tetvr.recon.synthetic import make_dataset
    from mi_tetvr.transfer import read_transfer_function
    tf = read_transfer_function(ROOT / "scenes" / "tf_default.json")
    volume = make_volume(default_volume(16 if quick else 32))
    make_dataset(volume, tf, views=views, res=24 if quick else 48, out_dir=out,
                 test_views=test_views, fov=30, progress=False)

    def truth(vertices):
        color, opacity = tf(np.clip(volume.sample(vertices), 0.0, 1.0))
        return np.asarray(color, np.float64), np.asarray(opacity, np.float64)
    return load_nerf(out), truth


def color_config(quick):
    from mi_tetvr.recon.config import FitConfig
    return FitConfig(grid_resolution=6 if quick else 12, iterations=60 if quick else 400,
                     views_per_step=2, jitter=False, checkpoint_every=10 ** 6,
                     log_every=10 ** 6)


def ct_case(out, name, views, quick, flux=1e4):
    """An X-ray data set of a CT volume (``views`` parallel-beam angles over 180
    degrees, 8 held out, ``flux`` photons) and its truth: ``(dataset, truth)``,
    truth(vertices) -> attenuation (n,)."""
    import sys
    sys.path.insert(0, str(Path(__file__).parent))
    from types import SimpleNamespace

    from bench_tomography import load
    from mi_tetvr.recon.datasets import load_nerf
    from mi_tetvr.recon.synthetic import make_xray_dataset
    volume, _ = load(SimpleNamespace(volume=name, quick=quick))
    made = make_xray_dataset(volume, out, views=views, test_views=8, flux=flux,
                             progress=False)
    vol, scale = made["volume"], made["info"]["attenuation_scale"]
    return load_nerf(out), (lambda vertices: vol.sample(vertices) * scale)


def fit(dataset, out, config):
    """Run the fit; returns its metrics and its trainer."""
    from mi_tetvr.recon.pipeline import run
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        metrics = run(dataset, out, config, resume=False, progress=False, log=log)
    from mi_tetvr.recon.checkpoint import load_checkpoint
    from mi_tetvr.recon.plan import fit_settings
    return metrics, load_checkpoint(out / "checkpoint.npz", dataset, fit_settings(out))


def spearman(a, b):
    from scipy.stats import spearmanr
    return float(spearmanr(a, b).statistic)


def part_probes(a, out):
    import drjit as dr
    import mitsuba as mi

    from mi_tetvr.rays import render_rays
    from mi_tetvr.recon import uncertainty as U
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.pipeline import first_trainer
    data, _ = color_case(out / "probes_data", 6, True, test_views=2)
    cfg = FitConfig(grid_resolution=2, iterations=20, views_per_step=2, jitter=False,
                    background=[1.0, 1.0, 1.0])
    _, tr = first_trainer(data, cfg, log=log)
    for _ in range(20):
        tr.step()
    views = tr.train[:2] if a.quick else tr.train
    o = np.concatenate([v.camera.rays()[0] for v in views])
    d = np.concatenate([v.camera.rays()[1] for v in views])
    t0 = time.perf_counter()
    dense = {}
    for name, (key, c) in tr.field.point_arrays.items():
        n = tr.opt.n_vertices
        col = np.zeros((n, c))
        for j in range(n * c):
            dr.set_grad(tr.opt[key], 0)
            out_c = tr._compared(render_rays(tr.scene, o, d, params=tr.params))
            e = np.zeros(n * c, np.float32)
            e[j] = 1.0
            dr.set_grad(tr.opt[key], mi.Float(e))
            dr.forward_to(out_c)
            col[j // c, j % c] = np.sum(np.array(dr.grad(out_c), np.float64) ** 2)
        dense[name] = col
    dense_s = time.perf_counter() - t0
    ref = np.concatenate([v.ravel() for v in dense.values()])
    print(f"dense J^T J: {sum(v.size for v in dense.values())} forward-mode renders of all "
          f"{len(views)} views, {dense_s:.1f} s")
    print(f"{'stride':>8} {'draws':>5} {'rel. error':>10} {'renders':>8} {'seconds':>8}")
    rows = []
    for s in (1, 2, 4, None):
        for draws in ((1, 4) if a.quick else (1, 4, 16)):
            if s is None and draws > 1:
                continue
            errs, secs = [], []
            for seed in range(1 if a.quick or s is None else 3):
                info = U.information(tr, views, strides=None if s is None else [s] * len(views),
                                     draws=draws, seed=seed, cap=64)
                est = np.concatenate([info.diagonal[k].ravel() for k in dense])
                errs.append(np.linalg.norm(est - ref) / np.linalg.norm(ref))
                secs.append(info.seconds)
            label = f"{info.strides[0]} (exact)" if s is None else str(s)
            rows.append(dict(stride=label, draws=draws, error=float(np.mean(errs)),
                             error_spread=[float(min(errs)), float(max(errs))],
                             renders=info.renders, seconds=float(np.median(secs)),
                             exact=info.exact))
            print(f"{label:>8} {draws:>5} {np.mean(errs):10.2e} {info.renders:8.0f} "
                  f"{np.median(secs):8.1f}")
    return {"dense_seconds": dense_s, "rows": rows}


def vertex_errors(trainer, truth):
    """``{value: (std (n,), |error| (n,), in view (n,) bool)}`` of the fit's values
    against the truth: an X-ray fit's attenuation; a color fit's color (the RMS over
    its channels) and opacity, "in view" where the true opacity is above 1 % of its
    largest (elsewhere a color is not seen)."""
    vertices, _, values = trainer.arrays()
    if trainer.field.scored == "transmittance":
        err = np.abs(values["attenuation"] - truth(vertices))
        return {"attenuation": (err, np.ones(len(err), bool))}
    color, opacity = truth(vertices)
    seen = opacity > 0.01 * opacity.max()
    return {"color": (np.sqrt(np.mean((values["color"] - color) ** 2, axis=1)), seen),
            "opacity": (np.abs(values["opacity"] - opacity), seen)}


def part_spearman(a, out):
    from mi_tetvr.recon import uncertainty as U
    from mi_tetvr.recon.config import FitConfig
    cases = [("engine CT, 24 views, 1e4 photons", "ct", "engine"),
             ("head MR, 24 views, 1e4 photons", "ct", "headmr"),
             ("color volume, 8 views", "color", None)]
    if a.cases:
        cases = [c for c in cases if (c[2] or c[1]) in a.cases.split(",")]
    if a.quick:
        cases = [("phantom 12^3, 24 views", "ct", "phantom"), cases[2]]
    print(f"{'case':<34} {'value':<11} {'where':<7} {'vertices':>9} {'std':>7} "
          f"{'crossings':>9} {'renders':>7} {'seconds':>7} {'exact':>5}")
    rows = []
    for label, kind, name in cases:
        work = out / f"spearman_{kind}_{name}"
        if kind == "ct":
            data, truth = ct_case(work / "data", name, 24, a.quick)
            config = FitConfig(model="absorption")
        else:
            data, truth = color_case(work / "data", 8, a.quick)
            config = color_config(a.quick)
        _, trainer = fit(data, work / "fit", config)
        u = U.laplace(trainer, penalty=U.fit_penalty(work / "fit"),
                      strides=None if a.stride is None else [a.stride] * len(trainer.train))
        for value, (err, seen) in vertex_errors(trainer, truth).items():
            std = np.sqrt(u.variance[value].mean(axis=1))
            for where, m in (("all", np.ones(len(err), bool)), ("in view", seen)):
                if where == "in view" and m.all():
                    continue
                rho = spearman(std[m], err[m])
                base = spearman(-u.information.crossings[m], err[m])
                rows.append(dict(case=label, value=value, vertices=where, count=int(m.sum()),
                                 spearman_std=rho, spearman_crossings=base,
                                 renders=u.information.renders,
                                 seconds=u.information.seconds, exact=u.information.exact,
                                 sigma2=u.sigma2))
                print(f"{label:<34} {value:<11} {where:<7} {int(m.sum()):>9,} {rho:7.3f} "
                      f"{base:9.3f} {u.information.renders:7.0f} "
                      f"{u.information.seconds:7.1f} {str(u.information.exact):>5}")
    return rows


def part_nextview(a, out):
    from mi_tetvr.recon import uncertainty as U
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import Dataset
    rows = []
    ct = "12^3 phantom" if a.quick else "engine CT"
    cases = [("color volume, 8 of 32 views", "color"), (f"{ct}, 12 of 64 angles", "ct")]
    for label, kind in cases:
        work = out / f"next_{kind}"
        if kind == "ct":
            data, _ = ct_case(work / "data", "phantom" if a.quick else "engine", 64, a.quick)
            config = FitConfig(model="absorption")
            start = np.sort(np.random.default_rng(0).choice(len(data.train), 12, replace=False))
        else:
            data, _ = color_case(work / "data", 32, a.quick)
            config = color_config(a.quick)
            start = np.arange(0, 32, 4)
        rest = [i for i in range(len(data.train)) if i not in set(start)]

        def subset(idx, data=data):
            return Dataset([data.train[i] for i in idx], data.test,
                           **{k: getattr(data, k) for k in ("pixel_sampling", "xray_flux")
                              if hasattr(data, k)})

        m0, trainer = fit(subset(start), work / "start", config)
        u = U.laplace(trainer, penalty=U.fit_penalty(work / "start"),
                      strides=None if a.stride is None else [a.stride] * len(trainer.train))
        if a.quick:
            rest = rest[::3]
        cams = [data.train[i].camera for i in rest]
        rng = np.random.default_rng(1)
        randoms = [rest[i] for i in rng.choice(len(rest), a.draws, replace=False)]
        m_rand = [fit(subset(list(start) + [r]), work / f"random_{r}", config)[0]["mean"]["psnr"]
                  for r in randoms]
        print(f"{label}: start {m0['mean']['psnr']:.2f} dB; random {randoms} -> "
              f"{', '.join(f'{p:.2f}' for p in m_rand)} (mean {np.mean(m_rand):.2f} dB)")
        for posterior in ("diagonal", "samples") if kind == "ct" else ("diagonal",):
            t0 = time.perf_counter()
            ranked = U.rank_views(trainer, u, cams, posterior=posterior, stride=a.stride)
            rank_s = time.perf_counter() - t0
            best = rest[ranked[0]["index"]]
            done = work / f"best_{best}"
            m_best = fit(subset(list(start) + [best]), done, config)[0]["mean"]["psnr"]
            row = dict(case=label, posterior=posterior, start_psnr=m0["mean"]["psnr"],
                       ranked_view=int(best), ranked_psnr=m_best,
                       random_views=[int(r) for r in randoms], random_psnr=m_rand,
                       random_mean=float(np.mean(m_rand)), ranking_seconds=rank_s,
                       candidates=len(rest),
                       gains={int(rest[r["index"]]): r["gain"] for r in ranked})
            if kind == "ct":
                row.update(gap_spearman=gap_spearman(data, start, rest, row["gains"]))
            rows.append(row)
            print(f"  {posterior}: ranked view {best} -> {m_best:.2f} dB "
                  f"({m_best - row['random_mean']:+.2f} against random); ranking "
                  f"{len(rest)} candidates in {rank_s:.0f} s"
                  + (f"; gain against the angle's gap to the training ones: Spearman "
                     f"{row['gap_spearman']['spearman']:.2f}, the top one's gap "
                     f"{row['gap_spearman']['top_gap']:.1f} of at most "
                     f"{row['gap_spearman']['max_gap']:.1f} degrees" if kind == "ct" else ""))
    return rows


def gap_spearman(data, start, rest, gains):
    """How the candidates' gains follow the angle's gap to the nearest training angle
    (what a scan misses): their Spearman correlation, the top candidate's gap and the
    largest."""
    def angle(c):
        return np.degrees(np.arctan2(c.to_world[1, 2], c.to_world[0, 2])) % 180.0
    train = np.array([angle(data.train[i].camera) for i in start])
    gaps = {i: float(np.abs((train - angle(data.train[i].camera) + 90.0) % 180.0 - 90.0).min())
            for i in rest}
    top = max(gains, key=gains.get)
    return {"spearman": spearman([gains[i] for i in rest], [gaps[i] for i in rest]),
            "top_gap": gaps[top], "max_gap": max(gaps.values())}


def main(a):
    import mitsuba as mi
    mi.set_variant(a.variant)
    info = header("uncertainty and next view")
    out = Path(a.out or tempfile.mkdtemp())
    results = {}
    for part, fn in (("probes", part_probes), ("spearman", part_spearman),
                     ("nextview", part_nextview)):
        if a.part in (part, "all"):
            print(f"## {part}")
            results[part] = fn(a, out)
    write_json(a, info, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(parse_args()))
