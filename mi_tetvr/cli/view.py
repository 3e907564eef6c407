"""``mi-tetvr view PATH``: the live viewer in the browser (:mod:`mi_tetvr.apps.viewer`) of
a mesh file (with ``render``'s settings as controls), an XML scene, a data set's cameras
and images, or a fit's folder (with its data set's cameras)."""
from __future__ import annotations

import json
from pathlib import Path

from mi_tetvr.apps.settings import DEFAULT_UP, numbers
from mi_tetvr.cli import flags
from mi_tetvr.cli.common import (MESH_SUFFIXES, forwarding, is_mesh_file, load_data, load_xml,
                                 refuse, set_variant)
from mi_tetvr.extras import require

NAME = "view"
HELP = ("a live viewer in the browser of a mesh, an XML scene, a data set's cameras and "
        "images, or a fit (with its cameras)")


def add_arguments(p):
    p.add_argument("path", help="tet mesh file, Mitsuba XML scene, data set folder, or a fit's "
                   "output folder")
    p.add_argument("--tf", help="mesh file: the transfer function of its scalar (a file or a "
                   "matplotlib colormap's name; the page offers presets)")
    p.add_argument("--scalar", help="mesh file: the array shown first (default: color and "
                   "opacity when it has them, else its only scalar)")
    p.add_argument("--data", help="fit folder: its data set (default: the one it records)")
    p.add_argument("--downscale", type=int, help="data set: shrink its images by this factor")
    p.add_argument("--up", type=flags.argument_type(numbers(3, nonzero=True), "numbers"),
                   default=DEFAULT_UP, metavar="X,Y,Z",
                   help="mesh file or XML scene: the up axis (default 0,0,1)")
    flags.res(p, None, "the refined image's longer side in pixels (default 512; the browser "
              "window sets the shape)")
    p.add_argument("--spp", type=int, default=1, help="passes the refined image accumulates "
                   "(default 1)")
    flags.serve(p)
    p.add_argument("--seconds", type=float, help="stop after this many seconds (default: at "
                   "Ctrl-C)")
    flags.out(p, "folder the save button writes images and cameras to (default views)",
              required=False)
    flags.mesh_flags(p)
    flags.variant(p)
    p.set_defaults(out="views")


def fit_dataset(fit_dir, data=None):
    """``(config, data set)`` of a fit's folder: its settings, and its data set
    (``data``, else the one its ``data.json`` records) at the fit's downscale."""
    from mi_tetvr.recon.plan import fit_settings
    fit_dir = Path(fit_dir)
    config = fit_settings(fit_dir)
    holdout = 8
    if data is None:
        record = fit_dir / "data.json"
        if not record.is_file():
            raise ValueError(f"{fit_dir} does not record its data set (fits before data.json "
                             f"was written): give it with --data DATA")
        saved = json.loads(record.read_text())
        data, holdout = saved["data"], saved.get("holdout", 8)
    return config, load_data(data, config.data.downscale, holdout)


def view_shown(a):
    """What ``view PATH`` shows: a fit's folder, a data set, an XML scene or a mesh."""
    import mitsuba as mi

    from mi_tetvr.apps.viewer import DataShown, FitShown, MeshShown, SceneShown
    path = Path(a.path)
    if not path.exists():
        raise FileNotFoundError(f"not found: {path}")
    fit = path.is_dir() and (path / "checkpoint.npz").is_file() \
        and (path / "config.json").is_file()
    mesh = is_mesh_file(path)
    if not mesh:
        refuse(a, ("tf", "scalar"), "to a fit, a data set or an XML scene (a mesh file's "
               "scalar is classified by them)")
    elif a.data:
        raise ValueError("--data names a fit's data set")
    if fit:
        from mi_tetvr.recon.checkpoint import load_checkpoint
        config, data = fit_dataset(path, a.data)
        print(f"{path}: loading the fit ({len(data.train)} training and {len(data.test)} "
              f"test views)")
        return FitShown(load_checkpoint(path / "checkpoint.npz", data, config))
    if mesh:
        return MeshShown(path, tf=a.tf, scalar=a.scalar, repair=a.repair,
                         cell_to_point=a.cell_to_point, up=a.up)
    if path.suffix.lower() == ".xml":
        props = {k: True for k in ("repair", "cell_to_point") if getattr(a, k)}
        return SceneShown(load_xml(mi, path, None, props, None), path, up=a.up)
    if a.data:
        raise ValueError("--data names a fit's data set")
    if path.is_file() and path.suffix.lower() != ".json":
        raise ValueError(f"view takes a tet mesh file ({', '.join(MESH_SUFFIXES)}), a "
                         f"Mitsuba XML scene, a data set or a fit's folder, got {path}")
    return DataShown(load_data(path, a.downscale, 8))


def run(a):
    require("viewer", "mi-tetvr view", "viser", "scipy", "PIL")
    set_variant(a.variant)
    if a.res is not None and a.res[0] != a.res[1]:
        raise ValueError("--res of the viewer is one number, the image's longer side (the "
                         "browser's window sets its shape)")
    from mi_tetvr.apps.viewer import Viewer
    shown = view_shown(a)
    viewer = Viewer(shown, port=a.port, host=a.host, resolution=(a.res or (512,))[0],
                    spp=a.spp, save_dir=a.out)
    print(f"viewer: {viewer.url}" + forwarding(a.host, viewer.port) + "; Ctrl-C stops it")
    try:
        viewer.run(seconds=a.seconds)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
