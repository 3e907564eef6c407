"""``mi-tetvr render SCENE.xml|MESH [MESH ...|SERIES.pvd] -o OUT``: a Mitsuba XML scene,
or a mesh file framed by a camera (:mod:`mi_tetvr.apps.framing`), or an orbit of one
(``--orbit N``: an MP4 and a contact sheet), or a time series of meshes (one camera and
one transfer-function range). Its options are the fields of
:class:`~mi_tetvr.apps.settings.RenderSettings`, which check which of them combine."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from mi_tetvr.apps.framing import mesh_extent, mesh_framing, mesh_scene, render_rgba
from mi_tetvr.apps.settings import RenderSettings
from mi_tetvr.cli import flags
from mi_tetvr.cli.common import (IMAGE_SUFFIXES, MESH_SUFFIXES, CommandError, is_mesh_file,
                                 load_scene, load_xml, plugin_error, read_mesh, render_errors,
                                 render_image, set_variant, srgb8, write_render)
from mi_tetvr.extras import require

NAME = "render"
HELP = "render a Mitsuba XML scene with tetmesh shapes, or a mesh file framed by a camera"


def add_arguments(p):
    p.add_argument("scene", nargs="+", help="Mitsuba XML scene, or a tet mesh file (.vtu, "
                   ".vtk, .msh, .mesh), or several (a time series; or a .pvd of them): one "
                   "camera and transfer function range for all")
    flags.settings_flags(p, RenderSettings)
    flags.out(p, "output image (.exr: linear RGBA; .png/.jpg: sRGB); repeatable", append=True)
    p.add_argument("--workers", type=int, default=None,
                   help="Ray workers: a partitioned mesh (a .pvtu written by `partition`) "
                   "rendered block by block and composited, or the frames of an orbit or a "
                   "series spread over them")
    p.add_argument("--address", default=None,
                   help="a running Ray cluster for --workers (default: RAY_ADDRESS, else a "
                   "local one of this machine's processes)")
    flags.variant(p)


def series_paths(names):
    """The files ``render`` is given: a ``.pvd`` collection expands to its
    data sets in time order (paths relative to it)."""
    import xml.etree.ElementTree as ET
    paths = []
    for name in names:
        path = Path(name)
        if not path.exists():
            raise FileNotFoundError(f"scene file not found: {path}")
        if path.suffix.lower() == ".pvd":
            try:
                sets = ET.parse(path).getroot().iter("DataSet")
                entries = sorted(((float(d.get("timestep", k)), d.get("file"))
                                  for k, d in enumerate(sets)), key=lambda e: e[0])
            except (ET.ParseError, TypeError, ValueError) as e:
                raise ValueError(f"cannot read the collection {path}: {e}") from None
            if not entries:
                raise ValueError(f"the collection {path} names no DataSet files")
            paths += [path.parent / f for _, f in entries]
        else:
            paths.append(path)
    return paths


def check_outputs(outs, video):
    """The ``-o`` files: images, and ``.mp4`` where a video is made (``video``)."""
    for out in outs:
        suffix = Path(out).suffix.lower()
        if suffix == ".mp4" and not video:
            raise ValueError(f"{out}: a video is written by --orbit N or of a series")
        if suffix not in IMAGE_SUFFIXES + ((".mp4",) if video else ()):
            raise ValueError(f"unsupported image format '{Path(out).suffix}' for {out} (use "
                             f"{', '.join(IMAGE_SUFFIXES)}"
                             + (", .mp4 for the video)" if video else ")"))


def run(a):
    if a.workers is not None or a.address is not None:
        require("cluster", "render --workers", "ray")
    if any(Path(o).suffix.lower() == ".mp4" for o in a.out):
        require("vis", "a video", "imageio_ffmpeg")
    s = flags.settings_of(RenderSettings, a)
    mi = set_variant(a.variant)
    paths = series_paths(a.scene)
    scene_path = paths[0]
    is_mesh = all(is_mesh_file(p) for p in paths)
    series = len(paths) > 1
    if not is_mesh and (series or scene_path.suffix.lower() != ".xml"):
        raise ValueError(f"render takes a Mitsuba XML scene, or tet mesh files "
                         f"({', '.join(MESH_SUFFIXES)}; several, or a .pvd of them, as a "
                         f"series), got {', '.join(str(p) for p in paths)}")
    if is_mesh and s.tf and Path(s.tf).suffix.lower() in (".json", ".xml") \
            and not Path(s.tf).exists():
        raise FileNotFoundError(f"transfer function file not found: {s.tf}")
    s.validate("mesh" if is_mesh else "xml", series=series)
    if s.sensor is not None and not Path(s.sensor).is_file():
        raise FileNotFoundError(f"sensor file not found: {s.sensor}")
    check_outputs(a.out, video=bool(s.orbit) or series)
    if s.orbit and not any(Path(o).suffix.lower() == ".mp4" for o in a.out):
        raise ValueError("--orbit writes a video: give an -o FILE.mp4 (and images for the "
                         "contact sheet)")
    distributed = a.workers is not None or a.address is not None
    if a.workers is not None and a.workers < 1:
        raise ValueError(f"--workers must be at least 1, got {a.workers}")
    if distributed and not (s.orbit or series):
        return render_partitioned(s, a, mi, scene_path)
    if s.orbit:
        return render_orbit(s, a.out, scene_path, a.workers, a.address)
    if series:
        return render_series(s, a.out, paths, a.workers, a.address)
    t0 = time.time()
    if is_mesh:
        mesh = read_mesh(s, scene_path)
        scene = load_scene(mi, mesh_scene(s, mesh, mesh_framing(
            [mesh_extent(s, mesh, scene_path)])), scene_path)
    else:
        props = {k: True for k in ("repair", "cell_to_point") if getattr(s, k)}
        scene = load_xml(mi, scene_path, s.res, props, s.classification)
    sensor = None
    if s.sensor is not None:
        try:
            sensor = mi.load_file(str(s.sensor))
        except Exception as e:
            raise CommandError(f"cannot load the sensor {s.sensor}: {plugin_error(e)}") \
                from None
        if not isinstance(sensor, mi.Sensor):
            raise ValueError(f"{s.sensor} holds a {type(sensor).__name__}, not a sensor")
    t1 = time.time()
    img = render_image(mi, scene, scene_path, spp=s.spp or 0,
                       **({} if sensor is None else {"sensor": sensor}))
    t2 = time.time()
    rgb = img[..., :3]
    alpha = img[..., 3] if img.shape[-1] > 3 else None
    for out in a.out:
        write_render(out, rgb, alpha)
    print(f"rendered {scene_path} at {img.shape[1]}x{img.shape[0]} (load {t1 - t0:.1f} s, "
          f"render {t2 - t1:.1f} s) -> {', '.join(a.out)}")


class FrameRenderer:
    """The frames of an orbit or a series, rendered in one process: this one,
    or a Ray worker's (``render --workers``), which loads its orbit's scene
    once and keeps its kernels for all its frames."""

    def __init__(self, settings, framing, variant, threads=None):
        self.s, self.framing = settings, framing
        self.mi = set_variant(variant)
        if threads:
            import drjit as dr
            dr.set_thread_count(int(threads))
        self.orbit = None

    def orbit_frame(self, path, azimuth):
        """The RGBA frame of the orbit's mesh ``path`` seen from ``azimuth``."""
        from mi_tetvr.apps.frames import Frames
        s = dataclasses.replace(self.s, view=(float(azimuth), self.s.azimuth_elevation[1]))
        if self.orbit is None or self.orbit[0] != path:
            mesh = read_mesh(s, path)
            d = mesh_scene(s, mesh, self.framing)
            # (one scene, the camera moving: each frame replays the first's kernels)
            self.orbit = (path, Frames(load_scene(self.mi, d, path)))
        from mi_tetvr.apps.framing import framed_scene
        recorded = self.orbit[1]
        with render_errors(path):
            return render_rgba(np.array(recorded.render_dict(
                framed_scene(s, self.framing)["sensor"])))

    def series_frame(self, path):
        """The RGBA frame of the series' mesh ``path``."""
        scene = load_scene(self.mi, mesh_scene(self.s, read_mesh(self.s, path), self.framing),
                           path)
        return render_image(self.mi, scene, path, spp=self.s.spp or 0)


