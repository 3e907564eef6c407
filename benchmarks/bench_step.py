"""Where a walk step's time goes: the code of the walk's loops and timed
variants of them, beside the plain walk (``plain_walk.py``).

Scene and rays as ``bench_render.py`` (a jittered grid carrying the blob
field, pixel-center rays, no early termination). Printed:

1. **The loops' code.** The LLVM IR of the kernels that Dr.Jit generates
   (kernel history with the IR kept), cut into the bodies of their symbolic
   loops, each without the loops nested in it, and counted by kind: gathers
   (reads of memory at per-lane addresses; a tet record read as one 16-byte
   packet counts once), scatters (atomic or per-thread additions into
   gradient buffers, one call per component), divisions, ``floor`` calls
   (one per exponential), selects (among them the loop state kept where a
   lane is done), float arithmetic (``fmul``, ``fadd``, ``fsub``, ``fma``),
   compares, shuffles and inserts (packet reads, constants). This is the
   work of one iteration of 8 rays (AVX2) or 16 (AVX-512). The loops:
   ``tetvr``'s walk (one step: ``tetvr_walk``), its trace loop around the
   walks (once per entry into the mesh and once after the last exit:
   Mitsuba's ray tracer, the entry face, the cursor's first face;
   ``tetvr_walk_trace``), the plain walk (``plain_walk``), and the adjoint
   walk of ``mi.render`` + ``dr.backward`` with gradients on colors,
   opacities and positions (one step).
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
from mi_tetvr.render import cursor  # noqa: E402
from mi_tetvr.render.cursor import WalkSettings  # noqa: E402
from mi_tetvr.render.walk import trace  # noqa: E402
from plain_walk import PlainBuffers, plain_trace  # noqa: E402

#: What the loops' instructions are counted as (LLVM IR).
KINDS = {"gather": r"@llvm\.masked\.gather|@gather_\d+x",
         "scatter": r"call fastcc void @(reduce|scatter)_\w+\(",
         "fdiv": r"= fdiv ", "floor": r"@llvm\.floor",
         "select": r"= select ", "arith": r"= f(mul|add|sub) |@llvm\.fma",
         "compare": r"= [fi]cmp ", "shuffle": r"= (shufflevector|insertelement) "}


def loop_bodies(ir: str) -> dict[str, str]:
    """The body of each symbolic loop in a kernel's LLVM IR, by its label,
    without the loops nested in it (a loop ``l_N`` runs from ``l_N_cond:``,
    which names it, through ``l_N_body:`` to ``l_N_end:``)."""
    spans = {}
    for m in re.finditer(r"^(l_\d+)_cond:\n\s*; Symbolic loop: (\S+)$", ir, re.M):
        name, label = m.group(1), m.group(2)
        body = ir.index(f"{name}_body:", m.end())
        end = ir.index(f"{name}_end:", body)
        spans[label] = (m.start(), body, end)
    out = {}
    for label, (_, body, end) in spans.items():
        inner = sorted((s, e) for lab, (s, _, e) in spans.items()
                       if lab != label and body < s < end)
        parts, at = [], body
        for s, e in inner:
            if s >= at:
                parts.append(ir[at:s])
                at = e
        parts.append(ir[at:end])
        out[label] = "".join(parts)
    return out


def split_branches(body: str) -> tuple[str, str, str]:
    """``(straight, taken, skipped)``: a loop body's code that every
    iteration runs, and the code of the true and false sides of its
    symbolic ``if`` statements (``l_N_t:`` or ``l_N_f:`` up to their
    trailer), which a packet of lanes runs only where one of them takes that
    side. The walk's branches are true where a segment is not empty: a step
    through a medium runs ``straight + taken``, one in empty space
    ``straight + skipped``."""
    parts, at = {"straight": [], "t": [], "f": []}, 0
    for m in re.finditer(r"^(l_\d+)_([tf]):$", body, re.M):
        if m.start() < at:
            continue                                  # (nested in a branch already cut)
        end = body.index(f"{m.group(1)}_{m.group(2)}_trailer:", m.end())
        parts["straight"].append(body[at:m.start()])
        parts[m.group(2)].append(body[m.start():end])
        at = end
    parts["straight"].append(body[at:])
    return tuple("".join(parts[k]) for k in ("straight", "t", "f"))


def n_instructions(code: str) -> int:
    return sum(1 for x in code.splitlines() if x.strip().startswith("%"))


def counts(body: str):
    """Instructions by kind of one iteration through a medium (the code
    outside branches and the true sides, :func:`split_branches`), and how
    many an iteration in empty space runs."""
    straight, taken, skipped = split_branches(body)
    code = straight + taken
    out = {"instructions": n_instructions(code)}
    for name, pattern in KINDS.items():
        out[name] = len(re.findall(pattern, code))
    out["empty space"] = n_instructions(straight + skipped)
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


def adjoint_ir(scene):
    """The IR of the largest kernel of ``mi.render`` and ``dr.backward`` with
    gradients on the volume's colors, opacities and positions (the adjoint
    walk: more operations than the primal's)."""
    params = mi.traverse(scene)
    keys = [k for k in params.keys() if k.split(".")[-1] in
            ("vertex_color", "vertex_opacity", "vertex_positions")]
    for k in keys:
        dr.enable_grad(params[k])
    params.update()

    def run():
        loss = dr.mean(dr.square(mi.render(scene, params, spp=1)), axis=None)
        dr.backward(loss)
        dr.eval([dr.grad(params[k]) for k in keys])
    ir = kernel_ir(run)
    for k in keys:
        dr.disable_grad(params[k])
    params.update()
    return ir


