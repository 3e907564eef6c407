"""Light transport benchmark: ``tetpath`` on a tet mesh against Mitsuba's
``volpath`` on the equivalent medium, time and samples to equal noise.

Scene: the cube [-1, 1]^3 as a ``cells^3`` tet grid holding an extinction
field (albedo 0.8, Henyey-Greenstein ``g = 0.3``) under an area light and a
sky, multiple scattering (``max_depth`` 8). Mitsuba renders the same field
in a ``cube``: a ``heterogeneous`` medium on a trilinear ``gridvolume``
(free flights by delta tracking against the global majorant, shadow rays by
ratio tracking) or a ``homogeneous`` one (distances sampled analytically).
``--field``:

* ``linear``: ``A + B x``, which the tet mesh and the grid both hold
  exactly (the same medium; a tight majorant: delta tracking's easy case);
* ``constant``: ``A`` (``volpath``'s analytic sampling: the walk's overhead);
* ``smoke``: a few dense blobs in thin air (peak extinction 30): a loose
  majorant, delta tracking's common case. The grid's trilinear cells and the
  tets' linear pieces differ inside a cell, so each method is scored against
  its own reference there.

The noise is the mean squared error against the reference (``volpath``, or
each method's own, at ``--ref-spp``); ``MSE x time`` is the time to a fixed
noise (lower is better), ``MSE x spp`` the samples to it.

The walk's work per camera ray (tets crossed) is printed beside delta
tracking's expected tracking steps (``majorant x chord``, the collisions of
the majorant process, real and null).

Usage::

    python benchmarks/bench_transport.py              # 16^3 cells, 64x64
    python benchmarks/bench_transport.py --quick      # 4^3 cells, 16x16, few samples
"""
from __future__ import annotations

from common import header, make_parser, timed, write_json


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=3, quick="--cells 4 --res 16 --spp 4,16 --ref-spp 256")
    p.add_argument("--cells", type=int, default=16, help="tet grid cells per axis (default 16)")
    p.add_argument("--res", type=int, default=64, help="image width = height (default 64)")
    p.add_argument("--spp", default="16,64", help="sample counts compared (default 16,64)")
    p.add_argument("--ref-spp", type=int, default=4096,
                   help="samples of the volpath reference (default 4096)")
    p.add_argument("--field", choices=("linear", "constant", "smoke"), default="linear",
                   help="the extinction field (default linear)")
    a = p.parse_args(argv)
    if a.quick:
        a.cells, a.res, a.spp, a.ref_spp = 4, 16, "4,16", 256
    return a


ARGS = parse_args()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402
from mi_tetvr.mesh.generate import blob_field, grid_mesh  # noqa: E402
from mi_tetvr.render.walk import trace  # noqa: E402

A, B, ALBEDO, G, DEPTH = 1.0, 0.8, 0.8, 0.3, 8
#: The smoke's peak extinction.
SMOKE = 30.0


def field(points, kind):
    """The extinction at ``points`` (k, 3)."""
    if kind == "constant":
        return np.full(len(points), A)
    if kind == "linear":
        return A + B * points[:, 0]
    return blob_field(points, SMOKE)[1] + 0.05


def grid_volume(n, kind):
    """The field at the nodes of an ``n^3`` lattice over the cube, as a
    trilinear ``gridvolume`` whose outermost voxel centres lie on the cube's
    faces (Mitsuba's samples sit at voxel centres)."""
    x = -1.0 + 2.0 * np.arange(n) / (n - 1)
    z, y, xx = np.meshgrid(x, x, x, indexing="ij")
    data = field(np.column_stack([xx.ravel(), y.ravel(), z.ravel()]), kind).reshape(n, n, n, 1)
    h = 2.0 / (n - 1)
    return {"type": "gridvolume", "data": mi.TensorXf(np.ascontiguousarray(data, np.float32)),
            "filter_type": "trilinear",
            "to_world": mi.ScalarTransform4f().translate([-1 - h / 2] * 3).scale([2 + h] * 3)}


