"""The ``mi-tetvr`` command line.

    mi-tetvr render SCENE.xml|MESH [MESH ...|SERIES.pvd] -o OUT.exr|.png|.mp4 [-o ...]
                    [--res WxH] [--spp N]
                    [--tf TF|COLORMAP] [--mode dvr|max|min|mean|slice|iso] [--view AZ,EL]
                    [--iso V,...] [--plane X,Y,Z,NX,NY,NZ] [--surface-opacity A]
                    [--clip X,Y,Z,NX,NY,NZ] [--clip-box X0,Y0,Z0,X1,Y1,Z1] [--orbit N]
                    [--value-range LO,HI] [--sensor SENSOR.xml]
    mi-tetvr info MESH [--json]
    mi-tetvr make-scenes [-o DIR]
    mi-tetvr make-dataset VOLUME|MESH (--tf TF | --xray) -o DIR [--views N] [--res WxH]
    mi-tetvr make-capture -o DIR [--views N] [--res WxH] [--spp S]
    mi-tetvr process-data IMAGES_DIR|VIDEO -o DIR [--reference DATA]
    mi-tetvr fit DATA -o DIR [--config FILE] [--print-config] [--time-budget MIN] [--viewer]
                 [...]
    mi-tetvr eval FIT_DIR|MESH DATA [-o METRICS.json]
    mi-tetvr refine MESH --select ARRAY [--fraction F] -o OUT
    mi-tetvr viewpoint MESH -o DIR [--tf TF] [--res WxH]
    mi-tetvr view MESH|SCENE.xml|DATA|FIT_DIR [--tf TF] [--port P] [--host H] [--res N]

Conventions (every command): ``-o/--out`` names what a command writes (a file or a
folder); ``--res WxH`` (or ``N`` for N x N) is an image size in pixels; ``--variant``
picks the Mitsuba variant of the commands that render; ``--quiet`` hides progress bars
(in a log file they are a line every few seconds); ``--repair`` and ``--cell-to-point``
apply to every mesh a command reads; ``--opacity-scale`` is a transfer function's
opacity per mesh radius (default 1). Errors are one line, ``mi-tetvr: ...``, exit
status 2 for bad usage and 1 otherwise; ``MI_TETVR_TRACEBACK=1`` shows the traceback.
"""
from __future__ import annotations

import argparse
import json
import textwrap
import sys
import time
from pathlib import Path

import numpy as np

from mi_tetvr.apps.framing import mesh_extent as _mesh_extent
from mi_tetvr.apps.framing import mesh_framing, mesh_scene, render_rgba
from mi_tetvr.apps.settings import DEFAULT_UP, OPACITY_SCALE, RenderSettings, numbers
from mi_tetvr.apps.settings import image_size as _image_size


def _set_variant(name):
    import mitsuba as mi
    if name not in mi.variants():
        sys.exit(f"mi-tetvr: Mitsuba variant '{name}' is not available here (available: "
                 f"{', '.join(v for v in mi.variants() if '_ad_' in v and v.endswith('_rgb'))}"
                 f"; mi_tetvr renders with {' or '.join(VARIANTS)})")
    try:
        mi.set_variant(name)
        import mi_tetvr
        mi_tetvr.register()
    except Exception as e:  # unavailable on this machine, or not a variant mi_tetvr renders in
        sys.exit(f"mi-tetvr: cannot use Mitsuba variant '{name}': {e}")
    return mi


IMAGE_SUFFIXES = (".exr", ".png", ".jpg", ".jpeg")


def _srgb8(rgb):
    """Linear RGB (h, w, 3) as 8-bit sRGB, by Mitsuba's conversion."""
    import mitsuba as mi
    bmp = mi.Bitmap(np.ascontiguousarray(rgb, dtype=np.float32), mi.Bitmap.PixelFormat.RGB)
    return np.array(bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8,
                                srgb_gamma=True), copy=True)


def _write_render(path, rgb, alpha=None):
    """Write a render: linear RGB (h, w, 3) [+ alpha (h, w)] as EXR (linear,
    R G B [A], premultiplied) or PNG/JPG (RGB over black, 8-bit sRGB through
    Mitsuba's conversion, no alpha).

    Data-set images go through :func:`mi_tetvr.recon.images.write_image`
    instead, whose PNGs keep alpha (straight) so that they read back as the
    same premultiplied RGBA; a render's PNG is a picture to look at.
    """
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
        mi.Bitmap(_srgb8(rgb), mi.Bitmap.PixelFormat.RGB).write(str(path))
    else:
        raise SystemExit(f"mi-tetvr: unsupported image format '{suffix}' (use .exr or .png)")


def scene_xml(path, res=None, shape_props=None, classification=None):
    """A Mitsuba XML scene as text, with every sensor's film set to ``res``
    ``(width, height)`` (a film is added where a sensor has none),
    ``shape_props`` (name -> boolean) set on every ``tetmesh`` shape and
    ``classification`` on every ``tetmesh`` with a transfer function."""
    import xml.etree.ElementTree as ET
    root = ET.parse(path).getroot()

    def put(parent, tag, name, value):
        for el in parent.findall(tag):
            if el.get("name") == name:
                el.set("value", value)
                return
        ET.SubElement(parent, tag, name=name, value=value)

    if res is not None:
        sensors = root.iter("sensor")
        for sensor in sensors:
            film = sensor.find("film")
            if film is None:
                film = ET.SubElement(sensor, "film", type="hdrfilm")
            put(film, "integer", "width", str(res[0]))
            put(film, "integer", "height", str(res[1]))
    for shape in root.iter("shape"):
        if shape.get("type") == "tetmesh":
            for name, value in (shape_props or {}).items():
                put(shape, "boolean", name, "true" if value else "false")
            has_tf = any(el.get("name") == "transfer_function" for el in shape)
            if classification and has_tf:
                put(shape, "string", "classification", classification)
    return ET.tostring(root, encoding="unicode")


def _plugin_error(e):
    """The message of an error raised in a plugin's constructor: Mitsuba
    passes on the Python traceback as text; its last line says what is wrong."""
    text = str(e)
    if "Traceback (most recent call last)" not in text:
        return text
    last = [line for line in text.splitlines() if line.strip()][-1]
    name, _, message = last.partition(": ")
    return f"{name.rsplit('.', 1)[-1]}: {message}" if message else last


def _read_mesh(a, path):
    """A mesh file for ``render``: its color and opacity (defaults where
    absent) and point arrays, ``--repair`` and ``--cell-to-point`` applied."""
    import warnings

    import mi_tetvr
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return mi_tetvr.read_tetmesh(path, repair=a.repair, cell_to_point=a.cell_to_point)
        except (ValueError, FileNotFoundError, KeyError) as e:
            sys.exit(f"mi-tetvr: {e}")


def settings_of(cls, a):
    """The settings dataclass ``cls`` (:class:`RenderSettings`) of a command line: its
    fields' options (:func:`settings_flags`) as parsed."""
    import dataclasses
    return cls(**{f.name: getattr(a, f.name) for f in dataclasses.fields(cls)})


