"""Where a fit step's time goes: render, loss, backward, optimizer, the safe step, the
scene's update, and in each the time of Dr.Jit's kernels against the host's (Python
tracing the kernels, NumPy, launching); the tets a ray crosses, the walk's rate against a
regular grid's at the same ray count, and what twice the rays in one launch cost.

The fit of a folder written by ``mi-tetvr fit`` is loaded from its checkpoint (its last
stage's mesh, values and optimizer state, with its data set, as ``mi-tetvr view`` loads it)
and stepped ``--steps`` times after ``--warmup`` steps (the kernels compiled). Every phase
of a step ends with a sync, so that its kernels are counted in it: the phases' sum is a
little slower than an unmeasured step, whose kernels overlap the host's work; the
unmeasured step's time is printed beside it (``--repeat`` runs of ``--steps`` steps).

Usage::

    mi-tetvr fit DATA -o FIT --downscale 4 --time-budget 10
    python benchmarks/bench_fit_step.py FIT --json out/fit_step.json
    python benchmarks/bench_fit_step.py --quick     # colmap-maupertuis at 1/16, a 4-step fit
"""
from __future__ import annotations

import statistics
import subprocess
import sys
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402

from common import header, make_parser, write_json  # noqa: E402
from fit_suite import DATA  # noqa: E402

QUICK_DATA = DATA / "colmap-maupertuis"


class Phases:
    """Wall time and kernel time per phase (each phase synced at both ends)."""

    def __init__(self, dr):
        self.dr = dr
        self.wall = defaultdict(float)
        self.kernels = defaultdict(float)
        self.depth = 0
        self.wrapped = []

    @contextmanager
    def phase(self, name):
        dr = self.dr
        if self.depth:                      # (a phase inside another counts in the outer one)
            yield
            return
        self.depth += 1
        dr.sync_thread()
        dr.kernel_history_clear()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            dr.sync_thread()
            self.wall[name] += time.perf_counter() - t0
            self.kernels[name] += sum(k["execution_time"] for k in dr.kernel_history(
                [dr.KernelType.JIT])) / 1000.0
            self.depth -= 1

    def wrap(self, owner, attr, name, evaluate=False):
        """Time ``owner.attr`` (a function or method) as phase ``name``; ``evaluate``: its
        result is evaluated inside the phase (lazy arrays)."""
        original = getattr(owner, attr)

        def timed(*args, **kw):
            with self.phase(name):
                out = original(*args, **kw)
                if evaluate:
                    self.dr.eval(out)
            return out
        setattr(owner, attr, timed)
        self.wrapped.append((owner, attr, original))

    def restore(self):
        """Put the wrapped functions back."""
        for owner, attr, original in reversed(self.wrapped):
            setattr(owner, attr, original)
        self.wrapped.clear()


def tets_per_ray(trainer, view):
    """The tets each pixel-centre ray of ``view`` crosses in the fit's scene (numpy)."""
    import drjit as dr
    from mi_tetvr.render.walk import trace
    scene = trainer.scene
    integrator = scene.integrator()
    rays = view.camera.rays_drjit()
    _, _, steps, _ = trace(scene, integrator.tet_group(scene), rays,
                           integrator.settings_for(scene), True)
    dr.eval(steps)
    return np.array(steps, np.float64)


def timed_min(fn, repeat=3):
    import drjit as dr
    fn()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        dr.sync_thread()
        best = min(best, time.perf_counter() - t0)
    return best


