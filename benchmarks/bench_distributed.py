"""Beyond one machine: a partitioned mesh over Ray workers, and many frames
over them.

1. *Scale*: a regular tet grid of about ``--tets`` tets (6 per cell; a smooth
   scalar shown by a transfer function) is written block by block as
   ``--blocks`` pieces of a ``.pvtu`` (the whole mesh is never held), then
   rendered by ``--blocks`` workers started one after the other (each loads
   its pieces before the next starts). Printed: the time to write, to the
   first image and per frame, each worker's peak memory (its process's
   resident set). Then one process is given the largest worker's peak as its
   memory limit (``RLIMIT_AS``, the address space, plus what the process held
   before loading) and asked to load block 0 (the control: it fits) and the
   whole mesh (the pieces joined, as ``render OUT.pvtu`` without workers does).
2. *Frames*: a time series of ``--frames`` meshes (``--cells``^3 grids with a
   moving field) rendered by ``render``'s frame loop in this process and by
   1 and 2 Ray workers (each keeps its kernels for its frames); frames per
   second after the cluster has started (its start is printed apart), the
   speed-up against one worker.

Usage::

    python benchmarks/bench_distributed.py                   # 100M tets, 24 frames
    python benchmarks/bench_distributed.py --quick           # 100k tets, 6 frames
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import header, make_parser, write_json


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=3, quick="--tets 1e5 --frames 6 --cells 10 --res 64")
    p.add_argument("--tets", type=float, default=100e6, help="tets of the partitioned grid "
                   "(default 1e8)")
    p.add_argument("--blocks", type=int, default=4, help="blocks and workers (default 4)")
    p.add_argument("--res", type=int, default=256, help="image width = height (default 256)")
    p.add_argument("--frames", type=int, default=24, help="frames of the time series")
    p.add_argument("--cells", type=int, default=40, help="cells per axis of each frame's "
                   "mesh (default 40: 384k tets)")
    p.add_argument("--dir", default=None, help="where the partitioned grid is written "
                   "(default: a temporary folder, removed after)")
    p.add_argument("--skip", choices=["scale", "frames"], action="append", default=[],
                   help="leave a part out")
    p.add_argument("--limited", help=argparse.SUPPRESS)     # (the child process's part)
    a = p.parse_args(argv)
    if a.quick:
        a.tets, a.frames, a.cells, a.res = 1e5, 6, 10, 64
    return a


def field(points):
    import numpy as np
    x, y, z = points.T
    return {"scalar": (np.exp(-4 * (x * x + y * y + z * z)) + 0.3 * np.sin(5 * x) * y)
            .astype(np.float32)}


def limited_load(pvtu, which, limit):
    """(in a child process) load block 0 or the whole mesh as a ``tetmesh``
    under an address-space limit of ``limit`` bytes above what is held now."""
    import resource

    import mitsuba as mi
    mi.set_variant(ARGS.variant)
    import mi_tetvr  # noqa: F811 (the child process exits before the module's import)
    from mi_tetvr.mesh.partition import read_partition, read_piece
    part = read_partition(pvtu)
    with open("/proc/self/status") as f:
        held = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize"))
    resource.setrlimit(resource.RLIMIT_AS, (held + limit, held + limit))
    try:
        if which == "block":
            V, T, pd, _, _ = read_piece(part, 0)
        else:
            mesh = mi_tetvr.read_tetmesh(pvtu, color=None, opacity=None)
            V, T, pd = mesh.vertices, mesh.tets, mesh.point_data
        shape = mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(
            V, T, scalar=pd["scalar"], transfer_function="viridis"))
        print(json.dumps({"loaded": True, "tets": int(len(T))}))
        del shape
    except MemoryError:
        print(json.dumps({"loaded": False, "error": "MemoryError"}))
    except Exception as e:       # an allocation refused deep inside a library
        print(json.dumps({"loaded": False, "error": f"{type(e).__name__}: {e}"[:200]}))


ARGS = parse_args()
if ARGS.limited:
    limited_load(*json.loads(ARGS.limited))
    sys.exit(0)

import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402,F401


def scale(root):
    from mi_tetvr.apps.framing import framed_scene, mesh_framing, shape_props
    from mi_tetvr.apps.settings import RenderSettings
    from mi_tetvr.distributed import PartitionedMesh
    from mi_tetvr.mesh.partition import write_grid_partition
    n = max(2, int(np.ceil((ARGS.tets / 6) ** (1 / 3) - 1e-9)))
    shape = (n, n, n)
    pvtu = Path(root) / "grid.pvtu"
    t0 = time.time()
    part = write_grid_partition(shape, pvtu, ARGS.blocks, field)
    t_write = time.time() - t0
    disk = sum(f.stat().st_size for f in (Path(root) / "grid").iterdir())
    print(f"grid of {n}^3 cells: {part.tets:,} tets, {part.vertices:,} points in "
          f"{ARGS.blocks} pieces of {min(b.tets for b in part.blocks):,} to "
          f"{max(b.tets for b in part.blocks):,} tets, written in {t_write:.1f} s "
          f"({disk / 2**30:.2f} GiB)")
    s = RenderSettings(tf="viridis", res=(ARGS.res, ARGS.res), view=(30.0, 20.0))
    framing = mesh_framing([(part.bounds[0], part.bounds[1], "scalar",
                             part.point_ranges["scalar"])])
    scene = mi.load_dict(framed_scene(s, framing))
    t0 = time.time()
    with PartitionedMesh(pvtu, ARGS.blocks, shape_props(s, framing), stagger=True) as pm:
        t_load = time.time() - t0
        img = np.array(pm.render(scene))
        t_first = time.time() - t0
        frames = []
        for _ in range(ARGS.repeat):
            t = time.time()
            np.array(pm.render(scene))
            frames.append(time.time() - t)
        memory = pm.peak_memory()
    print(f"{ARGS.blocks} workers: started and loaded in {t_load:.1f} s, first image "
          f"({ARGS.res}x{ARGS.res}) after {t_first:.1f} s; a frame in "
          f"{np.median(frames):.2f} s (min {min(frames):.2f}, max {max(frames):.2f}, "
          f"{ARGS.repeat} runs)")
    print("peak memory per worker: " + ", ".join(f"{m / 2**30:.2f} GiB" for m in memory)
          + f" ({max(memory) / (part.tets / ARGS.blocks):.0f} B per tet of a block)")
    limit = max(memory)
    loads = {}
    for which in ("block", "whole"):
        r = subprocess.run([sys.executable, __file__, "--variant", ARGS.variant, "--limited",
                            json.dumps([str(pvtu), which, limit])],
                           capture_output=True, text=True)
        lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
        loads[which] = json.loads(lines[-1]) if lines else {
            "loaded": False, "error": f"exit {r.returncode}: {r.stderr.strip()[-200:]}"}
        print(f"one process limited to {limit / 2**30:.2f} GiB of address space: "
              f"{'block 0' if which == 'block' else 'the whole mesh'} "
              + ("loads" if loads[which]["loaded"] else
                 f"does not load ({loads[which]['error']})"))
    return {"cells": n, "tets": part.tets, "vertices": part.vertices, "write_s": t_write,
            "disk_bytes": disk, "load_s": t_load, "first_image_s": t_first, "frame_s": frames,
            "peak_memory": memory, "limited_loads": loads,
            "image_max": float(img[..., :3].max())}


def frames(root):
    from mi_tetvr.apps.framing import mesh_extent, mesh_framing
    from mi_tetvr.apps.settings import RenderSettings
    from mi_tetvr.cli.render import FrameRenderer
    from mi_tetvr.cluster import connect
    from mi_tetvr.distributed import map_frames
    from mi_tetvr.mesh.generate import grid_mesh
    from mi_tetvr.mesh.io import read_tetmesh, write_tetmesh
    from mi_tetvr.mesh.tetmesh import TetMesh
    import ray
    V, T = grid_mesh(ARGS.cells, jitter=0.15)
    paths = []
    for k in range(ARGS.frames):
        f = field(V + np.array([0.6 * k / max(ARGS.frames, 1), 0.0, 0.0]))
        path = Path(root) / f"series_{k:03d}.vtu"
        write_tetmesh(path, TetMesh(V, T, point_data=f), color=None, opacity=None)
        paths.append(path)
    s = RenderSettings(tf="viridis", res=(ARGS.res, ARGS.res))
    framing = mesh_framing([mesh_extent(s, read_tetmesh(p, color=None, opacity=None), p)
                            for p in paths])
    calls = [(p,) for p in paths]
    out = {}
    r = FrameRenderer(s, framing, ARGS.variant)
    r.series_frame(paths[0])                      # (kernels compiled)
    t = time.time()
    for c in calls:
        r.series_frame(*c)
    out["this process"] = time.time() - t
    t = time.time()
    connect(2)
    out["cluster start"] = time.time() - t
    for w in (1, 2):
        t = time.time()
        map_frames(FrameRenderer, (s, framing, ARGS.variant), "series_frame", calls, w)
        out[f"{w} workers"] = time.time() - t
    ray.shutdown()
    n = ARGS.frames
    print(f"time series of {n} meshes of {len(T):,} tets at {ARGS.res}x{ARGS.res} "
          f"(the cluster started in {out['cluster start']:.1f} s):")
    for k in ("this process", "1 workers", "2 workers"):
        print(f"  {k:>13}: {out[k]:6.1f} s, {n / out[k]:5.2f} frames/s"
              + (f", x{out['1 workers'] / out[k]:.2f} of 1 worker" if "workers" in k else ""))
    return {"tets": len(T), "seconds": out,
            "fps": {k: n / v for k, v in out.items() if k != "cluster start"}}


def main():
    info = header("distributed: partitioned mesh over Ray workers, frames over workers")
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = ARGS.dir or tmp
        os.makedirs(root, exist_ok=True)
        if "scale" not in ARGS.skip:
            results["scale"] = scale(root)
        if "frames" not in ARGS.skip:
            results["frames"] = frames(tmp)
    write_json(ARGS, info, results)


if __name__ == "__main__":
    main()
