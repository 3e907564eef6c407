"""Data sets rendered from a scalar tet mesh: ground truth for transfer-function
and scalar reconstruction.

:func:`make_mesh_dataset` renders a mesh's scalar field, post-classified by a
transfer function, with ``tetvr`` through pixel centres from cameras on a
Fibonacci sphere (training) and at random (test) around the mesh, and writes a
NeRF-style data set with exact EXR images (linear, premultiplied RGBA) and a
``volume_info.json`` that names the mesh, the scalar, its range, the transfer
function and the opacity scale (fits read it to know the images are point
samples).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["make_mesh_dataset", "mesh_cameras"]


def mesh_cameras(bounds, views, test_views, res=256, fov=40.0, seed=0, up=(0.0, 0.0, 1.0)):
    """Training cameras on a Fibonacci sphere and random test cameras around
    the box ``bounds`` (2, 3), at the distance where the box's bounding sphere
    fills ``fov`` (degrees). Returns ``(train, test)`` lists of Camera."""
    from mi_tetvr.mesh.topology import bounding_radius
    from mi_tetvr.recon.camera import fibonacci_cameras, random_cameras
    lo, hi = np.asarray(bounds, np.float64)
    centre = (lo + hi) / 2
    distance = 1.05 * bounding_radius(bounds) / np.sin(np.radians(fov / 2))
    train = fibonacci_cameras(views, distance, res, fov, up=up, target=centre)
    test = random_cameras(test_views, distance, res, fov, seed=seed, up=up, target=centre) \
        if test_views else []
    return train, test


def make_mesh_dataset(mesh_path, tf_path, out_dir, views=8, test_views=8, res=256,
                      scalar=None, opacity_scale=1.0, fov=40.0, seed=0, progress=True):
    """Render a scalar tet mesh under a transfer function into a data set.

    Parameters
    ----------
    mesh_path : path
        A tet mesh with a scalar point array.
    tf_path : path
        Transfer function (project JSON or DiffTetVR XML), over the scalar's range.
    out_dir : path
    views, test_views : int
    res : int
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

    Returns
    -------
    dict
        What ``volume_info.json`` holds.
    """
    import mitsuba as mi
    from tqdm import tqdm

    from mi_tetvr.mesh.io import choose_scalar, read_tetmesh
    from mi_tetvr.mesh.topology import bounding_radius
    from mi_tetvr.recon.datasets import Dataset, View, write_nerf
    mesh_path, tf_path = Path(mesh_path).resolve(), Path(tf_path).resolve()
    mesh = read_tetmesh(mesh_path, color=None, opacity=None)
    name = choose_scalar(mesh.point_data, scalar, str(mesh_path), mesh.cell_data)
    values = np.asarray(mesh.point_data[name], np.float64)
    lo, hi = mesh.bounds
    extinction = float(opacity_scale) / bounding_radius(mesh.vertices)
    train, test = mesh_cameras((lo, hi), views, test_views, res, fov, seed)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "volume": {"type": "tetmesh", "filename": str(mesh_path),
                                     "scalar_attribute": name,
                                     "transfer_function": str(tf_path),
                                     "opacity_scale": extinction}})
    posed = {"train": [], "test": []}
    with tqdm(total=len(train) + len(test), desc="render views", disable=not progress) as bar:
        for split, cams in (("train", train), ("test", test)):
            for i, cam in enumerate(cams):
                d = cam.sensor_dict(sampler="stratified")
                d["sampler"]["jitter"] = False
                image = np.array(mi.render(scene, sensor=mi.load_dict(d), spp=1))
                posed[split].append(View(f"r_{i}", cam, image))
                bar.update(1)
    write_nerf(Dataset(posed["train"], posed["test"]), out_dir, image_format="exr")
    info = {"mesh": str(mesh_path), "scalar": name,
            "value_range": [float(values.min()), float(values.max())],
            "transfer_function": str(tf_path), "opacity_scale": float(opacity_scale),
            "extinction_scale": extinction,
            "model": "tetvr post-classified emission-absorption, premultiplied linear RGBA "
                     "over black, through pixel centres",
            "cameras": {"fov_x_deg": float(fov), "n_train": len(train), "n_test": len(test),
                        "train": "fibonacci sphere", "test": "uniform random", "seed": seed}}
    (Path(out_dir) / "volume_info.json").write_text(json.dumps(info, indent=1) + "\n")
    return info
