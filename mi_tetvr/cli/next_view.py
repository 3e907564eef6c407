"""``mi-tetvr next-view FIT DATA --candidates ...``: candidate cameras (or X-ray
angles) ranked by the information they would add to the fit (FisherRF's trace of
the information gain on the fit's Laplace variances)."""
from __future__ import annotations

import json
from pathlib import Path

from mi_tetvr.cli import flags
from mi_tetvr.cli.uncertainty import load, laplace, probe_flags

NAME = "next-view"
HELP = "rank candidate cameras or X-ray angles by the information they would add to a fit"


def add_arguments(p):
    p.add_argument("fit", help="a fit's output folder")
    p.add_argument("data", help="the data set it was fitted to")
    p.add_argument("--candidates", required=True,
                   help="a data set folder whose cameras are the candidates (their images are "
                        "not read), or N: N cameras on the training cameras' sphere (X-ray: N "
                        "angles over the scan's arc)")
    p.add_argument("--posterior", choices=("auto", "diagonal", "samples"), default="auto",
                   help="the current uncertainty the gain is taken on: diagonal (the variances, "
                   "FisherRF's), samples (an X-ray fit's whole posterior by draws: it sees "
                   "which directions the scan has not measured), auto (default: samples for "
                   "an X-ray fit, else diagonal)")
    p.add_argument("--top", type=int, default=10, help="rows printed (default 10)")
    flags.out(p, "also write the ranking to this JSON file", required=False)
    probe_flags(p)


def candidates(spec, dataset):
    """``(names, cameras)`` of ``--candidates``: a data set's, or N around the
    training ones (:func:`~mi_tetvr.recon.uncertainty.candidate_cameras`)."""
    from mi_tetvr.recon.uncertainty import candidate_cameras
    if spec.isdigit():
        cams = candidate_cameras([v.camera for v in dataset.train], int(spec))
        return [f"candidate {i}" for i in range(len(cams))], cams
    path = Path(spec)
    if not path.exists():
        raise FileNotFoundError(f"--candidates: neither a number nor a data set: {spec}")
    from mi_tetvr.recon.datasets import load_dataset
    other = load_dataset(path, holdout=None, load_images=False)
    views = other.train + other.test
    return [v.name for v in views], [v.camera for v in views]


def run(a):
    from mi_tetvr.recon.uncertainty import rank_views
    a.command = NAME
    trainer = load(a)
    names, cams = candidates(a.candidates, trainer.dataset)
    if not cams:
        raise ValueError("--candidates gives no camera")
    if a.top < 1:
        raise ValueError(f"--top must be at least 1, got {a.top}")
    u = laplace(a, trainer)
    rows = rank_views(trainer, u, cams, posterior=a.posterior, stride=a.stride, draws=a.draws,
                      seed=a.seed, progress=not a.quiet)
    print(f"{'rank':>4}  {'candidate':<24s} {'information gain':>16}")
    for k, r in enumerate(rows[:a.top]):
        print(f"{k + 1:>4}  {names[r['index']]:<24s} {r['gain']:16.4g}")
    if a.out:
        out = [{"rank": k + 1, "name": names[r["index"]], "gain": r["gain"],
                "to_world": cams[r["index"]].to_world.tolist()} for k, r in enumerate(rows)]
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out, indent=2))
