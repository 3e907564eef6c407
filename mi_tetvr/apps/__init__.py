"""Applications of the differentiable renderer that are not reconstruction.

:mod:`~mi_tetvr.apps.viewpoint`
    The best viewpoint of a volume (DiffDVR Sec. 5.1): gradient ascent of the opacity
    entropy over the camera's position on a sphere, and its plot.
:mod:`~mi_tetvr.apps.viewer`
    The live viewer in the browser (``mi-tetvr view``, ``fit --viewer``, :func:`serve`).
:mod:`~mi_tetvr.apps.framing`
    The scene of a mesh file as ``mi-tetvr render MESH`` and the viewer make it.
:mod:`~mi_tetvr.apps.settings`
    :class:`RenderSettings`: how a mesh file or a scene is rendered (``render``'s options,
    the viewer's controls), typed, and which of them combine.

Needs a Mitsuba variant (it renders).
"""
from __future__ import annotations

from mi_tetvr._lazy import lazy_exports

_LAZY = {"ViewpointSearch": "viewpoint", "best_viewpoint": "viewpoint",
         "default_starts": "viewpoint", "opacity_entropy": "viewpoint",
         "orbit_scene": "viewpoint", "plot_viewpoints": "viewpoint", "serve": "viewer",
         "RenderSettings": "settings"}

__all__ = [*_LAZY]

__getattr__, __dir__ = lazy_exports(__name__, _LAZY, globals())
