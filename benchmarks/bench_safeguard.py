"""Inversion-safeguard benchmark: :func:`mi_tetvr.recon.safeguard.safe_step` on a
jittered (0.2 of a cell, all tets positive) grid of ~1M tets (56^3 cells, 6 tets each = 1.05M tets).

Three steps, each a random per-vertex Gaussian step of standard deviation
``sigma`` times the cell size: small (0.02, nothing to shorten), moderate (0.15,
a few tets would invert) and large (0.5, most tets would invert). For each the
script prints the tets inverted by the raw step, the time of ``safe_step``
(per-vertex and global mode), the number of shortened vertices and the
smallest volume ratio after the safe step. As a baseline, the time of the raw
:func:`mi_tetvr.mesh.signed_volumes` of the mesh (one pass over the tets) is
printed too (the column "x vol pass" is the ratio). Timings (minimum of
``--repeat`` runs) are printed, not asserted.

Usage::

    python benchmarks/bench_safeguard.py            # 56^3 cells (1.05M tets)
    python benchmarks/bench_safeguard.py --quick    # 16^3 cells smoke run
"""
from __future__ import annotations

import os
import platform
import time

import numpy as np

from common import header_info, make_parser, write_json
from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.topology import signed_volumes
from mi_tetvr.recon.safeguard import safe_step


def main(argv=None):
    p = make_parser(__doc__, variant=False, repeat=3, quick="--cells 16")
    p.add_argument("--cells", type=int, default=56)
    p.add_argument("--ratio", type=float, default=0.1, help="min_volume_ratio")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if a.quick:
        a.cells = 16
    info = header_info("safe_step benchmark")
    rows = []
    print(f"# mi_tetvr safe_step benchmark (numpy {np.__version__}, python "
          f"{platform.python_version()}, {os.cpu_count()} CPU cores)")
    v, t = grid_mesh(a.cells, jitter=0.2, seed=a.seed)
    assert np.all(signed_volumes(v, t) > 0)
    h = 2.0 / a.cells
    v0 = signed_volumes(v, t)
    t_vol = np.inf
    for _ in range(a.repeat):
        t0 = time.perf_counter()
        signed_volumes(v, t)
        t_vol = min(t_vol, time.perf_counter() - t0)
    print(f"# mesh: {len(v)} vertices, {len(t)} tets; signed_volumes pass {t_vol * 1e3:.0f} ms")
    rng = np.random.default_rng(a.seed)
    print(f"{'sigma':>6} {'raw inverted':>13} {'mode':>10} {'time ms':>8} {'x vol pass':>10} "
          f"{'shortened':>10} {'inverted':>9} {'min ratio':>9}")
    for sigma in (0.02, 0.15, 0.5):
        d = rng.normal(size=v.shape) * sigma * h
        raw = int(np.count_nonzero(signed_volumes(v + d, t) <= 0))
        for per_vertex in (True, False):
            times = []
            for _ in range(a.repeat):
                t0 = time.perf_counter()
                out, n_short = safe_step(v, t, d, a.ratio, per_vertex=per_vertex)
                times.append(time.perf_counter() - t0)
            dt = min(times)
            vol = signed_volumes(v + out, t)
            print(f"{sigma:6.2f} {raw:13d} {'per-vertex' if per_vertex else 'global':>10} "
                  f"{dt * 1e3:8.0f} {dt / t_vol:10.1f} {n_short:10d} "
                  f"{int(np.count_nonzero(vol <= 0)):9d} {float((vol / v0).min()):9.3f}")
            rows.append(dict(sigma=sigma, raw_inverted=raw,
                             mode="per-vertex" if per_vertex else "global", time_ms=dt * 1e3,
                             over_volume_pass=dt / t_vol, shortened=n_short,
                             inverted=int(np.count_nonzero(vol <= 0)),
                             min_ratio=float((vol / v0).min()), runs_ms=[x * 1e3 for x in times]))
    write_json(a, info, {"mesh": dict(cells=a.cells, vertices=len(v), tets=len(t)),
                         "signed_volumes_ms": t_vol * 1e3, "rows": rows})


if __name__ == "__main__":
    main()
