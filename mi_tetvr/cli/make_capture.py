"""``mi-tetvr make-capture -o DIR``: a path-traced photo capture of a textured room with
objects (a test capture: transforms.json, lens distortion, exposure changes, noise)."""
from __future__ import annotations

from mi_tetvr.cli import flags
from mi_tetvr.cli.common import set_variant
from mi_tetvr.extras import require

NAME = "make-capture"
HELP = ("path-trace a photo capture of a textured room with objects from cameras inside it "
        "(a test capture: transforms.json, lens distortion, exposure changes, noise, no masks)")


def add_arguments(p):
    flags.out(p, "capture folder")
    p.add_argument("--views", type=int, default=48, help="photos (default 48)")
    flags.res(p, (320, 240))
    p.add_argument("--spp", type=int, default=12, help="samples per pixel (default 12)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    flags.quiet(p)
    flags.variant(p)


def run(a):
    require("sfm", "mi-tetvr make-capture", "pycolmap", "PIL")
    set_variant(a.variant)
    from mi_tetvr.recon.capture import make_room_capture
    width, height = a.res
    info = make_room_capture(a.out, views=a.views, width=width, height=height, spp=a.spp,
                             seed=a.seed, progress=not a.quiet)
    print(f"wrote {info['views']} photos of {width}x{height} (path traced, {a.spp} spp, OpenCV "
          f"lens, exposure and white balance per photo) and transforms.json to {a.out}")