def main(a):
    info = header("walk step profile")
    scene, v, tets, _, _ = grid_scene(a.cells, a.res, min_transmittance=0.0, alpha=False)
    integrator = scene.integrator()
    rays = pixel_rays(scene.sensors()[0], a.res)
    settings = WalkSettings(0.0, integrator.settings.max_steps,
                            integrator.retrace_epsilon * float(dr.norm(scene.bbox().extents())))
    ts = integrator.tet_group(scene)
    dr.eval(ts.buf, ts.params)
    plain = PlainBuffers(ts)
    steps = [0]

    def run_tetvr():
        C, T, n, _ = trace(scene, ts, rays, settings, True)
        dr.eval(C, T, n)
        steps[0] = int(dr.sum(n)[0]) if dr.width(n) else 0
        return C

    def run_plain():
        C, T, n = plain_trace(scene, ts, rays, 0.0, settings.max_steps, "model", plain)
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
    print("The walks' loop bodies (LLVM IR of one iteration, all lanes; nested loops apart):")
    cols = ["instructions"] + list(KINDS) + ["empty space"]
    print(f"{'':<24}" + "".join(f"{c:>13}" for c in cols))
    forward = loop_bodies(kernel_ir(run_tetvr))
    # (a mesh that is not convex is traced again after each exit: the trace
    # loop around the walks, counted on this grid by pretending it is not
    # convex; checkouts before the convex walk have only that loop)
    convex_scene = getattr(cursor, "convex_scene", None)
    cursor.convex_scene = lambda scene: False
    try:
        general = loop_bodies(kernel_ir(run_tetvr))
    finally:
        cursor.convex_scene = convex_scene
    rows = (("tetvr walk, a step", forward, "tetvr_walk"),
            ("plain walk, a step", loop_bodies(kernel_ir(run_plain)), "plain_walk"),
            ("adjoint walk, a step", loop_bodies(adjoint_ir(scene)), "tetvr_walk"),
            ("trace loop, an entry *", general, "tetvr_walk_trace"))
    for name, bodies, label in rows:
        c = counts(bodies.get(label, ""))
        results["loops"][name] = c
        print(f"{name:<24}" + "".join(f"{c[k]:>13}" for k in cols))
    print("(a step through a medium; 'empty space': the instructions of a step through a "
          "segment of zero extinction, which skips the integral's branch)")
    print("(* a mesh that is not convex: the loop that traces each ray again after it leaves "
          "the mesh, besides its walk; a convex mesh is traced once, without it)")
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
