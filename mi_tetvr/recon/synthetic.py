"""Data sets the project renders itself, ground truth for its reconstructions.

* :func:`make_dataset`: a regular-grid volume under a transfer function, rendered by the grid
  ray marcher (:func:`mi_tetvr.grid.marcher.render_volume`);
* :func:`make_mesh_dataset`: a scalar tet mesh's field post-classified by a transfer function,
  rendered by ``tetvr`` (exact EXR images);
* :func:`make_xray_dataset`: X-ray transmittance projections of a grid volume (exact line
  integrals of its trilinear field, :mod:`mi_tetvr.grid.xray`).

Conventions
-----------
Cameras
    Training cameras on a Fibonacci sphere, test cameras uniformly random on the same sphere
    (:func:`mi_tetvr.camera.fibonacci_cameras`, :func:`~mi_tetvr.camera.random_cameras`,
    around a mesh :func:`~mi_tetvr.camera.box_cameras`), unless given; X-ray cameras on a
    circle (:func:`mi_tetvr.grid.xray.xray_cameras`). Every image is rendered through its
    pixel centres: the data sets record ``pixel_sampling = "centers"``.
Files (NeRF-synthetic convention, written by :func:`mi_tetvr.recon.datasets.write_nerf`)
    ``transforms_{train,test}.json`` with ``camera_angle_x`` (radians), ``fl_x, fl_y, cx,
    cy, w, h`` (pixels) and per frame ``file_path`` and ``transform_matrix`` (OpenGL
    camera-to-world). Grid volumes: 8-bit RGBA PNG with **straight** (un-premultiplied)
    alpha and sRGB-encoded color; meshes: linear premultiplied EXR; X-ray: ``.npy``
    transmittance. ``volume_info.json`` (``xray_info.json``) records what was rendered.
"""
from __future__ import annotations

import json
from os import PathLike
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np

from mi_tetvr.camera import Camera, box_cameras, fibonacci_cameras, random_cameras
from mi_tetvr.grid.volume import Volume
from mi_tetvr.grid.xray import MAX_DEPTH, line_integrals, parallel_angles, xray_cameras
from mi_tetvr.recon.datasets import Dataset, View, write_nerf
from mi_tetvr.transfer import TransferFunction, json_dict

__all__ = ["make_dataset", "make_mesh_dataset", "make_xray_dataset"]

PathType = Union[str, "PathLike[str]"]


def make_dataset(volume: Volume, tf: TransferFunction, views: Union[int, Sequence[Camera]],
                 res=256, out_dir: PathType = "dataset",
                 test_views: Union[int, Sequence[Camera]] = 8, radius: float = 4.0,
                 fov: Optional[float] = None, seed: int = 0, step: float = 0.25,
                 value_range=(0.0, 1.0), opacity_scale: float = 1.0,
                 min_transmittance: float = 1e-4, up=(0.0, 0.0, 1.0),
                 progress: bool = True) -> dict:
    """Render train and test views of a grid volume into a NeRF-convention data set.

    Parameters
    ----------
    volume : Volume
    tf : TransferFunction
    views : int or list of Camera
        Training cameras, or their number (on a Fibonacci sphere,
        :func:`~mi_tetvr.camera.fibonacci_cameras`).
    res : int or (w, h)
        Image size for generated cameras.
    out_dir : path
        Receives ``transforms_train.json``, ``transforms_test.json``, ``volume_info.json``,
        ``train/r_<i>.png`` and ``test/r_<i>.png``.
    test_views : int or list of Camera
        Test cameras, or their number (uniformly random on the sphere, ``seed``,
        :func:`~mi_tetvr.camera.random_cameras`).
    radius, fov, up
        Camera sphere radius, horizontal fov in degrees (default
        :func:`~mi_tetvr.camera.default_fov`), up.
    seed : int
        Seed of the random test cameras.
    step, value_range, opacity_scale, min_transmittance
        See :func:`mi_tetvr.grid.marcher.render_rays`.
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    dict
        ``"train"``, ``"test"``: (n, h, w, 4) float32 premultiplied linear RGBA renders;
        ``"cameras_train"``, ``"cameras_test"``: lists of
        :class:`~mi_tetvr.recon.datasets.View` (named ``r_<i>``, with their images);
        ``"out_dir"``.
    """
    from mi_tetvr.grid.marcher import GridField, TFEval, render_volume
    from mi_tetvr.progress import progress_bar as tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if isinstance(views, (int, np.integer)):
        views = fibonacci_cameras(int(views), radius, res, fov, up=up)
    if isinstance(test_views, (int, np.integer)):
        test_views = random_cameras(int(test_views), radius, res, fov, seed=seed, up=up) \
            if test_views > 0 else []
    field = GridField(volume)
    tfe = TFEval(tf, value_range, opacity_scale)
    result = {"out_dir": str(out)}
    bar = tqdm(total=len(views) + len(test_views), desc="render views", disable=not progress)
    posed = {}
    for split, cams in (("train", views), ("test", test_views)):
        posed[split] = []
        for i, cam in enumerate(cams):
            img = render_volume(field, tfe, cam, step=step, min_transmittance=min_transmittance)
            posed[split].append(View(f"r_{i}", cam, img))
            bar.update(1)
        result[split] = (np.stack([p.image for p in posed[split]]) if cams
                         else np.zeros((0, 0, 0, 4), np.float32))
        result[f"cameras_{split}"] = posed[split]
    bar.close()
    write_nerf(Dataset(posed["train"], posed["test"], pixel_sampling="centers"), out)
    info = {"volume": volume.info(), "transfer_function": json_dict(tf),
            "value_range": [float(v) for v in value_range],
            "opacity_scale": float(opacity_scale), "step_voxels": float(step),
            "step_world": float(step * float(np.min(volume.spacing))),
            "min_transmittance": float(min_transmittance),
            "model": "post-classification emission-absorption, midpoint rule, "
                     "premultiplied linear RGB over black, alpha = 1 - T",
            "png": "RGBA 8-bit, sRGB color, straight alpha",
            "cameras": {"radius": float(radius), "fov_x_deg": float(views[0].fov_x) if views
                        else None, "up": [float(v) for v in up], "seed": int(seed),
                        "train": "fibonacci sphere" if views else None,
                        "n_train": len(views), "n_test": len(test_views),
                        "test": "uniform random on the sphere"}}
    with open(out / "volume_info.json", "w", encoding="utf-8") as f:
        json.dump(info, f, indent=2)
    return result