def render_frames(s, framing, method, calls, workers, address, bar):
    """The frames ``FrameRenderer.<method>(*call)`` for each call, here or
    over ``workers`` Ray workers (:func:`mi_tetvr.distributed.map_frames`)."""
    import mitsuba as mi
    if workers is None and address is None:
        r = FrameRenderer(s, framing, mi.variant())
        return [getattr(r, method)(*c) for c in bar(calls)]
    from mi_tetvr.distributed import map_frames
    progress = bar(range(len(calls)))
    frames = map_frames(FrameRenderer, (s, framing, mi.variant()), method, calls,
                        workers or 1, address, progress=progress.update)
    progress.close()
    return frames


def render_orbit(s, outs, path, workers=None, address=None):
    """``render MESH --orbit N`` (:class:`RenderSettings` ``s``): N frames once around
    ``--up`` from ``--view``, written as an MP4 (the ``.mp4`` outputs) and a contact
    sheet (the image outputs); ``workers``: spread over Ray workers."""
    from mi_tetvr.apps.orbit import contact_sheet, orbit_azimuths
    from mi_tetvr.video import FPS, write_video
    t0 = time.time()
    framing = mesh_framing([mesh_extent(s, read_mesh(s, path), path)])
    azimuth, _ = s.azimuth_elevation
    calls = [(path, float(az)) for az in orbit_azimuths(azimuth, s.orbit)]
    frames = np.stack(render_frames(s, framing, "orbit_frame", calls, workers, address,
                                    _bar("orbit")))
    sheet = contact_sheet(frames)
    for out in outs:
        if Path(out).suffix.lower() == ".mp4":
            write_video(out, np.stack([srgb8(f[..., :3]) for f in frames]), FPS)
        else:
            write_render(out, sheet[..., :3], sheet[..., 3] if sheet.shape[-1] > 3 else None)
    print(f"rendered {s.orbit} frames of {path} around {tuple(s.up_axis)} at "
          f"{frames.shape[2]}x{frames.shape[1]} ({time.time() - t0:.1f} s"
          f"{_on(workers, address)}) -> {', '.join(outs)}")