def _load_or_exit(mi, scene_dict, path):
    """``mi.load_dict``, or a one-line exit naming the plugin's error."""
    try:
        return mi.load_dict(scene_dict)
    except Exception as e:
        sys.exit(f"mi-tetvr: cannot load {path}: {_plugin_error(e)}")


def _render_or_exit(mi, scene, path, **kwargs):
    """``mi.render`` as an array (:func:`render_rgba`), or a one-line exit
    naming the innermost error (Dr.Jit wraps the integrator's)."""
    try:
        return render_rgba(np.array(mi.render(scene, **kwargs)))
    except Exception as e:
        while (e.__cause__ or e.__context__) is not None:
            e = e.__cause__ or e.__context__
        sys.exit(f"mi-tetvr: cannot render {path}: {_plugin_error(e)}")


def _render_orbit(s, outs, mi, path):
    """``render MESH --orbit N`` (:class:`RenderSettings` ``s``): N frames once around
    ``--up`` from ``--view``, written as an MP4 (the ``.mp4`` outputs) and a contact
    sheet (the image outputs)."""
    import dataclasses

    from mi_tetvr.apps.orbit import FPS, contact_sheet, orbit_azimuths, write_video
    from mi_tetvr.progress import progress_bar
    t0 = time.time()
    azimuth, elevation = s.azimuth_elevation
    mesh = _read_mesh(s, path)
    framing = mesh_framing([_mesh_extent(s, mesh, path)])
    frames = []
    scene = None
    for az in progress_bar(orbit_azimuths(azimuth, s.orbit), desc="orbit", unit="frame"):
        d = mesh_scene(dataclasses.replace(s, view=(float(az), elevation)), mesh, framing)
        if scene is None:
            scene = _load_or_exit(mi, d, path)
        frames.append(_render_or_exit(mi, scene, path, sensor=mi.load_dict(d["sensor"]),
                                      spp=s.spp or 0))
    frames = np.stack(frames)
    sheet = contact_sheet(frames)
    for out in outs:
        if Path(out).suffix.lower() == ".mp4":
            write_video(out, np.stack([_srgb8(f[..., :3]) for f in frames]), FPS)
        else:
            _write_render(out, sheet[..., :3], sheet[..., 3] if sheet.shape[-1] > 3 else None)
    print(f"rendered {s.orbit} frames of {path} around {tuple(s.up_axis)} at "
          f"{frames.shape[2]}x{frames.shape[1]} ({time.time() - t0:.1f} s) -> "
          f"{', '.join(outs)}")


def series_paths(names):
    """The files ``render`` is given: a ``.pvd`` collection expands to its
    data sets in time order (paths relative to it)."""
    import xml.etree.ElementTree as ET
    paths = []
    for name in names:
        path = Path(name)
        if not path.exists():
            sys.exit(f"mi-tetvr: scene file not found: {path}")
        if path.suffix.lower() == ".pvd":
            try:
                sets = ET.parse(path).getroot().iter("DataSet")
                entries = sorted(((float(d.get("timestep", k)), d.get("file"))
                                  for k, d in enumerate(sets)), key=lambda e: e[0])
            except (ET.ParseError, TypeError, ValueError) as e:
                sys.exit(f"mi-tetvr: cannot read the collection {path}: {e}")
            if not entries:
                sys.exit(f"mi-tetvr: the collection {path} names no DataSet files")
            paths += [path.parent / f for _, f in entries]
        else:
            paths.append(path)
    return paths


def _render_series(s, outs, mi, paths):
    """``render MESH MESH ...`` (or a ``.pvd``; :class:`RenderSettings` ``s``): every
    mesh with one transfer function range and one camera (:func:`mesh_framing` over
    all), as an MP4 (the ``.mp4`` outputs) and numbered images (``stem_0000.png``, ...)."""
    from mi_tetvr.apps.orbit import FPS, write_video
    from mi_tetvr.progress import progress_bar
    t0 = time.time()
    # the range and the box of all the meshes first (each read again to render: a
    # series need not fit in memory at once)
    framing = mesh_framing([_mesh_extent(s, _read_mesh(s, p), p) for p in paths])
    frames = []
    for path in progress_bar(paths, desc="series", unit="mesh"):
        scene = _load_or_exit(mi, mesh_scene(s, _read_mesh(s, path), framing), path)
        frames.append(_render_or_exit(mi, scene, path, spp=s.spp or 0))
    frames = np.stack(frames)
    written = []
    for out in outs:
        out = Path(out)
        if out.suffix.lower() == ".mp4":
            write_video(out, np.stack([_srgb8(f[..., :3]) for f in frames]), FPS)
            written.append(str(out))
            continue
        for k, f in enumerate(frames):
            name = out.with_name(f"{out.stem}_{k:04d}{out.suffix}")
            _write_render(name, f[..., :3], f[..., 3])
        written.append(str(out.with_name(f"{out.stem}_####{out.suffix}")))
    rng = framing["value_range"]
    print(f"rendered {len(paths)} meshes at {frames.shape[2]}x{frames.shape[1]}"
          + (f", '{framing['scalar']}' over [{rng[0]:.4g}, {rng[1]:.4g}]" if rng else "")
          + f" ({time.time() - t0:.1f} s) -> {', '.join(written)}")


def cmd_render(a):
    s = settings_of(RenderSettings, a)
    mi = _set_variant(a.variant)
    paths = series_paths(a.scene)
    scene_path = paths[0]
    is_mesh = all(p.suffix.lower() in MESH_SUFFIXES and not _is_image_data(p) for p in paths)
    series = len(paths) > 1
    if not is_mesh and (series or scene_path.suffix.lower() != ".xml"):
        sys.exit(f"mi-tetvr: render takes a Mitsuba XML scene, or tet mesh files "
                 f"({', '.join(MESH_SUFFIXES)}; several, or a .pvd of them, as a series), got "
                 f"{', '.join(str(p) for p in paths)}")
    if is_mesh and s.tf and Path(s.tf).suffix.lower() in (".json", ".xml") \
            and not Path(s.tf).exists():
        sys.exit(f"mi-tetvr: transfer function file not found: {s.tf}")
    try:
        s.validate("mesh" if is_mesh else "xml", series=series)
    except ValueError as e:
        sys.exit(f"mi-tetvr: {e}")
    if s.sensor is not None and not Path(s.sensor).is_file():
        sys.exit(f"mi-tetvr: sensor file not found: {s.sensor}")
    video = bool(s.orbit) or series
    for out in a.out:
        suffix = Path(out).suffix.lower()
        if suffix == ".mp4" and not video:
            sys.exit(f"mi-tetvr: {out}: a video is written by --orbit N or of a series")
        if suffix not in IMAGE_SUFFIXES + ((".mp4",) if video else ()):
            sys.exit(f"mi-tetvr: unsupported image format '{Path(out).suffix}' for {out} (use "
                     f"{', '.join(IMAGE_SUFFIXES)}" + (", .mp4 for the video)" if video
                                                       else ")"))
    if s.orbit and not any(Path(o).suffix.lower() == ".mp4" for o in a.out):
        sys.exit("mi-tetvr: --orbit writes a video: give an -o FILE.mp4 (and images for the "
                 "contact sheet)")
    if s.orbit:
        return _render_orbit(s, a.out, mi, scene_path)
    if series:
        return _render_series(s, a.out, mi, paths)
    t0 = time.time()
    if is_mesh:
        mesh = _read_mesh(s, scene_path)
        scene = _load_or_exit(mi, mesh_scene(s, mesh, mesh_framing(
            [_mesh_extent(s, mesh, scene_path)])), scene_path)
    else:
        try:
            props = {k: True for k in ("repair", "cell_to_point") if getattr(s, k)}
            text = scene_xml(scene_path, s.res, props, s.classification)
            mi.file_resolver().prepend(str(scene_path.resolve().parent))
            scene = mi.load_string(text)
        except Exception as e:
            sys.exit(f"mi-tetvr: cannot load {scene_path}: {_plugin_error(e)}")
    sensor = None
    if s.sensor is not None:
        try:
            sensor = mi.load_file(str(s.sensor))
        except Exception as e:
            sys.exit(f"mi-tetvr: cannot load the sensor {s.sensor}: {_plugin_error(e)}")
        if not isinstance(sensor, mi.Sensor):
            sys.exit(f"mi-tetvr: {s.sensor} holds a {type(sensor).__name__}, not a sensor")
    t1 = time.time()
    img = _render_or_exit(mi, scene, scene_path, spp=s.spp or 0,
                          **({} if sensor is None else {"sensor": sensor}))
    t2 = time.time()
    rgb = img[..., :3]
    alpha = img[..., 3] if img.shape[-1] > 3 else None
    for out in a.out:
        _write_render(out, rgb, alpha)
    print(f"rendered {scene_path} at {img.shape[1]}x{img.shape[0]} (load {t1 - t0:.1f} s, "
          f"render {t2 - t1:.1f} s) -> {', '.join(a.out)}")


