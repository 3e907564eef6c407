"""Training throughput: optimizer steps per second of ``mi-tetvr fit`` on the
engine CT at 256x256, this checkout against another (``--code DIR``).

The engine CT (``../shared/data/engine-ct``, transfer function
``scenes/tf_engine.json``) is rendered by the grid ray marcher into
``--views`` training and 4 test views of 256x256 (once, kept in ``--out``).
Each checkout then runs the same fixed-settings command (the other one
through ``benchmarks/checkout_cli.py``)::

    mi-tetvr fit DATA --restart --config {"resolution": R, "iterations": N}

(``R`` cells along the largest axis, ``N`` steps, the checkout's defaults for
everything else), alternating between the two checkouts ``--repeat`` times.
Reported per run: steps per second of the optimization (steps / the fit's
own optimization seconds, which leave out loading and the outputs) and the
held-out sRGB PSNR (scored by this checkout), so that a faster step is seen
to train as well.

Usage::

    python benchmarks/bench_training.py --code ../before --json out/training.json
    python benchmarks/bench_training.py --quick
"""
from __future__ import annotations

import json
import statistics
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from checkout_cli import command as checkout_command  # noqa: E402
from common import header, make_parser, write_json  # noqa: E402
from fit_suite import DATA, SETS, load_set_volume  # noqa: E402


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=2,
                    quick="--views 4 --res 32 --grid-resolution 8 --iterations 5")
    p.add_argument("--code", help="the other checkout (its fit runs with PYTHONPATH=DIR)")
    p.add_argument("--out", default="out/training", help="data and fits (default out/training)")
    p.add_argument("--views", type=int, default=24, help="training views (default 24)")
    p.add_argument("--res", type=int, default=256, help="view size (default 256)")
    p.add_argument("--grid-resolution", type=int, default=48,
                   help="the fit's grid resolution (default 48)")
    p.add_argument("--iterations", type=int, default=150, help="fit --iterations (default 150)")
    a = p.parse_args(argv)
    if a.quick:
        a.views, a.res, a.grid_resolution, a.iterations = 4, 32, 8, 5
    return a


def run_fit(code, data, out, a):
    """One fit; returns (steps per second, metrics.json)."""
    out.mkdir(parents=True, exist_ok=True)
    # settings as a config file: its key "resolution" reads in checkouts before and after
    # the flag became --grid-resolution
    config = out.resolve() / "bench_config.json"
    config.write_text(json.dumps({"resolution": a.grid_resolution,
                                  "iterations": a.iterations}))
    cmd = (checkout_command(code) if code else [sys.executable, "-m", "mi_tetvr.cli"]) + [
        "fit", str(data.resolve()), "--out", str(out.resolve()), "--restart",
        "--config", str(config), "--variant", a.variant]
    r = subprocess.run(cmd, capture_output=True, text=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fit.log").write_text(r.stdout + r.stderr)
    if r.returncode != 0:
        raise RuntimeError(f"fit failed ({r.returncode}): {r.stderr[-2000:]}")
    m = json.loads((out / "metrics.json").read_text())
    return m["step"] / m["optimization_seconds"], m


def main(argv=None):
    a = parse_args(argv)
    import mitsuba as mi
    mi.set_variant(a.variant)
    import mi_tetvr  # noqa: F401
    from mi_tetvr.recon.synthetic import make_dataset
    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.pipeline import evaluate_mesh
    info = header("training benchmark")
    out = Path(a.out)
    data = out / f"engine_{a.res}_{a.views}"
    if not (data / "transforms_train.json").is_file():
        if not (DATA / SETS["engine"]["volume"]).is_file():
            print(f"skipped: {DATA / SETS['engine']['volume']} not found (../shared/data)")
            return 0
        volume, tf = load_set_volume(SETS["engine"])
        make_dataset(volume, tf, out_dir=data, views=a.views, test_views=4, res=a.res,
                     fov=40.0, progress=False)
    dataset = load_dataset(data)
    codes = {"this checkout": None}
    if a.code:
        codes[f"--code {a.code}"] = a.code
    print(f"engine CT, {a.views} views of {a.res}x{a.res}; grid resolution {a.grid_resolution} "
          f"--iterations {a.iterations}")
    runs = {k: [] for k in codes}
    for rep in range(a.repeat):
        for label, code in codes.items():
            fit_dir = out / f"fit_{'this' if code is None else 'other'}"
            sps, m = run_fit(code, data, fit_dir, a)
            psnr = evaluate_mesh(fit_dir / "mesh.vtu", dataset)["mean"]["psnr"]
            runs[label].append(dict(steps_per_s=sps, steps=m["step"],
                                    optimization_s=m["optimization_seconds"],
                                    vertices=m["vertices"], tets=m["tets"], psnr=psnr))
            print(f"  {label:<28} run {rep + 1}: {sps:6.2f} steps/s ({m['step']} steps in "
                  f"{m['optimization_seconds']:.1f} s, {m['tets']:,} tets), "
                  f"held-out {psnr:.2f} dB", flush=True)
    summary = {k: statistics.median(r["steps_per_s"] for r in v) for k, v in runs.items()}
    print()
    for k, v in summary.items():
        spread = [r["steps_per_s"] for r in runs[k]]
        print(f"{k:<30} median {v:6.2f} steps/s (runs {', '.join(f'{x:.2f}' for x in spread)})")
    if a.code:
        this, other = summary["this checkout"], summary[f"--code {a.code}"]
        print(f"this checkout / --code: {this / other:.2f}x steps per second")
    write_json(a, info, {"runs": runs, "median_steps_per_s": summary})
    return 0


if __name__ == "__main__":
    sys.exit(main())
