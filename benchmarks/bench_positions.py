"""Joint color + position fitting against color-only, at equal vertex count,
and how far the inversion safeguard lets the position learning rate go.

Data: the project's default volume (``scenes/tf_default.json``) rendered by the
grid ray marcher (``--views`` training + 8 test views at ``--res``). Mesh: the
same regular grid for every run. For each position learning rate (in cell sizes
per step) the fit runs with the regularizer and the safeguard, and without
either; it prints held-out PSNR, inverted tets at the end, vertices whose step
the safeguard shortened, and time.

Usage::

    python benchmarks/bench_positions.py                 # 200 steps per run
    python benchmarks/bench_positions.py --steps 100 --lrs 0.1,1
    python benchmarks/bench_positions.py --quick         # smoke run
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

from common import header, make_parser, write_json


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=None,
                    quick="--steps 5 --res 16 --views 4 --grid-resolution 4 --lrs 0.3")
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--res", type=int, default=64)
    p.add_argument("--views", type=int, default=32)
    p.add_argument("--grid-resolution", type=int, default=16,
                   help="grid cells along the largest axis")
    p.add_argument("--lrs", default="0.03,0.1,0.3,1.0",
                   help="position learning rates in cell sizes per step")
    a = p.parse_args(argv)
    if a.quick:
        a.steps, a.res, a.views, a.grid_resolution, a.lrs = 5, 16, 4, 4, "0.3"
    return a


ARGS = parse_args()

import mitsuba as mi  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402,F401
from mi_tetvr.recon.datasets import load_nerf  # noqa: E402
from mi_tetvr.recon.config import FitConfig  # noqa: E402
from mi_tetvr.recon.pipeline import run  # noqa: E402
from mi_tetvr.mesh.scenes import default_volume  # noqa: E402
from mi_tetvr.transfer import read_transfer_function  # noqa: E402
from mi_tetvr.grid import make_volume  # noqa: E402
from mi_tetvr.recon.synthetic import make_dataset  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main(a):
    info = header("position fitting benchmark")
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="bench_positions_"))
    tf = read_transfer_function(ROOT / "scenes" / "tf_default.json")
    make_dataset(make_volume(default_volume(64)), tf, views=a.views, res=a.res,
                 out_dir=tmp / "data", test_views=8, fov=30, progress=False)
    data = load_nerf(tmp / "data")
    base = FitConfig(grid_resolution=a.grid_resolution, iterations=a.steps, views_per_step=4,
                     lr_color=0.03, lr_opacity=0.1, n_sub=4, jitter=False)
    runs = [("color only", base)]
    for lr in (float(x) for x in a.lrs.split(",")):
        runs.append(("joint, safeguard + regularizer", base.updated(lr_position=lr)))
        runs.append(("joint, unprotected", base.updated(lr_position=lr, safeguard=False,
                                                          regularizer=0.0)))
    print(f"{'run':32s} {'lr_pos':>7s} {'test PSNR':>9s} {'inverted':>9s} {'shortened':>10s} "
          f"{'time [s]':>9s}")
    for i, (name, cfg) in enumerate(runs):
        t0 = time.perf_counter()
        m = run(data, tmp / f"run{i}", cfg, resume=False, progress=False, log=lambda *x: None)
        dt = time.perf_counter() - t0
        print(f"{name:32s} {cfg.trainer.lr_position:7.2f} {m['mean']['psnr']:9.2f} "
              f"{m['inverted_tets']:9d} {m['shortened_position_steps']:10d} "
              f"{dt:9.1f}", flush=True)
        rows.append(dict(run=name, lr_position=cfg.trainer.lr_position, test_psnr=m["mean"]["psnr"],
                         inverted=m["inverted_tets"], shortened=m["shortened_position_steps"],
                         time_s=dt))
    print(f"({m['vertices']:,} vertices, {m['tets']:,} tets; {a.steps} steps of 4 views at "
          f"{a.res}x{a.res}; 'shortened' counts vertex steps cut by the safeguard)")
    write_json(a, info, {"vertices": m["vertices"], "tets": m["tets"], "rows": rows})


if __name__ == "__main__":
    main(ARGS)
