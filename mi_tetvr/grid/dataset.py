"""A regular-grid volume rendered into a NeRF-convention multi-view data set.

Conventions
-----------
Cameras
    Training cameras on a Fibonacci sphere, test cameras uniformly random on the same sphere
    (:func:`mi_tetvr.recon.camera.fibonacci_cameras`,
    :func:`~mi_tetvr.recon.camera.random_cameras`), unless given; each image is rendered through its pixel centers by
    :func:`mi_tetvr.grid.marcher.render_volume`.
Files (NeRF-synthetic convention, written by :func:`mi_tetvr.recon.datasets.write_nerf`)
    ``transforms_{train,test}.json`` with ``camera_angle_x`` (radians), ``fl_x, fl_y, cx,
    cy, w, h`` (pixels) and per frame ``file_path`` and ``transform_matrix`` (OpenGL
    camera-to-world).  Images are 8-bit RGBA PNG with **straight** (un-premultiplied) alpha
    and sRGB-encoded color: ``rgb_png = srgb(C / alpha)``, ``alpha_png = alpha``.
    ``volume_info.json`` records the volume, the transfer function, the marcher's settings
    and the cameras.
"""
from __future__ import annotations

import json
from os import PathLike
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np

from mi_tetvr.grid.marcher import GridField, TFEval, render_volume
from mi_tetvr.grid.volume import Volume
from mi_tetvr.recon.camera import Camera, fibonacci_cameras, random_cameras
from mi_tetvr.recon.datasets import Dataset, View, write_nerf
from mi_tetvr.transfer import TransferFunction, json_dict

__all__ = ["make_dataset"]

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
        :func:`~mi_tetvr.recon.camera.fibonacci_cameras`).
    res : int or (w, h)
        Image size for generated cameras.
    out_dir : path
        Receives ``transforms_train.json``, ``transforms_test.json``, ``volume_info.json``,
        ``train/r_<i>.png`` and ``test/r_<i>.png``.
    test_views : int or list of Camera
        Test cameras, or their number (uniformly random on the sphere, ``seed``,
        :func:`~mi_tetvr.recon.camera.random_cameras`).
    radius, fov, up
        Camera sphere radius, horizontal fov in degrees (default
        :func:`~mi_tetvr.recon.camera.default_fov`), up.
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
    from tqdm import tqdm

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
    write_nerf(Dataset(posed["train"], posed["test"]), out)
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
