"""The Dr.Jit kernels a plain color scene compiles, by hash: a change that must cost such
scenes nothing (a new optical model, a hook in the walk) leaves them equal, and then
there is nothing to time. Compare two trees::

    python benchmarks/kernel_hashes.py
    python benchmarks/checkout_cli.py BASE benchmarks/kernel_hashes.py

Scene: the jittered ``cells^3`` grid with the blob field's colors and opacities, one
``mi.render`` and one ``mi.render`` + ``dr.backward`` w.r.t. the colors, opacities and
positions; the kernels with the most operations are listed (hash, operations)."""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import grid_scene, header, make_parser, write_json  # noqa: E402

KEYS = ("volume.vertex_color", "volume.vertex_opacity", "volume.vertex_positions")


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=None, quick="--cells 4 --res 16")
    p.add_argument("--cells", type=int, default=6, help="grid cells per axis (default 6)")
    p.add_argument("--res", type=int, default=32, help="image side (default 32)")
    p.add_argument("--top", type=int, default=4, help="kernels listed (default 4)")
    a = p.parse_args(argv)
    if a.quick:
        a.cells, a.res = 4, 16
    return a


def main(argv=None):
    a = parse_args(argv)
    import drjit as dr
    import mitsuba as mi
    mi.set_variant(a.variant)

    import mi_tetvr
    info = header("kernel hashes of a plain color scene")
    scene = grid_scene(a.cells, a.res)[0]
    params = mi.traverse(scene)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()                     # (empties it)
    dr.eval(mi.render(scene, spp=1))
    for k in KEYS:
        dr.enable_grad(params[k])
    img = mi.render(scene, params, spp=1)
    dr.backward(dr.sum(img * img, axis=None))
    dr.eval([dr.grad(params[k]) for k in KEYS])
    launched = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    top = sorted(launched, key=lambda k: -k.get("operation_count", 0))[:a.top]
    print(f"mi_tetvr from {Path(mi_tetvr.__file__).parent}")
    for k in top:
        print(f"{k['hash']}  {k.get('operation_count', 0):6d} operations")
    hashes = [k["hash"] for k in top]
    write_json(a, info, {"hashes": hashes})
    return hashes


if __name__ == "__main__":
    main()