def _render_views(scene, train, test, spp=None, progress=True):
    """``{"train": views, "test": views}`` of ``scene`` from these cameras: one sample
    through each pixel centre (``spp`` None), or ``spp`` jittered samples per pixel with a
    seed of each view's own, the alpha set to 1 (a path-traced scene: opaque)."""
    import mitsuba as mi

    from mi_tetvr.progress import progress_bar as tqdm
    from mi_tetvr.recon.datasets import View
    posed = {"train": [], "test": []}
    with tqdm(total=len(train) + len(test), desc="render views", disable=not progress) as bar:
        for split, cams in (("train", train), ("test", test)):
            for i, cam in enumerate(cams):
                if spp is None:
                    d = cam.sensor_dict(sampler="stratified", jitter=False)
                    image = np.array(mi.render(scene, sensor=mi.load_dict(d), spp=1))
                else:
                    image = np.array(mi.render(scene, sensor=mi.load_dict(cam.sensor_dict(
                        spp=spp, sampler="independent")), seed=bar.n))
                    image[..., 3] = 1.0
                posed[split].append(View(f"r_{i}", cam, image))
                bar.update(1)
    return posed


def make_mesh_dataset(mesh_path, tf_path, out_dir, views=8, test_views=8, res=256,
                      scalar=None, opacity_scale=1.0, fov=40.0, seed=0, value_range=None,
                      repair=False, cell_to_point=False, progress=True, lights=None, spp=256):
    """Render a scalar tet mesh under a transfer function into a data set.

    Parameters
    ----------
    mesh_path : path
        A tet mesh with a scalar point array.
    tf_path : path
        Transfer function over the scalar's range: a file (project or ParaView JSON,
        DiffTetVR XML) or a matplotlib colormap's name.
    out_dir : path
    views, test_views : int
    res : int or (int, int)
        Image width and height.
    scalar : str, optional
        The point array (default: the only scalar one).
    opacity_scale : float
        The transfer function's opacity is per *mesh radius* times this (so a
        transfer function means the same on meshes of any size): the world
        extinction is ``opacity * opacity_scale / radius``.
    fov : float
        Horizontal field of view in degrees.
    seed : int
        Seed of the random test cameras.
    value_range : (2,) float, optional
        The scalar range the transfer function spans (default: the scalar's range).
    repair, cell_to_point : bool
        As :func:`~mi_tetvr.mesh.io.read_tetmesh` reads the mesh.
    lights : path, optional
        A Mitsuba scene file of known lighting (emitters and surfaces): the
        mesh is then a scattering medium (the transfer function's colors its
        albedo, its opacity the extinction, classified at the vertices), path
        traced by ``tetpath`` with ``spp`` samples per pixel under those
        lights; the images are opaque (alpha 1: the lights' scene is seen
        around the volume) and record area-averaged pixels.

    Returns
    -------
    dict
        What ``volume_info.json`` holds.
    """

    import mi_tetvr

    from mi_tetvr.mesh.io import choose_scalar, read_tetmesh
    from mi_tetvr.mesh.topology import bounding_radius
    from mi_tetvr.recon.datasets import Dataset, write_nerf
    mesh_path = Path(mesh_path).resolve()
    # a file, or a matplotlib colormap's name
    tf_path = Path(tf_path).resolve() if Path(tf_path).exists() else tf_path
    mesh = read_tetmesh(mesh_path, color=None, opacity=None, repair=repair,
                        cell_to_point=cell_to_point)
    name = choose_scalar(mesh.point_data, scalar, str(mesh_path), mesh.cell_data)
    values = np.asarray(mesh.point_data[name], np.float64)
    lo, hi = mesh.bounds
    extinction = float(opacity_scale) / bounding_radius(mesh.vertices)
    train, test = box_cameras((lo, hi), views, test_views, res, fov, seed)
    # the shape is built here from the mesh read above, its topology built once (a
    # mesh the shape refuses raises the shape's own error, before any scene)
    props = {"transfer_function": str(tf_path), "opacity_scale": extinction,
             **({} if value_range is None else {"value_min": float(value_range[0]),
                                                "value_max": float(value_range[1])})}
    if lights is not None:
        props.update(classification="pre", albedo="color")
    else:
        from mi_tetvr.render.properties import scalar_range
        scalar_range(values, name, props)      # (refused in the words of the file's array)
    volume = mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(mesh.vertices, mesh.tets,
                                                          scalar=values, **props),
                                    topology=mesh.topology)
    if lights is None:
        scene = mi_tetvr.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                                    "volume": volume})
    else:
        from mi_tetvr.render.surfaces import lights_scene
        scene = mi_tetvr.load_dict({"type": "scene", "integrator": {"type": "tetpath"},
                                    "volume": volume, **lights_scene(lights)})
    posed = _render_views(scene, train, test, None if lights is None else spp, progress)
    write_nerf(Dataset(posed["train"], posed["test"],
                       pixel_sampling="centers" if lights is None else "area"), out_dir,
               image_format="exr")
    info = {"mesh": str(mesh_path), "scalar": name,
            "value_range": [float(values.min()), float(values.max())] if value_range is None
            else [float(v) for v in value_range],
            "transfer_function": str(tf_path), "opacity_scale": float(opacity_scale),
            "extinction_scale": extinction,
            "model": "tetvr post-classified emission-absorption, premultiplied linear RGBA "
                     "over black, through pixel centres" if lights is None else
                     f"tetpath scattering medium (albedo: the transfer function's colors) lit "
                     f"by {Path(lights).resolve()}, {spp} samples per pixel, opaque",
            "cameras": {"fov_x_deg": float(fov), "n_train": len(train), "n_test": len(test),
                        "train": "fibonacci sphere", "test": "uniform random", "seed": seed}}
    (Path(out_dir) / "volume_info.json").write_text(json.dumps(info, indent=1) + "\n")
    return info