def walk_rates(trainer, view, cells=64):
    """The walk's rate (tet steps per second of ``trace()``) on ``view``'s rays in the fit's
    mesh and, at the same ray count, on the jittered ``cells``^3 grid seen from outside; and the
    render + backward of one launch of twice the view's rays over that of the view."""
    import drjit as dr
    import mitsuba as mi

    import mi_tetvr
    from mi_tetvr.camera import Camera
    from mi_tetvr.mesh.generate import grid_mesh
    from mi_tetvr.render.walk import trace

    def scene_of(V, T, C, O, cam):
        return mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                             "sensor": cam.sensor_dict(sampler="stratified", jitter=False),
                             "m": mi_tetvr.tetmesh_dict(V, T, C, O)})

    def rate(scene, cam):
        integrator = scene.integrator()
        ts, settings = integrator.tet_group(scene), integrator.settings_for(scene)
        rays = cam.rays_drjit()
        out = {}

        def run():
            out["steps"] = trace(scene, ts, rays, settings, True)[2]
            dr.eval(out["steps"])
        seconds = timed_min(run)
        return float(np.sum(np.array(out["steps"], np.float64))) / seconds

    def render_backward(scene):
        params = mi.traverse(scene)
        key = next(k for k in params.keys() if k.endswith("vertex_color"))
        dr.enable_grad(params[key])
        params.update()

        def run():
            dr.backward(dr.sum(mi.render(scene, params), axis=None))
            dr.eval(dr.grad(params[key]))
            dr.set_grad(params[key], 0)
        return timed_min(run)

    V, T, values = trainer.arrays()
    cam = view.camera
    fit = scene_of(V, T, values["color"], values["opacity"], cam)
    rng = np.random.default_rng(0)
    gv, gt = grid_mesh(cells, jitter=0.15, seed=1)
    side = int(round(np.sqrt(cam.width * cam.height)))
    grid_cam = Camera.look_at([2.6, 1.8, 3.4], [0, 0, 0], [0, 0, 1], side, side,
                              fx=side / 2 / np.tan(np.radians(16.5)))
    grid = scene_of(gv, gt, rng.uniform(0, 1, (len(gv), 3)), rng.uniform(0, 0.3, len(gv)),
                    grid_cam)
    w2, h2 = round(cam.width * np.sqrt(2)), round(cam.height * np.sqrt(2))
    f2 = cam.fx * w2 / cam.width                  # (square pixels: one focal length)
    twice = Camera(w2, h2, f2, f2, cam.cx * w2 / cam.width, cam.cy * h2 / cam.height,
                   cam.to_world)
    return {"fit_msteps_per_s": rate(fit, cam) / 1e6,
            "grid_msteps_per_s": rate(grid, grid_cam) / 1e6, "grid_cells": cells,
            "twice_the_rays_over_one": render_backward(scene_of(V, T, values["color"],
                                                                values["opacity"], twice))
            / render_backward(fit), "twice_size": (twice.width, twice.height)}


def quick_fit(out):
    """A 4-step fit of colmap-maupertuis at 1/16 (the smoke run's folder)."""
    if not QUICK_DATA.is_dir():
        sys.exit(f"--quick needs {QUICK_DATA}")
    cmd = [sys.executable, "-m", "mi_tetvr.cli", "fit", str(QUICK_DATA), "--out", str(out),
           "--downscale", "16", "--iterations", "4", "--restart", "--quiet"]
    subprocess.run(cmd, check=True, capture_output=True)
    return out


