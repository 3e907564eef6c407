"""Backward-pass benchmark: one ``mi.render`` + ``dr.backward`` against one
primal ``mi.render``, measured in the same run.

Scene: the jittered ``cells^3`` grid (64^3 = 1.57M tets) with the blob field,
``res x res`` pixel-center rays, default tetvr settings. The loss is the L2
distance to a target image rendered with perturbed colors and opacities;
gradients go to ``vertex_color``, ``vertex_opacity`` and ``vertex_positions``.
``mi.render`` with gradients runs the primal pass, then ``tetvr``'s
``render_backward`` runs the adjoint pass on the same rays, from the per-ray
values the primal pass kept (:mod:`mi_tetvr.render.replay`: no second primal
render); the breakdown rows time the parameter kinds and the adjoint pass
alone and compare the scatter strategies (``reduce_mode``) of the gradient
accumulation.

Usage::

    python benchmarks/bench_backward.py            # 64^3 cells, 256x256
    python benchmarks/bench_backward.py --quick    # 16^3 cells, 64x64
    python benchmarks/bench_backward.py --code ../before --rounds 3   # against another checkout

With ``--code DIR`` the script runs in turns with this checkout's package and
with ``DIR``'s (each run in a process of its own, ``--rounds`` times; each
with its integrator's default ``reduce_mode``) and prints render + backward /
render of both, per round and over the rounds.
"""
from __future__ import annotations

from common import (add_code_options, alternate, check_code, grid_scene, header, make_parser,
                    spread, timed, write_json)


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=3, quick="--cells 16 --res 64")
    p.add_argument("--cells", type=int, default=64, help="grid cells per axis (default 64)")
    p.add_argument("--res", type=int, default=256, help="image width = height (default 256)")
    p.add_argument("--n-sub", type=int, default=4, help="tetvr n_sub (default 4, as tetvr)")
    p.add_argument("--modes", default="auto,direct,local",
                   help="tetvr's reduce modes to compare (default auto,direct,local; also "
                        "expand)")
    add_code_options(p)
    a = p.parse_args(argv)
    check_code(p, a)
    if a.quick:
        a.cells, a.res = 16, 64
    return a


ARGS = parse_args()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402,F401

KEYS = ("volume.vertex_color", "volume.vertex_opacity", "volume.vertex_positions")


def compare(a):
    """This checkout against ``--code``, in turns (see the module docstring)."""
    argv = ["--cells", str(a.cells), "--res", str(a.res), "--n-sub", str(a.n_sub),
            "--repeat", str(a.repeat), "--variant", a.variant, "--modes", "auto"]
    info = header("backward benchmark, this checkout against --code " + str(a.code))
    rounds = alternate(__file__, argv, a.code, a.rounds)
    rows = []
    print(f"{'round':<7}{'render this':>12}{'+ backward':>12}{'ratio':>8}"
          f"{'render --code':>15}{'+ backward':>12}{'ratio':>8}")
    for r, row in enumerate(rounds):
        x = {}
        for name, res in row.items():
            by = {b["name"]: b for b in res["rows"]}
            x[name] = (by["primal mi.render"]["median_s"],
                       by["render + backward, all 3, reduce=auto"]["median_s"])
        rows.append(dict(this_primal_s=x["this"][0], this_backward_s=x["this"][1],
                         other_primal_s=x["other"][0], other_backward_s=x["other"][1],
                         this_ratio=x["this"][1] / x["this"][0],
                         other_ratio=x["other"][1] / x["other"][0]))
        y = rows[-1]
        print(f"{r + 1:<7}{y['this_primal_s']:>11.3f}s{y['this_backward_s']:>11.3f}s"
              f"{y['this_ratio']:>7.2f}x{y['other_primal_s']:>14.3f}s{y['other_backward_s']:>11.3f}s"
              f"{y['other_ratio']:>7.2f}x")
    print()
    print(f"render + backward / render: this {spread([y['this_ratio'] for y in rows])}x, --code "
          f"{spread([y['other_ratio'] for y in rows])}x; render + backward this / --code "
          f"{spread([y['this_backward_s'] / y['other_backward_s'] for y in rows])}x "
          f"(median [range] of {len(rows)} rounds)")
    write_json(a, info, {"code": a.code, "rounds": rows, "runs": rounds})
    return 0


