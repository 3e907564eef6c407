"""Scenes benchmark: what each feature of a scene costs (surfaces, a clip,
an isosurface drawn in the volume, overlapping meshes), and whether each
renders as fast as with another checkout's code.

Scene: the jittered ``cells^3`` grid carrying the blob field (as
``bench_render.py``), one jittered ray per pixel, ``mi.render`` (primal) and
``mi.render`` + ``dr.backward`` of an L2 loss w.r.t. the vertex colors (the
scalar for the overlay). Each configuration is timed warm (median of
``--repeat`` runs):

1. **volume only**: the scene as before surfaces existed;
2. **+ clip**: the same with a clip plane through the centre (``tetvr``'s
   ``clip_origin``, ``clip_normal``);
3. **+ surfaces**: the same volume before a floor and a wall and around a
   sphere (diffuse), lit by a point light, with ``prb`` (``max_depth`` 2) as
   the nested integrator;
4. **surfaces alone**: Mitsuba's ``prb`` on the same scene without the
   volume (what the nested integrator costs by itself);
5. **scalar volume** and **+ isosurface overlay**: the blob's opacity as a
   scalar under the default transfer function, alone and with an opaque
   isosurface drawn in it (``tetvr``'s ``overlay``, a ``tetproj``);
6. **two meshes apart / overlapping**: the volume and a copy of it moved by
   2.2 along x (disjoint: walked one mesh at a time) or by 0.5 (they
   overlap: the merged walk, one medium), the camera moved back to see both.

With ``--code DIR`` every configuration but Mitsuba's own is also timed with
another checkout's code (e.g. the code before a change; ``git worktree add
DIR COMMIT``), run in a subprocess through ``checkout_cli.py`` in
alternation with this checkout's, ``--rounds`` times; the ratios of the
rounds give the spread on a noisy machine.

Usage::

    python benchmarks/bench_scenes.py                    # 32^3 cells, 256x256
    python benchmarks/bench_scenes.py --code ../before   # and the other checkout
    python benchmarks/bench_scenes.py --quick            # 8^3 cells, 48x48
"""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from common import (CAM_ORIGIN, grid_scene, header, make_parser, render_steps, sensor_dict,
                    timed, write_json)


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=3, quick="--cells 8 --res 48 --rounds 1")
    p.add_argument("--cells", type=int, default=32, help="grid cells per axis (default 32)")
    p.add_argument("--res", type=int, default=256, help="image width = height (default 256)")
    p.add_argument("--code", help="another checkout whose volume-only render is timed too")
    p.add_argument("--rounds", type=int, default=3,
                   help="alternations of this checkout and --code (default 3)")
    p.add_argument("--configs", help="time these configurations alone, comma-separated "
                   "(what --code runs)")
    a = p.parse_args(argv)
    if a.code and not (Path(a.code) / "mi_tetvr").is_dir():
        p.error(f"--code {a.code}: not a checkout of mi_tetvr (no mi_tetvr/ in it)")
    if a.quick:
        a.cells, a.res, a.rounds = 8, 48, 1
    return a


ARGS = parse_args()

import mitsuba as mi  # noqa: E402

mi.set_variant(ARGS.variant)

import mi_tetvr  # noqa: E402,F401


def surfaces_dict():
    """A floor, a wall and a sphere inside the volume; a point light."""
    T = mi.ScalarTransform4f()
    return {
        "floor": {"type": "rectangle", "to_world": T.translate([0, -1.2, 0])
                  .rotate([1, 0, 0], -90).scale(4), "bsdf": {"type": "diffuse"}},
        "wall": {"type": "rectangle", "to_world": T.translate([0, 0, -2.0]).scale(4),
                 "bsdf": {"type": "diffuse"}},
        "ball": {"type": "sphere", "radius": 0.4, "bsdf": {"type": "diffuse"}},
        "light": {"type": "point", "position": [2, 3, 3],
                  "intensity": {"type": "rgb", "value": 20}},
    }


def jittered(res, back=1.0):
    """The benchmarks' camera, ``back`` times as far, one jittered ray per pixel."""
    s = sensor_dict(res)
    s["sampler"] = {"type": "independent", "sample_count": 1}
    if back != 1.0:
        s["to_world"] = mi.ScalarTransform4f().look_at(
            origin=[back * x for x in CAM_ORIGIN], target=[0, 0, 0], up=[0, 1, 0])
    return s


def time_scene(scene, keys, repeat):
    primal, backward = render_steps(scene, keys)
    return {"primal_s": timed(primal, repeat)[1],
            "backward_s": timed(backward, repeat)[1] if keys else None}


def volume_scene(a, **integrator):
    base = grid_scene(a.cells, a.res)[0]
    return mi.load_dict({"type": "scene", "integrator": {"type": "tetvr", **integrator},
                         "sensor": jittered(a.res), "volume": base.shapes()[0]})


def scalar_scene(a, overlay):
    from mi_tetvr.mesh.generate import blob_field, grid_mesh
    V, T = grid_mesh(a.cells, jitter=0.15)
    _, opacity = blob_field(V)
    integrator = {"type": "tetvr"}
    if overlay:
        integrator["overlay"] = {"type": "tetproj", "mode": "iso", "iso": "1.5"}
    tf = Path(__file__).resolve().parents[1] / "scenes" / "tf_default.json"
    return mi.load_dict({"type": "scene", "integrator": integrator, "sensor": jittered(a.res),
                         "volume": mi_tetvr.tetmesh_dict(V, T, scalar=opacity,
                                                         transfer_function=str(tf))})