def mesh_report(path, color="color", opacity="opacity", repair=False, cell_to_point=False):
    """What ``info`` says of a mesh file: its summary, or when it cannot be
    rendered, the problem (``problems``) and what ``--repair`` would drop
    (``repair``). Raises only for a file that cannot be read at all."""
    import warnings

    from mi_tetvr.mesh.io import read_mesh_file, read_tetmesh, tets_from_cells
    from mi_tetvr.mesh.topology import MeshError, repair_tets
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        try:
            mesh = read_tetmesh(path, color=color, opacity=opacity, repair=repair,
                                cell_to_point=cell_to_point)
            report = mesh.summary()
        except MeshError as e:
            raw = read_mesh_file(path)
            try:
                tets = tets_from_cells(raw, path)
            except MeshError:
                raise e from None
            keep, dropped = repair_tets(raw.points[:, :3], tets)
            report = {"vertices": len(raw.points), "tets": len(tets),
                      "problems": [str(e)],
                      "repair": {"drops": int((~keep).sum()),
                                 **{k: len(v) for k, v in dropped.items()
                                    if k != "boundary_faces"},
                                 "boundary_faces": dropped["boundary_faces"]}}
    if said:
        report["warnings"] = [str(w.message) for w in said]
    return report


def cmd_info(a):
    try:
        s = mesh_report(a.mesh, a.color, a.opacity, a.repair, a.cell_to_point)
    except (ValueError, FileNotFoundError) as e:
        if a.json:
            print(json.dumps({"mesh": a.mesh, "error": str(e)}, indent=2))
            sys.exit(1)
        sys.exit(f"mi-tetvr: {e}")
    if a.json:
        print(json.dumps(s, indent=2))
        return
    from mi_tetvr.mesh.topology import format_summary
    print(f"{a.mesh}")
    arrays = s.pop("arrays", {})
    notes = [f"{key[:-1]:<20} {text}" for key in ("problems", "warnings")
             for text in s.pop(key, [])]
    print("\n".join("  " + line for line in format_summary(s).splitlines() + notes))
    for name, d in arrays.items():
        rng = "" if d["range"] is None else f"  [{d['range'][0]:.6g}, {d['range'][1]:.6g}]"
        print(f"  {d['kind']} array {name!r:<14} {tuple(d['shape'])}{rng}")


def cmd_make_scenes(a):
    from mi_tetvr.mesh.scenes import make_scene_meshes
    for p in make_scene_meshes(a.out):
        print(f"wrote {p}")


def _load_data(path, downscale, holdout):
    from mi_tetvr.recon.datasets import load_dataset
    data = load_dataset(path, downscale=downscale or 1, holdout=holdout)
    if not data.train:
        raise ValueError(f"{path}: the data set has no training views (its frames list is "
                         f"empty, or none of its image files was found)")
    return data


def fit_config(a):
    """The FitConfig of a ``fit`` command line: the --config file's (or the defaults), with
    the options given on the command line over it."""
    from mi_tetvr.recon.config import FitConfig
    cfg = FitConfig.from_file(a.config) if a.config else FitConfig()
    return cfg.updated(**{name: getattr(a, dest) for dest, name in a.config_dests.items()
                          if getattr(a, dest) is not None})


def cmd_fit(a):
    import dataclasses
    cfg = fit_config(a)
    if a.print_config:
        print(json.dumps(dataclasses.asdict(cfg), indent=2))
        return
    from mi_tetvr.recon.config import INITS
    if a.viewer and cfg.linear_solver:
        sys.exit(f"mi-tetvr: --viewer shows the steps of an Adam fit; --model absorption "
                 f"solves with {cfg.linear_solver} (add --solver adam to watch it)")
    if cfg.init not in INITS and not Path(cfg.init).is_file():
        sys.exit(f"mi-tetvr: --init {cfg.init}: no such mesh file (or one of "
                 f"{', '.join(INITS)})")
    _set_variant(a.variant)
    from mi_tetvr.recon.pipeline import run
    data = _load_data(a.data, cfg.downscale, a.holdout)
    print(f"{a.data}: {len(data.train)} training and {len(data.test)} test views "
          f"({data.train[0].camera.width}x{data.train[0].camera.height})")
    Path(a.out).mkdir(parents=True, exist_ok=True)
    # what `view FIT_DIR` finds the data set by
    (Path(a.out) / "data.json").write_text(json.dumps(
        {"data": str(Path(a.data).resolve()), "holdout": a.holdout}, indent=2))

    def open_viewer(trainer):
        from mi_tetvr.apps.viewer import FitViewer
        v = FitViewer(trainer, port=a.port, host=a.host, resolution=a.view_res,
                      save_dir=Path(a.out) / "views")
        print(f"viewer: {v.url}" + _forwarding(a.host, v.port))
        return v
    try:
        metrics = run(data, a.out, cfg, resume=not a.restart, progress=not a.quiet,
                      viewer=open_viewer if a.viewer else None)
    except KeyboardInterrupt:
        sys.exit("mi-tetvr: interrupted; progress saved (run the same command to resume)")
    m = metrics["mean"]
    what = "transmittance" if cfg.model == "absorption" else "sRGB"
    from mi_tetvr.recon.pipeline import fitted_file
    result = fitted_file(cfg)
    print(f"test PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f} ({what}) over "
          f"{len(metrics['views'])} view(s) [{metrics['split']}]; {metrics['tets']:,} tets, "
          f"{metrics['step']:,} steps, {metrics['wall_seconds']:.0f} s -> "
          f"{Path(a.out) / result}")