def main(a):
    if a.code:
        return compare(a)
    info = header("backward benchmark")
    scene, v, tets, color, opacity = grid_scene(a.cells, a.res, n_sub=a.n_sub)
    print(f"mesh: {a.cells}^3 cells, {len(tets):,} tets; image {a.res}x{a.res}, 1 spp")
    params = mi.traverse(scene)
    # Target: the same mesh with perturbed attributes.
    base = {k: mi.Float(params[k]) for k in KEYS}
    params["volume.vertex_color"] = dr.clip(base["volume.vertex_color"] * 0.8 + 0.1, 0, 1)
    params["volume.vertex_opacity"] = base["volume.vertex_opacity"] * 1.3
    params.update()
    target = mi.TensorXf(mi.render(scene, spp=1))
    for k in KEYS:
        params[k] = base[k]
    params.update()
    dr.eval(target)

    def primal():
        img = mi.render(scene, spp=1)
        dr.eval(img)
        return img

    def backward(keys):
        def run():
            for k in KEYS:
                dr.disable_grad(params[k])
            for k in keys:
                dr.enable_grad(params[k])
            img = mi.render(scene, params, spp=1)
            loss = dr.mean(dr.square(img - target), axis=None)
            dr.backward(loss)
            grads = [dr.grad(params[k]) for k in keys]
            dr.eval(grads)
            return grads
        return run

    rows = []
    p_first, p_med, p_all, _ = timed(primal, a.repeat)
    rows.append(("primal mi.render", p_first, p_med, p_all))
    integrator = scene.integrator()
    # ("auto": tetvr's default, the walk's own choice per backend)
    modes = {"auto": integrator.settings.reduce, "local": dr.ReduceMode.Local,
             "direct": dr.ReduceMode.Direct, "expand": dr.ReduceMode.Expand}
    results = {}
    # (tetvr's default first: the rows below and the headline ratio use it)
    for name in ["auto"] + [m for m in a.modes.split(",") if m != "auto"]:
        integrator.settings.reduce = modes[name]
        f, m, al, grads = timed(backward(KEYS), a.repeat)
        results[name] = m
        rows.append((f"render + backward, all 3, reduce={name}", f, m, al))
    best = min(results, key=results.get)
    integrator.settings.reduce = modes["auto"]
    f, m, al, _ = timed(backward(KEYS[:2]), a.repeat)
    results["colors_opacities"] = m
    rows.append(("render + backward, colors and opacities", f, m, al))
    for k in KEYS:
        f, m, al, _ = timed(backward((k,)), a.repeat)
        rows.append((f"render + backward, {k.split('.')[-1]} only", f, m, al))
    # The adjoint pass alone: sample() in backward mode on the pixel rays.
    for k in KEYS:
        dr.enable_grad(params[k])
    sensor = scene.sensors()[0]
    with dr.suspend_grad():
        sampler, _ = integrator.prepare(sensor, 0, 1, integrator.aov_names())
        ray, _, _ = integrator.sample_rays(scene, sensor, sampler)
        dr.eval(ray)
        L, _, aovs, state = integrator.sample(dr.ADMode.Primal, scene, None, ray, None,
                                              None, True)
        dr.eval(L, aovs, state)
    δL = mi.Color3f(1.0)

    def adjoint():
        with dr.suspend_grad():
            integrator.sample(dr.ADMode.Backward, scene, None, ray, δL, state, True,
                              δaovs=[mi.Float(1.0)])
        dr.eval([dr.grad(params[k]) for k in KEYS])

    f, m, al, _ = timed(adjoint, a.repeat)
    rows.append(("adjoint pass alone (sample, backward mode)", f, m, al))

    print()
    print(f"{'':46s} {'1st run [s]':>11s} {'median [s]':>11s} {'/ primal':>9s}   runs [s]")
    for name, f, m, al in rows:
        print(f"{name:46s} {f:11.3f} {m:11.3f} {m / p_med:8.2f}x   "
              + ", ".join(f"{x:.3f}" for x in al))
    print()
    print(f"render + backward / primal render: {results['auto'] / p_med:.2f}x with tetvr's "
          f"default reduce_mode 'auto' (per-thread copies of the vertices' gradient sums on "
          f"LLVM, Dr.Jit's own choice on CUDA); the fastest mode here: {best}, "
          f"{results[best] / p_med:.2f}x")
    write_json(a, info, {
        "mesh": dict(cells=a.cells, tets=len(tets)), "image": dict(res=a.res, spp=1),
        "rows": [dict(name=name, first_s=f, median_s=m, over_primal=m / p_med, runs_s=al)
                 for name, f, m, al in rows],
        "best_reduce_mode": best, "render_backward_over_primal": results["auto"] / p_med})


if __name__ == "__main__":
    main(ARGS)
