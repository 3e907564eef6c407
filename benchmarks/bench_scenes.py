"""Scenes benchmark: what adding Mitsuba surfaces to a tet volume costs, what
overlapping meshes cost, and whether a volume-only scene renders as fast as
before.

Scene: the jittered ``cells^3`` grid carrying the blob field (as
``bench_render.py``), one jittered ray per pixel, ``mi.render`` (primal) and
``mi.render`` + ``dr.backward`` of an L2 loss w.r.t. the vertex colors. Each
configuration is timed warm (median of ``--repeat`` runs):

1. **volume only**: the scene as before surfaces existed;
2. **+ surfaces**: the same volume before a floor and a wall and around a
   sphere (diffuse), lit by a point light, with ``prb`` (``max_depth`` 2) as
   the nested integrator;
3. **surfaces alone**: Mitsuba's ``prb`` on the same scene without the
   volume (what the nested integrator costs by itself);
4. **two meshes apart / overlapping**: the volume and a copy of it moved by
   2.2 along x (disjoint: walked one mesh at a time) or by 0.5 (they
   overlap: the merged walk, one medium), the camera moved back to see both.

With ``--code DIR`` the volume-only configuration is also timed with another
checkout's code (e.g. the commit before surfaces; ``git worktree add DIR
COMMIT``), run in a subprocess through ``checkout_cli.py`` in alternation
with this checkout's, ``--rounds`` times; the ratios of the rounds give the
spread on a noisy machine.

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
    p.add_argument("--volume-only", action="store_true",
                   help="time the volume-only scene alone (what --code runs)")
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


def volume_only(a):
    scene = grid_scene(a.cells, a.res)[0]
    scene = mi.load_dict({"type": "scene", "integrator": scene.integrator(),
                          "sensor": jittered(a.res), "volume": scene.shapes()[0]})
    return time_scene(scene, ["volume.vertex_color"], a.repeat)


def other_checkout(a):
    """The volume-only timings with ``--code``'s package (a subprocess)."""
    from checkout_cli import command
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "other.json"
        cmd = command(a.code) + [str(Path(__file__).resolve()), "--volume-only",
                                 "--cells", str(a.cells), "--res", str(a.res), "--repeat",
                                 str(a.repeat), "--variant", a.variant, "--json", str(out)]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"--code {a.code} failed: {r.stderr[-2000:]}")
        return json.loads(out.read_text())["results"]["volume only"]


def main(a):
    info = header("scenes benchmark")
    print(f"mesh: {a.cells}^3 cells ({6 * a.cells ** 3:,} tets), image {a.res}x{a.res}, 1 spp")
    results = {}
    if a.volume_only:
        results["volume only"] = volume_only(a)
        write_json(a, info, results)
        return 0
    rounds = []
    for r in range(a.rounds if a.code else 1):
        this = volume_only(a)
        row = {"this": this}
        if a.code:
            row["other"] = other_checkout(a)
            print(f"round {r + 1}: volume only, primal {this['primal_s']:.3f} s (this) / "
                  f"{row['other']['primal_s']:.3f} s (--code): "
                  f"{this['primal_s'] / row['other']['primal_s']:.2f}x; backward "
                  f"{this['backward_s']:.3f} / {row['other']['backward_s']:.3f} s: "
                  f"{this['backward_s'] / row['other']['backward_s']:.2f}x")
        rounds.append(row)
    results["volume only"] = rounds[0]["this"]
    if a.code:
        results["rounds"] = rounds
        for k in ("primal_s", "backward_s"):
            ratios = [row["this"][k] / row["other"][k] for row in rounds]
            results[f"{k[:-2]} ratio this/--code"] = ratios
            print(f"volume only, {k[:-2]}: this / --code = {min(ratios):.2f}-{max(ratios):.2f}x "
                  f"over {len(ratios)} rounds (1 = as fast)")

    base = grid_scene(a.cells, a.res)[0]
    volume = base.shapes()[0]
    mixed = mi.load_dict({"type": "scene", "sensor": jittered(a.res), "volume": volume,
                          "integrator": {"type": "tetvr",
                                         "surfaces": {"type": "prb", "max_depth": 2}},
                          **surfaces_dict()})
    results["+ surfaces"] = time_scene(mixed, ["volume.vertex_color"], a.repeat)
    alone = mi.load_dict({"type": "scene", "sensor": jittered(a.res),
                          "integrator": {"type": "prb", "max_depth": 2}, **surfaces_dict()})
    results["surfaces alone (prb)"] = time_scene(alone, [], a.repeat)
    _, V, T, color, opacity = grid_scene(a.cells, 8)
    for name, shift in (("two meshes apart", 2.2), ("two meshes overlapping", 0.5)):
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "tetvr"}, "sensor": jittered(a.res, 1.6),
            "volume": mi_tetvr.tetmesh_dict(V, T, color, opacity),
            "copy": mi_tetvr.tetmesh_dict(V + [shift, 0.0, 0.0], T, color[:, ::-1].copy(),
                                          opacity)})
        results[name] = time_scene(scene, ["volume.vertex_color"], a.repeat)
    v = results["volume only"]
    print(f"{'configuration':24s} {'primal':>10s} {'backward':>10s}")
    for name, t in results.items():
        if isinstance(t, dict) and "primal_s" in t:
            b = f"{t['backward_s']:9.3f}s" if t["backward_s"] is not None else f"{'-':>10s}"
            print(f"{name:24s} {t['primal_s']:9.3f}s {b}")
    m = results["+ surfaces"]
    results["surfaces cost primal x"] = m["primal_s"] / v["primal_s"]
    results["surfaces cost backward x"] = m["backward_s"] / v["backward_s"]
    print(f"adding the surfaces: primal {results['surfaces cost primal x']:.2f}x, backward "
          f"{results['surfaces cost backward x']:.2f}x the volume-only time")
    o, p = results["two meshes overlapping"], results["two meshes apart"]
    results["overlap cost primal x"] = o["primal_s"] / p["primal_s"]
    results["overlap cost backward x"] = o["backward_s"] / p["backward_s"]
    print(f"two meshes overlapping (merged walk) / apart: primal "
          f"{results['overlap cost primal x']:.2f}x, backward "
          f"{results['overlap cost backward x']:.2f}x")
    write_json(a, info, results)
    return 0


if __name__ == "__main__":
    sys.exit(main(ARGS))
