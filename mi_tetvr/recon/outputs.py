"""What a finished fit writes to its folder: the fitted mesh or transfer function
(:func:`write_fitted`), the held-out comparisons, the progress plot, a capture's
fly-through and a learned background (:func:`write_outputs`), and how long writing
them takes (:func:`output_seconds`, what a time budget keeps back for them). Every kind
of fit, the X-ray attenuation's linear solvers included, writes its outputs here.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from mi_tetvr.recon.config import FitConfig
from mi_tetvr.recon.fields import field_type
from mi_tetvr.recon.metrics import display_rgb
from mi_tetvr.recon.plots import plot_history, save_comparison
from mi_tetvr.recon.trainer import TRAINING_VIEWS, Trainer

__all__ = ["write_outputs", "write_fitted", "fitted_file", "output_seconds",
           "write_flythrough", "flythrough_cameras", "FLYTHROUGH_FRAMES", "FLYTHROUGH_SPP"]


#: Frames of a capture's fly-through (``flythrough.mp4``, :func:`write_flythrough`): 2.5 s.
FLYTHROUGH_FRAMES = 60

#: Samples per pixel of the fly-through's frames (1: the pixel centres, as the fit sees the
#: photos without jitter; a frame then costs what a training render costs).
FLYTHROUGH_SPP = 1


def output_seconds(trainer: Trainer, now=time.perf_counter):
    """Estimated time of :func:`write_outputs`: one test render timed, times
    the views, and for a capture one fly-through frame timed, times the
    frames, with a margin for the files and plots."""
    views = trainer.dataset.test or trainer.dataset.train[:1]
    t0 = now()
    trainer.render_view(views[0])
    render = now() - t0
    # the held-out photos (16 samples per pixel when jittered) and the training PSNR's (one)
    seconds = 0.5 + 1.5 * (len(views) + TRAINING_VIEWS / (16 if trainer.jitter else 1)) * render
    path = flythrough_cameras(trainer)
    if path:
        # one frame timed (a small launch costs more per sample than the test render's)
        t0 = now()
        trainer.render_camera(path[len(path) // 2], FLYTHROUGH_SPP)
        seconds += 1.5 * len(path) * (now() - t0) + 1.0
    return seconds


def flythrough_cameras(trainer: Trainer):
    """The cameras of a capture's fly-through: along its photos' cameras in the order of their
    names (as taken), :data:`FLYTHROUGH_FRAMES` of them; ``[]`` for what is not a capture of a
    scene in its surroundings (views around an object, X-ray projections)."""
    from mi_tetvr.camera import camera_path
    views = sorted(trainer.dataset.train + trainer.dataset.test, key=lambda v: v.name)
    if trainer.config.data.scene != "unbounded" or len(views) < 2:
        return []
    return camera_path([v.camera for v in views], FLYTHROUGH_FRAMES)


def write_flythrough(trainer: Trainer, path):
    """``path`` (MP4): the fitted scene seen along the capture's camera path
    (:func:`flythrough_cameras`); returns the number of frames (0: not a capture)."""
    from mi_tetvr.video import write_video
    cameras = flythrough_cameras(trainer)
    if not cameras:
        return 0
    pictures = [np.round(255 * display_rgb(trainer.render_camera(c, FLYTHROUGH_SPP),
                                           trainer.background)).astype(np.uint8)
                for c in cameras]
    write_video(path, pictures)
    return len(pictures)


def fitted_file(config: FitConfig) -> str:
    """The file a fit with ``config`` writes what it fitted to, named after it (its
    field's ``fitted_file``): ``mesh.vtu`` (colors and opacities), ``attenuation.vtu``
    (``model`` absorption), ``scalar.vtu`` (``optimize`` scalar) or
    ``transfer_function.json`` (``optimize`` tf)."""
    return field_type(config.field).fitted_file


def write_fitted(trainer: Trainer, out: Path):
    """Write what was fitted to :func:`fitted_file`: a mesh with the field's point
    data (``color`` and ``opacity``, ``attenuation`` or ``scalar``) or, for a transfer
    function, project JSON (the texels as control points; over the scalar range that
    ``config.json`` records as ``value_range``) and its plot ``transfer_function.png``."""
    from mi_tetvr.mesh.io import write_tetmesh
    from mi_tetvr.mesh.tetmesh import TetMesh
    from mi_tetvr.recon.fields import TransferFunctionField
    from mi_tetvr.transfer import write_json
    vertices, tets, values = trainer.arrays()
    field = trainer.field
    path = out / field.fitted_file
    if isinstance(field, TransferFunctionField):
        from mi_tetvr.recon.plots import plot_transfer_functions
        tf = field.transfer_function(values)
        write_json(tf, path)
        plot_transfer_functions(out / "transfer_function.png", {"fitted": tf}, field.value_range)
        return
    if "sh" in field.point_arrays:
        # the mean color beside the spherical harmonics: what viewers without them show
        write_tetmesh(path, TetMesh(vertices, tets, field.mean_color(values["sh"]),
                                    values["opacity"], point_data={"sh": values["sh"]}))
    elif "color" in field.point_arrays:
        write_tetmesh(path, TetMesh(vertices, tets, values["color"], values["opacity"]))
    else:
        write_tetmesh(path, TetMesh(vertices, tets, point_data={
            k: values[k] for k in field.point_arrays}), color=None, opacity=None)


def write_view_panels(trainer: Trainer, views, folder: Path, fitted=None, mode="max"):
    """Write ``<view>.png`` per view to ``folder``: the fit's render | the view's image |
    the uncertainty of each value (the ``<value>_std`` point arrays of the mesh file
    ``fitted``, :mod:`~mi_tetvr.recon.uncertainty`), its ``mode`` (max or mean)
    projection from the view's camera in viridis over 0 to the array's largest value.
    Returns the names of the uncertainty arrays shown."""
    from mi_tetvr.recon.uncertainty import STD_SUFFIX, projection
    folder.mkdir(parents=True, exist_ok=True)
    vertices, tets, _ = trainer.arrays()
    stds = {}
    if fitted is not None and Path(fitted).suffix == ".vtu" and Path(fitted).is_file():
        from mi_tetvr.mesh.io import read_mesh_file
        data = read_mesh_file(fitted).point_data
        stds = {k: np.asarray(a, np.float64).reshape(len(vertices), -1)[:, 0]
                for k, a in data.items() if k.endswith(STD_SUFFIX) and len(a) == len(vertices)}
    shown = trainer.field.shown(trainer.background)
    for v in views:
        more = [projection(vertices, tets, s, v.camera, mode, (0.0, float(s.max())))
                for s in stds.values()]
        save_comparison(folder / f"{Path(v.name).stem}.png", trainer.render_view(v), v.image,
                        shown, more)
    return list(stds)


def write_outputs(trainer: Trainer, out: Path):
    """Write what was fitted (:func:`write_fitted`),
    ``test/*.png`` (render | target; X-ray transmittance in grey),
    ``progress.png``, for a capture of a scene in its surroundings ``flythrough.mp4`` (the
    scene along the photos' camera path, :func:`write_flythrough`) and, with a learned
    background, ``background.exr`` (its
    latitude-longitude texels, linear RGB: Mitsuba's ``envmap`` with the
    identity ``to_world`` renders it) to ``out``; returns the metrics (which
    :func:`run` writes to ``metrics.json`` with its timings)."""
    vertices, tets, _ = trainer.arrays()
    write_fitted(trainer, out)
    if trainer.learned_background:
        import mitsuba as mi
        texels = trainer.environment()[:, 1:-1]      # without the envmap's wrap-around columns
        mi.Bitmap(np.ascontiguousarray(texels)).write(str(out / "background.exr"))
    views = trainer.dataset.test or trainer.dataset.train[:1]
    metrics = trainer.evaluate(views)
    metrics.update(training_psnr=trainer.training_psnr(),
                   step=trainer.state.step, seconds=trainer.state.elapsed,
                   vertices=len(vertices), tets=len(tets), inverted_tets=trainer.inverted_tets(),
                   shortened_position_steps=trainer.state.shortened,
                   split="test" if trainer.dataset.test else "train (no test views)",
                   protocol={"test_views": trainer.dataset.protocol or "given",
                             "metrics": "PSNR and SSIM of sRGB images in [0, 1]"
                             + ("" if trainer.field.scored == "sRGB" else
                                f" (here: {trainer.field.scored})"),
                             "appearance": "none" if not trainer.appearance_index else
                             "a color transform per training photo; held-out photos "
                             "scored without one (the identity)"})
    renders = out / "test"
    renders.mkdir(exist_ok=True)
    shown = trainer.field.shown(trainer.background)
    for v in views:
        save_comparison(renders / f"{Path(v.name).stem}.png", trainer.render_view(v), v.image,
                        shown)
    plot_history(trainer.state.history, out / "progress.png", metrics["mean"]["psnr"])
    write_flythrough(trainer, out / "flythrough.mp4")
    return metrics
