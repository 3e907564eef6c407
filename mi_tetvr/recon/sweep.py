"""Sweeps of fits with Ray Tune: a grid of :class:`~mi_tetvr.recon.config.FitConfig`
settings, each combination one trial (a whole fit with its own time budget),
their held-out scores in one table.

A sweep file (YAML or JSON)::

    base:                 # settings every trial shares (optional)
      time_budget: 2
    grid:                 # each setting a list: every combination is a trial
      lr_color: [0.01, 0.02]
      regularizer: [1, 10]

Trials run ``workers`` at a time on Ray (a local cluster, or the one at
``address``); each writes its fit to ``OUT/trials/<its settings>/`` and the
table goes to ``OUT/sweep.csv`` (and ``sweep.md``), best held-out PSNR first.
"""
from __future__ import annotations

import itertools
import json
from pathlib import Path

from mi_tetvr.extras import needs

#: The scores of a trial, in the table's order.
SCORES = ("psnr", "ssim", "tets", "steps", "seconds")


def read_sweep(path):
    """``(base, grid)`` of a sweep file: two dicts of FitConfig settings, the
    grid's values lists (validated: unknown settings, empty lists and values
    FitConfig refuses raise ``ValueError``)."""
    from mi_tetvr.recon.config import FitConfig
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"sweep file not found: {path}")
    text = path.read_text()
    if path.suffix.lower() in (".yaml", ".yml"):
        with needs("cluster", "a YAML sweep file"):
            import yaml
        d = yaml.safe_load(text) or {}
    else:
        d = json.loads(text)
    if not isinstance(d, dict) or not isinstance(d.get("grid"), dict) or not d["grid"]:
        raise ValueError(f"{path}: a sweep has a 'grid' of settings, each a list of values "
                         f"(and optionally a 'base' of settings every trial shares)")
    extra = sorted(set(d) - {"base", "grid"})
    if extra:
        raise ValueError(f"{path}: unknown keys {extra} (a sweep has 'base' and 'grid')")
    base, grid = dict(d.get("base") or {}), {}
    for k, v in d["grid"].items():
        values = v if isinstance(v, list) else [v]
        if not values:
            raise ValueError(f"{path}: the grid's '{k}' has no values")
        grid[k] = values
    for combo in trials(grid):
        FitConfig().updated(**{**base, **combo})       # (refused here, not in a trial)
    return base, grid


def trials(grid):
    """Every combination of the grid's values, as dicts."""
    keys = list(grid)
    return [dict(zip(keys, values)) for values in itertools.product(*grid.values())]


def trial_name(combo):
    return ",".join(f"{k}={v}" for k, v in combo.items()).replace("/", "_")


def run_trial(config):
    """One trial (in a Ray worker): the fit of ``config['settings']`` on the data
    set; reports its held-out scores to Tune."""
    import mitsuba as mi
    with needs("cluster", "a sweep of fits"):
        from ray import tune

    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import load_dataset
    mi.set_variant(config["variant"])
    import drjit as dr
    dr.set_thread_count(int(config["threads"]))
    import mi_tetvr
    mi_tetvr.register()
    from mi_tetvr.recon.pipeline import run as run_fit
    combo = config["settings"]
    cfg = FitConfig().updated(**{**config["base"], **combo})
    data = load_dataset(config["data"], downscale=cfg.data.downscale or 1,
                        holdout=config["holdout"])
    out = Path(config["out"]) / "trials" / trial_name(combo)
    out.mkdir(parents=True, exist_ok=True)
    m = run_fit(data, out, cfg, resume=False, progress=False)
    tune.report({"psnr": m["mean"]["psnr"], "ssim": m["mean"]["ssim"], "tets": m["tets"],
                 "steps": m["step"], "seconds": m["wall_seconds"], "dir": str(out)})


def sweep(data, sweep_file, out, workers=1, address=None, holdout=8, variant="llvm_ad_rgb"):
    """Run the sweep of ``sweep_file`` on the data set ``data``: its trials
    ``workers`` at a time on Ray Tune. Returns the table (a list of dicts:
    the trial's settings and :data:`SCORES`), best PSNR first, also written
    to ``out/sweep.csv`` and ``out/sweep.md``."""
    with needs("cluster", "a sweep of fits"):
        import ray
        from ray import tune

    from mi_tetvr.cluster import connect
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import load_dataset
    base, grid = read_sweep(sweep_file)
    # the data set read here first: what is wrong with it is said before any trial
    load_dataset(data, downscale=FitConfig().updated(**base).data.downscale or 1, holdout=holdout)
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    started = connect(workers, address)
    try:
        cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        per_trial = max(1, cpus // max(1, int(workers)))
        space = {"settings": tune.grid_search(trials(grid)), "base": base,
                 "data": str(Path(data).resolve()), "out": str(out), "holdout": holdout,
                 "variant": variant, "threads": per_trial}
        tuner = tune.Tuner(
            tune.with_resources(run_trial, {"cpu": per_trial}), param_space=space,
            tune_config=tune.TuneConfig(max_concurrent_trials=int(workers),
                                        metric="psnr", mode="max"),
            run_config=tune.RunConfig(name="sweep", storage_path=str(out / "tune"),
                                      verbose=0))
        results = tuner.fit()
    finally:
        if started:
            ray.shutdown()
    rows, failed = [], []
    for r in results:
        combo = r.config["settings"]
        if r.error is not None or not r.metrics or "psnr" not in r.metrics:
            failed.append(f"{trial_name(combo)}: {r.error}")
            continue
        rows.append({**combo, **{k: r.metrics[k] for k in SCORES}, "dir": r.metrics["dir"]})
    if failed:
        raise RuntimeError(f"{len(failed)} of {len(results)} trials failed: "
                           + "; ".join(failed))
    rows.sort(key=lambda row: -row["psnr"])
    write_table(rows, list(grid), out)
    return rows


def write_table(rows, keys, out):
    """``out/sweep.csv`` and ``out/sweep.md`` of the trials."""
    import csv
    cols = keys + list(SCORES)
    with open(out / "sweep.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols + ["dir"])
        w.writeheader()
        w.writerows(rows)
    (out / "sweep.md").write_text(format_table(rows, keys) + "\n")


def format_table(rows, keys):
    """The trials as a Markdown table (held-out sRGB PSNR / SSIM)."""
    head = keys + ["held-out PSNR (dB)", "SSIM", "tets", "steps", "seconds"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lines.append("| " + " | ".join([str(r[k]) for k in keys] + [
            f"{r['psnr']:.2f}", f"{r['ssim']:.4f}", f"{r['tets']:,}", f"{r['steps']:,}",
            f"{r['seconds']:.0f}"]) + " |")
    return "\n".join(lines)
