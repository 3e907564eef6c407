"""The ``mi-tetvr`` command line.

    mi-tetvr render SCENE.xml -o OUT.exr|.png [--spp N] [--res WxH] [--variant V]
    mi-tetvr info MESH [--json] [--repair] [--cell-to-point]
    mi-tetvr make-scenes [DIR]
    mi-tetvr make-dataset VOLUME --tf TF --views N --res R --out DIR
    mi-tetvr fit DATA --out DIR [--config FILE.json] [--time-budget MIN] [...]
    mi-tetvr eval MESH DATA [--background R,G,B]
    mi-tetvr refine MESH --select ATTRIBUTE [--rank magnitude|value] --fraction F -o OUT
    mi-tetvr viewpoint MESH --out DIR [--tf TF --scalar NAME] [--res R] [--starts N]
    mi-tetvr process-data IMAGES_DIR|VIDEO --out DATA [--matcher M] [--reference DATASET]
    mi-tetvr make-capture --out DATA [--views N] [--res WxH] [--spp S]
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
        bmp = mi.Bitmap(np.ascontiguousarray(rgb, dtype=np.float32), mi.Bitmap.PixelFormat.RGB)
        bmp = bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)
        bmp.write(str(path))
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


def cmd_render(a):
    mi = _set_variant(a.variant)
    scene_path = Path(a.scene)
    if not scene_path.exists():
        sys.exit(f"mi-tetvr: scene file not found: {scene_path}")
    res = None
    if a.res:
        try:
            res = tuple(int(x) for x in a.res.lower().split("x"))
            if len(res) != 2 or min(res) < 1:
                raise ValueError
        except ValueError:
            sys.exit(f"mi-tetvr: --res must look like 512x512, got '{a.res}'")
    t0 = time.time()
    try:
        props = {k: True for k in ("repair", "cell_to_point") if getattr(a, k)}
        text = scene_xml(scene_path, res, props, a.classification)
        mi.file_resolver().prepend(str(scene_path.resolve().parent))
        scene = mi.load_string(text)
    except Exception as e:
        sys.exit(f"mi-tetvr: cannot load {scene_path}: {_plugin_error(e)}")
    t1 = time.time()
    try:
        img = np.array(mi.render(scene, spp=a.spp or 0))
    except Exception as e:
        # (Dr.Jit wraps the integrator's error: report the innermost one)
        while (e.__cause__ or e.__context__) is not None:
            e = e.__cause__ or e.__context__
        sys.exit(f"mi-tetvr: cannot render {scene_path}: {_plugin_error(e)}")
    t2 = time.time()
    rgb = img[..., :3]
    alpha = img[..., 3] if img.shape[-1] > 3 else None
    for out in a.output:
        _write_render(out, rgb, alpha)
    print(f"rendered {scene_path} at {img.shape[1]}x{img.shape[0]} (load {t1 - t0:.1f} s, "
          f"render {t2 - t1:.1f} s) -> {', '.join(a.output)}")


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
    for p in make_scene_meshes(a.dir):
        print(f"wrote {p}")


def _background(text):
    """'white', 'black' or 'r,g,b' (linear) -> list, None for RGBA fitting,
    'learn' for a learned environment."""
    if text is None or text == "none":
        return None
    if text == "learn":
        return text
    named = {"white": [1.0, 1.0, 1.0], "black": [0.0, 0.0, 0.0]}
    if text in named:
        return named[text]
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 3:
        raise SystemExit(f"mi-tetvr: --background must be none, learn, white, black or r,g,b; "
                         f"got {text!r}")
    return vals


def _load_data(path, downscale, holdout):
    from mi_tetvr.recon.datasets import load_dataset
    try:
        return load_dataset(path, downscale=downscale, holdout=holdout)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"mi-tetvr: {e}")


def cmd_fit(a):
    _set_variant(a.variant)
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.pipeline import run
    try:
        cfg = FitConfig.from_file(a.config) if a.config else FitConfig()
        overrides = {k: getattr(a, k) for k in (
            "init", "resolution", "iterations", "time_budget", "views_per_step", "lr_color",
            "lr_opacity", "lr_position", "loss", "loss_space", "regularizer", "downscale", "seed",
            "n_sub", "model", "optimize", "scalar", "transfer_function", "opacity_scale",
            "tf_resolution", "tf_smoothing", "tf_init", "smoothing", "scene")}
        if a.appearance is not None:
            overrides["appearance"] = a.appearance
        if a.background is not None:
            overrides["background"] = _background(a.background)
        if a.value_range is not None:
            try:
                overrides["value_range"] = [float(x) for x in a.value_range.split(",")]
            except ValueError:
                raise ValueError(f"--value-range must be lo,hi; got {a.value_range!r}") from None
        if a.freeze_boundary is not None:
            overrides["freeze_boundary"] = a.freeze_boundary
        cfg = cfg.updated(**overrides)
    except ValueError as e:
        sys.exit(f"mi-tetvr: {e}")
    data = _load_data(a.data, cfg.downscale, a.holdout)
    print(f"{a.data}: {len(data.train)} training and {len(data.test)} test views "
          f"({data.train[0].camera.width}x{data.train[0].camera.height})")
    try:
        metrics = run(data, a.out, cfg, resume=not a.restart)
    except KeyboardInterrupt:
        sys.exit("mi-tetvr: interrupted; progress saved (run the same command to resume)")
    m = metrics["mean"]
    what = "transmittance" if cfg.model == "absorption" else "sRGB"
    result = "transfer_function.json" if cfg.optimize == "tf" else "mesh.vtu"
    print(f"test PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f} ({what}) over "
          f"{len(metrics['views'])} view(s) [{metrics['split']}]; {metrics['tets']:,} tets, "
          f"{metrics['step']:,} steps, {metrics['wall_seconds']:.0f} s -> "
          f"{Path(a.out) / result}")


def cmd_eval(a):
    _set_variant(a.variant)
    from mi_tetvr.recon.pipeline import evaluate_mesh
    data = _load_data(a.data, a.downscale, a.holdout)
    if a.background == "learn":
        sys.exit("mi-tetvr: eval scores the mesh over a constant background; a fit with a "
                 "learned background scores itself (its metrics.json) and writes the "
                 "background to background.exr")
    metrics = evaluate_mesh(a.mesh, data, background=_background(a.background),
                            split=a.split)
    for name, m in metrics["views"].items():
        print(f"  {name:<24s} PSNR {m['psnr']:6.2f} dB  SSIM {m['ssim']:.4f}")
    m = metrics["mean"]
    print(f"mean PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f} (sRGB; linear PSNR "
          f"{m['psnr_linear']:.2f} dB) ({len(metrics['views'])} views)")
    if a.json:
        Path(a.json).write_text(json.dumps(metrics, indent=2))


MESH_SUFFIXES = (".vtu", ".msh", ".mesh", ".vtk")


def cmd_make_dataset(a):
    _set_variant(a.variant)
    from mi_tetvr.grid import load_volume, make_dataset
    from mi_tetvr.transfer import read_transfer_function
    path = Path(a.volume)
    if not path.exists():
        sys.exit(f"mi-tetvr: file not found: {path}")
    try:
        vr = None if a.value_range is None else tuple(float(x) for x in a.value_range.split(","))
        if a.xray:
            from mi_tetvr.grid.xray import make_xray_dataset
            info = make_xray_dataset(load_volume(path, value_range=vr), a.out, views=a.views,
                                     test_views=a.test_views, beam=a.beam,
                                     scale=a.attenuation, max_depth=a.max_depth)["info"]
            print(f"wrote {a.views} training and {a.test_views} test {a.beam}-beam projections "
                  f"(attenuation {info['attenuation_scale']:.4g} per unit, largest optical depth "
                  f"{info['max_depth']:.2f}) to {a.out}")
            return
        if a.tf is None:
            sys.exit("mi-tetvr: make-dataset needs --tf (or --xray for X-ray projections)")
        if path.suffix.lower() in MESH_SUFFIXES and not _is_image_data(path):
            from mi_tetvr.recon.synthetic import make_mesh_dataset
            info = make_mesh_dataset(path, a.tf, a.out, views=a.views, test_views=a.test_views,
                                     res=a.res, scalar=a.scalar, opacity_scale=a.opacity_scale,
                                     fov=a.fov or 40.0, seed=a.seed)
            print(f"wrote {a.views} training and {a.test_views} test views at {a.res}x{a.res} "
                  f"of '{info['scalar']}' to {a.out}")
            return
        volume = load_volume(path, value_range=vr)
        tf = read_transfer_function(a.tf)
    except (ValueError, FileNotFoundError, KeyError) as e:
        sys.exit(f"mi-tetvr: {e}")
    make_dataset(volume, tf, views=a.views, res=a.res, out_dir=a.out, test_views=a.test_views,
                 seed=a.seed, radius=a.radius, fov=a.fov, opacity_scale=a.opacity_scale)
    print(f"wrote {a.views} training and {a.test_views} test views at {a.res}x{a.res} to {a.out}")


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
    try:
        width, height = (int(x) for x in a.res.lower().split("x"))
    except ValueError:
        sys.exit(f"mi-tetvr: --res must be WxH, got {a.res!r}")
    info = make_room_capture(a.out, views=a.views, width=width, height=height, spp=a.spp,
                             seed=a.seed)
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
    write_tetmesh(a.output, out)
    print(f"{a.mesh}: {len(mesh.tets):,} tets, {len(mesh.vertices):,} vertices -> "
          f"{len(out.tets):,} tets, {len(out.vertices):,} vertices -> {a.output}")


def cmd_viewpoint(a):
    _set_variant(a.variant)
    import json
    import warnings

    import mi_tetvr
    from mi_tetvr.mesh.topology import bounding_radius
    from mi_tetvr.render.viewpoint import (ViewpointSearch, best_viewpoint, default_starts,
                                           orbit_scene, plot_viewpoints)
    from tqdm import tqdm
    path = Path(a.mesh)
    if not path.exists():
        sys.exit(f"mi-tetvr: mesh file not found: {path}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            mesh = mi_tetvr.read_tetmesh(path, repair=a.repair)
        except (ValueError, FileNotFoundError, KeyError) as e:
            sys.exit(f"mi-tetvr: {e}")
    lo, hi = mesh.bounds
    radius = bounding_radius(mesh.vertices)
    fov = 40.0
    shape = {"type": "tetmesh", "filename": str(path.resolve()), "repair": a.repair}
    if a.tf:
        shape["transfer_function"] = str(Path(a.tf).resolve())
        if a.scalar:
            shape["scalar_attribute"] = a.scalar
        shape["opacity_scale"] = a.opacity_scale / radius
    elif a.scalar:
        sys.exit("mi-tetvr: --scalar needs --tf")
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
                  resolution=a.res, iterations=a.iterations)
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


def _mesh_flags(parser):
    """The flags of the commands that read a mesh file."""
    parser.add_argument("--repair", action="store_true",
                        help="drop folded, flat and duplicate tets (reported)")
    parser.add_argument("--cell-to-point", action="store_true",
                        help="average per-cell arrays onto the vertices")


def main(argv=None):
    p = argparse.ArgumentParser(prog="mi-tetvr", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("render", help="render a Mitsuba XML scene with tetmesh shapes")
    r.add_argument("scene")
    r.add_argument("-o", "--output", action="append", required=True,
                   help="output image (.exr: linear RGBA; .png: sRGB); repeatable")
    r.add_argument("--spp", type=int, default=0, help="samples per pixel (default: the scene's)")
    r.add_argument("--res", help="resolution WxH of every sensor's film (default: the scene's)")
    _mesh_flags(r)
    r.add_argument("--classification", choices=("post", "pre"),
                   help="how tetmesh shapes with a transfer function classify their scalar: "
                        "post (along each ray, the default) or pre (vertices shaded at load)")
    r.add_argument("--variant", default="llvm_ad_rgb", help="llvm_ad_rgb (default) or cuda_ad_rgb")
    r.set_defaults(func=cmd_render)
    i = sub.add_parser("info", help="counts, bounds, boundary, quality and attributes of a mesh")
    i.add_argument("mesh")
    i.add_argument("--color", default="color", help="color point-data name")
    i.add_argument("--opacity", default="opacity", help="opacity point-data name")
    i.add_argument("--json", action="store_true", help="print the report as JSON (always, "
                   "also for a mesh with problems)")
    _mesh_flags(i)
    i.set_defaults(func=cmd_info)
    v = sub.add_parser("viewpoint", help="the camera position of highest opacity entropy "
                       "(DiffDVR's best viewpoint), by gradient ascent on the sphere")
    v.add_argument("mesh")
    v.add_argument("--out", required=True, help="folder for viewpoint.json, view.png and "
                   "viewpoint.png (the entropy over the sphere, the ascent paths)")
    v.add_argument("--tf", help="transfer function (post-classifies the scalar)")
    v.add_argument("--scalar", help="the scalar point array (default: the only one)")
    v.add_argument("--opacity-scale", type=float, default=4.0,
                   help="with --tf: extinction per the mesh's bounding radius (default 4)")
    v.add_argument("--res", type=int, default=128, help="image size (default 128)")
    v.add_argument("--starts", type=int, default=8, help="ascent starts (default 8)")
    v.add_argument("--iterations", type=int, default=20, help="steps per start (default 20)")
    v.add_argument("--samples", type=int, default=256,
                   help="Fibonacci-sphere views for comparison (default 256)")
    v.add_argument("--quiet", action="store_true", help="no progress bar")
    v.add_argument("--repair", action="store_true",
                   help="drop folded, flat and duplicate tets (reported)")
    v.add_argument("--variant", default="llvm_ad_rgb", help="llvm_ad_rgb (default) or cuda_ad_rgb")
    v.set_defaults(func=cmd_viewpoint)
    m = sub.add_parser("make-scenes", help="(re)generate the meshes of the bundled scenes")
    m.add_argument("dir", nargs="?", default=None)
    m.set_defaults(func=cmd_make_scenes)
    d = sub.add_parser("make-dataset", help="render a scalar volume or tet mesh into a "
                       "NeRF-style data set, or project a volume into X-ray images")
    d.add_argument("volume", help="scalar grid (.npy, .cvol, .mhd, .vti, raw .gz) or scalar "
                   "tet mesh (.vtu, .vtk, .msh, .mesh)")
    d.add_argument("--tf", help="transfer function (.json or DiffTetVR .xml)")
    d.add_argument("--scalar", help="the tet mesh's scalar point array (default: the only one)")
    d.add_argument("--xray", action="store_true", help="X-ray transmittance images (.npy) of "
                   "the grid volume's attenuation: exact line integrals of its trilinear field")
    d.add_argument("--beam", choices=("parallel", "cone"), default="parallel",
                   help="X-ray: parallel beam (orthographic, over 180 degrees; default) or cone "
                   "beam (perspective, over 360)")
    d.add_argument("--attenuation", type=float, help="X-ray: attenuation per unit length of a "
                   "normalised value 1 (default: from --max-depth)")
    d.add_argument("--max-depth", type=float, default=2.5, help="X-ray: the largest optical "
                   "depth of a training ray (default 2.5)")
    d.add_argument("--views", type=int, default=64, help="training views (default 64)")
    d.add_argument("--test-views", type=int, default=8, help="test views (default 8)")
    d.add_argument("--res", type=int, default=256, help="image size (default 256)")
    d.add_argument("--value-range", help="lo,hi of the raw values mapped to [0, 1] "
                   "(default: the data's range)")
    d.add_argument("--opacity-scale", type=float, default=1.0, help="multiplies the transfer "
                   "function's opacity (on a tet mesh: per mesh radius)")
    d.add_argument("--radius", type=float, default=4.0, help="camera distance (default 4)")
    d.add_argument("--fov", type=float, help="horizontal fov in degrees (default: frames the "
                   "[-1, 1]^3 box; 40 around a tet mesh)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--out", required=True)
    d.add_argument("--variant", default="llvm_ad_rgb")
    d.set_defaults(func=cmd_make_dataset)
    f = sub.add_parser("fit", help="reconstruct a tet-mesh volume from a multi-view data set")
    f.add_argument("data", help="NeRF-style folder (transforms*.json) or COLMAP model folder")
    f.add_argument("--out", required=True, help="output folder (also the checkpoint)")
    f.add_argument("--config",
                   help="JSON file of fit settings (see mi_tetvr.recon.config.FitConfig)")
    f.add_argument("--scene", choices=("auto", "object", "unbounded"),
                   help="object: views of an object with alpha masks (a grid over its visual "
                   "hull); unbounded: photos of a scene in its surroundings (its sparse points "
                   "and far shells tetrahedralized, a learned background, a color transform "
                   "per photo, L1 loss, cells added where the error is); auto (default): "
                   "object when the images have transparent pixels")
    f.add_argument("--init", help="auto (default: grid for objects, unbounded for scenes), "
                   "grid, tetwild, delaunay, unbounded or a mesh file (the scalar mesh with "
                   "--optimize tf or scalar)")
    f.add_argument("--appearance", action=argparse.BooleanOptionalAction, default=None,
                   help="fit an exposure and white balance (an affine color transform) per "
                   "training photo; held-out photos are scored without one (default: on for "
                   "unbounded scenes)")
    f.add_argument("--model", choices=("emission", "absorption"),
                   help="emission (default): colors and opacities from images; absorption: an "
                   "X-ray attenuation (point data 'attenuation') from transmittance images")
    f.add_argument("--optimize", choices=("volume", "tf", "scalar"),
                   help="volume (default): per-vertex colors and opacities; tf: the transfer "
                   "function over the init mesh's scalar; scalar: the scalar under --tf")
    f.add_argument("--scalar", help="the init mesh's scalar point array (default: the only one)")
    f.add_argument("--tf", dest="transfer_function",
                   help="the known transfer function (--optimize scalar)")
    f.add_argument("--opacity-scale", type=float, help="its opacity per mesh radius (as "
                   "make-dataset)")
    f.add_argument("--value-range", help="lo,hi: the scalar range the transfer function spans "
                   "(default: the init mesh's scalar range)")
    f.add_argument("--tf-resolution", type=int, help="transfer-function texels (default 64)")
    f.add_argument("--tf-smoothing", type=float,
                   help="weight of the transfer function's smoothing prior (default 0.01)")
    f.add_argument("--smoothing", type=float, help="weight of the smoothing prior across "
                   "edges of a fitted attenuation or scalar (default 0)")
    f.add_argument("--tf-init", choices=("flat", "random"), help="start of a fitted transfer "
                   "function (default flat)")
    f.add_argument("--resolution", type=int, help="grid cells along the largest axis "
                   "(default: chosen for --time-budget, else 32)")
    f.add_argument("--iterations", type=int,
                   help="optimizer steps (default 1500; ignored with --time-budget)")
    f.add_argument("--time-budget", type=float,
                   help="minutes for this command, outputs included: mesh size and steps "
                   "are fitted to it (resuming a run gives it the budget again)")
    f.add_argument("--views-per-step", type=int)
    f.add_argument("--lr-color", type=float)
    f.add_argument("--lr-opacity", type=float, help="optical depth per cell and step")
    f.add_argument("--lr-position", type=float, help="cell sizes per step; 0 = fixed")
    f.add_argument("--regularizer", type=float, help="tet-quality weight (with positions)")
    f.add_argument("--loss", choices=["l1", "l2"])
    f.add_argument("--loss-space", choices=["linear", "srgb"],
                   help="compare linear RGB or the sRGB pictures the metrics score")
    f.add_argument("--background", help="none (fit RGBA, default), learn (an environment map "
                   "fitted with the volume: photos of a scene in its surroundings), white, "
                   "black or r,g,b (linear)")
    f.add_argument("--freeze-boundary", action=argparse.BooleanOptionalAction, default=None)
    f.add_argument("--downscale", type=int, help="shrink images by this factor")
    f.add_argument("--holdout", type=int, default=8,
                   help="with a train split only: every N-th view is a test view (default 8)")
    f.add_argument("--n-sub", type=int)
    f.add_argument("--seed", type=int)
    f.add_argument("--restart", action="store_true", help="ignore an existing checkpoint")
    f.add_argument("--variant", default="llvm_ad_rgb")
    f.set_defaults(func=cmd_fit)
    e = sub.add_parser("eval", help="PSNR/SSIM of a mesh on a data set's test views")
    e.add_argument("mesh")
    e.add_argument("data")
    e.add_argument("--background", help="none (default), white, black or r,g,b")
    e.add_argument("--downscale", type=int, default=1)
    e.add_argument("--holdout", type=int, default=8)
    e.add_argument("--split", choices=["test", "train"], default="test")
    e.add_argument("--json", help="also write the metrics to this file")
    e.add_argument("--variant", default="llvm_ad_rgb")
    e.set_defaults(func=cmd_eval)
    mc = sub.add_parser("make-capture", help="path-trace a photo capture of a textured room "
                        "with objects from cameras inside it (a test capture: transforms.json, "
                        "lens distortion, exposure changes, noise, no masks)")
    mc.add_argument("--out", required=True)
    mc.add_argument("--views", type=int, default=48, help="photos (default 48)")
    mc.add_argument("--res", default="320x240", help="WxH (default 320x240)")
    mc.add_argument("--spp", type=int, default=12, help="samples per pixel (default 12)")
    mc.add_argument("--seed", type=int, default=0)
    mc.add_argument("--variant", default="llvm_ad_rgb")
    mc.set_defaults(func=cmd_make_capture)
    pd = sub.add_parser("process-data", help="camera poses of photos or a video by structure "
                        "from motion (COLMAP through pycolmap, CPU): a COLMAP data set for fit")
    pd.add_argument("images", help="folder of photos (.jpg, .png, ...) or a video file")
    pd.add_argument("--out", required=True, help="data set folder: images/, database.db, "
                    "sparse/0 (a COLMAP data set for fit and eval)")
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
    pd.add_argument("--quiet", action="store_true", help="no progress bar")
    pd.set_defaults(func=cmd_process_data)
    rf = sub.add_parser("refine", help="split the edges around the top vertices of a "
                        "point-data array")
    rf.add_argument("mesh")
    rf.add_argument("--select", required=True, help="point-data array to rank vertices by "
                    "(or color, opacity)")
    rf.add_argument("--rank", choices=["magnitude", "value"], default="magnitude",
                    help="magnitude (default): largest absolute values (vector norms) first, "
                    "negative as much as positive; value: highest signed values first")
    rf.add_argument("--fraction", type=float, default=0.05, help="top fraction (default 0.05)")
    rf.add_argument("-o", "--output", required=True)
    _mesh_flags(rf)
    rf.set_defaults(func=cmd_refine)
    a = p.parse_args(argv)
    a.func(a)


if __name__ == "__main__":
    main()