def _forwarding(host, port):
    """How to open a viewer served on this machine from another one."""
    if host not in ("127.0.0.1", "localhost"):
        return ""
    return (f" (from another machine: ssh -N -L {port}:localhost:{port} USER@THIS_HOST, "
            f"then open http://localhost:{port})")


def fit_dataset(fit_dir, data=None):
    """``(config, data set)`` of a fit's folder: its settings, and its data set
    (``data``, else the one its ``data.json`` records) at the fit's downscale."""
    from mi_tetvr.recon.config import FitConfig
    fit_dir = Path(fit_dir)
    config = FitConfig.from_file(fit_dir / "config.json")
    holdout = 8
    if data is None:
        record = fit_dir / "data.json"
        if not record.is_file():
            raise ValueError(f"{fit_dir} does not record its data set (fits before data.json "
                             f"was written): give it with --data DATA")
        saved = json.loads(record.read_text())
        data, holdout = saved["data"], saved.get("holdout", 8)
    return config, _load_data(data, config.downscale, holdout)


def view_shown(a):
    """What ``view PATH`` shows: a fit's folder, a data set, an XML scene or a mesh."""
    import mitsuba as mi

    from mi_tetvr.apps.viewer import DataShown, FitShown, MeshShown, SceneShown
    path = Path(a.path)
    if not path.exists():
        sys.exit(f"mi-tetvr: not found: {path}")
    fit = path.is_dir() and (path / "checkpoint.npz").is_file() \
        and (path / "config.json").is_file()
    mesh = path.suffix.lower() in MESH_SUFFIXES and not _is_image_data(path)
    if not mesh:
        _refuse(a, ("tf", "scalar"), "to a fit, a data set or an XML scene (a mesh file's "
                "scalar is classified by them)")
    elif a.data:
        sys.exit("mi-tetvr: --data names a fit's data set")
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
        try:
            props = {k: True for k in ("repair", "cell_to_point") if getattr(a, k)}
            mi.file_resolver().prepend(str(path.resolve().parent))
            scene = mi.load_string(scene_xml(path, None, props, None))
        except Exception as e:
            sys.exit(f"mi-tetvr: cannot load {path}: {_plugin_error(e)}")
        return SceneShown(scene, path, up=a.up)
    if a.data:
        sys.exit("mi-tetvr: --data names a fit's data set")
    if path.is_file() and path.suffix.lower() != ".json":
        sys.exit(f"mi-tetvr: view takes a tet mesh file ({', '.join(MESH_SUFFIXES)}), a "
                 f"Mitsuba XML scene, a data set or a fit's folder, got {path}")
    return DataShown(_load_data(path, a.downscale, 8))


def cmd_view(a):
    _set_variant(a.variant)
    if a.res is not None and a.res[0] != a.res[1]:
        sys.exit("mi-tetvr: --res of the viewer is one number, the image's longer side (the "
                 "browser's window sets its shape)")
    from mi_tetvr.apps.viewer import Viewer
    shown = view_shown(a)
    viewer = Viewer(shown, port=a.port, host=a.host, resolution=(a.res or (512,))[0],
                    spp=a.spp, save_dir=a.out)
    print(f"viewer: {viewer.url}" + _forwarding(a.host, viewer.port)
          + "; Ctrl-C stops it")
    try:
        viewer.run(seconds=a.seconds)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()


def cmd_eval(a):
    from mi_tetvr.recon.config import parse_background
    result = Path(a.result)
    if not result.exists():
        sys.exit(f"mi-tetvr: not found: {result}")
    background = parse_background(a.background) if a.background else None
    _set_variant(a.variant)
    from mi_tetvr.recon.pipeline import evaluate_fit, evaluate_mesh
    if result.is_dir():
        if a.background or a.repair or a.cell_to_point:
            sys.exit("mi-tetvr: --background, --repair and --cell-to-point apply to a mesh "
                     "file; a fit folder is scored with its own settings")
        metrics = evaluate_fit(result, a.data, split=a.split, downscale=a.downscale,
                               holdout=a.holdout)
    else:
        if background == "learn":
            sys.exit("mi-tetvr: a learned background is in the fit's folder: eval that "
                     "folder (mi-tetvr eval FIT_DIR DATA)")
        data = _load_data(a.data, a.downscale, a.holdout)
        metrics = evaluate_mesh(result, data, background=background, split=a.split,
                                repair=a.repair, cell_to_point=a.cell_to_point)
    for name, m in metrics["views"].items():
        print(f"  {name:<24s} PSNR {m['psnr']:6.2f} dB  SSIM {m['ssim']:.4f}")
    m = metrics["mean"]
    what = metrics.get("scored", "sRGB")
    linear = f"; linear PSNR {m['psnr_linear']:.2f} dB" if what == "sRGB" else ""
    print(f"mean PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f} ({what}{linear}) "
          f"({len(metrics['views'])} views)")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(metrics, indent=2))


MESH_SUFFIXES = (".vtu", ".msh", ".mesh", ".vtk")


def _refuse(a, names, why):
    """Exit naming the options among ``names`` that were given but do not apply."""
    given = [f"--{n.replace('_', '-')}" for n in names
             if getattr(a, n) not in (None, False)]
    if given:
        sys.exit(f"mi-tetvr: {', '.join(given)} {'does' if len(given) == 1 else 'do'} not "
                 f"apply {why}")


