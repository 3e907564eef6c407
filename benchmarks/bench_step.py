"""Where a walk step's time goes: the code of the walk's loop and timed
variants of it, beside the plain walk (``plain_walk.py``).

Scene and rays as ``bench_render.py`` (a jittered grid carrying the blob
field, pixel-center rays, no early termination). Printed:

1. **The loop's code.** The LLVM IR of the kernel that Dr.Jit generates for
   one image (kernel history with the IR kept), cut to the body of the
   walk's symbolic loop (``tetvr_walk``; ``plain_walk`` for the baseline):
   its instructions by kind: gathers (reads of memory at per-lane
   addresses), divisions, ``floor`` calls (one per exponential), selects
   (among them the loop state kept where a lane is done), float arithmetic
   (``fmul``, ``fadd``, ``fsub``, ``fma``), compares, shuffles and inserts
   (packet reads, constants).
   This is the work of one step of 8 rays (AVX2) or 16 (AVX-512).
2. **Timed variants** (median of ``--repeat`` warm runs, each in the same
   process on the same rays): the walk as it is; the same walk with a
   trivial segment integral (``C = c0 tau``, ``T = 1 - tau``: what the
   integral costs); and the plain walk with the same two integrals.

Usage::

    python benchmarks/bench_step.py            # 64^3 cells, 384x384
    python benchmarks/bench_step.py --quick    # 16^3 cells, 96x96
"""
from __future__ import annotations

import re
import sys

from common import grid_scene, header, make_parser, pixel_rays, timed, write_json


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=5, quick="--cells 16 --res 96")
    p.add_argument("--cells", type=int, default=64, help="grid cells per axis (default 64)")
    p.add_argument("--res", type=int, default=384, help="image width = height (default 384)")
    a = p.parse_args(argv)
    if a.quick:
        a.cells, a.res = 16, 96
    return a


ARGS = parse_args()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant(ARGS.variant)

import mi_tetvr  # noqa: E402,F401
from mi_tetvr.render.cursor import WalkSettings  # noqa: E402
from mi_tetvr.render.walk import trace  # noqa: E402
from plain_walk import plain_trace  # noqa: E402

#: What the loop's instructions are counted as (LLVM IR).
KINDS = {"gather": r"@llvm\.masked\.gather", "fdiv": r"= fdiv ", "floor": r"@llvm\.floor",
         "select": r"= select ", "arith": r"= f(mul|add|sub) |@llvm\.fma",
         "compare": r"= [fi]cmp ", "shuffle": r"= (shufflevector|insertelement) "}


def loop_body(ir: str, label: str) -> str:
    """The body of the symbolic loop named ``label`` in a kernel's LLVM IR."""
    at = ir.find(f"; Symbolic loop: {label}")
    if at < 0:
        return ""
    start = ir.find("_body:", at)
    end = ir.find("_end:", start)
    return ir[start:end]


def counts(body: str):
    lines = [x for x in body.splitlines() if x.strip().startswith("%")]
    out = {"instructions": len(lines)}
    for name, pattern in KINDS.items():
        out[name] = len(re.findall(pattern, body))
    return out


def kernel_ir(fn):
    """The IR of the largest kernel ``fn`` launches."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    fn()
    history = dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    big = max(history, key=lambda k: k.get("operation_count", 0))
    return big["ir"].getvalue() if hasattr(big["ir"], "getvalue") else str(big["ir"])


def main(a):
    info = header("walk step profile")
    scene, v, tets, _, _ = grid_scene(a.cells, a.res, min_transmittance=0.0, alpha=False)
    integrator = scene.integrator()
    rays = pixel_rays(scene.sensors()[0], a.res)
    settings = WalkSettings(0.0, integrator.settings.max_steps,
                            integrator.retrace_epsilon * float(dr.norm(scene.bbox().extents())))
    ts = integrator.tet_group(scene)
    dr.eval(ts.buf, ts.params)
    steps = [0]

    def run_tetvr():
        C, T, n, _ = trace(scene, ts, rays, settings, True)
        dr.eval(C, T, n)
        steps[0] = int(dr.sum(n)[0]) if dr.width(n) else 0
        return C

    def run_plain():
        C, T, n = plain_trace(scene, ts, rays, 0.0, settings.max_steps, "model")
        dr.eval(C, T, n)
        return C

    model = type(ts.model)
    exact = model.segment

    def trivial(self, params, length, a0, a1):
        tau = length * (a0.s + a1.s) * 0.5
        return a0.c * tau, 1.0 - tau, tau

    results = {"mesh": dict(cells=a.cells, tets=len(tets)), "res": a.res, "loops": {},
               "times": {}}
    print(f"mesh: {a.cells}^3 cells, {len(tets):,} tets; {a.res}x{a.res} pixel-center rays, "
          f"no early termination")
    print()
    print("The walk's loop body (LLVM IR of one step, all lanes):")
    cols = ["instructions"] + list(KINDS)
    print(f"{'':<14}" + "".join(f"{c:>13}" for c in cols))
    for name, fn, label in (("tetvr walk", run_tetvr, "tetvr_walk"),
                            ("plain walk", run_plain, "plain_walk")):
        c = counts(loop_body(kernel_ir(fn), label))
        results["loops"][name] = c
        print(f"{name:<14}" + "".join(f"{c[k]:>13}" for k in cols))
    print()
    print(f"{'variant':<44}{'median [s]':>11}{'Msteps/s':>10}   runs [s]")
    for name, fn, integral in (("tetvr walk", run_tetvr, exact),
                               ("tetvr walk, trivial integral", run_tetvr, trivial),
                               ("plain walk", run_plain, exact),
                               ("plain walk, trivial integral", run_plain, trivial)):
        model.segment = integral
        try:
            _, med, runs, _ = timed(fn, a.repeat)
        finally:
            model.segment = exact
        results["times"][name] = dict(median_s=med, runs_s=runs)
        n = steps[0] or 1
        print(f"{name:<44}{med:>11.3f}{n / med / 1e6:>10.1f}   "
              + ", ".join(f"{t:.3f}" for t in runs))
    t = results["times"]
    share = 1.0 - t["tetvr walk, trivial integral"]["median_s"] / t["tetvr walk"]["median_s"]
    ratio = t["plain walk"]["median_s"] / t["tetvr walk"]["median_s"]
    print()
    print(f"the segment integral: {100 * share:.0f} % of tetvr's walk; plain walk / tetvr walk: "
          f"{ratio:.2f}x")
    results["integral_share"] = share
    results["plain_over_tetvr"] = ratio
    write_json(a, info, results)
    return 0


if __name__ == "__main__":
    sys.exit(main(ARGS))
