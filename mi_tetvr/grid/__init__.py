"""Regular-grid volumes: readers and writers, the grid ray marcher and grid data sets.

* :mod:`mi_tetvr.grid.volume` -- the :class:`Volume` (a normalized scalar grid placed in
  ``[-1, 1]^3``), trilinear sampling in numpy, readers (raw, npy, cvol, mhd, vti) and writers.
  Numpy only.
* :mod:`mi_tetvr.grid.marcher` -- the Dr.Jit ray marcher: :class:`TFEval` (a transfer function
  evaluated exactly), :class:`GridField` (trilinear lookup), :func:`render_rays`,
  :func:`render_volume`, :func:`camera_rays`. Needs a Mitsuba variant when called.
* :mod:`mi_tetvr.grid.xray` -- X-ray projections: exact line integrals of the trilinear field,
  parallel- and cone-beam cameras, scikit-image's FBP and SART for comparison. Numpy only.

Data sets made of volumes are :mod:`mi_tetvr.recon.synthetic`'s.

Cameras are those of :mod:`mi_tetvr.camera`. Importing this package imports neither
Dr.Jit nor Mitsuba: the names of ``marcher`` are looked up in their modules
on first use (so they follow a reload of those modules after a variant switch).
"""
from __future__ import annotations

from mi_tetvr._lazy import lazy_exports

from .volume import Volume, load_volume, make_volume, trilinear_numpy, write_cvol, write_mhd

__all__ = ["Volume", "make_volume", "load_volume", "write_cvol", "write_mhd", "trilinear_numpy",
           "TFEval", "GridField", "render_rays", "render_volume", "camera_rays"]

_LAZY = {"TFEval": "marcher", "GridField": "marcher", "render_rays": "marcher",
         "render_volume": "marcher", "camera_rays": "marcher"}


__getattr__, __dir__ = lazy_exports(__name__, _LAZY, globals())
