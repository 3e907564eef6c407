"""``mi-tetvr uncertainty FIT DATA``: each fitted vertex value's standard deviation
(the fit's Laplace approximation), written beside the field in the fit's mesh."""
from __future__ import annotations

import json
from pathlib import Path

from mi_tetvr.cli import flags
from mi_tetvr.cli.common import set_variant
from mi_tetvr.extras import require

NAME = "uncertainty"
HELP = ("each fitted vertex value's standard deviation (Laplace), written into the fit's "
        "mesh as <value>_std point arrays")


def probe_flags(p):
    """The probing options of ``uncertainty`` and ``next-view``."""
    p.add_argument("--stride", type=int, help="probe pixels this far apart together (default: "
                   "per view, one more than the widest projected vertex star, at most 12: then "
                   "exact); 1: Hutchinson's estimator over whole images")
    p.add_argument("--draws", type=int, default=1, help="random sign draws per probe, averaged "
                   "(default 1)")
    p.add_argument("--seed", type=int, default=0, help="the signs' seed (default 0)")
    p.add_argument("--downscale", type=int, help="shrink the data set's images by this factor "
                   "(default: the fit's)")
    p.add_argument("--holdout", type=int, default=8,
                   help="with a train split only: every N-th view is a test view (default 8)")
    flags.quiet(p)
    flags.variant(p)


def add_arguments(p):
    p.add_argument("fit", help="a fit's output folder (colors and opacities, an attenuation, "
                   "a scalar)")
    p.add_argument("data", help="the data set it was fitted to")
    flags.out(p, "the mesh file to write, the fit's with the uncertainty arrays (default: "
              "the fit's own mesh file, its arrays kept)", required=False)
    probe_flags(p)


def load(a):
    """The fit of ``a.fit`` on ``a.data`` (a Trainer), its folder checked first."""
    require("recon", f"mi-tetvr {a.command}", "scipy", "skimage", "PIL")
    fit = Path(a.fit)
    if not fit.is_dir():
        raise FileNotFoundError(f"not a fit's folder: {fit}")
    if a.stride is not None and a.stride < 1 or a.draws < 1:
        raise ValueError(f"--stride and --draws must be at least 1, got {a.stride} and "
                         f"{a.draws}")
    set_variant(a.variant)
    from mi_tetvr.recon.pipeline import load_fit
    return load_fit(fit, a.data, a.downscale, a.holdout)


def laplace(a, trainer):
    """The fit's Laplace approximation (with an X-ray fit's own penalty)."""
    from mi_tetvr.recon.uncertainty import fit_penalty, laplace
    strides = None if a.stride is None else [a.stride] * len(trainer.train)
    return laplace(trainer, penalty=fit_penalty(a.fit), strides=strides, draws=a.draws,
                   seed=a.seed, progress=not a.quiet)


def run(a):
    import numpy as np

    from mi_tetvr.recon.uncertainty import CROSSINGS, write
    a.command = NAME
    trainer = load(a)
    path = Path(a.fit) / trainer.field.fitted_file
    if not path.is_file():
        raise FileNotFoundError(f"{a.fit} has no {trainer.field.fitted_file} to add the "
                                f"uncertainty to")
    u = laplace(a, trainer)
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    write(u, path, a.out)
    path = Path(a.out or path)
    info = u.information
    record = {"sigma2": u.sigma2, "renders": info.renders, "seconds": info.seconds,
              "exact": info.exact, "strides": info.strides, "draws": a.draws,
              "noise": "Poisson counts" if u.sigma2 == 1.0 and
              trainer.field.scored == "transmittance" else "training residuals",
              "std": {}}
    for name, std in u.std().items():
        q = np.percentile(std, [5, 50, 95])
        record["std"][name] = {"p5": q[0], "median": q[1], "p95": q[2], "max": float(std.max())}
        print(f"  {name:<20s} median {q[1]:.4g}, 5-95 % {q[0]:.4g} - {q[2]:.4g}, "
              f"max {std.max():.4g}")
    (Path(a.fit) / "uncertainty.json").write_text(json.dumps(record, indent=2))
    crossed = info.crossings
    print(f"{len(crossed):,} vertices ({int(np.sum(crossed == 0)):,} crossed by no training "
          f"ray); probing: {info.renders:.0f} renders' work in {info.seconds:.1f} s "
          f"({'exact' if info.exact else 'estimated: strides under the stars footprint'}, "
          f"strides {min(info.strides)}-{max(info.strides)}); "
          f"{', '.join(u.std())} and {CROSSINGS} -> {path}")