def main():
    p = make_parser(__doc__, quick="a 4-step fit of colmap-maupertuis at 1/16, 3 steps",
                    repeat=3)
    p.add_argument("fit", nargs="?", help="a fit's folder (checkpoint.npz, config.json, "
                   "data.json)")
    p.add_argument("--data", help="its data set (default: the one data.json names)")
    p.add_argument("--steps", type=int, default=20, help="measured steps (default 20)")
    p.add_argument("--warmup", type=int, default=5, help="steps first (default 5)")
    a = p.parse_args()
    if a.quick:
        a.fit, a.steps, a.warmup, a.repeat = str(quick_fit(Path("out/bench_fit_step"))), 3, 2, 1
    if not a.fit:
        p.error("a fit's folder is needed (or --quick)")
    if not (Path(a.fit) / "checkpoint.npz").is_file():
        p.error(f"{a.fit} is not a fit's folder (it has no checkpoint.npz: mi-tetvr fit writes "
                f"one)")

    import mitsuba as mi
    mi.set_variant(a.variant)
    import drjit as dr

    from mi_tetvr.cli.view import fit_dataset
    from mi_tetvr.recon import trainer as trainer_module
    from mi_tetvr.recon.checkpoint import load_checkpoint
    config, data = fit_dataset(Path(a.fit), a.data)
    trainer = load_checkpoint(Path(a.fit) / "checkpoint.npz", data, config)
    n_tets = len(trainer.tets)
    pixels = sum(v.camera.width * v.camera.height for v in data.train) / len(data.train)
    info = header("fit step breakdown")
    print(f"fit {a.fit}: {n_tets:,} tets, {len(data.train)} training photos of "
          f"{pixels:,.0f} pixels on average, {trainer.config.trainer.views_per_step} per step, "
          f"spp {trainer.config.trainer.spp}")

    crossed = tets_per_ray(trainer, data.train[0])
    print(f"tets crossed per ray (the first training photo, with early termination): "
          f"mean {crossed.mean():.0f}, median {np.median(crossed):.0f}, "
          f"99th percentile {np.percentile(crossed, 99):.0f}")

    for _ in range(a.warmup):
        trainer.step()
    dr.sync_thread()
    plain = []
    for _ in range(a.repeat):
        t0 = time.perf_counter()
        for _ in range(a.steps):
            trainer.step()
        dr.sync_thread()
        plain.append((time.perf_counter() - t0) / a.steps)

    phases = Phases(dr)
    cls = trainer_module.Trainer
    phases.wrap(cls, "render", "render", evaluate=True)
    phases.wrap(cls, "loss", "loss", evaluate=True)
    phases.wrap(cls, "metric_mse", "loss", evaluate=True)
    phases.wrap(trainer_module.dr, "backward", "backward")
    phases.wrap(type(trainer.opt), "step", "optimizer")
    phases.wrap(cls, "_safe_positions", "safe step")
    phases.wrap(type(trainer.params), "update", "scene update")
    phases.wrap(type(trainer.field), "project", "optimizer")
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    t0 = time.perf_counter()
    for _ in range(a.steps):
        trainer.step()
    dr.sync_thread()
    measured = (time.perf_counter() - t0) / a.steps
    dr.set_flag(dr.JitFlag.KernelHistory, False)

    phases.restore()

    rows = {}
    print(f"\n{'phase':<14}{'ms/step':>10}{'share':>8}{'kernels ms':>12}{'host ms':>10}")
    for name in ("render", "loss", "backward", "optimizer", "safe step", "scene update"):
        w, k = phases.wall[name] / a.steps, phases.kernels[name] / a.steps
        rows[name] = {"seconds": w, "kernel_seconds": k}
        print(f"{name:<14}{1e3 * w:>10.1f}{100 * w / measured:>7.1f}%{1e3 * k:>12.1f}"
              f"{1e3 * (w - k):>10.1f}")
    other = measured - sum(r["seconds"] for r in rows.values())
    rows["other"] = {"seconds": other, "kernel_seconds": 0.0}
    print(f"{'other':<14}{1e3 * other:>10.1f}{100 * other / measured:>7.1f}%")
    kernels = sum(r["kernel_seconds"] for r in rows.values())
    print(f"\nmeasured step {1e3 * measured:.1f} ms: kernels {1e3 * kernels:.1f} ms "
          f"({100 * kernels / measured:.0f} %), host {1e3 * (measured - kernels):.1f} ms")
    print(f"unmeasured step: {1e3 * statistics.median(plain):.1f} ms median over "
          f"{a.repeat} runs of {a.steps} ({', '.join(f'{1e3 * t:.1f}' for t in plain)}): "
          f"{1 / statistics.median(plain):.2f} steps/s")
    rates = walk_rates(trainer, data.train[0], cells=16 if a.quick else 64)
    print(f"\nwalk rate, trace() of the first photo's rays: {rates['fit_msteps_per_s']:.1f} M tet "
          f"steps/s; the {rates['grid_cells']}^3 jittered grid from outside at the same ray count: "
          f"{rates['grid_msteps_per_s']:.1f} M; render + backward of twice the rays in one "
          f"launch ({rates['twice_size'][0]}x{rates['twice_size'][1]}): "
          f"{rates['twice_the_rays_over_one']:.2f}x one photo's")
    write_json(a, info, {"tets": n_tets, "tets_per_ray_mean": float(crossed.mean()), **rates,
                         "phases": rows, "measured_step": measured,
                               "unmeasured_steps": plain})


if __name__ == "__main__":
    main()