def _bar(desc):
    from mi_tetvr.progress import progress_bar

    def bar(items):
        return progress_bar(items, desc=desc, unit="frame")
    return bar


def _on(workers, address):
    if workers is None and address is None:
        return ""
    return f" on {workers or 1} Ray worker{'s' if (workers or 1) > 1 else ''}"


def render_series(s, outs, paths, workers=None, address=None):
    """``render MESH MESH ...`` (or a ``.pvd``; :class:`RenderSettings` ``s``): every
    mesh with one transfer function range and one camera (:func:`mesh_framing` over
    all), as an MP4 (the ``.mp4`` outputs) and numbered images (``stem_0000.png``, ...);
    ``workers``: the frames spread over Ray workers."""
    from mi_tetvr.video import FPS, write_video
    t0 = time.time()
    # the range and the box of all the meshes first (each read again to render: a
    # series need not fit in memory at once)
    framing = mesh_framing([mesh_extent(s, read_mesh(s, p), p) for p in paths])
    frames = np.stack(render_frames(s, framing, "series_frame", [(p,) for p in paths],
                                    workers, address, _bar("series")))
    written = []
    for out in outs:
        out = Path(out)
        if out.suffix.lower() == ".mp4":
            write_video(out, np.stack([srgb8(f[..., :3]) for f in frames]), FPS)
            written.append(str(out))
            continue
        for k, f in enumerate(frames):
            name = out.with_name(f"{out.stem}_{k:04d}{out.suffix}")
            write_render(name, f[..., :3], f[..., 3])
        written.append(str(out.with_name(f"{out.stem}_####{out.suffix}")))
    rng = framing["value_range"]
    print(f"rendered {len(paths)} meshes at {frames.shape[2]}x{frames.shape[1]}"
          + (f", '{framing['scalar']}' over [{rng[0]:.4g}, {rng[1]:.4g}]" if rng else "")
          + f" ({time.time() - t0:.1f} s{_on(workers, address)}) -> {', '.join(written)}")


def render_partitioned(s, a, mi, path):
    """``render OUT.pvtu --workers N``: a partitioned mesh rendered by Ray
    workers, each holding its blocks (:mod:`mi_tetvr.distributed`), with the
    camera and transfer function of the whole mesh (its bounds and ranges
    from the partition, the mesh itself never read here)."""
    from mi_tetvr.apps.framing import framed_scene, mesh_framing, render_rgba, shape_props
    from mi_tetvr.distributed import PartitionedMesh
    from mi_tetvr.mesh.io import choose_scalar
    from mi_tetvr.mesh.partition import blocks_path, read_partition, read_piece
    from mi_tetvr.mesh.topology import MeshError
    if path.suffix.lower() != ".pvtu" or not blocks_path(path).is_file():
        raise ValueError(f"--workers renders a partitioned mesh (a .pvtu written by "
                         f"`mi-tetvr partition MESH -o OUT.pvtu --blocks N`), or an orbit or a "
                         f"series; got {path}")
    if s.mode != "dvr" or s.surface is not None:
        raise ValueError("a partitioned mesh is rendered in --mode dvr, without --iso or "
                         "--plane")
    t0 = time.time()
    try:
        part = read_partition(path)
    except MeshError as e:
        raise CommandError(str(e)) from None
    name, rng = None, None
    if s.classified:
        _, _, pd, cd, _ = read_piece(part, 0)
        for k in ("color", "opacity"):
            pd.pop(k, None)
        try:
            name = choose_scalar(pd, s.scalar, str(path), cd, cells=True)
        except MeshError as e:
            raise CommandError(str(e)) from None
        rng = part.point_ranges.get(name) or part.cell_ranges.get(name)
    framing = mesh_framing([(part.bounds[0], part.bounds[1], name, rng)])
    scene = load_scene(mi, framed_scene(s, framing), path)
    with PartitionedMesh(path, a.workers, shape_props(s, framing), a.address) as pm:
        t1 = time.time()
        with render_errors(path):
            img = render_rgba(np.array(pm.render(scene, spp=s.spp or 0)))
        t2 = time.time()
        memory = pm.peak_memory()
    for out in a.out:
        write_render(out, img[..., :3], img[..., 3])
    print(f"rendered {path} ({part.tets:,} tets in {len(part.blocks)} blocks) on "
          f"{len(memory)} workers at {img.shape[1]}x{img.shape[0]} (start and load "
          f"{t1 - t0:.1f} s, render {t2 - t1:.1f} s; peak memory per worker "
          f"{max(memory) / 2**20:,.0f} MiB) -> {', '.join(a.out)}")