def cmd_make_dataset(a):
    from mi_tetvr.recon.config import _numbers
    path = Path(a.volume)
    if not path.exists():
        sys.exit(f"mi-tetvr: file not found: {path}")
    vr = None if a.value_range is None else _numbers(2)(a.value_range)
    is_mesh = path.suffix.lower() in MESH_SUFFIXES and not _is_image_data(path)
    if a.xray:
        _refuse(a, ("tf", "scalar", "res", "seed"), "to X-ray projections (one pixel per "
                "voxel; the angles are even, not random)")
        if a.opacity_scale != OPACITY_SCALE:
            sys.exit("mi-tetvr: --opacity-scale does not apply to X-ray projections "
                     "(--attenuation or --max-depth set the attenuation)")
        if is_mesh:
            sys.exit(f"mi-tetvr: --xray projects a grid volume, not the tet mesh {path}")
        if (a.beam or "parallel") == "parallel":
            _refuse(a, ("fov", "radius"), "to a parallel beam (--beam cone has them)")
    else:
        _refuse(a, ("beam", "attenuation", "max_depth", "flux", "detail"), "without --xray")
        if a.tf is None:
            sys.exit("mi-tetvr: make-dataset needs --tf (or --xray for X-ray projections)")
        if is_mesh:
            _refuse(a, ("radius",), "to a tet mesh (the cameras frame its bounding sphere "
                    "in --fov)")
        else:
            _refuse(a, ("scalar", "repair", "cell_to_point"), "to a grid volume")
    _set_variant(a.variant)
    from mi_tetvr.grid import load_volume
    from mi_tetvr.recon.synthetic import make_dataset
    from mi_tetvr.transfer import read_transfer_function
    seed = 0 if a.seed is None else a.seed
    if a.xray:
        from mi_tetvr.grid.xray import MAX_DEPTH
        from mi_tetvr.recon.synthetic import make_xray_dataset
        beam = a.beam or "parallel"
        geometry = {} if beam == "parallel" else {
            "distance": 3.0 if a.radius is None else a.radius,
            "fov": 40.0 if a.fov is None else a.fov}
        if a.flux is not None and not a.flux > 0:
            sys.exit(f"mi-tetvr: --flux must be > 0 photons, got {a.flux:g}")
        if a.detail is not None and a.detail < 1:
            sys.exit(f"mi-tetvr: --detail must be a positive integer, got {a.detail}")
        info = make_xray_dataset(load_volume(path, value_range=vr), a.out, views=a.views,
                                 test_views=a.test_views, beam=beam, scale=a.attenuation,
                                 max_depth=MAX_DEPTH if a.max_depth is None else a.max_depth,
                                 flux=a.flux, seed=seed, detail=a.detail or 1,
                                 progress=not a.quiet,
                                 **geometry)["info"]
        if "resampled_from" in info:
            print(f"the volume's spacings differ ({info['resampled_from']['spacing']}): "
                  f"resampled to {info['volume']['shape_xyz']} samples of its x spacing for "
                  f"the parallel beam's square pixels on the z samples")
        print(f"wrote {a.views} training and {a.test_views} test {beam}-beam projections "
              f"(attenuation {info['attenuation_scale']:.4g} per unit, largest optical depth "
              f"{info['max_depth']:.2f}; noise: {info['noise']}) to {a.out}")
        return
    res = a.res or (256, 256)
    if is_mesh:
        from mi_tetvr.recon.synthetic import make_mesh_dataset
        info = make_mesh_dataset(path, a.tf, a.out, views=a.views, test_views=a.test_views,
                                 res=res, scalar=a.scalar, opacity_scale=a.opacity_scale,
                                 fov=40.0 if a.fov is None else a.fov, seed=seed,
                                 value_range=vr, repair=a.repair,
                                 cell_to_point=a.cell_to_point, progress=not a.quiet)
        print(f"wrote {a.views} training and {a.test_views} test views at {res[0]}x{res[1]} "
              f"of '{info['scalar']}' to {a.out}")
        return
    volume = load_volume(path, value_range=vr)
    tf = read_transfer_function(a.tf)
    make_dataset(volume, tf, views=a.views, res=res, out_dir=a.out, test_views=a.test_views,
                 seed=seed, radius=4.0 if a.radius is None else a.radius, fov=a.fov,
                 opacity_scale=a.opacity_scale, progress=not a.quiet)
    print(f"wrote {a.views} training and {a.test_views} test views at {res[0]}x{res[1]} to "
          f"{a.out}")


def cmd_process_data(a):
    from mi_tetvr.recon.sfm import align_cameras, run_sfm
    from mi_tetvr.recon.datasets import load_colmap, load_dataset
    try:
        s = run_sfm(a.images, a.out, matcher=a.matcher, max_image_size=a.max_image_size,
                    camera_model=a.camera_model, max_frames=a.max_frames,
                    single_camera=not a.camera_per_image, progress=not a.quiet)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"mi-tetvr: {e}")
    except KeyboardInterrupt:
        sys.exit("mi-tetvr: interrupted")
    cam = s["camera"]
    print(f"{a.out}: registered {s['images_registered']} of {s['images_given']} images, "
          f"{s['points']:,} points, mean reprojection error "
          f"{s['mean_reprojection_error']:.2f} px, mean track length "
          f"{s['mean_track_length']:.2f}, {s['seconds']:.1f} s ({cam['model']} "
          f"f = {cam['params'][0]:.1f} px) -> {s['model']}")
    if a.reference:
        try:
            ref = load_dataset(a.reference, holdout=None, load_images=False)
            est = load_colmap(a.out, holdout=None, load_images=False)
        except (ValueError, FileNotFoundError) as e:
            sys.exit(f"mi-tetvr: --reference: {e}")
        ref_cams = {Path(v.name).stem: v.camera for v in ref.views}
        pairs = [(v.camera, ref_cams[Path(v.name).stem]) for v in est.views
                 if Path(v.name).stem in ref_cams]
        if len(pairs) < 3:
            print(f"against {a.reference}: {len(pairs)} image name(s) in common, at least 3 "
                  f"are needed to compare the cameras")
        else:
            r = align_cameras([p[0] for p in pairs], [p[1] for p in pairs])
            print(f"against {a.reference} ({len(pairs)} images in common, similarity scale "
                  f"{r['scale']:.4g}): rotation error mean {r['rotation_error_deg_mean']:.2f}, "
                  f"median {r['rotation_error_deg_median']:.2f}, max "
                  f"{r['rotation_error_deg_max']:.2f} deg (relative rotations: max "
                  f"{r['relative_rotation_error_deg_max']:.2f} deg); position error mean "
                  f"{100 * r['position_error_mean']:.2f} %, median "
                  f"{100 * r['position_error_median']:.2f} %, max "
                  f"{100 * r['position_error_max']:.2f} % of the reference cameras' extent "
                  f"(bounding-box diagonal {r['scene_size']:.4g})")
    print(f"next: mi-tetvr fit {a.out} --out {Path(a.out).with_name(Path(a.out).name + '_fit')}"
          f"  (add --downscale N for large photos)")


def cmd_make_capture(a):
    _set_variant(a.variant)
    from mi_tetvr.recon.capture import make_room_capture
    width, height = a.res
    info = make_room_capture(a.out, views=a.views, width=width, height=height, spp=a.spp,
                             seed=a.seed, progress=not a.quiet)
    print(f"wrote {info['views']} photos of {width}x{height} (path traced, {a.spp} spp, OpenCV "
          f"lens, exposure and white balance per photo) and transforms.json to {a.out}")


def _is_image_data(path):
    """Whether a legacy .vtk file holds image data (a grid volume), not a mesh."""
    if path.suffix.lower() != ".vtk":
        return False
    with open(path, "rb") as f:
        head = f.read(1024)
    return b"STRUCTURED_POINTS" in head or b"IMAGE_DATA" in head


def cmd_refine(a):
    from mi_tetvr.mesh.io import read_tetmesh, write_tetmesh
    from mi_tetvr.mesh.refine import refine_mesh
    try:
        mesh = read_tetmesh(a.mesh, repair=a.repair, cell_to_point=a.cell_to_point)
        out = refine_mesh(mesh, a.select, a.fraction, rank=a.rank)
    except (ValueError, FileNotFoundError, KeyError) as e:
        sys.exit(f"mi-tetvr: {e}")
    write_tetmesh(a.out, out)
    print(f"{a.mesh}: {len(mesh.tets):,} tets, {len(mesh.vertices):,} vertices -> "
          f"{len(out.tets):,} tets, {len(out.vertices):,} vertices -> {a.out}")