def scenes(a):
    V, T = grid_mesh((a.cells,) * 3)
    phase = {"type": "hg", "g": G}
    sensor = {"type": "perspective", "fov": 40,
              "to_world": mi.ScalarTransform4f().look_at(origin=[0.5, 0.8, 4.5], target=[0, 0, 0],
                                                         up=[0, 1, 0]),
              "film": {"type": "hdrfilm", "width": a.res, "height": a.res,
                       "rfilter": {"type": "box"}},
              "sampler": {"type": "independent"}}
    lights = {"light": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate(
                  [0.5, 3, 0.5]).rotate([1, 0, 0], 90),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 6.0}}},
              "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.1, 0.12, 0.15]}}}
    sigma = field(V, a.field)
    if a.field == "constant":
        medium = {"type": "homogeneous", "sigma_t": A, "albedo": ALBEDO, "phase": phase}
    else:
        medium = {"type": "heterogeneous", "sigma_t": grid_volume(a.cells + 1, a.field),
                  "albedo": ALBEDO, "phase": phase}
    tet = mi.load_dict({"type": "scene", "sensor": sensor, **lights,
                        "integrator": {"type": "tetpath", "max_depth": DEPTH},
                        "vol": mi_tetvr.tetmesh_dict(V, T, opacity=sigma, albedo=ALBEDO,
                                                     phase=phase)})
    ref = mi.load_dict({"type": "scene", "sensor": sensor, **lights,
                        "integrator": {"type": "volpath", "max_depth": DEPTH},
                        "cube": {"type": "cube", "bsdf": {"type": "null"}, "interior": medium}})
    return tet, ref, len(T)


def walk_work(tet, res):
    """Mean tets crossed per camera ray through the cube (pixel centres), and
    delta tracking's expected steps on the same rays (majorant x chord)."""
    integrator = tet.integrator()
    ps = integrator.path_inputs(tet)
    sensor = tet.sensors()[0]
    idx = dr.arange(mi.UInt32, res * res)
    pos = mi.Vector2f(mi.Float(idx % res) + 0.5, mi.Float(idx // res) + 0.5) / res
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    _, T, steps, _ = trace(ps.boundaries, ps.ts, ray, ps.settings, mi.Bool(True))
    steps = np.asarray(steps, np.float64)
    o, d = np.asarray(ray.o).T, np.asarray(ray.d).T
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = np.maximum(np.minimum((-1 - o) / d, (1 - o) / d).max(1), 0)
        t1 = np.maximum((-1 - o) / d, (1 - o) / d).min(1)
    chord = np.maximum(t1 - t0, 0.0)
    hit = chord > 0
    majorant = float(field(np.asarray(ps.ts.buf.positions).reshape(-1, 3), ARGS.field).max())
    return steps[hit].mean(), (majorant * chord[hit]).mean()


def main(a):
    info = header("light transport benchmark (tetpath against volpath)")
    tet, ref, n_tets = scenes(a)
    what = {"constant": f"extinction {A}", "linear": f"extinction {A} + {B} x",
            "smoke": f"smoke (peak extinction {SMOKE})"}[a.field]
    print(f"cube: {a.cells}^3 cells, {n_tets:,} tets, {what}, albedo {ALBEDO}, hg g = {G}, "
          f"max_depth {DEPTH}; image {a.res}x{a.res}")
    steps, delta = walk_work(tet, a.res)
    print(f"work per camera ray through the cube: {steps:.1f} tets crossed (tetpath); "
          f"{delta:.2f} expected delta-tracking steps (volpath, majorant x chord)")
    truth = {"volpath": np.asarray(mi.render(ref, spp=a.ref_spp, seed=10_000))[..., :3]}
    # (the smoke: each its own reference, see the module docstring)
    truth["tetpath"] = (np.asarray(mi.render(tet, spp=a.ref_spp, seed=10_000))[..., :3]
                        if a.field == "smoke" else truth["volpath"])
    results = {"tets": n_tets, "tets_per_ray": steps, "delta_steps_per_ray": delta, "rows": []}
    print(f"\n{'spp':>5} {'method':>8} {'time s':>8} {'spread':>13} {'MSE':>10} "
          f"{'MSE x time':>11} {'MSE x spp':>10}")
    for spp in [int(s) for s in a.spp.split(",")]:
        row = {"spp": spp}
        for name, scene in (("tetpath", tet), ("volpath", ref)):
            seeds = iter(range(1, 1000))

            def render():
                return np.asarray(mi.render(scene, spp=spp, seed=next(seeds)))[..., :3]
            _, med, times, _ = timed(render, a.repeat)
            mse = np.mean([np.mean((render() - truth[name]) ** 2) for _ in range(a.repeat)])
            row[name] = {"time": med, "times": times, "mse": float(mse)}
            print(f"{spp:>5} {name:>8} {med:>8.3f} {min(times):>6.3f}-{max(times):<6.3f} "
                  f"{mse:>10.3e} {mse * med:>11.3e} {mse * spp:>10.3e}")
        t, v = row["tetpath"], row["volpath"]
        row["samples_ratio"] = v["mse"] / t["mse"]
        row["time_ratio"] = (t["mse"] * t["time"]) / (v["mse"] * v["time"])
        print(f"      volpath needs {row['samples_ratio']:.2f}x the samples of tetpath for its "
              f"noise; tetpath takes {row['time_ratio']:.2f}x volpath's time to equal noise")
        results["rows"].append(row)
    write_json(a, info, results)


if __name__ == "__main__":
    main(ARGS)
