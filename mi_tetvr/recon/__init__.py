"""Reconstruction: a tet-mesh volume fitted to images.

Data in
    :mod:`~mi_tetvr.camera` (:class:`Camera`: the one pinhole camera --
    OpenGL / OpenCV / COLMAP conventions, rays, projection, Mitsuba sensors),
    :mod:`~mi_tetvr.recon.datasets` (:class:`View`, :class:`Dataset`, NeRF and
    COLMAP readers, the NeRF writer), :mod:`~mi_tetvr.recon.images` (image files),
    :mod:`~mi_tetvr.recon.hull` (the region the cameras see).
Training
    :mod:`~mi_tetvr.recon.config` (:class:`FitConfig`, stages),
    :mod:`~mi_tetvr.recon.trainer` (:class:`Trainer`: one stage's loss and steps),
    :mod:`~mi_tetvr.recon.optim` (:class:`VertexAdam`: the optimizer state),
    :mod:`~mi_tetvr.recon.regularizer` (tet quality),
    :mod:`~mi_tetvr.recon.safeguard` (steps that would invert a tet are shortened),
    :mod:`~mi_tetvr.recon.checkpoint`, :mod:`~mi_tetvr.recon.pipeline` (the stages
    of ``mi-tetvr fit``, coarse-to-fine refinement between them, outputs).
Results
    :mod:`~mi_tetvr.recon.metrics` (compositing, PSNR, SSIM),
    :mod:`~mi_tetvr.recon.plots`.

The numpy modules are imported with the package; the names of the modules
that need a Mitsuba variant (optimizer, trainer, regularizer, checkpoint,
pipeline) are looked up on first use.
"""
from __future__ import annotations

from mi_tetvr._lazy import lazy_exports

from .config import FitConfig, coarse_to_fine
from .datasets import Dataset, View, load_colmap, load_dataset, load_nerf, write_nerf
from .hull import frusta_bounds, visual_hull_bounds
from .images import downscale_image, read_image, write_image
from .metrics import composite, image_metrics, psnr, ssim
from .safeguard import safe_step

_LAZY = {"VertexAdam": "optim", "Trainer": "trainer", "RunState": "trainer",
         "QualityRegularizer": "regularizer", "tet_regularizer": "regularizer",
         "save_checkpoint": "checkpoint", "load_checkpoint": "checkpoint",
         "run": "pipeline", "evaluate_mesh": "pipeline", "initial_mesh": "pipeline"}

__all__ = [
           "View", "Dataset", "load_dataset", "load_nerf", "load_colmap", "write_nerf",
           "read_image", "write_image", "downscale_image",
           "frusta_bounds", "visual_hull_bounds",
           "FitConfig", "coarse_to_fine", "composite", "psnr", "ssim", "image_metrics",
           "safe_step", *_LAZY]


__getattr__, __dir__ = lazy_exports(__name__, _LAZY, globals())
