"""Render + ``dr.backward`` of two checkouts, alternated in separate processes::

    python benchmarks/compare_backward.py BASE_DIR NEW_DIR [--rounds 3]

Each process imports ``mi_tetvr`` from its checkout, renders the 64^3 jittered
grid (1.57M tets) at 256x256 with ``tetvr`` with colors, opacities and
positions differentiated, and prints the fastest of 5 warm runs of the render
alone and of render + ``dr.backward``. Alternating processes and taking the
fastest run keep the machine's noise out of the comparison as far as it goes.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

CHILD = """
import sys, time
sys.path.insert(0, sys.argv[1]); sys.path.insert(0, sys.argv[1] + "/benchmarks")
import drjit as dr, mitsuba as mi
mi.set_variant("llvm_ad_rgb")
import mi_tetvr  # noqa: F401
from common import grid_scene
scene = grid_scene(64, 256)[0]
params = mi.traverse(scene)
keys = [k for k in params.keys()
        if k.endswith(("vertex_color", "vertex_opacity", "vertex_positions"))]

def fastest(grad):
    for k in keys:
        (dr.enable_grad if grad else dr.disable_grad)(params[k])
    params.update()
    times = []
    for _ in range(6):
        t = time.perf_counter()
        img = mi.render(scene, params, seed=0)
        if grad:
            dr.backward(dr.sum(img * img))
            dr.eval([dr.grad(params[k]) for k in keys])
        else:
            dr.eval(img)
        dr.sync_thread()
        times.append(time.perf_counter() - t)
        for k in keys:
            dr.clear_grad(params[k])
    return min(times[1:])

p, b = fastest(False), fastest(True)
print(f"render {p:.3f} s, render + backward {b:.3f} s, ratio {b / p:.2f}")
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dirs", nargs=2, help="the two checkouts (base first)")
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    for d in a.dirs:
        if not (Path(d) / "mi_tetvr" / "__init__.py").is_file():
            sys.exit(f"compare_backward: {d} is not a checkout of mi_tetvr "
                     f"(no mi_tetvr/__init__.py)")
    for r in range(a.rounds):
        for d in a.dirs:
            out = subprocess.run([sys.executable, "-c", CHILD, str(Path(d).resolve())],
                                 capture_output=True, text=True)
            line = out.stdout.strip().splitlines()[-1] if out.returncode == 0 else \
                f"failed: {out.stderr.strip()[-200:]}"
            print(f"round {r + 1} {d}: {line}", flush=True)


if __name__ == "__main__":
    main()
