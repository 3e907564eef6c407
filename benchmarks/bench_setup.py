"""A fit's first-stage set-up: what ``mi-tetvr fit`` does between the initial mesh and the
first step (the topology, the mesh summary it prints, the trainer with its scene), on a
regular grid of ``--grid`` cells (6 tets each), against another checkout (``--code DIR``),
the two run in alternation, ``--repeat`` times each.

    python benchmarks/bench_setup.py --code ../before --grid 64

Both run this file's :func:`setup_seconds` with their own code, as their ``run`` does it: a
checkout whose ``Trainer`` takes the ``topology`` builds it once and hands it on (to the
trainer and its ``tetmesh``); an earlier one builds it for the summary, in the trainer and
in the shape. Prints the seconds and the ratio per round and the median ratio.
"""
from __future__ import annotations

import argparse
import inspect
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import header, make_parser, write_json  # noqa: E402


def setup_seconds(grid, variant):
    """Seconds of the set-up on a grid of ``grid`` cells, in this process's code."""
    import mitsuba as mi
    mi.set_variant(variant)
    import mi_tetvr
    mi_tetvr.register()
    from mi_tetvr.mesh.initial import grid_init
    from mi_tetvr.mesh.topology import build_topology, format_summary, geometry_summary
    from mi_tetvr.camera import fibonacci_cameras
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import Dataset, View
    from mi_tetvr.recon.trainer import Trainer
    cams = fibonacci_cameras(4, 4.0, 32, 40.0)
    image = np.zeros((32, 32, 4), np.float32)
    data = Dataset([View(f"v{i}", c, image) for i, c in enumerate(cams[:3])],
                   [View("t", cams[3], image)])
    vertices, tets = grid_init([[-1, -1, -1], [1, 1, 1]], grid)
    cfg = FitConfig()
    hand_on = "topology" in inspect.signature(Trainer).parameters
    t0 = time.perf_counter()
    if hand_on:
        topology = build_topology(vertices, tets)
        format_summary(geometry_summary(vertices, topology))
        trainer = Trainer(data, vertices, tets, cfg, topology=topology)
    else:
        format_summary(geometry_summary(vertices, build_topology(vertices, tets, warn=False)))
        trainer = Trainer(data, vertices, tets, cfg)
    seconds = time.perf_counter() - t0
    return {"seconds": seconds, "tets": len(trainer.tets), "hands_on": hand_on}


def run_in(code, grid, variant):
    """:func:`setup_seconds` in a fresh process of the checkout ``code`` (None: this one)."""
    me = str(Path(__file__).resolve())
    args = [me, "--worker", "--grid", str(grid), "--variant", variant]
    if code:
        from checkout_cli import command
        cmd = command(code) + args
    else:
        cmd = [sys.executable] + args
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(r.stderr[-2000:])
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv=None):
    p = make_parser(__doc__, repeat=3, quick="--grid 8, one round, this checkout only")
    p.add_argument("--grid", type=int, default=64, help="grid cells per axis (default 64: "
                   "1.57M tets)")
    p.add_argument("--code", help="the other checkout (e.g. a worktree of an earlier commit)")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.worker:                     # one measurement, in this process's code
        print(json.dumps(setup_seconds(a.grid, a.variant)))
        return
    if a.quick:
        a.grid, a.repeat, a.code = 8, 1, None
    info = header(f"fit set-up on a {a.grid}^3 grid")
    rounds = []
    for i in range(a.repeat):
        this = run_in(None, a.grid, a.variant)
        other = run_in(a.code, a.grid, a.variant) if a.code else None
        rounds.append({"this": this, "code": other})
        line = f"round {i + 1}: this {this['seconds']:.2f} s ({this['tets']:,} tets)"
        if other:
            line += (f", code {other['seconds']:.2f} s: this / code "
                     f"{this['seconds'] / other['seconds']:.2f}x")
        print(line)
    if a.code:
        ratios = [r["this"]["seconds"] / r["code"]["seconds"] for r in rounds]
        print(f"this / code: median {np.median(ratios):.2f}x (range {min(ratios):.2f}-"
              f"{max(ratios):.2f}x over {len(ratios)} rounds)")
    write_json(a, info, {"rounds": rounds})


if __name__ == "__main__":
    main()