def make_xray_dataset(volume: Volume, out_dir, views: int = 64, test_views: int = 8,
                      beam: str = "parallel", scale: float | None = None,
                      max_depth: float = MAX_DEPTH, distance: float = 3.0, fov: float = 40.0,
                      flux: float | None = None, seed: int = 0, detail: int = 1,
                      progress: bool = True, arc: float | None = None) -> dict:
    """Write an X-ray data set of ``volume``: ``views`` training projections
    evenly over 180 degrees (parallel beam; 360 for a cone beam; ``arc``
    degrees for a limited-angle scan) and ``test_views`` held-out ones at
    angles between them.

    Parameters
    ----------
    volume : Volume
    out_dir : path
        Receives ``transforms_{train,test}.json`` (orthographic cameras:
        ``camera_model``, ``ortho_width``, ``ortho_height``; the volume's box as
        ``aabb``), ``{train,test}/<name>.npy`` (float32 transmittance) and
        ``xray_info.json`` (the volume, beam, angles, attenuation scale).
    scale : float, optional
        Attenuation per world unit of a normalised value 1 (default: the one
        whose largest optical depth over the training views is ``max_depth``).
    flux : float, optional
        Photons per pixel of the unattenuated beam: the training projections
        are Poisson counts ``N ~ Poisson(flux * T)`` stored as ``N / flux`` (the
        data set records ``xray_flux``, which weights the fit's rays); the
        held-out ones stay noise-free (what the true volume projects). Default:
        noise-free projections.
    seed : int
        Seed of the noise.
    arc : float, optional
        The angles the scan spans, in degrees (default 180 for a parallel
        beam, 360 for a cone beam): a limited-angle scan over less, its
        ``views`` angles ``k * arc / views`` from 0 as a full scan's, the
        held-out ones between them (within the arc too).
    detail : int
        1 (default): the projections are the exact line integrals of the
        volume's trilinear field. k > 1: of its cubic B-spline interpolant
        sampled k times finer (:meth:`Volume.refined`), a field no
        reconstruction on the volume's samples models exactly, as a scanned
        object is not (no "inverse crime"); the true values at the samples
        are the same.

    A parallel beam needs isotropic samples (its rows lie on the z samples,
    its pixels are square): a volume with other spacings is resampled
    (trilinear) to its x spacing first (:meth:`Volume.resampled`). Rays
    along the box's faces integrate what lies on them
    (:func:`~mi_tetvr.grid.xray.line_integrals`).

    Returns
    -------
    dict
        ``info`` (what ``xray_info.json`` holds), the ``train`` / ``test``
        views (:class:`~mi_tetvr.recon.datasets.View`) and the ``volume``
        projected (``volume`` itself, or resampled).
    """
    from mi_tetvr.progress import progress_bar as tqdm
    projected = volume
    if beam == "parallel" and not volume.isotropic():
        # the detector's rows lie on the z samples and its pixels are square
        projected = volume.resampled(float(volume.spacing[0]))
    full = 180.0 if beam == "parallel" else 360.0
    span = full if arc is None else float(arc)
    if not 0.0 < span <= full:
        raise ValueError(f"arc must lie in (0, {full:g}] degrees for a {beam} beam, got {arc}")
    # held-out angles halfway between training ones, spread over the scan
    angles = {"train": parallel_angles(views) * span / 180.0,
              "test": (np.arange(test_views) * (views / max(test_views, 1)) + 0.5) * span / views}
    depth = {}
    bar = tqdm(total=views + test_views, desc="project", disable=not progress)
    cams = {k: xray_cameras(projected, a, beam, distance, fov) for k, a in angles.items()}
    integrated = projected.refined(detail) if detail > 1 else projected
    for split, cs in cams.items():
        depth[split] = []
        for cam in cs:
            o, d = cam.rays()
            depth[split].append(line_integrals(integrated, o, d).reshape(cam.height, cam.width))
            bar.update(1)
    bar.close()
    if scale is None:
        scale = max_depth / max(max(float(x.max()) for x in depth["train"]), 1e-12)
    posed = {}
    rng = np.random.default_rng(seed)
    for split, cs in cams.items():
        posed[split] = []
        for i, (cam, dep) in enumerate(zip(cs, depth[split])):
            img = np.zeros((cam.height, cam.width, 4), np.float32)
            t = np.exp(-scale * dep)
            if flux is not None and split == "train":
                t = rng.poisson(float(flux) * t) / float(flux)
            img[..., 3] = 1.0 - t
            posed[split].append(View(f"p_{i:03d}", cam, img))
    lo, hi = projected.bounds()
    write_nerf(Dataset(posed["train"], posed["test"], bbox=np.stack([lo, hi]),
                       pixel_sampling="centers", xray_flux=flux), out_dir,
               image_format="npy")
    info = {"volume": projected.info(), "beam": beam, "arc_deg": span,
            "attenuation_scale": float(scale),
            "max_depth": float(max(float(x.max()) for x in depth["train"]) * scale),
            "angles_train_deg": angles["train"].tolist(),
            "angles_test_deg": angles["test"].tolist(),
            "noise": "none" if flux is None else
                     f"training projections: Poisson counts at {float(flux):g} photons per "
                     f"unattenuated pixel (seed {seed}); held-out ones noise-free",
            "xray_flux": None if flux is None else float(flux),
            "model": "absorption: transmittance exp(-integral of scale * trilinear value), "
                     "exact (two-point Gauss-Legendre between grid-plane crossings), through "
                     "pixel centres",
            "detail": int(detail),
            "integrated": integrated.info()["source"]}
    if projected is not volume:
        info["resampled_from"] = volume.info()
    (Path(out_dir) / "xray_info.json").write_text(json.dumps(info, indent=1) + "\n")
    return {"info": info, "train": posed["train"], "test": posed["test"], "volume": projected}