def cmd_viewpoint(a):
    _set_variant(a.variant)
    import json
    import warnings

    import mi_tetvr
    from mi_tetvr.mesh.topology import bounding_radius
    from mi_tetvr.apps.viewpoint import (ViewpointSearch, best_viewpoint, default_starts,
                                           orbit_scene, plot_viewpoints)
    from mi_tetvr.progress import progress_bar as tqdm
    path = Path(a.mesh)
    if not path.exists():
        sys.exit(f"mi-tetvr: mesh file not found: {path}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            mesh = mi_tetvr.read_tetmesh(path, repair=a.repair, cell_to_point=a.cell_to_point)
        except (ValueError, FileNotFoundError, KeyError) as e:
            sys.exit(f"mi-tetvr: {e}")
    lo, hi = mesh.bounds
    radius = bounding_radius(mesh.vertices)
    fov = 40.0
    shape = {"type": "tetmesh", "filename": str(path.resolve()), "repair": a.repair,
             "cell_to_point": a.cell_to_point}
    if a.tf:
        # a file, or a matplotlib colormap's name
        shape["transfer_function"] = str(Path(a.tf).resolve()) if Path(a.tf).exists() else a.tf
        if a.scalar:
            shape["scalar_attribute"] = a.scalar
        shape["opacity_scale"] = a.opacity_scale / radius
    elif a.scalar:
        sys.exit("mi-tetvr: --scalar needs --tf")
    elif a.opacity_scale != OPACITY_SCALE:
        sys.exit("mi-tetvr: --opacity-scale scales a transfer function's opacity: it needs --tf")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene, centre, distance = orbit_scene(shape, (lo, hi), a.res, fov)
    except Exception as e:
        sys.exit(f"mi-tetvr: cannot load {path}: {_plugin_error(e)}")
    search = ViewpointSearch(scene, centre.tolist(), distance, up=(0.0, 0.0, 1.0))
    starts = default_starts(a.starts)
    t0 = time.time()
    with tqdm(total=a.samples + len(starts), desc="viewpoint", disable=a.quiet) as bar:
        result = best_viewpoint(search, starts, a.iterations, a.samples, bar.update)
    result["seconds"] = time.time() - t0
    result.update(mesh=str(path), distance=distance, target=centre.tolist(), fov=fov,
                  resolution=list(a.res), iterations=a.iterations)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "viewpoint.json").write_text(json.dumps(result, indent=1) + "\n")
    image = search.image(result["longitude"], result["latitude"])
    _write_render(str(out / "view.png"), image[..., :3], image[..., 3])
    plot_viewpoints(result, out / "viewpoint.png")
    b = result["best_sampled"]
    print(f"{path}: longitude {result['longitude']:.1f}, latitude {result['latitude']:.1f} deg, "
          f"opacity entropy {result['entropy']:.4f} ({100 * result['ratio_to_best_sampled']:.1f} % "
          f"of the best of {b['samples']} sampled views, {b['entropy']:.4f}); "
          f"{result['seconds']:.0f} s -> {out}")


# --------------------------------------------------------------------------------------------
# the shared flags
# --------------------------------------------------------------------------------------------

#: The default of ``--test-views``.
TEST_VIEWS = 8
VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")


