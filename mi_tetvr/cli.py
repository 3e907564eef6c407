"""The ``mi-tetvr`` command line.

    mi-tetvr render SCENE.xml -o OUT.exr|.png [--spp N] [--res WxH] [--variant V]
    mi-tetvr info MESH [--json]
    mi-tetvr make-scenes [DIR]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def _set_variant(name):
    import mitsuba as mi
    try:
        mi.set_variant(name)
    except Exception as e:  # unknown or unavailable variant
        sys.exit(f"mi-tetvr: cannot use Mitsuba variant '{name}': {e}")
    import mi_tetvr
    mi_tetvr.register()
    return mi


def write_image(path, rgb, alpha=None):
    """Write linear RGB (h, w, 3) [+ alpha (h, w)] as EXR (linear, R G B A,
    RGB over a black background is premultiplied) or PNG/JPG (sRGB, RGB only)."""
    import mitsuba as mi
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        data = rgb if alpha is None else np.concatenate([rgb, alpha[..., None]], -1)
        bmp = mi.Bitmap(np.ascontiguousarray(data, dtype=np.float32),
                        mi.Bitmap.PixelFormat.RGB if alpha is None else mi.Bitmap.PixelFormat.RGBA)
        bmp.write(str(path))
    elif suffix in (".png", ".jpg", ".jpeg"):
        bmp = mi.Bitmap(np.ascontiguousarray(rgb, dtype=np.float32), mi.Bitmap.PixelFormat.RGB)
        bmp = bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)
        bmp.write(str(path))
    else:
        raise SystemExit(f"mi-tetvr: unsupported image format '{suffix}' (use .exr or .png)")


def cmd_render(a):
    mi = _set_variant(a.variant)
    scene_path = Path(a.scene)
    if not scene_path.exists():
        sys.exit(f"mi-tetvr: scene file not found: {scene_path}")
    params = {}
    if a.res:
        try:
            w, h = (int(x) for x in a.res.lower().split("x"))
        except ValueError:
            sys.exit(f"mi-tetvr: --res must look like 512x512, got '{a.res}'")
        params.update(resx=w, resy=h)
    t0 = time.time()
    try:
        scene = mi.load_file(str(scene_path), **params)
    except Exception as e:
        sys.exit(f"mi-tetvr: cannot load {scene_path}: {e}")
    if a.res and tuple(scene.sensors()[0].film().size()) != (w, h):
        sys.exit("mi-tetvr: --res needs a scene whose film uses $resx/$resy defaults")
    t1 = time.time()
    img = np.array(mi.render(scene, spp=a.spp or 0))
    t2 = time.time()
    rgb = img[..., :3]
    alpha = img[..., 3] if img.shape[-1] > 3 else None
    for out in a.output:
        write_image(out, rgb, alpha)
    print(f"rendered {scene_path} at {img.shape[1]}x{img.shape[0]} (load {t1 - t0:.1f} s, "
          f"render {t2 - t1:.1f} s) -> {', '.join(a.output)}")


def cmd_info(a):
    from mi_tetvr.io import read_tetmesh
    try:
        mesh = read_tetmesh(a.mesh, color=a.color, opacity=a.opacity)
        s = mesh.summary()
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"mi-tetvr: {e}")
    if a.json:
        print(json.dumps(s, indent=2))
        return
    print(f"{a.mesh}")
    w = max(len(k) for k in s)
    for k, v in s.items():
        if isinstance(v, float):
            v = f"{v:.6g}"
        elif isinstance(v, list) and v and isinstance(v[0], float):
            v = "[" + ", ".join(f"{x:.6g}" for x in v) + "]"
        print(f"  {k:<{w}}  {v}")


def cmd_make_scenes(a):
    from mi_tetvr.scenes import make_scene_meshes
    for p in make_scene_meshes(a.dir):
        print(f"wrote {p}")


def main(argv=None):
    p = argparse.ArgumentParser(prog="mi-tetvr", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("render", help="render a Mitsuba XML scene with tetmesh shapes")
    r.add_argument("scene")
    r.add_argument("-o", "--output", action="append", required=True,
                   help="output image (.exr: linear RGBA; .png: sRGB); repeatable")
    r.add_argument("--spp", type=int, default=0, help="samples per pixel (default: the scene's)")
    r.add_argument("--res", help="resolution WxH (the scene's film must use $resx/$resy)")
    r.add_argument("--variant", default="llvm_ad_rgb", help="llvm_ad_rgb (default) or cuda_ad_rgb")
    r.set_defaults(func=cmd_render)
    i = sub.add_parser("info", help="counts, bounds, boundary, quality and attributes of a mesh")
    i.add_argument("mesh")
    i.add_argument("--color", default="color", help="color point-data name")
    i.add_argument("--opacity", default="opacity", help="opacity point-data name")
    i.add_argument("--json", action="store_true")
    i.set_defaults(func=cmd_info)
    m = sub.add_parser("make-scenes", help="(re)generate the meshes of the bundled scenes")
    m.add_argument("dir", nargs="?", default=None)
    m.set_defaults(func=cmd_make_scenes)
    a = p.parse_args(argv)
    a.func(a)


if __name__ == "__main__":
    main()