def two_meshes(a, shift):
    _, V, T, color, opacity = grid_scene(a.cells, 8)
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "tetvr"}, "sensor": jittered(a.res, 1.6),
        "volume": mi_tetvr.tetmesh_dict(V, T, color, opacity),
        "copy": mi_tetvr.tetmesh_dict(V + [shift, 0.0, 0.0], T, color[:, ::-1].copy(),
                                      opacity)})


#: name -> (scene(args), keys differentiated, whether --code times it too)
CONFIGS = {
    "volume only": (lambda a: volume_scene(a), ["volume.vertex_color"], True),
    "+ clip": (lambda a: volume_scene(a, clip_origin=[0.0, 0.0, 0.0],
                                      clip_normal=[0.3, 0.2, 1.0]),
               ["volume.vertex_color"], True),
    "+ surfaces": (lambda a: mi.load_dict({
        "type": "scene", "sensor": jittered(a.res), "volume": volume_scene(a).shapes()[0],
        "integrator": {"type": "tetvr", "surfaces": {"type": "prb", "max_depth": 2}},
        **surfaces_dict()}), ["volume.vertex_color"], True),
    "surfaces alone (prb)": (lambda a: mi.load_dict({
        "type": "scene", "sensor": jittered(a.res),
        "integrator": {"type": "prb", "max_depth": 2}, **surfaces_dict()}), [], False),
    "scalar volume": (lambda a: scalar_scene(a, False), ["volume.vertex_scalar"], True),
    "+ isosurface overlay": (lambda a: scalar_scene(a, True), ["volume.vertex_scalar"], True),
    "two meshes apart": (lambda a: two_meshes(a, 2.2), ["volume.vertex_color"], True),
    "two meshes overlapping": (lambda a: two_meshes(a, 0.5), ["volume.vertex_color"], True),
}


def time_config(a, name):
    make, keys, _ = CONFIGS[name]
    return time_scene(make(a), keys, a.repeat)


def other_checkout(a, names):
    """The timings of the configurations ``names`` with ``--code``'s package
    (a subprocess)."""
    from checkout_cli import command
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "other.json"
        cmd = command(a.code) + [str(Path(__file__).resolve()), "--configs", ",".join(names),
                                 "--cells", str(a.cells), "--res", str(a.res), "--repeat",
                                 str(a.repeat), "--variant", a.variant, "--json", str(out)]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"--code {a.code} failed: {r.stderr[-2000:]}")
        return json.loads(out.read_text())["results"]


def main(a):
    info = header("scenes benchmark")
    print(f"mesh: {a.cells}^3 cells ({6 * a.cells ** 3:,} tets), image {a.res}x{a.res}, 1 spp")
    results = {}
    if a.configs:
        for name in a.configs.split(","):
            results[name] = time_config(a, name)
        write_json(a, info, results)
        return 0
    compared = [n for n, (_, _, both) in CONFIGS.items() if both] if a.code else []
    rounds = []
    for r in range(a.rounds if a.code else 1):
        this = {name: time_config(a, name) for name in CONFIGS if name in compared or r == 0}
        row = {"this": this}
        if a.code:
            row["other"] = other_checkout(a, compared)
            for name in compared:
                t, o = this[name], row["other"][name]
                print(f"round {r + 1}: {name:24s} primal {t['primal_s']:.3f} s / "
                      f"{o['primal_s']:.3f} s (--code) = {t['primal_s'] / o['primal_s']:.2f}x; "
                      f"backward {t['backward_s']:.3f} / {o['backward_s']:.3f} s = "
                      f"{t['backward_s'] / o['backward_s']:.2f}x")
        rounds.append(row)
    results.update(rounds[0]["this"])
    if a.code:
        results["rounds"] = rounds
        print()
        print(f"this / --code over {len(rounds)} rounds (1 = as fast):")
        for name in compared:
            for k in ("primal_s", "backward_s"):
                ratios = [row["this"][name][k] / row["other"][name][k] for row in rounds]
                results[f"{name}: {k[:-2]} ratio this/--code"] = ratios
            p = results[f"{name}: primal ratio this/--code"]
            b = results[f"{name}: backward ratio this/--code"]
            print(f"  {name:24s} primal {min(p):.2f}-{max(p):.2f}x, backward "
                  f"{min(b):.2f}-{max(b):.2f}x")
    v = results["volume only"]
    print(f"{'configuration':24s} {'primal':>10s} {'backward':>10s}")
    for name in CONFIGS:
        t = results[name]
        b = f"{t['backward_s']:9.3f}s" if t["backward_s"] is not None else f"{'-':>10s}"
        print(f"{name:24s} {t['primal_s']:9.3f}s {b}")
    for name, base in (("+ clip", v), ("+ surfaces", v),
                       ("+ isosurface overlay", results["scalar volume"]),
                       ("two meshes overlapping", results["two meshes apart"])):
        m = results[name]
        results[f"{name} cost primal x"] = m["primal_s"] / base["primal_s"]
        results[f"{name} cost backward x"] = m["backward_s"] / base["backward_s"]
        print(f"{name}: primal {results[f'{name} cost primal x']:.2f}x, backward "
              f"{results[f'{name} cost backward x']:.2f}x the time without it")
    write_json(a, info, results)
    return 0


if __name__ == "__main__":
    sys.exit(main(ARGS))