def _argument_type(parse, name):
    """``parse`` (text -> value, ``ValueError`` on bad text) as an argparse type: its
    message is argparse's error (exit status 2)."""
    def typed(text):
        try:
            return parse(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
    typed.__name__ = name
    return typed


#: ``WxH`` or ``N`` (N x N) -> (width, height), as an argparse type.
image_size = _argument_type(_image_size, "image_size")


def _out(parser, help, required=True, append=False):
    parser.add_argument("-o", "--out", required=required, action="append" if append else None,
                        help=help)


def _variant(parser):
    parser.add_argument("--variant", default="llvm_ad_rgb",
                        help="Mitsuba variant: llvm_ad_rgb (CPU, default) or cuda_ad_rgb (GPU)")


def _quiet(parser):
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bars (in a log file they write a line every few "
                             "seconds)")


def _mesh_flags(parser):
    """The flags of the commands that read a mesh file."""
    parser.add_argument("--repair", action="store_true",
                        help="drop folded, flat and duplicate tets of the mesh read (reported)")
    parser.add_argument("--cell-to-point", action="store_true",
                        help="average the mesh's per-cell arrays onto its vertices")


def _serve(parser):
    parser.add_argument("--port", type=int, default=8080,
                        help="viewer: the port to serve on (default 8080; the next free one "
                        "when taken)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="viewer: the address to listen on (default 127.0.0.1, this "
                        "machine only; 0.0.0.0: every network)")


def _res(parser, default, help="image size in pixels, WxH or N"):
    parser.add_argument("--res", type=image_size, default=default, metavar="WxH",
                        help=f"{help} (default {default[0]}x{default[1]})" if default else help)


def _opacity_scale(parser, default=OPACITY_SCALE):
    parser.add_argument("--opacity-scale", type=float, default=default,
                        help="with a transfer function: its opacity per mesh radius times this "
                             f"(per unit length on a grid volume; default {OPACITY_SCALE:g})")


def _setting_type(f):
    """The Python type a FitConfig field holds (from its annotation)."""
    text = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    for name, kind in (("bool", bool), ("int", int), ("float", float), ("str", str)):
        if text.split(" | ")[0] == name:
            return kind
    return str


def config_flags(parser):
    """One option per :class:`~mi_tetvr.recon.config.FitConfig` field, generated from the
    fields: ``--name-with-dashes`` (or the field's ``flag``), its type, choices and help
    with the default; every option's default is ``None`` (the config file's or the field's
    value stands). Returns {dest: field name}."""
    import dataclasses

    from mi_tetvr.recon.config import FitConfig
    group = parser.add_argument_group("fit settings (mi_tetvr.recon.config.FitConfig; also "
                                      "the keys of --config)")
    dests = {}
    for f in dataclasses.fields(FitConfig):
        meta = f.metadata
        default = "chosen by the run" if f.default is None else json.dumps(f.default)
        help = meta["help"] if "default" in meta["help"] else \
            f"{meta['help']} (default: {default})"
        kind = _setting_type(f)
        kw = dict(dest=f"cfg_{f.name}", default=None, help=help.replace("%", "%%"))
        if kind is bool:
            kw["action"] = argparse.BooleanOptionalAction
        else:
            kw.update(_typed(f, kind))
            if "choices" not in meta:
                kw["metavar"] = meta.get("metavar", {int: "N", float: "X"}.get(kind, "TEXT"))
        group.add_argument(meta.get("flag", "--" + f.name.replace("_", "-")), **kw)
        dests[f"cfg_{f.name}"] = f.name
    return dests


def settings_flags(parser, cls):
    """One option per field of the settings dataclass ``cls`` (:class:`RenderSettings`),
    generated from the fields as :func:`config_flags` does: ``--name-with-dashes`` (or the
    field's ``flag``), the field's default, type (its ``parse``), choices, metavar and
    help; a boolean is a switch (``store_true``). The parsed options are the settings
    again by :func:`settings_of`."""
    import dataclasses
    for f in dataclasses.fields(cls):
        meta = f.metadata
        kind = _setting_type(f)
        kw = dict(dest=f.name, default=f.default, help=meta["help"].replace("%", "%%"))
        if kind is bool:
            kw["action"] = "store_true"
        else:
            kw.update(_typed(f, kind))
            if "metavar" in meta:
                kw["metavar"] = meta["metavar"]
        parser.add_argument(meta.get("flag", "--" + f.name.replace("_", "-")), **kw)


def _typed(f, kind):
    """argparse's ``type`` (the field's ``parse``, else its type) and ``choices`` of a
    settings field."""
    kw = {"type": _argument_type(f.metadata.get("parse", kind), kind.__name__)}
    if "choices" in f.metadata:
        kw["choices"] = f.metadata["choices"]
    return kw


def build_parser():
    """The ``mi-tetvr`` argument parser (one subparser per command)."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        ver = version("mi_tetvr")
    except PackageNotFoundError:
        ver = "unknown"
    p = argparse.ArgumentParser(
        prog="mi-tetvr", description="Differentiable volume rendering of tetrahedral meshes "
        "in Mitsuba 3.", epilog=textwrap.fill(
            "Conventions: " + __doc__.split("Conventions (every command): ")[1].split("\n\n")[0]
            .replace("\n", " ").replace("%", "%%").replace("``", "'"), 88),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"mi-tetvr {ver}")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")

    r = sub.add_parser("render", help="render a Mitsuba XML scene with tetmesh shapes, or a "
                       "mesh file framed by a camera")
    r.add_argument("scene", nargs="+", help="Mitsuba XML scene, or a tet mesh file (.vtu, "
                   ".vtk, .msh, .mesh), or several (a time series; or a .pvd of them): one "
                   "camera and transfer function range for all")
    settings_flags(r, RenderSettings)
    _out(r, "output image (.exr: linear RGBA; .png/.jpg: sRGB); repeatable", append=True)
    _variant(r)
    r.set_defaults(func=cmd_render)

    i = sub.add_parser("info", help="counts, bounds, boundary, quality and arrays of a mesh")
    i.add_argument("mesh", help="tet mesh file (.vtu, .vtk, .msh, .mesh, ...)")
    i.add_argument("--color", default="color", help="color point array (default color)")
    i.add_argument("--opacity", default="opacity", help="opacity point array (default opacity)")
    i.add_argument("--json", action="store_true", help="print the report as JSON (always, "
                   "also for a mesh with problems)")
    _mesh_flags(i)
    i.set_defaults(func=cmd_info)

    m = sub.add_parser("make-scenes", help="(re)generate the meshes of the bundled scenes")
    _out(m, "folder of the scenes (default: the project's scenes/)", required=False)
    m.set_defaults(func=cmd_make_scenes)

    d = sub.add_parser("make-dataset", help="render a scalar volume or tet mesh into a "
                       "NeRF-style data set, or project a volume into X-ray images")
    d.add_argument("volume", help="scalar grid (.npy, .cvol, .mhd, .vti, raw .gz) or scalar "
                   "tet mesh (.vtu, .vtk, .msh, .mesh)")
    _out(d, "data set folder")
    d.add_argument("--tf", help="transfer function (.json: the project's or a ParaView colormap; "
                   "DiffTetVR .xml; or a matplotlib colormap's name)")
    d.add_argument("--scalar", help="the tet mesh's scalar point array (default: the only one)")
    d.add_argument("--views", type=int, default=64, help="training views (default 64)")
    d.add_argument("--test-views", type=int, default=TEST_VIEWS,
                   help=f"held-out views (default {TEST_VIEWS})")
    _res(d, None, "image size, WxH or N (default 256; X-ray: one pixel per voxel)")
    d.add_argument("--value-range", help="lo,hi of the values the transfer function spans "
                   "(default: the data's range)")
    _opacity_scale(d)
    d.add_argument("--radius", type=float, help="grid volume: camera distance from the centre "
                   "of its [-1, 1]^3 box (default 4); X-ray cone beam: source distance "
                   "(default 3)")
    d.add_argument("--fov", type=float, help="horizontal field of view in degrees (default: "
                   "frames the grid's box; 40 around a tet mesh and for a cone beam)")
    d.add_argument("--seed", type=int, help="seed of the random held-out cameras (default 0)")
    d.add_argument("--xray", action="store_true", help="X-ray transmittance images (.npy) of "
                   "the grid volume's attenuation: exact line integrals of its trilinear field")
    d.add_argument("--beam", choices=("parallel", "cone"), help="X-ray: parallel beam "
                   "(orthographic, over 180 degrees; default) or cone beam (perspective, "
                   "over 360)")
    d.add_argument("--attenuation", type=float, help="X-ray: attenuation per unit length of a "
                   "normalised value 1 (default: from --max-depth)")
    d.add_argument("--max-depth", type=float, help="X-ray: the largest optical depth of a "
                   "training ray (default 2.5)")
    d.add_argument("--flux", type=float, help="X-ray: photons per pixel of the unattenuated "
                   "beam: the training projections are Poisson counts (the fit weights its "
                   "rays by them); default: noise-free")
    d.add_argument("--detail", type=int, help="X-ray: integrate the volume's cubic B-spline "
                   "K times finer than its samples, a field no reconstruction on them models "
                   "exactly (default 1: its trilinear field)")
    _mesh_flags(d)
    _quiet(d)
    _variant(d)
    d.set_defaults(func=cmd_make_dataset)

    mc = sub.add_parser("make-capture", help="path-trace a photo capture of a textured room "
                        "with objects from cameras inside it (a test capture: transforms.json, "
                        "lens distortion, exposure changes, noise, no masks)")
    _out(mc, "capture folder")
    mc.add_argument("--views", type=int, default=48, help="photos (default 48)")
    _res(mc, (320, 240))
    mc.add_argument("--spp", type=int, default=12, help="samples per pixel (default 12)")
    mc.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    _quiet(mc)
    _variant(mc)
    mc.set_defaults(func=cmd_make_capture)

    pd = sub.add_parser("process-data", help="camera poses of photos or a video by structure "
                        "from motion (COLMAP through pycolmap, CPU): a COLMAP data set for fit")
    pd.add_argument("images", help="folder of photos (.jpg, .png, ...) or a video file")
    _out(pd, "data set folder: images/, database.db, sparse/0 (a COLMAP data set for fit and "
             "eval)")
    pd.add_argument("--matcher", choices=("exhaustive", "sequential"),
                    help="image pairs matched: all (default for photos) or neighbours in name "
                    "order (default for a video)")
    pd.add_argument("--max-image-size", type=int, default=1600,
                    help="longest image side for feature extraction (default 1600)")
    pd.add_argument("--camera-model", default="SIMPLE_RADIAL",
                    help="COLMAP camera model (default SIMPLE_RADIAL; SIMPLE_PINHOLE, PINHOLE, "
                    "RADIAL, OPENCV, ...)")
    pd.add_argument("--camera-per-image", action="store_true",
                    help="fit intrinsics per photo (photos from different cameras or zooms)")
    pd.add_argument("--max-frames", type=int, default=100,
                    help="frames taken evenly from a video (default 100)")
    pd.add_argument("--reference", help="a data set with known cameras of the same images "
                    "(NeRF-style or COLMAP): print the pose errors after a similarity alignment")
    _quiet(pd)
    pd.set_defaults(func=cmd_process_data)

    f = sub.add_parser("fit", help="reconstruct a tet-mesh volume from a multi-view data set")
    f.add_argument("data", help="NeRF-style folder (transforms*.json) or COLMAP model folder")
    _out(f, "output folder (also the checkpoint a later run resumes)")
    f.add_argument("--config", help="fit settings as JSON or YAML (keys: the settings below, "
                   "with underscores); options given here override it")
    f.add_argument("--print-config", action="store_true",
                   help="print the settings this command would fit with (JSON) and exit")
    f.add_argument("--holdout", type=int, default=8,
                   help="with a train split only: every N-th view is a test view (default 8)")
    f.add_argument("--restart", action="store_true", help="ignore an existing checkpoint")
    f.add_argument("--viewer", action="store_true", help="show the fit in the browser while it "
                   "runs: the mesh from the browser's camera between steps (in at most 10%% of "
                   "the time), the loss curve and the stage")
    _serve(f)
    f.add_argument("--view-res", type=int, default=384, metavar="N",
                   help="--viewer: the refined image's longer side (default 384)")
    _quiet(f)
    _variant(f)
    f.set_defaults(func=cmd_fit, config_dests=config_flags(f))

    w = sub.add_parser("view", help="a live viewer in the browser of a mesh, an XML scene, "
                       "a data set's cameras and images, or a fit (with its cameras)")
    w.add_argument("path", help="tet mesh file, Mitsuba XML scene, data set folder, or a fit's "
                   "output folder")
    w.add_argument("--tf", help="mesh file: the transfer function of its scalar (a file or a "
                   "matplotlib colormap's name; the page offers presets)")
    w.add_argument("--scalar", help="mesh file: the array shown first (default: color and "
                   "opacity when it has them, else its only scalar)")
    w.add_argument("--data", help="fit folder: its data set (default: the one it records)")
    w.add_argument("--downscale", type=int, help="data set: shrink its images by this factor")
    w.add_argument("--up", type=_argument_type(numbers(3, nonzero=True), "numbers"),
                   default=DEFAULT_UP,
                   metavar="X,Y,Z", help="mesh file or XML scene: the up axis (default 0,0,1)")
    _res(w, None, "the refined image's longer side in pixels (default 512; the browser "
         "window sets the shape)")
    w.add_argument("--spp", type=int, default=1, help="passes the refined image accumulates "
                   "(default 1)")
    _serve(w)
    w.add_argument("--seconds", type=float, help="stop after this many seconds (default: at "
                   "Ctrl-C)")
    _out(w, "folder the save button writes images and cameras to (default views)",
         required=False)
    _mesh_flags(w)
    _variant(w)
    w.set_defaults(func=cmd_view, out="views")

    e = sub.add_parser("eval", help="PSNR/SSIM of a fit (or a colored mesh) on a data set's "
                       "views, scored as the fit scores itself")
    e.add_argument("result", help="a fit's output folder (scores what it fitted: colors, an "
                   "attenuation, a scalar or a transfer function, with its background), or "
                   "a mesh file with color and opacity arrays")
    e.add_argument("data", help="the data set")
    _out(e, "also write the metrics to this JSON file", required=False)
    e.add_argument("--background", help="a mesh file's background: none (default), white, "
                   "black or r,g,b (a fit folder uses its own)")
    e.add_argument("--downscale", type=int, help="shrink images by this factor (default: the "
                   "fit's, else 1)")
    e.add_argument("--holdout", type=int, default=8,
                   help="with a train split only: every N-th view is a test view (default 8)")
    e.add_argument("--split", choices=["test", "train"], default="test")
    _mesh_flags(e)
    _variant(e)
    e.set_defaults(func=cmd_eval)

    rf = sub.add_parser("refine", help="split the edges around the top vertices of a "
                        "point-data array")
    rf.add_argument("mesh", help="tet mesh file")
    _out(rf, "refined mesh file (.vtu, ...)")
    rf.add_argument("--select", required=True, help="point-data array to rank vertices by "
                    "(or color, opacity)")
    rf.add_argument("--rank", choices=["magnitude", "value"], default="magnitude",
                    help="magnitude (default): largest absolute values (vector norms) first, "
                    "negative as much as positive; value: highest signed values first")
    rf.add_argument("--fraction", type=float, default=0.05, help="top fraction (default 0.05)")
    _mesh_flags(rf)
    rf.set_defaults(func=cmd_refine)

    v = sub.add_parser("viewpoint", help="the camera position of highest opacity entropy "
                       "(DiffDVR's best viewpoint), by gradient ascent on the sphere")
    v.add_argument("mesh", help="tet mesh file")
    _out(v, "folder for viewpoint.json, view.png and viewpoint.png (the entropy over the "
            "sphere, the ascent paths)")
    v.add_argument("--tf", help="transfer function (post-classifies the scalar): a file, or a "
                   "matplotlib colormap's name")
    v.add_argument("--scalar", help="the scalar point array (default: the only one)")
    _opacity_scale(v)
    _res(v, (128, 128))
    v.add_argument("--starts", type=int, default=8, help="ascent starts (default 8)")
    v.add_argument("--iterations", type=int, default=20, help="steps per start (default 20)")
    v.add_argument("--samples", type=int, default=256,
                   help="Fibonacci-sphere views for comparison (default 256)")
    _mesh_flags(v)
    _quiet(v)
    _variant(v)
    v.set_defaults(func=cmd_viewpoint)
    return p


def command_summary():
    """Markdown lines, one per command: its positional arguments, required options and
    the names of its other options (the fit settings in one group), with its help. The
    README's command list is this text (a test keeps them equal)."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    helps = {c.dest: c.help for c in sub._choices_actions}
    lines = []
    for name, p in sub.choices.items():
        words, optional = [f"mi-tetvr {name}"], []
        for a in p._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            if not a.option_strings:
                words.append(a.dest.upper().replace("-", "_"))
            elif a.dest.startswith("cfg_"):
                continue
            elif a.required:
                words.append(f"{a.option_strings[0]} {a.dest.upper()}")
            else:
                optional.append(max(a.option_strings, key=len))
        if any(a.dest.startswith("cfg_") for a in p._actions):
            optional.append("[every FitConfig setting: --time-budget, --scene, --init, ...]")
        lines.append(f"- `{' '.join(words)}` — {helps[name]}")
        if optional:
            lines.append(f"  options: {', '.join(f'`{o}`' if o.startswith('-') else o for o in optional)}")
    return "\n".join(lines)


def main(argv=None):
    import os
    a = build_parser().parse_args(argv)
    if os.environ.get("MI_TETVR_TRACEBACK"):
        return a.func(a)
    try:
        return a.func(a)
    except KeyboardInterrupt:
        sys.exit("mi-tetvr: interrupted")
    except (ValueError, KeyError, OSError, RuntimeError) as e:
        # what a command could not do with its input: one line (the library's messages say
        # what is wrong and the way past it); MI_TETVR_TRACEBACK=1 shows where
        text = str(e).strip("'\"") if isinstance(e, KeyError) else str(e)
        if isinstance(e, FileNotFoundError) and e.filename and str(e.filename) not in text:
            text = f"file not found: {e.filename}"
        sys.exit(f"mi-tetvr: {text or type(e).__name__}")


if __name__ == "__main__":
    main()
